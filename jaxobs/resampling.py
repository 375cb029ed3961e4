"""Resampling of weighted particles: the schemes every particle method of jaxobs uses.

Four unbiased schemes draw ancestor indices from log-weights, each by the inverse of the weights' cumulative
distribution at ``n`` points in ``[0, 1)``: :func:`multinomial` (independent uniforms), :func:`stratified` (one
uniform in each of ``n`` equal strata), :func:`systematic` (one uniform shifted across the strata) and
:func:`residual` (the integer parts of ``n w_i`` kept, the rest drawn multinomially); Douc, Cappé & Moulines 2005,
Chopin & Papaspiliopoulos 2020 ch. 9. :func:`resample` adds the adaptive rule on the effective sample size
(:func:`effective_sample_size`, Kong, Liu & Wong 1994) and the stop-gradient weights of Ścibior & Wood 2021, so
that a likelihood estimate differentiates into the Fisher-identity score estimate. Pure functions: eager,
``jit``, ``vmap``; indices carry no gradient.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks

__all__ = [
    "effective_sample_size",
    "multinomial",
    "stratified",
    "systematic",
    "residual",
    "SCHEMES",
    "Resampled",
    "resample",
]


def _log_weights(log_weights) -> jax.Array:
    """``log_weights`` checked to be a non-empty (N,) floating vector (at trace time)."""
    log_weights = jnp.asarray(log_weights)
    _checks.shape("log_weights", log_weights, (None,), "one log-weight per particle")
    if log_weights.shape[0] == 0 or not jnp.issubdtype(log_weights.dtype, jnp.floating):
        raise ValueError(f"log_weights must be a non-empty floating vector, got {log_weights.dtype}{log_weights.shape}")
    return log_weights


def effective_sample_size(log_weights):
    """The effective sample size ``(sum w)^2 / sum w^2`` of (unnormalised) log-weights (N,): ``N`` for equal
    weights, 1 when one particle holds all the weight (Kong, Liu & Wong 1994).

    Example:
      >>> import jax.numpy as jnp
      >>> float(effective_sample_size(jnp.log(jnp.array([0.5, 0.5, 0.0, 0.0]))))
      2.0
    """
    log_weights = _log_weights(log_weights)
    return jnp.exp(2 * jax.nn.logsumexp(log_weights) - jax.nn.logsumexp(2 * log_weights))


def _inverse_cdf(log_weights, points):
    """The index ``i`` with ``F_{i-1} <= u < F_i`` for each point ``u`` in ``[0, 1)``, ``F`` the cumulative
    normalised weights (zero-weight particles are never chosen but by rounding at the last one)."""
    weights = jax.nn.softmax(jax.lax.stop_gradient(log_weights))
    cdf = jnp.cumsum(weights).at[-1].set(1.0)
    return jnp.searchsorted(cdf, points, side="right").astype(jnp.int32)


def _count(num, log_weights) -> int:
    return log_weights.shape[0] if num is None else _checks.count("num", num, minimum=1, hint="indices to draw")


def multinomial(key, log_weights, num: int | None = None):
    """``num`` (default ``N``) ancestor indices drawn independently with probabilities ``softmax(log_weights)``.

    Args:
      key: a PRNG key.  log_weights: (N,) unnormalised log-weights.  num: how many indices (static).

    Returns:
      (num,) int32 indices in ``[0, N)``.
    """
    log_weights = _log_weights(log_weights)
    points = jax.random.uniform(key, (_count(num, log_weights),), log_weights.dtype)
    return _inverse_cdf(log_weights, points)


def stratified(key, log_weights, num: int | None = None):
    """Stratified resampling: the ``j``-th index from the point ``(j + U_j) / num``, ``U_j`` independent uniforms;
    each count is within one of ``num w_i`` more often than multinomially. Arguments and result as
    :func:`multinomial`."""
    log_weights = _log_weights(log_weights)
    num = _count(num, log_weights)
    uniforms = jax.random.uniform(key, (num,), log_weights.dtype)
    return _inverse_cdf(log_weights, (jnp.arange(num, dtype=log_weights.dtype) + uniforms) / num)


def systematic(key, log_weights, num: int | None = None):
    """Systematic resampling: the points ``(j + U) / num`` share one uniform ``U``, so particle ``i`` gets
    ``floor(num w_i)`` or ``ceil(num w_i)`` copies. Arguments and result as :func:`multinomial`."""
    log_weights = _log_weights(log_weights)
    num = _count(num, log_weights)
    uniform = jax.random.uniform(key, (), log_weights.dtype)
    return _inverse_cdf(log_weights, (jnp.arange(num, dtype=log_weights.dtype) + uniform) / num)


def residual(key, log_weights, num: int | None = None):
    """Residual resampling: particle ``i`` first gets ``floor(num w_i)`` copies, the remaining
    ``num - sum floor(num w_i)`` indices are drawn multinomially from the residuals ``num w_i - floor(num w_i)``.
    Arguments and result as :func:`multinomial` (the deterministic copies come first)."""
    log_weights = _log_weights(log_weights)
    num = _count(num, log_weights)
    scaled = num * jax.nn.softmax(jax.lax.stop_gradient(log_weights))
    copies = jnp.floor(scaled)
    kept = jnp.minimum(jnp.sum(copies), num).astype(jnp.int32)
    particles = jnp.arange(log_weights.shape[0], dtype=jnp.int32)
    deterministic = jnp.repeat(particles, copies.astype(jnp.int32), total_repeat_length=num)
    rest = jnp.maximum(scaled - copies, 0.0)
    tiny = jnp.finfo(log_weights.dtype).tiny
    drawn = multinomial(key, jnp.log(jnp.maximum(rest, tiny)) + jnp.where(rest > 0, 0.0, -jnp.inf), num)
    drawn = jnp.where(jnp.any(rest > 0), drawn, deterministic)  # all copies deterministic: nothing left to draw
    return jnp.where(jnp.arange(num) < kept, deterministic, drawn)


SCHEMES = {"multinomial": multinomial, "stratified": stratified, "systematic": systematic, "residual": residual}
"""The resampling schemes by name, each ``(key, log_weights, num=None) -> indices``."""


class Resampled(NamedTuple):
    """Result of :func:`resample` (``N`` particles).

    Attributes:
      ancestors: (N,) int32 index of each new particle's parent (``arange(N)`` when not resampled).
      log_weights: (N,) log-weights of the new particles; they sum (``logsumexp``) to the given total.
      resampled: () bool, whether the particles were resampled.
    """

    ancestors: jax.Array
    log_weights: jax.Array
    resampled: jax.Array


def resample(key, log_weights, *, scheme: str = "systematic", ess_threshold=1.0) -> Resampled:
    """Adaptive resampling with stop-gradient weights (Ścibior & Wood 2021).

    The particles are resampled by ``scheme`` when the effective sample size is below ``ess_threshold N``
    (``ess_threshold >= 1``: always; 0: never). A resampled particle ``j`` with parent ``a_j`` gets the
    log-weight ``sg(logsumexp(lw)) - log N + lw[a_j] - sg(lw[a_j])`` (``sg``: ``jax.lax.stop_gradient``): in
    value, an equal share of the total weight, as in the forward pass of any particle filter; in derivative,
    that of its parent's own log-weight. Differentiating a likelihood estimate built on these weights gives
    the Fisher-identity score estimate, ``sum_j W_j d log w(path_j)``, over the particles' genealogies.

    Args:
      key: a PRNG key.  log_weights: (N,) log-weights (unnormalised).
      scheme: a name in :data:`SCHEMES` (static).  ess_threshold: () fraction of ``N`` in ``[0, 1]`` (may be
        traced).

    Returns:
      :class:`Resampled`.

    Example:
      >>> import jax, jax.numpy as jnp
      >>> out = resample(jax.random.PRNGKey(0), jnp.log(jnp.array([0.7, 0.1, 0.1, 0.1])), ess_threshold=0.5)
      >>> out.resampled.item(), out.ancestors.tolist()
      (False, [0, 1, 2, 3])
    """
    log_weights = _log_weights(log_weights)
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {sorted(SCHEMES)}, got {scheme!r}")
    threshold = jnp.asarray(ess_threshold, log_weights.dtype)
    _checks.shape("ess_threshold", threshold, (), "a fraction of the number of particles")
    num = log_weights.shape[0]
    drawn = SCHEMES[scheme](key, log_weights)
    low = effective_sample_size(jax.lax.stop_gradient(log_weights)) < threshold * num
    resampled = (threshold >= 1) | low
    parent = log_weights[drawn]
    total = jax.lax.stop_gradient(jax.nn.logsumexp(log_weights))
    shared = total - math.log(num) + parent - jax.lax.stop_gradient(parent)
    return Resampled(
        jnp.where(resampled, drawn, jnp.arange(num, dtype=jnp.int32)), jnp.where(resampled, shared, log_weights),
        resampled,
    )  # fmt: skip
