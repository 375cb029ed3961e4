"""The vehicle sideslip sweep (jaxobs.papers.grip2010.sideslip_sweep): the config file, bad configs, and one small run
through
``jaxobs sweep`` (two manoeuvres x two road frictions, 2.5 s each)."""

import numpy as np
import pytest

from jaxobs import cli
from jaxobs._config import load_toml
from jaxobs.papers.grip2010 import sideslip_sweep as sweep
from jaxobs.sweep import load_results


def test_default_config_file_validates():
    path = "tuning/sideslip_sweep.toml"
    assert sweep.SCENARIO.validate(load_toml(path), path) == sweep.DEFAULT_CONFIG


@pytest.mark.parametrize(
    "given, key",
    [
        ({"grid": {"manoeuvre": ["slalom"]}}, "grid.manoeuvre"),
        ({"grid": {"friction": [0.0]}}, "grid.friction"),
        ({"grid": {"drift": [-0.1]}}, "grid.drift"),
        ({"grid": {"mass": []}}, "grid.mass"),
        ({"grid": {"seeds": 0}}, "grid.seeds"),
        ({"simulation": {"error_start": 20.0}}, "simulation.error_start"),
    ],
)
def test_bad_config_names_the_key(given, key):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        sweep.SCENARIO.validate(given, "test.toml")


@pytest.mark.slow  # end to end through the CLI, like the other sweeps' runs
def test_cli_sweep_small_grid(tmp_path):
    """Rows in grid order (manoeuvre slowest), all finite. The traced manoeuvre switch drives each test drive (the
    lane change reaches a true sideslip above 3 deg, the sine steer stays below 1.5 deg) and the friction scale
    reaches the plant (the lane change on 0.7 of the friction slides more: measured 6.1 against 3.5 deg). At the
    nominal friction both observers keep the sideslip RMS error below 0.3 deg (measured 0.10 to 0.16), and on the
    lane change, which saturates the tyres, both end with the road friction within 0.15 (measured errors 0.04 and
    0.09 for the NVSO, 0.015 and 0.0002 for the EKF)."""
    config = tmp_path / "sideslip.toml"
    config.write_text(
        'scenario = "sideslip"\nchunk_size = 4\n[grid]\nmanoeuvre = ["double_lane_change_120kmh", "sine_steer"]\n'
        "friction = [1.0, 0.7]\nacc_bias = [0.0]\ndrift = [0.0]\nmass = [1.0]\ncornering_stiffness = [1.0]\n"
        "[simulation]\nduration = 2.5\nerror_start = 0.5\n"
    )
    out = tmp_path / "sweep"
    assert cli.main(["sweep", "--config", str(config), "--out", str(out), "--no-progress"]) == 0
    cols = load_results(out)
    assert cols["index"].tolist() == [0, 1, 2, 3]
    assert cols["param.manoeuvre"].tolist() == [0, 0, 1, 1]
    assert cols["param.friction"].tolist() == [1.0, 0.7, 1.0, 0.7]
    assert np.all(cols["metric.finite"])
    peak = cols["metric.true_beta_max_deg"]
    assert peak[0] > 3.0 and peak[1] > peak[0] + 1.0 and np.all(peak[2:] < 1.5), peak
    nominal = cols["param.friction"] == 1.0
    for obs in sweep.OBSERVERS:
        assert np.all(cols[f"metric.{obs}.beta_rms_deg"][nominal] < 0.3)
        assert np.all(np.abs(cols[f"metric.{obs}.friction_error"][:2]) < 0.15)
    summary = (out / "report.md").read_text()
    assert "double_lane_change_120kmh" in summary and (out / "sideslip.png").exists()
