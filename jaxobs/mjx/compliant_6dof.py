"""6-DOF compliant-motion plant in MuJoCo MJX (Cortesão, MRAC chapter §7, Table 1, eq. 56-61, Figure 4).

A peg held through a compliant force/torque sensor: three slide and three hinge joints, each a joint spring and
a velocity servo as in :mod:`jaxobs.mjx.force_1dof`, with the peg-on-hole contact moment coupled to the alignment
rotation (:func:`coupling_force`). Users pass and read Table 1's units (N, N·m, mm/s, rad/s); the conversion lives
only in :func:`with_params` and :func:`sensor_wrench`. :func:`closed_loop_rollout` runs one controller per DOF
(:func:`stack_controllers`); the per-DOF AOBs and the scenario are in :mod:`jaxobs.papers.cortesao.mrac`. The
model, the coupling and the simplifications against the real setup: docs/theory/mjx.md.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxobs import _checks
from jaxobs.mjx.common import check_timing, dead_time_step, initial_data, input_series, put_model, step
from jaxobs.observers.base import Controller, ControllerInputs

__all__ = [
    "DOF_NAMES",
    "N_DOF",
    "NOMINAL_STIFFNESS",
    "CONTROL_PERIOD",
    "SUBSTEPS",
    "Compliant6Params",
    "check_per_dof",
    "WrenchRollout",
    "Compliant6Rollout",
    "load_model",
    "with_params",
    "sensor_wrench",
    "contact_point",
    "coupling_force",
    "rollout",
    "closed_loop_rollout",
    "stack_controllers",
]

ASSET = "compliant_6dof.xml"
TIMESTEP = 0.001  # s, physics step (the MJCF's option/timestep)
SUBSTEPS = 8  # physics steps per control step
CONTROL_PERIOD = TIMESTEP * SUBSTEPS  # h = 8 ms (MRAC chapter, Table 1)
N_DOF = 6
DOF_NAMES = ("x", "y", "z", "rx", "ry", "rz")  # joints and actuators, in the order of the wrench
X, Y, Z, RX, RY, RZ = range(N_DOF)
_SITE = "contact"
_BODY = "tool"
# Table-1 units (N/mm, N·m/rad; N, N·m) to model units (N/mm, N·mm/rad; N, N·mm)
_TO_MODEL = np.array([1.0, 1.0, 1.0, 1e3, 1e3, 1e3])

NOMINAL_STIFFNESS = (3.0, 3.0, 20.0, 100.0, 100.0, 100.0)
"""Nominal stiffnesses of the shipped model (N/mm for x, y, z; N·m/rad for the rotations): those of
Table 1 of Cortesão's MRAC chapter, with the z rotation (not printed there) chosen as 100 N·m/rad."""


def _default(values):
    return dataclasses.field(default_factory=lambda: np.array(values, dtype=float))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Compliant6Params:
    """Physical parameters of the 6-DOF plant, in Table-1 units (per-DOF arrays in the order x, y, z, rx, ry, rz).

    Attributes:
      stiffness: sensor + environment stiffness ``K_i`` (6,): N/mm for x, y, z and N·m/rad for the rotations
        (>= 0; 0 is a DOF the environment does not resist, e.g. the pivoting peg's ``ry`` during alignment).
      time_constant: position-loop time constant ``Tp`` in s, scalar or (6,) (> 0).
      damping: sensor + environment damping ``D_i`` (N s/mm, N·m·s/rad), scalar or (6,) (>= 0); part of the
        measured wrench, acting on the joint coordinates (not through the contact point).
      servo_gain: velocity-servo gain ``kv_i`` (N s/mm, N·m·s/rad), scalar or (6,) (> 0); the DOF's inertia is
        ``kv Tp`` and its servo yields to the contact force by ``K / kv``.
      contact_radius: ``rho`` (mm), the contact point's distance from the peg axis (23 mm peg: 11.5).
      contact_depth: ``l`` (mm), the peg tip's depth below the sensor origin (the 30 mm peg length; the real
        sensor-to-tip distance is not printed).
      tilt: the peg's initial tilt about ``y`` (rad) at ``q = 0``.
      coupling: scale of the lever arm ``p0`` (1 nominal, 0 decouples the six DOF).
    """

    stiffness: jax.Array = _default(NOMINAL_STIFFNESS)
    time_constant: jax.Array = _default(0.032)
    damping: jax.Array = _default(0.0)
    servo_gain: jax.Array = _default([1e5, 1e5, 1e5, 1e6, 1e6, 1e6])
    contact_radius: jax.Array = _default(11.5)
    contact_depth: jax.Array = _default(30.0)
    tilt: jax.Array = _default(0.04)
    coupling: jax.Array = _default(1.0)

    def validate(self, prefix: str = "") -> None:
        """Raise ``ValueError`` naming the bad field, after ``prefix`` (e.g. ``"params."``); shapes at trace time,
        values where concrete."""
        check_per_dof(f"{prefix}stiffness", self.stiffness, minimum=0.0, strict=False)
        check_per_dof(f"{prefix}time_constant", self.time_constant, minimum=0.0, strict=True)
        check_per_dof(f"{prefix}damping", self.damping, minimum=0.0, strict=False)
        check_per_dof(f"{prefix}servo_gain", self.servo_gain, minimum=0.0, strict=True)
        for name in ("contact_radius", "contact_depth", "tilt", "coupling"):
            value = getattr(self, name)
            if np.shape(value) != ():
                raise ValueError(f"{prefix}{name} must be a scalar, got shape {np.shape(value)}")
            if _checks.is_concrete(value) and not np.isfinite(np.asarray(value)):
                raise ValueError(f"{prefix}{name} must be finite, got {value}")

    def per_dof(self, name: str, dtype=None) -> jax.Array:
        """The field ``name`` broadcast to shape (6,)."""
        return jnp.broadcast_to(jnp.asarray(getattr(self, name), dtype), (N_DOF,))


def check_per_dof(name: str, value, *, minimum: float, strict: bool) -> None:
    """``ValueError`` unless ``value`` is a scalar or (6,) per-DOF value, and where concrete finite and above
    ``minimum`` (``strict``) or at least ``minimum``."""
    shape = np.shape(value)
    if shape not in ((), (N_DOF,)):
        raise ValueError(f"{name} must be a scalar or have shape ({N_DOF},) (x, y, z, rx, ry, rz), got {shape}")
    if not _checks.is_concrete(value):
        return
    a = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or infinite entries")
    bad = a <= minimum if strict else a < minimum
    if np.any(bad):
        rel = ">" if strict else ">="
        raise ValueError(f"{name} must be {rel} {minimum} in every DOF, got {a.tolist()}")


class WrenchRollout(NamedTuple):
    """Per control step ``k`` of :func:`rollout` (time ``k h``; leading axis time, then the 6 DOF).

    Attributes:
      wrench: (T, 6) measured wrench (N, N·m): simulated sensor wrench plus noise
      wrench_true: (T, 6) noise-free sensor wrench (N, N·m)
      position: (T, 6) joint coordinates q (mm, rad past the untensioned contact)
      velocity: (T, 6) qdot (mm/s, rad/s)
      applied: (T, 6) plant input during step k (mm/s, rad/s): the command d samples earlier
    """

    wrench: jax.Array
    wrench_true: jax.Array
    position: jax.Array
    velocity: jax.Array
    applied: jax.Array


class Compliant6Rollout(NamedTuple):
    """Per control step ``k`` of :func:`closed_loop_rollout` (leading axis time, then the 6 DOF).

    Attributes:
      wrench: (T, 6) measured wrench y_k (N, N·m): sensor wrench plus noise, what the controllers read
      wrench_true: (T, 6) noise-free sensor wrench (N, N·m)
      position: (T, 6) joint coordinates q (mm, rad)
      velocity: (T, 6) qdot (mm/s, rad/s)
      command: (T, 6) controller commands u_k = r_k - L x_hat_k (mm/s, rad/s)
      applied: (T, 6) plant input during step k: (u + v_d + d)_{k-d}
      controller: per-DOF controller outputs (e.g. FeedbackOutputs), leading axes (T, 6)
    """

    wrench: jax.Array
    wrench_true: jax.Array
    position: jax.Array
    velocity: jax.Array
    command: jax.Array
    applied: jax.Array
    controller: object


# --------------------------------------------------------------------------------------------
# Model


def _contact_lever_arm(params: Compliant6Params, dtype) -> jax.Array:
    """``coupling * R_y(tilt) (rho, 0, -l)`` (mm), the site position at ``q = 0``."""
    rho, depth, tilt, c = (
        jnp.asarray(getattr(params, f), dtype) for f in ("contact_radius", "contact_depth", "tilt", "coupling")
    )
    cos, sin = jnp.cos(tilt), jnp.sin(tilt)
    return c * jnp.stack([rho * cos - depth * sin, jnp.zeros_like(rho), -rho * sin - depth * cos])


def _tool_inertia(model) -> jax.Array:
    """The tool body's own contribution to each joint's inertia at ``q = 0`` (mass, mass, mass, Ixx, Iyy, Izz)."""
    mass = jnp.asarray(model.body_mass)[1]
    inertia = jnp.asarray(model.body_inertia)[1]
    return jnp.concatenate([jnp.broadcast_to(mass, (3,)), inertia])


def with_params(model: mjx.Model, params: Compliant6Params) -> mjx.Model:
    """Return ``model`` with the physical ``params`` written into its array fields (pure, traceable, vmappable).

    The one place where parameters map to fields (rotational entries converted from N·m to N·mm):
    ``jnt_stiffness = K``, ``dof_damping = D``, ``actuator_gainprm[:, 0] = kv``, ``actuator_biasprm[:, 2] = -kv``,
    ``dof_armature = kv Tp - tool inertia``, ``site_pos[contact] = coupling R_y(tilt) (rho, 0, -l)``.
    Derived fields used only by constraints are left as they are: constraints and contacts are disabled.
    """
    params.validate("params.")
    dtype = model.jnt_stiffness.dtype
    unit = jnp.asarray(_TO_MODEL, dtype)
    stiffness, damping, kv = (params.per_dof(f, dtype) * unit for f in ("stiffness", "damping", "servo_gain"))
    inertia = kv * params.per_dof("time_constant", dtype)
    if _checks.is_concrete(inertia, model.body_mass, model.body_inertia):
        tool = np.asarray(_tool_inertia(model))
        if np.any(np.asarray(inertia) <= tool):
            raise ValueError(
                f"servo_gain * time_constant (model units {np.asarray(inertia).tolist()}) must exceed the tool's own "
                f"inertia {tool.tolist()} in every DOF; raise servo_gain"
            )
    return model.replace(
        jnt_stiffness=stiffness,
        dof_damping=damping,
        dof_armature=inertia - _tool_inertia(model).astype(dtype),
        actuator_gainprm=jnp.asarray(model.actuator_gainprm).at[:, 0].set(kv),
        actuator_biasprm=jnp.asarray(model.actuator_biasprm).at[:, 2].set(-kv),
        site_pos=jnp.asarray(model.site_pos).at[0].set(_contact_lever_arm(params, dtype)),
    )


def load_model(params: Compliant6Params | None = None) -> tuple[mujoco.MjModel, mjx.Model]:
    """Load the packaged MJCF and return ``(mj_model, mjx_model)`` with ``params`` applied to both.

    ``params`` must be concrete here (build batches with :func:`with_params` under ``vmap``).
    """
    params = Compliant6Params() if params is None else params
    params.validate()
    xml = importlib.resources.files("jaxobs.mjx").joinpath("assets", ASSET).read_text()
    m = mujoco.MjModel.from_xml_string(xml)
    joints = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in DOF_NAMES]
    actuators = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in DOF_NAMES]
    site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, _SITE)
    body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, _BODY)
    layout = (joints, actuators, list(m.jnt_dofadr), list(m.actuator_trnid[:, 0]), site, body, m.nv)
    assert layout == (list(range(6)), list(range(6)), list(range(6)), list(range(6)), 0, 1, 6), (
        "compliant_6dof.xml layout changed; update with_params"
    )
    mx = with_params(put_model(m), params)
    for field in ("jnt_stiffness", "dof_damping", "dof_armature", "actuator_gainprm", "actuator_biasprm", "site_pos"):
        getattr(m, field)[...] = np.asarray(getattr(mx, field))
    return m, mx


# --------------------------------------------------------------------------------------------
# Coupling and sensor


def _qpos(model: mjx.Model, qpos) -> jax.Array:
    """``qpos`` (nq,) as an array, its shape checked at trace time (one configuration: ``vmap`` for a batch)."""
    qpos = _checks.real_array("qpos", qpos)
    _checks.shape("qpos", qpos, (model.nq,), "one configuration")
    return qpos


def contact_point(model: mjx.Model, qpos: jax.Array) -> jax.Array:
    """The contact point ``p(theta) = R_y(theta) p0`` (mm, sensor frame, x and z components) for the
    alignment rotation ``theta = q_ry``: MuJoCo's own position of the ``contact`` site relative to the tool
    body when only ``ry`` is deflected."""
    qpos = _qpos(model, qpos)
    theta = qpos[RY] - model.qpos_spring[RY]
    p0x, p0z = model.site_pos[0, 0], model.site_pos[0, 2]
    cos, sin = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([cos * p0x + sin * p0z, -sin * p0x + cos * p0z])


def _contact(model: mjx.Model, qpos: jax.Array):
    """``(p, s, f)``: contact point, its displacement ``s = p - p0`` and the contact-spring forces (f_x, f_z)."""
    p = contact_point(model, qpos)
    s = p - jnp.stack([model.site_pos[0, 0], model.site_pos[0, 2]])
    k = jnp.stack([model.jnt_stiffness[X], model.jnt_stiffness[Z]])
    q = jnp.stack([qpos[X] - model.qpos_spring[X], qpos[Z] - model.qpos_spring[Z]])
    return p, s, k * (q + s)


def coupling_force(model: mjx.Model, qpos: jax.Array) -> jax.Array:
    """The peg-on-hole coupling as a generalized force (6,) in model units (N, N·mm).

    It is ``-dV_c/dq``::

        (-K_x s_x, 0, -K_z s_z, 0, -(p_z f_x - p_x f_z), 0)

    with ``p``, ``s`` and the contact forces ``f`` of docs/theory/mjx.md; zero for a zero lever arm. Added to
    ``qfrc_applied`` before every physics step; MuJoCo's diagonal joint springs supply the rest of the force."""
    p, s, f = _contact(model, _qpos(model, qpos))
    moment = p[1] * f[0] - p[0] * f[1]
    zero = jnp.zeros_like(moment)
    k = model.jnt_stiffness
    return jnp.stack([-k[X] * s[0], zero, -k[Z] * s[1], zero, -moment, zero])


def sensor_wrench(model: mjx.Model, data: mjx.Data) -> jax.Array:
    """The noise-free sensor wrench (6,) of the state in ``data``, in N and N·m.

    ``K (q - springref) + D qdot - coupling_force(q)``: the joints' passive force (MuJoCo's
    ``-qfrc_passive``; gravity and fluid forces are off) plus the contact coupling, i.e.
    ``f_x = K_x (q_x + s_x)``, ``f_z = K_z (q_z + s_z)``, ``m_y = K_ry theta + p_z f_x - p_x f_z`` (plus damping),
    the other components ``K_i q_i + D_i qdot_i``. Computed from the state, so a controller can read it before
    choosing the step's command. Moments are converted from the model's N·mm to N·m.
    """
    _checks.fields("data", data, "qpos (q,), qvel (v,)")  # one state: vmap for a batch
    q = data.qpos - model.qpos_spring
    wrench = model.jnt_stiffness * q + model.dof_damping * data.qvel - coupling_force(model, data.qpos)
    return wrench / jnp.asarray(_TO_MODEL, wrench.dtype)


def _advance(model: mjx.Model, substeps: int, d: int, data: mjx.Data, fifo: jax.Array, u_k: jax.Array):
    """One control step: push ``u_k`` (6,) into the dead-time FIFO (d, 6), pop ``u_{k-d}`` and hold it (ZOH) for
    ``substeps`` physics steps, each with the coupling force of its start state in ``qfrc_applied``.
    Returns ``(data, fifo, applied)``; shared by :func:`rollout` and :func:`closed_loop_rollout`."""
    applied, fifo = dead_time_step(fifo, u_k, d)
    data = data.replace(ctrl=applied)

    def substep(_, data):
        return step(model, data.replace(qfrc_applied=coupling_force(model, data.qpos)))

    data = jax.lax.fori_loop(0, substeps, substep, data)
    return data, fifo, applied


def _leading(name: str, value, what: str) -> jax.Array:
    value = jnp.asarray(value)
    if value.ndim != 2 or value.shape[1] != N_DOF:
        raise ValueError(f"{name} must have shape (T, {N_DOF}) ({what} per control step and DOF), got {value.shape}")
    if _checks.is_concrete(value) and not np.all(np.isfinite(np.asarray(value))):
        raise ValueError(f"{name} contains NaN or infinite entries")
    return value


def _start(model: mjx.Model, dtype) -> mjx.Data:
    data = initial_data(model, dtype)
    return data.replace(qfrc_applied=data.qfrc_applied.astype(dtype))


def rollout(model: mjx.Model, commands, *, dead_time_samples: int = 5, substeps: int = SUBSTEPS, noise=None):
    """The open-loop plant over ``len(commands)`` control steps in one ``lax.scan``.

    Control step ``k``: the wrench is sampled (:func:`sensor_wrench` of the state at ``k h``) and ``noise[k]``
    added; the FIFO pops ``u_{k-d}`` and pushes ``u_k``; ``u_{k-d}`` is held for ``substeps`` physics steps.
    Starts at rest at the untensioned contact (zero wrench).

    Args:
      model: an ``mjx.Model`` from :func:`load_model` / :func:`with_params`.
      commands: velocity commands (T, 6) in mm/s and rad/s.
      dead_time_samples, substeps: Python ints (5 and 8 in the paper's setup).
      noise: additive wrench noise (T, 6) in N and N·m, or None.

    Returns:
      :class:`WrenchRollout`; pure (``jit``, ``vmap``, ``grad``, ``jacfwd``).
    """
    check_timing(dead_time_samples, substeps)
    commands = _leading("commands", commands, "one velocity command")
    dtype = jnp.result_type(commands, model.jnt_stiffness.dtype, float)
    commands = commands.astype(dtype)
    noise = input_series("noise", noise, (commands.shape[0], N_DOF), dtype, "commands")
    d = int(dead_time_samples)

    def control_step(carry, inputs):
        data, fifo = carry
        u_k, v_k = inputs
        wrench, position, velocity = sensor_wrench(model, data), data.qpos, data.qvel
        data, fifo, applied = _advance(model, substeps, d, data, fifo, u_k)
        return (data, fifo), WrenchRollout(wrench + v_k, wrench, position, velocity, applied)

    _, out = jax.lax.scan(control_step, (_start(model, dtype), jnp.zeros((d, N_DOF), dtype)), (commands, noise))
    return out


def _check_controllers(params) -> None:
    leaves = jax.tree_util.tree_leaves(params)
    sizes = {np.shape(leaf)[0] if np.ndim(leaf) else None for leaf in leaves}
    if not leaves or sizes != {N_DOF}:
        raise ValueError(
            f"params must hold {N_DOF} per-DOF controllers stacked on a leading axis "
            f"(stack_controllers / design), got leading sizes {sorted(sizes, key=str)}"
        )


def closed_loop_rollout(
    model: mjx.Model,
    controller: Controller,
    params,
    reference,
    *,
    dead_time_samples: int = 5,
    substeps: int = SUBSTEPS,
    feedforward=None,
    noise=None,
    disturbance=None,
) -> Compliant6Rollout:
    """The 6-DOF plant under six per-DOF observer-based controllers, in one ``lax.scan`` over control steps.

    At control step ``k`` (time ``k h``)::

        y_k      = w(q(k h)) + n_k                      sensor wrench (sensor_wrench, N and N·m) plus noise
        state, o = vmap(controller.step)(params, state, ControllerInputs(y_k[:, None], r_k[:, None]))  per DOF
        u_k      = o.u[:, 0]                             e.g. the AOB's r - [L_r 1] [x_r; p]_hat
        FIFO    <- u_k + v_d,k + d_k;  pop the entry d samples old           dead time (d, 6)
        plant   <- ``substeps`` (coupling force, mjx.step) with that input held (ZOH)

    The velocity feedforward ``v_d`` and the disturbance ``d`` both enter at the plant input, outside the
    observers' models (the AOB cancels them, the CKF does not; §7.1).

    Args:
      model: an ``mjx.Model`` from :func:`load_model` / :func:`with_params` (the true plant).
      controller: any :class:`~jaxobs.observers.base.Controller` of one DOF (one output, one input), e.g.
        :data:`jaxobs.observers.active.active_observer_controller`.
      params: six per-DOF controller parameters stacked on a leading axis of size 6 (all the same shape), e.g.
        from :func:`stack_controllers` or :func:`jaxobs.papers.cortesao.mrac.design`.
      reference: controller references ``r_k`` (T, 6), e.g. ``L_1 f_d`` per DOF.
      dead_time_samples, substeps: as in :func:`rollout`.
      feedforward: velocity feedforward ``v_d`` (T, 6) in mm/s and rad/s, or None.
      noise: wrench noise (T, 6) in N and N·m, or None (draw it outside; ``vmap`` over keys for seed batches).
      disturbance: input disturbance (T, 6) in mm/s and rad/s, or None.

    Returns:
      :class:`Compliant6Rollout`; pure: ``jit``, ``vmap`` (over models from :func:`with_params`, noise,
      controller parameters), ``grad`` and ``jacfwd`` work through it.
    """
    check_timing(dead_time_samples, substeps)
    _check_controllers(params)
    reference = _leading("reference", reference, "one controller reference")
    dtype = jnp.result_type(reference, model.jnt_stiffness.dtype, float)
    reference = reference.astype(dtype)
    n_steps = reference.shape[0]
    feedforward = input_series("feedforward", feedforward, (n_steps, N_DOF), dtype, "reference")
    noise = input_series("noise", noise, (n_steps, N_DOF), dtype, "reference")
    disturbance = input_series("disturbance", disturbance, (n_steps, N_DOF), dtype, "reference")
    d = int(dead_time_samples)
    controller_step = jax.vmap(controller.step)

    def control_step(carry, inputs):
        data, fifo, ctrl_state = carry
        r_k, ff_k, n_k, d_k = inputs
        wrench = sensor_wrench(model, data)
        y_k = wrench + n_k
        ctrl_state, ctrl_out = controller_step(params, ctrl_state, ControllerInputs(y_k[:, None], r_k[:, None]))
        _checks.shape("params", ctrl_out.u, (N_DOF, 1), "per DOF the controller's command u must have "
                      "one entry, the DOF's velocity command")  # fmt: skip
        u_k = ctrl_out.u[:, 0].astype(dtype)
        position, velocity = data.qpos, data.qvel
        data, fifo, applied = _advance(model, substeps, d, data, fifo, u_k + ff_k + d_k)
        out = Compliant6Rollout(y_k, wrench, position, velocity, u_k, applied, ctrl_out)
        return (data, fifo, ctrl_state), out

    carry = (_start(model, dtype), jnp.zeros((d, N_DOF), dtype), jax.vmap(controller.init)(params))
    _, out = jax.lax.scan(control_step, carry, (reference, feedforward, noise, disturbance))
    return out


# --------------------------------------------------------------------------------------------
# Stacking per-DOF controllers


def stack_controllers(controllers):
    """Stack six per-DOF controller parameters (same pytree structure and shapes) on a leading axis.

    An AOB-1 and a CKF of the same plant differ in state size: build the CKF as the AOB-1 with
    ``set_active(params, 0.0)`` (and a fixed gain in ``gain``/``gain_passive`` for the SBA), as
    :func:`jaxobs.papers.cortesao.mrac.design` does, so that the six stack."""
    controllers = list(controllers)
    if len(controllers) != N_DOF:
        raise ValueError(
            f"controllers must hold {N_DOF} per-DOF controllers (x, y, z, rx, ry, rz), got {len(controllers)}"
        )
    structure = jax.tree_util.tree_structure(controllers[0])
    shapes = [jnp.shape(leaf) for leaf in jax.tree_util.tree_leaves(controllers[0])]
    for i, c in enumerate(controllers[1:], 1):
        same = jax.tree_util.tree_structure(c) == structure
        if not same or [jnp.shape(leaf) for leaf in jax.tree_util.tree_leaves(c)] != shapes:
            raise ValueError(
                f"controllers[{i}] ({DOF_NAMES[i]}) differs in structure or shapes from controllers[0]; build a CKF "
                "as an AOB with set_active(params, 0.0) and give every controller fixed gains or none"
            )
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *controllers)
