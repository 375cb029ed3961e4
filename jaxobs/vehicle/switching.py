"""The friction-estimation switch of Grip 2010 §2.5, shared by the NVSO (:mod:`jaxobs.vehicle.nvso`) and the EKF
baseline of §2.9 (:mod:`jaxobs.vehicle.ekf`), with the gates it is built of.

Friction estimation turns on when (i) ``|HP(a_y - r v_x)| > vy_dot_threshold`` (``HP`` a high-pass of time
constant ``high_pass_time``) and the reference yaw rate ``r_ref = v_x delta / (L + K_us v_x^2)`` of the linear
single track exceeds ``yaw_rate_threshold``, or (ii) the car oversteers (``(|r| -+ |r_ref|) v_x >
oversteer_threshold`` for ``r`` and ``r_ref`` of the same or of opposite signs), or (iii) the ESC intervenes but not
for steady-state understeer (understeer ``(|r_ref| - |r|) v_x > understeer_threshold`` with ``r`` and ``r_ref`` of
the same sign while the high-pass test of (i) fails); it turns off ``off_delay`` seconds after the last sample with
(i), (ii) or (iii). The details: docs/theory/vehicle.md (the NVSO).

``smooth``: ``None`` for exact switches; a positive sharpness ``k`` replaces every switch ``x > c`` by the gate
``sigmoid(k (x - c) / scale)``, so that thresholds get gradients.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.vehicle.model import VehicleParams, check_vehicle, reference_yaw_rate
from jaxobs.vehicle.sensors import SENSOR_RATE

__all__ = ["SwitchingParams", "make_switching", "Switching", "switching", "gate", "either"]


class SwitchingParams(NamedTuple):
    """Thresholds of the switch (module docstring); build with :func:`make_switching`. The NVSO's
    :class:`~jaxobs.vehicle.NVSOParams` has the same fields with the same defaults, so :func:`switching` takes it
    too.

    Attributes:
      vehicle: the :class:`~jaxobs.vehicle.VehicleParams` of the reference yaw rate.
      vy_dot_threshold, yaw_rate_threshold, oversteer_threshold, off_delay, high_pass_time: (m/s^2, rad/s, m/s^2,
        s, s).  understeer_threshold: the steady-state understeer that condition (iii) leaves out (m/s^2).
        accel_margin: the 1.2 of ``accel_margin g mu >= |(a_x, a_y)|`` (the least friction the accelerations show).
        dt: sample period (s).  smooth: ``None`` (exact switches) or the gate sharpness (> 0).
    """

    vehicle: VehicleParams
    vy_dot_threshold: jax.Array = 1.0
    yaw_rate_threshold: jax.Array = 0.1
    oversteer_threshold: jax.Array = 1.0
    off_delay: jax.Array = 0.5
    high_pass_time: jax.Array = 10.0
    understeer_threshold: jax.Array = 1.0
    accel_margin: jax.Array = 1.2
    dt: jax.Array = 1.0 / SENSOR_RATE
    smooth: jax.Array | None = None


def make_switching(vehicle: VehicleParams | None = None, **settings) -> SwitchingParams:
    """The switch for ``vehicle`` (default :class:`~jaxobs.vehicle.VehicleParams`) with the defaults of
    :class:`SwitchingParams` overridden by ``settings`` (``ValueError`` for an unknown field; concrete values
    positive, ``smooth`` ``None`` or positive)."""
    vehicle = check_vehicle(vehicle)
    fields = list(SwitchingParams._fields[1:])
    unknown = sorted(set(settings) - set(fields))
    if unknown:
        raise ValueError(f"unknown switching settings {unknown}; the fields are {fields}")
    for name, value in settings.items():
        if name != "smooth" or value is not None:
            _checks.positive(name, value)
    return SwitchingParams(vehicle, **settings)


def gate(smooth, x, threshold, scale):
    """``x > threshold`` as 0/1 (``smooth`` ``None``), or its sigmoid of sharpness ``smooth`` on the given
    ``scale``."""
    x, threshold, scale = _checks.float_arrays(x=x, threshold=threshold, scale=scale)
    if smooth is None:
        return (x > threshold).astype(jnp.result_type(x, float))
    return jax.nn.sigmoid(smooth * (x - threshold) / scale)


def either(*gates):
    """Logical or of 0/1 values (or gates): ``1 - prod(1 - g)``."""
    gates = _checks.float_arrays(**{f"gates[{i}]": g for i, g in enumerate(gates)})
    out = 1.0 - gates[0]
    for g in gates[1:]:
        out = out * (1.0 - g)
    return 1.0 - out


class Switching(NamedTuple):
    """Result of :func:`switching`: the mode of the next interval, the filter and timer states, and the understeer
    with the "same sign" test it used (the NVSO's ``K_theta_b`` reduction (3) gates the same understeer).

    Attributes:
      mode: () 1: friction estimation on (a gate value when smooth)
      off_timer: () time since the conditions last held (s)
      low_pass: () the high-pass filter's low-pass state
      understeer: () ``(|r_ref| - |r|) v_x`` with ``r_ref`` the linear single track's reference yaw rate (m/s^2)
      same_sign: () r and r_ref of the same sign (outside the dead band)
    """

    mode: jax.Array
    off_timer: jax.Array
    low_pass: jax.Array
    understeer: jax.Array
    same_sign: jax.Array


def switching(params, off_timer, low_pass, vx, r, ay, steering_wheel, esc_active) -> Switching:
    """The friction-estimation switch of Grip 2010 §2.5 (module docstring), shared by the NVSO and the EKF baseline
    of §2.9: from the timer and high-pass states of the last sample, the estimated ``vx``, the measured yaw rate
    ``r``, roll-corrected ``ay``, steering-wheel angle and ESC status (0/1), with the thresholds (and ``smooth``) of
    ``params``, a :class:`SwitchingParams` or an :class:`~jaxobs.vehicle.NVSOParams`. One sample: the seven
    values are scalars (``vmap`` for a batch), checked at trace time."""
    _checks.fields("params", params, ", ".join(f"{name} ()" for name in SwitchingParams._fields[1:-1]))
    check_vehicle(params.vehicle, "params.vehicle")
    _checks.shapes("off_timer (), low_pass (), vx (), r (), ay (), steering_wheel (), esc_active ()",
                   off_timer, low_pass, vx, r, ay, steering_wheel, esc_active)  # fmt: skip
    dt = params.dt
    r_ref = reference_yaw_rate(params.vehicle, vx, steering_wheel)
    high_pass = ay - r * vx - low_pass
    dead_band = (params.yaw_rate_threshold / 10) ** 2  # "same sign" excludes zero yaw rates (no tie at r_ref = 0)
    same_sign = gate(params.smooth, r * r_ref, dead_band, dead_band)
    smooth = params.smooth
    lateral_motion = gate(smooth, jnp.abs(high_pass), params.vy_dot_threshold, params.vy_dot_threshold)
    excited = lateral_motion * gate(smooth, jnp.abs(r_ref), params.yaw_rate_threshold, params.yaw_rate_threshold)
    opposite = gate(params.smooth, -r * r_ref, dead_band, dead_band)  # counter-steering: the car yaws against the wheel
    threshold = params.oversteer_threshold
    understeer = (jnp.abs(r_ref) - jnp.abs(r)) * vx  # < 0: the car yaws more than the reference
    oversteer = either(
        same_sign * gate(params.smooth, -understeer, threshold, threshold),
        opposite * gate(params.smooth, (jnp.abs(r) + jnp.abs(r_ref)) * vx, threshold, threshold),
    )
    steady_understeer = (
        same_sign
        * (1.0 - lateral_motion)
        * gate(smooth, understeer, params.understeer_threshold, params.understeer_threshold)
    )
    esc = esc_active * (1.0 - steady_understeer)
    on = either(excited, oversteer, esc)
    # on while (i), (ii) or (iii) holds and off_delay after; the half sample keeps the comparison off ties at k dt
    timer = (1.0 - on) * (off_timer + dt)
    mode = gate(params.smooth, params.off_delay + dt / 2 - timer, 0.0, params.off_delay)
    low_pass = low_pass + dt / params.high_pass_time * high_pass
    return Switching(mode, timer, low_pass, understeer, same_sign)
