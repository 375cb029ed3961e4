"""Consistency tests of a filter on its outputs: NEES and NIS with their chi-square bands, and innovation whiteness.

A consistent filter's errors match its covariances: the normalised estimation error squared (:func:`nees`, with the
true states of a simulation) and the normalised innovation squared (:func:`nis`) are chi-square distributed with
the state and the measurement dimension as degrees of freedom, and its innovations are white (:func:`whiteness`,
on the sample :func:`autocovariance`). Each works on the outputs of :func:`~jaxobs.observers.base.run` for one
record or a batch of Monte-Carlo runs (Bar-Shalom, Li & Kirubarajan 2001, §5.4; Mehra 1970), under ``jit``,
``vmap`` and ``grad``. The tests and their bands: docs/guides/estimation-breadth.md.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.special import gammainc, ndtri

from jaxobs import _checks
from jaxobs._linalg import cholesky, solve_lower

__all__ = ["ChiSquareTest", "nees", "nis", "chi2_quantile", "autocovariance", "WhitenessTest", "whiteness"]


class ChiSquareTest(NamedTuple):
    """A chi-square consistency test over ``N`` runs of ``T`` samples (:func:`nees`, :func:`nis`).

    Attributes:
      statistic: (N, T) the normalised squared error of every run and sample (0 where nothing is observed)
      dof: (N, T) its degrees of freedom (the state size, or the number of observed measurement components)
      average: (T,) the statistic averaged over the runs, ``(1/N) sum_i eps_k^i``
      lower: (T,) the lower end of the two-sided band of ``average``: ``chi2_a(sum_i dof_k^i) / N``,
        ``a = (1 - confidence) / 2``
      upper: (T,) its upper end, ``chi2_{1-a}(sum_i dof_k^i) / N``
      fraction_inside: () the fraction of samples whose ``average`` lies in its band (about ``confidence`` for a
        consistent filter)
      time_average: () the statistic averaged over every run and sample
      time_band: (2,) the band of ``time_average``, from ``chi2(sum of all dof) / (N T)``: exact for independent
        samples, as the innovations of a consistent filter are (NIS); a filter's estimation errors are correlated
        in time, so for NEES it is too narrow (use the per-sample band over runs)
    """

    statistic: jax.Array
    dof: jax.Array
    average: jax.Array
    lower: jax.Array
    upper: jax.Array
    fraction_inside: jax.Array
    time_average: jax.Array
    time_band: jax.Array


@jax.jit
def chi2_quantile(q, dof):
    """The quantile ``x`` with ``P(chi2(dof) <= x) = q`` for ``0 < q < 1`` and ``dof > 0`` (arrays broadcast; 0
    where ``dof`` is 0): 100 bisections on ``log x`` of the regularised incomplete gamma function
    ``P(dof/2, x/2)`` (``jax.scipy.special.gammainc``), to its rounding. Traceable, so degrees of freedom that
    depend on the data (missing measurements) work under ``jit``.

    Example:
      >>> round(float(chi2_quantile(0.975, 3.0)), 4)  # scipy.stats.chi2.ppf(0.975, 3)
      9.3484
    """
    q, dof = jnp.broadcast_arrays(*(jnp.asarray(a, jnp.result_type(q, dof, float)) for a in (q, dof)))
    positive = dof > 0
    half = jnp.where(positive, dof / 2.0, 1.0)
    # a bracket of log x: exp(-700) is below any quantile a test band asks for, the upper end above it
    low = jnp.full_like(q, -700.0)
    high = jnp.log(jnp.where(positive, dof, 1.0) + 40.0 * jnp.sqrt(jnp.where(positive, dof, 1.0)) + 200.0)

    def bisect(_, bounds):
        low, high = bounds
        middle = 0.5 * (low + high)
        below = gammainc(half, 0.5 * jnp.exp(middle)) < q
        return jnp.where(below, middle, low), jnp.where(below, high, middle)

    low, high = jax.lax.fori_loop(0, 100, bisect, (low, high))
    return jnp.where(positive, jnp.exp(0.5 * (low + high)), 0.0)


def _runs(name: str, value, trailing: int):
    """``value`` with a leading runs axis: (T, ...) becomes (1, T, ...); ``trailing`` is the number of axes after
    the time axis."""
    value = jnp.asarray(value)
    if value.ndim == trailing + 1:
        return value[None]
    if value.ndim != trailing + 2:
        raise ValueError(f"{name} must have shape (T, ...) or (N, T, ...) with {trailing} axes after the time axis, "
                         f"got {value.shape}")  # fmt: skip
    return value


@jax.jit
def _chi_square_test(statistic, dof, confidence) -> ChiSquareTest:
    confidence = jnp.asarray(confidence, statistic.dtype)
    runs, samples = statistic.shape
    tail = (1.0 - confidence) / 2.0
    total = jnp.sum(dof, axis=0)
    average = jnp.mean(statistic, axis=0)
    lower, upper = (chi2_quantile(q, total) / runs for q in (tail, 1.0 - tail))
    inside = (average >= lower) & (average <= upper)
    all_dof = jnp.sum(total)
    band = jnp.stack([chi2_quantile(q, all_dof) for q in (tail, 1.0 - tail)]) / (runs * samples)
    return ChiSquareTest(statistic, dof, average, lower, upper, jnp.mean(inside.astype(statistic.dtype)),
                         jnp.mean(statistic), band)  # fmt: skip


@jax.jit
def _quadratic_forms(error, covariance):
    """``e' M^{-1} e`` of every pair of (N, T, k) errors and (N, T, k, k) covariances, with Cholesky factors."""
    flat = lambda a: a.reshape(-1, *a.shape[2:])  # noqa: E731
    z = jax.vmap(solve_lower)(cholesky(flat(covariance)), flat(error).astype(covariance.dtype))
    return jnp.sum(z * z, axis=-1).reshape(error.shape[:2])


def nees(outputs, x_true, *, confidence=0.95) -> ChiSquareTest:
    """The normalised estimation error squared ``eps_k = (x_k - x_hat_k)' P_k^{-1} (x_k - x_hat_k)`` of a filter
    against the true states of a simulation, and its chi-square test with ``n`` degrees of freedom per sample
    (Bar-Shalom, Li & Kirubarajan 2001, §5.4.2): over ``N`` runs, ``N`` times the average at a sample is
    chi-square with ``N n`` degrees of freedom.

    Args:
      outputs: a filter's outputs with ``x`` (T, n) and ``P`` (T, n, n), or with a leading runs axis (N, T, ...):
        those of the Kalman filter with ``output_covariance``, the EKF, the UKF, an IMM.
      x_true: (T, n) or (N, T, n) the true states.
      confidence: the probability of the two-sided band (default 0.95).

    Returns:
      :class:`ChiSquareTest`.
    """
    x = _runs("outputs.x", outputs.x, 1)
    if getattr(outputs, "P", None) is None:
        raise ValueError("outputs has no covariance P: run the filter with output_covariance=True")
    P = _runs("outputs.P", outputs.P, 2)
    x_true = _runs("x_true", x_true, 1)
    _checks.shape("x_true", x_true, x.shape, "the true states, shaped like outputs.x")
    _checks.shape("outputs.P", P, (*x.shape, x.shape[-1]), "one (n, n) covariance per estimate")
    statistic = _quadratic_forms(x_true - x, P)
    dof = jnp.full(x.shape[:2], x.shape[-1], statistic.dtype)
    return _chi_square_test(statistic, dof, confidence)


def nis(outputs, y=None, *, confidence=0.95) -> ChiSquareTest:
    """The normalised innovation squared ``nu_k = e_k' S_k^{-1} e_k`` of a filter's innovations ``e_k`` and their
    covariances ``S_k``, and its chi-square test with the number of observed components as degrees of freedom
    (Bar-Shalom, Li & Kirubarajan 2001, §5.4.2). Needs no true states: the test of a filter on recorded data.

    Args:
      outputs: a filter's outputs with ``innovation`` (T, p) and ``S`` (T, p, p), or with a leading runs axis:
        those of the Kalman filter (any form), the EKF, the UKF.
      y: the measurements (T, p) or (N, T, p), to count the observed (finite) components when some are missing
        (a missing component contributes 0 to ``nu_k`` and to its degrees of freedom); ``None``: all observed.
      confidence: the probability of the two-sided band (default 0.95).

    Returns:
      :class:`ChiSquareTest`.
    """
    if getattr(outputs, "S", None) is None:
        raise ValueError("outputs has no innovation covariance S: use a Kalman-type filter with a noise model")
    e = _runs("outputs.innovation", outputs.innovation, 1)
    S = _runs("outputs.S", outputs.S, 2)
    _checks.shape("outputs.S", S, (*e.shape, e.shape[-1]), "one (p, p) innovation covariance per innovation")
    statistic = _quadratic_forms(e, S)
    if y is None:
        dof = jnp.full(e.shape[:2], e.shape[-1], statistic.dtype)
    else:
        y = _runs("y", y, 1)
        _checks.shape("y", y, e.shape, "the measurements, shaped like outputs.innovation")
        dof = jnp.sum(jnp.isfinite(y), axis=-1).astype(statistic.dtype)
    return _chi_square_test(statistic, dof, confidence)


def autocovariance(innovation, lags: int):
    """The sample autocovariances ``C_j = (1 / (T - j)) sum_k e_{k+j} e_k'`` of a sequence, ``j = 0 .. lags - 1``,
    averaged over runs: the statistics of :func:`whiteness` and of autocovariance least squares
    (:func:`jaxobs.learning.als`). Unbiased for a stationary zero-mean sequence.

    Args:
      innovation: (T, p) or (N, T, p) (e.g. ``outputs.innovation`` after the filter's transient).
      lags: the number of lags (an integer in ``[1, T - 1]``).

    Returns:
      (lags, p, p) with ``C_j[a, b]`` the covariance of ``e_{k+j}[a]`` and ``e_k[b]``.
    """
    e = _runs("innovation", innovation, 1)
    lags = _checks.count("lags", lags, minimum=1, maximum=max(e.shape[1] - 1, 1), hint="autocovariance lags")
    return _autocovariance(e.astype(jnp.result_type(e, float)), lags=lags)


@partial(jax.jit, static_argnames=("lags",))
def _autocovariance(e, *, lags: int):
    runs, T = e.shape[:2]
    return jnp.stack([jnp.einsum("rka,rkb->ab", e[:, j:], e[:, : T - j]) / (runs * (T - j)) for j in range(lags)])


class WhitenessTest(NamedTuple):
    """The whiteness test of :func:`whiteness`.

    Attributes:
      autocorrelation: (L, p) the normalised autocorrelation ``rho_j = C_j[i, i] / C_0[i, i]`` of each component
        at the lags ``j = 1 .. L``
      bound: (L,) the half-width of the band: white innovations fall within ``+- bound`` with probability
        ``confidence`` (``z / sqrt(N (T - j))``)
      fraction_inside: () the fraction of autocorrelations within their band (about ``confidence`` when white)
    """

    autocorrelation: jax.Array
    bound: jax.Array
    fraction_inside: jax.Array


def whiteness(innovation, lags: int = 20, *, confidence=0.95) -> WhitenessTest:
    """The innovation whiteness test (Mehra 1970; Bar-Shalom, Li & Kirubarajan 2001, §5.4.2): the normalised
    sample autocorrelation of each component at lags ``1 .. lags``; for white innovations each is asymptotically
    normal with variance ``1 / (N (T - j))``, so about ``confidence`` of them fall within ``+- z / sqrt(N (T -
    j))``, ``z`` the normal quantile of ``(1 + confidence) / 2``. A filter with the wrong gain (a wrong ``Q`` or
    ``R``) leaves correlated innovations: many values outside the band.

    Args:
      innovation: (T, p) or (N, T, p), e.g. ``outputs.innovation`` after the transient (without missing
        components).
      lags: the largest lag ``L`` (an integer in ``[1, T - 2]``).
      confidence: the probability of the band (default 0.95).

    Returns:
      :class:`WhitenessTest`.
    """
    e = _runs("innovation", innovation, 1)
    lags = _checks.count("lags", lags, minimum=1, maximum=max(e.shape[1] - 2, 1), hint="autocorrelation lags")
    covariances = autocovariance(e, lags + 1)
    variance = jnp.diagonal(covariances[0])
    rho = jnp.diagonal(covariances[1:], axis1=1, axis2=2) / variance
    z = ndtri(0.5 + 0.5 * jnp.asarray(confidence, rho.dtype))
    pairs = e.shape[0] * (e.shape[1] - jnp.arange(1, lags + 1))
    bound = z / jnp.sqrt(pairs.astype(rho.dtype))
    inside = jnp.abs(rho) <= bound[:, None]
    return WhitenessTest(rho, bound, jnp.mean(inside.astype(rho.dtype)))
