"""The Example 5.6 gain/noise sweep (jaxobs.papers.grip2010.example56_sweep)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs import cli
from jaxobs._config import ConfigError, load_toml
from jaxobs.papers.grip2010 import example56_sweep as sweep
from jaxobs.sweep import config_key, load_results

TINY = {
    "chunk_size": 4,
    "grid": {"K_phi": [3.0, 10.0], "adaptation_gain": [3.0], "noise_variance": [0.0, 1.0], "seeds": 2},
    "scenario_timing": {"segment_s": 2.0, "window_s": 1.0},
}


def test_default_config_file_validates():
    path = "tuning/grip_example56_sweep.toml"
    assert sweep.SCENARIO.validate(load_toml(path), path) == sweep.DEFAULT_CONFIG


@pytest.mark.parametrize(
    "given, key",
    [
        ({"grid": {"K_phi": []}}, "grid.K_phi"),
        ({"grid": {"adaptation_gain": [1.0, 0.0]}}, "grid.adaptation_gain"),
        ({"grid": {"noise_variance": [-1.0]}}, "grid.noise_variance"),
        ({"grid": {"seeds": 0}}, "grid.seeds"),
        ({"gradient": {"adaptation_gain": 0.0}}, "gradient.adaptation_gain"),
        ({"scenario_timing": {"segment_s": 2.0, "window_s": 3.0}}, "scenario_timing.window_s"),
    ],
)
def test_bad_config_names_the_key(given, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        sweep.SCENARIO.validate(given)


def test_index_runs_over_the_grid_seeds_fastest():
    grid = {"K_phi": [1.0, 2.0], "adaptation_gain": [3.0, 4.0, 5.0], "noise_variance": [0.0, 1.0], "seeds": 2}
    config = sweep.SCENARIO.validate({"grid": grid})
    sampler, _, n, _ = sweep.make_sweep(config)
    assert n == 24
    p = jax.vmap(lambda i: sampler(config_key(0, i), i))(jnp.arange(n))
    rows = np.stack([np.asarray(p[k], float) for k in (*sweep.GRID, "noise_seed")], axis=1)
    expected = [(k, g, v, s) for k in (1.0, 2.0) for g in (3.0, 4.0, 5.0) for v in (0.0, 1.0) for s in (0, 1)]
    np.testing.assert_array_equal(rows, np.asarray(expected))


def test_cli_sweep_end_to_end(tmp_path):
    """A tiny grid (2 s segments): the gradient law sees the same noise at every (K_phi, adaptation_gain) point (common
    random numbers), the noise-free runs do not depend on the seed, and the report matches the rows."""
    config = tmp_path / "grip.toml"
    config.write_text(
        'scenario = "grip-example56"\nchunk_size = 4\n[grid]\nK_phi = [3.0, 10.0]\nadaptation_gain = [3.0]\n'
        "noise_variance = [0.0, 1.0]\nseeds = 2\n[scenario_timing]\nsegment_s = 2.0\nwindow_s = 1.0\n"
    )
    out = tmp_path / "sweep"
    assert cli.main(["sweep", "--config", str(config), "--out", str(out), "--no-progress"]) == 0
    cols = load_results(out)
    assert cols["index"].tolist() == list(range(8))
    t = sweep._grid_table(sweep.SCENARIO.validate(TINY), cols)
    for law in sweep.LAWS:
        assert np.all(np.isfinite(t[law]["mean"])) and np.all(t[law]["peak"] > 0)
        np.testing.assert_array_equal(t[law]["mean"][:, :, 0, 0], t[law]["mean"][:, :, 0, 1])  # no noise: seeds agree
    np.testing.assert_array_equal(t["gradient"]["mean"][0], t["gradient"]["mean"][1])  # same noise at both K_phi
    assert not np.array_equal(t["modular"]["mean"][0], t["modular"]["mean"][1])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["num_configs"] == 8 and len(summary["grid"]) == 4
    point = next(p for p in summary["grid"] if p["K_phi"] == 10.0 and p["noise_variance"] == 1.0)
    assert point["modular"]["median_mean_abs_theta_error"] == pytest.approx(np.median(t["modular"]["mean"][1, 0, 1]))
    assert 0.0 <= point["modular_better_fraction"] <= 1.0
    assert (out / "grid.png").is_file() and "grid.png" in (out / "report.md").read_text()


@pytest.mark.slow
@pytest.mark.published
def test_readme_sweep_figures(tmp_path):
    """The README's figures of ``jaxobs sweep --config tuning/grip_example56_sweep.toml`` (192 configurations),
    from a fresh run of that command: at the printed gains with unit noise variance, both laws' median errors and
    the modular estimator's share of better seed x segment pairs; the best grid point's error. Regression snapshots
    of this implementation (seeded noise), pinned to their printed digits."""
    from tests._published import pin

    out = tmp_path / "grip"
    path = "tuning/grip_example56_sweep.toml"
    assert cli.main(["sweep", "--config", path, "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    key = lambda p: (p["K_phi"], p["adaptation_gain"], p["noise_variance"])  # noqa: E731
    point = next(p for p in summary["grid"] if key(p) == (10.0, 3.0, 1.0))
    pattern = (
        r"\(10, 3\) give a median mean \|theta_tilde\| over each segment's last 5 s of ([0-9.]+) against the "
        r"gradient law's ([0-9.]+) \(lower in ([0-9]+) %"
    )
    pin(point["modular"]["median_mean_abs_theta_error"], pattern, 1)
    pin(point["gradient"]["median_mean_abs_theta_error"], pattern, 2)
    pin(100 * point["modular_better_fraction"], pattern, 3)
    best = summary["best_modular_gains"]["1.0"]
    assert (best["K_phi"], best["adaptation_gain"]) == (10.0, 0.3)
    pin(best["median_mean_abs_theta_error"], r"\(10, 0\.3\), with ([0-9.]+)")
