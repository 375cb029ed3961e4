"""Matrix equations of control and estimation: the discrete algebraic Riccati equation (:func:`dare`, and
:func:`filter_dare` for the Kalman filter), the continuous one (:func:`care`), the continuous Lyapunov equation
(:func:`lyapunov`), the Stein (discrete Lyapunov) equation (:func:`stein`) and the stability test :func:`is_stable`.

Riccati solvers by structured doubling with a residual and closed-loop stability check, refined by Newton, with
implicit-function gradients; ``converged`` means the stabilising solution was found. The Kalman recursion whose
fixed point the filter DARE is lives in :mod:`jaxobs.kalman_steps`.

Every function here is pure and works eagerly, under ``jit``, ``vmap`` and ``grad``.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs._jit import jit
from jaxobs._linalg import is_positive_definite, is_positive_semidefinite, small_solve, solve_spd, symmetrize
from jaxobs.lti import unobservable_modes

__all__ = [
    "dare",
    "filter_dare",
    "DareSolution",
    "require_converged",
    "stein",
    "is_stable",
    "care",
    "CareSolution",
    "require_care_converged",
    "lyapunov",
]


# --------------------------------------------------------------------------------------------
# Discrete algebraic Riccati equation


class DareSolution(NamedTuple):
    """Stabilising solution of a DARE and how well it solves it.

    Attributes:
      X: (n, n) the solution (for the filter DARE of (Phi', C'): the a-priori steady-state covariance)
      residual: () max |Ricc(X) - X| / max(|X|, scale): scale = max|Q|, or R / |B|^2 when Q = 0
      converged: () the stabilising solution was found: X finite and positive semidefinite, R + B'XB positive
        definite, closed loop stable, residual small
    """

    X: jax.Array
    residual: jax.Array
    converged: jax.Array


# Double-word arithmetic for the DARE residual, whose terms cancel to many digits: a value is the
# unevaluated sum ``hi + lo`` of two floats (Ogita, Rump & Oishi 2005, "Accurate sum and dot product").
# Only additions and exact products are used, so the compiler's fused multiply-adds cannot break it.


def _two_sum(a, b):
    """``(s, e)`` with ``s = fl(a + b)`` and ``s + e = a + b`` exactly (Knuth's TwoSum)."""
    s = a + b
    v = s - a
    return s, (a - (s - v)) + (b - v)


def _slices(a, axis: int, k: int):
    """``a = a1 + a2 + a3`` exactly, ``a1`` and ``a2`` with ``beta`` bits relative to the largest entry of their
    row (``axis=-1``) or column (``axis=-2``), ``beta = (p - 2 - ceil(log2 k)) // 2`` for a ``p``-bit mantissa:
    products of such slices summed over ``k`` terms are exact in any order, with or without fused
    multiply-adds (Ozaki, Ogita, Oishi & Rump 2012). Each slice is ``a`` rounded by adding and subtracting
    ``1.5 * 2^(e + p - 1 - beta)`` (``2^e`` above the row's largest entry)."""
    finfo = jnp.finfo(a.dtype)
    p = finfo.nmant + 1
    beta = (p - 2 - max(k - 1, 1).bit_length()) // 2
    int_type = {64: jnp.int64, 32: jnp.int32, 16: jnp.int16}[finfo.bits]
    bits = jax.lax.bitcast_convert_type(jnp.max(jnp.abs(a), axis=axis, keepdims=True), int_type)
    biased = bits >> finfo.nmant  # biased exponent of the largest entry: it is below 2^(biased - bias + 1)
    # sigma = 1.5 * 2^(e + p - 1 - beta) with e = biased - bias + 1, assembled from its bit pattern
    sigma_bits = ((biased + (p - beta)) << finfo.nmant) | (1 << (finfo.nmant - 1))
    sigma = jax.lax.bitcast_convert_type(sigma_bits.astype(int_type), a.dtype)
    sigma = jax.lax.optimization_barrier(sigma)  # computed once, not in each slice's fused loop
    slices = []
    for _ in range(2):
        hi = (a + sigma) - sigma
        slices.append(hi)
        a, sigma = a - hi, sigma * 2.0**-beta
    return (*slices, a)


def _dot2(a, b):
    """``a @ b`` as a double-word ``(hi, lo)`` with an error of about ``eps^2 k`` times the largest entries of
    ``a``'s row and ``b``'s column: the three leading slice products of :func:`_slices` are exact and summed
    with :func:`_two_sum`, the remaining ones (``eps^2`` smaller) in working precision."""
    k = a.shape[-1]
    a1, a2, a3 = _slices(a, -1, k)
    b1, b2, b3 = _slices(b, -2, k)
    s, e1 = _two_sum(a1 @ b1, a1 @ b2)
    s, e2 = _two_sum(s, a2 @ b1)
    return _two_sum(s, (e1 + e2) + (a1 @ b3 + a2 @ (b2 + b3) + a3 @ b))


def _control_residual(A, B, Q, R, X, R_gain=None):
    """Residual of the control DARE ``X = A'XA - A'XB (R + B'XB)^{-1} B'XA + Q`` at ``X``.

    Returns ``(F, K, A_c)`` with the gain ``K = (R_gain + B'XB)^{-1} B'XA`` (``R_gain`` defaults to ``R``),
    ``A_c = A - B K`` and ``F = A_c' X A_c + K' R K + Q - X``, the residual of one Riccati step with that gain.
    For the optimal gain this is the DARE residual, stationary in ``K`` (errors in the gain enter at second
    order). Its terms cancel to ``|F| << |A_c|^2 |X|``, so ``F`` is evaluated in double-word arithmetic
    (:func:`_dot2`, about ``eps^2`` relative to the terms) and rounded once: Newton steps with it recover the
    digits that a residual in working precision leaves to the DARE's condition number.
    """
    K = _gain(A, B, R if R_gain is None else R_gain, X)
    n, m = B.shape[-2:]
    BK, BK_lo = _dot2(B, K)
    Ac, t = _two_sum(A, -BK)
    Ac, Ac_lo = _two_sum(Ac, t - BK_lo)  # A - B K, double-word
    # A_c' X A_c + K' R K = Z' M Z with Z = [A_c; K], M = blockdiag(X, R): two products
    Z = jnp.concatenate([Ac, K], axis=-2)
    Z_lo = jnp.concatenate([Ac_lo, jnp.zeros_like(K)], axis=-2)
    M = jnp.block([[X, jnp.zeros((n, m), X.dtype)], [jnp.zeros((m, n), X.dtype), R]])
    MZ, t = _dot2(M, Z)
    MZ, MZ_lo = _two_sum(MZ, t + M @ Z_lo)
    W, W_lo = _dot2(Z.T, MZ)
    F, e1 = _two_sum(W, Q)
    F, e2 = _two_sum(F, -X)
    lo = W_lo + (Z.T @ MZ_lo + Z_lo.T @ MZ)
    return symmetrize(F + ((e1 + e2) + lo)), K, Ac


def _doubling(A, G, H, max_iters):
    """Structured doubling algorithm (SDA) for ``X = H + A' X (I + G X)^{-1} A`` (control DARE with
    ``G = B R^{-1} B'``, ``H = Q``).

    SDA iterates ``A <- A W^{-1} A``, ``G <- G + A W^{-1} G A'``, ``H <- H + A' H W^{-1} A`` with
    ``W = I + G H``; ``H_j`` is the Riccati recursion after ``2^j`` steps from zero and ``A_j`` behaves
    like the ``2^j``-th power of the closed loop, so both converge quadratically once ``2^j`` exceeds the
    closed loop's time constant (Chu, Fan, Lin & Wang 2004). Iterates until ``A_j`` is below
    ``eps^(1/4)`` of ``A`` (the remaining error of ``H`` is then about ``sqrt(eps)``, which one Newton step
    removes) or ``max_iters`` is reached. A stalling ``H`` is no stopping criterion: with precise sensors the
    recursion lingers near a non-stabilising solution for many steps before it leaves it.
    """
    n = A.shape[-1]
    eye = jnp.eye(n, dtype=A.dtype)
    small = jnp.finfo(A.dtype).eps ** 0.25 * jnp.maximum(jnp.max(jnp.abs(A)), jnp.finfo(A.dtype).tiny)

    def cond(carry):
        A_j, _, _, it = carry
        return (it < max_iters) & (jnp.max(jnp.abs(A_j)) > small)  # NaN (diverged) stops, flagged later

    def body(carry):
        A, G, H, it = carry
        X = small_solve(eye + G @ H, jnp.concatenate([A, G], axis=1))  # W^-1 [A, G]
        AX = A @ X
        A_new = AX[:, :n]
        G_new = symmetrize(G + AX[:, n:] @ A.T)
        H_new = symmetrize(H + A.T @ H @ X[:, :n])
        return A_new, G_new, H_new, it + 1

    return jax.lax.while_loop(cond, body, (A, symmetrize(G), symmetrize(H), 0))[2]


def _smith(A, E, max_iters: int, atol=None):
    """Smith's doubling for ``X = A X A' + E``: ``X <- X + A_j X A_j'``, ``A_j <- A_j^2``.

    Stops when ``A^(2^j)`` is below ``eps / 1000`` (max norm) or, given ``atol``, once the next term
    ``A_j X A_j'`` is below ``atol`` and ``n max|A_j| < 1``; at most ``max_iters`` squarings. Returns
    ``(X, stable)``: ``stable`` when ``n max|A_j| < 1`` at the end, which proves the spectral radius of ``A``
    below one (``rho(A)^(2^j) <= ||A_j||_2 <= n max|A_j|``). A matrix with an eigenvalue on or outside the
    unit circle never gets there (its powers stay large or overflow): the closed-loop stability test of
    the DARE solvers, by squaring, with no eigenvalue solver (none runs on GPUs in JAX).
    """
    n = A.shape[-1]
    small = jnp.finfo(A.dtype).eps * 1e-3

    def decayed(A_j):  # NaN-safe: XLA's vectorised max may skip NaN entries
        return jnp.all(jnp.isfinite(A_j)) & (n * jnp.max(jnp.abs(A_j)) < 1)

    def cond(carry):
        A_j, X, it = carry
        a = jnp.max(jnp.abs(A_j))
        done = a <= small
        if atol is not None:
            done = done | ((n * a < 1) & (a * a * jnp.max(jnp.abs(X)) <= atol))
        return (it < max_iters) & ~done & jnp.all(jnp.isfinite(A_j))

    def body(carry):
        A_j, X, it = carry
        return A_j @ A_j, X + A_j @ X @ A_j.T, it + 1

    A_j, X, _ = jax.lax.while_loop(cond, body, (A, E, 0))
    return X, decayed(A_j)


def is_stable(A, max_iters: int = 64):
    """Whether the spectral radius of the (n, n) matrix ``A`` is below one, decided by squaring (:func:`_smith`):
    no eigenvalue solver, so it runs on every backend. Works under ``jit``/``vmap``; undecided to rounding for
    spectral radii within about ``1e-14`` of one."""
    (A,) = _square_arguments(A=A)
    return _smith(A, jnp.zeros_like(A), _checks.count("max_iters", max_iters, minimum=1))[1]


def _square_arguments(**matrices):
    """The named (n, n) matrices of :func:`stein`, :func:`lyapunov` and :func:`is_stable` as arrays of one floating
    dtype (:func:`jaxobs._checks.float_arrays`: nested lists, also of traced scalars, are read as arrays), their
    shapes checked at trace time, naming the argument (one matrix, no leading batch axis: ``vmap`` for a batch)."""
    arrays = _checks.float_arrays(**matrices)
    n = jnp.shape(arrays[0])[-1] if jnp.ndim(arrays[0]) else 0
    for name, M in zip(matrices, arrays, strict=True):
        _checks.matrix(name, M, shape=(n, n), square=True)
    return arrays


def stein(A, E, max_iters: int = 64):
    """Solve the Stein (discrete Lyapunov) equation ``X = A X A' + E`` for a stable ``A``
    (``scipy.linalg.solve_discrete_lyapunov(A, E)``).

    Args:
      A: (n, n) with spectral radius below one.  E: (n, n).
      max_iters: at most ``max_iters`` squarings.

    Smith's doubling: ``X <- X + A X A'``, ``A <- A A``, until ``A^(2^j)`` vanishes. Linear in ``E``. Pure; works
    under ``jit``, ``vmap`` and ``grad``: derivatives (forward and reverse) by the implicit function theorem, one
    more Stein solve (``dX = A dX A' + dA X A' + A X dA' + dE``; the adjoint solves the equation of ``A'``), not a
    backpropagation through the doubling.

    Example:
      >>> import numpy as np, scipy.linalg
      >>> A, E = np.array([[0.5, 0.2], [0.0, -0.3]]), np.eye(2)
      >>> bool(np.allclose(stein(A, E), scipy.linalg.solve_discrete_lyapunov(A, E)))
      True
    """
    A, E = _square_arguments(A=A, E=E)
    return _stein(A, E, _checks.count("max_iters", max_iters, minimum=1))


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def _stein(A, E, max_iters):
    """:func:`stein`'s solve on checked arrays, with its implicit derivative."""
    return _smith(A, E, max_iters)[0]


@_stein.defjvp
def _stein_jvp(max_iters, primals, tangents):
    """``dX = A dX A' + (dA X A' + A X dA' + dE)``: a Stein solve as a ``custom_linear_solve``, whose transpose
    (reverse mode) is the Stein equation of ``A'``."""
    (A, E), (dA, dE) = primals, tangents
    X = _stein(A, E, max_iters)
    rhs = dA @ X @ A.T + A @ X @ dA.T + dE
    dX = jax.lax.custom_linear_solve(
        lambda Y: Y - A @ Y @ A.T,
        rhs,
        lambda _, b: _stein(A, b, max_iters),
        lambda _, b: _stein(A.T, b, max_iters),
    )
    return X, dX


class _Newton(NamedTuple):
    """Carry of the Newton iteration in :func:`_solve_control_dare`."""

    X: jax.Array
    F: jax.Array  # residual at X of the gain for R_gain (carried, or evaluated afresh at a round's start)
    size: jax.Array  # relative size of the last correction (inf before the first)
    previous: jax.Array  # ... and of the one before
    first: jax.Array  # ... and of the round's first correction (NaN before it)
    halvings: jax.Array  # corrections 0.3 to 0.7 of the one before, since the last faster one (linear rate)
    stable: jax.Array  # the last correction's closed loop is stable
    steps: jax.Array  # Newton steps so far
    R_gain: jax.Array  # R of the gain used by the next step (regularised in an attempt's first step)


def _solve_control_dare(A, B, Q, R, max_iters, newton_steps):
    """Stabilising solution of the control DARE: doubling for a first approximation, then Newton's method.

    1. SDA (:func:`_doubling`) on ``Q + delta I`` with ``delta = 4 n eps max|Q|`` (just above the rounding
       of ``Q``): where an unstable mode is not excited by ``Q`` the doubling from zero would converge to a
       non-stabilising solution; the tiny regulariser makes its limit the stabilising one.
    2. Newton's method on the true data (Hewer 1971), in defect-correction form: with the residual ``F`` at
       ``X`` and the closed loop ``A_c``, solve the Stein equation ``N = A_c' N A_c + F`` (:func:`_smith`)
       and set ``X <- X + N``, until the correction is at the rounding level of ``X`` (``4 eps``) or stalls
       at the floor set by the conditioning. The residual is evaluated in double-word arithmetic
       (:func:`_control_residual`) at the start of a round and carried from step to step by the exact
       update of :func:`_next_residual`; a round whose first correction exceeded ``eps^(1/3)`` of ``X`` (a
       far start, whose carried residual has drifted by rounding errors of that size) is followed by
       another. From the doubling's answer: one round of two steps.
    3. Precise sensors on unstable plants can break the doubling down (``I + G H`` singular to working
       precision, ``G = B R^{-1} B'``). If no stabilising solution was found, both steps are repeated with
       the doubling run on ``R + (|B'B| |Q| / kappa) I`` for ``kappa`` in ``_KAPPAS``; the regularised
       solution's gain is stabilising, the first Newton step (Hewer's step with that gain) keeps it so,
       and the following steps converge to the solution of the true data.

    Returns ``(X, residual, found)``: the relative residual ``max|F(X)| / max(|X|, scale)`` (``scale`` is
    ``max|Q|``, or ``1 / max|B R^{-1} B'|`` when ``Q = 0``) and whether the stabilising solution was found:
    ``X`` finite and positive semidefinite (to ``sqrt(eps)`` of ``max(|X|, scale)``), ``R + B'XB`` positive
    definite, the last Newton step's closed loop stable (its powers decayed, :func:`_smith`: no
    eigenvalue on or outside the unit circle), and Newton's method settled: its corrections fell to ``4 eps``
    of ``X``, or stalled below ``sqrt(eps)``, and not at a linear rate (four corrections of 0.3 to 0.7 of
    the one before since the last faster one). Where the solution sits on the boundary of existence (a
    closed-loop eigenvalue on the unit circle, reached only in the limit of the regulariser) Newton's
    method converges linearly, halving its corrections to the end: not settled.
    """
    n, m = B.shape[-2:]
    dtype = A.dtype
    eps = jnp.finfo(dtype).eps
    q_scale = jnp.max(jnp.abs(Q))
    g_scale = jnp.max(jnp.abs(B @ solve_spd(R, B.T)))
    scale = jnp.where(q_scale > 0, q_scale, jnp.where(g_scale > 0, 1.0 / g_scale, 1.0))
    H = symmetrize(Q) + 4 * n * eps * scale * jnp.eye(n, dtype=dtype)
    bq = jnp.max(jnp.abs(B.T @ B)) * q_scale

    def step(c: _Newton) -> _Newton:
        K = _gain(A, B, c.R_gain, c.X)
        Ac = A - B @ K
        N, stable = _smith(Ac.T, c.F, max_iters, atol=0.1 * eps * jnp.max(jnp.abs(c.X)))
        N = symmetrize(N)
        X, rounding = _two_sum(c.X, N)
        F = _next_residual(B, R, c.F, X, N, rounding, K, Ac, c.R_gain - R)
        size = jnp.max(jnp.abs(N)) / jnp.maximum(jnp.max(jnp.abs(X)), scale)
        size = jnp.where(jnp.all(jnp.isfinite(N)) & jnp.isfinite(size), size, jnp.inf)
        ratio = size / c.size
        halvings = jnp.where(ratio <= 0.3, 0, jnp.where(ratio < 0.7, c.halvings + 1, c.halvings))
        first = jnp.where(jnp.isnan(c.first), size, c.first)
        return _Newton(X, F, size, c.size, first, halvings, stable, c.steps + 1, R)

    def stepping(c: _Newton):
        go = (c.steps < newton_steps) & (c.size > 4 * eps) & jnp.all(jnp.isfinite(c.X))
        return go & ~_stalled(c.size, c.previous)

    def newton_round(c: _Newton) -> _Newton:
        F = _control_residual(A, B, Q, R, c.X, c.R_gain)[0]
        inf, nan, zero = jnp.asarray(jnp.inf, dtype), jnp.asarray(jnp.nan, dtype), jnp.asarray(0)
        return jax.lax.while_loop(stepping, step, c._replace(F=F, size=inf, previous=inf, first=nan, halvings=zero))

    def another_round(c: _Newton):
        far = jnp.isnan(c.first) | (c.first > eps ** (1 / 3))
        return far & (c.steps < newton_steps) & jnp.all(jnp.isfinite(c.X))

    def attempt(carry):
        *_, j = carry
        R_reg = R + jnp.where(j > 0, bq / jnp.asarray((1.0,) + _KAPPAS, dtype)[j], 0.0) * jnp.eye(m, dtype=dtype)
        X = _doubling(A, B @ solve_spd(R_reg, B.T), H, max_iters)
        inf, nan, zero = jnp.asarray(jnp.inf, dtype), jnp.asarray(jnp.nan, dtype), jnp.asarray(0)
        c = _Newton(X, jnp.zeros_like(X), inf, inf, nan, zero, jnp.asarray(False), zero, R_reg)
        c = jax.lax.while_loop(another_round, newton_round, c)
        converged = (c.size <= 4 * eps) | (_stalled(c.size, c.previous) & (c.size <= jnp.sqrt(eps)))
        settled = converged & (c.halvings < 4)
        return c.X, c.F, c.stable & settled & jnp.all(jnp.isfinite(c.X)), j + 1

    def retry(carry):
        _, _, found, j = carry
        return ~found & (j <= len(_KAPPAS))

    init = (jnp.zeros_like(A), jnp.zeros_like(A), jnp.asarray(False), 0)
    X, F, found, _ = jax.lax.while_loop(retry, attempt, init)
    residual = jnp.max(jnp.abs(F)) / jnp.maximum(jnp.max(jnp.abs(X)), scale)
    well_posed = is_positive_semidefinite(X, scale) & is_positive_definite(R + B.T @ X @ B)
    return X, jnp.where(jnp.all(jnp.isfinite(F)) & jnp.isfinite(residual), residual, jnp.inf), found & well_posed


def _stalled(size, previous):
    """Newton's corrections stopped converging: the last is not below 0.9 of the one before (at the rounding
    floor they wander; a solution on the boundary of existence makes them halve steadily instead, which
    :func:`_solve_control_dare` counts)."""
    return size > 0.9 * previous


def _gain(A, B, R, X):
    """``K = (R + B'XB)^{-1} B'XA``."""
    XB = X @ B
    return solve_spd(symmetrize(R + B.T @ XB), XB.T @ A)


def _next_residual(B, R, F, X_new, N, rounding, K, Ac, dR):
    """The DARE residual at ``X_new = X + N - rounding`` from the residual ``F`` of the gain ``K`` at ``X``.

    The residual of a gain is affine in ``X``, and the optimal gain's is below any other's by a square
    (``S (K - K*)`` completed): with ``A_c = A - B K``, ``S = R + B' X_new B``, ``D = B' N A_c + dR K``
    (``dR = R_gain - R``, the difference ``S_new (K* - K)`` when ``K`` is optimal for ``R_gain`` at ``X``)::

        F(X_new) = F - (N - A_c' N A_c) - D' S^{-1} D + (rounding - A_c' rounding A_c)

    Every term is of the size of ``N`` (or of the rounding of ``X + N``), so working precision suffices where
    evaluating ``F(X_new)`` afresh would cancel ``|A_c|^2 |X|`` down to ``|F|``.
    """
    D = B.T @ N @ Ac + dR @ K
    S = symmetrize(R + B.T @ X_new @ B)
    smith_error = F - (N - Ac.T @ N @ Ac)
    return symmetrize(smith_error - D.T @ solve_spd(S, D) + (rounding - Ac.T @ rounding @ Ac))


@partial(jax.custom_jvp, nondiff_argnums=(4,))
def _control_dare(A, B, Q, R, max_iters):
    return _solve_control_dare(A, B, Q, R, max_iters, _NEWTON_STEPS)


@_control_dare.defjvp
def _control_dare_jvp(max_iters, primals, tangents):
    """Implicit differentiation: at the solution, ``dX = A_c' dX A_c + E`` with ``A_c = A - B K``,
    ``K = (R + B'XB)^{-1} B'XA`` (envelope theorem on the optimal gain) and
    ``E = M + M' + K' dR K + dQ``, ``M = A_c' X (dA - dB K)``. The Stein solve is a
    ``custom_linear_solve`` so reverse mode transposes it (one adjoint Stein solve) instead of
    backpropagating through the iterations. The residual and the flag have zero tangents.
    """
    A, B, Q, R = primals
    dA, dB, dQ, dR = tangents
    X, residual, found = _control_dare(A, B, Q, R, max_iters)
    K = _gain(A, B, R, X)
    Ac = A - B @ K
    M = Ac.T @ X @ (dA - dB @ K)
    E = M + M.T + K.T @ dR @ K + dQ

    def matvec(Y):
        return Y - Ac.T @ Y @ Ac

    def solve(_, b):
        return _stein(Ac.T, b, max_iters)

    def transpose_solve(_, b):
        return _stein(Ac, b, max_iters)

    dX = jax.lax.custom_linear_solve(matvec, E, solve, transpose_solve)
    no_tangent = np.zeros(jnp.shape(found), dtype=jax.dtypes.float0)
    return (X, residual, found), (dX, jnp.zeros_like(residual), no_tangent)


@partial(jit, static_argnames=("max_iters", "tol"), what="dare (behind dlqr, dlqe and the steady-state filters)")
def _solve(A, B, Q, R, *, max_iters: int, tol: float) -> DareSolution:
    """The control DARE ``X = A'XA - A'XB (R + B'XB)^{-1} B'XA + Q`` (``scipy.linalg.solve_discrete_are``'s
    form), compiled once per shape so that eager calls cost one dispatch. ``converged`` also needs the
    residual below ``tol``."""
    X, residual, found = _control_dare(A, B, Q, R, max_iters)
    return DareSolution(X, residual, found & (residual < tol))


def dare(A, B, Q, R, *, max_iters: int = 64, tol: float | None = None) -> DareSolution:
    """Stabilising solution ``X`` of the discrete algebraic Riccati equation.

    As ``scipy.linalg.solve_discrete_are(A, B, Q, R)``::

        X = A' X A - A' X B (R + B' X B)^{-1} B' X A + Q

    Args:
      A: (n, n).  B: (n, m).  Q: (n, n) positive semidefinite.  R: (m, m) positive definite.
      max_iters: at most ``max_iters`` doublings (a horizon of ``2**max_iters`` Riccati steps) and as many
        squarings per Stein solve.
      tol: the relative residual below which the solution counts as converged (default ``sqrt(eps)``).

    The LQR of ``(A, B)`` takes ``X`` as the cost-to-go (:func:`jaxobs.design.dlqr`); the Kalman filter of a
    model ``(Phi, C)`` solves the equation of ``(Phi', C')``, whose ``X`` is the steady-state a-priori
    covariance (Cortesão 2006 eq. 28), with gain ``kalman_gain(X, C, R)``. Solved by structured doubling
    (Chu, Fan, Lin & Wang 2004) refined by Newton's method with a residual in double-word arithmetic: as
    accurate as SciPy's Schur method or more on the DAREX benchmark collection (Abels & Benner 1999), for
    precise sensors (``R`` down to ``1e-12`` of ``Q``) and unstable ``A`` (``benchmarks/dare_accuracy.py``).
    Gradients (forward and reverse) come from the implicit function theorem: one Stein solve, not
    backpropagation through the iterations.

    Returns a :class:`DareSolution` ``(X, residual, converged)``. ``converged`` means the stabilising solution
    was found: ``X`` finite and positive semidefinite (to ``sqrt(eps)`` of its largest entry), ``R + B'XB``
    positive definite, the closed loop ``A - B K`` (``K = (R + B'XB)^{-1} B'XA``) stable, Newton's method
    settled, and the residual below ``tol``. It is False (a flag, never an exception, so it works under ``jit``)
    when no stabilising solution exists (``(A, B)`` not stabilisable, or ``Q`` does not penalise a mode on the
    unit circle), when traced ``Q`` or ``R`` are not semidefinite / definite (the checks that raise eagerly cannot
    run on tracers; the solution is then indefinite), or when the working precision does not resolve the problem
    (e.g. the AOB-3 design in float32); :func:`require_converged` turns the flag into an error message for eager
    callers.

    Example:
      >>> import numpy as np, scipy.linalg
      >>> A, B = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]])
      >>> sol = dare(A, B, np.eye(2), np.eye(1))
      >>> X = scipy.linalg.solve_discrete_are(A, B, np.eye(2), np.eye(1))
      >>> bool(sol.converged), bool(np.allclose(sol.X, X))
      (True, True)
    """
    A, B, Q, R, tol = _riccati_arguments(A, B, Q, R, tol)
    return _solve(A, B, Q, R, max_iters=int(max_iters), tol=tol)


def _riccati_arguments(A, B, Q, R, tol):
    """``(A, B, Q, R, tol)`` of :func:`dare` and :func:`care` as arrays of one floating dtype
    (:func:`jaxobs._checks.float_arrays`: nested lists, also of traced scalars, are read as arrays), checked (shapes
    at trace time, definiteness when concrete); ``tol`` defaults to the square root of its machine epsilon."""
    A, B, Q, R = _checks.float_arrays(A=A, B=B, Q=Q, R=R)
    n = jnp.shape(A)[-1] if jnp.ndim(A) else 0
    _checks.matrix("A", A, shape=(n, n), square=True)
    _checks.matrix("B", B, shape=(n, None))
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True, size=B.shape[-1])
    return A, B, Q, R, float(np.sqrt(np.finfo(A.dtype).eps)) if tol is None else float(tol)


def filter_dare(Phi, C, Q, R, *, what: str = "the filter DARE") -> DareSolution:
    """The filter (estimation) DARE of a model ``(Phi, C)``, ``P = Phi P Phi' - Phi P C'(C P C' + R)^{-1} C P Phi'
    + Q``: :func:`dare` of ``(Phi', C', Q, R)``, whose ``X`` is the steady-state a-priori covariance (Cortesão 2006
    eq. 28; the gain is ``kalman_gain(X, C, R)``). Eagerly, raises ``ValueError`` with the reason (``what`` names
    the solve) when it did not converge; under tracing the flag is in the result.

    Args:
      Phi: (n, n).  C: (p, n).  Q: (n, n) positive semidefinite.  R: (p, p) positive definite.
    """
    Phi, C = _checks.float_arrays(Phi=Phi, C=C)
    _checks.matrix("Phi", Phi, square=True)
    _checks.matrix("C", C, shape=(None, np.shape(Phi)[-1]))
    A, B = jnp.swapaxes(Phi, -1, -2), jnp.swapaxes(C, -1, -2)
    sol = dare(A, B, Q, R)
    require_converged(sol, A, B, Q, R, what=what, estimation=True)
    return sol


def require_converged(sol: DareSolution, A, B, Q, R, *, what: str, estimation: bool = False) -> None:
    """Raise ``ValueError`` saying why when ``sol`` (from :func:`dare` on ``(A, B, Q, R)``) is concrete and not
    converged; do nothing under ``jit``/``vmap``/``grad``, where the flag travels with the result.

    For eager design calls (:func:`jaxobs.design.dlqr`, :func:`jaxobs.observers.kalman.with_steady_state_gain`,
    ...). ``what`` names the caller's solve in the message; ``estimation`` words it for the filter of the model
    ``(Phi, C) = (A', B')``. The reason is found on the concrete data: an unstabilisable (undetectable) mode on
    or outside the unit circle, a unit-circle mode that ``Q`` does not reach, a working precision below
    float64, or else an ill-conditioned problem.
    """
    if not _checks.is_concrete(sol.converged) or bool(np.all(np.asarray(sol.converged))):
        return
    Phi, C = np.swapaxes(np.asarray(A), -1, -2), np.swapaxes(np.asarray(B), -1, -2)
    raise ValueError(f"{what} did not converge: {_failure_reason(sol, Phi, C, Q, control=not estimation)}")


def _failure_reason(sol: DareSolution, Phi, C, Q, control: bool) -> str:
    """Why :func:`dare` found no stabilising solution: the first of the tests below that holds (eager, NumPy)."""
    Phi, C, Q = (np.asarray(M, np.float64) for M in (Phi, C, Q))
    n = Phi.shape[-1]
    pair = "(A, B) is not stabilisable" if control else "(Phi, C) is not detectable"
    seen = "moved by B" if control else "seen by C"
    excite = (
        "penalised by Q: (Q^{1/2}, A) has an unobservable mode on the unit circle"
        if control
        else "excited by Q: (Phi, Q^{1/2}) has an uncontrollable mode on the unit circle"
    )
    scale = max(np.max(np.abs(Phi)), 1.0)
    for lam in np.linalg.eigvals(Phi):
        shifted = lam * np.eye(n) - Phi
        if abs(lam) >= 1 - 1e-9:
            C_scaled = C / max(np.max(np.abs(C)), np.finfo(float).tiny) * scale
            if np.linalg.svd(np.vstack([shifted, C_scaled]), compute_uv=False)[-1] <= 1e-9 * scale:
                return (
                    f"the DARE has no stabilising solution: {pair}, the mode at eigenvalue {lam:.6g} "
                    f"(|eigenvalue| = {abs(lam):.6g} >= 1) is not {seen}"
                )
        if abs(abs(lam) - 1) <= 1e-9:
            Q_scaled = Q / max(np.max(np.abs(Q)), np.finfo(float).tiny) * scale
            if np.linalg.svd(np.hstack([shifted, Q_scaled]), compute_uv=False)[-1] <= 1e-9 * scale:
                return (
                    f"the DARE has no stabilising solution: the mode at eigenvalue {lam:.6g} on the unit circle "
                    f"is not {excite}"
                )
    dtype = np.asarray(sol.X).dtype
    residual = float(np.max(np.asarray(sol.residual)))
    if np.finfo(dtype).eps > np.finfo(np.float64).eps:
        return (
            f"{dtype} does not resolve this problem (residual {residual:.3g}); enable float64 with "
            "jax.config.update('jax_enable_x64', True) and pass float64 arrays"
        )
    return (
        f"no stabilising solution was found in float64 (residual {residual:.3g}, solution "
        f"{'finite' if np.all(np.isfinite(np.asarray(sol.X))) else 'not finite'}): the problem is too "
        "ill-conditioned, e.g. a closed-loop pole within about 1e-8 of the unit circle"
    )


# Newton steps in all (each attempt): from the doubling's answer one or two suffice; from a regularised
# doubling (precise sensors on unstable plants) up to about eight
_NEWTON_STEPS = 16
# kappa of the regularised doublings tried when the first attempt fails: R + (|B'B| |Q| / kappa) I
_KAPPAS = (1e4, 1.0)


# --------------------------------------------------------------------------------------------
# Continuous algebraic Riccati equation (CARE) and continuous Lyapunov equation, by Cayley transforms onto the
# discrete machinery above


class CareSolution(NamedTuple):
    """Stabilising solution of a CARE and how well it solves it.

    Attributes:
      X: (n, n) the solution (for the filter CARE of (A', C'): the steady-state Kalman-Bucy covariance)
      residual: () max |Ric(X)| / the largest of its terms max|Q|, 2 max|XA|, max|XGX| (G = B R^-1 B'),
        floored at gamma^2 / max|G| where Q = 0, gamma the frequency scale of the Cayley shift
      converged: () the stabilising solution was found: X finite and positive semidefinite, R positive definite,
        A - B K Hurwitz, residual small
    """

    X: jax.Array
    residual: jax.Array
    converged: jax.Array


def _norm_bound(A):
    """``max(|A|_1, |A|_inf)``: a bound on the spectral radius of ``A`` and of ``A'``."""
    return jnp.maximum(jnp.max(jnp.sum(jnp.abs(A), axis=-2)), jnp.max(jnp.sum(jnp.abs(A), axis=-1)))


def _cayley(A, gamma):
    """``(A_d, M)`` with ``M = (A - gamma I)^{-1}`` and the Cayley transform ``A_d = (A + gamma I) M = I + 2 gamma M``:
    ``A_d`` is Schur stable exactly when ``A`` is Hurwitz (an eigenvalue ``mu`` maps to ``(mu + gamma)/(mu - gamma)``,
    inside the unit circle for ``Re mu < 0``, near its centre for ``|mu|`` near ``gamma``)."""
    n = A.shape[-1]
    eye = jnp.eye(n, dtype=A.dtype)
    M = small_solve(A - gamma * eye, eye)
    return eye + 2 * gamma * M, M


def _geometric_mean_modulus(M, power: int, bound):
    """``|det M|^(1/power)`` (the geometric mean of the eigenvalue moduli for ``power`` = the size of ``M``) from an
    LU factorisation, clipped to ``[sqrt(eps) bound, bound]``; ``bound`` where ``M`` is singular."""
    logdet = jnp.linalg.slogdet(M)[1] / power
    mean = jnp.where(jnp.isfinite(logdet), jnp.exp(jnp.minimum(logdet, jnp.log(bound))), bound)
    return jnp.clip(mean, jnp.sqrt(jnp.finfo(M.dtype).eps) * bound, bound)


def _lyapunov(A, E, max_iters, atol=None):
    """``(X, stable)`` for ``A' X + X A + E = 0``: with the Cayley transform (:func:`_cayley`) of shift ``gamma``, the
    geometric mean of the eigenvalue moduli of ``A`` (``|det A|^(1/n)``: it maps the spectrum of a Hurwitz ``A``
    symmetrically about the centre of the unit disc, and a Hurwitz ``A`` has no eigenvalue on the positive real axis),
    the equation is the Stein equation ``X = A_d' X A_d + 2 gamma M' E M``, solved by :func:`_smith`, whose ``stable``
    says ``A_d`` is Schur stable, that is ``A`` Hurwitz."""
    bound = _norm_bound(A)
    bound = jnp.where(bound > 0, bound, 1.0)
    gamma = _geometric_mean_modulus(A, A.shape[-1], bound)
    Ad, M = _cayley(A, gamma)
    return _smith(Ad.T, 2 * gamma * M.T @ E @ M, max_iters, atol=atol)


def lyapunov(A, E, max_iters: int = 64):
    """Solve the continuous Lyapunov equation ``A X + X A' + E = 0`` for a Hurwitz ``A`` (python-control's
    ``lyap(A, E)``, SciPy's ``solve_continuous_lyapunov(A, -E)``): the Stein equation of its Cayley transform
    (:func:`stein`'s doubling).

    Args:
      A: (n, n) Hurwitz.  E: (n, n).
      max_iters: at most ``max_iters`` squarings.

    Linear in ``E``. Pure; works under ``jit``, ``vmap`` and ``grad``: derivatives (forward and reverse) by the
    implicit function theorem, one more Lyapunov solve (``A dX + dX A' + dA X + X dA' + dE = 0``; the adjoint
    solves the equation of ``A'``).

    Example:
      >>> import numpy as np
      >>> X = lyapunov(np.array([[-1.0, 2.0], [0.0, -3.0]]), np.eye(2))
      >>> bool(np.allclose(np.array([[-1.0, 2.0], [0.0, -3.0]]) @ X + X @ np.array([[-1.0, 0.0], [2.0, -3.0]]),
      ...                  -np.eye(2)))
      True
    """
    A, E = _square_arguments(A=A, E=E)
    return _lyap(A, E, _checks.count("max_iters", max_iters, minimum=1))


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def _lyap(A, E, max_iters):
    """:func:`lyapunov`'s solve on checked arrays, with its implicit derivative."""
    return _lyapunov(A.T, E, max_iters)[0]


@_lyap.defjvp
def _lyap_jvp(max_iters, primals, tangents):
    """``A dX + dX A' + (dA X + X dA' + dE) = 0``: a Lyapunov solve as a ``custom_linear_solve``, whose transpose
    (reverse mode) is the Lyapunov equation of ``A'``."""
    (A, E), (dA, dE) = primals, tangents
    X = _lyap(A, E, max_iters)
    rhs = dA @ X + X @ dA.T + dE
    dX = jax.lax.custom_linear_solve(
        lambda Y: -(A @ Y + Y @ A.T),
        rhs,
        lambda _, b: _lyap(A, b, max_iters),
        lambda _, b: _lyap(A.T, b, max_iters),
    )
    return X, dX


# Multiples of the nominal Cayley shift of the CARE tried by the conditioning test, in order of preference
_SHIFT_FACTORS = (1.0, 2**-0.5, 2**0.5, 0.5, 2.0, 2**-1.5, 2**1.5)


def _care_nominal_shift(A, G, Q):
    """The nominal Cayley shift of the CARE: the geometric mean of the eigenvalue moduli of the Hamiltonian
    ``H = [[A, -G], [-Q, -A']]``, ``|det H|^(1/2n)``. Where the stabilising solution exists it equals that of the
    closed loop's (the eigenvalues of ``H`` are those of ``A - G X`` and their mirror images), so the transform maps
    the closed-loop spectrum symmetrically about the centre of the unit disc. ``H`` is balanced first (``G / s``,
    ``s Q``, ``s = sqrt(|Q| / |G|)``); the result is clipped to the spectral bound ``|A| + sqrt(|G| |Q|)``."""
    n = A.shape[-1]
    g, q = _norm_bound(G), _norm_bound(Q)
    s = jnp.where((g > 0) & (q > 0), jnp.sqrt(q / jnp.where(g > 0, g, 1.0)), 1.0)
    H = jnp.block([[A, -G / s], [-s * Q, -A.T]])
    bound = _norm_bound(A) + jnp.sqrt(g * q)
    return _geometric_mean_modulus(H, 2 * n, jnp.where(bound > 0, bound, 1.0))


def _care_shift(A, G, Q):
    """The Cayley shift of :func:`_solve_care`: the nominal one (:func:`_care_nominal_shift`) can be an eigenvalue of
    ``A`` (an unstable ``A`` with ``Q = 0`` has ``|det H|^(1/2n) = |det A|^(1/n)``, the eigenvalue itself for
    ``n = 1``), where ``A - gamma I`` is singular. A cheap test moves it away: of the multiples ``_SHIFT_FACTORS`` of
    the nominal value, the one with the smallest ``cond_1(A - gamma I) * max(factor, 1 / factor)`` (the penalty
    prefers the nominal shift)."""
    n = A.shape[-1]
    nominal = _care_nominal_shift(A, G, Q)
    factors = jnp.asarray(_SHIFT_FACTORS, A.dtype)
    shifted = A[None] - (nominal * factors)[:, None, None] * jnp.eye(n, dtype=A.dtype)
    norm1 = lambda M: jnp.max(jnp.sum(jnp.abs(M), axis=-2), axis=-1)
    cond = norm1(shifted) * norm1(jnp.linalg.inv(shifted))
    score = jnp.where(jnp.isfinite(cond), cond, jnp.inf) * jnp.maximum(factors, 1 / factors)
    return nominal * factors[jnp.argmin(score)]


def _care_terms(A, B, Q, R, X):
    """The CARE residual ``F = A'X + XA - X G X + Q`` (``G = B R^{-1} B'``) at ``X``, in the form stationary in the gain
    ``K = R^{-1} B' X``: ``F = A_c' X + X A_c + K' R K + Q`` with ``A_c = A - B K``; its terms cancel to ``|F|``, so it
    is evaluated in double-word arithmetic (:func:`_dot2`) and rounded once. Returns ``(F, K, A_c, size)``, ``size``
    the largest of the terms ``max|Q|``, ``2 max|XA|``, ``max|XGX|`` (the scale of the relative residual)."""
    K = solve_spd(symmetrize(R), B.T @ X)
    BK, BK_lo = _dot2(B, K)
    Ac, t = _two_sum(A, -BK)
    Ac, Ac_lo = _two_sum(Ac, t - BK_lo)  # A - B K, double-word
    XA, XA_lo = _dot2(X, Ac)
    XA_lo = XA_lo + X @ Ac_lo
    RK, RK_lo = _dot2(R, K)
    KRK, KRK_lo = _dot2(K.T, RK)
    KRK_lo = KRK_lo + K.T @ RK_lo
    F, e1 = _two_sum(XA, XA.T)
    F, e2 = _two_sum(F, KRK)
    F, e3 = _two_sum(F, Q)
    F = symmetrize(F + ((e1 + e2 + e3) + (XA_lo + XA_lo.T + KRK_lo)))
    size = jnp.maximum(jnp.max(jnp.abs(Q)), jnp.maximum(2 * jnp.max(jnp.abs(X @ A)), jnp.max(jnp.abs(KRK))))
    return F, K, Ac, size


def _care_to_dare(A, B, Q, R, gamma):
    """The DARE ``(A_d, B_d, Q_d, R_d)`` whose stabilising solution is the CARE's.

    By the Cayley transform of the Hamiltonian with shift ``gamma`` (Chu, Fan & Lin 2005, the initial step of
    their doubling for the CARE). With
    ``A_g = A - gamma I``, ``Z = A_g^{-1} B``, ``Y = A_g^{-T} Q A_g^{-1}``::

        R_d = R + Z' Q Z,   B_d = sqrt(2 gamma) Z,   Q_d = 2 gamma (Y - A_g^{-T} Q Z R_d^{-1} Z' Q A_g^{-1}),
        A_d = (A + gamma I) A_g^{-1} - 2 gamma Z R_d^{-1} Z' Q A_g^{-1}

    (``R_d > 0``, ``Q_d >= 0``): the pencil of the DARE is the Cayley transform ``(H + gamma I)(H - gamma I)^{-1}`` of
    the Hamiltonian ``H = [[A, -G], [-Q, -A']]``, which maps its stable invariant subspace ``[I; X]`` to the DARE's.
    """
    Ad0, M = _cayley(A, gamma)  # (A + gamma I) A_g^{-1}, A_g^{-1}
    Z = M @ B
    QM = Q @ M  # Q A_g^{-1}
    Rd = symmetrize(R + Z.T @ Q @ Z)
    W = solve_spd(Rd, Z.T @ QM)  # R_d^{-1} Z' Q A_g^{-1}
    Qd = symmetrize(2 * gamma * (M.T @ QM - QM.T @ Z @ W))
    Ad = Ad0 - 2 * gamma * Z @ W
    return Ad, jnp.sqrt(2 * gamma) * Z, Qd, Rd


class _CareNewton(NamedTuple):
    """Carry of the Newton(-Kleinman) iteration of :func:`_solve_care`."""

    X: jax.Array
    size: jax.Array  # relative size of the last correction (inf before the first)
    previous: jax.Array  # ... and of the one before
    halvings: jax.Array  # corrections 0.3 to 0.7 of the one before, since the last faster one (linear rate)
    stable: jax.Array  # the last correction's closed loop is Hurwitz
    steps: jax.Array


def _solve_care(A, B, Q, R, max_iters):
    """Stabilising solution of the CARE ``A'X + XA - X B R^{-1} B' X + Q = 0``.

    1. The Cayley transform with the shift ``gamma`` of :func:`_care_shift` (near the geometric mean of the
       closed-loop eigenvalue moduli, away from the eigenvalues of ``A``) maps it to a DARE (:func:`_care_to_dare`)
       solved by :func:`_solve_control_dare` (doubling, Newton's method, regularised retries).
    2. Newton-Kleinman steps on the CARE itself (Kleinman 1968): the residual ``F`` in double-word arithmetic
       (:func:`_care_terms`), the correction from the Lyapunov equation ``A_c' N + N A_c + F = 0``
       (:func:`_lyapunov`), until it is at the rounding level of ``X`` or stalls; they remove what the transform
       lost to rounding (``eps`` times the conditioning of ``A - gamma I`` and of the transformed closed loop).

    Returns ``(X, residual, found)``: ``found`` when ``X`` is finite and positive semidefinite, ``R`` positive
    definite, the last correction's closed loop Hurwitz, and
    Newton's method settled (to ``4 eps``, or stalled below ``sqrt(eps)``, and not at a linear rate: where the
    closed loop has an eigenvalue on the imaginary axis, in the limit of existence, the corrections halve steadily).
    """
    dtype = A.dtype
    eps = jnp.finfo(dtype).eps
    G = B @ solve_spd(symmetrize(R), B.T)
    gamma = _care_shift(A, G, Q)
    X0 = symmetrize(_solve_control_dare(*_care_to_dare(A, B, Q, R, gamma), max_iters, _NEWTON_STEPS)[0])
    q_scale = jnp.max(jnp.abs(Q))
    g_scale = jnp.max(jnp.abs(G))
    # the size of X where it is zero (the relative correction needs a floor): |Q| / gamma, or gamma / |G| when Q = 0
    scale = jnp.where(q_scale > 0, q_scale / gamma, jnp.where(g_scale > 0, gamma / g_scale, 1.0))

    def step(c: _CareNewton) -> _CareNewton:
        F, _, Ac, _ = _care_terms(A, B, Q, R, c.X)
        N, stable = _lyapunov(Ac, F, max_iters, atol=0.1 * eps * jnp.max(jnp.abs(c.X)))
        X = symmetrize(c.X + symmetrize(N))
        size = jnp.max(jnp.abs(N)) / jnp.maximum(jnp.max(jnp.abs(X)), scale)
        size = jnp.where(jnp.all(jnp.isfinite(N)) & jnp.isfinite(size), size, jnp.inf)
        ratio = size / c.size
        halvings = jnp.where(ratio <= 0.3, 0, jnp.where(ratio < 0.7, c.halvings + 1, c.halvings))
        return _CareNewton(X, size, c.size, halvings, stable, c.steps + 1)

    def stepping(c: _CareNewton):
        go = (c.steps < _NEWTON_STEPS) & (c.size > 4 * eps) & jnp.all(jnp.isfinite(c.X))
        return go & ~_stalled(c.size, c.previous)

    inf, zero = jnp.asarray(jnp.inf, dtype), jnp.asarray(0)
    c = jax.lax.while_loop(stepping, step, _CareNewton(X0, inf, inf, zero, jnp.asarray(False), zero))
    F, _, _, size = _care_terms(A, B, Q, R, c.X)
    settled = ((c.size <= 4 * eps) | (_stalled(c.size, c.previous) & (c.size <= jnp.sqrt(eps)))) & (c.halvings < 4)
    residual = jnp.max(jnp.abs(F)) / jnp.maximum(size, gamma * scale)  # floor gamma^2 / |G| where Q = 0
    residual = jnp.where(jnp.isfinite(residual), residual, jnp.inf)
    well_posed = is_positive_semidefinite(c.X, scale) & is_positive_definite(R)
    return c.X, residual, c.stable & settled & jnp.all(jnp.isfinite(c.X)) & well_posed


@partial(jax.custom_jvp, nondiff_argnums=(4,))
def _care(A, B, Q, R, max_iters):
    return _solve_care(A, B, Q, R, max_iters)


@_care.defjvp
def _care_jvp(max_iters, primals, tangents):
    """Implicit differentiation: at the solution, ``A_c' dX + dX A_c + E = 0`` with ``A_c = A - B K``,
    ``K = R^{-1} B' X`` and ``E = M + M' + K' dR K + dQ``, ``M = X (dA - dB K)``; the Lyapunov solve is a
    ``custom_linear_solve`` (its transpose is the Lyapunov equation of ``A_c'``), so reverse mode costs one adjoint
    solve, not a backpropagation through the iterations. The residual and the flag have zero tangents."""
    A, B, Q, R = primals
    dA, dB, dQ, dR = tangents
    X, residual, found = _care(A, B, Q, R, max_iters)
    K = solve_spd(symmetrize(R), B.T @ X)
    Ac = A - B @ K
    M = X @ (dA - dB @ K)
    E = M + M.T + K.T @ dR @ K + dQ

    def matvec(Y):
        return -(Ac.T @ Y + Y @ Ac)

    def solve(_, b):
        return _lyapunov(Ac, b, max_iters)[0]

    def transpose_solve(_, b):
        return _lyapunov(Ac.T, b, max_iters)[0]

    dX = jax.lax.custom_linear_solve(matvec, E, solve, transpose_solve)
    no_tangent = np.zeros(jnp.shape(found), dtype=jax.dtypes.float0)
    return (X, residual, found), (dX, jnp.zeros_like(residual), no_tangent)


@partial(jit, static_argnames=("max_iters", "tol"), what="care (behind lqr and lqe)")
def _solve_care_jit(A, B, Q, R, *, max_iters: int, tol: float) -> CareSolution:
    """:func:`care`'s numerical core, compiled once per shape; ``converged`` also needs the residual below ``tol``."""
    X, residual, found = _care(A, B, Q, R, max_iters)
    return CareSolution(X, residual, found & (residual < tol))


def care(A, B, Q, R, *, max_iters: int = 64, tol: float | None = None) -> CareSolution:
    """Stabilising solution ``X`` of the continuous algebraic Riccati equation.

    As ``scipy.linalg.solve_continuous_are(A, B, Q, R)``::

        A' X + X A - X B R^{-1} B' X + Q = 0

    Args:
      A: (n, n).  B: (n, m).  Q: (n, n) positive semidefinite.  R: (m, m) positive definite.
      max_iters: at most ``max_iters`` doublings and as many squarings per Lyapunov solve.
      tol: the relative residual below which the solution counts as converged (default ``sqrt(eps)``).

    The LQR of ``x' = A x + B u`` takes ``X`` as the cost-to-go (:func:`jaxobs.design.lqr`); the Kalman-Bucy filter
    of ``(A, C)`` solves the equation of ``(A', C')``, whose ``X`` is the steady-state error covariance
    (:func:`jaxobs.design.lqe`; Grip 2010 eq. 1.7). Solved in pure JAX: a Cayley transform, with a shift above the
    spectral radius of the Hamiltonian (never at an eigenvalue of ``A``), maps it to a DARE solved by :func:`dare`'s
    doubling and Newton machinery; Newton-Kleinman steps on the CARE, with the residual in double-word arithmetic,
    then restore the digits the transform lost. Gradients (forward and reverse) by the implicit function theorem:
    one Lyapunov solve.

    Returns a :class:`CareSolution` ``(X, residual, converged)``. ``converged`` means the stabilising solution was
    found: ``X`` finite and positive semidefinite, ``R`` positive definite (traced ``Q`` and ``R`` are not checked
    otherwise), ``A - B K`` Hurwitz (``K = R^{-1} B' X``; tested on its Cayley transform by squaring, no
    eigenvalue solver), Newton's method settled, and the residual below ``tol``. It is False (a flag, never an
    exception, so it works under ``jit``) when no stabilising solution exists (``(A, B)`` not stabilisable, or a
    mode on the imaginary axis that ``Q`` does not penalise) or when the working precision does not resolve the
    problem; eager design calls (:func:`jaxobs.design.lqr`) turn it into an error with the reason.

    Example:
      >>> import numpy as np, scipy.linalg
      >>> A, B = np.array([[0.0, 1.0], [2.0, -1.0]]), np.array([[0.0], [1.0]])
      >>> sol = care(A, B, np.eye(2), np.eye(1))
      >>> X = scipy.linalg.solve_continuous_are(A, B, np.eye(2), np.eye(1))
      >>> bool(sol.converged), bool(np.allclose(sol.X, X))
      (True, True)
    """
    A, B, Q, R, tol = _riccati_arguments(A, B, Q, R, tol)
    return _solve_care_jit(A, B, Q, R, max_iters=int(max_iters), tol=tol)


def require_care_converged(sol: CareSolution, A, B, Q, *, what: str, estimation: bool = False) -> None:
    """:func:`require_converged` for :func:`care` on ``(A, B, Q, R)``: raise ``ValueError`` saying why when ``sol`` is
    concrete and not converged (``estimation`` words it for the Kalman-Bucy filter of ``(A', B')``); nothing under
    tracing. Reasons, tested on the concrete data: an unstabilisable (undetectable) mode in the closed right
    half-plane, a mode on the imaginary axis that ``Q`` does not reach, a working precision below float64, or else
    an ill-conditioned problem."""
    if not _checks.is_concrete(sol.converged) or bool(np.all(np.asarray(sol.converged))):
        return
    A, B, Q = (np.asarray(M, np.float64) for M in (A, B, Q))
    pair, seen = ("(A, B) is not stabilisable", "moved by B")
    if estimation:
        pair, seen = "(A, C) is not detectable", "seen by C"
    for lam in unobservable_modes(A.T, B.T, lambda lam: lam.real >= -1e-9 * max(1.0, abs(lam))):
        raise ValueError(
            f"{what} did not converge: the CARE has no stabilising solution: {pair}, the mode at eigenvalue "
            f"{lam:.6g} (real part >= 0) is not {seen}"
        )
    excite = "excited by the process noise" if estimation else "penalised by Q"
    for lam in unobservable_modes(A, Q, lambda lam: abs(lam.real) <= 1e-9 * max(1.0, abs(lam))):
        raise ValueError(
            f"{what} did not converge: the CARE has no stabilising solution: the mode at eigenvalue {lam:.6g} on the "
            f"imaginary axis is not {excite}"
        )
    dtype = np.asarray(sol.X).dtype
    residual = float(np.max(np.asarray(sol.residual)))
    if np.finfo(dtype).eps > np.finfo(np.float64).eps:
        reason = (
            f"{dtype} does not resolve this problem (residual {residual:.3g}); enable float64 with "
            "jax.config.update('jax_enable_x64', True) and pass float64 arrays"
        )
    else:
        reason = (
            f"no stabilising solution was found in float64 (residual {residual:.3g}): the problem is too "
            "ill-conditioned, e.g. a closed-loop pole within rounding of the imaginary axis"
        )
    raise ValueError(f"{what} did not converge: {reason}")
