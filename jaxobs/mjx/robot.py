"""Your own robot in MuJoCo MJX: a closed loop over any MJCF, its linearisation, and named model mismatch.

A :class:`Robot` (:func:`make_robot`) names what a controller sees of a model: the actuators it drives, the
sensors it measures, the control period, the dead time, the sensor noise and an operating point, in whose
deviations the controller works. The state is ``(qpos, qvel, act)``, its deviations live in the tangent space
(``2 nv + na``: free and ball joints, actuator activations), a quaternion sensor's deviation is a rotation vector,
and acceleration-stage sensors (accelerometer, force, touch) read the command acting when they are sampled.
:func:`linearize` gives the discrete ``(Phi, Gamma, C)`` by ``jax.jacfwd`` of ``mjx.step`` (warning when the
operating point is not an equilibrium), :func:`holding_ctrl` the control that holds a pose at rest,
:func:`mismatch` scales named model fields (``body_mass[payload]``, ``opt.gravity``, ...), and :func:`rollout`
runs any controller in one ``lax.scan``. Forward- and reverse-mode gradients go through contacts and joint limits
(MJX's constraint solver, differentiated implicitly: :func:`jaxobs.mjx.common.solve`). The requirements and the
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
from jaxobs.mjx import estimation, manifold
from jaxobs.mjx.common import check_solver_iterations, dead_time_step
from jaxobs.observers.base import Controller, ControllerInputs

__all__ = [
    "Robot",
    "RobotRollout",
    "load_mjcf",
    "make_robot",
    "steady_activation",
    "holding_ctrl",
    "warn_outside_joint_ranges",
    "linearize",
    "mismatch",
    "rollout",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Robot:
    """What a controller sees of an MJX model (build it with :func:`make_robot`).

    Attributes:
      model: the nominal ``mjx.Model``.
      qpos0: (nq,) operating-point positions.  qvel0: (nv,) operating-point velocities.
      act0: (na,) operating-point actuator activations.
      ctrl0: (nu,) operating-point control of every actuator.
      sensor_noise: (p,) standard deviation of the noise on each measured entry (a quaternion sensor has 3, a
        rotation vector in radians).
      actuators: static, the ``ctrl`` indices the controller drives (``m`` of them, in the given order).
      sensors: static, the ``sensordata`` indices it measures.
      sensor_names: static, the names of the measured sensors, in order.
      feedthrough: static, a measured sensor is of the acceleration stage: it reads the command applied when it
        is sampled (the linearisation's measurement then depends on that command).
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
    act0: jax.Array
    ctrl0: jax.Array
    sensor_noise: jax.Array
    actuators: tuple = dataclasses.field(metadata=dict(static=True))
    sensors: tuple = dataclasses.field(metadata=dict(static=True))
    sensor_names: tuple = dataclasses.field(default=(), metadata=dict(static=True))
    feedthrough: bool = dataclasses.field(default=False, metadata=dict(static=True))
    substeps: int = dataclasses.field(default=1, metadata=dict(static=True))
    dead_time: int = dataclasses.field(default=0, metadata=dict(static=True))
    timestep: float = dataclasses.field(default=0.002, metadata=dict(static=True))
    solver_iterations: int | None = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def period(self) -> float:
        """The control period ``h = substeps * timestep`` in seconds."""
        return self.timestep * self.substeps

    @property
    def x0(self) -> jax.Array:
        """The operating-point state ``(qpos0, qvel0, act0)``."""
        return jnp.concatenate([self.qpos0, self.qvel0, self.act0])

    @property
    def state_manifold(self):
        """The :class:`~jaxobs.nonlinear.Manifold` of the state (:func:`jaxobs.mjx.manifold.state_manifold`)."""
        return manifold.state_manifold(self.model)

    @property
    def sensor_manifold(self):
        """The :class:`~jaxobs.nonlinear.Manifold` of the measured readings."""
        return manifold.sensor_manifold(self.model, self.sensor_names)


def load_mjcf(mjcf) -> mujoco.MjModel:
    """An ``MjModel`` from ``mjcf``: a path to an MJCF file (a relative one from the current directory, failing that
    the MJCF of that name shipped with jaxobs, ``jaxobs/mjx/assets``: ``free_flyer.xml``, ``muscle_arm.xml``,
    ``cartpole_payload.xml``, ...; the rule of the configs' paths), the XML text, or an ``MjModel`` (returned as
    is); ``ValueError`` naming the file for an unreadable or invalid one."""
    if isinstance(mjcf, mujoco.MjModel):
        return mjcf
    text, source = str(mjcf), "<string>"
    if not text.lstrip().startswith("<"):
        source, path = text, Path(text)
        if not path.is_absolute() and not path.is_file() and (estimation.ASSETS / path).is_file():
            path = estimation.ASSETS / path
        try:
            return mujoco.MjModel.from_xml_path(str(path))
        except ValueError as exc:  # mujoco reports missing files, XML and schema errors as ValueError
            raise ValueError(f"MJCF {source}: cannot load it, nor a shipped robot of that name ({exc})") from exc
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
    sensor_noise=None,
    qpos0=None,
    qvel0=None,
    act0=None,
    ctrl0=None,
    solver_iterations: int | None = None,
) -> Robot:
    """A :class:`Robot` of ``mjcf`` (see :func:`load_mjcf`): any model MJX can simulate (free and ball joints,
    actuator activations, sensors of every stage); what MJX cannot do is a ``ValueError`` that names it.

    Args:
      mjcf: path, XML text or ``mujoco.MjModel``.
      actuators: names of the actuators the controller drives (its ``u`` has one entry per name, in order).
      sensors: names of the sensors it measures (its ``y`` holds their entries, in order: a 3-D sensor gives
        three, a quaternion sensor (``framequat``, ``ballquat``) three, its rotation away from the operating point).
      substeps: physics steps per control period (int >= 1).  dead_time: command dead time in control periods.
      sensor_noise: standard deviation of the measurement noise: a scalar or one per measured entry (p,); None:
        each sensor's ``noise`` attribute in the MJCF (0 where unset).
      qpos0, qvel0, act0, ctrl0: the operating point (defaults: the model's ``qpos0``, zero velocity, zero
        control, and the activations that ``ctrl0`` holds at rest: the control itself for filter and muscle
        dynamics, 0 for an integrator).
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
    if isinstance(actuators, str) or isinstance(sensors, str):
        raise ValueError("actuators and sensors must be lists of names, not one string")
    if not actuators:
        raise ValueError("actuators: name at least one actuator the controller drives")
    if not sensors:
        raise ValueError("sensors: name at least one sensor the controller measures")
    act = tuple(_index(m, "actuator", mujoco.mjtObj.mjOBJ_ACTUATOR, m.nu, a) for a in actuators)
    ids = manifold.sensor_ids(m, sensors)
    rows, tangent = manifold.tangent_rows(m, sensors)
    for name, given, chosen in (("actuators", actuators, act), ("sensors", sensors, tuple(ids))):
        if len(set(chosen)) != len(chosen):
            raise ValueError(f"{name}: each may be named once, got {list(given)}")
    substeps = _checks.count("substeps", substeps, minimum=1, hint="physics steps per control period")
    dead_time = _checks.count("dead_time", dead_time, minimum=0, hint="control periods")
    solver_iterations = check_solver_iterations(solver_iterations)
    model = estimation.put(m)
    dtype = model.body_mass.dtype
    ctrl0 = _checks.vector("ctrl0", np.zeros(m.nu) if ctrl0 is None else ctrl0, m.nu, dtype, what=f"{m.nu} entries")
    point = {"qpos0": (qpos0, m.qpos0, m.nq), "qvel0": (qvel0, np.zeros(m.nv), m.nv),
             "act0": (act0, lambda: steady_activation(m, ctrl0), m.na)}  # fmt: skip
    values = {k: _checks.vector(k, (d() if callable(d) else d) if v is None else v, n, dtype, what=f"{n} entries")
              for k, (v, d, n) in point.items()}  # fmt: skip
    if sensor_noise is None:
        sensor_noise = estimation.sensor_noise(m, sensors)
    noise = _checks.per_entry("sensor_noise", sensor_noise, sum(tangent), dtype, "one per measured entry")
    if np.any(np.asarray(noise) < 0):
        raise ValueError(f"sensor_noise must be >= 0, got {np.asarray(noise)}")
    feedthrough = bool(np.any(m.sensor_needstage[ids] == mujoco.mjtStage.mjSTAGE_ACC))
    return Robot(model, values["qpos0"], values["qvel0"], values["act0"], ctrl0, noise, act, rows,
                 tuple(sensors), feedthrough, substeps, dead_time, float(m.opt.timestep),
                 solver_iterations)  # fmt: skip


_REST_DYNAMICS = tuple(int(d) for d in (mujoco.mjtDyn.mjDYN_FILTER, mujoco.mjtDyn.mjDYN_FILTEREXACT,
                                          mujoco.mjtDyn.mjDYN_MUSCLE))  # fmt: skip


def steady_activation(mjcf, ctrl) -> np.ndarray:
    """The activations (na,) at which a constant control ``ctrl`` (nu,) leaves them at rest: the control itself
    (clamped to ``ctrlrange``, to [0, 1] for a muscle, and to ``actrange``) for filter and muscle dynamics; 0 for
    an integrator or user dynamics, whose activation rests at any value under zero control."""
    m = load_mjcf(mjcf)
    ctrl = np.asarray(ctrl, float)
    if ctrl.shape != (m.nu,):
        raise ValueError(f"ctrl must have one entry per actuator ({m.nu}), got shape {ctrl.shape}")
    act = np.zeros(m.na)
    for i in np.flatnonzero(np.asarray(m.actuator_actadr) >= 0):
        value = ctrl[i]
        if m.actuator_ctrllimited[i]:
            value = np.clip(value, *m.actuator_ctrlrange[i])
        if m.actuator_dyntype[i] == mujoco.mjtDyn.mjDYN_MUSCLE:
            value = np.clip(value, 0.0, 1.0)
        if m.actuator_actlimited[i]:
            value = np.clip(value, *m.actuator_actrange[i])
        adr, num = m.actuator_actadr[i], m.actuator_actnum[i]
        act[adr : adr + num] = value if int(m.actuator_dyntype[i]) in _REST_DYNAMICS else 0.0
    return act


def holding_ctrl(mjcf, qpos=None, *, near=None) -> np.ndarray:
    """The control of every actuator (nu,) that holds the pose ``qpos`` at rest: the ``ctrl0`` of an operating
    point that is not an equilibrium by itself (a pose against gravity, a spring or a contact).

    MuJoCo's inverse dynamics (``mj_inverse`` at zero velocity and acceleration) gives the generalised force
    ``f`` the pose needs; the actuators' force is affine in the control, ``J ctrl + b`` (nv,), with each
    activation at rest (:func:`steady_activation`; a muscle's force is affine in its activation), and ``ctrl`` is
    the least-squares solution of ``J ctrl + b = f`` (the one nearest to ``near`` when several actuators share a
    joint).

    Args:
      mjcf: path, XML text or ``mujoco.MjModel`` (see :func:`load_mjcf`).
      qpos: (nq,) the pose (default: the model's ``qpos0``).
      near: (nu,) the control the solution is nearest to among those that hold the pose (default zeros): the
        co-contraction of antagonistic muscles, which pull only (``ctrlrange`` [0, 1]).

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
        data.ctrl[:], data.act[:] = ctrl, steady_activation(free, ctrl)  # an activation at rest follows ctrl
        mujoco.mj_forward(free, data)
        forces.append(data.qfrc_actuator.copy())
    b, J = forces[0], np.array(forces[1:]).T.reshape(m.nv, m.nu) - forces[0][:, None]
    base = np.zeros(m.nu) if near is None else np.asarray(near, float)
    if base.shape != (m.nu,) or not np.all(np.isfinite(base)):
        raise ValueError(f"near must be {m.nu} finite entries (one per actuator), got {np.ravel(base).tolist()}")
    ctrl = base + np.linalg.lstsq(J, needed - b - J @ base, rcond=None)[0]
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


def warn_outside_joint_ranges(model, qpos, what: str) -> list[str]:
    """Warn (``UserWarning``, one line each) for every limited hinge or slide joint whose entry of the concrete
    ``qpos`` (nq,) lies outside its range, naming ``what`` (e.g. "robot.qpos0"), the joint, its type and its range
    in the model's units (radians for a hinge: an MJCF's ranges are read in degrees unless its ``<compiler
    angle="radian">`` says otherwise). ``model``: an ``mjx.Model`` or ``mujoco.MjModel``; returns the messages."""
    qpos = np.asarray(qpos, float)
    messages = []
    for j in range(model.njnt):
        kind = int(model.jnt_type[j])
        if not model.jnt_limited[j] or kind not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            continue
        low, high = (float(v) for v in np.asarray(model.jnt_range[j]))
        value = float(qpos[int(model.jnt_qposadr[j])])
        if low <= value <= high:
            continue
        hinge = kind == int(mujoco.mjtJoint.mjJNT_HINGE)
        unit = "rad" if hinge else "m"
        name = mjx.id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) if isinstance(model, mjx.Model) else model.joint(j).name
        hint = ' (MJCF ranges are in degrees unless <compiler angle="radian">)' if hinge else ""
        messages.append(f"{what}: {'hinge' if hinge else 'slide'} joint {name or f'#{j}'!r} at {value:.4g} {unit} "
                        f"lies outside its range [{low:.4g}, {high:.4g}] {unit}{hint}; the joint will sit at its "
                        "limit")  # fmt: skip
    for message in messages:
        warnings.warn(message, UserWarning, stacklevel=2)
    return messages


def _step(robot: Robot, model: mjx.Model, x, applied, t):
    """The state after one control period from ``x = (qpos, qvel, act)`` with ``applied`` (m,) on the named
    actuators."""
    ctrl = robot.ctrl0.at[jnp.asarray(robot.actuators)].add(applied)
    return estimation.transition(model, substeps=robot.substeps, solver_iterations=robot.solver_iterations)(x, ctrl, t)


def _sense(robot: Robot, model: mjx.Model, x, applied):
    """The measured readings of the state ``x`` with ``applied`` (m,) the command acting when they are sampled."""
    ctrl = robot.ctrl0.at[jnp.asarray(robot.actuators)].add(applied)
    return estimation.measurement(model, robot.sensor_names)(x, ctrl)


def _operating_state(robot: Robot, qpos0=None, qvel0=None, act0=None):
    given = {"qpos0": qpos0, "qvel0": qvel0, "act0": act0}
    parts = []
    for name, what in (("qpos0", "qpos"), ("qvel0", "qvel"), ("act0", "act")):
        nominal = getattr(robot, name)
        value = nominal if given[name] is None else jnp.asarray(given[name], nominal.dtype)
        _checks.shape(name, value, nominal.shape, f"one entry per {what}")
        parts.append(value)
    return jnp.concatenate(parts)


@partial(jit, what="linearize")
def _jacobians(robot: Robot, x0):
    """``(Phi, Gamma, C, D, drift)`` of one control period at ``x0`` in the tangent coordinates of the state and of
    the readings (compiled once per robot structure): ``D`` maps the command acting at the sample to the readings,
    ``drift`` (d,) is the transition's constant term ``f(x0, 0) - x0``, zero at an equilibrium."""
    space, readings = robot.state_manifold, robot.sensor_manifold
    u0 = jnp.zeros(len(robot.actuators), x0.dtype)
    y0 = _sense(robot, robot.model, x0, u0)

    def both(dx, u):
        x = space.retract(x0, dx)
        x_next = space.difference(_step(robot, robot.model, x, u, jnp.zeros((), x0.dtype)), x0)
        return (x_next, readings.difference(_sense(robot, robot.model, x, u), y0)), x_next

    zero = jnp.zeros((space.dim,), x0.dtype)
    ((Phi, Gamma), (C, D)), drift = jax.jacfwd(both, argnums=(0, 1), has_aux=True)(zero, u0)
    return Phi, Gamma, C, D, drift


def _warn_unless_equilibrium(robot: Robot, drift) -> None:
    """Warn when a concrete ``drift`` (the state's change over one period with ``u = 0``) is not negligible."""
    if isinstance(drift, jax.core.Tracer):
        return
    drift = np.asarray(drift)
    tolerance = max(1e-6, 1000 * np.finfo(drift.dtype).eps)
    i = int(np.argmax(np.abs(drift)))
    if abs(drift[i]) <= tolerance:
        return
    warnings.warn(
        f"linearize: the operating point is not an equilibrium: with u = 0 one control period changes "
        f"{_tangent_entry(robot.model, i)} by {drift[i]:.3g}; the linear model drops this drift, so a design on it "
        "regulates towards a point the robot does not rest at. Hold the pose with ctrl0=holding_ctrl(mjcf, qpos0), "
        "or linearise about a rest pose.",
        RuntimeWarning,
        stacklevel=3,
    )


def _tangent_entry(model: mjx.Model, i: int) -> str:
    """The name of entry ``i`` of the state's tangent space: ``qpos[i] (joint 'name')`` (a position degree of
    freedom, indexed like ``qvel``), ``qvel[i] (joint ...)`` or ``act[j] (actuator ...)``."""
    nv = model.nv
    if i < 2 * nv:
        joint = mjx.id2name(model, mujoco.mjtObj.mjOBJ_JOINT, int(np.asarray(model.dof_jntid)[i % nv]))
        return f"{'qpos' if i < nv else 'qvel'}[{i % nv}] (joint {joint!r})"
    j = i - 2 * nv
    owner = int(np.flatnonzero(np.asarray(model.actuator_actadr) <= j).max(initial=0))
    return f"act[{j}] (actuator {mjx.id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, owner)!r})"


def _augment(Phi, Gamma, C, D, dead_time: int, feedthrough: bool):
    """The linear model with the commands in flight as states: slots ``[a_{k-1}, u_{k-d}, ..., u_{k-1}]`` (oldest
    first; ``a_{k-1} = u_{k-1-d}``, the command applied over the last period, only with ``feedthrough``: the
    readings ``C dx_k + D a_{k-1}`` need it). The command applied over period ``k`` is ``u_{k-d}``: the slot after
    ``a_{k-1}``, or the input itself without a dead time."""
    slots = dead_time + int(feedthrough)
    if not slots:
        return Phi, Gamma, C
    (n, m), dtype = Gamma.shape, Gamma.dtype
    acting = jnp.zeros((n, slots * m), dtype)
    if dead_time:
        acting = acting.at[:, int(feedthrough) * m : (int(feedthrough) + 1) * m].set(Gamma)
    Phi = jnp.block([[Phi, acting], [jnp.zeros((slots * m, n), dtype), jnp.eye(slots * m, k=m, dtype=dtype)]])
    direct = Gamma if not dead_time else jnp.zeros((n, m), dtype)
    Gamma = jnp.concatenate([direct, jnp.zeros(((slots - 1) * m, m), dtype), jnp.eye(m, dtype=dtype)])
    read = [C, D] if feedthrough else [C]
    C = jnp.concatenate([*read, jnp.zeros((C.shape[0], (slots - len(read) + 1) * m), dtype)], axis=1)
    return Phi, Gamma, C


def linearize(robot: Robot, qpos0=None, qvel0=None, ctrl0=None, act0=None) -> StateSpace:
    """The discrete linear model of ``robot`` over one control period about an operating point.

    The operating point defaults to the robot's; the model is ``jax.jacfwd`` of the transition (``substeps``
    ``mjx.step`` calls, command held) in the tangent space of the state (``d = 2 nv + na``: a free or ball joint's
    rotation as a 3-vector, :func:`jaxobs.mjx.manifold.state_manifold`) and of the readings::

        dx_{k+1} = Phi dx_k + Gamma du_{k-d},   dy_k = C dx_k (+ D a_{k-1}),   dx = x - x0 on the manifold

    With a dead time ``d > 0`` the state is augmented with the commands in flight, ``[dx, u_{k-d}, ...,
    u_{k-1}]`` (oldest first, as :func:`jaxobs.lti.c2d`); an acceleration-stage sensor reads the command applied
    over the last period, ``a_{k-1} = u_{k-1-d}``, kept as one more slot before them (``robot.feedthrough``):
    ``n = d_x + (d + 1) m``. The operating point should be an equilibrium: the transition's constant term is
    dropped, and a ``RuntimeWarning`` (eager calls) names the joint or activation that drifts when one period moves
    the state by more than 1e-6 (:func:`holding_ctrl` gives the ``ctrl0`` that holds a pose). ``ctrl0`` (nu,) and
    ``act0`` (na,) replace the robot's operating control and activations.

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
    estimation.check_rotations(robot.model, "linearize")
    x0 = _operating_state(robot, qpos0, qvel0, act0)
    Phi, Gamma, C, D, drift = _jacobians(robot, x0)
    _warn_unless_equilibrium(robot, drift)
    return ss(*_augment(Phi, Gamma, C, D, robot.dead_time, robot.feedthrough), dt=robot.period)


# --------------------------------------------------------------------------------------------
# Named mismatch

_OBJECTS = {  # field prefix -> (object type, count attribute, what it is called)
    "body_": (mujoco.mjtObj.mjOBJ_BODY, "nbody", "body"),
    "jnt_": (mujoco.mjtObj.mjOBJ_JOINT, "njnt", "joint"),
    "dof_": (mujoco.mjtObj.mjOBJ_JOINT, "njnt", "joint"),  # named by the joint: its rows are the joint's dofs
    "geom_": (mujoco.mjtObj.mjOBJ_GEOM, "ngeom", "geom"),
    "site_": (mujoco.mjtObj.mjOBJ_SITE, "nsite", "site"),
    "cam_": (mujoco.mjtObj.mjOBJ_CAMERA, "ncam", "camera"),
    "light_": (mujoco.mjtObj.mjOBJ_LIGHT, "nlight", "light"),
    "mat_": (mujoco.mjtObj.mjOBJ_MATERIAL, "nmat", "material"),
    "pair_": (mujoco.mjtObj.mjOBJ_PAIR, "npair", "pair"),
    "eq_": (mujoco.mjtObj.mjOBJ_EQUALITY, "neq", "equality"),
    "tendon_": (mujoco.mjtObj.mjOBJ_TENDON, "ntendon", "tendon"),
    "actuator_": (mujoco.mjtObj.mjOBJ_ACTUATOR, "nu", "actuator"),
    "sensor_": (mujoco.mjtObj.mjOBJ_SENSOR, "nsensor", "sensor"),
}
_FIXED_OPTIONS = ("timestep",)  # the control period's base: the robot's timing, not a mismatch


def _floating(value) -> bool:
    return isinstance(value, jax.Array) and jnp.issubdtype(value.dtype, jnp.floating)


def _scalable_fields(model: mjx.Model) -> list[str]:
    """The model's floating-point array fields (leaves of the pytree; ``opt.<name>`` for the physics options)."""
    fields = [f.name for f in dataclasses.fields(model) if _floating(getattr(model, f.name))]
    options = [f"opt.{f.name}" for f in dataclasses.fields(model.opt)
               if _floating(getattr(model.opt, f.name)) and f.name not in _FIXED_OPTIONS]  # fmt: skip
    return fields + options


def _rows(model: mjx.Model, key: str, field: str, name: str):
    """The rows of ``field`` that belong to the object ``name`` (by the field's prefix)."""
    prefix = next((p for p in _OBJECTS if field.startswith(p)), None)
    if prefix is None:
        raise ValueError(f"mismatch key {key!r}: {field!r} has no named rows (fields of objects, such as body_*, "
                         f"take a name: {', '.join(p + '*' for p in _OBJECTS)}); scale it as a whole")  # fmt: skip
    obj, count, what = _OBJECTS[prefix]
    i = mjx.name2id(model, obj, name)
    if i < 0:
        valid = [n for j in range(getattr(model, count)) if (n := mjx.id2name(model, obj, j))]
        plural = "bodies" if what == "body" else f"{what}s"
        raise ValueError(f"mismatch key {key!r}: unknown {what} {name!r}; the model's {plural} are: "
                         f"{', '.join(map(repr, valid)) or 'none'}")  # fmt: skip
    if prefix != "dof_":
        return int(i)
    dofs = np.flatnonzero(np.asarray(model.dof_jntid) == i)  # a free joint has 6, a ball joint 3
    return int(dofs[0]) if dofs.size == 1 else dofs


def _parse(model: mjx.Model, key: str):
    """``"field[name]"`` -> (field, rows) and ``"field"`` -> (field, None); ``ValueError`` listing valid names."""
    field, _, rest = key.partition("[")
    name = rest[:-1].strip().strip("'\"") if rest else None
    if rest and not rest.endswith("]"):
        raise ValueError(f"mismatch key {key!r}: expected 'field' or 'field[name]'")
    fields = _scalable_fields(model)
    if field not in fields:
        raise ValueError(f"mismatch key {key!r}: {field!r} is not a scalable model field; valid fields: "
                         f"{', '.join(fields)}")  # fmt: skip
    return field, None if name is None else _rows(model, key, field, name)


def mismatch(model: mjx.Model, scales: dict) -> mjx.Model:
    """``model`` with named fields multiplied by factors: ``scales = {"body_mass[payload]": 1.5,
    "dof_damping[hinge]": 0.8, "actuator_gear": 0.9, "opt.gravity": 1.02}``. Any floating-point field of the
    ``mjx.Model`` can be scaled, and any physics option as ``opt.<name>`` (``opt.gravity``, ``opt.density``,
    ``opt.viscosity``, ``opt.wind``, ...; not ``opt.timestep``, the robot's timing). ``field[name]`` scales the
    row of the named object (a body, joint, geom, site, camera, light, material, pair, equality, tendon, actuator
    or sensor by the field's prefix; ``dof_*`` fields are named by their joint and scale all its degrees of
    freedom, six for a free joint; a row such as ``body_inertia`` or ``geom_friction`` scales as a whole);
    ``field`` alone scales every entry. Keys are static, factors may be traced:
    ``jax.vmap(lambda s: mismatch(model, s))`` over a dict of (B,) factors gives B plants.

    Derived constants that MuJoCo computes at load time (``body_subtreemass``, ``dof_invweight0``,
    ``actuator_acc0``, ...) keep their nominal values: they enter only the constraint solver's regularisation.
    A body's mass and inertia are separate fields (scale both for a uniformly denser body).
    """
    updates: dict[str, Any] = {}
    for key, factor in scales.items():
        field, row = _parse(model, key)
        value = updates.get(field, _field(model, field))
        factor = jnp.asarray(factor, value.dtype)
        _checks.shape(f"scales[{key!r}]", factor, (), "one factor per key")
        updates[field] = value * factor if row is None else value.at[row].multiply(factor)
    options = {k.removeprefix("opt."): v for k, v in updates.items() if k.startswith("opt.")}
    fields = {k: v for k, v in updates.items() if not k.startswith("opt.")}
    return model.replace(**fields, **({"opt": model.opt.replace(**options)} if options else {}))


def _field(model: mjx.Model, field: str):
    return getattr(model.opt, field.removeprefix("opt.")) if field.startswith("opt.") else getattr(model, field)


# --------------------------------------------------------------------------------------------
# Closed loop


class RobotRollout(NamedTuple):
    """Per control step ``k`` of :func:`rollout` (time ``k h``; leading axis: time ``T = steps``).

    The state is absolute, the measurements and commands are the controller's: deviations from the operating
    point (``y`` from ``s(x0)``, ``u`` from ``ctrl0``).

    Attributes:
      x: (T, nq + nv + na) the plant state ``(qpos, qvel, act)`` at ``k h``, absolute.
      dx: (T, d) its deviation from the operating point on the tangent space (``d = 2 nv + na``), what the
        linearisation's state holds.
      y: (T, p) the measurement the controller read, ``s(x(k h)) - s(x0) + v_k``: a deviation (a quaternion
        sensor's a rotation vector), noise included.
      y_true: (T, p) the same deviation without the noise.
      u: (T, m) the controller's command ``u_k``, added to ``ctrl0`` on the named actuators.
      applied: (T, m) the command acting during period ``k``, ``u_{k-d}`` (zeros for the first ``d`` periods).
      controller: the controller's outputs per step (its ``out`` pytree, each leaf with the leading axis T).
    """

    x: jax.Array
    dx: jax.Array
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

        y_k      = s(x(k h), a_{k-1}) - s(x0) + v_k,  v_k ~ N(0, diag(sensor_noise^2))    measured readings
        state, o = controller.step(params, state, ControllerInputs(y_k, r_k))
        FIFO    <- o.u (m,); pop a_k = u_{k-d}                                       dead time d periods
        plant   <- substeps mjx.step calls with ctrl = ctrl0 + a_k on the named actuators (held)

    The readings are deviations on their tangent space (a quaternion sensor's a rotation vector); an
    acceleration-stage sensor reads the command applied over the period that ends at the sample, ``a_{k-1}``
    (``a_{-1} = 0``).

    Args:
      robot: the :class:`Robot`.  controller: any :class:`~jaxobs.observers.base.Controller` whose ``u`` has one
        entry per named actuator.  params: its params.
      scales: mismatch factors by field key (:func:`mismatch`), or None for the nominal model.
      key: PRNG key of the sensor noise.  steps: control periods (static int >= 1).
      dx0: (d,) initial deviation of the state from the operating point, on its tangent space (``2 nv + na``
        entries; default zero).
      reference: ``r_k``, shape (steps, q) (default zeros of shape (steps, m)).

    Returns:
      :class:`RobotRollout`. Pure: ``jit``, ``vmap`` (over scales, keys, params), ``jax.jvp`` / ``jacfwd`` and
      ``grad``, contacts and joint limits included (docs/theory/mjx.md).
    """
    steps = _checks.count("steps", steps, minimum=1, hint="control periods")
    model = robot.model if not scales else mismatch(robot.model, scales)
    space, readings = robot.state_manifold, robot.sensor_manifold
    x_op = _operating_state(robot)
    dtype = x_op.dtype
    m, p = len(robot.actuators), readings.dim
    x0 = x_op
    if dx0 is not None:
        x0 = space.retract(x_op, _checks.vector("dx0", dx0, space.dim, dtype, what="one entry per tangent direction"))
    if reference is None:
        reference = jnp.zeros((steps, m), dtype)
    reference = jnp.asarray(reference, dtype)
    if reference.ndim != 2 or reference.shape[0] != steps:
        raise ValueError(f"reference must have shape (steps, q) = ({steps}, q), got {reference.shape}")
    noise = robot.sensor_noise * jax.random.normal(key, (steps, p), dtype)
    y_op = _sense(robot, robot.model, x_op, jnp.zeros((m,), dtype))
    h = robot.period

    def control_step(carry, inputs):
        k, r_k, v_k = inputs
        x, fifo, last, state = carry
        y_true = readings.difference(_sense(robot, model, x, last), y_op)
        y = y_true + v_k
        state, out = controller.step(params, state, ControllerInputs(y, r_k))
        _checks.shape("params", out.u, (m,), f"the controller's command u needs one entry per named actuator ({m})")
        u = out.u.astype(dtype)
        applied, fifo = dead_time_step(fifo, u, robot.dead_time)
        x_next = _step(robot, model, x, applied, k * h)
        return (x_next, fifo, applied, state), RobotRollout(x, space.difference(x, x_op), y, y_true, u, applied, out)

    carry = (x0, jnp.zeros((robot.dead_time, m), dtype), jnp.zeros((m,), dtype), controller.init(params))
    _, out = jax.lax.scan(control_step, carry, (jnp.arange(steps, dtype=dtype), reference, noise))
    return out
