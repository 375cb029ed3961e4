"""``jaxobs tune``: config errors, the random search's box, and (slow) small end-to-end runs against the MJX
force plant: outputs, resume from the checkpoint, a corrupt checkpoint, a training set with diverging plants,
and the held-out loss falling."""

import json

import numpy as np
import pytest

from jaxobs._config import ConfigError
from jaxobs.cli import main
from jaxobs.papers import tune_job, tuning_config
from jaxobs.papers.cortesao import force_tuning, peg_tuning
from jaxobs.papers.tune_job import markdown_report
from jaxobs.tuning import gradient_mode


def test_default_config_is_the_one_dof_stiffness_problem():
    config = force_tuning.PROBLEM.validate()
    assert config["problem"] == "force-1dof"
    assert config["plants"]["stiffness_scale"] == [0.5, 1.5]  # +-50 % stiffness mismatch
    assert config["design"]["order"] == 1
    assert (config["design"]["q_active"], config["design"]["R"]) == (1e-5, 2.1e-2)  # The MRAC chapter eq. 62, 64
    theta = force_tuning.initial_theta(config, force_tuning.nominal_design()[0])
    np.testing.assert_allclose(np.exp(theta["log_q"]), [1e-12] * 7 + [1e-5], rtol=1e-12)


@pytest.mark.parametrize(
    "toml, key",
    [
        ('problem = "nope"\n', "problem"),
        ("[plants]\ntrain = 0\n", "plants.train"),
        ("[plants]\nstiffness_scale = [1.5, 0.5]\n", "plants.stiffness_scale"),
        ("[design]\norder = 4\n", "design.order"),
        ('[design]\nparameterisation = "full"\n', "design.parameterisation"),
        ('[optimizer]\noptimizer = "newton"\n', "optimizer"),
        ("[optimizer]\nlearning_rate = -1.0\n", "optimizer"),
        ("[scenario]\nwhatever = 1\n", "scenario.whatever"),
    ],
)
def test_config_errors_name_the_key_and_file_and_exit_2(tmp_path, capsys, toml, key):
    path = tmp_path / "bad.toml"
    path.write_text(toml)
    out = tmp_path / "out"
    assert main(["tune", "--config", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and key in err
    assert not out.exists()


def test_invalid_mjcf_exits_2(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    (tmp_path / "plant.xml").write_text("<mujoco><worldbody></worldbody></mujoco>")
    path.write_text(f'[plants]\nmjcf = "{tmp_path / "plant.xml"}"\n')
    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert "plant.xml: the force sensor is missing" in capsys.readouterr().err


SMALL = """
[plants]
train = 3
heldout = 4
[scenario]
duration = 0.4
[design]
parameterisation = "{kind}"
[optimizer]
steps = {steps}
screening = 15
evolve = 0
checkpoint_every = 2
[baseline]
random_search = {search}
"""


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["diagonal", "cholesky", "structured"])
def test_small_run_writes_its_outputs_and_resumes(tmp_path, capsys, kind):
    """Every parameterisation runs the shipped strategy without its CMA-ES (16 screened candidates, then 2 starts;
    tests/tuning covers the exploration) end to end on the MJX
    plant (the random search, which runs as long as the tuning, with the diagonal one only); a rerun with more steps
    continues the checkpoint, and a rerun of the finished one leaves tuned.json as it was (no compilation, no new
    time); a corrupt checkpoint is an error (exit 2), not a silent restart. The report names the parameters."""
    config, out = tmp_path / "small.toml", tmp_path / "out"
    search = str(kind == "diagonal").lower()
    config.write_text(SMALL.format(kind=kind, steps=3, search=search))
    assert main(["tune", "--config", str(config), "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "tuned.json").read_text())
    assert summary["evaluations"] == 2 * 3 and summary["rollouts"] == (16 + 2 * 3) * 3
    assert set(summary["heldout"]["tuned"]) >= {"objective", "finite_fraction", "p50", "p90", "max"}
    if kind == "diagonal":
        found = summary["random_search"]
        assert found["equal rollouts"]["rollouts"] == (16 + 2 * 3) * 3  # the baseline at as many rollouts
        assert found["equal time"]["seconds"] <= summary["seconds_tune"]
        assert found["candidates"] >= 22 and found["spread"] == 8.0  # the problem's search box
        baselines = {"random search, equal rollouts", "random search, equal time"}
        assert set(summary["heldout"]) == {"hand-set", "tuned", *baselines}
    assert summary["train_objective"]["tuned"] < summary["train_objective"]["hand-set"]
    for name in ("loss_curves.png", "parameters.png", "responses.png", "checkpoint.npz", "report.md"):
        assert (out / name).stat().st_size > 0
    report = (out / "report.md").read_text()
    assert f"| tuned | {summary['heldout']['tuned']['objective']:.4g} |" in report
    first = {"diagonal": "log Q[F]", "cholesky": "log scale Q[F]", "structured": "log q_plant"}[kind]
    assert summary["parameter_labels"]["log_r"] == ["log R[force]"] and f"| {first} |" in report
    config.write_text(SMALL.format(kind=kind, steps=5, search=search))
    assert main(["tune", "--config", str(config), "--out", str(out), "--no-progress"]) == 0
    resumed = json.loads((out / "tuned.json").read_text())
    assert resumed["evaluations"] > 6 and all(start["evaluations"] <= 5 for start in resumed["starts"])
    assert resumed["train_objective"]["hand-set"] == summary["train_objective"]["hand-set"]
    assert resumed["compile_seconds_tune"] > summary["compile_seconds_tune"]  # both runs' compilations
    capsys.readouterr()
    assert main(["tune", "--config", str(config), "--out", str(out), "--no-progress"]) == 0  # finished: a rerun
    assert "holds a finished run" in capsys.readouterr().err
    assert json.loads((out / "tuned.json").read_text()) == resumed  # no compilation, no new time, no new scores
    (out / "checkpoint.npz").write_bytes(b"garbage")
    capsys.readouterr()
    assert main(["tune", "--config", str(config), "--out", str(out), "--no-progress"]) == 2
    assert "corrupt" in capsys.readouterr().err


@pytest.mark.slow
def test_spectral_radius_penalty():
    """The optional penalty is the mean squared excess of the closed-loop spectral radius (eq. 59, analytic
    true plants of the training batch) over design.spectral_radius_limit, checked against NumPy eigenvalues;
    it is differentiable (finite, non-zero gradient where active)."""
    import jax
    import jax.numpy as jnp

    from jaxobs.observers.active import active_observer_controller
    from jaxobs.papers.cortesao.force_control import EXAMPLE1
    from jaxobs.plants import force_plant
    from jaxobs.stability import closed_loop_matrix

    config = force_tuning.PROBLEM.validate(
        {"plants": {"train": 3, "heldout": 1}, "scenario": {"duration": 0.1}, "design": {"spectral_radius_limit": 0.9}}
    )
    problem = force_tuning.build_problem(config)
    theta = problem.theta0
    plant, L = force_tuning.nominal_design()
    base = force_tuning.active.make_aob(plant, 1, 2.1e-2)
    ctrl = force_tuning.controller(theta, base, L, plant.n_states, 1)
    rho = [
        np.max(np.abs(np.linalg.eigvals(np.asarray(
            closed_loop_matrix(force_plant(ks, tp, EXAMPLE1.h, 0.04), active_observer_controller, ctrl)))))
        for ks, tp in zip(problem.train["ks"], problem.train["tp"], strict=True)
    ]  # fmt: skip
    expected = np.mean(np.maximum(np.array(rho) - 0.9, 0.0) ** 2)
    assert expected > 0
    assert float(problem.penalty(theta)) == pytest.approx(expected, rel=1e-9)
    grad = jax.grad(problem.penalty)(theta)
    assert np.all(np.isfinite(grad["log_q"])) and float(jnp.abs(grad["log_q"][-1])) > 0
    default_limit = force_tuning.PROBLEM.validate()["design"]["spectral_radius_limit"]
    assert max(rho) < default_limit  # the default limit: no penalty


def test_peg_config_is_validated(tmp_path, capsys):
    config = peg_tuning.PROBLEM.validate({"problem": "peg-on-hole"})
    assert config["problem"] == "peg-on-hole" and config["optimizer"]["gradient"] == "auto"
    theta0 = peg_tuning.PROBLEM.build(config).theta0  # 4 parameters: forward mode
    assert gradient_mode(tuning_config.settings(config), theta0) == "forward"
    path = tmp_path / "bad.toml"
    path.write_text('problem = "peg-on-hole"\n[scenario]\nalignment_end = 9.0\n')
    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "out")]) == 2
    assert "scenario.alignment_end" in capsys.readouterr().err


def test_out_dir_of_another_run_is_refused(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "config.json").write_text('{"tag": "another run"}')
    assert main(["tune", "--out", str(out), "--no-progress"]) == 2
    assert "holds a tuning run of another configuration" in capsys.readouterr().err
    (out / "config.json").write_text("{not json")
    assert main(["tune", "--out", str(out), "--no-progress"]) == 2
    assert "unreadable" in capsys.readouterr().err


def test_the_search_box_is_the_problems_spread():
    """The box theta0 +- baseline.spread (8 for the force problem) on every log coordinate; a Cholesky factor's
    couplings (dimensionless) +- COUPLING_HALF_WIDTH, its unused upper triangle fixed; the tuner's screening gets
    the same spread and seed; a spread of 0 is refused."""
    config = force_tuning.PROBLEM.validate({"design": {"parameterisation": "cholesky"}})
    assert config["baseline"]["spread"] == 8.0
    theta0 = {"q_cholesky": np.diag([1.0, 2.0]), "log_r": np.asarray(-3.0)}
    box = tuning_config.search_box(config, theta0, cholesky=("q_cholesky",))
    coupling = tuning_config.COUPLING_HALF_WIDTH
    np.testing.assert_array_equal(box["q_cholesky"][0], [[-7.0, 0.0], [-coupling, -6.0]])
    np.testing.assert_array_equal(box["q_cholesky"][1], [[9.0, 0.0], [coupling, 10.0]])
    assert (float(box["log_r"][0]), float(box["log_r"][1])) == (-11.0, 5.0)
    given = force_tuning.PROBLEM.validate({"baseline": {"spread": 2.5}, "seed": 7})
    assert (tuning_config.settings(given).spread, tuning_config.settings(given).seed) == (2.5, 7)
    with pytest.raises(ConfigError, match="baseline.spread: must be > 0"):
        force_tuning.PROBLEM.validate({"baseline": {"spread": 0.0}})
    position = tune_job._box_position({"q_cholesky": np.diag([1.0, 10.0]), "log_r": np.asarray(-11.0)}, box)
    assert position == {"q_cholesky": [0.5, 0.5, 1.0], "log_r": [0.0]}


DIVERGING = """
[plants]
stiffness_scale = [0.5, 20.0]
train = 8
heldout = 8
[scenario]
duration = 1.0
force_limit = 900.0
[optimizer]  # adam from the hand-set design alone, the penalised divergence at work (not the shipped strategy)
optimizer = "adam"
learning_rate = 0.2
clip_norm = 5.0
screening = 0
evolve = 0
starts = 1
patience = 12
steps = 10
[baseline]
random_search = false
"""


@pytest.mark.slow
def test_diverging_training_plants_are_penalised_and_the_held_out_loss_falls(tmp_path, capsys):
    """Stiffness up to 20x nominal: 2 of 8 training plants exceed the 900 N limit under the hand-set design. The
    tuner starts (penalising them), and in 10 evaluations the held-out objective falls (measured 7.35e4 ->
    6.29e3) with every held-out plant kept below the limit (hand-set: 7 of 8)."""
    config, out = tmp_path / "diverging.toml", tmp_path / "out"
    config.write_text(DIVERGING)
    assert main(["tune", "--config", str(config), "--out", str(out), "--no-progress"]) == 0
    assert "2 of 8 training plants diverge under the initial design" in capsys.readouterr().err
    summary = json.loads((out / "tuned.json").read_text())
    assert summary["train_diverged"] == {"hand-set": 2, "tuned": 0}
    hand, tuned = summary["heldout"]["hand-set"], summary["heldout"]["tuned"]
    assert hand["finite_fraction"] == 7 / 8 and tuned["finite_fraction"] == 1.0
    assert tuned["objective"] < 0.5 * hand["objective"]
    assert tuned["p90"] < hand["p90"]


def _held(objective, reduction):
    return {"objective": objective, "reduction_vs_hand_set": reduction, "finite_fraction": 1.0, "p50": objective,
            "p90": 2 * objective, "max": 3 * objective}  # fmt: skip


def test_the_report_gives_held_out_results_run_time_and_baselines():
    """report.md, from tuned.json's content: a row per design (the change against the hand-set design), the time
    split into compiling and computing, a row per start, the random search's budgets, the parameters by name (a log
    entry's change as its factor), the settings, the figures."""
    summary = {
        "problem": "force-1dof", "stopped": "converged", "converged": True, "evaluations": 12, "rollouts": 3000,
        "seconds_tune": 30.0, "compile_seconds_tune": 10.0, "train_objective": {"hand-set": 4.0, "tuned": 1.0},
        "config": {"plants": {"train": 4, "heldout": 8}, "optimizer": {"objective": "cvar", "steps": 20}},
        "heldout": {"hand-set": _held(5.0, 0.0), "tuned": _held(2.0, 0.6),
                    "random search, equal time": _held(4.0, 0.2)},
        "starts": [{"objective": 1.0, "diverged": 0, "evaluations": 7, "stopped": "converged"},
                   {"objective": 1.5, "diverged": 1, "evaluations": 5, "stopped": "converged"}],
        "random_search": {"spread": 2.0, "candidates": 50, "tuned_position_in_box": {},
                          "equal time": {"candidates": 40, "rollouts": 160, "seconds": 29.0, "train_objective": 3.0}},
        "figures": ["loss_curves.png"],
        "parameter_labels": {"log_q": ["log Q[F]", "log Q[p]"], "c": ["coupling"]},
        "theta": {"hand-set": {"log_q": [0.0, -2.0], "c": [0.5]}, "tuned": {"log_q": [0.0, -2.0 + np.log(2.0)],
                                                                           "c": [0.25]}},
    }  # fmt: skip
    report = markdown_report(summary)
    assert "| log Q[F] | 0 | 0 | x 1 |" in report and "| log Q[p] | -2 | -1.307 | x 2 |" in report
    assert "| coupling | 0.5 | 0.25 | -0.25 |" in report
    assert "| hand-set | 5 | - | 100 % | 5 | 10 | 15 |" in report
    assert "| tuned | 2 | -60.0 % | 100 % | 2 | 4 | 6 |" in report
    assert "| random search, equal time | 4 | -20.0 % |" in report
    assert "30.0 s of tuning (10.0 s compiling, 20.0 s computing" in report and "3 000 rollouts" in report
    assert "| 1 | 1.5 | 1 | 5 | converged |" in report
    assert "| equal time | 40 | 160 | 29 | 3 |" in report
    assert '- `objective = "cvar"`' in report and "![loss_curves.png](loss_curves.png)" in report
