"""Monte-Carlo sweep of the Liu & Peng §4.2 estimators (jaxobs.papers.liu_peng.vehicle_lateral_sweep)."""

import json

import jax
import pytest

from jaxobs import cli
from jaxobs.papers.liu_peng import vehicle_lateral, vehicle_lateral_sweep
from jaxobs.sweep import config_key
from tests._published import pin


def test_default_config_file_validates():
    from jaxobs._config import load_toml

    path = "tuning/liu_peng_sweep.toml"
    config = vehicle_lateral_sweep.SCENARIO.validate(load_toml(path), path)
    assert config == vehicle_lateral_sweep.DEFAULT_CONFIG


@pytest.mark.slow  # the ideal case is checked on the reproduction in tests/papers/liu_peng/test_vehicle_lateral.py
def test_no_mismatch_no_noise_reproduces_the_ideal_case():
    """Nominal truth, no noise, no low-pass: every per-method RMS equals liu_peng's ideal case (the truth here is
    simulated with 100 Hz steps of 1 ms scans instead of a NumPy loop, so agreement is to rounding, 1e-9)."""
    point = {name: [1.0, 1.0] for name in vehicle_lateral_sweep.SCALES}
    config = vehicle_lateral_sweep.SCENARIO.validate(
        {
            "vehicle": {**point, "steer_offset_deg": [0.0, 0.0], "count": 1},
            "noise": {"std": 0.0, "sine": 0.0},
            "estimators": {"lowpass": False},
        }
    )
    sampler, evaluate, _, _ = vehicle_lateral_sweep.make_sweep(config)
    metrics = jax.jit(evaluate)(sampler(config_key(0, 0), 0))
    reference = vehicle_lateral.run_case("parameters", "ideal")["rms"]
    for method in vehicle_lateral.METHODS:
        for error in vehicle_lateral_sweep.ERRORS:
            assert float(metrics[f"{error}_rms"][method]) == pytest.approx(reference[method][error], rel=1e-9)


@pytest.mark.slow
@pytest.mark.published
def test_readme_sweep_figures(tmp_path):
    """The README's figures of ``jaxobs sweep --config tuning/liu_peng_sweep.toml`` (500 vehicles), from a fresh run
    of that command: median RMS v_y error per estimator, the 90th percentiles, the Kalman filter's share of best
    vehicles. Regression snapshots of this implementation (a seeded Monte-Carlo run), pinned to their printed
    digits."""
    out = tmp_path / "lp"
    assert cli.main(["sweep", "--config", "tuning/liu_peng_sweep.toml", "--out", str(out), "--no-progress"]) == 0
    v = json.loads((out / "summary.json").read_text())["v_y_rms"]
    medians = (
        r"inverse dynamics ([0-9.]+), H-infinity ([0-9.]+), AOB-1 ([0-9.]+), "
        r"Kalman filter without a disturbance state ([0-9.]+) m/s"
    )
    for group, method in enumerate(("inverse_dynamics", "hinf", "aob", "kalman"), start=1):
        pin(v[method]["median"], medians, group)
    p90 = r"\(90th percentile ([0-9.]+) against ([0-9.]+) to ([0-9.]+) m/s\)"
    pin(v["kalman"]["p90"], p90, 1)
    pin(min(v[m]["p90"] for m in ("inverse_dynamics", "hinf", "aob")), p90, 2)
    pin(max(v[m]["p90"] for m in ("inverse_dynamics", "hinf", "aob")), p90, 3)
    pin(100 * v["kalman"]["best_fraction"], r"is best on ([0-9.]+) % of the vehicles")
