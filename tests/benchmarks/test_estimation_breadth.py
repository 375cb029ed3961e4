"""Smoke test of benchmarks/estimation_breadth.py on a tiny grid: it runs, writes its JSON and figure, and every
peer installed (filterpy's IMM, cuthbert's quadrature filter) returns the same filtered means as jaxobs. The speed
itself is measured by the benchmark, not tested."""

import importlib.util
import json
import sys

import pytest

from tests import ROOT


@pytest.mark.slow
def test_runs_and_the_peers_agree(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("estimation_breadth", ROOT / "benchmarks" / "estimation_breadth.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(["--out", str(tmp_path), "--steps", "30", "--batches", "2", "--rounds", "1"])
    results = json.loads((tmp_path / "estimation_breadth.json").read_text())["results"]["B=2"]
    assert (tmp_path / "estimation_breadth.png").stat().st_size > 10_000
    for case in ("imm", "cubature", "gauss_hermite"):
        if "peer" in results[case]:
            assert results[case]["max_relative_difference"] < 1e-8, case
