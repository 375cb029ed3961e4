"""The nonlinear vehicle sideslip observer (NVSO) of Grip 2010 ch. 2 (Grip, Imsland, Johansen, Kalkkuhl & Suissa
2009), run on the ESC sensors of :mod:`jaxobs.vehicle.sensors` as an :class:`~jaxobs.observers.base.Estimator`.

It estimates ``v_x``, ``v_y``, the friction ``theta`` (``peak_friction``), the inclination and the bank with two
modes, friction estimation off and on (2.18)-(2.27), switched by the logic of §2.5
(:mod:`jaxobs.vehicle.switching`), discretised by forward Euler at the sensor period (§2.8), with the
tyre-relaxation filter of §2.8 on the friction model's output. ``smooth`` replaces every switch by a sigmoid gate so
that gains and thresholds get gradients. :func:`make_nvso`, :data:`nvso`. The equations, the switches, the standstill
guard and the departures from §2.8: docs/theory/vehicle.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.observers.base import Estimator, EstimatorInputs
from jaxobs.vehicle.model import GRAVITY, MIN_SPEED, VehicleParams, check_vehicle, friction_model
from jaxobs.vehicle.sensors import AX, AY, ESC_ACTIVE, N_SENSORS, STEERING_WHEEL, VX_REF, WHEEL_SPEED, YAW_RATE
from jaxobs.vehicle.switching import SwitchingParams, either, gate, switching

_SWITCHING = SwitchingParams._field_defaults  # the thresholds the EKF baseline shares

__all__ = ["NVSOParams", "NVSOState", "NVSOOutputs", "make_nvso", "nvso"]


class NVSOParams(NamedTuple):
    """Gains, thresholds and bounds of the NVSO (docs/theory/vehicle.md); build with :func:`make_nvso`. Every field is a
    leaf (``smooth=None`` has none), so the params can be batched, differentiated and tuned.

    Attributes:
      vehicle: the :class:`~jaxobs.vehicle.VehicleParams` of the friction model.
      K_vx, K_vx_min: nominal and least longitudinal gain (1/s).  wheel_spread: the wheel-velocity spread that
        halves ``K_vx`` (m/s).
      K_vy: lateral injection gain.  K_theta: friction adaptation gain (1/(m/s^2 s)).  K_e: attraction of
        ``theta`` to ``theta_default`` in mode 1 (1/s).
      K_theta_i, K_theta_i_on: inclination gains of modes 1 and 2 (dimensionless, times ``K_vx``).
      K_theta_b: bank gain (rad / (m/s^2 s)).  theta_b_reduction: factor on ``K_theta_b`` when a reduction holds.
      c1 (m/s^2), c2 (rad/s^2), c3 (m/s^2): the ``K_theta_b`` reduction thresholds.
      theta_default: ``theta*``.  theta_min, theta_max: the clip bounds.  accel_margin: the 1.2 of
        ``accel_margin g theta >= |(a_x, a_y)|``.
      vy_dot_threshold, yaw_rate_threshold, oversteer_threshold, off_delay, high_pass_time, understeer_threshold:
        the switching logic of :mod:`jaxobs.vehicle.switching`, with the defaults of its
        :class:`~jaxobs.vehicle.SwitchingParams` (m/s^2, rad/s, m/s^2, s, s, m/s^2).
      min_speed: standstill guard (m/s).  dt: sample period (s).  vx0: initial ``v_x`` used before the first
        finite ``v_x,ref`` (m/s).
      relaxation_length: ``l_e`` of the tyre-relaxation filter (m, >= 0), Grip 2010 §2.8 (and §4.7): the friction
        model's output (``a_y*`` and the yaw acceleration ``psi''*``) is filtered by ``1 / (T s + 1)`` with the
        speed-dependent ``T = T_e + l_e / v_x_hat`` (Pacejka 2006, ch. 1; the thesis gives no values). The default
        (0.5 in :class:`NVSOParams`; :func:`make_nvso` takes the vehicle's ``relaxation_length``) matches the
        simulator's tyres (:class:`~jaxobs.vehicle.VehicleParams`, ``tan_alpha' = (v / l_relax)(tan_alpha_ss -
        tan_alpha)``, the same lag ``l / v`` in the linear range). 0 (with ``relaxation_time`` 0) switches the filter
        off: the model output is used as it is.
      relaxation_time: ``T_e`` of the same filter (s, >= 0); 0 assumed (the simulator has no lag beyond ``l / v``).
      peak_friction: 1 (default): ``theta`` is the friction model's road-tyre friction coefficient ``mu_H``, as in
        Imsland et al. 2007, so the tyre curve's shape (the slip of its peak) follows it, with the regressor
        ``a_y^ / theta`` in (2.25) (the sign of ``d a_y^ / d mu_H``, Grip 2010 Prop. 5.3); 0: ``theta`` scales the
        friction-1 model, ``a_y^ = theta a_y*``, as Grip 2010 §2.4.1 chooses for a simpler analysis ("variation in
        mu_H does not correspond precisely to a scaling of the friction forces"). In ``[0, 1]``; values between
        blend the two (a leaf, so it batches like the others).
    """

    vehicle: VehicleParams
    K_vx: jax.Array = 1.0
    K_vx_min: jax.Array = 0.3
    wheel_spread: jax.Array = 0.5
    K_vy: jax.Array = 1.0
    K_theta: jax.Array = 3.0
    K_e: jax.Array = 0.5
    K_theta_i: jax.Array = 0.02
    K_theta_i_on: jax.Array = 0.005
    K_theta_b: jax.Array = 0.05
    theta_b_reduction: jax.Array = 0.1
    c1: jax.Array = 1.0
    c2: jax.Array = 0.5
    c3: jax.Array = 1.0
    theta_default: jax.Array = 1.0
    theta_min: jax.Array = 0.05
    theta_max: jax.Array = 1.1
    accel_margin: jax.Array = _SWITCHING["accel_margin"]
    vy_dot_threshold: jax.Array = _SWITCHING["vy_dot_threshold"]
    yaw_rate_threshold: jax.Array = _SWITCHING["yaw_rate_threshold"]
    oversteer_threshold: jax.Array = _SWITCHING["oversteer_threshold"]
    off_delay: jax.Array = _SWITCHING["off_delay"]
    high_pass_time: jax.Array = _SWITCHING["high_pass_time"]
    understeer_threshold: jax.Array = _SWITCHING["understeer_threshold"]
    min_speed: jax.Array = MIN_SPEED
    dt: jax.Array = _SWITCHING["dt"]
    vx0: jax.Array = 20.0
    smooth: jax.Array | None = None
    relaxation_length: jax.Array = VehicleParams.relaxation_length
    relaxation_time: jax.Array = 0.0
    peak_friction: jax.Array = 1.0


_POSITIVE = (
    "K_vx", "K_vx_min", "wheel_spread", "K_vy", "K_theta", "K_e", "c1", "c2", "c3", "theta_default", "theta_max",
    "accel_margin", "vy_dot_threshold", "yaw_rate_threshold", "oversteer_threshold", "off_delay", "high_pass_time",
    "understeer_threshold", "min_speed", "dt",
)  # fmt: skip
_NON_NEGATIVE = ("K_theta_i", "K_theta_i_on", "K_theta_b", "theta_b_reduction", "theta_min", "vx0", "relaxation_length",
                 "relaxation_time", "peak_friction")  # fmt: skip


def make_nvso(vehicle: VehicleParams | None = None, **settings) -> NVSOParams:
    """The NVSO for ``vehicle`` (default :class:`~jaxobs.vehicle.VehicleParams`) with the defaults of
    :class:`NVSOParams` (assumed: Grip 2010 ch. 2 gives no values) overridden by ``settings``.

    Args:
      vehicle: the vehicle whose friction model the observer uses.
      settings: any field of :class:`NVSOParams` (``ValueError`` for an unknown one). Concrete values are checked:
        gains, thresholds and times positive (``ValueError`` naming the field); ``theta_min < theta_max``;
        ``smooth`` ``None`` or positive. ``relaxation_length`` defaults to ``vehicle.relaxation_length`` (the
        filter of §2.8 matches the simulated tyres); pass 0 to switch the filter off.

    Example:
      >>> from jaxobs.vehicle import make_nvso
      >>> params = make_nvso(K_vy=0.8, smooth=50.0)
      >>> float(params.K_vy), float(params.smooth)
      (0.8, 50.0)
    """
    vehicle = check_vehicle(vehicle)
    unknown = sorted(set(settings) - set(NVSOParams._fields[1:]))
    if unknown:
        raise ValueError(f"unknown NVSO settings {unknown}; the fields are {list(NVSOParams._fields[1:])}")
    for name in _POSITIVE:
        if name in settings:
            _checks.positive(name, settings[name])
    for name in _NON_NEGATIVE:
        if name in settings:
            _checks.positive(name, settings[name], allow_zero=True)
    settings.setdefault("relaxation_length", vehicle.relaxation_length)
    params = NVSOParams(vehicle, **settings)
    lo, hi = params.theta_min, params.theta_max
    if _checks.is_concrete(lo, hi) and not np.all(np.asarray(lo) < np.asarray(hi)):  # NumPy: no tracer under jit
        raise ValueError(f"theta_min must be below theta_max (the bounds of theta), got {lo!r} >= {hi!r}")
    if params.smooth is not None:
        _checks.positive("smooth", params.smooth)
    if _checks.is_concrete(params.peak_friction) and not np.all(np.asarray(params.peak_friction) <= 1):
        raise ValueError(f"peak_friction must lie in [0, 1] (1: theta is mu_H), got {params.peak_friction!r}")
    return params


class NVSOState(NamedTuple):
    """State of :data:`nvso` between samples.

    Attributes:
      x: (5,) estimate (v_x, v_y, theta, theta_i, theta_b) at t_{k-1}
      mode: () friction estimation on (1) / off (0); a gate value in [0, 1] when smooth
      off_timer: () time since the switching conditions last held (s)
      low_pass: () the low-pass part of the high-pass filter of a_y - r v_x
      relaxed: (2,) the friction model's ``a_y`` and ``psi''`` after the tyre-relaxation filter (§2.8), at
        t_{k-1}: at the friction ``theta`` (``peak_friction``), at 1 otherwise
      y: (N_SENSORS,) last finite measurement (held over the next interval)
      started: () bool: a sample has been processed (the first step outputs the initial estimate)
      missing: () int32, non-finite sensor samples skipped so far
    """

    x: jax.Array
    mode: jax.Array
    off_timer: jax.Array
    low_pass: jax.Array
    relaxed: jax.Array
    y: jax.Array
    started: jax.Array
    missing: jax.Array


class NVSOOutputs(NamedTuple):
    """Outputs of one sample of :data:`nvso`.

    Attributes:
      x: (5,) (v_x, v_y, theta, theta_i, theta_b) at t_k
      beta: () sideslip arctan(v_y / max(v_x, min_speed)) (rad)
      mode: () the mode used over the interval
      innovation: (2,) (v_x,ref - v_x, a_y - a_y^) that drove the interval
      xi: () d a_y* / d v_y (1/s)
      regressor: () the regressor of the update law (2.25) before ``Lambda``: ``a_y^ / theta``, the relaxed
        ``a_y*`` when ``theta`` scales the model (m/s^2)
      K_theta_b: () the bank gain used (after reductions)
    """

    x: jax.Array
    beta: jax.Array
    mode: jax.Array
    innovation: jax.Array
    xi: jax.Array
    regressor: jax.Array
    K_theta_b: jax.Array


def _init(params: NVSOParams) -> NVSOState:
    check_vehicle(params.vehicle, "params.vehicle")  # one observer, checked at trace time: vmap for a batch
    _checks.fields("params", params, ", ".join(f"{name} ()" for name in NVSOParams._fields[1:]))
    dtype = jnp.result_type(params.vx0, params.theta_default, params.vehicle.mass, float)  # the vehicle's precision
    v = params.vehicle
    vx0 = jnp.asarray(params.vx0, dtype)
    y = jnp.zeros((N_SENSORS,), dtype).at[WHEEL_SPEED].set(vx0 / v.wheel_radius).at[VX_REF].set(vx0)
    x = jnp.stack([vx0, 0.0 * vx0, jnp.asarray(params.theta_default, dtype), 0.0 * vx0, 0.0 * vx0])
    zero = jnp.zeros((), dtype)
    return NVSOState(x, zero, jnp.asarray(params.off_delay, dtype), zero, jnp.zeros((2,), dtype), y,
                     jnp.zeros((), bool), jnp.zeros((), jnp.int32))  # fmt: skip


def _longitudinal_gain(params: NVSOParams, sw, omega, r) -> jax.Array:
    """K_vx, lowered by the spread of the four wheels' longitudinal velocities (wheel speeds ``omega`` (4,), steering
    wheel angle ``sw``, yaw rate ``r``): spinning or locked wheels make v_x,ref less trustworthy."""
    v = params.vehicle
    delta = sw / v.steering_ratio
    half_f, half_r = v.track_front / 2, v.track_rear / 2
    lateral = jnp.stack(jnp.broadcast_arrays(half_f, -half_f, half_r, -half_r))
    steer = jnp.stack([jnp.cos(delta), jnp.cos(delta), jnp.ones_like(delta), jnp.ones_like(delta)])
    wheel_vx = omega * v.wheel_radius / steer + r * lateral
    spread = jnp.sqrt(jnp.mean((wheel_vx - jnp.mean(wheel_vx)) ** 2) + 1e-12)
    return jnp.maximum(params.K_vx_min, params.K_vx / (1.0 + (spread / params.wheel_spread) ** 2))


def _step(params: NVSOParams, state: NVSOState, inputs: EstimatorInputs):
    v, dt = params.vehicle, params.dt
    dtype = state.x.dtype
    y = _checks.vector("inputs.y", inputs.y, N_SENSORS, dtype, what="the NVSO's sensors", check_finite=False)
    finite = jnp.isfinite(y)
    y_now = jnp.where(finite, y, state.y)
    missing = state.missing + jnp.sum(~finite).astype(jnp.int32)

    m = state.y  # the measurement held over [t_{k-1}, t_k]
    ax, ay, r, sw, omega, vref = m[AX], m[AY], m[YAW_RATE], m[STEERING_WHEEL], m[WHEEL_SPEED], m[VX_REF]
    roll = 1.0 + v.roll_gradient * GRAVITY
    ay = ay / roll  # roll correction, Grip 2010 §2.2
    vx, vy, theta, theta_i, theta_b = state.x

    # theta is the model's friction mu_H (peak_friction = 1: the tyre curve's shape follows it) or a factor on the
    # friction-1 model (0: a_y^ = theta a_y*, (2.25) as printed). xi, the direction of the a_y injections (2.24)
    # and (2.27), is always the friction-1 model's slope, which does not vanish where a low-friction tyre saturates.
    p = params.peak_friction
    friction, scale = p * theta + (1.0 - p), p + (1.0 - p) * theta

    def model(vy, friction):
        f = friction_model(v, vx, vy, r, sw, omega, ax, ay, friction)
        return jnp.stack([f.ay, f.yaw_moment / v.yaw_inertia])

    _, (xi, _) = jax.jvp(lambda vy: model(vy, 1.0), (vy,), (jnp.ones_like(vy),))
    static = model(vy, friction)
    # tyre relaxation (Grip 2010 §2.8): the model output through 1 / (T s + 1), T = T_e + l_e / v_x, discretised
    # exactly for the model output held over the interval and taken at its end (T = 0: no filter, alpha = 1).
    T = params.relaxation_time + params.relaxation_length / jnp.maximum(vx, params.min_speed)
    alpha = -jnp.expm1(-dt / jnp.maximum(T, 1e-3 * dt))  # floor: alpha = 1 - e^-1000 = 1, finite gradients
    alpha = jnp.where(state.started, alpha, 1.0)  # starts at the model's output at the (straight) initial estimate
    relaxed = state.relaxed + alpha * (static - state.relaxed)
    ay_model, yaw_acc_model = scale * relaxed
    # the regressor of (2.25): a_y^ per unit friction, a_y* itself when theta scales the model. For theta = mu_H it
    # has the sign of d a_y^ / d mu_H (a_y^ grows with mu_H at every slip) without its vanishing in the linear
    # range: the monotone numerical search of Grip 2010 Prop. 5.3
    regressor = ay_model / jnp.maximum(theta, params.theta_min)
    lam = jax.lax.rsqrt(jnp.maximum(xi**2 + regressor**2, 1e-12))
    e = ay - ay_model

    K_vx = _longitudinal_gain(params, sw, omega, r)

    # switching logic (§2.5) and the K_theta_b reductions (§2.7)
    switch = switching(params, state.off_timer, state.low_pass, vx, r, ay, sw, m[ESC_ACTIVE])
    yaw_acc = (y_now[YAW_RATE] - r) / dt
    reduce = either(
        gate(params.smooth, jnp.abs(e), params.c1, params.c1),
        gate(params.smooth, jnp.abs(yaw_acc - yaw_acc_model), params.c2, params.c2),
        switch.same_sign * gate(params.smooth, switch.understeer, params.c3, params.c3),
    )
    K_theta_b = params.K_theta_b * (1.0 - reduce * (1.0 - params.theta_b_reduction))
    moving = gate(params.smooth, vx, params.min_speed, params.min_speed)

    # the two modes (2.18)-(2.27), blended by the mode of the interval
    mode = state.mode
    kinematic_x = ax + r * vy + GRAVITY * theta_i + K_vx * (vref - vx)
    kinematic_y = ay - r * vx - GRAVITY * theta_b
    injection = (1.0 - mode) * (-params.K_vy * e) + mode * params.K_vy * lam * xi * e
    d_vy = moving * (kinematic_y + injection) - (1.0 - moving) * K_vx * vy
    d_theta_off = params.K_e * (params.theta_default - theta)
    d_theta = (1.0 - moving * mode) * d_theta_off + moving * mode * params.K_theta * lam * regressor * e
    K_theta_i = (1.0 - mode) * params.K_theta_i + mode * params.K_theta_i_on
    d_theta_i = K_theta_i * K_vx * (vref - vx)
    d_theta_b = moving * K_theta_b * ((1.0 - mode) * e - mode * lam * xi * e)
    x = state.x + dt * jnp.stack([kinematic_x, d_vy, d_theta, d_theta_i, d_theta_b])
    lower = jnp.maximum(params.theta_min, jnp.hypot(ax, ay) / (params.accel_margin * GRAVITY))
    x = x.at[2].set(jnp.clip(x[2], jnp.minimum(lower, params.theta_max), params.theta_max))

    next_mode, timer, low_pass = switch.mode, switch.off_timer, switch.low_pass

    first = ~state.started
    x0 = state.x.at[0].set(y_now[VX_REF])
    x = jnp.where(first, x0, x)
    next_mode = jnp.where(first, state.mode, next_mode)
    timer = jnp.where(first, state.off_timer, timer)
    low_pass = jnp.where(first, y_now[AY] / roll - y_now[YAW_RATE] * y_now[VX_REF], low_pass)  # HP starts at 0
    new_state = NVSOState(x, next_mode, timer, low_pass, relaxed, y_now, jnp.ones((), bool), missing)
    beta = jnp.arctan2(x[1], jnp.maximum(x[0], params.min_speed))
    outputs = NVSOOutputs(x, beta, mode, jnp.stack([vref - vx, e]), xi, regressor, K_theta_b)
    return new_state, outputs


nvso = Estimator(_init, _step)
"""The NVSO (docs/theory/vehicle.md) as an :class:`~jaxobs.observers.base.Estimator` over :class:`NVSOParams`.

Inputs: ``EstimatorInputs(y)`` with ``y`` (:data:`~jaxobs.vehicle.N_SENSORS`,) (:func:`~jaxobs.vehicle.sensor_inputs`);
``u_prev`` is unused.
State: :class:`NVSOState`. Outputs: :class:`NVSOOutputs`."""
