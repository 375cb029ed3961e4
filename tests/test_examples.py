"""The examples under examples/ that the guides of docs/ include: each script runs and prints what its
``# prints:`` comments say (the numbers the guides quote); each small config runs through the command line and
prints what its guide shows.

A script whose first line is ``# slow: ...`` is a slow test. Scripts run as a user runs them (``python
examples/NAME.py`` in a fresh interpreter, from a scratch working directory), importing this checkout.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests import ROOT

pytestmark = pytest.mark.published

EXAMPLES = ROOT / "examples"
CHECKED_BY = re.compile(r"^# checked by: (tests/\S+\.py)", re.M)  # a script with its own test, which asserts on
SCRIPTS = sorted(s for s in EXAMPLES.glob("*.py") if not CHECKED_BY.search(s.read_text()))  # what it measures
PRINTS = re.compile(r"#\s*prints:\s?(.*)$")


def expected_output(script: Path) -> list[str]:
    """The lines of every ``# prints: TEXT`` comment of ``script``, in order."""
    return [m.group(1).rstrip() for line in script.read_text().splitlines() if (m := PRINTS.search(line))]


def _param(script: Path):
    slow = script.read_text().startswith("# slow:")
    return pytest.param(script, id=script.stem, marks=[pytest.mark.slow] if slow else [])


def test_every_guide_snippet_comes_from_an_example():
    """Every ``--8<--`` inclusion in docs/ is well formed (a formatter once broke them into plain text) and names an
    existing example (and, when given, one of its sections)."""
    snippet = re.compile(r'--8<-- "([^":]+)(?::([\w-]+))?"')
    for page in (ROOT / "docs").rglob("*.md"):
        text = page.read_text()
        assert len(snippet.findall(text)) == text.count("--8"), f"{page.name}: a malformed --8<-- inclusion"
        for path, section in snippet.findall(text):
            target = ROOT / path
            assert target.is_file(), f"{page.name}: {path} does not exist"
            if section:
                assert f"[start:{section}]" in target.read_text(), f"{page.name}: {path} has no section {section}"


def test_an_example_checked_elsewhere_names_an_existing_test():
    for script in EXAMPLES.glob("*.py"):
        if match := CHECKED_BY.search(script.read_text()):
            test = ROOT / match.group(1)
            assert test.is_file() and script.name in test.read_text(), f"{script.name}: {match.group(1)}"


@pytest.mark.parametrize("script", [_param(s) for s in SCRIPTS])
def test_example_prints_what_the_guide_says(script, tmp_path):
    expected = expected_output(script)
    assert expected, f"{script.name} has no '# prints:' comment to check"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    printed = [line.rstrip() for line in done.stdout.splitlines()]
    assert printed == expected, f"{script.name} printed\n" + "\n".join(printed)


@pytest.mark.slow
@pytest.mark.parametrize("command, guide", [("sweep", "sweeps"), ("tune", "tuning")])
def test_example_config_runs_as_its_guide_shows(command, guide, tmp_path, capsys):
    """The guide's small config (examples/COMMAND-small.toml) runs from the command line and prints the results
    (the indented lines of the command's summary) that the guide's transcript shows."""
    from jaxobs.cli import main

    out = tmp_path / command
    assert main([command, "--config", str(EXAMPLES / f"{command}-small.toml"), "--out", str(out),
                 "--no-progress"]) == 0  # fmt: skip
    results = [line.rstrip() for line in capsys.readouterr().out.splitlines() if line.startswith("  ")]
    assert results
    page = (ROOT / "docs" / "guides" / f"{guide}.md").read_text()
    assert [line for line in results if line not in page] == []
