"""Test drives modelled on those of Grip 2010 §2.10 (Figs. 2.4-2.8), with amplitudes chosen for the default
:class:`~jaxobs.vehicle.VehicleParams` (the thesis's drives used a test vehicle whose data are not published).

A test drive is a :class:`Manoeuvre`: a :class:`Command` per time (what the driver is asked to do), a duration and an
initial speed. Each below is one, looked up by name with :func:`manoeuvre` or passed by name to
:func:`~jaxobs.vehicle.simulate`; the peaks below were measured with the default vehicle
(``tests/vehicle/test_manoeuvres.py`` pins them):

* ``straight``: 100 km/h straight ahead on a flat road, 10 s (no lateral excitation).
* ``sine_steer``: 80 km/h, steering-wheel sine of 45 deg at 0.5 Hz, 10 s: peak 0.58 g, sideslip 0.85 deg.
* ``step_steer_200kmh``: 200 km/h, steering-wheel steps alternating +-9.5 deg every 4 s (0.3 s ramps) on a
  1.5 deg bank, 20 s: peak 0.43 g (Fig. 2.4: about +-0.4 g).
* ``double_lane_change_120kmh``: 120 km/h, a steering sequence for the ISO 3888-1 double lane change (one
  50 deg sine period of 2.2 s out, 1 s straight, one back) on a 0.5 deg bank, 8 s: peak 0.92 g, sideslip
  3.9 deg (Fig. 2.5: 0.90 g).
* ``circle_40m_ramp``: counter-clockwise circle of 40 m radius (curvature tracking), speed ramped at
  0.1 m/s^2 from 8 m/s, 120 s: the front axle saturates, the radius grows to 44 m at 0.86 g (Fig. 2.6:
  0.93 and 0.84 g with two tyre sets).
* ``ice_lake_circles``: friction 0.25 (ice and snow), 30 m circles at 7.5 +- 1.5 m/s (20 s period); at each
  speed-up the rear axle breaks loose and the curvature-tracking driver counter-steers: sideslip up to
  50 deg, above 10 deg for 41 of 120 s, speed down to 2.8 m/s (Fig. 2.7).
* ``mountain_road``: snow (friction 0.4), a winding road at 12 +- 2 m/s with bank up to 4 deg and inclination up
  to 6 deg, 60 s: peak 0.38 g (Fig. 2.8).

The road friction of a manoeuvre scales the tyres' own (``Command.friction``); set the tyres' ``mu`` for other
surfaces.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["Command", "Manoeuvre", "MANOEUVRES", "manoeuvre"]


class Command(NamedTuple):
    """What the driver is asked to do at one time (all scalars). ``steering_wheel`` (rad, feed-forward),
    ``curvature`` (1/m) and ``curvature_gain`` (rad of road-wheel angle per 1/m of curvature error; 0 = open
    loop), ``speed`` (m/s) and ``acceleration`` (m/s^2, feed-forward), the road's ``bank`` and ``inclination``
    (rad) and ``friction`` (scale of the tyres' peak friction)."""

    steering_wheel: jax.Array = 0.0
    curvature: jax.Array = 0.0
    curvature_gain: jax.Array = 0.0
    speed: jax.Array = 20.0
    acceleration: jax.Array = 0.0
    bank: jax.Array = 0.0
    inclination: jax.Array = 0.0
    friction: jax.Array = 1.0


class Manoeuvre(NamedTuple):
    """A test drive.

    Attributes:
      name: the manoeuvre's name
      command: ``command(t) -> Command`` (traceable)
      duration: its duration (s)
      initial_speed: the vehicle's speed at ``t = 0`` (m/s)
    """

    name: str
    command: Callable
    duration: float
    initial_speed: float


_DEG = jnp.pi / 180
_L, _RATIO = 2.8, 15.5  # the default vehicle's wheelbase and steering ratio (feed-forward of the circle drives)


def _ramp(t, start, length):
    """0 before ``start``, 1 after ``start + length``, a half cosine in between."""
    s = jnp.clip((t - start) / length, 0.0, 1.0)
    return 0.5 * (1.0 - jnp.cos(jnp.pi * s))


def _straight(t):
    return Command(speed=100 / 3.6)


def _sine_steer(t):
    return Command(steering_wheel=45 * _DEG * jnp.sin(jnp.pi * t), speed=80 / 3.6)


def _step_steer(t):
    k = jnp.floor(t / 4.0)
    sign = jnp.where(jnp.mod(k, 2) == 0, 1.0, -1.0)
    previous = jnp.where(k == 0, 0.0, -sign)
    level = previous + (sign - previous) * _ramp(t, 4.0 * k, 0.3)
    return Command(steering_wheel=9.5 * _DEG * level, speed=200 / 3.6, bank=1.5 * _DEG)


def _lane_change(t):
    period, start, gap = 2.2, 1.0, 1.0
    out = jnp.where((t >= start) & (t < start + period), jnp.sin(2 * jnp.pi * (t - start) / period), 0.0)
    back_start = start + period + gap
    back = jnp.where(
        (t >= back_start) & (t < back_start + period), jnp.sin(2 * jnp.pi * (t - back_start) / period), 0.0
    )
    return Command(steering_wheel=50 * _DEG * (out - back), speed=120 / 3.6, bank=0.5 * _DEG)


def _circle(t):
    radius = 40.0
    return Command(
        steering_wheel=_RATIO * _L / radius,
        curvature=1 / radius,
        curvature_gain=10.0,
        speed=8.0 + 0.1 * t,
        acceleration=0.1,
    )


def _ice_lake(t):
    radius, period = 30.0, 20.0
    pulse = 2 * jnp.pi * t / period
    return Command(
        steering_wheel=_RATIO * _L / radius,
        curvature=1 / radius,
        curvature_gain=8.0,
        speed=7.5 + 1.5 * jnp.sin(pulse),
        acceleration=1.5 * 2 * jnp.pi / period * jnp.cos(pulse),
        friction=0.25,
    )


def _mountain(t):
    curvature = (jnp.sin(2 * jnp.pi * t / 12.0) + 0.5 * jnp.sin(2 * jnp.pi * t / 7.0)) / 70.0
    return Command(
        steering_wheel=_RATIO * _L * curvature,
        curvature=curvature,
        curvature_gain=5.0,
        speed=12.0 + 2.0 * jnp.sin(2 * jnp.pi * t / 25.0),
        acceleration=2.0 * 2 * jnp.pi / 25.0 * jnp.cos(2 * jnp.pi * t / 25.0),
        bank=4 * _DEG * jnp.sin(2 * jnp.pi * t / 17.0),
        inclination=6 * _DEG * jnp.sin(2 * jnp.pi * t / 40.0),
        friction=0.4,
    )


MANOEUVRES = {
    m.name: m
    for m in (
        Manoeuvre("straight", _straight, 10.0, 100 / 3.6),
        Manoeuvre("sine_steer", _sine_steer, 10.0, 80 / 3.6),
        Manoeuvre("step_steer_200kmh", _step_steer, 20.0, 200 / 3.6),
        Manoeuvre("double_lane_change_120kmh", _lane_change, 8.0, 120 / 3.6),
        Manoeuvre("circle_40m_ramp", _circle, 120.0, 8.0),
        Manoeuvre("ice_lake_circles", _ice_lake, 120.0, 7.5),
        Manoeuvre("mountain_road", _mountain, 60.0, 12.0),
    )
}
"""The named test drives (module docstring)."""


def manoeuvre(name: str) -> Manoeuvre:
    """The test drive called ``name`` (a key of :data:`MANOEUVRES`); ``ValueError`` listing them otherwise."""
    if name not in MANOEUVRES:
        raise ValueError(f"manoeuvre must be one of {sorted(MANOEUVRES)}, got {name!r}")
    return MANOEUVRES[name]
