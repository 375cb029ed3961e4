"""Your own robot in MuJoCo MJX: a closed loop over any MJCF, its linearisation, and named model mismatch.

A :class:`Robot` (:func:`make_robot`) names what a controller sees of a model: the actuators it drives, the
sensors it measures, the control period, the dead time, the sensor noise and an operating point, in whose
deviations the controller works. :func:`linearize` gives the discrete ``(Phi, Gamma, C)`` by ``jax.jacfwd`` of
``mjx.step`` (warning when the operating point is not an equilibrium), :func:`holding_ctrl` the control that holds a
pose at rest, :func:`mismatch` scales named model fields (``body_mass[payload]``, ...), and :func:`rollout` runs any
controller in one ``lax.scan``. Forward- and reverse-mode gradients go through contacts and joint limits (MJX's
constraint solver, differentiated implicitly: :func:`jaxobs.mjx.common.solve`). The requirements and the
differentiation notes: docs/theory/mjx.md.
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxobs import _checks
from jaxobs._jit import jit
from jaxobs.lti import StateSpace, ss
from jaxobs.mjx import estimation
from jaxobs.mjx.common import check_solver_iterations, dead_time_step, put_model
from jaxobs.observers.base import Controller, ControllerInputs

__all__ = ["Robot", "RobotRollout", "load_mjcf", "make_robot", "holding_ctrl", "linearize", "mismatch", "rollout"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Robot:
    """What a controller sees of an MJX model (build it with :func:`make_robot`).

    Attributes:
      model: the nominal ``mjx.Model``.
      qpos0: (nq,) operating-point positions.  qvel0: (nv,) operating-point velocities.
      ctrl0: (nu,) operating-point control of every actuator.
      sensor_noise: (p,) standard deviation of the noise on each measured ``sensordata`` entry.
      actuators: static, the ``ctrl`` indices the controller drives (``m`` of them, in the given order).
      sensors: static, the ``sensordata`` indices it measures (``p`` of them).
      substeps: static, physics steps per control period (``h = substeps * model.opt.timestep``).
      dead_time: static, command dead time in control periods (``u_k`` acts during period ``k + d``).
      timestep: static, the model's physics time step in seconds (so the period is known under tracing).
      solver_iterations: static, the constraint solver of each physics step: None runs MJX's solver at the model's
        settings (its iterations and tolerance; derivatives by the implicit function theorem), an int ``K >= 1``
        exactly ``K`` Newton iterations, differentiated through each (:func:`jaxobs.mjx.common.step`).
    """

    model: mjx.Model
    qpos0: jax.Array
    qvel0: jax.Array
    ctrl0: jax.Array
    sensor_noise: jax.Array
    actuators: tuple = dataclasses.field(metadata=dict(static=True))
    sensors: tuple = dataclasses.field(metadata=dict(static=True))
    substeps: int = dataclasses.field(default=1, metadata=dict(static=True))
    dead_time: int = dataclasses.field(default=0, metadata=dict(static=True))
    timestep: float = dataclasses.field(default=0.002, metadata=dict(static=True))
    solver_iterations: int | None = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def period(self) -> float:
        """The control period ``h = substeps * timestep`` in seconds."""
        return self.timestep * self.substeps


def load_mjcf(mjcf) -> mujoco.MjModel:
    """An ``MjModel`` from ``mjcf``: a path to an MJCF file, the XML text, or an ``MjModel`` (returned as is);
    ``ValueError`` naming the file for an unreadable or invalid one."""
    if isinstance(mjcf, mujoco.MjModel):
        return mjcf
    text, source = str(mjcf), "<string>"
    if not text.lstrip().startswith("<"):
        source = text
        try:
            return mujoco.MjModel.from_xml_path(str(Path(text)))
        except ValueError as exc:  # mujoco reports missing files, XML and schema errors as ValueError
            raise ValueError(f"MJCF {source}: cannot load it ({exc})") from exc
    try:
        return mujoco.MjModel.from_xml_string(text)
    except ValueError as exc:
        raise ValueError(f"MJCF {source}: invalid model ({exc})") from exc


def _names(model, obj: mujoco.mjtObj, count: int) -> list[str]:
    return [mujoco.mj_id2name(model, obj, i) or f"#{i}" for i in range(count)]


def _index(model, what: str, obj: mujoco.mjtObj, count: int, name: str) -> int:
    """The id of the ``what`` named ``name``; ``ValueError`` listing the valid names."""
    i = mujoco.mj_name2id(model, obj, name)
    if i < 0:
        valid = ", ".join(repr(n) for n in _names(model, obj, count)) or "none"
        raise ValueError(f"unknown {what} {name!r}; the model's {what}s are: {valid}")
    return int(i)


def make_robot(
    mjcf,
    actuators,
    sensors,
    *,
    substeps: int = 1,
    dead_time: int = 0,
    sensor_noise=0.0,
    qpos0=None,
    qvel0=None,
    ctrl0=None,
    solver_iterations: int | None = None,
) -> Robot:
    """A :class:`Robot` of ``mjcf`` (see :func:`load_mjcf`).

    Args:
      mjcf: path, XML text or ``mujoco.MjModel``.
      actuators: names of the actuators the controller drives (its ``u`` has one entry per name, in order).
      sensors: names of the sensors it measures (its ``y`` holds their ``sensordata`` entries, in order).
      substeps: physics steps per control period (int >= 1).  dead_time: command dead time in control periods.
      sensor_noise: standard deviation of the measurement noise: a scalar or one per measured entry (p,).
      qpos0, qvel0, ctrl0: the operating point (defaults: the model's ``qpos0``, zero velocity, zero control).
      solver_iterations: the constraint solver per physics step (see :class:`Robot`): None or 0 for MJX's solver at
        the model's settings, an int ``K >= 1`` for exactly ``K`` iterations; both work with ``jax.grad``.

    Example:
      >>> from jaxobs.mjx import estimation, robot
      >>> mj_model, _ = estimation.load_cartpole()
      >>> arm = robot.make_robot(mj_model, ["push"], ["cart_position"], substeps=2, sensor_noise=0.005)
      >>> arm.actuators, arm.sensors, round(arm.period, 3)
      ((0,), (0,), 0.02)
    """
    m = load_mjcf(mjcf)
    estimation.check_model(m, sensors=False)
    if isinstance(actuators, str) or isinstance(sensors, str):
        raise ValueError("actuators and sensors must be lists of names, not one string")
    if not actuators:
        raise ValueError("actuators: name at least one actuator the controller drives")
    if not sensors:
        raise ValueError("sensors: name at least one sensor the controller measures")
    act = tuple(_index(m, "actuator", mujoco.mjtObj.mjOBJ_ACTUATOR, m.nu, a) for a in actuators)
    rows = []
    for s in sensors:
        i = _index(m, "sensor", mujoco.mjtObj.mjOBJ_SENSOR, m.nsensor, s)
        if m.sensor_needstage[i] == mujoco.mjtStage.mjSTAGE_ACC:
            raise ValueError(f"sensor {s!r} is of the acceleration stage (it depends on the command being chosen); "
                             "measure position- or velocity-stage sensors")  # fmt: skip
        rows += range(m.sensor_adr[i], m.sensor_adr[i] + m.sensor_dim[i])
    for name, given, ids in (("actuators", actuators, act), ("sensors", sensors, tuple(rows))):
        if len(set(ids)) != len(ids):
            raise ValueError(f"{name}: each may be named once, got {list(given)}")
    substeps = _checks.count("substeps", substeps, minimum=1, hint="physics steps per control period")
    dead_time = _checks.count("dead_time", dead_time, minimum=0, hint="control periods")
    solver_iterations = check_solver_iterations(solver_iterations)
    model = put_model(m)
    dtype = model.body_mass.dtype
    point = {"qpos0": (qpos0, m.qpos0, m.nq), "qvel0": (qvel0, np.zeros(m.nv), m.nv),
             "ctrl0": (ctrl0, np.zeros(m.nu), m.nu)}  # fmt: skip
    values = {k: _checks.vector(k, d if v is None else v, n, dtype, what=f"{n} entries")
              for k, (v, d, n) in point.items()}  # fmt: skip
    noise = _checks.per_entry("sensor_noise", sensor_noise, len(rows), dtype, "one per measured sensordata entry")
    if np.any(np.asarray(noise) < 0):
        raise ValueError(f"sensor_noise must be >= 0, got {np.asarray(noise)}")
    return Robot(model, values["qpos0"], values["qvel0"], values["ctrl0"], noise, act, tuple(rows), substeps, dead_time,
                 float(m.opt.timestep), solver_iterations)  # fmt: skip


def holding_ctrl(mjcf, qpos=None) -> np.ndarray:
    """The control of every actuator (nu,) that holds the pose ``qpos`` at rest: the ``ctrl0`` of an operating
    point that is not an equilibrium by itself (a pose against gravity, a spring or a contact).

    MuJoCo's inverse dynamics (``mj_inverse`` at zero velocity and acceleration) gives the generalised force
    ``f`` the pose needs; the actuators' force is affine in the control, ``J ctrl + b`` (nv,), and ``ctrl`` is
    the least-squares solution of ``J ctrl + b = f`` (the smallest one when several actuators share a joint).

    Args:
      mjcf: path, XML text or ``mujoco.MjModel`` (see :func:`load_mjcf`).
      qpos: (nq,) the pose (default: the model's ``qpos0``).

    Raises:
      ValueError: when the actuators cannot produce ``f`` (a loaded joint without an actuator, fewer actuators
        than loaded directions), naming the joints left unheld, or when ``ctrl`` lies outside an actuator's
        ``ctrlrange``.

    Example:
      >>> from jaxobs.mjx import estimation, robot
      >>> mj_model, _ = estimation.load_cartpole()
      >>> robot.holding_ctrl(mj_model, [0.0, 0.0]).round(6).tolist()  # the hanging pole rests without a push
      [0.0]
    """
    m = load_mjcf(mjcf)
    estimation.check_model(m, sensors=False)
    pose = np.asarray(m.qpos0 if qpos is None else qpos, float)
    if pose.shape != (m.nq,) or not np.all(np.isfinite(pose)):
        raise ValueError(f"qpos must be {m.nq} finite entries (one per qpos), got {pose.tolist()}")
    data = mujoco.MjData(m)
    data.qpos[:] = pose
    mujoco.mj_inverse(m, data)
    needed = data.qfrc_inverse.copy()
    free = copy.copy(m)  # the control unclamped, to read the affine map off unit controls
    free.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL
    forces = []
    for ctrl in np.vstack([np.zeros(m.nu), np.eye(m.nu)]):
        data.ctrl[:] = ctrl
        mujoco.mj_forward(free, data)
        forces.append(data.qfrc_actuator.copy())
    b, J = forces[0], np.array(forces[1:]).T.reshape(m.nv, m.nu) - forces[0][:, None]
    ctrl = np.linalg.lstsq(J, needed - b, rcond=None)[0]
    residual = np.abs(J @ ctrl + b - needed)
    unheld = np.flatnonzero(residual > 1e-6 * max(1.0, np.max(np.abs(needed))))
    joints = _names(m, mujoco.mjtObj.mjOBJ_JOINT, m.njnt)
    if unheld.size:
        shown = ", ".join(f"{joints[m.dof_jntid[i]]!r} ({residual[i]:.3g} unheld)" for i in unheld)
        raise ValueError(
            f"the actuators cannot hold this pose at rest: no control produces the force it needs on joint {shown}; "
            "choose a pose that is an equilibrium there, or actuate those joints"
        )
    low, high = m.actuator_ctrlrange.T
    outside = [i for i in range(m.nu) if m.actuator_ctrllimited[i] and not low[i] <= ctrl[i] <= high[i]]
    if outside:
        names = _names(m, mujoco.mjtObj.mjOBJ_ACTUATOR, m.nu)
        shown = ", ".join(f"{names[i]!r} needs {ctrl[i]:.4g}, range [{low[i]:g}, {high[i]:g}]" for i in outside)
        raise ValueError(f"the actuators cannot hold this pose at rest: outside ctrlrange: {shown}")
    return ctrl


# --------------------------------------------------------------------------------------------
# Transition and measurement in the controller's coordinates


def _step(robot: Robot, model: mjx.Model, x, applied, t):
    """The state after one control period from ``x = (qpos, qvel)`` with ``applied`` (m,) on the named actuators."""
    ctrl = robot.ctrl0.at[jnp.asarray(robot.actuators)].add(applied)
    return estimation.transition(model, substeps=robot.substeps, solver_iterations=robot.solver_iterations)(x, ctrl, t)


def _sense(robot: Robot, model: mjx.Model, x):
    """The measured ``sensordata`` entries (p,) of the state ``x``."""
    return estimation.measurement(model)(x)[jnp.asarray(robot.sensors)]


def _operating_state(robot: Robot, qpos0=None, qvel0=None):
    qpos = robot.qpos0 if qpos0 is None else jnp.asarray(qpos0, robot.qpos0.dtype)
    qvel = robot.qvel0 if qvel0 is None else jnp.asarray(qvel0, robot.qvel0.dtype)
    _checks.shape("qpos0", qpos, robot.qpos0.shape, "one entry per qpos")
    _checks.shape("qvel0", qvel, robot.qvel0.shape, "one entry per qvel")
    return jnp.concatenate([qpos, qvel])


@partial(jit, what="linearize")
def _jacobians(robot: Robot, x0):
    """``(Phi, Gamma, C, drift)`` of one control period at ``x0`` (compiled once per robot structure); ``drift``
    (nq + nv,) is the transition's constant term ``f(x0, 0) - x0``, zero at an equilibrium."""
    u0 = jnp.zeros(len(robot.actuators), x0.dtype)

    def both(x, u):
        x_next = _step(robot, robot.model, x, u, jnp.zeros((), x0.dtype))
        return (x_next, _sense(robot, robot.model, x)), x_next - x

    ((Phi, Gamma), (C, _)), drift = jax.jacfwd(both, argnums=(0, 1), has_aux=True)(x0, u0)  # x and u tangents
    return Phi, Gamma, C, drift


def _warn_unless_equilibrium(robot: Robot, drift) -> None:
    """Warn when a concrete ``drift`` (the state's change over one period with ``u = 0``) is not negligible."""
    if isinstance(drift, jax.core.Tracer):
        return
    drift = np.asarray(drift)
    tolerance = max(1e-6, 1000 * np.finfo(drift.dtype).eps)
    i = int(np.argmax(np.abs(drift)))
    if abs(drift[i]) <= tolerance:
        return
    nq = robot.qpos0.shape[0]
    joint = mjx.id2name(robot.model, mujoco.mjtObj.mjOBJ_JOINT, int(np.asarray(robot.model.dof_jntid)[i % nq]))
    warnings.warn(
        f"linearize: the operating point is not an equilibrium: with u = 0 one control period changes "
        f"{'qpos' if i < nq else 'qvel'}[{i % nq}] (joint {joint!r}) by {drift[i]:.3g}; the linear model drops this "
        "drift, so a design on it regulates towards a point the robot does not rest at. Hold the pose with "
        "ctrl0=holding_ctrl(mjcf, qpos0), or linearise about a rest pose.",
        RuntimeWarning,
        stacklevel=3,
    )


def linearize(robot: Robot, qpos0=None, qvel0=None, ctrl0=None) -> StateSpace:
    """The discrete linear model of ``robot`` over one control period about an operating point.

    The operating point defaults to the robot's; the model is ``jax.jacfwd`` of the transition (``substeps``
    ``mjx.step`` calls, command held)::

        dx_{k+1} = Phi dx_k + Gamma du_{k-d},   dy_k = C dx_k,   dx = (qpos, qvel) - (qpos0, qvel0)

    With a dead time ``d > 0`` the state is augmented with the commands in flight, ``[dx, u_{k-d}, ...,
    u_{k-1}]`` (oldest first, as :func:`jaxobs.lti.c2d`): ``n = nq + nv + d m``. The operating point should be
    an equilibrium: the transition's constant term is dropped, and a ``RuntimeWarning`` (eager calls) names the
    joint that drifts when one period moves the state by more than 1e-6 (:func:`holding_ctrl` gives the
    ``ctrl0`` that holds a pose). ``ctrl0`` (nu,) replaces the robot's operating control.

    Returns:
      :class:`jaxobs.lti.StateSpace`: ``Phi`` (n, n), ``Gamma`` (n, m) and ``C`` (p, n) (also its ``A``, ``B``),
      ``D = 0`` and ``dt`` the control period; the nominal model a linear controller is designed on. Pure and
      traceable (a mismatched model: ``dataclasses.replace(robot, model=mismatch(robot.model, scales))``); the
      Jacobians are compiled once per robot structure, so later eager calls are one dispatch.

    Example:
      >>> from jaxobs.mjx import estimation, robot
      >>> arm = robot.make_robot(estimation.load_cartpole()[0], ["push"], ["cart_position"], substeps=2, dead_time=1)
      >>> lin = robot.linearize(arm)
      >>> lin.Phi.shape, lin.Gamma.shape, lin.C.shape
      ((5, 5), (5, 1), (1, 5))
    """
    if ctrl0 is not None:
        ctrl0 = _checks.vector("ctrl0", ctrl0, robot.ctrl0.shape[0], robot.ctrl0.dtype, what="one entry per actuator")
        robot = dataclasses.replace(robot, ctrl0=ctrl0)
    x0 = _operating_state(robot, qpos0, qvel0)
    Phi, Gamma, C, drift = _jacobians(robot, x0)
    _warn_unless_equilibrium(robot, drift)
    d, (n, m) = robot.dead_time, Gamma.shape
    if d:
        slots = d * m
        Phi = jnp.block([[Phi, Gamma, jnp.zeros((n, slots - m), x0.dtype)],
                         [jnp.zeros((slots, n), x0.dtype), jnp.eye(slots, k=m, dtype=x0.dtype)]])  # fmt: skip
        Gamma = jnp.concatenate([jnp.zeros((n + slots - m, m), x0.dtype), jnp.eye(m, dtype=x0.dtype)])
        C = jnp.concatenate([C, jnp.zeros((C.shape[0], slots), x0.dtype)], axis=1)
    return ss(Phi, Gamma, C, dt=robot.period)


# --------------------------------------------------------------------------------------------
# Named mismatch

_OBJECTS = {  # field prefix -> (object type, count attribute)
    "body_": (mujoco.mjtObj.mjOBJ_BODY, "nbody"),
    "jnt_": (mujoco.mjtObj.mjOBJ_JOINT, "njnt"),
    "dof_": (mujoco.mjtObj.mjOBJ_JOINT, "njnt"),  # named by the joint (hinge and slide joints have one dof)
    "geom_": (mujoco.mjtObj.mjOBJ_GEOM, "ngeom"),
    "site_": (mujoco.mjtObj.mjOBJ_SITE, "nsite"),
    "actuator_": (mujoco.mjtObj.mjOBJ_ACTUATOR, "nu"),
    "tendon_": (mujoco.mjtObj.mjOBJ_TENDON, "ntendon"),
}


def _scalable_fields(model: mjx.Model) -> list[str]:
    """The model's floating-point array fields (leaves of the pytree) with a per-object first axis."""
    fields = []
    for f in dataclasses.fields(model):
        value = getattr(model, f.name)
        prefix = next((p for p in _OBJECTS if f.name.startswith(p)), None)
        if prefix and isinstance(value, jax.Array) and jnp.issubdtype(value.dtype, jnp.floating):
            fields.append(f.name)
    return fields


def _parse(model: mjx.Model, key: str) -> tuple[str, int | None]:
    """``"field[name]"`` -> (field, row) and ``"field"`` -> (field, None); ``ValueError`` listing valid names."""
    field, _, rest = key.partition("[")
    name = rest[:-1].strip().strip("'\"") if rest else None
    if rest and not rest.endswith("]"):
        raise ValueError(f"mismatch key {key!r}: expected 'field' or 'field[name]'")
    fields = _scalable_fields(model)
    if field not in fields:
        raise ValueError(f"mismatch key {key!r}: {field!r} is not a scalable model field; valid fields: "
                         f"{', '.join(fields)}")  # fmt: skip
    if name is None:
        return field, None
    prefix = next(p for p in _OBJECTS if field.startswith(p))
    obj, count = _OBJECTS[prefix]
    what = {"body_": "body", "jnt_": "joint", "dof_": "joint", "geom_": "geom", "site_": "site",
            "actuator_": "actuator", "tendon_": "tendon"}[prefix]  # fmt: skip
    i = mjx.name2id(model, obj, name)
    if i < 0:
        valid = [n for j in range(getattr(model, count)) if (n := mjx.id2name(model, obj, j))]
        plural = "bodies" if what == "body" else f"{what}s"
        raise ValueError(f"mismatch key {key!r}: unknown {what} {name!r}; the model's {plural} are: "
                         f"{', '.join(map(repr, valid)) or 'none'}")  # fmt: skip
    return field, int(np.asarray(model.jnt_dofadr)[i]) if prefix == "dof_" else int(i)


def mismatch(model: mjx.Model, scales: dict) -> mjx.Model:
    """``model`` with named fields multiplied by factors: ``scales = {"body_mass[payload]": 1.5,
    "dof_damping[hinge]": 0.8, "actuator_gear": 0.9}``. ``field[name]`` scales the row of the named object (a
    body, joint, geom, site, actuator or tendon by the field's prefix; ``dof_*`` fields are named by their hinge
    or slide joint; a row such as ``body_inertia`` or ``geom_friction`` scales as a whole); ``field`` alone
    scales every entry. Keys are static, factors may be traced: ``jax.vmap(lambda s: mismatch(model, s))`` over
    a dict of (B,) factors gives B plants.

    Derived constants that MuJoCo computes at load time (``body_subtreemass``, ``dof_invweight0``,
    ``actuator_acc0``, ...) keep their nominal values: they enter only the constraint solver's regularisation.
    A body's mass and inertia are separate fields (scale both for a uniformly denser body).
    """
    updates: dict[str, Any] = {}
    for key, factor in scales.items():
        field, row = _parse(model, key)
        value = updates.get(field, getattr(model, field))
        factor = jnp.asarray(factor, value.dtype)
        _checks.shape(f"scales[{key!r}]", factor, (), "one factor per key")
        updates[field] = value * factor if row is None else value.at[row].multiply(factor)
    return model.replace(**updates)


# --------------------------------------------------------------------------------------------
# Closed loop


class RobotRollout(NamedTuple):
    """Per control step ``k`` of :func:`rollout` (time ``k h``; leading axis: time ``T = steps``).

    The state is absolute, the measurements and commands are the controller's: deviations from the operating
    point (``y`` from ``s(x0)``, ``u`` from ``ctrl0``).

    Attributes:
      x: (T, nq + nv) the plant state ``(qpos, qvel)`` at ``k h``, absolute (``x - (qpos0, qvel0)`` is the
        deviation the linearisation's state holds).
      y: (T, p) the measurement the controller read, ``s(x(k h)) - s(x0) + v_k``: a deviation, noise included.
      y_true: (T, p) the same deviation without the noise.
      u: (T, m) the controller's command ``u_k``, added to ``ctrl0`` on the named actuators.
      applied: (T, m) the command acting during period ``k``, ``u_{k-d}`` (zeros for the first ``d`` periods).
      controller: the controller's outputs per step (its ``out`` pytree, each leaf with the leading axis T).
    """

    x: jax.Array
    y: jax.Array
    y_true: jax.Array
    u: jax.Array
    applied: jax.Array
    controller: Any


def rollout(
    robot: Robot,
    controller: Controller,
    params,
    scales: dict | None,
    key,
    steps: int,
    *,
    dx0=None,
    reference=None,
) -> RobotRollout:
    """``robot`` under ``controller`` for ``steps`` control periods, in one ``lax.scan``.

    The robot carries the mismatch ``scales`` (:func:`mismatch`). At control step ``k`` (time ``k h``)::

        y_k      = s(x(k h)) - s(x0) + v_k,  v_k ~ N(0, diag(sensor_noise^2))     measured sensordata entries
        state, o = controller.step(params, state, ControllerInputs(y_k, r_k))
        FIFO    <- o.u (m,); pop u_{k-d}                                         dead time d periods
        plant   <- substeps mjx.step calls with ctrl = ctrl0 + u_{k-d} on the named actuators (held)

    Args:
      robot: the :class:`Robot`.  controller: any :class:`~jaxobs.observers.base.Controller` whose ``u`` has one
        entry per named actuator.  params: its params.
      scales: mismatch factors by field key (:func:`mismatch`), or None for the nominal model.
      key: PRNG key of the sensor noise.  steps: control periods (static int >= 1).
      dx0: (nq + nv,) initial deviation of ``(qpos, qvel)`` from the operating point (default zero).
      reference: ``r_k``, shape (steps, q) (default zeros of shape (steps, m)).

    Returns:
      :class:`RobotRollout`. Pure: ``jit``, ``vmap`` (over scales, keys, params), ``jax.jvp`` / ``jacfwd`` and
      ``grad``, contacts and joint limits included (docs/theory/mjx.md).
    """
    steps = _checks.count("steps", steps, minimum=1, hint="control periods")
    model = robot.model if not scales else mismatch(robot.model, scales)
    x_op = _operating_state(robot)
    dtype = x_op.dtype
    n, m, p = x_op.shape[0], len(robot.actuators), len(robot.sensors)
    x0 = x_op if dx0 is None else x_op + _checks.vector("dx0", dx0, n, dtype, what="one entry per qpos and qvel")
    if reference is None:
        reference = jnp.zeros((steps, m), dtype)
    reference = jnp.asarray(reference, dtype)
    if reference.ndim != 2 or reference.shape[0] != steps:
        raise ValueError(f"reference must have shape (steps, q) = ({steps}, q), got {reference.shape}")
    noise = robot.sensor_noise * jax.random.normal(key, (steps, p), dtype)
    y_op = _sense(robot, robot.model, x_op)
    h = robot.period

    def control_step(carry, inputs):
        k, r_k, v_k = inputs
        x, fifo, state = carry
        y_true = _sense(robot, model, x) - y_op
        y = y_true + v_k
        state, out = controller.step(params, state, ControllerInputs(y, r_k))
        _checks.shape("params", out.u, (m,), f"the controller's command u needs one entry per named actuator ({m})")
        u = out.u.astype(dtype)
        applied, fifo = dead_time_step(fifo, u, robot.dead_time)
        x_next = _step(robot, model, x, applied, k * h)
        return (x_next, fifo, state), RobotRollout(x, y, y_true, u, applied, out)

    carry = (x0, jnp.zeros((robot.dead_time, m), dtype), controller.init(params))
    _, out = jax.lax.scan(control_step, carry, (jnp.arange(steps, dtype=dtype), reference, noise))
    return out
