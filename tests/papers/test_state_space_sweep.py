"""A user's own sweep end to end: the TOML state-space block (jaxobs.papers.state_space_sweep), a SweepScenario in the
user's module (``jaxobs sweep --scenario module:NAME``, the TOML's ``scenario = "module:NAME"``) and an installed
one (the ``jaxobs.sweeps`` entry points), each from a temporary directory, with the generic report; the checks of
the TOML block name the key; invalid configurations and a design unstable on the nominal plant are reported.

The two-mass spring of the robustness-sweep guide (tuning/two-mass.toml) runs in the slow set, its published
stable fractions pinned."""

import json
import logging
import re

import numpy as np
import pytest

from jaxobs._config import ConfigError
from jaxobs.cli import main
from jaxobs.lti import c2d, ss
from jaxobs.papers import registry
from jaxobs.papers.state_space_sweep import SCENARIO, nominal_values, parse
from jaxobs.sweep import load_results
from tests import ROOT
from tests._published import pin

MY_SWEEP = '''
"""A cheap scenario of my own: stable below 0.5, invalid above 0.9."""
import jax
import jax.numpy as jnp

from jaxobs.papers.scenarios import Sweep, SweepScenario


def build(config):
    def sampler(key, index):
        return {"x": jax.random.uniform(key), "noise_key": jax.random.split(key)[0]}

    def evaluate(p):
        valid = p["x"] < 0.9
        return {"valid": valid, "stable": valid & (p["x"] < 0.5),
                "gain_margin": jnp.where(valid & (p["x"] < 0.5), 1 / p["x"], jnp.nan)}

    return Sweep(sampler, evaluate, config["configs"])


SCENARIO = SweepScenario(name="my-sweep", summary=__doc__, build=build, units={"x": "m"},
                         defaults={"scenario": "my-sweep", "seed": 0, "chunk_size": 50, "configs": 200},
                         notes={"configs": "how many"}, size_key="configs")
NOT_A_SCENARIO = 3
'''


def _run(capsys, *argv) -> tuple[int, list[str], str]:
    status = main([*argv, "--no-progress"] if argv[0] == "sweep" and "--print-config" not in argv else list(argv))
    out, err = capsys.readouterr()
    return status, out.strip().splitlines(), err


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    """A temporary working directory holding my_sweep.py (the module a user writes beside the command)."""
    (tmp_path / "my_sweep.py").write_text(MY_SWEEP)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))  # removed again after the test (the resolver adds it only for a while)
    return tmp_path


def test_a_scenario_of_my_own_module_runs_from_the_command_line(user_dir, capsys):
    status, out, err = _run(capsys, "sweep", "--scenario", "my_sweep:SCENARIO", "--out", "out")
    assert status == 0, err
    rows = load_results(user_dir / "out")
    invalid = int((rows["param.x"] >= 0.9).sum())
    assert out[-1] == f"  invalid configurations: {invalid} of 200" and out[-2].startswith(
        "  all    stable fraction 0."
    )
    summary = json.loads((user_dir / "out" / "summary.json").read_text())
    assert summary["figures"] == ["stable_fraction.png", "metrics.png"] and summary["invalid"] == invalid > 0
    assert list(rows) == ["index", "param.x", "metric.gain_margin", "metric.stable", "metric.valid"]  # no key
    report = (user_dir / "out" / "report.md").read_text()
    assert report.startswith("# Sweep my-sweep\n") and "| x (m) |" in report
    # the same scenario named in a config file, with a key of its own changed: a larger sweep, extended
    (user_dir / "mine.toml").write_text('scenario = "my_sweep:SCENARIO"\nconfigs = 300\n')
    status, out, err = _run(capsys, "sweep", "--config", "mine.toml", "--out", "out")
    assert status == 0, err
    assert out[-1] == f"  invalid configurations: {int((load_results('out')['param.x'] >= 0.9).sum())} of 300"
    assert json.loads((user_dir / "out" / "manifest.json").read_text())["config"]["scenario"] == "my-sweep"


def test_print_config_of_my_scenario_names_it_as_given(user_dir, capsys):
    status, out, _ = _run(capsys, "sweep", "--scenario", "my_sweep:SCENARIO", "--print-config")
    assert status == 0
    text = "\n".join(out)
    assert 'scenario = "my_sweep:SCENARIO"' in text and "# how many\nconfigs = 200" in text
    assert "# base of every configuration's random key" in text  # the common keys have their notes


@pytest.mark.parametrize(
    "reference, message",
    [
        ("nowhere:SCENARIO", "cannot import 'nowhere' (no module 'nowhere' in "),
        ("my_sweep:NOPE", "module 'my_sweep' ("),
        ("my_sweep:NOT_A_SCENARIO", "my_sweep:NOT_A_SCENARIO is a int, not a jaxobs.papers.scenarios.SweepScenario"),
        ("my_sweep", "must be one of 'force-control', "),
        (":SCENARIO", "':SCENARIO' is not a reference 'module:ATTRIBUTE'"),
    ],
)
def test_a_reference_that_cannot_be_loaded_exits_2_with_one_line(user_dir, capsys, reference, message):
    status, out, err = _run(capsys, "sweep", "--scenario", reference, "--out", "out")
    assert status == 2 and len(err.strip().splitlines()) == 1
    assert err.startswith(f"jaxobs sweep: --scenario: scenario: {message}"), err


def test_a_config_and_a_scenario_flag_that_disagree_exit_2(user_dir, capsys):
    (user_dir / "other.toml").write_text('scenario = "liu-peng"\n')
    status, _, err = _run(capsys, "sweep", "--config", "other.toml", "--scenario", "my_sweep:SCENARIO")
    assert status == 2
    assert err.strip() == "jaxobs sweep: other.toml: scenario: is 'liu-peng', not the 'my_sweep:SCENARIO' of --scenario"


def test_an_installed_scenario_is_listed_and_runs(user_dir, capsys, monkeypatch):
    """An entry point of the group jaxobs.sweeps (what a package's pyproject.toml declares)."""
    dist = user_dir / "my_sweep_pkg-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: my-sweep-pkg\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[jaxobs.sweeps]\nmy-sweep = my_sweep:SCENARIO\n")
    assert list(registry.sweep_scenarios())[-1] == "my-sweep"
    status, out, _ = _run(capsys, "sweep", "--list")
    scenarios = out[: out.index("")]  # then the shipped configs
    assert status == 0 and scenarios[-1].startswith("my-sweep") and "A cheap scenario of my own" in scenarios[-1]
    status, out, err = _run(capsys, "sweep", "--scenario", "my-sweep", "--out", "out")
    assert status == 0, err
    (dist / "entry_points.txt").write_text("[jaxobs.sweeps]\nsomething-else = my_sweep:SCENARIO\n")
    with pytest.raises(ValueError, match="the name is not its scenario's name, 'my-sweep'"):
        registry.sweep_scenarios()


# ---------------------------------------------------------------------------------------------------------------
# the TOML state-space block


def _config(**tables) -> dict:
    return {"scenario": "state-space", **tables}


@pytest.mark.parametrize(
    "given, key, message",
    [
        (_config(model={"A": [[0, 1], ["-q", 0]], "B": [[0], [1]], "C": [[1, 0]]}), "model.A[1][0]",
         "'-q': the name 'q' is not allowed (parameters: k, J_m, J_l, c, tau;"),
        (_config(model={"dead_time": "__import__('os')"}), "model.dead_time", "\"__import__('os')\": '__import__("),
        (_config(model={"B": [[0], [1], [0]]}), "model.B", "must be 4 rows, one per state (A 4x4, B 3x1, C 1x4"),
        (_config(model={"D": [[1]]}), "model.D", "must be zero"),
        (_config(model={"A": [[0, 1], [2]]}), "model.A", "must be a matrix: a list of rows of equal length"),
        (_config(model={"time": "sampled"}), "model.time", "must be one of 'continuous', 'discrete'"),
        (_config(parameters={"k": {"nominal": 1.0, "range": [-1.0, 1.0], "distribution": "log-uniform"}}),
         "parameters.k.range", "a log-uniform range must be positive"),
        (_config(parameters={"k": {"nomnal": 1.0}}), "parameters.k.nomnal", "unknown key"),
        (_config(parameters={"k": 3.0}), "parameters.k", "must be a table (keys: nominal, unit, range, scale"),
        (_config(design={"Q": [1.0, 1.0]}), "design.Q", "needs 4 entries (one per state of the model)"),
        (_config(design={"measurement_noise": [0.0]}), "design.measurement_noise", "entries must be positive"),
        (_config(model={"C": [[1, 0, 0, 0], [0, 0, 1, 0]], "D": [[0], [0]]}, design={"measurement_noise": [1e-6, 1e-6]},
                 noise={"sensor_std": [0.0, 0.0]}, simulation={"reference": [0.0, 0.01]}),
         "simulation.reference", "the step's pre-gain needs as many outputs as inputs (2 and 1)"),
        (_config(parameters={"k": {"nominal": 0.0, "range": [0.5, 2.0]}}), "parameters.k.range",
         "a relative range of a zero nominal value is a point"),
    ],
)  # fmt: skip
def test_the_toml_block_is_checked_key_by_key(given, key, message):
    with pytest.raises(ConfigError, match=rf"^my.toml: {re.escape(key)}: {re.escape(message)}"):
        SCENARIO.validate(given, "my.toml")


def _two_mass(k, J_m, J_l, c):
    A = [[0, 1, 0, 0], [-k / J_m, -c / J_m, k / J_m, c / J_m], [0, 0, 0, 1], [k / J_l, c / J_l, -k / J_l, -c / J_l]]
    return ss(A, [[0], [1 / J_m], [0], [0]], [[0, 0, 1, 0]])


def test_the_plant_of_the_expressions_is_the_model_discretised():
    """The default block's expressions give the two-mass spring, discretised with its dead time in as many slots
    as the largest dead time of the range needs (3.5 ms at 2 ms: 2); discrete models delay by whole samples."""
    config = SCENARIO.validate()
    model = parse(config, "x")
    values = nominal_values(config) | {"k": 120.0, "tau": 0.003}
    want = c2d(_two_mass(120.0, 0.01, 0.02, 0.05), 0.002, 0.003, n_delay=2)
    got = model.plant(values)
    assert model.n_delay == 2
    for a, b in zip((got.A, got.B, got.C), (want.A, want.B, want.C), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    discrete = SCENARIO.validate({"model": {"time": "discrete", "A": [[0.5, 0], [1, 0.2]], "B": [[1], [0]],
                                            "C": [[0, 1]], "D": [[0]]},
                                  "parameters": {"tau": {"nominal": 0.004, "range": [0.0, 0.006], "scale": "absolute"}},
                                  "design": {"Q": [1, 1], "process_noise": [1, 1]}})  # fmt: skip
    model = parse(discrete, "x")
    plant = model.plant({"tau": 0.004})  # 2 samples of 2 ms, in 3 slots
    assert model.n_delay == 3
    x, impulse = np.zeros(plant.n_states), []
    for k in range(6):
        impulse.append((np.asarray(plant.C) @ x).item())
        x = np.asarray(plant.A) @ x + np.asarray(plant.B)[:, 0] * (k == 0)
    np.testing.assert_allclose(impulse, [0, 0, 0, 0, 1, 0.7])  # C B = 0, then C A B = 1, C A^2 B = 0.7, delayed 2
    assert np.isnan(np.asarray(model.plant({"tau": 0.008}).A)).all()  # 4 samples: beyond the slots, invalid
    assert parse(SCENARIO.validate({"model": {"dead_time": 0.001}}), "x").n_delay == 1  # a number, not a name
    with pytest.raises(ConfigError, match="^x: model.dead_time: must be a number or an expression"):
        SCENARIO.validate({"model": {"dead_time": [0.001]}}, "x")


# ---------------------------------------------------------------------------------------------------------------
# end to end (slow): the guide's two-mass spring, invalid configurations, a design unstable on the nominal plant


@pytest.mark.slow
@pytest.mark.published
def test_the_guides_two_mass_spring_from_a_temporary_directory(tmp_path, monkeypatch, capsys):
    """tuning/two-mass.toml as the guide runs it: the stable fraction per stiffness bin it prints, the generic
    report's figures."""
    monkeypatch.chdir(tmp_path)
    status, out, err = _run(capsys, "sweep", "--config", str(ROOT / "tuning" / "two-mass.toml"), "--out", "out")
    assert status == 0, err
    assert out[-1] == "  invalid configurations: 0 of 10000"
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["figures"] == ["stable_fraction.png", "metrics.png"]
    pin(summary["stable_fraction"], r"two-mass\.toml.*?stable fraction ([0-9.]+)")
    bins = summary["parameters"]["k"]["bins"]
    fractions = " ".join(f"{b['stable_fraction']:.2f}" for b in bins)
    assert re.search(rf"\| k \(N m/rad\) \| [\d.]+ to [\d.]+ \| 10 equal bins \| \d+ to \d+ \| {fractions} \|",
                     (ROOT / "docs" / "guides" / "sweeps.md").read_text()), fractions  # fmt: skip


@pytest.mark.slow
def test_invalid_configurations_and_a_nominally_unstable_design_are_reported(tmp_path, caplog):
    """A dead time below 0 in 10 % of the configurations makes them invalid: counted, NaN margins, no statistic
    (under an AOB-2 design); a design unstable on the nominal plant (a fast LQG that ignores the 1.5 ms of dead
    time) is said to be before the sweep."""
    given = {"scenario": "state-space", "configs": 400, "chunk_size": 200, "simulation": {"duration": 0.1},
             "design": {"family": "aob", "order": 2, "q_active": 1.0},
             "parameters": {**SCENARIO.defaults["parameters"],
                            "tau": {"nominal": 0.0015, "range": [-0.0005, 0.0045], "scale": "absolute"}}}  # fmt: skip
    summary = SCENARIO.run(SCENARIO.validate(given, "x"), tmp_path / "invalid", progress=False)
    rows = load_results(tmp_path / "invalid")
    invalid = rows["param.tau"] < 0
    assert summary["invalid"] == int(invalid.sum()) and 25 <= summary["invalid"] <= 55
    assert not rows["metric.valid"][invalid].any() and rows["metric.valid"][~invalid].all()
    for name in ("spectral_radius", "gain_margin", "phase_margin", "delay_margin", "rms_error"):
        assert np.isnan(rows[f"metric.{name}"][invalid]).all(), name
    assert "Invalid configurations: " in (tmp_path / "invalid" / "report.md").read_text()
    caplog.set_level(logging.WARNING, logger="jaxobs")
    unstable = {
        "scenario": "state-space",
        "configs": 4,
        "chunk_size": 4,
        "simulation": {"duration": 0.02},
        "design": {"dead_time": 0, "Q": [0, 0, 1e8, 0], "R": [1e-4], "process_noise": [0, 100, 0, 100]},
    }
    SCENARIO.run(SCENARIO.validate(unstable, "x"), tmp_path / "unstable", progress=False)
    assert "the lqg design is unstable (spectral radius 1.148) on the nominal plant" in caplog.text


@pytest.mark.slow  # compiles the module's two-mass LQG sweep
def test_the_guides_module_is_the_one_the_command_runs(tmp_path, monkeypatch, capsys):
    """The guide's two_mass.py (its first python block under "From your own module") is a module the command runs
    with --scenario, from the directory that holds it (a small run of it)."""
    page = (ROOT / "docs" / "guides" / "sweeps.md").read_text()
    section = page.split("### From your own module")[1]
    code = section.split("```python\n")[1].split("```")[0]
    (tmp_path / "two_mass.py").write_text(code)
    (tmp_path / "small.toml").write_text('scenario = "two_mass:SCENARIO"\nconfigs = 8\nchunk_size = 4\n'
                                         "num_points = 64\n")  # fmt: skip
    monkeypatch.chdir(tmp_path)
    status, out, err = _run(capsys, "sweep", "--config", "small.toml", "--out", "out")
    assert status == 0, err
    assert out[-1] == "  invalid configurations: 0 of 8"
