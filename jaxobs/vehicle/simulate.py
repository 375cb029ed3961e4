"""Simulating the two-track model under a driver: a :class:`Command` per time, RK4 at a fixed plant step.

:func:`driver` turns the command and the state into plant inputs (open-loop or curvature-tracking steering,
speed-tracking wheel torques with a proportional stand-in for traction control and ABS); :func:`simulate`
integrates the model under it with :func:`jaxobs.ct.trajectory` (RK4, :data:`PLANT_STEP`) in one ``lax.scan`` and
returns the states, the specific forces and the sideslip at every plant step. The driver's laws:
docs/theory/vehicle.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

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
    steady_state,
    wheel_kinematics,
)

__all__ = [
    "PLANT_STEP",
    "SPEED_GAIN",
    "SLIP_LIMIT",
    "STEERING_LOCK",
    "Trajectory",
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
    (m/s^2), the sideslip ``beta`` (rad) and the normal loads ``fz`` (T+1, 4)."""

    time: jax.Array
    state: VehicleState
    inputs: Inputs
    ax: jax.Array
    ay: jax.Array
    beta: jax.Array
    fz: jax.Array


def driver(p: VehicleParams, x: VehicleState, c: Command) -> Inputs:
    """The plant inputs the driver applies in state ``x`` to follow the command ``c`` (docs/theory/vehicle.md)."""
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
    v_l, _, _ = wheel_kinematics(p, x.vx, x.vy, x.r, steering)
    kappa = (x.omega * p.wheel_radius - v_l) / jnp.maximum(jnp.abs(v_l), MIN_SPEED)
    limiter = jnp.clip(1.0 - jnp.maximum(jnp.sign(torque) * kappa, 0.0) / SLIP_LIMIT, 0.0, 1.0)
    return Inputs(steering, torque * limiter, c.bank, c.inclination, c.friction)


def _command(manoeuvre: Manoeuvre, t) -> Command:
    c = manoeuvre.command(t)
    return Command(*(jnp.asarray(v, jnp.result_type(t)) for v in c))


def simulate(manoeuvre: Manoeuvre, params: VehicleParams, *, duration=None, dt: float = PLANT_STEP) -> Trajectory:
    """Simulate ``manoeuvre`` (a :class:`Manoeuvre`) with the vehicle ``params`` from a straight run at its
    initial speed.

    Args:
      manoeuvre: the test drive, or the name of one of :data:`jaxobs.vehicle.MANOEUVRES` (``ValueError`` listing
        them for another name).  params: the vehicle (validated when concrete; fields may be traced, e.g. under
        ``vmap``).
      duration: simulated time (s, > 0, default the manoeuvre's); rounded to whole plant steps, at most 2**31 - 1.
      dt: plant step (s, > 0, static).

    Returns:
      a :class:`Trajectory` with ``round(duration / dt) + 1`` samples.
    """
    if isinstance(manoeuvre, str):
        manoeuvre = manoeuvres.manoeuvre(manoeuvre)
    if not isinstance(manoeuvre, Manoeuvre):
        raise ValueError(f"manoeuvre must be a Manoeuvre or the name of one, got {type(manoeuvre).__name__}")
    params = check_vehicle(params, "params")
    _checks.positive_scalar("dt", dt)
    duration = manoeuvre.duration if duration is None else duration
    _checks.positive_scalar("duration", duration)
    steps = max(int(round(duration / dt)), 1)
    if steps > _checks.MAX_INDEX:
        raise ValueError(f"duration = {duration:g} s is {steps} plant steps of {dt:g} s, more than 2**31 - 1")
    x0 = steady_state(params, jnp.asarray(manoeuvre.initial_speed, float))

    def f(x, _, t):
        return dynamics(params, x, driver(params, x, _command(manoeuvre, t)))

    states = ct.trajectory(f, x0, jnp.zeros(steps), h=dt)
    time = dt * jnp.arange(steps + 1, dtype=states.vx.dtype)

    def outputs(x, t):
        u = driver(params, x, _command(manoeuvre, t))
        f = forces(params, x, u)
        return u, f.ax, f.ay, f.fz

    inputs, ax, ay, fz = jax.vmap(outputs)(states, time)
    return Trajectory(time, states, inputs, ax, ay, jnp.arctan2(states.vy, states.vx), fz)
