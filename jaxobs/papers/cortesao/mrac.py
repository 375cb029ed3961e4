"""Cortesão, "Model Reference Adaptive Control for Robotic Manipulation with Kalman Active Observers"
(IntechOpen chapter), §7: the six per-DOF controllers of the 6-DOF compliant-motion task (eq. 62-68) and the
peg-on-hole alignment scenario (§7.4, Figures 4-6), on the MJX plant of :mod:`jaxobs.mjx.compliant_6dof`.

:func:`design` builds the six controllers (AOB-1 on five DOF, a CKF with the sensor-based gain on z) stacked on a
leading axis; :func:`peg_on_hole_scenario` scripts the alignment; :func:`jaxobs.mjx.compliant_6dof.closed_loop_rollout`
runs them with one ``vmap`` over DOF. :func:`design` raises ``ValueError`` unless float64 is enabled. Chosen values and
simplifications: docs/theory/papers.md.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.design import critically_damped_gain
from jaxobs.mjx.compliant_6dof import (
    CONTROL_PERIOD,
    N_DOF,
    NOMINAL_STIFFNESS,
    RY,
    Compliant6Params,
    X,
    Z,
    check_per_dof,
)
from jaxobs.observers.active import aob_noise_covariance, feedback_gain, make_aob, sensor_based_gain
from jaxobs.observers.feedback import FeedbackParams
from jaxobs.plants import force_plant

__all__ = [
    "TABLE1_STIFFNESS",
    "SENSOR_NOISE_VARIANCE",
    "PegOnHoleScenario",
    "design",
    "force_reference",
    "peg_on_hole_scenario",
]


class PegOnHoleScenario(NamedTuple):
    """The alignment phase of §7.4 (:func:`peg_on_hole_scenario`); series have shape (T, 6).

    Attributes:
      t: (T,) time (s)
      force_setpoint: f_d (N, N·m)
      feedforward: v_d (mm/s, rad/s): w_y alignment velocity, v_z feedforward bias
      reference: controller reference r = L_1 f_d
      plant: the alignment-phase plant (K_ry = 0: the peg pivots on the contact)
      controllers: the six per-DOF AOB controllers, stacked (m_y feedback off)
    """

    t: jax.Array
    force_setpoint: jax.Array
    feedforward: jax.Array
    reference: jax.Array
    plant: Compliant6Params
    controllers: FeedbackParams


TABLE1_STIFFNESS = NOMINAL_STIFFNESS
"""Table 1: 3, 3, 20 N/mm; 100, 100 N·m/rad. The z rotation (last entry) is not printed: chosen (100 N·m/rad)."""

SENSOR_NOISE_VARIANCE = (2.1e-2, 7.4e-4, 2.1e-2, 1e-4, 1e-4, 1e-4)
"""``R`` per wrench component in N^2 and (N·m)^2: f_x eq. 64, f_y eq. 67; f_z and the moments are not
printed (chosen: f_z as f_x, moments std 0.01 N·m)."""

Q_PLANT_FX = 1e-12  # eq. 62, plant-state entries of Q(f_x)
Q_ACTIVE_FX = 1e-5  # eq. 62, active-state entry of Q(f_x) (AOB-1: the variance of xi_p)
P0_FX = 1e-4  # eq. 63
TAU_C_OVER_TP = 10.0  # eq. 68


def _check_design(params, noise_variance, q_active, process_noise, n_obs: int, sba, feedback_off, steady_state):
    """:func:`design`'s arguments, a ``ValueError`` naming the bad one (``n_obs``: observer states per DOF)."""
    params.validate()
    if _checks.is_concrete(params.stiffness) and np.any(np.asarray(params.stiffness) <= 0):
        raise ValueError(
            f"stiffness must be > 0 in every DOF for a design (Ks/(s(1+Tp s)) is uncontrollable at Ks = 0), "
            f"got {np.asarray(params.stiffness).tolist()}"
        )
    check_per_dof("noise_variance", noise_variance, minimum=0.0, strict=True)
    if q_active is not None:
        check_per_dof("q_active", q_active, minimum=0.0, strict=False)
        if process_noise is not None:
            raise ValueError("give q_active or process_noise, not both")
    if process_noise is not None:
        _checks.shape("process_noise", process_noise, (N_DOF, n_obs, n_obs), "one (n, n) Q per DOF")
        _checks.covariance("process_noise", process_noise, definite=False, size=n_obs, batch=True)
    for name, dofs in (("sba", sba), ("feedback_off", feedback_off)):
        if any(not isinstance(i, (int, np.integer)) or not 0 <= i < N_DOF for i in dofs):
            raise ValueError(f"{name} must list DOF indices in 0..5 (x, y, z, rx, ry, rz), got {dofs!r}")
    if not steady_state and sba:
        raise ValueError("steady_state=False needs sba=(): the SBA gain is fixed, the time-varying AOBs have none")


def design(
    params: Compliant6Params | None = None,
    *,
    noise_variance=SENSOR_NOISE_VARIANCE,
    q_active=None,
    process_noise=None,
    h: float = CONTROL_PERIOD,
    dead_time_samples: int = 5,
    tau_c_over_tp: float = TAU_C_OVER_TP,
    sba=(Z,),
    feedback_off=(),
    steady_state: bool = True,
) -> FeedbackParams:
    """The six per-DOF controllers of §7.3 (eq. 62-68), stacked on a leading axis of size 6.

    Per DOF ``i``: ``force_plant(K_i, Tp_i, h, d h)``, ``L_r`` by :func:`jaxobs.design.critically_damped_gain`
    with ``tau_c = tau_c_over_tp * Tp_i`` (eq. 68), ``R_i = noise_variance[i]``, and with ``a_i = R_i / R(f_x)``
    (eq. 65-66) an AOB-1 with ``Q = a_i diag(1e-12, ..., 1e-12, 1e-5)`` (eq. 62) and ``P0 = a_i 1e-4 I``
    (eq. 63). The DOF in ``sba`` (default ``z``, §7.4) get the CKF with the sensor-based gain
    ``K = [1, 0, ..., 0]'`` (the AOB-1 with ``active = 0``, same shape). The DOF in ``feedback_off`` get
    ``L = 0`` (no force feedback: the command is the reference plus feedforward; §7.4 switches the ``m_y``
    controller on only for the insertion).

    Args:
      params: the nominal plant (Table-1 stiffnesses; every stiffness must be > 0 here).
      noise_variance: ``R`` per DOF (6,), N^2 and (N·m)^2 (:data:`SENSOR_NOISE_VARIANCE`).
      q_active: active-state variances (6,) replacing ``a_i 1e-5`` (may be traced, e.g. ``exp`` of a tuned log).
      process_noise: (6, n, n) full per-DOF ``Q`` replacing eq. 62's (then ``q_active`` must be None), ``n = 3 +
        dead_time_samples`` observer states ``[F, dF/dt, u_{k-d}, ..., u_{k-1}, p]``; may be traced.
      steady_state: steady-state Kalman gains (DARE with implicit derivatives, so tuners can differentiate
        through the design); ``False`` (time-varying gains) needs ``sba=()``, since the SBA gain is fixed and
        the six controllers must share one pytree structure.

    Returns:
      stacked :class:`~jaxobs.observers.feedback.FeedbackParams` of
      :data:`~jaxobs.observers.active.active_observer_controller` (leading axis 6, 8 observer states each).
    """
    params = Compliant6Params() if params is None else params
    n_obs = 3 + int(dead_time_samples)
    _check_design(params, noise_variance, q_active, process_noise, n_obs, sba, feedback_off, steady_state)
    r = jnp.broadcast_to(jnp.asarray(noise_variance, float), (N_DOF,))
    if r.dtype != jnp.float64:
        raise ValueError(
            "design() needs float64: with Q entries of 1e-12..1e-5 the float32 DARE returns near-zero gains; "
            "enable it in your entry point with jax.config.update('jax_enable_x64', True)"
        )
    ratio = r / r[X]  # eq. 65-66
    if process_noise is None:
        q_active = Q_ACTIVE_FX * ratio if q_active is None else jnp.broadcast_to(jnp.asarray(q_active, float), (N_DOF,))
        process_noise = jax.vmap(lambda a, b: aob_noise_covariance(n_obs - 1, 1, 1, a, b))(Q_PLANT_FX * ratio, q_active)
    Q = jnp.asarray(process_noise, float)
    controllers = _design_aobs(
        params.per_dof("stiffness", float), params.per_dof("time_constant", float), r, Q, P0_FX * ratio, h=float(h),
        dead_time_samples=int(dead_time_samples), tau_c_over_tp=float(tau_c_over_tp), steady_state=bool(steady_state),
    )  # fmt: skip
    aobs = controllers.estimator
    if sba:
        sensor_based = jnp.asarray([i in sba for i in range(N_DOF)])
        gain = jnp.broadcast_to(sensor_based_gain(aobs.C[0]), aobs.gain.shape)
        aobs = dataclasses.replace(
            aobs,
            active=jnp.where(sensor_based, 0.0, aobs.active),
            gain=jnp.where(sensor_based[:, None, None], gain, aobs.gain),
            gain_passive=jnp.where(sensor_based[:, None, None], gain, aobs.gain_passive),
        )
    L = controllers.L
    if feedback_off:
        off = jnp.asarray([i in feedback_off for i in range(N_DOF)])
        L = jnp.where(off[:, None, None], 0.0, L)
    return FeedbackParams(aobs, L)


@functools.partial(jax.jit, static_argnames=("h", "dead_time_samples", "tau_c_over_tp", "steady_state"))
def _design_aobs(stiffness, tp, r, Q, p0, *, h, dead_time_samples, tau_c_over_tp, steady_state):
    """The six AOB-1 of eq. 62-68 in one ``vmap`` over DOF (compiled once per process; traceable)."""

    def one(ks, tp, r, Q, p0):
        plant = force_plant(ks, tp, h, dead_time_samples * h)
        L_r = critically_damped_gain(plant, tau_c_over_tp * tp)
        P0 = p0 * jnp.eye(plant.n_states + 1)
        aob = make_aob(plant, 1, r, Q=Q, P0=P0, steady_state=steady_state)
        return FeedbackParams(aob, feedback_gain(aob, L_r))

    return jax.vmap(one)(stiffness, tp, r, Q, p0)


def force_reference(controllers: FeedbackParams, force_setpoint) -> jax.Array:
    """``r = L_1 f_d`` per DOF (unit DC gain from desired to measured wrench, Cortesão 2006 "L_1 r_k");
    ``force_setpoint`` of shape (T, 6) or (6,). Zero for a DOF with its feedback off."""
    return jnp.asarray(force_setpoint) * controllers.L[:, 0, 0]


def _smoothstep(x):
    x = jnp.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def peg_on_hole_scenario(
    params: Compliant6Params | None = None,
    *,
    duration: float = 4.0,
    contact_force=(-5.0, 10.0),
    contact_ramp: float = 0.5,
    alignment=(1.5, 3.5),
    insertion_velocity_bias: float = 0.05,
    h: float = CONTROL_PERIOD,
) -> PegOnHoleScenario:
    """The alignment phase of the peg-on-hole task (§7.4, Figure 4) with the controllers of §7.3-7.4.

    Scripted in place of the paper's ANN reference generator (the magnitudes are not printed; chosen here):

    * ``f_x`` (negative) and ``f_z`` (positive) keep the three-point contact: setpoints ``contact_force``
      (N), ramped in smoothly over ``contact_ramp`` s from the untensioned start; ``f_y``, ``m_x``, ``m_z`` zero;
    * ``w_y`` (negative) aligns the peg: a raised-cosine velocity feedforward over the ``alignment`` window
      (s) whose integral is ``-tilt``, so the peg ends upright; the ``m_y`` controller is off (``L = 0``) and
      the plant's ``K_ry = 0`` (the peg pivots on the contact), so ``m_y`` is the contact force's moment;
    * ``v_z`` carries a constant feedforward bias ``insertion_velocity_bias`` (mm/s), the ANN's training
      error of Fig. 6.c that the CKF, SBA on ``z`` cannot reject.

    Controllers: :func:`design` on ``params`` (Table-1 stiffnesses) with AOB-1 HBA on x, y, rx, ry, rz, CKF SBA
    on z, and ``feedback_off=(ry,)``. Run it with
    ``closed_loop_rollout(with_params(model, s.plant), active_observer_controller, s.controllers, s.reference,
    feedforward=s.feedforward)``.
    """
    params = Compliant6Params() if params is None else params
    params.validate()
    t0, t1 = (float(v) for v in alignment)
    if not 0.0 <= t0 < t1 <= duration:
        raise ValueError(f"alignment must be a window (t0, t1) with 0 <= t0 < t1 <= duration, got {alignment!r}")
    if contact_ramp <= 0:
        raise ValueError(f"contact_ramp must be > 0 s, got {contact_ramp}")
    n_steps = int(round(duration / h))
    t = jnp.arange(n_steps) * h
    ramp = _smoothstep(t / contact_ramp)
    fx, fz = (float(v) for v in contact_force)
    setpoint = jnp.zeros((n_steps, N_DOF)).at[:, X].set(fx * ramp).at[:, Z].set(fz * ramp)
    width = t1 - t0
    window = (t >= t0) & (t < t1)
    w_y = jnp.where(window, -params.tilt * (1.0 - jnp.cos(2.0 * jnp.pi * (t - t0) / width)) / width, 0.0)
    feedforward = jnp.zeros((n_steps, N_DOF)).at[:, RY].set(w_y).at[:, Z].set(insertion_velocity_bias)
    controllers = design(params, h=h, feedback_off=(RY,))
    plant = dataclasses.replace(params, stiffness=params.per_dof("stiffness", float).at[RY].set(0.0))
    return PegOnHoleScenario(t, setpoint, feedforward, force_reference(controllers, setpoint), plant, controllers)
