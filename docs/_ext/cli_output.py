"""The command output the pages show, kept in the pages themselves: after ``<!-- jaxobs-cli: ARGS -->`` a console
block with the output of ``jaxobs ARGS`` (help texts, ``--list``, ``--print-config``), up to
``<!-- /jaxobs-cli -->``. The pages read the same in the repository and on the site.

``python docs/_ext/cli_output.py`` regenerates every such block from this checkout's command (and names the pages
it changed); tests/test_docs.py fails while a page's blocks are not what the command prints. Help texts are
formatted for a terminal of :data:`COLUMNS` columns, whatever the terminal that runs this.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).parents[2]
COLUMNS = 100
BLOCK = re.compile(r"<!-- jaxobs-cli: (?P<args>.*?) -->\n(?:.*?<!-- /jaxobs-cli -->\n)?", re.S)


def output(args: str) -> str:
    """The console block of ``jaxobs ARGS``, as this checkout's command prints it."""
    sys.path.insert(0, str(ROOT))
    import jaxobs
    from jaxobs.cli import main

    if Path(jaxobs.__file__).parent != ROOT / "jaxobs":
        raise RuntimeError(f"the pages would show {jaxobs.__file__}, not this checkout's jaxobs")
    out, columns = io.StringIO(), os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(COLUMNS)
    try:
        with contextlib.redirect_stdout(out):
            status = main(shlex.split(args))
    except SystemExit as exc:  # --help, --version
        status = exc.code
    finally:
        os.environ.pop("COLUMNS") if columns is None else os.environ.update(COLUMNS=columns)
    if status:
        raise RuntimeError(f"jaxobs {args} exited with status {status}")
    return f"```console\n$ jaxobs {args}\n{out.getvalue().rstrip()}\n```\n"


def fill(text: str) -> str:
    """``text`` with every ``jaxobs-cli`` block (or bare marker) holding the command's current output."""
    return BLOCK.sub(lambda m: f"<!-- jaxobs-cli: {m['args']} -->\n{output(m['args'])}<!-- /jaxobs-cli -->\n", text)


def pages() -> list[Path]:
    """The Markdown pages with a ``jaxobs-cli`` marker."""
    return [p for p in sorted((ROOT / "docs").rglob("*.md")) if "<!-- jaxobs-cli: " in p.read_text()]


if __name__ == "__main__":
    for page in pages():
        text = page.read_text()
        filled = fill(text)
        if filled != text:
            page.write_text(filled)
            print(f"updated {page.relative_to(ROOT)}")
