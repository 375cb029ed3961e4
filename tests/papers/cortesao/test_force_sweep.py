"""The default robustness sweep (`jaxobs sweep`): config validation, the padded linear controllers,
and a small end-to-end run with its report."""

import json
import os
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.cli import main
from jaxobs.closed_loop import simulate
from jaxobs.observers.active import active_observer_controller
from jaxobs.observers.linear import linear_controller
from jaxobs.papers.cortesao import force_sweep as fr
from jaxobs.papers.cortesao.example1 import aob_params
from jaxobs.papers.cortesao.force_control import EXAMPLE1, example1_disturbance, nominal_design, with_feedback
from jaxobs.plants import force_plant
from tests import run_cli
from tests._published import pin

SMALL = {
    "chunk_size": 64,
    "controllers": {"grid_points": 2},
    "simulation": {"configs_per_design": 8, "duration": 2.0},
    "margins": {"num_points": 128},
}


@pytest.mark.slow  # compiles the sweep's full step
def test_padded_linear_controller_is_the_steady_state_aob():
    """The sweep's stacked controllers (zero-padded to a common size) run exactly like the AOB."""
    plant, L_r = nominal_design()
    params = with_feedback(aob_params(plant, 2), L_r)
    true = force_plant(1.5, 0.04, EXAMPLE1.h, 6.5 * EXAMPLE1.h, n_delay=9)
    t = jnp.arange(300) * EXAMPLE1.h
    ref, dist = jnp.full(300, 4.0), example1_disturbance(t)
    aob = simulate(true, active_observer_controller, params, ref, disturbance=dist)
    padded = active_observer_controller.linear(params).padded(12)
    lin = simulate(true, linear_controller, padded, ref, disturbance=dist)
    np.testing.assert_allclose(lin.y_true, aob.y_true, rtol=1e-10, atol=1e-10)


def test_default_config_is_at_least_1e5_configurations():
    config = fr.SCENARIO.validate()
    ctl = config["controllers"]
    count = len(ctl["orders"]) * ctl["grid_points"] ** 2 * config["simulation"]["configs_per_design"]
    assert count >= 100_000
    assert config["simulation"]["duration"] / EXAMPLE1.h == 2500


@pytest.mark.parametrize(
    "toml, key",
    [
        ("[plant]\nstifness = [1.0, 2.0]\n", "plant.stifness"),
        ("seed = 'zero'\n", "seed"),
        ("[plant]\nstiffness = [3.0, 3.0]\n", "plant.stiffness"),
        ("[plant]\nstiffness = [-1.0, 3.0]\n", "plant.stiffness"),
        ("[plant]\ndead_time_samples = [-2.0, 3.0]\n", "plant.dead_time_samples"),
        ("[plant]\ndead_time_samples = [3.0, 500.0]\n", "plant.dead_time_samples"),
        ("[controllers]\norders = [1, 9]\n", "controllers.orders"),
        ("[controllers]\ngrid_points = 0\n", "controllers.grid_points"),
        ("[simulation]\nduration = 0.0\n", "simulation.duration"),
        ("plant = 3\n", "plant"),
    ],
)
def test_config_errors_name_the_key_and_file_and_exit_2(tmp_path, capsys, toml, key):
    path = tmp_path / "bad.toml"
    path.write_text(toml)
    out = tmp_path / "out"
    assert main(["sweep", "--config", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and key in err
    assert not out.exists()  # nothing computed


def test_missing_or_invalid_toml_exits_2(tmp_path, capsys):
    assert main(["sweep", "--config", str(tmp_path / "none.toml")]) == 2
    path = tmp_path / "broken.toml"
    path.write_text("[plant\n")
    assert main(["sweep", "--config", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "not valid TOML" in capsys.readouterr().err


SMALL_TOML = (
    "chunk_size = 64\n[controllers]\ngrid_points = 2\n[simulation]\nconfigs_per_design = 8\nduration = 2.0\n"
    "[margins]\nnum_points = 128\n"
)


@pytest.fixture(scope="module")
def small_sweep(tmp_path_factory):
    """The SMALL sweep run by the CLI on one device: (config path, out dir)."""
    root = tmp_path_factory.mktemp("small")
    path, out = root / "small.toml", root / "sweep"
    path.write_text(SMALL_TOML)
    assert main(["sweep", "--config", str(path), "--out", str(out), "--no-progress"]) == 0
    return path, out


@pytest.mark.slow
def test_small_sweep_end_to_end(small_sweep):
    path, out = small_sweep
    summary = json.loads((out / "summary.json").read_text())
    assert summary["num_configs"] == 4 * 4 * 8
    for name in ("stability_maps.png", "distributions.png", "worst_cases.png", "report.md"):
        assert (out / name).is_file()
    cols = fr.load_results(out)
    stable = cols["metric.stable"]
    assert 0 < stable.mean() < 1  # the default mismatch range holds stable and unstable loops
    assert np.all(np.isfinite(cols["metric.rms_force_error"][stable]))
    assert np.all((cols["param.stiffness"] >= 0.3) & (cols["param.stiffness"] <= 30.0))
    # rerunning continues (nothing left to compute) and gives the same summary numbers
    assert main(["sweep", "--config", str(path), "--out", str(out), "--no-progress"]) == 0
    again = json.loads((out / "summary.json").read_text())
    assert again["controllers"] == summary["controllers"] and again["chunks_computed"] == 0


@pytest.mark.slow
def test_two_host_devices_give_the_one_device_results(small_sweep, tmp_path):
    """The default evaluation calls batched LAPACK kernels (LU, eigenvalues), which run in blocks that keep them
    sequential (jaxobs.batching): two host devices compute the one-device rows, up to rounding (the two devices
    share the thread pool, and sums of the 2500-step simulation round differently: at most 6.5e-12 relative in
    the RMS force error and 3.1e-12 in the peak force, measured; every other column bit for bit)."""
    path, reference = small_sweep
    out = tmp_path / "two"
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip(),
    }
    cmd = [sys.executable, "-m", "jaxobs.cli", "sweep", "--config", str(path), "--out", str(out), "--no-progress"]
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert json.loads((out / "manifest.json").read_text())["device_count"] == 2
    want, got = fr.load_results(reference), fr.load_results(out)
    assert list(got) == list(want)
    for name in want:
        if name in ("metric.rms_force_error", "metric.peak_force"):
            np.testing.assert_allclose(got[name], want[name], rtol=1e-10, err_msg=name)
        else:
            assert np.array_equal(got[name], want[name], equal_nan=True), name


@pytest.mark.slow
@pytest.mark.published
def test_readme_default_sweep_figures(tmp_path):
    """The README's figures of the default ``jaxobs sweep`` (100 000 configurations), from a fresh run of that
    command: stable fractions over the whole range and within x1.5 of the nominal stiffness, median phase margins
    and RMS force errors of the stable loops. Regression snapshots of this implementation (a seeded Monte-Carlo
    run), pinned to their printed digits; the fractions may differ by a few configurations on another machine
    (loops within rounding of rho = 1), hence the allowance of 2e-4 (5 of 25 000; within x1.5: 5e-4)."""
    out = tmp_path / "sweep"
    run_cli(["sweep", "--out", str(out), "--no-progress"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["num_configs"] == 100_000
    c = summary["controllers"]
    names = ("AOB-1", "AOB-2", "AOB-3", "CKF")
    whole = r"whole mismatch range: AOB-1 ([0-9.]+), AOB-2 ([0-9.]+), AOB-3 ([0-9.]+), CKF ([0-9.]+);"
    near = r"nominal stiffness: ([0-9.]+), ([0-9.]+), ([0-9.]+), ([0-9.]+)\."
    rms = r"median RMS force error falls with it \(([0-9.]+), ([0-9.]+), ([0-9.]+) N; CKF ([0-9.]+) N\)"
    for group, name in enumerate(names, start=1):
        pin(c[name]["stable_fraction"], whole, group, noise=2e-4)
        pin(c[name]["stable_fraction_within_50pct_stiffness"], near, group, noise=5e-4)
        pin(c[name]["rms_force_error_stable"]["median"], rms, group)
    for group, name in enumerate(names[:3], start=1):
        pin(
            c[name]["phase_margin_stable"]["median"],
            r"falls with the order \(([0-9.]+), ([0-9.]+), ([0-9.]+) degrees\)",
            group,
        )
