"""The code on the documentation pages: every ``python`` block of a page runs, in order, as one script in a fresh
interpreter (from a scratch directory holding the repository's ``tuning/``, as a user runs it
from the repository root), and prints what the page's ``Output`` blocks show (each after the block that prints it;
together, in order, the script's output), number for number within one unit of the last printed digit (integers
exactly). Code lines (python, TOML, shell) fit the site's column.

The scripts run as a user's would: one that read a sweep's results used to abort at exit now and then ("terminate
called without an active exception"), which ``jaxobs.sweep.load_results`` no longer provokes; the exit status is
checked.

A page whose first line is ``<!-- test: slow ... -->`` is a slow test. The blocks are found by mktestdocs. The README's
tour is checked by the same helpers (tests/test_readme.py).
"""

import os
import re
import subprocess
import sys

import pytest
from mktestdocs import grab_code_blocks

from tests import ROOT

pytestmark = pytest.mark.published

DOCS = ROOT / "docs"
OUTPUT = 'text title="Output"'  # the info string of an output block
FRAGMENTS = {  # pages whose python blocks are parts of a larger file, not a script
    "guides/adding-a-paper.md": "the skeleton of a reproduction module, with elisions",
}
COLUMN = 88  # characters of a code line that the site shows without scrolling
IMPORT_NOISE = re.compile(r"Failed to import (mujoco_)?warp: ")  # mujoco.mjx 3.17 prints this on import (stdout)
NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def _pages() -> list:
    pages = [p for p in sorted(DOCS.rglob("*.md")) if grab_code_blocks(p.read_text(), lang="python")]
    return [
        pytest.param(p, id=p.relative_to(DOCS).as_posix(),
                     marks=[pytest.mark.slow] if p.read_text().startswith("<!-- test: slow") else [])
        for p in pages
        if p.relative_to(DOCS).as_posix() not in FRAGMENTS
    ]  # fmt: skip


def _unit(number: str) -> float:
    """One unit of the last printed digit of ``number`` ("0.177" -> 1e-3, "4.2e-03" -> 1e-4); 0 for an integer
    ("60": a count is exact)."""
    mantissa, _, exponent = number.lower().partition("e")
    if "." not in mantissa and not exponent:
        return 0.0
    return 10.0 ** (int(exponent or 0) - len(mantissa.partition(".")[2]))


def same_output(printed: str, shown: str) -> bool:
    """Whether ``printed`` reads as ``shown``: the same text between the numbers, each number within one unit of
    the last digit ``shown`` prints (an integer: equal)."""
    if NUMBER.split(printed) != NUMBER.split(shown):  # also: as many numbers
        return False
    pairs = zip(NUMBER.findall(printed), NUMBER.findall(shown), strict=True)
    return all(abs(float(a) - float(b)) <= _unit(b) * (1 + 1e-9) for a, b in pairs)


def test_same_output_allows_the_last_digit_only():
    assert same_output("RMS 0.178, 60 missing", "RMS 0.177, 60 missing")
    assert not same_output("RMS 0.179, 60 missing", "RMS 0.177, 60 missing")
    assert not same_output("RMS 0.177, 61 missing", "RMS 0.177, 60 missing")
    assert not same_output("rms 0.177", "RMS 0.177")


def assert_prints_its_output(page, tmp_path, python: str | None = None) -> None:
    """Runs the ``python`` blocks of the markdown file ``page`` as one script from ``tmp_path`` and checks that it
    prints what the page's ``Output`` blocks show; the docs pages and the README are checked alike. ``python``:
    another interpreter (an installed jaxobs, tests/test_package.py), run without the repository on its path."""
    text = page.read_text()
    code = "\n".join(grab_code_blocks(text, lang="python"))
    shown = "".join(grab_code_blocks(text, lang=OUTPUT)).rstrip("\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if python is None:
        (tmp_path / "tuning").symlink_to(ROOT / "tuning")
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    done = subprocess.run([python or sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    printed = "\n".join(line.rstrip() for line in done.stdout.splitlines() if not IMPORT_NOISE.match(line))
    assert same_output(printed, shown), f"{page.name} printed\n{printed}\n\nand shows\n{shown}"


@pytest.mark.parametrize("page", _pages())
def test_page_code_prints_its_output(page, tmp_path):
    assert_prints_its_output(page, tmp_path)


def _code_lines(info: str, block: str) -> list:
    """The code lines a block shows: a python, toml or bash block's own, a ``--8<-- "PATH"`` line replaced by the
    lines of PATH, and a console block's commands (its output is the program's)."""
    include = re.compile(r'^--8<-- "([^"]+)"$')
    language = info.split()[0] if info.strip() else ""
    lines = []
    for line in block.splitlines():
        match = include.match(line)
        if match:
            lines += (ROOT / match.group(1)).read_text().splitlines()
        elif language in ("python", "toml", "bash") or (language == "console" and line.startswith("$ ")):
            lines.append(line)
    return lines


def assert_code_lines_fit_the_column(pages: list) -> None:
    """Checks that no code line of the markdown files ``pages`` is longer than ``COLUMN`` characters."""
    fence = re.compile(r"^```(.*?)\n(.*?)^```", re.M | re.S)
    long = [
        f"{page.relative_to(ROOT)}: {line[:60]}..."
        for page in pages
        for info, block in fence.findall(page.read_text())
        for line in _code_lines(info, block)
        if len(line) > COLUMN
    ]
    assert not long, f"{len(long)} code lines longer than {COLUMN} characters:\n" + "\n".join(long)


def test_code_lines_fit_the_column():
    assert_code_lines_fit_the_column(sorted(DOCS.rglob("*.md")))


def test_every_page_is_in_the_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    listed = set(re.findall(r"^\s*-\s[^#\n]*?:\s*([\w/.-]+\.md)\s*$", nav, re.M))
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md") if not p.is_relative_to(DOCS / "_ext")}
    assert pages - listed == set(), "pages missing from mkdocs.yml's nav"
