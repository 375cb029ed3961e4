"""What examples/ holds besides the guides' code (which lives on the pages, run by tests/test_docs.py): the files a
page includes name an existing file whose path the page shows, a script has its own test, and each small config
runs through the command line and prints what its guide shows."""

import re

import pytest

from tests import ROOT

pytestmark = pytest.mark.published

EXAMPLES = ROOT / "examples"
CHECKED_BY = re.compile(r"^# checked by: (tests/\S+\.py)", re.M)  # a script with the test that asserts on it


def test_every_included_file_exists_and_the_page_names_it():
    """Every ``--8<--`` inclusion in docs/ is well formed (a formatter once broke them into plain text), names an
    existing file, and the page shows that file's path so a reader knows what to run."""
    snippet = re.compile(r'^--8<-- "([^"]+)"$', re.M)
    for page in (ROOT / "docs").rglob("*.md"):
        text = page.read_text()
        assert len(snippet.findall(text)) == text.count("--8"), f"{page.name}: a malformed --8<-- inclusion"
        for path in snippet.findall(text):
            assert (ROOT / path).is_file(), f"{page.name}: {path} does not exist"
            assert f"`{path}`" in text or f" {path}" in text, f"{page.name}: the page does not name {path}"


def test_every_script_names_its_test():
    for script in EXAMPLES.glob("*.py"):
        match = CHECKED_BY.search(script.read_text())
        assert match, f"{script.name}: no '# checked by: tests/...' line"
        test = ROOT / match.group(1)
        assert test.is_file() and script.name in test.read_text(), f"{script.name}: {match.group(1)}"


# the guides' small configs run from an installed wheel: tests/test_package.py
