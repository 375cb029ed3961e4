"""1-DOF robot force-control plant in MuJoCo MJX (Cortesão, MRAC chapter §7, eq. 56-58; Cortesão 2006 §7).

A tool on a slide joint: the compliant force sensor is the joint spring (``Ks`` in N/mm), the robot's position
loop a velocity servo on the inertia ``kv Tp``, the command a velocity (mm/s) behind a dead-time FIFO; the
measured force is the joint's passive force plus noise (:func:`sensor_force`). :func:`rollout` runs it open loop,
:func:`closed_loop_rollout` under any controller of :func:`jaxobs.closed_loop.simulate`; :func:`with_params` is
the one place parameters map to model fields, so mismatched batches are a ``vmap`` over it. The derivation and the
simplifications against the real robot: docs/theory/mjx.md.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxobs import _checks
from jaxobs.mjx.common import (
    check_timing,
    dead_time_step,
    initial_data,
    input_series,
    is_int_at_least,
    put_model,
    step,
)
from jaxobs.observers.base import Controller, ControllerInputs

__all__ = [
    "CONTROL_PERIOD",
    "SUBSTEPS",
    "ForcePlantParams",
    "ForceRollout",
    "load_model",
    "with_params",
    "rollout",
    "ClosedLoopRollout",
    "closed_loop_rollout",
    "sensor_force",
]

ASSET = "force_1dof.xml"
TIMESTEP = 0.001  # s, physics step (the MJCF's option/timestep)
SUBSTEPS = 8  # physics steps per control step
CONTROL_PERIOD = TIMESTEP * SUBSTEPS  # h = 8 ms (the MRAC chapter Table 1)
_JOINT = "x"
_BODY = "tool"
_ACTUATOR = "servo"


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ForcePlantParams:
    """Physical parameters of the 1-DOF force plant (mm, N, s units; the MRAC chapter Table 1 nominal values).

    Attributes:
      stiffness: sensor + environment stiffness ``Ks`` in N/mm (> 0).
      time_constant: position-loop time constant ``Tp`` in s (> 0).
      damping: sensor + environment damping ``Ds`` in N s/mm (>= 0); it is part of the measured force.
      servo_gain: velocity-servo gain ``kv`` in N s/mm (> 0); the robot's total moving inertia is
        ``kv Tp`` (so an inertia mismatch is a ``time_constant`` mismatch here) and the position loop yields to
        the contact force by ``stiffness / servo_gain``.
    """

    stiffness: float = 3.0
    time_constant: float = 0.032
    damping: float = 0.0
    servo_gain: float = 1.0e4

    def validate(self, prefix: str = "") -> None:
        """Raise ``ValueError`` naming the bad field, after ``prefix`` (e.g. ``"params."``); shapes at trace time,
        values where concrete."""
        _checks.positive_scalar(f"{prefix}stiffness", self.stiffness)
        _checks.positive_scalar(f"{prefix}time_constant", self.time_constant)
        _checks.positive_scalar(f"{prefix}damping", self.damping, allow_zero=True)
        _checks.positive_scalar(f"{prefix}servo_gain", self.servo_gain)


class ForceRollout(NamedTuple):
    """Per control step ``k`` (at time ``k h``, before the step's command acts).

    Attributes:
      force: (T,) measured force (N): simulated sensor force plus noise
      force_true: (T,) noise-free sensor force (N)
      position: (T,) tool position x (mm past the contact point)
      velocity: (T,) tool velocity (mm/s)
      applied: (T,) command applied during step k (mm/s), i.e. u_{k-d}
      surface: (T,) environment surface position x_e at k h (mm)
    """

    force: jax.Array
    force_true: jax.Array
    position: jax.Array
    velocity: jax.Array
    applied: jax.Array
    surface: jax.Array


def _ids(m: mujoco.MjModel) -> tuple[int, int, int]:
    jnt = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, _JOINT)
    body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, _BODY)
    act = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, _ACTUATOR)
    return jnt, body, act


def _tool_body(model) -> int:
    """Index of the body moved by the force joint (the tool)."""
    return int(np.asarray(model.jnt_bodyid)[0])


def with_params(model: mjx.Model, params: ForcePlantParams) -> mjx.Model:
    """Return ``model`` with the physical ``params`` written into its array fields (pure, traceable).

    The one place where parameters map to fields: ``jnt_stiffness = stiffness``, ``dof_damping = damping``,
    ``actuator_gainprm[0] = kv``, ``actuator_biasprm[2] = -kv``, ``dof_armature = kv time_constant - m_tool``.
    Derived fields used only by constraints (``dof_invweight0``, ``actuator_acc0``, ...) are left as
    they are: constraints and contacts are disabled in this model.
    """
    params.validate("params.")
    if _checks.is_concrete(params.servo_gain, params.time_constant, model.body_mass):
        inertia = float(params.servo_gain) * float(params.time_constant)
        tool_mass = float(np.asarray(model.body_mass)[_tool_body(model)])
        if inertia <= tool_mass:
            raise ValueError(
                f"servo_gain * time_constant = {inertia} must exceed the tool mass {tool_mass} t; raise servo_gain"
            )
    dtype = model.jnt_stiffness.dtype
    fields = (params.stiffness, params.time_constant, params.damping, params.servo_gain)
    ks, tp, damping, kv = (jnp.asarray(v, dtype) for v in fields)
    return model.replace(
        jnt_stiffness=jnp.asarray(model.jnt_stiffness).at[0].set(ks),
        dof_damping=jnp.asarray(model.dof_damping).at[0].set(damping),
        dof_armature=jnp.asarray(model.dof_armature).at[0].set(kv * tp - model.body_mass[_tool_body(model)]),
        actuator_gainprm=jnp.asarray(model.actuator_gainprm).at[0, 0].set(kv),
        actuator_biasprm=jnp.asarray(model.actuator_biasprm).at[0, 2].set(-kv),
    )


def _parse_mjcf(xml) -> mujoco.MjModel:
    """The packaged MJCF (``xml=None``) or a user's file, checked for what this plant needs: a slide joint
    ``x`` (the compliant force sensor: its spring gives the force) as the first joint, the body ``tool`` it
    moves, and a velocity actuator ``servo`` on it. Anything else is a ``ValueError`` naming the file."""
    if xml is None:
        source = f"jaxobs/mjx/assets/{ASSET}"
        text = importlib.resources.files("jaxobs.mjx").joinpath("assets", ASSET).read_text()
    else:
        source = str(xml)
        try:
            text = Path(xml).read_text()
        except OSError as exc:
            raise ValueError(f"MJCF {source}: cannot read it ({exc})") from exc
    try:
        m = mujoco.MjModel.from_xml_string(text)
    except ValueError as exc:  # mujoco reports XML and schema errors as ValueError
        raise ValueError(f"MJCF {source}: invalid model: {exc}") from exc
    jnt, body, act = _ids(m)
    if jnt != 0 or m.jnt_type[0] != mujoco.mjtJoint.mjJNT_SLIDE:
        raise ValueError(
            f"MJCF {source}: the force sensor is missing: the first joint must be the slide joint '{_JOINT}' "
            "whose spring is the compliant sensor"
        )
    if body < 0 or m.jnt_bodyid[0] != body:
        raise ValueError(f"MJCF {source}: joint '{_JOINT}' must move the body '{_BODY}'")
    if act != 0 or m.actuator_trnid[0, 0] != jnt or m.actuator_biasprm[0, 2] >= 0:
        raise ValueError(f"MJCF {source}: the first actuator must be the velocity servo '{_ACTUATOR}' on '{_JOINT}'")
    return m


def load_model(params: ForcePlantParams | None = None, *, xml=None) -> tuple[mujoco.MjModel, mjx.Model]:
    """Load the packaged MJCF (or the file ``xml``, which must have the same joint, body and actuator
    names; see :func:`_parse_mjcf`) and return ``(mj_model, mjx_model)`` with ``params`` applied to both.

    ``params`` must be concrete here (build batches with :func:`with_params` under ``vmap``).
    """
    params = ForcePlantParams() if params is None else params
    params.validate()
    m = _parse_mjcf(xml)
    kv, tp = float(params.servo_gain), float(params.time_constant)
    tool_mass = m.body_mass[_tool_body(m)]
    if kv * tp <= tool_mass:
        raise ValueError(f"servo_gain * time_constant = {kv * tp} must exceed the tool mass {tool_mass} t")
    m.jnt_stiffness[0] = float(params.stiffness)
    m.dof_damping[0] = float(params.damping)
    m.dof_armature[0] = kv * tp - tool_mass
    m.actuator_gainprm[0, 0] = kv
    m.actuator_biasprm[0, 2] = -kv
    return m, put_model(m)


def sensor_force(model: mjx.Model, data: mjx.Data) -> jax.Array:
    """The noise-free sensor force of the state in ``data``: ``Ks (x - springref) + Ds xdot``.

    This is ``-qfrc_passive`` as MuJoCo evaluates it at the start of the next step (spring plus damper;
    gravity, fluid forces and gravity compensation are off in this model), computed from the state so a
    controller can read it before choosing the step's command.
    """
    _checks.fields("data", data, "qpos (q,), qvel (v,)")  # one state: vmap for a batch
    x = data.qpos[0] - model.qpos_spring[0]
    return model.jnt_stiffness[0] * x + model.dof_damping[0] * data.qvel[0]


def _at_surface(model: mjx.Model, surface) -> mjx.Model:
    """``model`` with the environment surface (the spring's rest position ``qpos_spring``) at ``surface`` mm."""
    return model.replace(qpos_spring=jnp.asarray(model.qpos_spring).at[0].set(surface))


def _advance(model: mjx.Model, substeps: int, d: int, data, fifo, u_k, surface, surface_velocity):
    """One control step of the plant: push ``u_k`` into the dead-time FIFO, pop ``u_{k-d}`` and hold it
    (ZOH) for ``substeps`` physics steps (:func:`jaxobs.mjx.common.step`) while the surface moves from ``surface`` at
    ``surface_velocity`` mm/s (one position per physics step). Returns ``(data, fifo, applied, surface)``.
    Shared by the open-loop :func:`rollout` and :func:`closed_loop_rollout`."""
    applied, fifo = dead_time_step(fifo, u_k, d)
    data = data.replace(ctrl=data.ctrl.at[0].set(applied))
    dx = surface_velocity * model.opt.timestep

    def substep(_, carry):
        data, surface = carry
        return step(_at_surface(model, surface), data), surface + dx

    data, surface = jax.lax.fori_loop(0, substeps, substep, (data, surface))
    return data, fifo, applied, surface


def _truncate(carry, k, horizon: int | None):
    """Truncated backpropagation through time: cut the gradient through the scan carry every ``horizon``
    control steps (parameters closed over by the step still receive every chunk's gradient)."""
    if horizon is None:
        return carry
    cut = (k % horizon) == 0
    return jax.tree.map(lambda c: jnp.where(cut, jax.lax.stop_gradient(c), c), carry)


def _check_horizon(gradient_horizon) -> None:
    if gradient_horizon is not None and not is_int_at_least(gradient_horizon, 1):
        raise ValueError(f"gradient_horizon must be None or a Python int >= 1, got {gradient_horizon!r}")


def rollout(
    model: mjx.Model,
    commands,
    *,
    dead_time_samples: int = 5,
    substeps: int = SUBSTEPS,
    noise=None,
    fifo_init=None,
    surface_velocity=None,
    gradient_horizon: int | None = None,
) -> ForceRollout:
    """Simulate the plant over ``len(commands)`` control steps in one ``lax.scan``.

    Control step ``k`` (time ``k h``, ``h = substeps * model.opt.timestep``): the force is sampled
    (:func:`sensor_force` of the state at ``k h``) and ``noise[k]`` added; the command FIFO pops
    ``u_{k-d}`` and pushes ``u_k``; ``u_{k-d}`` is held for ``substeps`` ``mjx.step`` calls (an inner
    ``lax.scan``). Starts at rest at the contact point (``F = 0``), the surface at 0.

    Args:
      model: an ``mjx.Model`` from :func:`load_model` / :func:`with_params`.
      commands: velocity commands ``u_k`` in mm/s, shape ``(T,)``.
      dead_time_samples: command dead time ``d`` in control samples (Python int >= 0; 5 in the papers).
      substeps: physics steps per control step (Python int >= 1).
      noise: additive force-sensor noise in N, shape ``(T,)``, or None. Draw it outside, e.g.
        ``sigma * jax.random.normal(key, (T,))``, and ``vmap`` over keys for seed batches.
      fifo_init: the ``d`` commands issued before step 0 (oldest first), shape ``(d,)``; zeros by default.
      surface_velocity: velocity of the environment surface in mm/s during each control step, shape
        ``(T,)``, or None (fixed). A positive velocity recedes from the tool and lowers the force: the
        moving surface of the stochastic AOB paper §4 (``xdot_e = 2 mm/s`` from 8 s). The sensor force is
        ``Ks (x - x_e) + Ds xdot``.
      gradient_horizon: truncate backpropagation through the plant state every this many control steps
        (None: full gradients); bounds the memory of the backward pass and its growth on long horizons.

    Returns:
      :class:`ForceRollout` of arrays of shape ``(T,)``. Pure: works under ``jit``, ``vmap``, ``grad``,
      ``jacfwd``.
    """
    check_timing(dead_time_samples, substeps)
    _check_horizon(gradient_horizon)
    commands = jnp.asarray(commands)
    if commands.ndim != 1:
        raise ValueError(f"commands must have shape (T,) (one velocity command per control step), got {commands.shape}")
    if _checks.is_concrete(commands) and not np.all(np.isfinite(np.asarray(commands))):
        raise ValueError("commands contains NaN or infinite entries")
    dtype = jnp.result_type(commands, model.jnt_stiffness.dtype, float)
    commands = commands.astype(dtype)
    n_steps = commands.shape[0]
    noise = input_series("noise", noise, n_steps, dtype, "commands")
    d = int(dead_time_samples)
    fifo = input_series("fifo_init", fifo_init, d, dtype, "the dead time (dead_time_samples entries)")
    v_e = input_series("surface_velocity", surface_velocity, n_steps, dtype, "commands")

    def control_step(carry, inputs):
        k, u_k, noise_k, v_k = inputs
        data, fifo, surface = _truncate(carry, k, gradient_horizon)
        force = sensor_force(_at_surface(model, surface), data)
        position, velocity = data.qpos[0], data.qvel[0]
        data, fifo, applied, surface_next = _advance(model, substeps, d, data, fifo, u_k, surface, v_k)
        out = ForceRollout(force + noise_k, force, position, velocity, applied, surface)
        return (data, fifo, surface_next), out

    carry = (initial_data(model, dtype), fifo, jnp.zeros((), dtype))
    _, out = jax.lax.scan(control_step, carry, (jnp.arange(n_steps), commands, noise, v_e))
    return out


class ClosedLoopRollout(NamedTuple):
    """Per control step ``k`` of :func:`closed_loop_rollout` (time ``k h``; leading axis: time).

    Attributes:
      force: (T,) measured force y_k (N): sensor force plus noise, what the controller reads
      force_true: (T,) noise-free sensor force (N)
      position: (T,) tool position x (mm past the contact point)
      velocity: (T,) tool velocity (mm/s)
      command: (T,) controller command u_k = r_k - L x_hat_k (mm/s)
      applied: (T,) plant input during step k: u_{k-d} + disturbance_{k-d} (mm/s)
      controller: the controller's outputs per step (e.g. FeedbackOutputs: u, x, the estimator's outputs)
      surface: (T,) environment surface position x_e at k h (mm)
    """

    force: jax.Array
    force_true: jax.Array
    position: jax.Array
    velocity: jax.Array
    command: jax.Array
    applied: jax.Array
    controller: object
    surface: jax.Array


def closed_loop_rollout(
    model: mjx.Model,
    controller: Controller,
    params,
    reference,
    *,
    dead_time_samples: int = 5,
    substeps: int = SUBSTEPS,
    noise=None,
    disturbance=None,
    surface_velocity=None,
    gradient_horizon: int | None = None,
) -> ClosedLoopRollout:
    """The MJX force plant under observer-based state feedback, in one ``lax.scan`` over control steps.

    The MJX counterpart of :func:`jaxobs.closed_loop.simulate` with the same controller protocol. At
    control step ``k`` (time ``k h``)::

        y_k      = F(x(k h)) + v_k                          sensor force (sensor_force) plus noise
        state, o = controller.step(params, state, ControllerInputs(y_k, r_k))
        u_k      = o.u                                       e.g. the AOB's r_k - [L_r 1] [x_r; p]_hat
        FIFO    <- u_k + d_k;  pop u_{k-d} + d_{k-d}         dead time d samples (disturbance at the plant
                                                             input, before the dead time, as in simulate)
        plant   <- ``substeps`` mjx.step calls with that input held (ZOH)

    The controller is built on the nominal discrete model (e.g. an AOB on :func:`jaxobs.plants.force_plant`,
    whose delay states model the same ``d`` samples); the state feedback lives in its params
    (``u = r - L x_hat``, with the AOB's active state fed forward through its ``L_Np = 1`` entry), exactly as
    in ``simulate``.

    Args:
      model: an ``mjx.Model`` from :func:`load_model` / :func:`with_params` (the true plant; it may differ
        from the controller's nominal model).
      controller: any :class:`~jaxobs.observers.base.Controller` whose outputs have ``u`` of shape (1,), e.g.
        :data:`jaxobs.observers.active.active_observer_controller`.
      params: the controller's params (e.g. :class:`~jaxobs.observers.feedback.FeedbackParams`).
      reference: ``r_k`` in mm/s, shape ``(T,)`` (``r_k = L_1 F_d`` for a desired force ``F_d``).
      dead_time_samples, substeps: as in :func:`rollout`.
      noise: force-sensor noise ``v_k`` in N, shape ``(T,)``, or None.
      disturbance: input disturbance ``d_k`` in mm/s, shape ``(T,)``, or None.
      surface_velocity, gradient_horizon: as in :func:`rollout` (moving environment surface in mm/s;
        truncated backpropagation through the plant and controller state).

    Returns:
      :class:`ClosedLoopRollout`; pure: works under ``jit``, ``vmap`` (over models from
      :func:`with_params`, noise, controller parameters), ``grad`` and ``jacfwd``.
    """
    check_timing(dead_time_samples, substeps)
    _check_horizon(gradient_horizon)
    reference = jnp.asarray(reference)
    if reference.ndim != 1:
        raise ValueError(f"reference must have shape (T,) (one reference per control step), got {reference.shape}")
    dtype = jnp.result_type(reference, model.jnt_stiffness.dtype, float)
    reference = reference.astype(dtype)
    n_steps = reference.shape[0]
    noise = input_series("noise", noise, n_steps, dtype, "reference")
    disturbance = input_series("disturbance", disturbance, n_steps, dtype, "reference")
    v_e = input_series("surface_velocity", surface_velocity, n_steps, dtype, "reference")
    d = int(dead_time_samples)

    def control_step(carry, inputs):
        k, r_k, v_k, d_k, ve_k = inputs
        data, fifo, ctrl_state, surface = _truncate(carry, k, gradient_horizon)
        force = sensor_force(_at_surface(model, surface), data)
        y_k = force + v_k
        ctrl_state, ctrl_out = controller.step(params, ctrl_state, ControllerInputs(y_k[None], r_k[None]))
        _checks.shape("params", ctrl_out.u, (1,), "the controller's command u must have one entry, the "
                      "1-DOF plant's velocity command")  # fmt: skip
        u_k = ctrl_out.u[0].astype(dtype)
        position, velocity = data.qpos[0], data.qvel[0]
        data, fifo, applied, surface_next = _advance(model, substeps, d, data, fifo, u_k + d_k, surface, ve_k)
        out = ClosedLoopRollout(y_k, force, position, velocity, u_k, applied, ctrl_out, surface)
        return (data, fifo, ctrl_state, surface_next), out

    carry = (initial_data(model, dtype), jnp.zeros(d, dtype), controller.init(params), jnp.zeros((), dtype))
    _, out = jax.lax.scan(control_step, carry, (jnp.arange(n_steps), reference, noise, disturbance, v_e))
    return out
