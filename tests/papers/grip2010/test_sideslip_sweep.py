"""The vehicle sideslip sweep (jaxobs.papers.grip2010.sideslip_sweep): the config file, bad configs, one small run
through ``jaxobs sweep`` (two manoeuvres x two road frictions, 2.5 s each) and (slow) the published figures of the
shipped config."""

import json

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


@pytest.mark.slow
@pytest.mark.published
def test_published_sweep_figures(tmp_path):
    """The figures of ``jaxobs sweep --config tuning/sideslip_sweep.toml`` (96 configurations) in the sweep results,
    from a fresh run of that command: the NVSO's and the EKF's median sideslip RMS errors per drive, the median
    friction errors with and without the cornering-stiffness mismatch, and the range of the friction errors on the
    sine steer on friction 1 with that mismatch. Regression snapshots of this implementation (seeded noise), pinned
    to their printed digits."""
    from tests._published import pin

    out = tmp_path / "sideslip"
    assert cli.main(["sweep", "--config", "tuning/sideslip_sweep.toml", "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["num_configs"] == 96 and summary["finite_fraction"] == 1.0
    by_drive = summary["median_by_manoeuvre"]
    for drive, words in (("sine_steer", "on the sine steer"), ("double_lane_change_120kmh", "on the lane change"),
                         ("mountain_road", "on the mountain road")):  # fmt: skip
        pattern = rf"([0-9.]+) against ([0-9.]+) deg {words}"
        pin(by_drive[drive]["nvso"]["beta_rms_deg"], pattern, 1)
        pin(by_drive[drive]["ekf"]["beta_rms_deg"], pattern, 2)
    stiffness = summary["median_by_axis"]["cornering_stiffness"]
    pattern = r"\(median (-?[0-9.]+) with that mismatch against (-?[0-9.]+) without;"
    pin(stiffness["0.8"]["nvso"]["friction_error"], pattern, 1)
    pin(stiffness["1.0"]["nvso"]["friction_error"], pattern, 2)
    cols = load_results(out)
    soft = (cols["param.manoeuvre"] == 0) & (cols["param.friction"] == 1.0) & (cols["param.cornering_stiffness"] == 0.8)
    pattern = r"the NVSO ends ([0-9.]+) to ([0-9.]+) below the road's friction, the EKF ([0-9.]+) to ([0-9.]+)\)"
    for observer, low, high in (("nvso", 1, 2), ("ekf", 3, 4)):
        below = -cols[f"metric.{observer}.friction_error"][soft]
        pin(below.min(), pattern, low)
        pin(below.max(), pattern, high)
