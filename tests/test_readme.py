"""The README: short, and its tour runs as printed. (The numbers of the README and of the docs pages are pinned by
the tests that compute them, through tests/_published.py.)"""

import re

import pytest

from tests import ROOT

pytestmark = pytest.mark.published

README = ROOT / "README.md"
MAX_BYTES = 15_000  # what it is, the two commands, a tour, capabilities, a performance summary; the rest in docs/


def test_readme_is_short():
    size = len(README.read_bytes())
    assert size <= MAX_BYTES, f"README.md is {size} bytes (at most {MAX_BYTES}): move details to docs/"


@pytest.mark.slow
def test_readme_tour_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python example"
    for code in blocks:
        exec(compile(code, "README.md", "exec"), {})
    out = capsys.readouterr().out
    assert "largest stable Ks: 5.44 N/mm" in out
    assert "held-out loss 5.82 -> 2\n" in out  # the tuning example (adam at step 0.5, no clipping)
    assert "(200, 2) 10" in out  # the filtering example
