"""Smoke test of benchmarks/tuning.py on its smallest problem with an exact optimum: two methods, one seed, a
short budget; it writes its JSON, figure and tables, replaces a file's table markers (``--readme``) and its
summary is read from the anytime records. The comparison itself is measured by the benchmark, not tested."""

import importlib.util
import json

import pytest

from tests import ROOT

SCRIPT = ROOT / "benchmarks" / "tuning.py"


@pytest.mark.slow
def test_benchmark_runs_and_writes_its_tables(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPT.parent))
    spec = importlib.util.spec_from_file_location("tuning_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    page = tmp_path / "page.md"
    page.write_text(
        "a\n<!-- tuning-table -->\nstale rows\n<!-- tuning-table -->\n"
        "b\n<!-- tuning-anytime -->\n<!-- tuning-anytime -->\n"
    )
    argv = ["--out", str(tmp_path), "--problems", "gain-schedule-100", "--seeds", "1", "--budget", "40",
            "--methods", "jaxobs", "random search", "--readme", str(page)]  # fmt: skip
    results = module.main(argv)
    run = results["gain-schedule-100"]
    assert json.loads((tmp_path / "tuning.json").read_text())["results"]["gain-schedule-100"]["runs"].keys() == {
        "jaxobs",
        "random search",
    }
    assert (tmp_path / "tuning.png").stat().st_size > 0
    summary = module.summarise(run)
    # every method scores the hand-set design first (46 % above J*); none ends below the exact optimum
    assert all(0 <= s["min"] <= s["median"] < 0.5 for s in summary.values())
    text = page.read_text()
    assert "stale rows" not in text and "| gain-schedule-100 (104; +-1.5 max gain) | 40 s |" in text
    assert "| gain-schedule-100 | jaxobs |" in text
