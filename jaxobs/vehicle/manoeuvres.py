"""Test drives modelled on those of Grip 2010 §2.10 (Figs. 2.4-2.8), with amplitudes chosen for the default
:class:`~jaxobs.vehicle.VehicleParams` (the thesis's test vehicle is not published).

A test drive is a :class:`Manoeuvre`: a :class:`Command` per time, a duration and an initial speed.
:data:`MANOEUVRES` holds the named ones (``straight``, ``sine_steer``, ``step_steer_200kmh``,
``double_lane_change_120kmh``, ``circle_40m_ramp``, ``ice_lake_circles``, ``mountain_road``), looked up with
:func:`manoeuvre` or passed by name to :func:`~jaxobs.vehicle.simulate`. Each drive and the peaks it reaches with
the default vehicle: docs/theory/vehicle.md.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks

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

    def check(self, name: str) -> Command:
        """The command, its fields checked to be scalars at trace time (one command: ``vmap`` for a batch), naming
        ``name.field``."""
        _checks.fields(name, self, ", ".join(f"{field} ()" for field in self._fields))
        return self


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
"""The named test drives (docs/theory/vehicle.md)."""


def manoeuvre(name: str) -> Manoeuvre:
    """The test drive called ``name`` (a key of :data:`MANOEUVRES`); ``ValueError`` listing them otherwise."""
    if name not in MANOEUVRES:
        raise ValueError(f"manoeuvre must be one of {sorted(MANOEUVRES)}, got {name!r}")
    return MANOEUVRES[name]
