"""The road inclination and bank estimators of Grip 2010 ch. 4 (Grip, Imsland, Johansen, Kalkkuhl & Suissa 2009,
ACC) and the positive-realness gain bounds of its Lemmas 4.1 and 4.2.

On a slanted road ``v_x' = a_x + r v_y + g sin(Theta)``, ``v_y' = a_y - r v_x - g cos(Theta) sin(Phi)`` (4.5);
the estimators treat ``theta_i = sin(Theta)`` and ``theta_b = cos(Theta) sin(Phi)`` as constants and estimate
them by integral action on the two velocity residuals.

Error systems and gain bounds. With ``K_vx(t) = a + (K_vx(t) - a)``, ``0 < a < K_vx,min``, the inclination error
``(v_x~, theta_i~)`` is the linear system (4.8) in feedback with a sector ``[0, inf]`` nonlinearity; the origin is
GES when its transfer function ``G(s) = (s + g K_theta_i) / (s^2 + a s + g K_theta_i a)`` is strictly positive
real, i.e. ``K_theta_i < a / g`` (Lemma 4.1). Likewise the bank error (4.11) with ``a_y~ = -delta(t) v_y~``,
``delta >= delta_min > 0``: ``G(s) = (K_vy s + g K_theta_b) / (s^2 + K_vy delta_min s + g K_theta_b delta_min)``,
SPR iff ``K_theta_b < K_vy^2 delta_min / g`` (Lemma 4.2; the thesis's statement prints the gain as "K_theta1").
:func:`inclination_error_system`, :func:`bank_error_system` give the linear parts, :func:`inclination_gain_bound`,
:func:`bank_gain_bound` the bounds, and :func:`lemma_check` evaluates :func:`jaxobs.lti.is_spr` on either side.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.lti import StateSpace, is_spr, ss
from jaxobs.vehicle.model import GRAVITY

__all__ = [
    "inclination_error_system",
    "bank_error_system",
    "inclination_gain_bound",
    "bank_gain_bound",
    "LemmaCheck",
    "lemma_check",
]


def inclination_error_system(a, K_theta_i, g=GRAVITY) -> StateSpace:
    """The linear part of the inclination error system (4.8), state ``(v_x~, theta_i~)``, input ``u`` (the
    sector part ``-(K_vx(t) - a) v_x~``), output ``v_x~``: ``A = [[-a, g], [-K_theta_i a, 0]]``,
    ``B = [1, K_theta_i]'``, ``C = [1, 0]``. Args: ``a`` (1/s, ``0 < a < K_vx,min``), ``K_theta_i``, ``g``
    (m/s^2). Traceable (jit, vmap, grad)."""
    a, K, g = jnp.broadcast_arrays(*(jnp.asarray(v, _checks.float_dtype(a=a, K_theta_i=K_theta_i, g=g))
                                     for v in (a, K_theta_i, g)))  # fmt: skip
    zero, one = jnp.zeros_like(a), jnp.ones_like(a)
    A = jnp.stack([jnp.stack([-a, g]), jnp.stack([-K * a, zero])])
    return ss(A, jnp.stack([one, K])[:, None], jnp.stack([one, zero])[None, :])


def bank_error_system(K_vy, delta_min, K_theta_b, g=GRAVITY) -> StateSpace:
    """The linear part of the bank error system (4.11), state ``(v_y~, theta_b~)``, input ``u = -(delta -
    delta_min) v_y~``, output ``v_y~``: ``A = [[-K_vy delta_min, -g], [K_theta_b delta_min, 0]]``,
    ``B = [K_vy, -K_theta_b]'``, ``C = [1, 0]``. Args: ``K_vy``, ``delta_min`` (1/s, the least slope of
    ``-a_y~`` in ``v_y~``, Assumption 4.1), ``K_theta_b``, ``g``. Traceable."""
    dtype = _checks.float_dtype(K_vy=K_vy, delta_min=delta_min, K_theta_b=K_theta_b, g=g)
    k, d, K, g = jnp.broadcast_arrays(*(jnp.asarray(v, dtype) for v in (K_vy, delta_min, K_theta_b, g)))
    zero, one = jnp.zeros_like(k), jnp.ones_like(k)
    A = jnp.stack([jnp.stack([-k * d, -g]), jnp.stack([K * d, zero])])
    return ss(A, jnp.stack([k, -K])[:, None], jnp.stack([one, zero])[None, :])


def inclination_gain_bound(a, g=GRAVITY):
    """Lemma 4.1: the inclination estimator is GES for ``0 < K_theta_i < a / g``; returns ``a / g``."""
    return jnp.asarray(a) / g


def bank_gain_bound(K_vy, delta_min, g=GRAVITY):
    """Lemma 4.2: the bank estimator is GES for ``0 < K_theta_b < K_vy^2 delta_min / g``; returns the bound."""
    return jnp.asarray(K_vy) ** 2 * delta_min / g


class LemmaCheck(NamedTuple):
    """:func:`lemma_check`'s result: the ``bound`` and whether the error system is SPR at ``bound (1 - rel)``
    (``spr_below``) and ``bound (1 + rel)`` (``spr_above``)."""

    bound: float
    spr_below: bool
    spr_above: bool


def lemma_check(lemma: str, *, a=None, K_vy=None, delta_min=None, g=GRAVITY, rel=1e-3) -> LemmaCheck:
    """Evaluate :func:`jaxobs.lti.is_spr` on the error system of Lemma 4.1 (``lemma="4.1"``, needs ``a``) or
    Lemma 4.2 (``"4.2"``, needs ``K_vy`` and ``delta_min``) with the gain a relative ``rel`` below and above the
    bound (design time, concrete values). The lemma holds when ``spr_below`` and not ``spr_above``.

    Example:
      >>> check = lemma_check("4.1", a=0.5)             # bound a / g
      >>> round(check.bound, 6), check.spr_below, check.spr_above
      (0.050968, True, False)
    """
    _checks.positive_scalar("rel", rel)
    if lemma == "4.1":
        _checks.positive_scalar("a", a)
        bound = float(inclination_gain_bound(a, g))
        system = lambda K: inclination_error_system(a, K, g)
    elif lemma == "4.2":
        _checks.positive_scalar("K_vy", K_vy)
        _checks.positive_scalar("delta_min", delta_min)
        bound = float(bank_gain_bound(K_vy, delta_min, g))
        system = lambda K: bank_error_system(K_vy, delta_min, K, g)
    else:
        raise ValueError(f"lemma must be '4.1' or '4.2', got {lemma!r}")
    spr = [is_spr(s.A, s.B, s.C) for s in (system(bound * (1 - rel)), system(bound * (1 + rel)))]
    return LemmaCheck(bound, *spr)
