"""Estimation and control through saturations (Grip 2010, ch. 8 and 9).

Chapter 8 (Grip, Saberi & Wang) stabilises ``x' = A x + B u``, ``y = sat(C x)`` (8.1) globally by a sampled hybrid
controller: on each interval ``(kT, kT + T]`` the input is ``u(kT + tau) = -B' exp(-A' tau) U_k`` (8.2), so that
``x(kT + T) = exp(A T) x(kT) - Bbar U_k`` (8.7, :func:`interval_map`), with ``Bbar`` of (8.4). ``U_k`` (8.3) first
drives each output out of saturation in turn with a geometrically growing push ``alpha^k`` along ``h_j``, using only
the sign of ``y_j``; once every output has been unsaturated at least once, the masked observability Gramian ``D`` and
data vector ``xi`` of (8.5) give ``x(0) = D^{-1} xi`` and the deadbeat command puts ``x`` at the origin one interval
later. :func:`saturated_output_design` checks the assumptions and precomputes the constants,
:func:`simulate_saturated_outputs` runs the loop (jit/vmap over initial states).

Chapter 9 (Grip, Saberi, Stoorvogel, Wang & Roy) detects, from the output of a linear system ``L2`` driven through a
saturation, which input explains a window of output: :func:`hypothesis_residual` is the consistency statistic of
(9.6)-(9.8) for any hypothesis "the window is the free response of ``(F, H)`` plus the response to the known input
``u`` through ``Bf``", and :func:`explains` decides it relative to the quadrature accuracy (the statistic at step
``h`` against the one at ``2 h``). :func:`sandwich_detectors` applies it to the three hypotheses of Theorem 9.1,
:func:`low_gain_are` solves the family (9.12) with :func:`jaxobs.riccati.care`, and :func:`simulate_sandwich` runs
the three-stage controller of §9.4.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.riccati import care

__all__ = [
    "sat",
    "require_controllable_observable",
    "SaturatedOutputDesign",
    "saturated_output_design",
    "interval_map",
    "SaturatedOutputTrace",
    "simulate_saturated_outputs",
    "hypothesis_residual",
    "explains",
    "forced_response",
    "DetectorResult",
    "sandwich_detectors",
    "SandwichDesign",
    "sandwich_design",
    "low_gain_are",
    "SandwichTrace",
    "simulate_sandwich",
    "STAGES",
    "CLASSES",
]


def sat(v):
    """The standard saturation ``sign(v) min(1, |v|)``, componentwise."""
    return jnp.clip(v, -1.0, 1.0)


def _pair_rank(A, B) -> int:
    """Rank of the controllability matrix ``[B, AB, ..., A^{n-1} B]`` (NumPy, SVD with a relative tolerance)."""
    A, B = np.asarray(A, np.float64), np.asarray(B, np.float64)
    blocks, block = [], B
    for _ in range(A.shape[0]):
        blocks.append(block)
        block = A @ block
    K = np.hstack(blocks)
    s = np.linalg.svd(K, compute_uv=False)
    return int(np.sum(s > 1e-10 * max(s[0], np.finfo(float).tiny))) if s.size else 0


def require_controllable_observable(A, B, C, *, names: tuple[str, str] = ("(A, B)", "(C, A)")) -> None:
    """Raise ``ValueError`` naming the pair and its rank when ``(A, B)`` is not controllable or ``(C, A)`` not
    observable (Assumption 8.1, 9.1); eager (skipped on tracers)."""
    if not _checks.is_concrete(A, B, C):
        return
    n = np.shape(A)[0]
    for name, rank, what in ((names[0], _pair_rank(A, B), "controllable"),
                             (names[1], _pair_rank(np.transpose(A), np.transpose(C)), "observable")):  # fmt: skip
        if rank < n:
            matrix = "controllability" if what == "controllable" else "observability"
            raise ValueError(f"{name} must be {what}: its {matrix} matrix has rank {rank} < n = {n}")


def _van_loan(F, Q, T):
    """``int_0^T exp(F (T - s)) Q exp(-F' s) ds``: the top-right block of ``exp([[F, Q], [0, -F']] T)``."""
    n = F.shape[-1]
    top = jnp.concatenate([F, Q], axis=1)
    bottom = jnp.concatenate([jnp.zeros_like(F), -F.T], axis=1)
    return jax.scipy.linalg.expm(jnp.concatenate([top, bottom], axis=0) * T)[:n, n:]


def _matrices(**named):
    dtype = _checks.float_dtype(**named)
    out = []
    for name, value in named.items():
        _checks.matrix(name, value)
        out.append(jnp.asarray(value, dtype))
    return dtype, out


# ---------------------------------------------------------------------------------------------------- chapter 8


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SaturatedOutputDesign:
    """The constants of the controller (8.2)-(8.5); build with :func:`saturated_output_design`.

    Attributes:
      A: (n, n).  B: (n, m).  C: (p, n).  T: () interval length.  alpha: () ``rho ||exp(A T)||``.
      H: (p, n) the push directions, row ``i`` is ``h_i`` (``C_i h_i > 0``).
      expAT: (n, n) ``exp(A T)``.  Bbar: (n, n) (8.4).  Bbar_inv: (n, n) its inverse.
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    T: jax.Array
    alpha: jax.Array
    H: jax.Array
    expAT: jax.Array
    Bbar: jax.Array
    Bbar_inv: jax.Array


ALPHA_NORMS = {"2": 2, "1": 1, "inf": np.inf, "fro": "fro"}


def saturated_output_design(A, B, C, *, T, rho, H=None, alpha_norm: str = "2") -> SaturatedOutputDesign:
    """Check Assumption 8.1 and the design rules, and precompute ``alpha``, ``exp(A T)`` and ``Bbar`` (8.4).

    Args:
      A: (n, n).  B: (n, m).  C: (p, n): the plant (8.1), ``(A, B)`` controllable and ``(C, A)`` observable.
      T: () interval length ``> 0``.  rho: () ``> 1``, ``alpha = rho ||exp(A T)||``.
      H: (p, n) the vectors ``h_i`` as rows, each with ``C_i h_i > 0``; default ``C`` (``h_i = C_i'``, §8.4).
      alpha_norm: the matrix norm of ``||exp(A T)||``: ``"2"`` (spectral, the default), ``"1"``, ``"inf"`` or
        ``"fro"`` (the thesis does not say which; ``grip2010-saturated-outputs`` compares them).

    ``Bbar`` is computed exactly as a block of one matrix exponential (Van Loan 1978). Eager: the assumptions are
    checked on concrete values and raise ``ValueError`` naming the argument.

    Example:
      >>> import numpy as np
      >>> d = saturated_output_design([[0.0]], [[1.0]], [[1.0]], T=0.5, rho=1.1)
      >>> float(d.alpha), float(d.Bbar[0, 0])
      (1.1, 0.5)
    """
    dtype, (A, B, C) = _matrices(A=A, B=B, C=C)
    n = A.shape[0]
    _checks.matrix("A", A, square=True)
    _checks.matrix("B", B, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    _checks.positive_scalar("T", T)
    _checks.positive_scalar("rho", rho)
    if _checks.is_concrete(rho) and float(rho) <= 1:
        raise ValueError(f"rho must be > 1 (alpha = rho ||exp(A T)|| must exceed ||exp(A T)||), got {float(rho)}")
    if alpha_norm not in ALPHA_NORMS:
        raise ValueError(f"alpha_norm must be one of {sorted(ALPHA_NORMS)}, got {alpha_norm!r}")
    H = C if H is None else jnp.asarray(H, dtype)
    _checks.matrix("H", H, shape=C.shape)
    require_controllable_observable(A, B, C)
    if _checks.is_concrete(H, C):
        ch = np.sum(np.asarray(C) * np.asarray(H), axis=1)
        bad = np.flatnonzero(ch <= 0)
        if bad.size:
            raise ValueError(f"H: C_i h_i must be > 0 for every output, got C_i h_i = {ch[bad[0]]:.6g} for i = {bad[0]}")
    T = jnp.asarray(T, dtype)
    expAT = jax.scipy.linalg.expm(A * T)
    alpha = jnp.asarray(rho, dtype) * jnp.linalg.norm(expAT, ord=ALPHA_NORMS[alpha_norm])
    Bbar = _van_loan(A, B @ B.T, T)
    return SaturatedOutputDesign(A, B, C, T, alpha, H, expAT, Bbar, jnp.linalg.inv(Bbar))


def interval_map(design: SaturatedOutputDesign, x, U):
    """``x(kT + T) = exp(A T) x(kT) - Bbar U_k`` (8.7): the exact state one interval later under (8.2)."""
    return design.expAT @ x - design.Bbar @ U


class SaturatedOutputTrace(NamedTuple):
    """One entry per interval ``(kT, kT + T]`` (leading axis ``K``) of :func:`simulate_saturated_outputs`.

    Attributes:
      mode: (K,) int 0 while desaturating, 1 for the deadbeat command (the Gramian was ready at ``kT``).
      j: (K,) int the output pushed out of saturation (``-1`` in deadbeat mode).
      U: (K, n) the command ``U_k``.  x_start: (K, n) ``x(kT)``.  x_end: (K, n) ``x(kT + T)``.
      unsaturated: (K, p) bool: output ``i`` was unsaturated somewhere in the interval (``sigma_i`` grew).
      sigma: (K, p) ``sigma_i(kT + T)`` (8.5a).
      condition: (K,) the condition number of ``D(kT)`` (inf while singular).
      ill_conditioned: (K,) bool: every output had been unsaturated at ``kT`` but ``D(kT)`` was too
        ill-conditioned to invert, so desaturation continued (pushing the least-unsaturated output).
      x_hat: (K, n) ``exp(A kT) D^{-1} xi + mu`` at ``kT`` in deadbeat mode (zeros before).
      x0_hat: (K, n) ``D^{-1}(kT) xi(kT)``, the reconstruction of ``x(0)`` (zeros while not ready).
      xi: (K, n) ``xi(kT + T)``.  D: (K, n, n) ``D(kT + T)`` (8.5b, d).
    """

    mode: jax.Array
    j: jax.Array
    U: jax.Array
    x_start: jax.Array
    x_end: jax.Array
    unsaturated: jax.Array
    sigma: jax.Array
    condition: jax.Array
    ill_conditioned: jax.Array
    x_hat: jax.Array
    x0_hat: jax.Array
    xi: jax.Array
    D: jax.Array


def _condition(D):
    """Condition number of a symmetric positive semidefinite matrix (inf when singular), and its eigenvalues."""
    eig = jnp.linalg.eigvalsh((D + D.T) / 2)
    top = jnp.max(jnp.abs(eig))
    low = eig[0]
    return jnp.where(low > 0, top / jnp.where(low > 0, low, 1), jnp.inf), eig


def _rk4(f, z, d):
    k1 = f(z)
    k2 = f(jax.tree_util.tree_map(lambda a, b: a + d / 2 * b, z, k1))
    k3 = f(jax.tree_util.tree_map(lambda a, b: a + d / 2 * b, z, k2))
    k4 = f(jax.tree_util.tree_map(lambda a, b: a + d * b, z, k3))
    return jax.tree_util.tree_map(lambda a, b, c, e, g: a + d / 6 * (b + 2 * c + 2 * e + g), z, k1, k2, k3, k4)


def simulate_saturated_outputs(
    design: SaturatedOutputDesign, x0, num_intervals: int, *, substeps: int = 200, cond_max: float = 1e12
) -> SaturatedOutputTrace:
    """Run the plant (8.1) under the controller (8.2)-(8.5) for ``num_intervals`` intervals.

    Inside each interval the plant, ``mu`` (8.5c), ``exp(A' t)`` and the integrals ``sigma``, ``xi``, ``D`` (8.5a,
    b, d) are integrated together with ``substeps`` classical RK4 steps (the input ``-B' exp(-A' tau) U_k`` as the
    state ``v' = -A' v``, ``v(0) = U_k``); ``U_k`` is decided at ``kT`` by (8.3). The deadbeat branch is taken when
    every ``sigma_i(kT) > 0`` *and* ``cond(D(kT)) <= cond_max``; otherwise (flagged in ``ill_conditioned``) the
    desaturation goes on with the output of smallest ``sigma_i``, so the state never becomes NaN.

    Args:
      design: :func:`saturated_output_design`.  x0: (n,) the initial state.
      num_intervals: static number of intervals ``K``.  substeps: static RK4 steps per interval.
      cond_max: the largest condition number of ``D`` that is inverted.

    Returns: a :class:`SaturatedOutputTrace`. Pure; works under ``jit`` and ``vmap`` over ``x0``.
    """
    num_intervals = _checks.count("num_intervals", num_intervals, minimum=1)
    substeps = _checks.count("substeps", substeps, minimum=1)
    A, B, C, H = design.A, design.B, design.C, design.H
    n, p = A.shape[0], C.shape[0]
    dtype = A.dtype
    x0 = _checks.vector("x0", x0, n, dtype)
    d = design.T / substeps

    def rhs(z):
        x, mu, v, Psi, sigma, xi, D = z
        u = -B.T @ v
        w = 1 - jnp.abs(sat(C @ x))
        y = sat(C @ x)
        PC = Psi.T @ C.T  # exp(A' t) C'
        return (A @ x + B @ u, A @ mu + B @ u, -A.T @ v, A @ Psi, w, PC @ (w * (y - C @ mu)), (PC * w) @ PC.T)

    def interval(carry, k):
        x, mu, Psi, sigma, xi, D = carry
        cond, _ = _condition(D)
        all_out = jnp.all(sigma > 0)
        ready = all_out & (cond <= cond_max) & jnp.all(jnp.isfinite(D))
        D_safe = jnp.where(ready, D, jnp.eye(n, dtype=dtype))
        x0_hat = jnp.where(ready, jnp.linalg.solve(D_safe, xi), 0)
        x_hat = jnp.where(ready, Psi @ x0_hat + mu, 0)
        U_deadbeat = design.Bbar_inv @ (design.expAT @ x_hat)
        j = jnp.where(jnp.any(sigma == 0), jnp.argmax(sigma == 0), jnp.argmin(sigma))
        y_j = sat(C[j] @ x)
        h = H[j]
        U_push = design.Bbar_inv @ (design.alpha**k * (design.alpha * h - design.expAT @ h) * y_j)
        U = jnp.where(ready, U_deadbeat, U_push)
        z = (x, mu, U, Psi, sigma, xi, D)
        z = jax.lax.fori_loop(0, substeps, lambda _, z: _rk4(rhs, z, d), z)
        x1, mu1, _, Psi1, sigma1, xi1, D1 = z
        out = SaturatedOutputTrace(
            mode=ready.astype(jnp.int32), j=jnp.where(ready, -1, j).astype(jnp.int32), U=U, x_start=x, x_end=x1,
            unsaturated=sigma1 > sigma, sigma=sigma1, condition=cond, ill_conditioned=all_out & ~ready,
            x_hat=x_hat, x0_hat=x0_hat, xi=xi1, D=D1,
        )  # fmt: skip
        return (x1, mu1, Psi1, sigma1, xi1, D1), out

    zeros = jnp.zeros(n, dtype)
    carry = (x0, zeros, jnp.eye(n, dtype=dtype), jnp.zeros(p, dtype), zeros, jnp.zeros((n, n), dtype))
    return jax.lax.scan(interval, carry, jnp.arange(num_intervals, dtype=dtype))[1]
