"""The own-robot tuning problem (jaxobs.papers.robot_tuning): its config (TOML of any MJCF), and a slow end-to-end
run of the shipped payload-cart example that pins its README row."""

import json

import numpy as np
import pytest

from jaxobs._config import ConfigError, load_toml
from jaxobs.cli import main
from jaxobs.papers import robot_tuning
from tests import ROOT, run_cli


def test_shipped_config_file_validates_to_the_default():
    path = "tuning/cartpole_payload.toml"
    # the shipped file's robot and the default's resolve to the same packaged MJCF
    assert robot_tuning.PROBLEM.validate(load_toml(path), path) == robot_tuning.PROBLEM.validate({})
    arm = robot_tuning.PROBLEM.validate(load_toml("tuning/arm_on_table.toml"), "tuning/arm_on_table.toml")
    assert arm["robot"]["solver_iterations"] == 4
    full = {"tuning/arm_on_table_cholesky.toml": "kalman", "tuning/cartpole_payload_aob.toml": "aob"}
    for path, observer in full.items():
        design = robot_tuning.PROBLEM.validate(load_toml(path), path)["design"]
        assert (design["observer"], design["parameterisation"]) == (observer, "cholesky")


def test_full_covariances_start_at_the_hand_set_filter():
    """The Cholesky parameterisation of the hand-set Q (every filter state: qpos, qvel, command in flight, active
    state) and R designs the same AOB as the log-diagonal one; it counts 21 + 3 free parameters. design.lqr_state
    takes the (qpos, qvel) count or the linearised model's (the command in flight too), as dlqr does."""
    given = {"problem": robot_tuning.NAME, "scenario": {"duration": 0.1},
             "design": {"observer": "aob", "q_input": [1e-4], "q_active": [1e-2]}}  # fmt: skip
    diagonal = robot_tuning.build_problem(robot_tuning.PROBLEM.validate(given))
    given["design"].update(parameterisation="cholesky", lqr_state=[10.0, 10.0, 1.0, 1.0, 0.0])
    full = robot_tuning.build_problem(robot_tuning.PROBLEM.validate(given))
    assert {k: v.shape for k, v in full.theta0.items()} == {"q_cholesky": (6, 6), "r_cholesky": (2, 2)}
    assert sum(int(np.sum(hi > lo)) for lo, hi in full.search_box.values()) == 24
    np.testing.assert_allclose(full.describe(full.theta0)["kalman_gain"],
                               diagonal.describe(diagonal.theta0)["kalman_gain"], rtol=1e-9)  # fmt: skip


@pytest.mark.parametrize(
    "given, key",
    [
        ({"robot": {"actuators": [1]}}, "robot.actuators"),
        ({"robot": {"dead_time": -1}}, "robot.dead_time"),
        ({"plants": {"mismatch": {"body_mass[payload]": [0.0, 2.0]}}}, r"plants.mismatch.body_mass\[payload\]"),
        ({"plants": {"mismatch": {"body_mass[payload]": ["heavy"]}}}, r"plants.mismatch.body_mass\[payload\]"),
        ({"plants": {"mismatch": {}}}, "plants.mismatch"),
        ({"scenario": {"tracked": ["pole_tip"]}}, "scenario.tracked"),
        ({"scenario": {"reference": [0.5, 0.1]}}, "scenario.tracked"),
        ({"design": {"lqr_input": [0.01, 0.01]}}, "design.lqr_input"),
        ({"robot": {"sensor_noise": [0.0, 0.1]}}, "robot.sensor_noise"),
        ({"design": {"observer": "luenberger"}}, "design.observer"),
        ({"design": {"parameterisation": "full"}}, "design.parameterisation"),
        ({"design": {"observer": "aob"}}, "design.q_active"),
        ({"design": {"q_input": [1e-4, 1e-4]}}, "design.q_input"),
        ({"design": {"q_input": [-1e-4]}}, "design.q_input"),
        ({"design": {"observer": "aob", "q_active": [0.0]}}, "design.q_active"),
        ({"design": {"parameterisation": "cholesky"}}, "design.q_input"),
    ],
)
def test_bad_config_names_the_key(given, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        robot_tuning.PROBLEM.validate({"problem": robot_tuning.NAME, **given})


@pytest.mark.parametrize(
    "toml, message",
    [
        ('[robot]\nmjcf = "no/such/robot.xml"\n', "MJCF no/such/robot.xml: cannot load it"),
        ('[robot]\nactuators = ["motor"]\n', "unknown actuator 'motor'; the model's actuators are: 'push'"),
        ('[plants.mismatch]\n"body_mass[load]" = [0.5, 2.0]\n', "unknown body 'load'; the model's bodies are: "),
        ('[plants.mismatch]\n"dof_dampin[hinge]" = [0.5, 2.0]\n', "'dof_dampin' is not a scalable model field"),
        ("[design]\nq = [1e-6, 1e-6, 1e-4]\n", "design.q: needs one value per qpos and qvel entry (4), got 3"),
        (
            "[design]\nlqr_state = [10.0, 10.0, 1.0]\n",
            "design.lqr_state: needs one weight per qpos and qvel entry (4) or per state of the linearised model (5: "
            "qpos, qvel, then 1 x 1 commands in flight), got 3",
        ),
    ],
)
def test_robot_errors_exit_2_with_the_reason(tmp_path, capsys, toml, message):
    """Checked before anything compiles: the MJCF, the names in it, the mismatched fields and the counts the model
    sets; nothing is written to the output directory, so the corrected config is not refused as another run's."""
    path = tmp_path / "robot.toml"
    path.write_text('problem = "own-robot"\n' + toml)
    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "out" / "config.json").exists()


def test_a_constrained_model_without_a_solver_count_is_refused_in_reverse_mode(tmp_path, capsys):
    """The arm with a wall and a joint limit, its solver left to MJX's while loop: refused before anything compiles,
    naming the key to change."""
    path = tmp_path / "arm.toml"
    path.write_text(
        (ROOT / "tuning/arm_on_table.toml").read_text().replace("solver_iterations = 4", "solver_iterations = 0")
    )
    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "robot.solver_iterations: the model has 5 constraint rows" in err and "Traceback" not in err


@pytest.mark.slow
@pytest.mark.published
def test_readme_table_row(tmp_path):
    """``jaxobs tune --config tuning/cartpole_payload.toml`` end to end: every output, in the report format of the
    other problems, the tuned filter lowers the training objective, and the README's tuning-table row: the held-out
    objectives of the hand-set filter, the tuned one and the random search at equal rollouts (seeded, so
    reproducible; the equal-time search depends on the machine's speed and is not pinned)."""
    from tests._published import pin

    out = tmp_path / "robot"
    run_cli(["tune", "--config", "tuning/cartpole_payload.toml", "--out", str(out), "--no-progress"])
    summary = json.loads((out / "tuned.json").read_text())
    assert summary["converged"] and all(start["stopped"] == "converged" for start in summary["starts"])
    assert summary["train_diverged"] == {"hand-set": 0, "tuned": 0}
    assert summary["train_objective"]["tuned"] < summary["train_objective"]["hand-set"]
    searched = {"random search, equal rollouts", "random search, equal time"}
    assert set(summary["heldout"]) == {"hand-set", "tuned", *searched}
    assert summary["parameters"]["hand-set"]["R_diagonal"] == pytest.approx([0.002**2, 0.005**2])
    for name in ("loss_curves.png", "parameters.png", "responses.png"):
        assert (out / name).is_file()
    held = summary["heldout"]
    row = r"\| Own robot, [^|]*\| ([0-9.e-]+) \| ([0-9.e-]+) \(-([0-9.]+) %\) \| ([0-9.e-]+) \(-([0-9.]+) %\)"
    pin(held["hand-set"]["objective"], row, 1)
    pin(held["tuned"]["objective"], row, 2)
    pin(100 * held["tuned"]["reduction_vs_hand_set"], row, 3)
    pin(held["random search, equal rollouts"]["objective"], row, 4)
    pin(100 * held["random search, equal rollouts"]["reduction_vs_hand_set"], row, 5)
