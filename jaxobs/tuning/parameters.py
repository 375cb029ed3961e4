"""Parameterisations of tuned designs: unconstrained ``theta`` to constrained values, each with its inverse (to
start from a hand-set design)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxobs import _checks

__all__ = ["cholesky_covariance", "cholesky_parameters", "unit_interval", "unit_interval_parameters", "log_labels",
           "cholesky_labels"]  # fmt: skip


def cholesky_covariance(raw):
    """``Q = L L^T`` with ``L = diag(exp(diag(raw))) (I + tril(raw, -1))``: positive definite for every ``raw``
    (..., n, n). The diagonal of ``raw`` holds log standard-deviation scales, its strict lower triangle
    dimensionless couplings (a row's entries relative to its own scale), so one search box fits covariances of any
    units; the strict upper triangle is ignored. Leading axes are batch axes.

    Example:
      >>> import jax.numpy as jnp
      >>> from jaxobs.tuning import cholesky_covariance
      >>> cholesky_covariance(jnp.array([[0.0, 0.0], [0.5, jnp.log(2.0)]])).tolist()
      [[1.0, 1.0], [1.0, 5.0]]
    """
    raw = jnp.asarray(raw)
    scale = jnp.exp(jnp.diagonal(raw, axis1=-2, axis2=-1))
    lower = scale[..., :, None] * (jnp.tril(raw, -1) + jnp.eye(raw.shape[-1], dtype=raw.dtype))
    return lower @ jnp.swapaxes(lower, -1, -2)


def cholesky_parameters(cov):
    """The ``raw`` of :func:`cholesky_covariance` for a positive-definite ``cov`` (..., n, n) (its inverse)."""
    lower = jnp.linalg.cholesky(jnp.asarray(cov))
    if not bool(jnp.all(jnp.isfinite(lower))):
        raise ValueError("cov must be symmetric positive definite for a Cholesky parameterisation")
    scale = jnp.diagonal(lower, axis1=-2, axis2=-1)
    n = lower.shape[-1]
    return jnp.tril(lower / scale[..., :, None], -1) + jnp.log(scale)[..., :, None] * jnp.eye(n, dtype=lower.dtype)


def unit_interval(raw):
    """A factor in ``(0, 1)`` (e.g. ``c`` of Cortesão 2006 eq. 55): the logistic function of ``raw``."""
    (raw,) = _checks.float_arrays(raw=raw)
    return jax.nn.sigmoid(raw)


def unit_interval_parameters(value):
    """The ``raw`` of :func:`unit_interval` (the logit); ``value`` must be in ``(0, 1)``."""
    value = jnp.asarray(value, float)
    if bool(jnp.any((value <= 0) | (value >= 1))):
        raise ValueError(f"value must lie strictly between 0 and 1, got {value}")
    return jnp.log(value) - jnp.log1p(-value)


def log_labels(symbol: str, names) -> list[str]:
    """Labels of log variances, one per name: ``log_labels("Q", ["F", "p"]) == ["log Q[F]", "log Q[p]"]`` (the
    diagonal of ``symbol``, for :attr:`jaxobs.tuning.TuningProblem.labels`)."""
    return [f"log {symbol}[{name}]" for name in names]


def cholesky_labels(symbol: str, names) -> list[list[str]]:
    """Labels of :func:`cholesky_covariance`'s ``raw`` (n, n) for a covariance ``symbol`` over ``names``: the
    diagonal ``log scale {symbol}[a]``, below it ``coupling {symbol}[a, b]``, above it ``unused``.

    Example:
      >>> from jaxobs.tuning import cholesky_labels
      >>> cholesky_labels("R", ["x", "y"])
      [['log scale R[x]', 'unused'], ['coupling R[y, x]', 'log scale R[y]']]
    """
    names = list(names)
    return [[f"log scale {symbol}[{a}]" if i == j else f"coupling {symbol}[{a}, {b}]" if j < i else "unused"
             for j, b in enumerate(names)] for i, a in enumerate(names)]  # fmt: skip
