"""Analytic plant models (continuous-time physics, discretised with dead time by :func:`jaxobs.lti.c2d`).

:func:`force_plant` is the one-degree-of-freedom robot force-control plant of the Active Observer papers
(Cortesão 2006 §7, eq. 80; Cortesão, MRAC chapter eq. 56-61): a position-controlled robot with the first-order
position response ``1 / (1 + Tp s)`` and an input dead time ``Td`` pushing on an environment of stiffness ``Ks``,

    G(s) = k1 / (s (s + p1)) e^{-s Td},    k1 = Ks / Tp,    p1 = 1 / Tp,

with states ``[force, force derivative]`` and a velocity command as input. The papers' numbers come out with
``Ks`` in N/mm and the command in mm/s (forces in N).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.lti import StateSpace, c2d, ss

__all__ = ["force_plant"]


def force_plant(stiffness, time_constant, h: float, dead_time, *, n_delay: int | None = None, input_gain=1.0
                ) -> StateSpace:  # fmt: skip
    """The delay-augmented discrete force plant (Cortesão, MRAC chapter eq. 57-61, discretised by Cortesão
    2006 eq. 11-18).

    Args:
      stiffness: environment (plus sensor) stiffness ``Ks``, N/mm.  time_constant: position-loop time constant
        ``Tp``, s.
      h: sample time, s (a Python number).  dead_time: input dead time ``Td``, s.
      n_delay: number of delay slots; required when ``dead_time`` is traced (see :func:`jaxobs.lti.c2d`).
      input_gain: a mismatch factor of the robot's velocity gain (1 nominally).

    ``stiffness``, ``time_constant``, ``dead_time`` and ``input_gain`` are scalars and may be traced (``vmap`` over
    mismatched plants, ``grad``); the model has their floating dtype (float32 in, float32 out).
    Returns the discrete :class:`~jaxobs.lti.StateSpace` with states ``[F, dF/dt, u_{k-d}, ..., u_{k-1}]``.

    Example:
      >>> from jaxobs.plants import force_plant
      >>> plant = force_plant(3.0, 0.032, 0.008, 0.040)
      >>> plant.n_states, plant.dt
      (7, 0.008)
    """
    _checks.positive_scalar("stiffness", stiffness)
    _checks.positive_scalar("time_constant", time_constant)
    Ks, Tp, gain, _ = _checks.arrays("stiffness (), time_constant (), input_gain (), dead_time ()",
                                     stiffness, time_constant, input_gain, dead_time)  # fmt: skip
    # c2d gets dead_time as given: a Python number stays concrete under an outer trace (no n_delay needed)
    zero = jnp.zeros((), Ks.dtype)
    A = jnp.stack([jnp.stack([zero, zero + 1.0]), jnp.stack([zero, -1.0 / Tp])])
    B = jnp.stack([zero, gain * Ks / Tp])[:, None]
    return c2d(ss(A, B, jnp.array([[1.0, 0.0]], Ks.dtype)), h, dead_time, n_delay=n_delay)
