"""ESC-type sensors (Grip 2010 §2.1, §2.8): accelerometers, yaw-rate gyro, steering-wheel angle, wheel speeds and
a longitudinal reference velocity, sampled at 100 Hz with bias, drift, noise and the 15 Hz low-pass.

:func:`measure` samples a trajectory (the lateral accelerometer rolls with the body, Grip 2010 §2.2; ``v_x,ref``
from the front wheel speeds stands in for the algorithms Grip 2010 §2.3 assumes given); :data:`N_SENSORS` and the
column indices :data:`AX` .. :data:`VX_REF` lay out the sensor vector the observers take (:func:`sensor_inputs`).
The sensor model: docs/theory/vehicle.md.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.observers.base import EstimatorInputs
from jaxobs.vehicle.model import GRAVITY, VehicleParams, check_vehicle
from jaxobs.vehicle.simulate import PLANT_STEP, Trajectory

__all__ = [
    "SENSOR_RATE",
    "N_SENSORS",
    "AX",
    "AY",
    "YAW_RATE",
    "STEERING_WHEEL",
    "WHEEL_SPEED",
    "VX_REF",
    "ESC_ACTIVE",
    "SensorParams",
    "Measurements",
    "measure",
    "low_pass",
    "sensor_inputs",
]

SENSOR_RATE = 100.0
"""ESC sensor rate (Hz), the 10 ms sample time of Grip 2010 §2.8."""

N_SENSORS = 10
"""Entries of the sensor vector the vehicle observers take: ``a_x``, ``a_y``, yaw rate, steering-wheel angle, the
four wheel speeds (FL, FR, RL, RR), ``v_x,ref`` and the ESC's status (1 while it intervenes; :func:`sensor_inputs`)."""
AX, AY, YAW_RATE, STEERING_WHEEL, WHEEL_SPEED, VX_REF, ESC_ACTIVE = 0, 1, 2, 3, slice(4, 8), 8, 9
"""Where each measurement sits in the sensor vector (``WHEEL_SPEED`` a slice of the four wheels)."""

_CHANNELS = ("ax", "ay", "yaw_rate", "steering_wheel", "wheel_speed")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SensorParams:
    """Errors of the ESC sensors (defaults assumed for automotive-grade sensors: white noise only; Grip 2010
    §2.8 gives bias + drift maxima of 1.0 m/s^2 (0.6 on low friction) for the accelerometers and 3.5 deg/s for
    the yaw rate, to be set per experiment).

    Attributes:
      bias_ax, bias_ay: accelerometer biases (m/s^2).  bias_yaw_rate: gyro bias (rad/s).
      bias_steering: steering-wheel angle offset (rad).
      drift_acc: random-walk intensity of both accelerometers (m/s^2 per sqrt(s), >= 0).
      drift_yaw_rate: of the gyro (rad/s per sqrt(s), >= 0).
      noise_acc: white-noise standard deviation of the accelerometers (m/s^2, >= 0); 0.05 assumed.
      noise_yaw_rate: of the gyro (rad/s, >= 0); 0.002 assumed (0.1 deg/s).
      noise_steering: of the steering-wheel angle (rad, >= 0); 0.002 assumed.
      noise_wheel: of each wheel speed (rad/s, >= 0); 0.1 assumed.
      cutoff: corner frequency ``f_c`` of the low-pass (Hz, > 0; ``inf`` for none); 15 Hz (Grip 2010 §2.8).
    """

    bias_ax: float = 0.0
    bias_ay: float = 0.0
    bias_yaw_rate: float = 0.0
    bias_steering: float = 0.0
    drift_acc: float = 0.0
    drift_yaw_rate: float = 0.0
    noise_acc: float = 0.05
    noise_yaw_rate: float = 0.002
    noise_steering: float = 0.002
    noise_wheel: float = 0.1
    cutoff: float = 15.0

    def validate(self) -> None:
        """Raise ``ValueError`` naming the bad field (concrete values only; skipped under tracing)."""
        for name in ("bias_ax", "bias_ay", "bias_yaw_rate", "bias_steering"):
            _checks.finite(name, getattr(self, name))
        for name in ("drift_acc", "drift_yaw_rate", "noise_acc", "noise_yaw_rate", "noise_steering", "noise_wheel"):
            _checks.positive(name, getattr(self, name), allow_zero=True)
        if _checks.is_concrete(self.cutoff) and not np.all(np.asarray(self.cutoff) > 0):
            raise ValueError(f"cutoff must be positive (Hz, inf for no low-pass), got {self.cutoff!r}")


class Measurements(NamedTuple):
    """Sensor samples at ``time`` (K,): ``ax``, ``ay`` (m/s^2), ``yaw_rate`` (rad/s), ``steering_wheel`` (rad),
    ``wheel_speed`` (K, 4) (rad/s, FL, FR, RL, RR), ``vx_ref`` (m/s) and the ESC's status ``esc_active`` (0/1, the
    trajectory's at each sample)."""

    time: jax.Array
    ax: jax.Array
    ay: jax.Array
    yaw_rate: jax.Array
    steering_wheel: jax.Array
    wheel_speed: jax.Array
    vx_ref: jax.Array
    esc_active: jax.Array


def low_pass(x, cutoff, period):
    """First-order discrete low-pass along the leading axis of ``x`` (docs/theory/vehicle.md), ``y_0 = x_0``.

    Args:
      x: (K, ...) samples.  cutoff: cut-off frequency (Hz, > 0; ``inf`` for none).  period: sample period (s,
        finite, > 0). Both checked where concrete; traced values outside the range give NaN.
    """
    x = _checks.real_array("x", x)
    if x.ndim == 0 or x.shape[0] == 0:
        raise ValueError(f"x must have at least one sample along its leading axis, got shape {x.shape}")
    if _checks.is_concrete(cutoff) and not np.all(np.asarray(cutoff) > 0):
        raise ValueError(f"cutoff must be positive (Hz, inf for no low-pass), got {cutoff!r}")
    _checks.positive("period", period)
    a = 1.0 - jnp.exp(-2.0 * jnp.pi * cutoff * period)
    a = jnp.where((cutoff > 0) & (period > 0) & jnp.isfinite(period), a, jnp.nan)

    def step(y, xk):
        y = y + a * (xk - y)
        return y, y

    return jax.lax.scan(step, x[0], x)[1]


def _period_ratio(rate, dt) -> int:
    """Plant steps per sensor sample; ``ValueError`` unless ``1 / (rate dt)`` is a whole number >= 1."""
    _checks.positive_scalar("rate", rate)
    _checks.positive_scalar("dt", dt)
    ratio = 1.0 / (float(rate) * float(dt))
    n = round(ratio)
    if n < 1 or not math.isclose(ratio, n, rel_tol=1e-9):
        raise ValueError(
            f"rate must make the sensor period a whole multiple of the plant step dt = {dt} s: got rate = {rate} Hz, "
            f"a period of {ratio:g} plant steps"
        )
    return n


_TRAJECTORY = (
    "trajectory.time (k,), trajectory.ax (k,), trajectory.ay (k,), trajectory.state.r (k,), "
    "trajectory.state.omega (k, 4), trajectory.inputs.steering_wheel (k,), trajectory.esc_active (k,)"
)
"""The shapes of the trajectory fields that :func:`measure` reads: one drive of K plant samples."""


def measure(
    trajectory: Trajectory,
    params: VehicleParams,
    sensors: SensorParams,
    key,
    *,
    rate: float = SENSOR_RATE,
    dt: float = PLANT_STEP,
) -> Measurements:
    """ESC measurements of a simulated drive.

    Args:
      trajectory: the drive (:func:`jaxobs.vehicle.simulate`) at the plant step ``dt``.
      params: the vehicle that drove it (roll gradient, wheel radius, geometry, steering ratio).
      sensors: the sensor errors (:class:`SensorParams`).  key: a ``jax.random`` key for drift and noise.
      rate: sensor rate (Hz, static); ``1 / (rate dt)`` must be a whole number.  dt: the plant step (s, static).

    Returns:
      :class:`Measurements` at every ``1 / (rate dt)``-th plant sample, starting at the first.
    """
    sensors.validate()
    tr, s = trajectory, sensors
    _checks.shapes(_TRAJECTORY, tr.time, tr.ax, tr.ay, tr.state.r, tr.state.omega, tr.inputs.steering_wheel,
                   tr.esc_active)  # fmt: skip
    _checks.fields("sensors", s, ", ".join(f"{f.name} ()" for f in dataclasses.fields(s)))
    params, key = check_vehicle(params, "params"), _checks.key("key", key)
    n = _period_ratio(rate, dt)
    period = n * dt
    tr = jax.tree_util.tree_map(lambda a: a[::n], trajectory)
    keys = jax.random.split(key, 10)
    dtype = tr.ax.dtype

    def channel(truth, bias, drift, noise, k_drift, k_noise):
        steps = jax.random.normal(k_drift, truth.shape, dtype).at[0].set(0.0)
        walk = drift * jnp.sqrt(period) * jnp.cumsum(steps, axis=0)
        return truth + bias + walk + noise * jax.random.normal(k_noise, truth.shape, dtype)

    roll = 1.0 + params.roll_gradient * GRAVITY
    raw = {
        "ax": channel(tr.ax, s.bias_ax, s.drift_acc, s.noise_acc, keys[0], keys[1]),
        "ay": channel(roll * tr.ay, s.bias_ay, s.drift_acc, s.noise_acc, keys[2], keys[3]),
        "yaw_rate": channel(tr.state.r, s.bias_yaw_rate, s.drift_yaw_rate, s.noise_yaw_rate, keys[4], keys[5]),
        "steering_wheel": channel(tr.inputs.steering_wheel, s.bias_steering, 0.0, s.noise_steering, keys[6], keys[7]),
        "wheel_speed": channel(tr.state.omega, 0.0, 0.0, s.noise_wheel, keys[8], keys[9]),
    }
    out = {name: low_pass(raw[name], s.cutoff, period) for name in _CHANNELS}
    delta = out["steering_wheel"] / params.steering_ratio
    half = params.track_front / 2
    front = out["wheel_speed"][:, :2] * params.wheel_radius / jnp.cos(delta)[:, None]
    vx_ref = jnp.mean(front + out["yaw_rate"][:, None] * jnp.stack([half, -half]), axis=1)
    return Measurements(time=tr.time, vx_ref=vx_ref, esc_active=tr.esc_active, **out)


def sensor_inputs(measurements: Measurements) -> EstimatorInputs:
    """The vehicle observers' inputs from :class:`Measurements` (K samples): ``y`` (K, :data:`N_SENSORS`) in the
    layout of :data:`AX` ... :data:`ESC_ACTIVE`."""
    m = measurements
    _checks.fields("measurements", m, "time (k,), ax (k,), ay (k,), yaw_rate (k,), steering_wheel (k,), "
                   "wheel_speed (k, 4), vx_ref (k,), esc_active (k,)")  # fmt: skip
    columns = [m.ax[:, None], m.ay[:, None], m.yaw_rate[:, None], m.steering_wheel[:, None], m.wheel_speed]
    return EstimatorInputs(y=jnp.concatenate([*columns, m.vx_ref[:, None], m.esc_active[:, None]], axis=1))
