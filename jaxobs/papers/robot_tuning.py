"""Tuning the Kalman filter of an LQG controller against MJX rollouts of your own robot (any MJCF).

The robot (:func:`jaxobs.mjx.robot.make_robot`) is the config's MJCF with its actuators, sensors, control period,
dead time and sensor noise; the controller (steady-state Kalman filter, LQR, reference pre-gain) is designed on the
model linearised about the operating point; with ``design.observer = "aob"`` the filter is an AOB-1 whose active
state (an equivalent input disturbance per actuator) the feedback cancels (Cortesão 2006 eq. 49-50). Tuned: the
filter's noise covariances, as log diagonals (``design.parameterisation = "diagonal"``) or as full Cholesky factors
of ``Q`` over every filter state and of ``R`` (``"cholesky"``); the loss is the error against the desired closed
loop (Cortesão 2006 eq. 43) on plants with mismatched fields. Shipped example:
``cartpole_payload.xml`` (a shipped robot) with ``tuning/cartpole_payload.toml``. Details: docs/theory/papers.md.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, check_choice, fail
from jaxobs.closed_loop import ideal_response
from jaxobs.observers import active, feedback, kalman
from jaxobs.papers.scenarios import TuningScenario
from jaxobs.papers.tuning_config import (
    BASELINE_DEFAULTS,
    SHIPPED_STRATEGY,
    optimizer_defaults,
    search_box,
    settings,
)
from jaxobs.tuning import TuningProblem, cholesky_covariance, cholesky_parameters, gradient_mode

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "LQG", "PROBLEM", "build_problem", "lqg_params"]

NAME = "own-robot"
OBSERVERS = ("kalman", "aob")
PARAMETERISATIONS = ("diagonal", "cholesky")

LQG = feedback.observer_controller(kalman.kalman_filter)
"""The controller: a Kalman filter with the state feedback ``u = N r - L x_hat`` (params: :func:`lqg_params`)."""

DEFAULT_CONFIG = {
    "problem": NAME,
    "seed": 0,
    "robot": {
        "mjcf": "cartpole_payload.xml",
        "actuators": ["push"],
        "sensors": ["cart_position", "pole_angle"],
        "substeps": 2,
        "dead_time": 1,
        "sensor_noise": [0.002, 0.005],
        "qpos0": [],
        "ctrl0": [],
        "solver_iterations": 4,
    },
    "plants": {"train": 8, "heldout": 32, "mismatch": {"body_mass[payload]": [0.25, 2.0]}},
    "scenario": {
        "duration": 3.0,
        "tracked": ["cart_position"],
        "reference": [0.5],
        "output_weights": [1.0, 1.0],
        "input_weight": 0.0,
        "state_limit": 10.0,
    },
    "design": {
        "observer": "kalman",
        "parameterisation": "diagonal",
        "q": [1e-6, 1e-6, 1e-4, 1e-4],
        "q_input": [],
        "q_active": [],
        "lqr_state": [10.0, 10.0, 1.0, 1.0],
        "lqr_input": [0.01],
    },
    "optimizer": optimizer_defaults(**SHIPPED_STRATEGY, checkpoint_every=5),
    "baseline": {**BASELINE_DEFAULTS, "spread": 4.0},
}
"""Tune the Kalman filter of the cart with a hanging payload of unknown mass (0.25x to 2x the nominal 0.5 kg)."""

CONFIG_NOTES = {
    "robot": "your robot: the MJCF and what the controller sees of it (jaxobs.mjx.robot.make_robot)",
    "robot.mjcf": "path of the MJCF file: relative to the config file's directory (the current directory without "
    "one), or the name of a shipped robot (cartpole_payload.xml, arm_on_table.xml)",
    "robot.actuators": "names of the actuators the controller drives",
    "robot.sensors": "names of the sensors it measures (position or velocity stage)",
    "robot.substeps": "physics steps per control period",
    "robot.dead_time": "command dead time in control periods",
    "robot.sensor_noise": "standard deviation of the true sensors' noise, one per measured sensordata entry",
    "robot.qpos0": "operating point (qpos) to linearise about and regulate around; empty: the model's qpos0",
    "robot.ctrl0": "operating-point control of every actuator; empty: zero (a qpos0 that gravity or a spring moves "
    "needs the control that holds it: jaxobs.mjx.robot.holding_ctrl)",
    "robot.solver_iterations": "constraint-solver iterations per physics step of a model with contacts, limits or "
    "equalities (a fixed loop that reverse mode differentiates); 0: MJX's solver to its tolerance (forward mode only)",
    "plants": "the mismatched plants, drawn per plant (training and held-out sets from independent keys)",
    "plants.train": "training plants (one rollout each per gradient evaluation)",
    "plants.heldout": "held-out plants, never used in training, that score the designs",
    "plants.mismatch": "'field[name]' = [low, high]: a factor on a model field, uniform (jaxobs.mjx.robot.mismatch)",
    "plants.mismatch.body_mass[payload]": "factor on the mass of the body 'payload' (the shipped example's)",
    "scenario": "the rollout every plant runs, and its loss",
    "scenario.duration": "rollout length (s)",
    "scenario.tracked": "sensors (one per actuator) whose values follow the reference",
    "scenario.reference": "set-point of the tracked sensors (deviation from the operating point), from t = 0",
    "scenario.output_weights": "loss weight of each measured entry's squared error to the desired closed loop's",
    "scenario.input_weight": "loss weight of the squared command",
    "scenario.state_limit": "a rollout whose (qpos, qvel) leaves the operating point by more counts as diverged",
    "design": "the observer-based controller on the linearised nominal model; the filter's Q and R are tuned",
    "design.observer": "'kalman' (the LQG) or 'aob' (an AOB-1: an active state per actuator, cancelled by the "
    "feedback)",
    "design.parameterisation": "'diagonal' (log variances of q, q_active and R) or 'cholesky' (full Q over every "
    "filter state, dead-time and active states included, and full R)",
    "design.q": "hand-set process noise variances of (qpos, qvel) (R starts at sensor_noise^2)",
    "design.q_input": "process noise variance of the commands in flight (dead-time states), one per actuator: an "
    "input disturbance; empty: 0 (exact commands; the cholesky parameterisation needs > 0 with a dead time)",
    "design.q_active": "hand-set variance of the active state's increment per control period, one per actuator (AOB)",
    "design.lqr_state": "LQR state weights: one per qpos and qvel entry (the commands in flight weighted 0), or one "
    "per state of the linearised model (qpos, qvel, then the dead-time commands, oldest first: the count "
    "jaxobs.design.dlqr takes)",
    "design.lqr_input": "LQR input weights, one per actuator",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    rb, sc, d = config["robot"], config["scenario"], config["design"]
    for key in ("robot.substeps", "plants.train", "plants.heldout"):
        check_at_least(config, source, key, 1)
    check_at_least(config, source, "robot.dead_time", 0)
    check_at_least(config, source, "robot.solver_iterations", 0)
    for key in ("scenario.duration", "scenario.state_limit"):
        check_at_least(config, source, key, 0, strict=True)
    check_at_least(config, source, "scenario.input_weight", 0)
    if not config["plants"]["mismatch"]:
        fail(source, "plants.mismatch", "name at least one model field to mismatch")
    for key, bounds in config["plants"]["mismatch"].items():
        if len(bounds) != 2 or not 0 < bounds[0] <= bounds[1]:
            fail(
                source,
                f"plants.mismatch.{key}",
                f"must be a range [low, high] of factors, 0 < low <= high, got {bounds}",
            )
    n_act = len(rb["actuators"])
    if len(sc["tracked"]) != n_act or len(sc["reference"]) != n_act:
        fail(source, "scenario.tracked", f"needs one tracked sensor and one reference per actuator ({n_act})")
    if not set(sc["tracked"]) <= set(rb["sensors"]):
        fail(source, "scenario.tracked", f"must name measured sensors ({', '.join(rb['sensors'])})")
    if len(d["lqr_input"]) != n_act:
        fail(source, "design.lqr_input", f"needs one weight per actuator ({n_act})")
    check_choice(config, source, "design.observer", OBSERVERS)
    check_choice(config, source, "design.parameterisation", PARAMETERISATIONS)
    for key, needed in (("q_input", False), ("q_active", d["observer"] == "aob")):
        if (d[key] or needed) and len(d[key]) != n_act:
            fail(source, f"design.{key}", f"needs one variance per actuator ({n_act})")
    for key, lowest in (("q_input", "must be >= 0"), ("q_active", "must be > 0")):
        if any(v < 0 or (v == 0 and key == "q_active") for v in d[key]):
            fail(source, f"design.{key}", f"variances {lowest}")
    if d["parameterisation"] == "cholesky" and rb["dead_time"] and not all(v > 0 for v in d["q_input"] or [0]):
        fail(source, "design.q_input", "the cholesky parameterisation needs a positive variance per actuator for "
             "the dead-time states (a full Q must be positive definite)")  # fmt: skip
    for key in ("design.q", "design.lqr_input", "robot.sensor_noise"):
        if any(v <= 0 for v in config[key.split(".")[0]][key.split(".")[1]]):
            fail(source, key, "must be positive")
    for key, weights in (("design.lqr_state", d["lqr_state"]), ("scenario.output_weights", sc["output_weights"])):
        if any(v < 0 for v in weights):
            fail(source, key, "weights must be >= 0")


def lqg_params(lin, Q, R, L, N):
    """The params of :data:`LQG`: the steady-state Kalman filter of the linear model ``lin`` (a
    :class:`jaxobs.lti.StateSpace`) with the noise covariances ``Q``, ``R``, and the state feedback ``L`` with the
    reference pre-gain ``N``."""
    est = kalman.make_kalman(lin.Phi, lin.C, Q, R, Gamma=lin.Gamma, steady_state=True)
    return feedback.FeedbackParams(est, L, N)


def _robot(config: dict):
    from jaxobs.mjx.robot import make_robot

    rb = config["robot"]
    timing = {"substeps": rb["substeps"], "dead_time": rb["dead_time"], "sensor_noise": rb["sensor_noise"]}
    point = {"qpos0": rb["qpos0"] or None, "ctrl0": rb["ctrl0"] or None}
    return make_robot(rb["mjcf"], rb["actuators"], rb["sensors"], **timing, **point,
                      solver_iterations=rb["solver_iterations"] or None)  # fmt: skip


def _check_differentiable(robot, config: dict, theta0: dict) -> None:
    """Refuse, before anything is compiled, a model whose constraint solver reverse mode cannot differentiate."""
    from jaxobs.mjx.common import constraint_rows, initial_data

    if robot.solver_iterations is None and gradient_mode(settings(config), theta0) == "reverse":
        rows = constraint_rows(initial_data(robot.model, robot.qpos0.dtype))
        if rows:
            raise ValueError(
                f"robot.solver_iterations: the model has {rows} constraint rows (contacts, joint limits, equalities), "
                "whose solver loop reverse mode cannot differentiate; set robot.solver_iterations >= 1 (e.g. 4) or "
                "optimizer.gradient = 'forward'"
            )


def build_problem(config: dict) -> TuningProblem:
    """The :class:`jaxobs.tuning.TuningProblem` of ``config`` (see the module docstring)."""
    from jaxobs import design
    from jaxobs.lti import ss
    from jaxobs.mjx.robot import linearize, mismatch, rollout

    robot = _robot(config)
    sc, d = config["scenario"], config["design"]
    n_x, p, m = robot.qpos0.shape[0] + robot.qvel0.shape[0], len(robot.sensors), len(robot.actuators)
    n = n_x + robot.dead_time * m
    for key, size, what in (("scenario.output_weights", p, "measured sensordata entry"),
                            ("design.q", n_x, "qpos and qvel entry")):  # fmt: skip
        section, name = key.split(".")
        if len(config[section][name]) != size:
            raise ValueError(f"{key}: needs one value per {what} ({size}), got {len(config[section][name])}")
    if len(d["lqr_state"]) not in (n_x, n):
        raise ValueError(f"design.lqr_state: needs one weight per qpos and qvel entry ({n_x}) or per state of the "
                         f"linearised model ({n}: qpos, qvel, then {robot.dead_time} x {m} commands in flight), got "
                         f"{len(d['lqr_state'])}")  # fmt: skip
    aob = d["observer"] == "aob"
    q_input = jnp.tile(jnp.asarray(d["q_input"] or [0.0] * m, float), robot.dead_time)
    hand_set = {"log_q": jnp.log(jnp.asarray(d["q"], float)),
                "log_r": jnp.log(jnp.asarray(config["robot"]["sensor_noise"], float) ** 2)}  # fmt: skip
    if aob:
        hand_set["log_q_active"] = jnp.log(jnp.asarray(d["q_active"], float))

    def covariances(theta):
        """``(Q, R)`` of the filter (every state: qpos, qvel, commands in flight, active states)."""
        if "q_cholesky" in theta:
            return cholesky_covariance(theta["q_cholesky"]), cholesky_covariance(theta["r_cholesky"])
        q = [jnp.exp(theta["log_q"]), q_input] + ([jnp.exp(theta["log_q_active"])] if aob else [])
        return jnp.diag(jnp.concatenate(q)), jnp.diag(jnp.exp(theta["log_r"]))

    theta0 = hand_set
    if d["parameterisation"] == "cholesky":
        Q0, R0 = covariances(hand_set)
        theta0 = {"q_cholesky": cholesky_parameters(Q0), "r_cholesky": cholesky_parameters(R0)}
    _check_differentiable(robot, config, theta0)
    for key in config["plants"]["mismatch"]:
        mismatch(robot.model, {key: 1.0})  # names checked before any compilation
    lin = linearize(robot)
    lqr_state = jnp.zeros(n).at[: len(d["lqr_state"])].set(jnp.asarray(d["lqr_state"], float))
    L, _, _ = design.dlqr(lin.Phi, lin.Gamma, jnp.diag(lqr_state), jnp.diag(jnp.asarray(d["lqr_input"], float)))
    rows = _tracked_rows(robot, config)
    N = design.reference_gain(ss(lin.Phi, lin.Gamma, lin.C[jnp.asarray(rows)], dt=lin.dt), L)
    steps = max(1, int(round(sc["duration"] / robot.period)))
    reference = jnp.broadcast_to(jnp.asarray(sc["reference"], float), (steps, len(rows)))
    desired = ideal_response(lin, L, reference @ N.T)  # (steps, p): the LQR with the true state, nominal model
    weights = jnp.asarray(sc["output_weights"], float)
    x_op = jnp.concatenate([robot.qpos0, robot.qvel0])
    estimator_controller = active.active_observer_controller if aob else LQG

    def controller(theta):
        Q, R = covariances(theta)
        if not aob:
            return lqg_params(lin, Q, R, L, N)
        observer = active.make_aob(lin, 1, R, Q=Q, steady_state=True)
        return feedback.FeedbackParams(observer, active.feedback_gain(observer, L), N)

    def run(theta, plants):
        params = controller(theta)

        def one(scales, key):
            return rollout(robot, estimator_controller, params, scales, key, steps, reference=reference)

        return jax.vmap(one)(plants["scales"], plants["key"])

    def losses(theta, plants):
        out = run(theta, plants)
        error = jnp.sum(weights * (out.y_true - desired) ** 2, axis=-1) + sc["input_weight"] * jnp.sum(out.u**2, -1)
        loss = jnp.mean(error, axis=-1)
        excursion = jnp.max(jnp.abs(out.x - x_op), axis=(-2, -1))
        return loss, ~jnp.isfinite(loss) | ~(excursion < sc["state_limit"])

    def sample(which):
        key = jax.random.fold_in(jax.random.PRNGKey(config["seed"]), {"train": 0, "heldout": 1}[which])
        count, ranges = config["plants"][which], config["plants"]["mismatch"]
        keys = jax.random.split(key, len(ranges) + 1)
        scales = {k: jax.random.uniform(kk, (count,), minval=lo, maxval=hi)
                  for kk, (k, (lo, hi)) in zip(keys[1:], ranges.items(), strict=True)}  # fmt: skip
        return {"scales": scales, "key": jax.random.split(keys[0], count)}

    traces = jax.jit(lambda theta, plants: run(theta, plants).y_true)
    setpoint = np.full(desired.shape[1], np.nan)
    setpoint[rows] = sc["reference"]

    def responses(theta, plants):
        return {
            "t": robot.period * np.arange(steps),
            "output": traces(theta, plants),
            "desired": np.asarray(desired),
            "labels": [
                ", ".join(f"{k} x{float(v[i]):.2f}" for k, v in plants["scales"].items())
                for i in range(len(plants["key"]))
            ],  # fmt: skip
            "ylabel": [f"{name} (deviation)" for name in _entry_names(robot, config)],
            "setpoint": setpoint,
        }

    def describe(theta):
        Q, R = (np.asarray(a) for a in covariances(theta))
        full = "q_cholesky" in theta
        return {
            ("Q" if full else "Q_diagonal"): (Q if full else np.diagonal(Q)).tolist(),
            ("R" if full else "R_diagonal"): (R if full else np.diagonal(R)).tolist(),
            "kalman_gain": np.asarray(controller(theta).estimator.gain).tolist(),
        }

    return TuningProblem(
        theta0=theta0,
        losses=losses,
        train=sample("train"),
        heldout=sample("heldout"),
        describe=describe,
        responses=responses,
        search_box=search_box(config, theta0, cholesky=("q_cholesky", "r_cholesky")),
    )


def _entry_names(robot, config: dict) -> list[str]:
    """A name per measured entry (row of ``y``): its sensor's, indexed where the sensor has several."""
    import mujoco
    from mujoco import mjx

    names = []
    for name in config["robot"]["sensors"]:
        dim = int(robot.model.sensor_dim[mjx.name2id(robot.model, mujoco.mjtObj.mjOBJ_SENSOR, name)])
        names += [name] if dim == 1 else [f"{name}[{i}]" for i in range(dim)]
    return names


def _tracked_rows(robot, config: dict) -> list[int]:
    """The measured entry (row of ``y``) of each tracked sensor (its first ``sensordata`` entry)."""
    import mujoco
    from mujoco import mjx

    adr = np.asarray(robot.model.sensor_adr)
    return [robot.sensors.index(int(adr[mjx.name2id(robot.model, mujoco.mjtObj.mjOBJ_SENSOR, name)]))
            for name in config["scenario"]["tracked"]]  # fmt: skip


PROBLEM = TuningScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=build_problem,
    open_tables=("plants.mismatch",),
    size_keys=("scenario.duration", "plants.train", "plants.heldout", "robot.substeps", "robot.solver_iterations"),
    path_keys=("robot.mjcf",),
)
