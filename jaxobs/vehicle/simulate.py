"""Simulating the two-track model under a driver: a :class:`Command` per time, RK4 at a fixed plant step.

:func:`driver` turns the command and the state into plant inputs (open-loop or curvature-tracking steering,
speed-tracking wheel torques with a proportional stand-in for traction control and ABS, and, when an
:class:`ESCParams` is given, the yaw control of an ESC by braking single wheels, :func:`esc_intervention`);
:func:`simulate` integrates the model under it with :func:`jaxobs.ct.trajectory` (RK4, :data:`PLANT_STEP`) in one
``lax.scan`` and returns the states, the specific forces, the sideslip and the ESC's status at every plant step. The
driver's laws: docs/theory/vehicle.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks, ct
from jaxobs.vehicle import manoeuvres
from jaxobs.vehicle.manoeuvres import Command, Manoeuvre
from jaxobs.vehicle.model import (
    AIR_DENSITY,
    GRAVITY,
    MIN_SPEED,
    Inputs,
    VehicleParams,
    VehicleState,
    check_vehicle,
    dynamics,
    forces,
    reference_yaw_rate,
    steady_state,
    wheel_kinematics,
)

__all__ = [
    "PLANT_STEP",
    "SPEED_GAIN",
    "SLIP_LIMIT",
    "STEERING_LOCK",
    "Trajectory",
    "ESCParams",
    "esc_intervention",
    "driver",
    "simulate",
]

PLANT_STEP = 1e-3
"""Default plant step (s): 10 RK4 steps per 100 Hz sensor sample."""
SPEED_GAIN = 1.0
"""Driver's speed-tracking gain (1/s)."""
SLIP_LIMIT = 0.15
"""Slip at which the driver's traction and anti-lock limiter has removed a wheel's whole torque (assumed)."""
STEERING_LOCK = 0.6
"""Largest road-wheel angle the driver applies (rad, about 34 deg; assumed)."""


class Trajectory(NamedTuple):
    """A simulated drive at the plant step: ``time`` (T+1,), ``state`` (a :class:`VehicleState` of stacked
    arrays), the plant ``inputs`` (an :class:`Inputs` of stacked arrays), the specific forces ``ax``, ``ay``
    (m/s^2), the sideslip ``beta`` (rad), the normal loads ``fz`` (T+1, 4) and ``esc_active`` (T+1,), 1 where the
    ESC brakes a wheel (:func:`esc_intervention`; all 0 without an ESC)."""

    time: jax.Array
    state: VehicleState
    inputs: Inputs
    ax: jax.Array
    ay: jax.Array
    beta: jax.Array
    fz: jax.Array
    esc_active: jax.Array


class ESCParams(NamedTuple):
    """The simulated ESC's yaw control (assumed values; the law: :func:`esc_intervention`).

    Attributes:
      yaw_rate_threshold: dead band of the yaw-rate error (rad/s, > 0); 0.05 (about 3 deg/s).
      gain: yaw moment per unit yaw-rate error beyond the dead band (N m s/rad, > 0).
      max_brake_torque: largest brake torque on the braked wheel (N m, > 0).
      drive_cut: the fraction of the driving torques the ESC removes while it intervenes (in [0, 1]); 1.
      friction_margin: the ESC's reference yaw rate is held below ``friction_margin mu g / v_x`` with ``mu`` the
        road's friction scale (:class:`~jaxobs.vehicle.Inputs` ``friction``, the peak friction of the default
        tyres; the ESC's own friction estimate, taken exact; > 0).
    """

    yaw_rate_threshold: jax.Array = 0.05
    gain: jax.Array = 2.0e4
    max_brake_torque: jax.Array = 1500.0
    drive_cut: jax.Array = 1.0
    friction_margin: jax.Array = 1.0


def esc_intervention(p: VehicleParams, esc: ESCParams, x: VehicleState, steering_wheel, friction):
    """The ESC's brake torques (4,) (N m, <= 0) and whether it intervenes (0/1) in state ``x``; while it intervenes
    the :func:`driver` also removes the fraction ``drive_cut`` of the driving torques.

    The reference ``r_d`` is the :func:`~jaxobs.vehicle.model.reference_yaw_rate` of the steering-wheel angle,
    held below ``friction_margin friction g / v_x`` (``friction`` the road's friction scale). Beyond the dead
    band ``|r - r_d| > yaw_rate_threshold`` the ESC asks for the yaw moment ``-gain (e - threshold sign e)`` of the
    error ``e = r - r_d`` and brakes one wheel on the side that gives it: the outer front wheel when ``e`` has the
    sign of ``r`` (the car yaws too much in its own direction: oversteer), the inner rear wheel otherwise
    (understeer), as production ESCs do.
    """
    p = check_vehicle(p, "p")
    VehicleState.check(x, "x")
    steering_wheel, friction = _checks.arrays("steering_wheel (), friction ()", steering_wheel, friction)
    vx = jnp.maximum(x.vx, MIN_SPEED)
    limit = esc.friction_margin * friction * GRAVITY / vx
    r_d = jnp.clip(reference_yaw_rate(p, vx, steering_wheel), -limit, limit)
    e = x.r - r_d
    excess = jnp.maximum(jnp.abs(e) - esc.yaw_rate_threshold, 0.0)
    moment = -jnp.sign(e) * esc.gain * excess  # yaw moment asked for (N m, counter-clockwise > 0)
    oversteer = e * x.r > 0  # yawing too much in its own direction (counter-steered drifts included)
    left = moment > 0  # braking a left wheel (FL, RL) turns the car counter-clockwise
    half_track = jnp.where(oversteer, p.track_front, p.track_rear) / 2
    torque = jnp.minimum(jnp.abs(moment) / half_track * p.wheel_radius, esc.max_brake_torque)
    wheel = jnp.where(oversteer, 0, 2) + jnp.where(left, 0, 1)
    brake = -torque * (jnp.arange(4) == wheel)
    return brake, (excess > 0).astype(brake.dtype)


def driver(p: VehicleParams, x: VehicleState, c: Command, esc: ESCParams | None = None) -> Inputs:
    """The plant inputs the driver applies in state ``x`` to follow the command ``c``, with the brake torques of
    the ``esc`` (:func:`esc_intervention`; ``None``: no ESC) added before the traction and anti-lock limiter
    (docs/theory/vehicle.md). One vehicle, state and command (``vmap`` for a batch), checked at trace time."""
    p, x, c = check_vehicle(p, "p"), VehicleState.check(x, "x"), Command.check(c, "c")
    curvature = x.r / jnp.maximum(x.vx, MIN_SPEED)
    steering = c.steering_wheel + p.steering_ratio * c.curvature_gain * (c.curvature - curvature)
    steering = jnp.clip(steering, -p.steering_ratio * STEERING_LOCK, p.steering_ratio * STEERING_LOCK)
    drag = 0.5 * AIR_DENSITY * p.drag_area * x.vx * jnp.abs(x.vx)
    accel = c.acceleration + SPEED_GAIN * (c.speed - x.vx) - GRAVITY * jnp.sin(c.inclination)
    total = p.wheel_radius * (p.mass * accel + drag)
    drive, brake = jnp.maximum(total, 0.0), jnp.minimum(total, 0.0)
    front = brake * p.brake_share_front / 2
    rear = (drive + brake * (1 - p.brake_share_front)) / 2
    torque = jnp.stack([front, front, rear, rear])
    if esc is not None:
        brake, active = esc_intervention(p, esc, x, steering, c.friction)
        torque = torque - active * esc.drive_cut * jnp.maximum(torque, 0.0) + brake
    v_l, _, _ = wheel_kinematics(p, x.vx, x.vy, x.r, steering)
    kappa = (x.omega * p.wheel_radius - v_l) / jnp.maximum(jnp.abs(v_l), MIN_SPEED)
    limiter = jnp.clip(1.0 - jnp.maximum(jnp.sign(torque) * kappa, 0.0) / SLIP_LIMIT, 0.0, 1.0)
    return Inputs(steering, torque * limiter, c.bank, c.inclination, c.friction)


def _command(manoeuvre: Manoeuvre, t) -> Command:
    c = manoeuvre.command(t)
    return Command(*(jnp.asarray(v, jnp.result_type(t)) for v in c))


def simulate(
    manoeuvre: Manoeuvre,
    params: VehicleParams,
    *,
    duration=None,
    dt: float = PLANT_STEP,
    esc: ESCParams | None = None,
) -> Trajectory:
    """Simulate ``manoeuvre`` (a :class:`Manoeuvre`) with the vehicle ``params`` from a straight run at its
    initial speed.

    Args:
      manoeuvre: the test drive, or the name of one of :data:`jaxobs.vehicle.MANOEUVRES` (``ValueError`` listing
        them for another name).  params: the vehicle (validated when concrete; fields may be traced, e.g. under
        ``vmap``).
      duration: simulated time (s, > 0, default the manoeuvre's); rounded to whole plant steps, at most 2**31 - 1.
      dt: plant step (s, > 0, static).
      esc: the car's ESC (:class:`ESCParams`; ``None``, the default: no ESC).

    Returns:
      a :class:`Trajectory` with ``round(duration / dt) + 1`` samples.
    """
    if isinstance(manoeuvre, str):
        manoeuvre = manoeuvres.manoeuvre(manoeuvre)
    if not isinstance(manoeuvre, Manoeuvre):
        raise ValueError(f"manoeuvre must be a Manoeuvre or the name of one, got {type(manoeuvre).__name__}")
    params = check_vehicle(params, "params")
    if esc is not None:
        if not isinstance(esc, ESCParams):
            raise ValueError(f"esc must be an ESCParams or None, got {type(esc).__name__}")
        for name, value in esc._asdict().items():
            _checks.positive(f"esc.{name}", value, allow_zero=name == "drive_cut")
        if _checks.is_concrete(esc.drive_cut) and not np.all(np.asarray(esc.drive_cut) <= 1.0):
            raise ValueError(f"esc.drive_cut must be in [0, 1], got {esc.drive_cut!r}")
    _checks.positive_scalar("dt", dt)
    duration = manoeuvre.duration if duration is None else duration
    _checks.positive_scalar("duration", duration)
    steps = max(int(round(duration / dt)), 1)
    if steps > _checks.MAX_INDEX:
        raise ValueError(f"duration = {duration:g} s is {steps} plant steps of {dt:g} s, more than 2**31 - 1")
    x0 = steady_state(params, jnp.asarray(manoeuvre.initial_speed, jnp.result_type(params.mass, float)))

    def f(x, _, t):
        return dynamics(params, x, driver(params, x, _command(manoeuvre, t), esc))

    states = ct.trajectory(f, x0, jnp.zeros(steps), h=dt)
    time = dt * jnp.arange(steps + 1, dtype=states.vx.dtype)

    def outputs(x, t):
        c = _command(manoeuvre, t)
        u = driver(params, x, c, esc)
        f = forces(params, x, u)
        active = jnp.zeros_like(t) if esc is None else esc_intervention(params, esc, x, u.steering_wheel, c.friction)[1]
        return u, f.ax, f.ay, f.fz, active

    inputs, ax, ay, fz, active = jax.vmap(outputs)(states, time)
    return Trajectory(time, states, inputs, ax, ay, jnp.arctan2(states.vy, states.vx), fz, active)
