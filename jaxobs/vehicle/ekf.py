"""The extended Kalman filter baseline of Grip 2010 §2.9 for vehicle sideslip, on the toolkit's EKF
(:mod:`jaxobs.observers.ekf`), with Bierman's U-D measurement update as an option.

State (8,): ``v_x``, ``v_y``, the inclination, the bank, the road friction ``mu`` and the derivatives of the last
three as filtered white noise; measurements (4,): ``a_x``, ``a_y``, the yaw acceleration and ``v_x,ref`` against
the friction model. Friction estimation switches between slow and fast with the NVSO's rule
(:mod:`jaxobs.vehicle.switching`). The noise intensities, thresholds, innovation gate, attraction of ``mu`` and
prior are assumed defaults (:func:`make_vehicle_ekf`; the thesis gives no numbers). :data:`vehicle_ekf`. The model,
the projection of ``mu`` and why the gate, prior and attraction are needed: docs/theory/vehicle.md.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.tree_util import Partial

from jaxobs import _checks
from jaxobs.nonlinear import GaussianState, nonlinear_model
from jaxobs.observers.base import Estimator, EstimatorInputs
from jaxobs.observers.ekf import EKFParams, extended_kalman_filter, make_ekf
from jaxobs.vehicle.model import GRAVITY, VehicleParams, check_vehicle, friction_model
from jaxobs.vehicle.sensors import (
    AX,
    AY,
    ESC_ACTIVE,
    N_SENSORS,
    SENSOR_RATE,
    STEERING_WHEEL,
    VX_REF,
    WHEEL_SPEED,
    YAW_RATE,
)
from jaxobs.vehicle.switching import SwitchingParams, make_switching, switching

__all__ = ["VehicleEKFParams", "VehicleEKFState", "VehicleEKFOutputs", "make_vehicle_ekf", "vehicle_ekf"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class VehicleEKFParams:
    """The vehicle EKF; build with :func:`make_vehicle_ekf`.

    Attributes:
      vehicle: the :class:`~jaxobs.vehicle.VehicleParams` of the friction model.
      ekf: the :class:`~jaxobs.observers.ekf.EKFParams` of the state-space model (its measurement function is
        rebound to the current sensors at every step); ``ekf.bierman`` selects Bierman's update.
      mu_bounds: (2,) the range of ``mu`` the friction model is evaluated at.
      switching: the :class:`~jaxobs.vehicle.switching.SwitchingParams` whose thresholds (and ``smooth``) select
        slow or fast friction estimation.
      q_mu: (2,) the intensities of the noise that drives ``d_mu`` in slow and fast friction estimation.
    """

    vehicle: VehicleParams
    ekf: EKFParams
    mu_bounds: jax.Array
    switching: SwitchingParams
    q_mu: jax.Array


class VehicleEKFState(NamedTuple):
    """State of :data:`vehicle_ekf` between samples.

    Attributes:
      filter: the EKF's state
      mode: () fast friction estimation (1) or slow (0), for the next interval
      off_timer: () the switching logic's timer (s)
      low_pass: () its high-pass filter's state
      sensors: (N_SENSORS,) last finite sensor sample
      missing: () int32, non-finite sensor entries so far
    """

    filter: GaussianState
    mode: jax.Array
    off_timer: jax.Array
    low_pass: jax.Array
    sensors: jax.Array
    missing: jax.Array


class VehicleEKFOutputs(NamedTuple):
    """Outputs of one sample of :data:`vehicle_ekf`.

    Attributes:
      x: (8,) a-posteriori state (v_x, v_y, theta_i, theta_b, mu, d_i, d_b, d_mu)
      P: (8, 8) its covariance
      beta: () sideslip arctan(v_y / v_x) (rad)
      mode: () the friction-estimation mode of the interval (1 fast)
      innovation: (4,) (a_x, a_y, r', v_x,ref) minus the model at the prior (0 where skipped)
    """

    x: jax.Array
    P: jax.Array
    beta: jax.Array
    mode: jax.Array
    innovation: jax.Array


def _process(constants, x, u, t):
    """The Euler map ``x + dt f(x, u)`` of the process model (docs/theory/vehicle.md); ``constants = (dt, tau, k_mu,
    mu0)``, ``u = (a_x, a_y, r, 1 - m)`` with the friction-estimation mode ``m`` of the interval."""
    dt, tau, k_mu, mu0 = constants
    ax, ay, r, slow = u
    vx, vy, _, _, mu, d_i, d_b, d_mu = x
    rate = jnp.stack([ax + r * vy + GRAVITY * x[2], ay - r * vx - GRAVITY * x[3], d_i, d_b,
                      d_mu - slow * k_mu * (mu - mu0), -d_i / tau, -d_b / tau, -d_mu / tau])  # fmt: skip
    return x + dt * rate


def _measurement(vehicle, mu_bounds, sensors, x):
    """``(a_x, a_y, r', v_x)`` of the friction model at the state ``x`` and the current ``sensors``."""
    ax, ay = sensors[AX], sensors[AY] / (1.0 + vehicle.roll_gradient * GRAVITY)
    mu = jnp.clip(x[4], mu_bounds[0], mu_bounds[1])
    r, steering_wheel, wheel_speed = sensors[YAW_RATE], sensors[STEERING_WHEEL], sensors[WHEEL_SPEED]
    f = friction_model(vehicle, x[0], x[1], r, steering_wheel, wheel_speed, ax, ay, mu)
    return jnp.stack([f.ax, f.ay, f.yaw_moment / vehicle.yaw_inertia, x[0]])


def make_vehicle_ekf(
    vehicle: VehicleParams | None = None,
    *,
    bierman: bool = False,
    q_v: float = 0.3,
    q_d=(0.005, 0.005),
    q_mu=(0.005, 0.1),
    tau: float = 1.0,
    r_std=(0.3, 0.3, 0.3, 0.1),
    vx0: float = 20.0,
    P0_diag=(0.01, 0.1, 1e-3, 1e-3, 0.01, 1e-5, 1e-5, 1e-4),
    mu0: float = 1.0,
    mu_bounds=(0.05, 1.5),
    dt: float = 1.0 / SENSOR_RATE,
    switching: SwitchingParams | None = None,
    gate: float | None = 4.0,
    mu_attraction: float = 0.5,
) -> VehicleEKFParams:
    """The EKF of Grip 2010 §2.9 for ``vehicle`` (default :class:`~jaxobs.vehicle.VehicleParams`).

    Args:
      vehicle: the vehicle whose friction model the filter uses.
      bierman: Bierman's U-D measurement update (:func:`jaxobs.kalman_steps.bierman_update`) instead of Joseph.
      q_v: process noise of the velocity equations (m/s^2, > 0).  q_d: (2,) intensities of the white noises that
        drive ``d_i``, ``d_b`` (> 0).  q_mu: (2,) that of ``d_mu`` in slow and in fast friction estimation (> 0).
        tau: the noise filters' time constant (s, > 0).
      r_std: (4,) measurement standard deviations of ``a_x``, ``a_y`` (m/s^2), ``r'`` (rad/s^2), ``v_x,ref``
        (m/s) (> 0; they include the friction model's error).
      vx0: prior mean of ``v_x`` (m/s), used only when the first sample has no finite ``v_x,ref`` (otherwise the
        prior mean is that ``v_x,ref``, as the NVSO starts); the other means are 0 and ``mu0``.
      P0_diag: (8,) prior variances (>= 0). Default: ``v_x`` 0.01 (the ``v_x,ref`` it starts from, ``r_std``
        0.1 m/s), ``v_y`` 0.1 (0.3 m/s), the angles 1e-3 (1.8 deg), ``mu`` 0.01 (0.1 about the nominal
        surface), the derivatives 1e-5, 1e-5, 1e-4. A wide prior (variances 1 on ``v_x`` and ``v_y``, 0.05 on
        ``mu``) lets the first updates take a start-up transient for a low friction (docs/theory/vehicle.md).
      mu_bounds: (lo, hi) with ``0 < lo < hi``: the friction range the model is evaluated at.
      dt: sample period (s, > 0).
      switching: the :class:`~jaxobs.vehicle.switching.SwitchingParams` of the switching rule (default
        ``make_switching(vehicle, dt=dt)``, the NVSO's thresholds; its ``dt`` must be this ``dt``).
      gate: innovation gate in standard deviations (> 0; default 4, ``None`` for none): a measurement component
        whose innovation exceeds ``gate`` times its predicted standard deviation is skipped as an outlier
        (:func:`jaxobs.kalman_steps.innovation_gate`) and counted in ``state.filter.gated``; it keeps transients
        the friction model cannot explain (no tyre relaxation) out of the friction estimate.
      mu_attraction: rate ``k_mu`` (1/s, >= 0; default 0.5, the NVSO's ``K_e``) at which ``mu`` is drawn to
        ``mu0`` in slow friction estimation (the NVSO's (2.20)); 0 for the pure filtered-white-noise model.

    Example:
      >>> from jaxobs.vehicle.ekf import make_vehicle_ekf
      >>> params = make_vehicle_ekf(bierman=True)
      >>> params.ekf.bierman, params.ekf.model.x0.shape
      (True, (8,))
    """
    vehicle = check_vehicle(vehicle)
    dtype = jnp.result_type(vehicle.mass, float)  # the vehicle's precision
    q_d, r_std, P0_diag = (_checks.real_array(k, v).astype(dtype) for k, v in (("q_d", q_d), ("r_std", r_std),
                                                                             ("P0_diag", P0_diag)))  # fmt: skip
    for name, value in (("q_v", q_v), ("q_d", q_d), ("q_mu", q_mu), ("tau", tau), ("r_std", r_std), ("dt", dt)):
        _checks.positive(name, value)
    _checks.positive("P0_diag", P0_diag, allow_zero=True)
    _checks.positive("mu_attraction", mu_attraction, allow_zero=True)
    _checks.positive("mu0", mu0)
    _checks.shape("q_d", q_d, (2,), "one intensity per angle derivative")
    q_mu = jnp.asarray(q_mu, dtype)
    _checks.shape("q_mu", q_mu, (2,), "(slow, fast)")
    switching = make_switching(vehicle, dt=dt) if switching is None else switching
    if not isinstance(switching, SwitchingParams):
        kind = type(switching).__name__
        raise ValueError(f"switching must be SwitchingParams (jaxobs.vehicle.make_switching), got {kind}")
    _checks.shape("r_std", r_std, (4,), "one per measurement (a_x, a_y, r', v_x,ref)")
    _checks.shape("P0_diag", P0_diag, (8,), "one variance per state")
    mu_bounds = _checked_mu_bounds(mu_bounds, dtype)
    Q = dt * jnp.diag(jnp.concatenate([jnp.full(2, q_v**2, dtype), jnp.zeros(3, dtype), q_d**2, q_mu[:1] ** 2]))
    x0 = jnp.zeros(8, dtype).at[0].set(vx0).at[4].set(mu0)
    constants = tuple(jnp.asarray(c, dtype) for c in (dt, tau, mu_attraction, mu0))
    f = Partial(_process, constants)
    h = Partial(_measurement, vehicle, mu_bounds, jnp.zeros(N_SENSORS, dtype))
    model = nonlinear_model(f, h, Q, jnp.diag(r_std**2), x0=x0, P0=jnp.diag(P0_diag), n_inputs=4, dt=dt)
    return VehicleEKFParams(vehicle, make_ekf(model, bierman=bierman, gate=gate), mu_bounds, switching, q_mu)


def _checked_mu_bounds(mu_bounds, dtype) -> jax.Array:
    """``mu_bounds`` as a (2,) array ``(lo, hi)`` of ``dtype``, positive, ``lo < hi`` where concrete."""
    mu_bounds = jnp.asarray(mu_bounds, dtype)
    _checks.shape("mu_bounds", mu_bounds, (2,), "(lo, hi)")
    _checks.positive("mu_bounds", mu_bounds)
    if _checks.is_concrete(mu_bounds) and not bool(mu_bounds[0] < mu_bounds[1]):
        raise ValueError(f"mu_bounds must have lo < hi, got {mu_bounds.tolist()}")
    return mu_bounds


def _init(params: VehicleEKFParams) -> VehicleEKFState:
    check_vehicle(params.vehicle, "params.vehicle")  # one filter, checked at trace time: vmap for a batch
    _checks.fields("params", params, "mu_bounds (2,), q_mu (2,)")
    _checks.fields("params.ekf.model", params.ekf.model, "Q (8, 8), R (4, 4), x0 (8,), P0 (8, 8)")
    model = params.ekf.model
    sensors = jnp.zeros((N_SENSORS,), model.x0.dtype).at[VX_REF].set(model.x0[0])
    sensors = sensors.at[WHEEL_SPEED].set(model.x0[0] / params.vehicle.wheel_radius)
    zero = jnp.zeros((), model.x0.dtype)
    timer = jnp.asarray(params.switching.off_delay, model.x0.dtype)
    return VehicleEKFState(extended_kalman_filter.init(params.ekf), zero, timer, zero, sensors,
                           jnp.zeros((), jnp.int32))  # fmt: skip


def _step(params: VehicleEKFParams, state: VehicleEKFState, inputs: EstimatorInputs):
    model, vehicle = params.ekf.model, params.vehicle
    dtype = model.x0.dtype
    y = _checks.vector("inputs.y", inputs.y, N_SENSORS, dtype, what="the vehicle's sensors", check_finite=False)
    finite = jnp.isfinite(y)
    sensors = jnp.where(finite, y, state.sensors)
    previous = state.sensors
    roll = 1.0 + vehicle.roll_gradient * GRAVITY
    u_prev = jnp.stack([previous[AX], previous[AY] / roll, previous[YAW_RATE], 1.0 - state.mode])
    first = ~state.filter.started
    # the prior mean of v_x is the first finite v_x,ref (the NVSO's start); vx0 only without one
    start = state.filter.x.at[0].set(jnp.where(finite[VX_REF], y[VX_REF], state.filter.x[0]))
    filt = state.filter._replace(x=jnp.where(first, start, state.filter.x))
    # r' needs two finite yaw-rate samples; NaN (skipped by the EKF) otherwise and at the first sample
    yaw_acc = jnp.where(state.filter.started & finite[YAW_RATE], (y[YAW_RATE] - previous[YAW_RATE]) / model.dt, jnp.nan)
    z = jnp.stack([y[AX], y[AY] / roll, yaw_acc, y[VX_REF]])
    h = Partial(_measurement, vehicle, params.mu_bounds, sensors)
    q_mu = (1.0 - state.mode) * params.q_mu[0] ** 2 + state.mode * params.q_mu[1] ** 2
    Q = model.Q.at[7, 7].set(model.dt * q_mu)
    ekf = dataclasses.replace(params.ekf, model=dataclasses.replace(model, h=h, Q=Q))
    filt, out = extended_kalman_filter.step(ekf, filt, EstimatorInputs(y=z, u_prev=u_prev))
    # projection onto [max(lo, |(a_x, a_y)| / (accel_margin g)), hi] (the NVSO's bounds, Grip 2010 §2.8)
    lower = jnp.maximum(
        params.mu_bounds[0], jnp.hypot(sensors[AX], sensors[AY] / roll) / (params.switching.accel_margin * GRAVITY)
    )
    x = out.x.at[4].set(jnp.clip(out.x[4], jnp.minimum(lower, params.mu_bounds[1]), params.mu_bounds[1]))
    filt, out = filt._replace(x=x), out._replace(x=x)
    switch = switching(params.switching, state.off_timer, state.low_pass, out.x[0], sensors[YAW_RATE],
                       sensors[AY] / roll, sensors[STEERING_WHEEL], sensors[ESC_ACTIVE])  # fmt: skip
    mode = jnp.where(first, state.mode, switch.mode)
    timer = jnp.where(first, state.off_timer, switch.off_timer)
    low_pass = jnp.where(first, sensors[AY] / roll - sensors[YAW_RATE] * out.x[0], switch.low_pass)  # HP starts at 0
    missing = state.missing + jnp.sum(~finite).astype(jnp.int32)
    beta = jnp.arctan2(out.x[1], out.x[0])
    new_state = VehicleEKFState(filt, mode, timer, low_pass, sensors, missing)
    return new_state, VehicleEKFOutputs(out.x, out.P, beta, state.mode, out.innovation)


vehicle_ekf = Estimator(_init, _step)
"""The vehicle EKF (docs/theory/vehicle.md) as an :class:`~jaxobs.observers.base.Estimator` over
:class:`VehicleEKFParams`. Inputs: ``EstimatorInputs(y)`` with the sensors ``y`` (:data:`jaxobs.vehicle.N_SENSORS`,)
(:func:`jaxobs.vehicle.sensor_inputs`). State: :class:`VehicleEKFState`. Outputs: :class:`VehicleEKFOutputs`."""
