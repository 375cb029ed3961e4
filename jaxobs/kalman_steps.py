"""The Kalman building blocks every Kalman-type estimator shares (Cortesão 2006 eq. 27-29).

The covariance recursion (:func:`kalman_gain`, :func:`riccati_step`, :func:`covariance_sequence`),
:func:`predict`, the Joseph-form :func:`update` with missing data (a non-finite component of ``y_k`` is
marginalised out), the innovation, its covariance and :func:`innovation_log_likelihood`, and the same steps in
U-D (:func:`bierman_update`) and square-root form (:func:`square_root_predict`, :func:`square_root_update`). The
steady state of the recursion, the filter DARE, is solved in :mod:`jaxobs.matrix_equations`. Every function is
pure (eager, ``jit``, ``vmap``, ``grad``). The equations: docs/theory/estimators.md.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular

from jaxobs import _checks
from jaxobs._linalg import cho_solve, cholesky, solve_lower, solve_spd, symmetrize

__all__ = [
    "predict_covariance",
    "kalman_gain",
    "joseph_covariance",
    "CovarianceUpdate",
    "update_covariance_factors",
    "update_covariance_moments",
    "update_covariance",
    "riccati_step",
    "CovarianceSequence",
    "covariance_sequence",
    "Update",
    "predict",
    "update",
    "moment_update",
    "innovation_gate",
    "bierman_update",
    "ud_factor",
    "observed",
    "observed_model",
    "innovation_log_likelihood",
    "tria",
    "psd_factor",
    "SquareRootUpdate",
    "square_root_predict",
    "square_root_update",
]


# --------------------------------------------------------------------------------------------
# Covariance algebra: the Riccati recursion of eq. 27-29

_UPDATE_SHAPES = "P1 (n, n), C (p, n), R (p, p)"


def predict_covariance(P, Phi, Q):
    """A-priori covariance ``Phi P Phi' + Q`` (eq. 28).

    Symmetric to rounding only: the filters symmetrise once per step, in :func:`update_covariance`
    (a batched transpose costs XLA on CPU as much as a matrix product). ``Phi'`` is materialised behind an
    optimization barrier: folded into the product instead, the transposed operand sends XLA's CPU backend to a
    slower kernel (``benchmarks/estimation.py``, ``filter``; the numbers in docs/theory/measurements.md).
    Shapes: ``P`` (n, n), ``Phi`` (n, n), ``Q`` (n, n).
    """
    P, Phi, Q = _checks.arrays("P (n, n), Phi (n, n), Q (n, n)", P, Phi, Q)
    return Phi @ P @ jax.lax.optimization_barrier(jnp.swapaxes(Phi, -1, -2)) + Q


def kalman_gain(P1, C, R):
    """Kalman gain ``K = P1 C' (C P1 C' + R)^{-1}`` (eq. 27) by a linear solve, never an inverse.

    With the DARE solution ``P`` (a-priori, see :func:`dare`) this is the steady-state gain.
    Shapes: ``P1`` (n, n), ``C`` (p, n), ``R`` (p, p); ``K`` (n, p).
    """
    P1, C, R = _checks.arrays(_UPDATE_SHAPES, P1, C, R)
    CP1 = C @ P1
    return solve_spd(symmetrize(CP1 @ C.T + R), CP1).T


def joseph_covariance(P1, C, R, K, CP1=None):
    """Error covariance after a measurement update with any gain ``K`` (n, p): ``(I - K C) P1 (I - K C)' + K R K'``
    (eq. 29 in Joseph form, exact for every gain, the Kalman gain or not), symmetric. ``CP1``: ``C P1`` if known.
    With fewer outputs than half the states each factor is applied as a rank-p correction, ``(I - K C) X = X - K
    (C X)``: ``4 n^2 p`` flops instead of ``2 n^3``.
    Shapes: ``P1`` (n, n), ``C`` (p, n), ``R`` (p, p), ``K`` (n, p), ``CP1`` (p, n)."""
    P1, C, R, K, CP1 = _checks.arrays(_UPDATE_SHAPES + ", K (n, p), CP1 (p, n)", P1, C, R, K, CP1)
    n, m = C.shape[-1], C.shape[-2]
    if 2 * m < n:
        left = P1 - K @ (C @ P1 if CP1 is None else CP1)  # (I - K C) P1
        congruence = left - (left @ C.T) @ K.T  # ((I - K C) P1) (I - K C)'
    else:
        IKC = jnp.eye(n, dtype=P1.dtype) - K @ C
        congruence = IKC @ P1 @ IKC.T
    return symmetrize(congruence + K @ R @ K.T)


class CovarianceUpdate(NamedTuple):
    """Result of :func:`update_covariance_factors` (``n`` states, ``p`` outputs).

    Attributes:
      P: (n, n) a-posteriori covariance
      K: (n, p) Kalman gain
      S: (p, p) innovation covariance C P1 C' + R
      S_chol: (p, p) its lower Cholesky factor
    """

    P: jax.Array
    K: jax.Array
    S: jax.Array
    S_chol: jax.Array


def update_covariance_factors(P1, C, R, *, joseph: bool = True) -> CovarianceUpdate:
    """Measurement update with the innovation covariance and its Cholesky factor (eq. 27 and 29).

    ``S = C P1 C' + R`` is factored once (``S = L L'``) and the factor serves the gain ``K = P1 C' S^{-1}`` and
    the caller (a log-likelihood needs ``log det S`` and ``L^{-1} e``).

    ``joseph=True`` (default): ``P = (I - K C) P1 (I - K C)' + K R K'`` (:func:`joseph_covariance`), a congruence
    plus a PSD term, so ``P`` stays symmetric positive semidefinite in floating point even for very precise
    measurements. ``joseph=False``: the standard form
    ``P = P1 - W' W``, ``W = L^{-1} C P1`` (``= P1 - K S K'``, as dynamax): one product instead of three or four,
    symmetric, but a difference that cancels at the scale of ``P1`` when a measurement is far more precise than
    the prior, where it can lose definiteness. Shapes: ``P1`` (n, n), ``C`` (p, n), ``R`` (p, p).
    """
    P1, C, R = _checks.arrays(_UPDATE_SHAPES, P1, C, R)
    CP1 = C @ P1
    S = symmetrize(CP1 @ C.T + R)
    if not joseph:
        return update_covariance_moments(P1, CP1, S)
    S_chol = cholesky(S)
    K = cho_solve(S_chol, CP1).T
    return CovarianceUpdate(joseph_covariance(P1, C, R, K, CP1), K, S, S_chol)


def update_covariance_moments(P1, CP1, S) -> CovarianceUpdate:
    """The standard-form update of :func:`update_covariance_factors` from the moments of the predicted measurement:
    ``CP1`` (p, n) its covariance with the state (``C P1``) and ``S`` (p, p) the innovation covariance
    (``C P1 C' + R``), read from its lower triangle. A sigma-point filter has both without a matrix ``C``.
    ``P = P1 - W' W``, ``W = L^{-1} CP1``, ``K = L'^{-1} W``. Shapes: ``P1`` (n, n), ``CP1`` (p, n), ``S`` (p, p)."""
    P1, CP1, S = _checks.arrays("P1 (n, n), CP1 (p, n), S (p, p)", P1, CP1, S)
    S_chol = cholesky(S)
    W = solve_lower(S_chol, CP1)
    return CovarianceUpdate(symmetrize(P1 - W.T @ W), solve_lower(S_chol, W, transpose=True).T, S, S_chol)


def update_covariance(P1, C, R):
    """Measurement update in Joseph form: returns ``(P, K)`` (eq. 27 and 29); see
    :func:`update_covariance_factors`."""
    P, K, _, _ = update_covariance_factors(P1, C, R)
    return P, K


def riccati_step(P_prev, Phi, C, Q, R):
    """One step of eq. 27-29: ``P_{k-1} -> (P_k, K_k, P1_k)``, all three exactly symmetric.
    Shapes: ``P_prev`` (n, n), ``Phi`` (n, n), ``C`` (p, n), ``Q`` (n, n), ``R`` (p, p)."""
    P_prev, Phi, C, Q, R = _checks.arrays("P_prev (n, n), Phi (n, n), C (p, n), Q (n, n), R (p, p)",
                                          P_prev, Phi, C, Q, R)  # fmt: skip
    P1 = predict_covariance(P_prev, Phi, Q)
    P, K = update_covariance(P1, C, R)
    return P, K, symmetrize(P1)


class CovarianceSequence(NamedTuple):
    """Result of :func:`covariance_sequence`, stacked over time (leading axis ``T = num_steps``).

    Attributes:
      P: (T, n, n) a-posteriori covariances P_k
      K: (T, n, p) Kalman gains K_k
      P_prior: (T, n, n) a-priori covariances P1_k
    """

    P: jax.Array
    K: jax.Array
    P_prior: jax.Array


def covariance_sequence(P_init, Phi, C, Q, R, num_steps: int) -> CovarianceSequence:
    """Gains and covariances of ``num_steps`` Riccati steps from ``P_{-1} = P_init`` (``lax.scan``).

    The papers initialise with ``P_{-1} = Q_0`` (Cortesão 2006 §7.2). Shapes: ``P_init`` (n, n), ``Phi`` (n, n),
    ``C`` (p, n), ``Q`` (n, n), ``R`` (p, p); ``num_steps`` static.
    """
    P_init, Phi, C, Q, R = _checks.arrays("P_init (n, n), Phi (n, n), C (p, n), Q (n, n), R (p, p)",
                                          P_init, Phi, C, Q, R)  # fmt: skip
    num_steps = _checks.count("num_steps", num_steps)
    n = Phi.shape[-1]
    _checks.covariance("P_init", P_init, definite=False, size=n)
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True, size=C.shape[-2])

    def body(P, _):
        P, K, P1 = riccati_step(P, Phi, C, Q, R)
        return P, CovarianceSequence(P, K, P1)

    _, seq = jax.lax.scan(body, P_init, None, length=num_steps)
    return seq


# --------------------------------------------------------------------------------------------
# Mean and covariance with missing data and the log-likelihood


class Update(NamedTuple):
    """Result of :func:`update` (shapes for ``n`` states and ``p`` outputs).

    Attributes:
      x: (n,) a-posteriori mean
      P: (n, n) a-posteriori covariance (the given one when a fixed gain is used)
      K: (n, p) gain used (zero columns for missing components)
      innovation: (p,) y_k - C x_prior, 0 for missing components
      n_missing: () number of missing components
      S: (p, p) innovation covariance of the observed components, 1 on a missing diagonal
      log_likelihood: () log p(y_k | y_0..y_{k-1}) of the observed components
    """

    x: jax.Array
    P: jax.Array
    K: jax.Array
    innovation: jax.Array
    n_missing: jax.Array
    S: jax.Array | None = None
    log_likelihood: jax.Array | None = None


def predict(x, P, Phi, Q, Gamma=None, u_prev=None, *, skip=None):
    """A-priori mean and covariance: ``(Phi x + Gamma u_prev, Phi P Phi' + Q)``.

    ``P`` may be ``None`` (fixed-gain filters propagate no covariance); ``Gamma``/``u_prev`` ``None`` for a
    model without inputs. ``skip`` (a traced bool) returns ``(x, P)`` unchanged instead: the first step of a
    filter whose prior is that of ``x_0`` (the state at the first measurement) has no prediction.
    Shapes: ``x`` (n,), ``P`` (n, n), ``Phi`` (n, n), ``Q`` (n, n), ``Gamma`` (n, m), ``u_prev`` (m,), ``skip`` ().
    """
    x, P, Phi, Q, Gamma, u_prev = _checks.arrays("x (n,), P (n, n), Phi (n, n), Q (n, n), Gamma (n, m), u_prev (m,)",
                                                 x, P, Phi, Q, Gamma, u_prev)  # fmt: skip
    _checks.shapes("skip ()", skip)
    x_prior = Phi @ x
    if u_prev is not None:
        x_prior = x_prior + Gamma @ u_prev
    P_prior = None if P is None else predict_covariance(P, Phi, Q)
    if skip is not None:
        x_prior = jnp.where(skip, x, x_prior)
        P_prior = None if P is None else jnp.where(skip, P, P_prior)
    return x_prior, P_prior


def observed(y, dtype=None):
    """``(mask, y_observed)`` of a measurement ``y`` (p,): ``mask`` 1 on finite components and 0 on missing ones
    (in ``dtype``, default ``y``'s), ``y_observed`` with the missing ones set to 0, so that no NaN reaches a
    product or a gradient."""
    (y,) = _checks.arrays("y (p,)", y)
    finite = jnp.isfinite(y)
    return finite.astype(dtype or y.dtype), jnp.where(finite, y, 0.0)


def observed_model(C, R, mask):
    """``(C, R)`` with the rows of missing components (``mask`` 0, from :func:`observed`) removed: rows of ``C``
    zeroed, their rows and columns of ``R`` replaced by a unit variance placeholder. ``C P C' + R`` is then the
    innovation covariance of the observed components with 1 on a missing diagonal, which adds exactly 0 to a
    log-determinant. Shapes: ``C`` (p, n), ``R`` (p, p), ``mask`` (p,)."""
    C, R, mask = _checks.arrays("C (p, n), R (p, p), mask (p,)", C, R, mask)
    return C * mask[:, None], R * jnp.outer(mask, mask) + jnp.diag(1.0 - mask)


def innovation_log_likelihood(innovation, S, n_observed):
    """``log N(innovation; 0, S)`` over ``n_observed`` components: ``-(n log 2 pi + log det S + e' S^{-1} e) / 2``
    with a Cholesky factor of ``S`` (p, p). Components with ``innovation`` 0 and a unit row and column of ``S``
    (missing ones, see :func:`update`) add exactly 0. Shapes: ``innovation`` (p,), ``S`` (p, p), ``n_observed`` ()."""
    innovation, S, n_observed = _checks.arrays("innovation (p,), S (p, p), n_observed ()", innovation, S, n_observed)
    return _log_normal(innovation, cholesky(S), n_observed)


def _log_normal(innovation, S_sqrt, n_observed):
    """:func:`innovation_log_likelihood` from a triangular factor ``S_sqrt`` of ``S`` (diagonal of either sign)."""
    z = solve_lower(S_sqrt, innovation)
    log_det = 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diagonal(S_sqrt))))
    return -0.5 * (n_observed * math.log(2.0 * math.pi) + log_det + z @ z)


def _innovation(y, predicted):
    """``(mask, innovation, n_missing)`` of a measurement ``y`` (p,) against its prediction (p,): the innovation is
    0 on missing components, and ``y`` is masked before the subtraction, so no NaN reaches a gradient."""
    mask, y_observed = observed(y, predicted.dtype)
    return mask, (y_observed - predicted) * mask, jnp.sum(1 - mask.astype(jnp.int32))


def update(x_prior, P_prior, C, R, y, gain=None, *, joseph: bool = True, predicted=None) -> Update:
    """Measurement update of ``(x_prior, P_prior)`` with ``y`` (p,); non-finite components are missing.

    ``predicted`` (p,): the predicted measurement, ``C x_prior`` by default; a nonlinear filter passes its
    linearisation's ``h_bar`` (the innovation is then ``y - h_bar`` and ``C`` the linearised measurement map).

    With ``gain=None`` the gain comes from ``P_prior`` and the Joseph form (``joseph=False``: the standard form,
    see :func:`update_covariance_factors`) updates the covariance; with a
    fixed ``gain`` (n, p) the covariance is returned unchanged and the innovation of missing components is
    zero (so they do not move the estimate).

    ``S`` and ``log_likelihood`` are those of the observed components (exact marginals; 0 when all are missing).
    With a fixed gain they assume it is a Kalman gain of the model ``(C, R)``, such as the steady-state gain: then
    ``C K = I - R S^{-1}`` (eq. 27), so ``S = (I - C K)^{-1} R`` is the steady-state ``C P_prior C' + R`` without
    its ``P_prior``; they are ``None`` when ``R`` is ``None`` (an observer without a noise model).
    Shapes: ``x_prior`` (n,), ``P_prior`` (n, n), ``C`` (p, n), ``R`` (p, p), ``y`` (p,), ``gain`` (n, p).
    """
    x_prior, P_prior, C, R, gain, predicted = _checks.arrays(
        "x_prior (n,), P_prior (n, n), C (p, n), R (p, p), gain (n, p), predicted (p,)",
        x_prior, P_prior, C, R, gain, predicted,
    )  # fmt: skip
    (y,) = _checks.arrays(f"y ({C.shape[-2]},)", y)
    mask, innovation, n_missing = _innovation(y, C @ x_prior if predicted is None else predicted)
    S = ll = None
    if gain is None:
        P, K, S, S_chol = update_covariance_factors(P_prior, *observed_model(C, R, mask), joseph=joseph)
        ll = _log_normal(innovation, S_chol, jnp.sum(mask))
    else:
        P, K = P_prior, gain
        if R is not None:
            S_full = jnp.linalg.solve(jnp.eye(C.shape[-2], dtype=R.dtype) - C @ gain, R)
            S = symmetrize(S_full) * jnp.outer(mask, mask) + jnp.diag(1.0 - mask)
            ll = innovation_log_likelihood(innovation, S, jnp.sum(mask))
    return Update(x_prior + K @ innovation, P, K, innovation, n_missing, S, ll)


def moment_update(x_prior, P_prior, cross, cov, R, y, predicted) -> Update:
    """:func:`update` in standard form from the moments of the predicted measurement ``h(x)``, ``x ~ N(x_prior,
    P_prior)``: its mean ``predicted`` (p,), its covariance with the state ``cross`` (n, p) and its own ``cov``
    (p, p), so that ``S = cov + R`` and ``K = cross S^{-1}`` (the sigma-point update, Särkkä 2013 §5.5). With the
    moments of a linear map, ``cross = P_prior C'`` and ``cov = C P_prior C'``, it is ``update(..., joseph=False)``.
    Missing components of ``y`` are removed as in :func:`update`."""
    x_prior, P_prior, cross, cov, R, predicted = _checks.arrays(
        "x_prior (n,), P_prior (n, n), cross (n, p), cov (p, p), R (p, p), predicted (p,)",
        x_prior, P_prior, cross, cov, R, predicted,
    )  # fmt: skip
    (y,) = _checks.arrays(f"y ({R.shape[-1]},)", y)
    mask, innovation, n_missing = _innovation(y, predicted)
    S = (cov + R) * (mask[:, None] * mask[None, :]) + jnp.diag(1.0 - mask)
    P, K, S, S_chol = update_covariance_moments(P_prior, cross.T * mask[:, None], symmetrize(S))
    ll = _log_normal(innovation, S_chol, jnp.sum(mask))
    return Update(x_prior + K @ innovation, P, K, innovation, n_missing, S, ll)


def innovation_gate(innovation, C, P_prior, R, threshold):
    """The innovation test of a measurement update: a (p,) bool, true for each component whose innovation lies
    within ``threshold`` standard deviations of its prediction, ``|e_i| <= threshold sqrt(S_ii)`` with ``S = C
    P_prior C' + R`` (a per-component validation gate on the normalised innovation, as tracking, navigation and
    vehicle filters reject outliers; Bar-Shalom, Li & Kirubarajan 2001). A filter skips the other components like
    missing ones.
    Shapes: ``innovation`` (p,), ``C`` (p, n), ``P_prior`` (n, n), ``R`` (p, p); ``threshold`` () > 0."""
    innovation, C, P_prior, R, threshold = _checks.arrays(
        "innovation (p,), C (p, n), P_prior (n, n), R (p, p), threshold ()", innovation, C, P_prior, R, threshold
    )
    S_diag = jnp.sum((C @ P_prior) * C, axis=-1) + jnp.diagonal(R)
    return ~(jnp.abs(innovation) > threshold * jnp.sqrt(S_diag))  # NaN (missing) innovations pass


# --------------------------------------------------------------------------------------------
# U-D factorised form: P = U diag(d) U', U unit upper triangular (Bierman 1977)


def ud_factor(P):
    """``(U, d)`` with ``P = U diag(d) U'`` for a symmetric positive semidefinite ``P`` (n, n): ``U`` unit upper
    triangular, ``d`` (n,) >= 0 (Bierman 1977, §III.2, columns from the last). A zero pivot (a singular ``P``)
    gives a zero column above the unit diagonal, so the product is still ``P``."""
    (P,) = _checks.arrays("P (n, n)", P)
    n = P.shape[-1]
    index = jnp.arange(n)

    def column(k, carry):
        A, U, d = carry
        j = n - 1 - k
        pivot = jnp.maximum(A[j, j], 0.0)
        positive = pivot > 0
        u = jnp.where((index < j) & positive, A[:, j] / jnp.where(positive, pivot, 1.0), 0.0)
        A = A - pivot * jnp.outer(u, u)
        return A, U.at[:, j].set(u.at[j].set(1.0)), d.at[j].set(pivot)

    init = (symmetrize(P), jnp.zeros_like(P), jnp.zeros(P.shape[:-1], P.dtype))
    _, U, d = jax.lax.fori_loop(0, n, column, init)
    return U, d


def _bierman_scalar(U, d, h, r):
    """Bierman's update of ``(U, d)`` with one scalar measurement ``z = h x + v``, ``var v = r > 0``: returns
    ``(U, d, k, alpha)`` with the gain ``k`` (n,) and the innovation variance ``alpha = h P h' + r``. Every new
    ``d_j = d_j alpha_{j-1} / alpha_j`` with ``0 < alpha_{j-1} <= alpha_j``, so the factors stay positive
    semidefinite however small ``r`` is."""
    n = d.shape[-1]
    index = jnp.arange(n)
    f = U.T @ h
    v = d * f

    def column(j, carry):
        U, d, b, alpha = carry
        new_alpha = alpha + f[j] * v[j]
        above = index < j
        u_old = U[:, j]
        U = U.at[:, j].set(jnp.where(above, u_old - (f[j] / alpha) * b, u_old))
        b = jnp.where(above, b + u_old * v[j], b).at[j].set(v[j])
        return U, d.at[j].set(d[j] * alpha / new_alpha), b, new_alpha

    U, d, b, alpha = jax.lax.fori_loop(0, n, column, (U, d, jnp.zeros_like(v), r))
    return U, d, b / alpha, alpha


def bierman_update(x_prior, P_prior, C, R, y, *, predicted=None) -> Update:
    """:func:`update` by Bierman's U-D algorithm (Bierman 1977; the EKF of Grip 2010 §2.9 uses it): the same
    :class:`Update` fields, equal to the Joseph form in exact arithmetic.

    ``P_prior`` is factorised as ``U diag(d) U'`` (:func:`ud_factor`), the measurement is whitened with the
    Cholesky factor ``L`` of ``R`` (``L^{-1} y = L^{-1} C x + e``, ``var e = I``; missing components removed as in
    :func:`update`) and its components are processed one at a time, each a scalar update of ``(U, d)`` that keeps
    ``d >= 0``: the a-posteriori covariance ``U diag(d) U'`` stays positive semidefinite as ``R -> 0``, where the
    standard form ``(I - K C) P_prior`` loses definiteness in floating point. The reported gain is that of the
    whole sequence, ``x = x_prior + K (y - C x_prior)``. Shapes and ``predicted`` as in :func:`update` (``R``
    (p, p) positive definite).
    """
    x_prior, P_prior, C, R, predicted = _checks.arrays(
        "x_prior (n,), P_prior (n, n), C (p, n), R (p, p), predicted (p,)", x_prior, P_prior, C, R, predicted
    )
    (y,) = _checks.arrays(f"y ({C.shape[-2]},)", y)
    mask, innovation, n_missing = _innovation(y, C @ x_prior if predicted is None else predicted)
    C_o, R_o = observed_model(C, R, mask)
    L = jnp.linalg.cholesky(symmetrize(R_o))
    H = solve_triangular(L, C_o, lower=True)  # whitened rows, unit variances
    p, n = C.shape[-2], x_prior.shape[-1]
    U, d = ud_factor(P_prior)

    def scalar(carry, i):
        U, d, G = carry  # G: the correction so far, G e, for the whitened innovations e
        U, d, k, _ = _bierman_scalar(U, d, H[i], jnp.ones((), x_prior.dtype))
        G = G - jnp.outer(k, H[i] @ G) + jnp.outer(k, jnp.eye(p, dtype=G.dtype)[i])
        return (U, d, G), None

    (U, d, G), _ = jax.lax.scan(scalar, (U, d, jnp.zeros((n, p), x_prior.dtype)), jnp.arange(p))
    K = solve_triangular(L, G.T, lower=True, trans=1).T  # G L^{-1}
    S = symmetrize(C_o @ P_prior @ C_o.T + R_o)
    ll = innovation_log_likelihood(innovation, S, jnp.sum(mask))
    P = symmetrize((U * d) @ U.T)
    return Update(x_prior + K @ innovation, P, K, innovation, n_missing, S, ll)


# --------------------------------------------------------------------------------------------
# Square-root form: covariances carried as factors, P = P_sqrt P_sqrt'


def _transpose(A):
    return jnp.swapaxes(A, -1, -2)


def tria(A):
    """A lower-triangular ``(n, n)`` factor ``T`` with ``T T' = A A'`` for ``A`` (n, k), ``k >= n``: the
    transposed R factor of a QR decomposition of ``A'`` (Arasaratnam & Haykin 2008). Its diagonal may have
    either sign.

    Its derivative is finite where ``A`` is rank deficient (a singular covariance): differentiating ``T T' = A A'``
    with ``A = T V'`` (``V`` the QR's orthonormal factor) gives ``T^+ dT + (T^+ dT)' = X + X'``,
    ``X = T^+ dA V``, on the column space of ``T``, whose lower-triangular solution ``dT = T (tril(X + X') -
    diag(X))`` is completed by the part of ``dA V`` outside that space, ``(I - T T^+) dA V``; ``T^+`` is the
    pseudo-inverse, which the standard QR derivative replaces by an inverse that does not exist there.
    """
    (A,) = _checks.arrays("A (n, k)", A)
    if A.shape[-1] < A.shape[-2]:
        raise ValueError(f"A must have at least as many columns as rows (tria), got shape {A.shape}")
    return _tria(A)


@jax.custom_jvp
def _tria(A):
    return _transpose(jnp.linalg.qr(_transpose(A), mode="r"))


@_tria.defjvp
def _tria_jvp(primals, tangents):
    (A,), (dA,) = primals, tangents
    V, R = jnp.linalg.qr(_transpose(A), mode="reduced")
    T = _transpose(R)
    T_pinv = jnp.linalg.pinv(T)
    dAV = dA @ V
    X = T_pinv @ dAV
    n = T.shape[-1]
    lower = jnp.tril(X + _transpose(X)) - X * jnp.eye(n, dtype=X.dtype)
    outside = dAV - T @ (T_pinv @ dAV)  # (I - T T^+) dA V
    return T, T @ lower + outside


def psd_factor(M):
    """A lower-triangular factor ``F`` (n, n) with ``F F' = M`` of a symmetric positive semidefinite ``M`` (n, n):
    its Cholesky factor where ``M`` is positive definite, else (a singular ``M``) the eigendecomposition with the
    rounding-level negative eigenvalues clipped, triangularised (:func:`tria`).

    Differentiable also where ``M`` has repeated eigenvalues (``M = q I``, where the derivative of an
    eigendecomposition divides by zero gaps) and where it is singular: ``dF = F Phi(F^+ dM F^+')``, ``Phi`` the
    lower triangle with half the diagonal, ``F^+`` the pseudo-inverse. Where ``M`` is definite that is the
    derivative of the Cholesky factor (Murray 2016, "Differentiation of the Cholesky decomposition"); where it is
    singular, that of the factor of ``M`` on its range (``dF F' + F dF'`` is ``dM`` projected on the range: the
    factor has no derivative across it).

    Example:
      >>> F = psd_factor(jnp.array([[4.0, 2.0], [2.0, 2.0]]))
      >>> F.tolist(), (F @ F.T).tolist()
      ([[2.0, 0.0], [1.0, 1.0]], [[4.0, 2.0], [2.0, 2.0]])
    """
    (M,) = _checks.arrays("M (n, n)", M)
    return _psd_factor(symmetrize(M))


@jax.custom_jvp
def _psd_factor(M):
    L = cholesky(M)
    definite = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L) > 0)

    def eigen(M):
        w, V = jnp.linalg.eigh(M)
        return tria(V * jnp.sqrt(jnp.clip(w, 0.0)))

    return jax.lax.cond(definite, lambda M: L, eigen, M)


@_psd_factor.defjvp
def _psd_factor_jvp(primals, tangents):
    (M,), (dM,) = primals, tangents
    F = _psd_factor(M)
    F_pinv = jnp.linalg.pinv(F)
    X = F_pinv @ symmetrize(dM) @ _transpose(F_pinv)
    return F, F @ (jnp.tril(X) - 0.5 * jnp.diag(jnp.diagonal(X)))


class SquareRootUpdate(NamedTuple):
    """Result of :func:`square_root_update` (shapes for ``n`` states and ``p`` outputs).

    Attributes:
      x: (n,) a-posteriori mean
      P_sqrt: (n, n) lower-triangular factor of the a-posteriori covariance
      K: (n, p) gain (zero columns for missing components)
      innovation: (p,) y_k - C x_prior, 0 for missing components
      n_missing: () number of missing components
      S_sqrt: (p, p) lower-triangular factor of S (as in Update; 1 on a missing diagonal)
      log_likelihood: () log p(y_k | y_0..y_{k-1}) of the observed components
    """

    x: jax.Array
    P_sqrt: jax.Array
    K: jax.Array
    innovation: jax.Array
    n_missing: jax.Array
    S_sqrt: jax.Array
    log_likelihood: jax.Array


def square_root_predict(x, P_sqrt, Phi, Q_sqrt, Gamma=None, u_prev=None, *, skip=None):
    """:func:`predict` with factors: ``P_sqrt`` (n, n) of ``P`` and ``Q_sqrt`` (n, r) of ``Q = Q_sqrt Q_sqrt'``;
    the a-priori factor is ``tria([Phi P_sqrt, Q_sqrt])`` (:func:`tria`). Shapes: ``x`` (n,), ``Phi`` (n, n),
    ``Gamma`` (n, m), ``u_prev`` (m,), ``skip`` ()."""
    x, P_sqrt, Phi, Q_sqrt = _checks.arrays("x (n,), P_sqrt (n, n), Phi (n, n), Q_sqrt (n, r)", x, P_sqrt, Phi, Q_sqrt)
    x_prior, _ = predict(x, None, Phi, None, Gamma, u_prev, skip=skip)
    P_prior = tria(jnp.concatenate([Phi @ P_sqrt, Q_sqrt], axis=-1))
    if skip is not None:
        P_prior = jnp.where(skip, P_sqrt, P_prior)
    return x_prior, P_prior


def square_root_update(x_prior, P_sqrt, C, R_sqrt, y) -> SquareRootUpdate:
    """:func:`update` with factors: ``P_sqrt`` (n, n) of the a-priori covariance, ``R_sqrt`` (p, s) of ``R``.

    One triangularisation of the pre-array (Bierman 1977)::

        [[C P_sqrt, R_sqrt, D], [P_sqrt, 0, 0]]  ->  tria  ->  [[S_sqrt, 0], [G, P_sqrt_post]],  K = G S_sqrt^{-1}

    with the rows of missing components of ``C`` and ``R_sqrt`` zeroed and ``D`` the unit placeholder on their
    diagonal (as in :func:`update`). Shapes: ``x_prior`` (n,), ``C`` (p, n), ``y`` (p,).
    """
    x_prior, P_sqrt, C, R_sqrt, y = _checks.arrays("x_prior (n,), P_sqrt (n, n), C (p, n), R_sqrt (p, s), y (p,)",
                                                   x_prior, P_sqrt, C, R_sqrt, y)  # fmt: skip
    mask, innovation, n_missing = _innovation(y, C @ x_prior)
    p, n = C.shape[-2], P_sqrt.shape[-1]
    dtype = x_prior.dtype
    top = jnp.concatenate([(C * mask[:, None]) @ P_sqrt, R_sqrt * mask[:, None], jnp.diag(1.0 - mask)], axis=-1)
    bottom = jnp.concatenate([P_sqrt, jnp.zeros((n, top.shape[-1] - n), dtype)], axis=-1)
    post = tria(jnp.concatenate([top, bottom], axis=-2))
    S_sqrt, G, P_post = post[:p, :p], post[p:, :p], post[p:, p:]
    K = _transpose(solve_triangular(_transpose(S_sqrt), _transpose(G), lower=False))  # G S_sqrt^{-1}
    ll = _log_normal(innovation, S_sqrt, jnp.sum(mask))
    return SquareRootUpdate(x_prior + K @ innovation, P_post, K, innovation, n_missing, S_sqrt, ll)
