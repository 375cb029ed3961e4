"""Smoke test of benchmarks/sideslip.py on a tiny batch: it runs, writes its JSON, and its NumPy NVSO and EKF (written
out independently, one loop over the samples) agree with jaxobs' sideslip. The speeds themselves are measured by the
benchmark, not tested."""

import importlib.util
import json

import pytest

from tests import ROOT

SCRIPT = ROOT / "benchmarks" / "sideslip.py"


@pytest.mark.slow  # runs the benchmark script end to end
def test_tiny_batch_agrees_with_numpy(tmp_path):
    """2 vehicles x 60 samples of the lane change: the NumPy peers' sideslip matches jaxobs' within 1e-8 deg (their
    derivatives by central differences; measured 5e-12 deg for the NVSO and 1e-9 for the EKF on 800 samples)."""
    spec = importlib.util.spec_from_file_location("sideslip_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    results = module.main(["--out", str(tmp_path), "--vehicles", "2", "--samples", "60", "--rounds", "1"])
    assert json.loads((tmp_path / "sideslip.json").read_text())["results"]["vehicles"] == 2
    assert set(results["observers"]) == {"nvso", "ekf", "ekf_bierman", "nvso_numpy", "ekf_numpy"}
    assert results["problems"] == {}
    for name, difference in results["numpy_max_difference_deg"].items():
        assert difference < 1e-8, (name, difference)
