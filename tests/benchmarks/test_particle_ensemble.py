"""Smoke test of benchmarks/particle_ensemble.py on a tiny workload: it runs every workload against the installed
peers, writes its JSON, and its agreement checks hold (filterpy's EnKF fed jaxobs's ensemble and draws equals it
to rounding; the particle filters' log-likelihood estimates agree within their standard errors). The speed
itself is measured by the benchmark, not tested."""

import importlib.util
import json

import pytest

from tests import ROOT

SCRIPT = ROOT / "benchmarks" / "particle_ensemble.py"


@pytest.mark.slow
def test_benchmark_runs_and_agrees(tmp_path):
    pytest.importorskip("cuthbert")
    pytest.importorskip("filterpy")
    spec = importlib.util.spec_from_file_location("particle_ensemble_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    argv = ["--out", str(tmp_path), "--batches", "2", "--particles", "200", "--members", "8", "--steps", "12",
            "--rounds", "1", "--no-plot"]  # fmt: skip
    results = module.main(argv)
    assert json.loads((tmp_path / "particle_ensemble.json").read_text())["config"] == results["config"]
    for workload, cells in results["workloads"].items():
        for record in cells:
            assert record["entries"]["jaxobs"]["status"] == "ok", workload
            assert all(entry["status"] == "ok" for entry in record["entries"].values()), (workload, record)
    assert results["agreement"]["enkf_filterpy"]["max_abs_difference_of_ensembles"] < 1e-8
    pf = results["agreement"]["pf_log_likelihood"]
    error = (pf["jaxobs"]["standard_error"] ** 2 + pf["cuthbert"]["standard_error"] ** 2) ** 0.5
    assert abs(pf["jaxobs"]["mean"] - pf["cuthbert"]["mean"]) < 4 * error
