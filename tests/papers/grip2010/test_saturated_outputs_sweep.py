"""The saturated-output controller sweep (jaxobs.papers.grip2010.saturated_outputs_sweep)."""

import json

import numpy as np
import pytest

from jaxobs import cli
from jaxobs._config import ConfigError, load_toml
from jaxobs.papers.grip2010 import saturated_outputs_sweep as sweep
from jaxobs.sweep import load_results


def test_default_config_file_validates():
    path = "tuning/saturated_outputs_sweep.toml"
    assert sweep.SCENARIO.validate(load_toml(path), path) == sweep.DEFAULT_CONFIG


@pytest.mark.parametrize(
    "given, key",
    [
        ({"grid": {"T": []}}, "grid.T"),
        ({"grid": {"rho": [1.0]}}, "grid.rho"),
        ({"grid": {"h_scale": [0.0]}}, "grid.h_scale"),
        ({"grid": {"initial_states": 0}}, "grid.initial_states"),
        ({"initial": {"radius_min": 10.0, "radius_max": 1.0}}, "initial.radius_max"),
        ({"run": {"cond_max": 1.0}}, "run.cond_max"),
    ],
)
def test_bad_config_names_the_key(given, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        sweep.SCENARIO.validate(given)


def test_cli_sweep_end_to_end(tmp_path):
    """A tiny grid: the printed design (rho = 1.1) reaches deadbeat from every state and rests at the origin; with
    rho = 2 the push grows so fast that from the largest state y2 crosses the linear band between two RK4 nodes and
    is never seen unsaturated (§8.4's warning, at this step): no deadbeat, reported as such. Every run that reached
    deadbeat rests at the origin; the same initial states at every grid point."""
    config = tmp_path / "sat.toml"
    config.write_text(
        'scenario = "saturated-outputs"\nchunk_size = 8\n[grid]\nT = [0.5]\nrho = [1.1, 2.0]\nh_scale = [1.0]\n'
        "initial_states = 4\n[initial]\nradius_min = 0.1\nradius_max = 100.0\n[run]\nintervals = 25\nsubsteps = 20\n"
    )
    out = tmp_path / "out"
    assert cli.main(["sweep", "--config", str(config), "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["num_configs"] == 8
    printed = next(p for p in summary["grid"] if p["rho"] == 1.1)
    assert printed["deadbeat_fraction"] == 1.0 and printed["stabilised_fraction"] == 1.0
    cols = load_results(out)
    done = cols["metric.deadbeat_interval"] > 0
    assert np.all(cols["metric.final_norm"][done] < 1e-6 * np.maximum(cols["metric.radius"][done], 1))
    assert np.all((cols["metric.first_unsaturated_interval[1]"] > 0) | ~done)
    radius = cols["metric.radius"].reshape(2, 4)
    np.testing.assert_array_equal(radius[0], radius[1])  # common random numbers
    assert 0.1 <= radius.min() and radius.max() <= 100.0
    assert (out / "grid.png").exists() and (out / "report.md").exists()
