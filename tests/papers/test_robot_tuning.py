"""The own-robot tuning problem (jaxobs.papers.robot_tuning): its config (TOML of any MJCF), and a slow end-to-end
run of the shipped payload-cart example that pins its README row."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from jaxobs._config import ConfigError, load_toml
from jaxobs.cli import main
from jaxobs.papers import robot_tuning
from jaxobs.papers.shipped import ROBOTS
from tests import ROOT, run_cli


def test_shipped_config_file_validates_to_the_default():
    path = "tuning/cartpole_payload.toml"
    # the shipped file's robot and the default's resolve to the same packaged MJCF
    assert robot_tuning.PROBLEM.validate(load_toml(path), path) == robot_tuning.PROBLEM.validate({})
    arm = robot_tuning.PROBLEM.validate(load_toml("tuning/arm_on_table.toml"), "tuning/arm_on_table.toml")
    assert arm["robot"]["solver_iterations"] == 0  # MJX's solver at the MJCF's settings
    for path in ("tuning/free_flyer.toml", "tuning/muscle_arm.toml"):
        config = robot_tuning.PROBLEM.validate(load_toml(path), path)
        assert config["robot"]["mjcf"] == str(ROBOTS / Path(path).name.replace(".toml", ".xml"))
        assert config["optimizer"]["gradient"] == "reverse"
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


@pytest.mark.slow
def test_reverse_mode_tunes_an_mjcf_whose_solver_settings_are_left_as_written(tmp_path):
    """The arm with a wall and a joint limit, its MJCF asking for 50 solver iterations to a tolerance of 1e-10 and
    ``robot.solver_iterations`` left out: ``jaxobs tune`` runs in reverse mode through MJX's own solver (implicit
    derivatives) and writes a finite tuned objective."""
    mjcf = tmp_path / "arm.xml"
    mjcf.write_text((ROBOTS / "arm_on_table.xml").read_text()
                    .replace('iterations="20"', 'iterations="50" tolerance="1e-10"'))  # fmt: skip
    toml = (ROOT / "tuning/arm_on_table.toml").read_text().replace("solver_iterations = 0", "")
    small = {
        'mjcf = "arm_on_table.xml"': f'mjcf = "{mjcf}"',
        "train = 8": "train = 2",
        "heldout = 32": "heldout = 2",
        "duration = 2.0": "duration = 0.4",
        "screening = 127": "screening = 0",
        "starts = 2": "starts = 1",
        "steps = 100": "steps = 2",
        "random_search = true": "random_search = false",
    }
    for old, new in small.items():
        toml = toml.replace(old, new)
    config = tmp_path / "arm.toml"
    config.write_text(toml)
    assert robot_tuning.PROBLEM.validate(load_toml(config), str(config))["robot"]["solver_iterations"] == 0
    assert main(["tune", "--config", str(config), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    tuned = json.loads((tmp_path / "out" / "tuned.json").read_text())
    assert tuned["config"]["optimizer"]["gradient"] == "reverse" and tuned["evaluations"] >= 1
    assert np.isfinite(tuned["train_objective"]["tuned"]) and tuned["train_diverged"]["tuned"] == 0


def test_a_floating_base_with_an_imu_is_a_tuning_problem_and_mjx_limits_are_one_line(tmp_path, capsys):
    """The free flyer's config builds (its tangent-space linearisation is compiled once: slow under load, so only
    the checks before it run here): a tracked quaternion sensor counts 3 entries, one reference each; an integrator
    MJX lacks ends the command with one line naming it, and RK4 (which MJX differentiates wrongly at a free joint)
    with one naming the joint and the file."""
    flyer = (ROOT / "tuning/free_flyer.toml").read_text()
    implicit = (ROBOTS / "free_flyer.xml").read_text().replace('integrator="Euler"', 'integrator="implicit"')
    (tmp_path / "implicit.xml").write_text(implicit)
    (tmp_path / "rk4.xml").write_text(implicit.replace('integrator="implicit"', 'integrator="RK4"'))
    for toml, message in (
        (flyer.replace('tracked = ["position_fix", "star_tracker", "shoulder_angle", "elbow_angle"]',
                       'tracked = ["position_fix", "star_tracker", "shoulder_angle"]'),
         "scenario.tracked: the tracked sensors have 7 entries; the reference gain needs one per actuator (8)"),
        (flyer.replace('q = [1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6,', 'q = [1e-6,'),
         "design.q: needs one value per tangent entry of the state (nv positions, nv velocities, na activations) "
         "(16), got 9"),
        (flyer.replace('mjcf = "free_flyer.xml"', f'mjcf = "{tmp_path / "implicit.xml"}"'),
         "cannot simulate this model: mjtIntegrator.mjINT_IMPLICIT"),
        (flyer.replace('mjcf = "free_flyer.xml"', f'mjcf = "{tmp_path / "rk4.xml"}"'),
         f"robot.mjcf {tmp_path / 'rk4.xml'}: linearize: MJX's RK4 integrator differentiates the rotation of the free "
         "joint 'root' wrongly"),
    ):  # fmt: skip
        path = tmp_path / "flyer.toml"
        path.write_text(toml)
        status = main(["tune", "--config", str(path), "--out", str(tmp_path / "out"), "--no-progress"])
        err = capsys.readouterr().err
        assert status == 2 and message in err and "Traceback" not in err, err


@pytest.mark.slow
@pytest.mark.published
def test_readme_table_row(tmp_path):
    """``jaxobs tune --config tuning/cartpole_payload.toml`` end to end: every output, in the report format of the
    other problems, the tuned filter lowers the training objective, and the README's tuning-table row: the held-out
    objectives of the hand-set filter, the tuned one and the random search at equal rollouts (seeded, so
    reproducible; the equal-time search depends on the machine's speed, is not pinned, and is left out here)."""
    from tests._published import pin

    out = tmp_path / "robot"
    run_cli(["tune", "--config", "tuning/cartpole_payload.toml", "--set", "baseline.equal_time=false", "--out",
             str(out), "--no-progress"])  # fmt: skip
    summary = json.loads((out / "tuned.json").read_text())
    assert summary["converged"] and all(start["stopped"] == "converged" for start in summary["starts"])
    assert summary["train_diverged"] == {"hand-set": 0, "tuned": 0}
    assert summary["train_objective"]["tuned"] < summary["train_objective"]["hand-set"]
    assert set(summary["heldout"]) == {"hand-set", "tuned", "random search, equal rollouts"}
    assert summary["parameters"]["hand-set"]["R_diagonal"] == pytest.approx([0.002**2, 0.005**2])
    for name in ("loss_curves.png", "parameters.png", "responses.png"):
        assert (out / name).is_file()
    held = summary["heldout"]
    row = r"\| Own robot, the payload cart[^|]*\| ([0-9.e-]+) \| ([0-9.e-]+) \(-([0-9.]+) %\) "
    row += r"\| ([0-9.e-]+) \(-([0-9.]+) %\)"
    pin(held["hand-set"]["objective"], row, 1)
    pin(held["tuned"]["objective"], row, 2)
    pin(100 * held["tuned"]["reduction_vs_hand_set"], row, 3)
    pin(held["random search, equal rollouts"]["objective"], row, 4)
    pin(100 * held["random search, equal rollouts"]["reduction_vs_hand_set"], row, 5)


def test_a_set_point_or_operating_point_outside_a_joint_range_warns_naming_the_joint():
    """The shipped arm drives its elbow against its limit on purpose (reference -0.45 rad, range [-0.3, 1.2]): the
    warning names the key, the joint, its range in radians and the MJCF's angle unit; inside the range, nothing."""
    path = "tuning/arm_on_table.toml"
    config = robot_tuning.PROBLEM.validate(load_toml(path), path)
    robot = robot_tuning._robot(config)
    with pytest.warns(UserWarning) as caught:
        robot_tuning._warn_outside_ranges(robot, config)
    (message,) = [str(w.message) for w in caught]
    assert message.startswith("scenario.reference (from robot.qpos0): hinge joint 'elbow' at -0.45 rad lies outside "
                              "its range [-0.3, 1.2] rad (MJCF ranges are in degrees unless")  # fmt: skip
    config["scenario"]["reference"] = [-0.85, 0.5]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        robot_tuning._warn_outside_ranges(robot, config)
    config["robot"]["qpos0"] = [0.0, 2.0]
    with pytest.warns(UserWarning, match=r"^robot.qpos0: hinge joint 'elbow' at 2 rad lies outside"):
        robot_tuning._warn_outside_ranges(robot_tuning._robot(config), config)
