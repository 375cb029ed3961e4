"""Tuning the Kalman filter of an LQG controller against MJX rollouts of your own robot (any MJCF).

The robot (:func:`jaxobs.mjx.robot.make_robot`) is the config's MJCF (any model MJX can simulate: floating bases,
muscles, sensors of every stage) with its actuators, sensors, control period, dead time and sensor noise; the
controller (steady-state Kalman filter, LQR, reference pre-gain) is designed on the model linearised about the
operating point in the state's tangent space; with ``design.observer = "aob"`` the filter is an AOB-1 whose active
state (an equivalent input disturbance per actuator) the feedback cancels (Cortesão 2006 eq. 49-50). Tuned: the
filter's noise covariances, as log diagonals (``design.parameterisation = "diagonal"``) or as full Cholesky factors
of ``Q`` over every filter state and of ``R`` (``"cholesky"``); the loss is the error against the desired closed
loop (Cortesão 2006 eq. 43) on plants with mismatched fields. Shipped example:
``cartpole_payload.xml`` (a shipped robot) with ``tuning/cartpole_payload.toml``; a floating base and a muscle arm:
``tuning/free_flyer.toml``, ``tuning/muscle_arm.toml``. Details: docs/theory/papers.md.
"""

from __future__ import annotations

import functools

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
from jaxobs.tuning import (
    TuningProblem,
    cholesky_covariance,
    cholesky_labels,
    cholesky_parameters,
    gradient_mode,
    log_labels,
)

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
        "act0": [],
        "solver_iterations": 0,
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
    "one), or the name of a shipped robot (cartpole_payload.xml, arm_on_table.xml, free_flyer.xml, muscle_arm.xml)",
    "robot.actuators": "names of the actuators the controller drives",
    "robot.sensors": "names of the sensors it measures (any stage: an accelerometer or a force sensor reads the "
    "command acting when it is sampled; a framequat or ballquat reading counts 3 entries, its rotation)",
    "robot.substeps": "physics steps per control period",
    "robot.dead_time": "command dead time in control periods",
    "robot.sensor_noise": "standard deviation of the true sensors' noise, one per measured entry; empty: each "
    "sensor's noise attribute in the MJCF",
    "robot.qpos0": "operating point (qpos, quaternions of free and ball joints included) to linearise about and "
    "regulate around; empty: the model's qpos0",
    "robot.ctrl0": "operating-point control of every actuator; empty: zero (a qpos0 that gravity or a spring moves "
    "needs the control that holds it: jaxobs.mjx.robot.holding_ctrl)",
    "robot.act0": "operating-point actuator activations (muscles, filtered actuators); empty: those ctrl0 holds at "
    "rest (jaxobs.mjx.robot.steady_activation)",
    "robot.solver_iterations": "constraint solver of a model with contacts, limits or equalities: 0, MJX's solver at "
    "the MJCF's settings (its iterations and tolerance), differentiated implicitly; K >= 1, exactly K Newton "
    "iterations per physics step, differentiated through each (jaxobs.mjx.common.step)",
    "plants": "the mismatched plants, drawn per plant (training and held-out sets from independent keys)",
    "plants.train": "training plants (one rollout each per gradient evaluation)",
    "plants.heldout": "held-out plants, never used in training, that score the designs",
    "plants.mismatch": "'field[name]' = [low, high]: a factor on a model field, uniform (jaxobs.mjx.robot.mismatch)",
    "plants.mismatch.body_mass[payload]": "factor on the mass of the body 'payload' (the shipped example's)",
    "scenario": "the rollout every plant runs, and its loss",
    "scenario.duration": "rollout length (s)",
    "scenario.tracked": "sensors whose entries follow the reference: one entry per actuator in all (a 3-D sensor "
    "tracks three)",
    "scenario.reference": "set-point of each tracked entry (deviation from the operating point), from t = 0",
    "scenario.output_weights": "loss weight of each measured entry's squared error to the desired closed loop's",
    "scenario.input_weight": "loss weight of the squared command",
    "scenario.state_limit": "a rollout whose state leaves the operating point by more (any entry of its tangent "
    "deviation: positions, rotations, velocities, activations) counts as diverged",
    "design": "the observer-based controller on the linearised nominal model; the filter's Q and R are tuned",
    "design.observer": "'kalman' (the LQG) or 'aob' (an AOB-1: an active state per actuator, cancelled by the "
    "feedback)",
    "design.parameterisation": "'diagonal' (log variances of q, q_active and R) or 'cholesky' (full Q over every "
    "filter state, dead-time and active states included, and full R)",
    "design.q": "hand-set process noise variances of the state's tangent entries: nv positions (a free joint's "
    "3 positions and 3 rotations), nv velocities, na activations (R starts at sensor_noise^2)",
    "design.q_input": "process noise variance of the commands in flight (dead-time states, and the command an "
    "acceleration-stage sensor reads), one per actuator: an input disturbance; empty: 0 (exact commands; the "
    "cholesky parameterisation needs > 0 with such states)",
    "design.q_active": "hand-set variance of the active state's increment per control period, one per actuator (AOB)",
    "design.lqr_state": "LQR state weights: one per tangent entry of the state (as design.q; the commands in flight "
    "weighted 0), or one per state of the linearised model (then the commands in flight, oldest first: the count "
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
    if not 0 < len(sc["tracked"]) <= n_act or len(sc["reference"]) != n_act:
        fail(source, "scenario.tracked", f"needs tracked sensors with one entry and one reference per actuator "
             f"({n_act})")  # fmt: skip
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
        # (a measured acceleration-stage sensor adds a command state too: build_problem checks that with the model)
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
    timing = {"substeps": rb["substeps"], "dead_time": rb["dead_time"], "sensor_noise": rb["sensor_noise"] or None}
    point = {"qpos0": rb["qpos0"] or None, "ctrl0": rb["ctrl0"] or None, "act0": rb["act0"] or None}
    return make_robot(rb["mjcf"], rb["actuators"], rb["sensors"], **timing, **point,
                      solver_iterations=rb["solver_iterations"])  # fmt: skip


def _check_differentiable(robot, config: dict, theta0: dict) -> None:
    """Refuse, before anything is compiled, acceleration-stage sensors that reverse mode cannot differentiate: the
    measurement reads them after MJX's own constraint solve (the transition's solve is differentiated implicitly)."""
    from jaxobs.mjx.common import constraint_rows, initial_data

    if gradient_mode(settings(config), theta0) != "reverse":
        return
    rows = constraint_rows(initial_data(robot.model, robot.qpos0.dtype))
    if rows and robot.feedthrough:
        raise ValueError(
            f"robot.sensors: an acceleration-stage sensor on a model with {rows} constraint rows is read after MJX's "
            "constraint solve to its tolerance, a loop reverse mode cannot differentiate; set optimizer.gradient = "
            "'forward' (or measure position- and velocity-stage sensors)"
        )


def _check_sizes(robot, config: dict) -> int:
    """``ValueError`` naming the key whose length does not fit ``robot`` (``scenario.output_weights``, ``design.q``,
    ``design.lqr_state``, ``design.q_input``) or a measured entry without noise; returns the command slots of the
    linearised model (commands in flight, and the one a feedthrough sensor reads)."""
    d = config["design"]
    n_x, p, m = robot.state_manifold.dim, robot.sensor_manifold.dim, len(robot.actuators)
    slots = robot.dead_time + int(robot.feedthrough)
    n = n_x + slots * m
    what_x = "tangent entry of the state (nv positions, nv velocities, na activations)"
    if n_x == robot.qpos0.shape[0] + robot.qvel0.shape[0]:
        what_x = "qpos and qvel entry"
    for key, size, what in (("scenario.output_weights", p, "measured entry"), ("design.q", n_x, what_x)):
        section, name = key.split(".")
        if len(config[section][name]) != size:
            raise ValueError(f"{key}: needs one value per {what} ({size}), got {len(config[section][name])}")
    if len(d["lqr_state"]) not in (n_x, n):
        state = "qpos, qvel" if what_x == "qpos and qvel entry" else "the state"
        raise ValueError(f"design.lqr_state: needs one weight per {what_x} ({n_x}) or per state of the linearised "
                         f"model ({n}: {state}, then {slots} x {m} commands in flight), got "
                         f"{len(d['lqr_state'])}")  # fmt: skip
    if d["parameterisation"] == "cholesky" and slots and not all(v > 0 for v in d["q_input"] or [0]):
        raise ValueError("design.q_input: the cholesky parameterisation needs a positive variance per actuator for the "
                         "command states (a full Q must be positive definite)")  # fmt: skip
    if not np.all(np.asarray(robot.sensor_noise) > 0):
        raise ValueError("robot.sensor_noise: every measured entry needs a positive noise (the filter's R starts at "
                         f"its square); got {np.asarray(robot.sensor_noise).tolist()}")  # fmt: skip
    return slots


def _sample_plants(config: dict, which: str) -> dict:
    """The ``which`` ("train" or "heldout") plants: ``{"scales": {field: (count,)}, "key": (count,) keys}``, drawn
    uniformly in the mismatch ranges from a key of their own."""
    key = jax.random.fold_in(jax.random.PRNGKey(config["seed"]), {"train": 0, "heldout": 1}[which])
    count, ranges = config["plants"][which], config["plants"]["mismatch"]
    keys = jax.random.split(key, len(ranges) + 1)
    scales = {k: jax.random.uniform(kk, (count,), minval=lo, maxval=hi)
              for kk, (k, (lo, hi)) in zip(keys[1:], ranges.items(), strict=True)}  # fmt: skip
    return {"scales": scales, "key": jax.random.split(keys[0], count)}


def _responses(robot, config: dict, traces, desired, rows, theta, plants) -> dict:
    """The held-out responses of the design ``theta`` for ``jaxobs tune``'s figure: ``traces(theta, plants)`` (the
    measured deviations) against the ``desired`` closed loop, the tracked ``rows``' set-points, a label per plant."""
    setpoint = np.full(desired.shape[1], np.nan)
    setpoint[rows] = config["scenario"]["reference"]
    return {
        "t": robot.period * np.arange(desired.shape[0]),
        "output": traces(theta, plants),
        "desired": desired,
        "labels": [
            ", ".join(f"{k} x{float(v[i]):.2f}" for k, v in plants["scales"].items()) for i in range(len(plants["key"]))
        ],
        "ylabel": [
            f"{name} (deviation{f', {unit}' if unit else ''})"
            for name, unit in zip(_entry_names(robot, config), _entry_units(robot, config), strict=True)
        ],
        "setpoint": setpoint,
    }


def _describe(covariances, controller, theta) -> dict:
    """The design ``theta`` as ``tuned.json`` shows it: ``Q`` and ``R`` (their diagonals when diagonal) and the
    filter's gain."""
    Q, R = (np.asarray(a) for a in covariances(theta))
    full = "q_cholesky" in theta
    return {
        ("Q" if full else "Q_diagonal"): (Q if full else np.diagonal(Q)).tolist(),
        ("R" if full else "R_diagonal"): (R if full else np.diagonal(R)).tolist(),
        "kalman_gain": np.asarray(controller(theta).estimator.gain).tolist(),
    }


def build_problem(config: dict) -> TuningProblem:
    """The :class:`jaxobs.tuning.TuningProblem` of ``config`` (see the module docstring)."""
    from jaxobs import design
    from jaxobs.lti import ss
    from jaxobs.mjx.robot import mismatch, rollout

    robot = _robot(config)
    sc, d = config["scenario"], config["design"]
    slots, m = _check_sizes(robot, config), len(robot.actuators)
    n = robot.state_manifold.dim + slots * m
    aob = d["observer"] == "aob"
    q_input = jnp.tile(jnp.asarray(d["q_input"] or [0.0] * m, float), slots)
    hand_set = {"log_q": jnp.log(jnp.asarray(d["q"], float)), "log_r": jnp.log(robot.sensor_noise**2)}
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
    rows = _tracked_rows(robot, config)
    if len(rows) != m:
        raise ValueError(f"scenario.tracked: the tracked sensors have {len(rows)} entries; the reference gain needs "
                         f"one per actuator ({m})")  # fmt: skip
    _warn_outside_ranges(robot, config)
    for key in config["plants"]["mismatch"]:
        mismatch(robot.model, {key: 1.0})  # names checked before any compilation
    lin = _linearized(robot, config)
    lqr_state = jnp.zeros(n).at[: len(d["lqr_state"])].set(jnp.asarray(d["lqr_state"], float))
    L, _, _ = design.dlqr(lin.Phi, lin.Gamma, jnp.diag(lqr_state), jnp.diag(jnp.asarray(d["lqr_input"], float)))
    N = design.reference_gain(ss(lin.Phi, lin.Gamma, lin.C[jnp.asarray(rows)], dt=lin.dt), L)
    steps = max(1, int(round(sc["duration"] / robot.period)))
    reference = jnp.broadcast_to(jnp.asarray(sc["reference"], float), (steps, len(rows)))
    desired = ideal_response(lin, L, reference @ N.T)  # (steps, p): the LQR with the true state, nominal model
    weights = jnp.asarray(sc["output_weights"], float)
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
        excursion = jnp.max(jnp.abs(out.dx), axis=(-2, -1))
        return loss, ~jnp.isfinite(loss) | ~(excursion < sc["state_limit"])

    traces = jax.jit(lambda theta, plants: run(theta, plants).y_true)

    return TuningProblem(
        theta0=theta0,
        losses=losses,
        train=_sample_plants(config, "train"),
        heldout=_sample_plants(config, "heldout"),
        describe=functools.partial(_describe, covariances, controller),
        responses=functools.partial(_responses, robot, config, traces, np.asarray(desired), rows),
        search_box=search_box(config, theta0, cholesky=("q_cholesky", "r_cholesky")),
        labels=_labels(robot, config, slots, theta0),
        loss_unit=_loss_unit(robot, config),
    )


def _linearized(robot, config: dict):
    """:func:`jaxobs.mjx.robot.linearize` of ``robot``; a model it refuses (MJX differentiates it wrongly) is named by
    its MJCF file."""
    from jaxobs.mjx.robot import linearize

    try:
        return linearize(robot)
    except ValueError as exc:
        raise ValueError(f"robot.mjcf {config['robot']['mjcf']}: {exc}") from None


def _labels(robot, config: dict, slots: int, theta0: dict) -> dict:
    """What each entry of ``theta0`` is: the filter's states (the state's tangent entries, the commands in flight,
    the active states) and the measured entries."""
    from jaxobs.mjx.manifold import tangent_names

    actuators = config["robot"]["actuators"]
    states, entries = tangent_names(robot.model), _entry_names(robot, config)
    active = [f"{a} active" for a in actuators] if config["design"]["observer"] == "aob" else []
    if "q_cholesky" in theta0:
        flight = [f"{a} command {s + 1}" for s in range(slots) for a in actuators]  # oldest first
        return {"q_cholesky": cholesky_labels("Q", [*states, *flight, *active]),
                "r_cholesky": cholesky_labels("R", entries)}  # fmt: skip
    labels = {"log_q": log_labels("Q", states), "log_r": log_labels("R", entries)}
    return {**labels, "log_q_active": log_labels("Q", active)} if active else labels


def _entry_units(robot, config: dict) -> list[str]:
    from jaxobs.mjx.manifold import sensor_units

    return sensor_units(robot.model, config["robot"]["sensors"])


def _loss_unit(robot, config: dict) -> str:
    """The loss's unit: the squared unit of the weighted entries when they share one and the command is not
    weighted, else a description."""
    weights = config["scenario"]["output_weights"]
    units = {u for u, w in zip(_entry_units(robot, config), weights, strict=True) if w > 0}
    if len(units) == 1 and "" not in units and config["scenario"]["input_weight"] == 0:
        return f"{units.pop()}²"
    return "weighted, mixed units"


def _entry_names(robot, config: dict) -> list[str]:
    """A name per measured entry (row of ``y``): its sensor's, indexed where the sensor has several."""
    from jaxobs.mjx.manifold import tangent_rows

    names = []
    for name in config["robot"]["sensors"]:
        size = tangent_rows(robot.model, [name])[1][0]
        names += [name] if size == 1 else [f"{name}[{i}]" for i in range(size)]
    return names


def _warn_outside_ranges(robot, config: dict) -> None:
    """Warn when the operating point (``robot.qpos0``) or a tracked joint's set-point (its ``jointpos`` sensor's
    entry of ``qpos0`` plus ``scenario.reference``) lies outside the joint's range."""
    import mujoco

    from jaxobs.mjx.manifold import sensor_ids, tangent_rows
    from jaxobs.mjx.robot import warn_outside_joint_ranges

    model, qpos0 = robot.model, np.asarray(robot.qpos0, float)
    if warn_outside_joint_ranges(model, qpos0, "robot.qpos0"):
        return
    tracked = config["scenario"]["tracked"]
    target, entry = qpos0.copy(), 0
    for sensor, size in zip(sensor_ids(model, tracked), tangent_rows(model, tracked)[1], strict=True):
        if int(model.sensor_type[sensor]) == int(mujoco.mjtSensor.mjSENS_JOINTPOS):
            target[int(model.jnt_qposadr[int(model.sensor_objid[sensor])])] += config["scenario"]["reference"][entry]
        entry += size
    warn_outside_joint_ranges(model, target, "scenario.reference (from robot.qpos0)")


def _tracked_rows(robot, config: dict) -> list[int]:
    """The measured entries (rows of ``y``) of the tracked sensors, in order."""
    from jaxobs.mjx.manifold import tangent_rows

    sizes = tangent_rows(robot.model, config["robot"]["sensors"])[1]
    start = dict(zip(config["robot"]["sensors"], np.cumsum((0, *sizes[:-1])).tolist(), strict=True))
    return [start[name] + i for name in config["scenario"]["tracked"]
            for i in range(sizes[config["robot"]["sensors"].index(name)])]  # fmt: skip


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
