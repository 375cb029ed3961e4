"""The README's tour runs as printed. (The README's other numbers are pinned by the tests that compute them,
through tests/_readme.py.)"""

import re

import pytest

from tests import ROOT

pytestmark = pytest.mark.published


@pytest.mark.slow
def test_readme_tour_runs(capsys):
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, "README has no python example"
    for code in blocks:
        exec(compile(code, "README.md", "exec"), {})
    out = capsys.readouterr().out
    assert "largest stable Ks: 5.44 N/mm" in out
    assert "held-out loss 5.82 -> 1.98" in out  # the tuning example
    assert "(200, 2) 10" in out  # the filtering example
