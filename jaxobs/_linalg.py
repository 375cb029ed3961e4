"""Small dense linear algebra for batches of matrices: solves and Cholesky factors that XLA fuses.

XLA on CPU runs a ``vmap``-ed batch of small LAPACK calls (Cholesky, triangular and LU solves) as one library call
per matrix, plus layout copies around each: for a filter's small innovation covariance those calls cost more than
the rest of the step. Up to a size limit, the functions here unroll the algorithm into elementwise operations on
whole batches, which XLA fuses into a few loops; above it they call ``jax.numpy``/``jax.scipy``. Matrix products
are left to XLA's batched dot. Every function takes a leading batch of any shape (``...``), is pure and works
eagerly, under ``jit``, ``vmap`` and ``grad``. Measured by ``benchmarks/estimation.py`` and
``benchmarks/kalman_throughput.py`` (docs/theory/measurements.md).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular

__all__ = [
    "UNROLL_MAX",
    "FACTOR_UNROLL_MAX",
    "small_solve",
    "cholesky",
    "solve_lower",
    "cho_solve",
    "solve_spd",
    "symmetrize",
    "is_positive_semidefinite",
    "is_positive_definite",
]

UNROLL_MAX = 16
"""Largest system that :func:`small_solve` solves by unrolled substitution sweeps."""

FACTOR_UNROLL_MAX = 8
"""Largest factor (Cholesky, triangular solve) that is unrolled: a larger unrolled factor, such as the 10 x 10
Cholesky of the smoother's gain, compiles longer and runs no faster than LAPACK's (``benchmarks/estimation.py``,
``smooth``)."""


def small_solve(W, X):
    """``W^{-1} X`` for a square ``W`` (..., n, n): LU with partial pivoting (LAPACK), then, for at most
    ``UNROLL_MAX`` unknowns, the two triangular solves as unrolled substitution sweeps over the whole batch.

    XLA's CPU triangular solve of a batch of small systems costs more than the LU itself; the sweeps fuse into
    one elementwise loop per unknown (``benchmarks/kalman_throughput.py``, scenario ``dare``).
    """
    n = W.shape[-1]
    if n > UNROLL_MAX:
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


def cholesky(S):
    """Lower-triangular ``L`` with ``L L' = S`` for a symmetric positive definite ``S`` (..., p, p), read from its
    lower triangle. Up to ``FACTOR_UNROLL_MAX`` rows, the Cholesky-Banachiewicz recursion entry by entry; NaN entries
    where ``S`` is not positive definite, as ``jnp.linalg.cholesky``."""
    p = S.shape[-1]
    if p > FACTOR_UNROLL_MAX:
        return jax.lax.linalg.cholesky(S, symmetrize_input=False)  # LAPACK's potrf reads the lower triangle too
    L = [[None] * p for _ in range(p)]
    for j in range(p):
        for i in range(j, p):
            entry = S[..., i, j]
            for k in range(j):
                entry = entry - L[i][k] * L[j][k]
            L[i][j] = jnp.sqrt(entry) if i == j else entry / L[j][j]
    zero = jnp.zeros_like(S[..., 0, 0])
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(p)], axis=-1) for i in range(p)], axis=-2)


def solve_lower(L, B, *, transpose: bool = False):
    """``L^{-1} B`` (``transpose=True``: ``L'^{-1} B``) for a lower-triangular ``L`` (..., p, p) with a non-zero
    diagonal (only its lower triangle is read) and ``B`` (..., p) or (..., p, k): forward (backward) substitution,
    unrolled up to ``FACTOR_UNROLL_MAX`` rows."""
    p = L.shape[-1]
    vector = B.ndim == L.ndim - 1
    B = B[..., None] if vector else B
    if p > FACTOR_UNROLL_MAX:
        X = solve_triangular(L, B, lower=True, trans=1 if transpose else 0)
    else:
        X = _substitution(L, B, transpose)
    return X[..., 0] if vector else X


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def _substitution(L, B, transpose):
    """The unrolled substitution of :func:`solve_lower` for ``B`` (..., p, k)."""
    p = L.shape[-1]
    factor = jnp.swapaxes(L, -1, -2) if transpose else L  # row i of the triangular system: factor[..., i, :]
    order = range(p - 1, -1, -1) if transpose else range(p)
    rows = [None] * p
    for i in order:
        row = B[..., i, :]
        for k in range(i + 1, p) if transpose else range(i):
            row = row - factor[..., i, k, None] * rows[k]
        rows[i] = row / factor[..., i, i, None]
    return jnp.stack(rows, axis=-2)


@_substitution.defjvp
def _substitution_jvp(transpose, primals, tangents):
    """``dX = L^{-1} (dB - dL X)`` (``L'`` for ``transpose``), one more substitution: differentiating the unrolled
    one entry by entry instead makes the log-likelihood gradient's program larger, slower to compile and no faster
    to run (``benchmarks/estimation.py``, ``grad``)."""
    (L, B), (dL, dB) = primals, tangents
    X = _substitution(L, B, transpose)
    dL = jnp.tril(dL)  # the upper triangle is not read
    return X, _substitution(L, dB - (jnp.swapaxes(dL, -1, -2) if transpose else dL) @ X, transpose)


def cho_solve(L, B):
    """``S^{-1} B`` from the lower Cholesky factor ``L`` of ``S`` (:func:`cholesky`): two substitutions."""
    return solve_lower(L, solve_lower(L, B), transpose=True)


def solve_spd(S, B):
    """``S^{-1} B`` for a symmetric positive definite ``S`` (..., p, p): a division for ``p = 1``, else through
    its Cholesky factor (:func:`cholesky`, :func:`cho_solve`)."""
    if S.shape[-1] == 1:
        return B / S[..., :1, :1]
    return cho_solve(cholesky(S), B)


def symmetrize(P):
    """``(P + P') / 2``."""
    return 0.5 * (P + jnp.swapaxes(P, -1, -2))


def is_positive_semidefinite(S, scale=0.0):
    """Traced test (a bool array over the batch) that ``S`` (..., p, p) is finite and positive semidefinite to
    rounding: the Cholesky factor of ``(S + S') / 2 + delta I`` is finite, ``delta = sqrt(eps) max(max|S|, scale)``
    plus the smallest normal number (an eigenvalue above ``-delta`` passes; ``scale``: the size of ``S`` where it
    is zero, e.g. a Riccati equation's). The Riccati solvers add it to ``converged``
    (:mod:`jaxobs.matrix_equations`)."""
    info = jnp.finfo(S.dtype)
    delta = jnp.sqrt(info.eps) * jnp.maximum(jnp.max(jnp.abs(S), axis=(-2, -1)), scale) + info.tiny
    shifted = symmetrize(S) + delta[..., None, None] * jnp.eye(S.shape[-1], dtype=S.dtype)
    return jnp.all(jnp.isfinite(cholesky(shifted)), axis=(-2, -1))


def is_positive_definite(S):
    """Traced test (a bool array over the batch) that ``S`` (..., p, p) is finite and symmetric positive definite
    in working precision: its Cholesky factor (of ``(S + S') / 2``) is finite with a positive diagonal."""
    L = cholesky(symmetrize(S))
    diagonal = jnp.diagonal(L, axis1=-2, axis2=-1)
    return jnp.all(jnp.isfinite(L), axis=(-2, -1)) & jnp.all(diagonal > 0, axis=-1)
