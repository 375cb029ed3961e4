"""The extended Kalman filter baseline of Grip 2010 §2.9 for vehicle sideslip, on the toolkit's EKF
(:mod:`jaxobs.observers.ekf`), with Bierman's U-D measurement update as an option.

State (8,): ``v_x``, ``v_y`` (m/s), the inclination ``theta_i = sin(Theta)``, the bank ``theta_b = cos(Theta)
sin(Phi)``, the road friction ``mu`` (the scale of the tyres' peak friction, 1 = their own) and the time
derivatives ``d_i``, ``d_b``, ``d_mu`` of the last three, each a first-order filtered white noise (§2.9: "the
derivatives of mu_H, inclination and bank are modelled as filtered white noise")::

    v_x' = a_x + r v_y + g theta_i,    v_y' = a_y - r v_x - g theta_b                     (2.11)-(2.12)
    theta_i' = d_i,  theta_b' = d_b,  mu' = d_mu,    d' = -d / tau + w,   var w = q_d^2

with the measured ``a_x``, the roll-corrected ``a_y`` and the yaw rate ``r`` of the previous sample as known inputs
(the yaw rate as a known time-varying signal makes the process model linear time-varying, as in the thesis), and
white process noise ``q_v`` (m/s^2) on the two velocity equations (the accelerometer noise). Forward Euler at the
sensor period (§2.9): ``x_k = x_{k-1} + dt f(x_{k-1}, u_{k-1})``, ``Q = dt diag(q_v^2, q_v^2, 0, 0, 0, q_d^2)``.

Measurements (4,): ``a_x``, the roll-corrected ``a_y``, the yaw acceleration ``r'`` (the difference of two yaw-rate
samples over ``dt``) and ``v_x,ref``; the model is the friction model (:func:`jaxobs.vehicle.friction_model`) at the
estimated ``v_x``, ``v_y`` and friction ``mu`` (clipped to ``mu_bounds``), evaluated with the current steering
angle, wheel speeds, yaw rate and the loads of the measured accelerations (force and moment balances: ``a_x = F_x /
m``, ``a_y = F_y / m``, ``r' = M / I_z``), and ``v_x`` for ``v_x,ref``.

Assumptions and departures (the thesis gives no numbers): the noise intensities and the prior are assumed
defaults (:class:`VehicleEKFParams`); the thesis switches between slow and fast friction estimation with the
NVSO's rule, here ``q_d`` is fixed (one intensity per derivative). Missing data: a non-finite sensor sample is
held at the channel's last finite value in the model and the measurements built from it are skipped by the EKF;
both are counted (``state.missing`` counts the non-finite sensor entries).
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
from jaxobs.vehicle.model import GRAVITY, VehicleParams, friction_model
from jaxobs.vehicle.nvso import N_SENSORS
from jaxobs.vehicle.sensors import SENSOR_RATE

__all__ = ["VehicleEKFParams", "VehicleEKFState", "VehicleEKFOutputs", "make_vehicle_ekf", "vehicle_ekf"]

_AX, _AY, _R, _SW, _OMEGA, _VREF = 0, 1, 2, 3, slice(4, 8), 8


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class VehicleEKFParams:
    """The vehicle EKF; build with :func:`make_vehicle_ekf`.

    Attributes:
      vehicle: the :class:`~jaxobs.vehicle.VehicleParams` of the friction model.
      ekf: the :class:`~jaxobs.observers.ekf.EKFParams` of the state-space model (its measurement function is
        rebound to the current sensors at every step); ``ekf.bierman`` selects Bierman's update.
      mu_bounds: (2,) the range of ``mu`` the friction model is evaluated at.
    """

    vehicle: VehicleParams
    ekf: EKFParams
    mu_bounds: jax.Array


class VehicleEKFState(NamedTuple):
    filter: GaussianState  # the EKF's state
    sensors: jax.Array  # (N_SENSORS,) last finite sensor sample
    missing: jax.Array  # () int32, non-finite sensor entries so far


class VehicleEKFOutputs(NamedTuple):
    x: jax.Array  # (8,) a-posteriori state (v_x, v_y, theta_i, theta_b, mu, d_i, d_b, d_mu)
    P: jax.Array  # (8, 8) its covariance
    beta: jax.Array  # () sideslip arctan(v_y / v_x) (rad)
    innovation: jax.Array  # (4,) (a_x, a_y, r', v_x,ref) minus the model at the prior (0 where skipped)


def _process(constants, x, u, t):
    """The Euler map ``x + dt f(x, u)`` of the process model (module docstring); ``constants = (dt, tau)``."""
    dt, tau = constants
    ax, ay, r = u
    vx, vy, _, _, _, d_i, d_b, d_mu = x
    rate = jnp.stack([ax + r * vy + GRAVITY * x[2], ay - r * vx - GRAVITY * x[3], d_i, d_b, d_mu,
                      -d_i / tau, -d_b / tau, -d_mu / tau])  # fmt: skip
    return x + dt * rate


def _measurement(vehicle, mu_bounds, sensors, x):
    """``(a_x, a_y, r', v_x)`` of the friction model at the state ``x`` and the current ``sensors``."""
    ax, ay = sensors[_AX], sensors[_AY] / (1.0 + vehicle.roll_gradient * GRAVITY)
    mu = jnp.clip(x[4], mu_bounds[0], mu_bounds[1])
    f = friction_model(vehicle, x[0], x[1], sensors[_R], sensors[_SW], sensors[_OMEGA], ax, ay, mu)
    return jnp.stack([f.ax, f.ay, f.yaw_moment / vehicle.yaw_inertia, x[0]])


def make_vehicle_ekf(
    vehicle: VehicleParams | None = None,
    *,
    bierman: bool = False,
    q_v: float = 0.3,
    q_d=(0.005, 0.005, 0.05),
    tau: float = 1.0,
    r_std=(0.3, 0.3, 0.3, 0.1),
    vx0: float = 20.0,
    P0_diag=(1.0, 1.0, 1e-3, 1e-3, 0.05, 1e-5, 1e-5, 1e-3),
    mu0: float = 1.0,
    mu_bounds=(0.05, 1.5),
    dt: float = 1.0 / SENSOR_RATE,
) -> VehicleEKFParams:
    """The EKF of Grip 2010 §2.9 for ``vehicle`` (default :class:`~jaxobs.vehicle.VehicleParams`).

    Args:
      vehicle: the vehicle whose friction model the filter uses.
      bierman: Bierman's U-D measurement update (:func:`jaxobs.kalman_steps.bierman_update`) instead of Joseph.
      q_v: process noise of the velocity equations (m/s^2, > 0).  q_d: (3,) intensities of the white noises that
        drive ``d_i``, ``d_b``, ``d_mu`` (> 0).  tau: their filters' time constant (s, > 0).
      r_std: (4,) measurement standard deviations of ``a_x``, ``a_y`` (m/s^2), ``r'`` (rad/s^2), ``v_x,ref``
        (m/s) (> 0; they include the friction model's error).
      vx0: prior mean of ``v_x`` (m/s); the other means are 0 and ``mu0``.  P0_diag: (8,) prior variances (>= 0).
      mu_bounds: (lo, hi) with ``0 < lo < hi``: the friction range the model is evaluated at.
      dt: sample period (s, > 0).

    Example:
      >>> from jaxobs.vehicle.ekf import make_vehicle_ekf
      >>> params = make_vehicle_ekf(bierman=True)
      >>> params.ekf.bierman, params.ekf.model.x0.shape
      (True, (8,))
    """
    vehicle = VehicleParams() if vehicle is None else vehicle
    if not isinstance(vehicle, VehicleParams):
        raise ValueError(f"vehicle must be a VehicleParams, got {type(vehicle).__name__}")
    vehicle.validate()
    for name, value in (("q_v", q_v), ("q_d", q_d), ("tau", tau), ("r_std", r_std), ("dt", dt)):
        _checks.positive(name, value)
    _checks.positive("P0_diag", P0_diag, allow_zero=True)
    _checks.positive("mu0", mu0)
    q_d, r_std, P0_diag = jnp.asarray(q_d, float), jnp.asarray(r_std, float), jnp.asarray(P0_diag, float)
    _checks.shape("q_d", q_d, (3,), "one intensity per derivative state")
    _checks.shape("r_std", r_std, (4,), "one per measurement (a_x, a_y, r', v_x,ref)")
    _checks.shape("P0_diag", P0_diag, (8,), "one variance per state")
    mu_bounds = jnp.asarray(mu_bounds, float)
    _checks.shape("mu_bounds", mu_bounds, (2,), "(lo, hi)")
    _checks.positive("mu_bounds", mu_bounds)
    if _checks.is_concrete(mu_bounds) and not bool(mu_bounds[0] < mu_bounds[1]):
        raise ValueError(f"mu_bounds must have lo < hi, got {mu_bounds.tolist()}")
    Q = dt * jnp.diag(jnp.concatenate([jnp.full(2, q_v**2), jnp.zeros(3), q_d**2]))
    x0 = jnp.zeros(8).at[0].set(vx0).at[4].set(mu0)
    f = Partial(_process, (jnp.asarray(dt, float), jnp.asarray(tau, float)))
    h = Partial(_measurement, vehicle, mu_bounds, jnp.zeros(N_SENSORS))
    model = nonlinear_model(f, h, Q, jnp.diag(r_std**2), x0=x0, P0=jnp.diag(P0_diag), n_inputs=3, dt=dt)
    return VehicleEKFParams(vehicle, make_ekf(model, bierman=bierman), mu_bounds)


def _init(params: VehicleEKFParams) -> VehicleEKFState:
    model = params.ekf.model
    sensors = jnp.zeros((N_SENSORS,), model.x0.dtype).at[_VREF].set(model.x0[0])
    sensors = sensors.at[_OMEGA].set(model.x0[0] / params.vehicle.wheel_radius)
    return VehicleEKFState(extended_kalman_filter.init(params.ekf), sensors, jnp.zeros((), jnp.int32))


def _step(params: VehicleEKFParams, state: VehicleEKFState, inputs: EstimatorInputs):
    model, vehicle = params.ekf.model, params.vehicle
    dtype = model.x0.dtype
    y = _checks.vector("inputs.y", inputs.y, N_SENSORS, dtype, what="the vehicle's sensors", check_finite=False)
    finite = jnp.isfinite(y)
    sensors = jnp.where(finite, y, state.sensors)
    previous = state.sensors
    roll = 1.0 + vehicle.roll_gradient * GRAVITY
    u_prev = jnp.stack([previous[_AX], previous[_AY] / roll, previous[_R]])
    # r' needs two finite yaw-rate samples; NaN (skipped by the EKF) otherwise and at the first sample
    yaw_acc = jnp.where(state.filter.started & finite[_R], (y[_R] - previous[_R]) / model.dt, jnp.nan)
    z = jnp.stack([y[_AX], y[_AY] / roll, yaw_acc, y[_VREF]])
    h = Partial(_measurement, vehicle, params.mu_bounds, sensors)
    ekf = dataclasses.replace(params.ekf, model=dataclasses.replace(model, h=h))
    filt, out = extended_kalman_filter.step(ekf, state.filter, EstimatorInputs(y=z, u_prev=u_prev))
    missing = state.missing + jnp.sum(~finite).astype(jnp.int32)
    beta = jnp.arctan2(out.x[1], out.x[0])
    return VehicleEKFState(filt, sensors, missing), VehicleEKFOutputs(out.x, out.P, beta, out.innovation)


vehicle_ekf = Estimator(_init, _step)
"""The vehicle EKF (module docstring) as an :class:`~jaxobs.observers.base.Estimator` over
:class:`VehicleEKFParams`. Inputs: ``EstimatorInputs(y)`` with the sensors ``y`` (:data:`jaxobs.vehicle.N_SENSORS`,)
(:func:`jaxobs.vehicle.sensor_inputs`). State: :class:`VehicleEKFState`. Outputs: :class:`VehicleEKFOutputs`."""
