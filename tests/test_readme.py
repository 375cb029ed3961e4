"""The README: short, and its tour prints what its ``Output`` blocks show, checked as the docs pages are (by
tests/test_docs.py). (The numbers of the README and of the docs pages are pinned by the tests that compute them,
through tests/_published.py.)"""

import pytest

from tests import ROOT
from tests.test_docs import assert_code_lines_fit_the_column

pytestmark = pytest.mark.published

README = ROOT / "README.md"
MAX_BYTES = 15_000  # what it is, the two commands, a tour, capabilities, a performance summary; the rest in docs/


def test_readme_is_short():
    size = len(README.read_bytes())
    assert size <= MAX_BYTES, f"README.md is {size} bytes (at most {MAX_BYTES}): move details to docs/"


def test_readme_code_lines_fit_the_column():
    assert_code_lines_fit_the_column([README])


# the tour runs from an installed wheel: tests/test_package.py
