"""Riccati recursions: the Kalman covariance step, its sequence over time, and the discrete
algebraic Riccati equation (DARE).

Notation of Cortesão 2006 (seed 000) eq. 27-29, for ``x_k = Phi x_{k-1} + w_k``, ``y_k = C x_k + v_k``,
``E[w w'] = Q``, ``E[v v'] = R``::

    P1_k = Phi P_{k-1} Phi' + Q                      (a-priori covariance, eq. 28)
    K_k  = P1_k C' (C P1_k C' + R)^{-1}              (Kalman gain, eq. 27)
    P_k  = (I - K_k C) P1_k (I - K_k C)' + K_k R K_k'   (a-posteriori, eq. 29 in Joseph form)

Every function here is pure and works eagerly, under ``jit``, ``vmap`` and ``grad``.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks

__all__ = [
    "symmetrize",
    "predict_covariance",
    "update_covariance",
    "riccati_step",
    "covariance_sequence",
    "kalman_gain",
    "dare",
    "DareSolution",
    "stein",
]


def symmetrize(P):
    """``(P + P') / 2``."""
    return 0.5 * (P + jnp.swapaxes(P, -1, -2))


# Sizes up to which ``_small_matmul`` and ``_small_solve`` unroll into fused elementwise loops.
_UNROLL_MAX = 16


def _small_matmul(a, b):
    """``a @ b``; for an inner dimension of at most 16, as a sum of broadcast outer products.

    XLA on CPU runs a batch of small dot products (what ``vmap`` makes of ``Phi @ P``) as one
    library call per matrix; the sum of ``k`` outer products fuses into one elementwise loop over
    the whole batch, about 1.5x faster for a batch of 10 x 10 matrices
    (``benchmarks/kalman_throughput.py``, scenario ``independent``). The result is materialised
    (an optimisation barrier): fused into a consumer, such as a second product, it would be
    recomputed for every element of that consumer.
    """
    k = a.shape[-1]
    if k > _UNROLL_MAX:
        return a @ b
    terms = (a[..., :, j, None] * b[..., None, j, :] for j in range(k))
    total = next(terms)
    for term in terms:
        total = total + term
    return jax.lax.optimization_barrier(total)


def predict_covariance(P, Phi, Q):
    """A-priori covariance ``Phi P Phi' + Q`` (eq. 28).

    Symmetric to rounding only: the filters symmetrise once per step, in :func:`update_covariance`
    (a batched transpose costs XLA on CPU as much as a matrix product).
    """
    return _small_matmul(_small_matmul(Phi, P), jnp.swapaxes(Phi, -1, -2)) + Q


def _solve_spd(S, B):
    """``S^{-1} B`` for a symmetric positive definite ``S``: a division for one output, else Cholesky."""
    if S.shape[-1] == 1:
        return B / S[..., :1, :1]
    return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(S), B)


def _small_solve(W, X):
    """``W^{-1} X`` for a square ``W``: LU with partial pivoting (LAPACK), then, for at most 16
    unknowns, the two triangular solves as unrolled substitution sweeps over the whole batch.

    XLA's CPU triangular solve costs about 3x the LU itself for a batch of 10 x 10 systems; the
    sweeps fuse into one elementwise loop per unknown (``benchmarks/kalman_throughput.py``,
    scenario ``dare``).
    """
    n = W.shape[-1]
    if n > _UNROLL_MAX:
        return jnp.linalg.solve(W, X)
    lu, _, permutation = jax.lax.linalg.lu(W)
    Y = jnp.take_along_axis(X, permutation[..., :, None], axis=-2)
    rows = jnp.arange(n)[:, None]
    lower = jnp.where(rows > rows.T, lu, 0.0)  # unit lower triangular factor, diagonal dropped
    pivots = jnp.diagonal(lu, axis1=-2, axis2=-1)[..., :, None]
    upper = jnp.where(rows < rows.T, lu, 0.0) / pivots  # U = diag(pivots) (I + upper)
    for k in range(n - 1):  # L y = P X
        Y = Y - lower[..., :, k, None] * Y[..., k, None, :]
    Y = Y / pivots
    for k in reversed(range(1, n)):  # (I + upper) x = diag(pivots)^-1 y
        Y = Y - upper[..., :, k, None] * Y[..., k, None, :]
    return Y


def kalman_gain(P1, C, R):
    """Kalman gain ``K = P1 C' (C P1 C' + R)^{-1}`` (eq. 27) by a linear solve, never an inverse.

    With the DARE solution ``P`` (a-priori, see :func:`dare`) this is the steady-state gain.
    """
    CP1 = C @ P1
    return _solve_spd(symmetrize(CP1 @ C.T + R), CP1).T


def update_covariance(P1, C, R):
    """Measurement update in Joseph form: returns ``(P, K)`` (eq. 27 and 29).

    ``P = (I - K C) P1 (I - K C)' + K R K'``: a congruence plus a PSD term, so ``P`` stays symmetric
    positive semidefinite in floating point even for very precise measurements (the expanded
    form ``P1 - K C P1 - ...`` cancels at the scale of ``P1`` and can turn indefinite). With fewer
    outputs than half the states, each factor is applied as a rank-m correction,
    ``(I - K C) X = X - K (C X)``: the same congruence in ``4 n^2 m`` flops instead of ``2 n^3``.
    """
    CP1 = C @ P1
    S = symmetrize(CP1 @ C.T + R)
    K = _solve_spd(S, CP1).T
    n, m = C.shape[-1], C.shape[-2]
    if 2 * m < n:
        left = P1 - K @ CP1  # (I - K C) P1
        congruence = left - (left @ C.T) @ K.T  # ((I - K C) P1) (I - K C)'
    else:
        IKC = jnp.eye(n, dtype=P1.dtype) - K @ C
        congruence = IKC @ P1 @ IKC.T
    return symmetrize(congruence + K @ R @ K.T), K


def riccati_step(P_prev, Phi, C, Q, R):
    """One step of eq. 27-29: ``P_{k-1} -> (P_k, K_k, P1_k)``, all three exactly symmetric."""
    P1 = predict_covariance(P_prev, Phi, Q)
    P, K = update_covariance(P1, C, R)
    return P, K, symmetrize(P1)


class CovarianceSequence(NamedTuple):
    """Stacked over time (leading axis ``num_steps``)."""

    P: jax.Array  # a-posteriori covariances P_k
    K: jax.Array  # Kalman gains K_k
    P_prior: jax.Array  # a-priori covariances P1_k


def covariance_sequence(P_init, Phi, C, Q, R, num_steps: int) -> CovarianceSequence:
    """Gains and covariances of ``num_steps`` Riccati steps from ``P_{-1} = P_init`` (``lax.scan``).

    The papers initialise with ``P_{-1} = Q_0`` (seed 000 §7.2).
    """
    n = Phi.shape[-1]
    _checks.matrix("Phi", Phi, shape=(n, n), square=True)
    _checks.matrix("C", C, shape=(None, n))
    _checks.covariance("P_init", P_init, definite=False, size=n)
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True, size=C.shape[-2])

    def body(P, _):
        P, K, P1 = riccati_step(P, Phi, C, Q, R)
        return P, CovarianceSequence(P, K, P1)

    _, seq = jax.lax.scan(body, P_init, None, length=num_steps)
    return seq


# --------------------------------------------------------------------------------------------
# Discrete algebraic Riccati equation


class DareSolution(NamedTuple):
    """Stabilising solution of the filter DARE and how well it solves it."""

    P: jax.Array  # a-priori steady-state covariance
    residual: jax.Array  # max |Ricc(P) - P| / max |P|
    converged: jax.Array  # P finite and residual below sqrt(machine epsilon)


def _riccati_map(P, Phi, C, Q, R):
    """``Phi P Phi' - Phi P C' (C P C' + R)^{-1} C P Phi' + Q``."""
    S = C @ P @ C.T + R
    PhiPCt = Phi @ P @ C.T
    return Phi @ P @ Phi.T - PhiPCt @ _solve_spd(S, PhiPCt.T) + Q


def _doubling(Phi, C, Q, R, max_iters, tol):
    """Structured doubling algorithm (SDA) for the filter DARE.

    The filter DARE is the control DARE of ``(A, B) = (Phi', C')``. SDA iterates
    ``A <- A W^{-1} A``, ``G <- G + A W^{-1} G A'``, ``H <- H + A' H W^{-1} A`` with ``W = I + G H``,
    from ``A = Phi', G = C' R^{-1} C, H = Q``; ``H_j`` equals the Riccati recursion after ``2^j``
    steps from zero, so it converges quadratically to the stabilising solution. Iterates until
    the relative change of ``H`` is below ``tol`` or ``max_iters`` is reached.
    """
    n = Phi.shape[-1]
    eye = jnp.eye(n, dtype=Phi.dtype)
    G0 = C.T @ _solve_spd(R, C)

    def cond(carry):
        _, _, _, change, it = carry
        return (it < max_iters) & (change > tol)

    def body(carry):
        A, G, H, _, it = carry
        X = _small_solve(eye + G @ H, jnp.concatenate([A, G], axis=1))  # W^-1 [A, G]
        AX = A @ X
        A_new = AX[:, :n]
        G_new = symmetrize(G + AX[:, n:] @ A.T)
        H_new = symmetrize(H + A.T @ H @ X[:, :n])
        change = jnp.max(jnp.abs(H_new - H)) / jnp.maximum(1.0, jnp.max(jnp.abs(H_new)))
        change = jnp.where(jnp.isfinite(change), change, 0.0)  # diverged: stop, flagged later
        return A_new, G_new, H_new, change, it + 1

    init = (Phi.T, symmetrize(G0), symmetrize(Q), jnp.asarray(jnp.inf, Phi.dtype), 0)
    return jax.lax.while_loop(cond, body, init)[2]


def stein(A, E, max_iters: int = 64):
    """Solve the Stein (discrete Lyapunov) equation ``X = A X A' + E`` for a stable ``A``.

    Smith's doubling: ``X <- X + A X A'``, ``A <- A A``, until ``A^(2^j)`` vanishes (at most
    ``max_iters`` squarings). Linear in ``E``.
    """

    def cond(carry):
        A_j, _, it = carry
        return (it < max_iters) & (jnp.max(jnp.abs(A_j)) > jnp.finfo(A_j.dtype).eps * 1e-3)

    def body(carry):
        A_j, X, it = carry
        return A_j @ A_j, X + A_j @ X @ A_j.T, it + 1

    return jax.lax.while_loop(cond, body, (A, E, 0))[1]


@partial(jax.custom_jvp, nondiff_argnums=(4, 5))
def _dare_P(Phi, C, Q, R, max_iters, tol):
    return _doubling(Phi, C, Q, R, max_iters, tol)


@_dare_P.defjvp
def _dare_P_jvp(max_iters, tol, primals, tangents):
    """Implicit differentiation: at the solution, ``dP = Phi_c dP Phi_c' + E`` with
    ``Phi_c = Phi - K_p C``, ``K_p = Phi P C' S^{-1}`` (envelope theorem on the optimal gain) and
    ``E = (dPhi - K_p dC) P Phi_c' + Phi_c P (dPhi - K_p dC)' + K_p dR K_p' + dQ``.
    The Stein solve is a ``custom_linear_solve`` so reverse mode transposes it (one adjoint Stein
    solve) instead of backpropagating through the doubling iterations.
    """
    Phi, C, Q, R = primals
    dPhi, dC, dQ, dR = tangents
    P = _dare_P(Phi, C, Q, R, max_iters, tol)
    S = C @ P @ C.T + R
    Kp = _solve_spd(S, C @ P @ Phi.T).T
    Phi_c = Phi - Kp @ C
    M = (dPhi - Kp @ dC) @ P @ Phi_c.T
    E = M + M.T + Kp @ dR @ Kp.T + dQ

    def matvec(X):
        return X - Phi_c @ X @ Phi_c.T

    def solve(_, b):
        return stein(Phi_c, b)

    def transpose_solve(_, b):
        return stein(Phi_c.T, b)

    dP = jax.lax.custom_linear_solve(matvec, E, solve, transpose_solve)
    return P, dP


def dare(Phi, C, Q, R, *, max_iters: int = 64, tol: float | None = None) -> DareSolution:
    """Stabilising solution of the filter DARE ``P = Phi P Phi' - Phi P C'(C P C' + R)^{-1} C P Phi' + Q``.

    The same ``P`` as ``scipy.linalg.solve_discrete_are(Phi.T, C.T, Q, R)``: the steady-state
    a-priori covariance ``P1`` of eq. 28; the steady-state Kalman gain is
    ``kalman_gain(sol.P, C, R)``. Solved by a structured doubling algorithm (at most
    ``max_iters`` doublings, i.e. a horizon of ``2**max_iters`` Riccati steps). Gradients (forward and
    reverse) come from the implicit function theorem: one Stein solve, not backpropagation
    through the iterations.

    Returns a :class:`DareSolution`; ``converged`` is False (never an exception under ``jit``) when
    ``(Phi, C)`` is not detectable or ``(Phi, Q^{1/2})`` not stabilisable enough for the iteration to
    settle, which shows as a non-finite ``P`` or a large residual.
    """
    n = Phi.shape[-1]
    _checks.matrix("Phi", Phi, shape=(n, n), square=True)
    _checks.matrix("C", C, shape=(None, n))
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True, size=C.shape[-2])
    dtype = jnp.result_type(Phi, C, Q, R, float)
    Phi, C, Q, R = (jnp.asarray(M, dtype) for M in (Phi, C, Q, R))
    eps = jnp.finfo(dtype).eps
    step_tol = float(100 * eps) if tol is None else tol
    P = _dare_P(Phi, C, Q, R, max_iters, step_tol)
    P_stop = jax.lax.stop_gradient(P)
    scale = jnp.maximum(jnp.max(jnp.abs(P_stop)), jnp.finfo(dtype).tiny)
    residual = jnp.max(jnp.abs(_riccati_map(P_stop, Phi, C, Q, R) - P_stop)) / scale
    residual = jnp.where(jnp.isfinite(residual), residual, jnp.inf)
    converged = jnp.all(jnp.isfinite(P_stop)) & (residual < jnp.sqrt(eps))
    return DareSolution(P, residual, converged)
