"""Inverse-dynamics state and disturbance observer (Liu & Peng 2002, §2-3).

For ``x' = A x + known(u, y) + B d``, ``y = C x`` (eq. 1) the observer (eq. 2, 4) estimates ``x`` and ``d``; its
gains follow Case 1 (:func:`case1_gains`) or Case 2 (:func:`case2_gains`), its error dynamics
(:func:`error_dynamics`) are a descriptor system whose stability :func:`fact35` tests (Fact 3.5, with the exact
condition), and :func:`design_gains` places its poles. :func:`make_inverse_dynamics` builds the parameters and
:data:`inverse_dynamics_observer` runs it on samples (backward Euler on the descriptor form). Design-time checks
use NumPy on concrete arrays and raise ``ValueError``; under ``jit``/``vmap``/``grad`` they are skipped. The
equations: docs/theory/estimators.md.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from jaxobs import _checks
from jaxobs.lti import obsv
from jaxobs.observers.base import Estimator, EstimatorInputs

__all__ = [
    "InverseDynamicsParams",
    "InverseDynamicsState",
    "InverseDynamicsOutputs",
    "Fact35",
    "inverse_dynamics_observer",
    "make_inverse_dynamics",
    "left_inverse",
    "case1_f2",
    "case1_gains",
    "case2_gains",
    "error_dynamics",
    "fact35",
    "plant_zeros",
    "DesignResult",
    "design_gains",
]


# --------------------------------------------------------------------------------------------- gains


def left_inverse(B, rho=None):
    """Left inverse ``B+ = B^dagger + rho (I - B B^dagger)`` of a full-column-rank ``B`` (``B+ B = I``).

    ``rho`` (``(n_d, n)``, default 0) spans every left inverse. Traceable and differentiable.
    """
    B = jnp.atleast_2d(jnp.asarray(B))
    _checks.matrix("B", B)
    B = B.astype(_checks.float_dtype(B=B, rho=rho))
    n, nd = B.shape
    B_dag = jnp.linalg.solve(B.T @ B, B.T)
    if rho is None:
        return B_dag
    rho = jnp.atleast_2d(jnp.asarray(rho, B.dtype))
    _checks.matrix("rho", rho, shape=(nd, n))
    return B_dag + rho @ (jnp.eye(n, dtype=B.dtype) - B @ B_dag)


@_checks.design_time()
def case1_f2(B, C):
    """The minimum-norm ``F2`` with ``F2 C B = I`` (eq. 5), or ``ValueError`` if none exists (go to Case 2)."""
    B, C = (np.atleast_2d(np.asarray(M, dtype=float)) for M in (B, C))
    CB = C @ B
    r = np.linalg.matrix_rank(CB, tol=1e-10 * max(np.linalg.norm(C) * np.linalg.norm(B), 1e-300))
    if r < B.shape[1]:
        raise ValueError(
            f"B, C: no F2 satisfies F2 C B = I (Case 1, eq. 5): C B has rank {r} < n_d = {B.shape[1]} "
            "(relative degree above one, or fewer independent outputs than disturbances); use case=2 (Lemma 3.3)"
        )
    return np.linalg.pinv(CB)


def _gain_arguments(A, B, C, F1, F2):
    """The plant and the gains of Lemmas 3.1 and 3.3 as 2-D arrays of one dtype, their shapes checked."""
    arrays = (jnp.atleast_2d(M) for M in _checks.float_arrays(A=A, B=B, C=C, F1=F1, F2=F2))
    return _checks.arrays("A (n, n), B (n, d), C (y, n), F1 (d, y), F2 (d, y)", *arrays)


def case1_gains(A, B, C, F1, F2):
    """``(G1, G2, G3)`` of Lemma 3.1: ``-(F1 C + F2 C A)``, ``0``, ``-F2 C``. Traceable. Shapes: ``A`` (n, n),
    ``B`` (n, n_d), ``C`` (n_y, n), ``F1``, ``F2`` (n_d, n_y)."""
    A, B, C, F1, F2 = _gain_arguments(A, B, C, F1, F2)
    G1 = -(F1 @ C + F2 @ C @ A)
    return G1, jnp.zeros_like(G1), -F2 @ C


def case2_gains(A, B, C, F1, F2, rho=None):
    """``(G1, G2, G3)`` of Lemma 3.3, eq. 12-14, with ``B+ = left_inverse(B, rho)``. Traceable. Shapes as
    :func:`case1_gains`."""
    A, B, C, F1, F2 = _gain_arguments(A, B, C, F1, F2)
    Bp = left_inverse(B, rho)
    return -(F1 @ C + Bp @ A), -(F2 @ C - Bp), -Bp


def error_dynamics(A, B, C, K, G1, G2):
    """``(M_e, A_e)`` of ``M_e e' = A_e e``: ``M_e = I - B G2``, ``A_e = A - K C + B G1``.

    With the Case 1 gains this is eq. 8 (``M_e = I``); with the Case 2 gains, eq. 17-18. Traceable. Shapes:
    ``A`` (n, n), ``B`` (n, n_d), ``C`` (n_y, n), ``K`` (n, n_y), ``G1``, ``G2`` (n_d, n).
    """
    arrays = (jnp.atleast_2d(M) for M in _checks.float_arrays(A=A, B=B, C=C, K=K, G1=G1, G2=G2))
    A, B, C, K, G1, G2 = _checks.arrays("A (n, n), B (n, d), C (y, n), K (n, y), G1 (d, n), G2 (d, n)", *arrays)
    n = A.shape[-1]
    return jnp.eye(n, dtype=A.dtype) - B @ G2, A - K @ C + B @ G1


class Fact35(NamedTuple):
    """Stability of ``M_e e' = A_e e`` through the SVD of ``M_e`` (eq. 19-26, Fact 3.5); ``n`` states, ``n_M`` the
    rank of ``M_e``.

    Attributes:
      stable: () bool, exact: ``A22`` nonsingular and ``sigma_M^{-1} S`` Hurwitz (finite poles in the open LHP).
      printed_stable: () bool, Fact 3.5 as printed: ``A22`` and ``S`` Hurwitz.
      rank: int, ``n_M = rank M_e``.
      A11, A12, A21, A22: (n_M, n_M), (n_M, n - n_M), (n - n_M, n_M), (n - n_M, n - n_M), the blocks of ``A_e``
        in the SVD bases of ``M_e``.
      S: (n_M, n_M) ``A11 - A12 A22^{-1} A21``.
      poles: (n_M,) complex, the eigenvalues of ``sigma_M^{-1} S``: the finite poles of the error dynamics.
      fast: (n - n_M,) complex, the eigenvalues of ``A22`` (the "fast" part of Fact 3.4).
    """

    stable: jax.Array
    printed_stable: jax.Array
    rank: int
    A11: jax.Array
    A12: jax.Array
    A21: jax.Array
    A22: jax.Array
    S: jax.Array
    poles: jax.Array
    fast: jax.Array


def fact35(M_e, A_e, *, rank: int | None = None, U=None, V=None, tol: float = 1e-9) -> Fact35:
    """Fact 3.5 test. ``rank`` (n_M) is found from the singular values when ``M_e`` is concrete and
    must be given under tracing. Flags are arrays (``jit``-safe); eigenvalues are complex.

    ``U, V`` (optional) give the SVD bases, e.g. the explicit ones printed in §4.1. The columns of ``U`` and
    ``V`` for the zero singular values are any orthonormal bases of the two null spaces, chosen
    independently, so the sign (and Hurwitz property) of ``A22`` in ``printed_stable`` depends on that
    choice; only its nonsingularity, ``S`` up to congruence and the exact ``stable``/``poles`` do not.
    """
    M_e, A_e = _checks.arrays("M_e (n, n), A_e (n, n)", M_e, A_e)
    n = M_e.shape[-1]
    U_svd, s, Vt = jnp.linalg.svd(M_e)
    U = U_svd if U is None else jnp.asarray(U, A_e.dtype)
    Vt = Vt if V is None else jnp.asarray(V, A_e.dtype).T
    if rank is None:
        if not _checks.is_concrete(M_e):
            raise ValueError("rank must be given when M_e is traced (e.g. under jit or vmap)")
        s_np = np.asarray(s)
        rank = int(np.sum(s_np > tol * max(s_np[0], 1e-300)))
    rank = _checks.count("rank", rank, maximum=n)
    T = U.T @ A_e @ Vt.T
    A11, A12, A21, A22 = T[:rank, :rank], T[:rank, rank:], T[rank:, :rank], T[rank:, rank:]
    if rank == n:
        S, fast = A11, jnp.zeros((0,), jnp.complex128 if A_e.dtype == jnp.float64 else jnp.complex64)
        fast_ok = jnp.asarray(True)
        nonsingular = jnp.asarray(True)
    else:
        S = A11 - A12 @ jnp.linalg.solve(A22, A21)
        fast = jnp.linalg.eigvals(A22)
        fast_ok = jnp.all(fast.real < 0)
        a22_scale = jnp.maximum(jnp.max(jnp.abs(T)), jnp.finfo(T.dtype).tiny)
        nonsingular = jnp.min(jnp.linalg.svd(A22, compute_uv=False)) > tol * a22_scale
    sigma = jnp.diagonal(U.T @ M_e @ Vt.T)[:rank]  # = s[:rank] for an SVD basis
    poles = jnp.linalg.eigvals(S / sigma[:, None])
    slow_printed = jnp.all(jnp.linalg.eigvals(S).real < 0)
    finite = jnp.all(jnp.isfinite(poles))
    stable = nonsingular & finite & jnp.all(poles.real < 0)
    return Fact35(stable, fast_ok & slow_printed & nonsingular, rank, A11, A12, A21, A22, S, poles, fast)


@_checks.design_time()
def plant_zeros(A, B, C):
    """Invariant zeros of ``(A, B, C, 0)`` for ``n_y = n_d`` (finite generalised eigenvalues of the
    Rosenbrock pencil). Design time (SciPy)."""
    A, B, C = (np.atleast_2d(np.asarray(M, dtype=float)) for M in (A, B, C))
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    if p != m:
        raise ValueError(f"C: plant_zeros needs as many outputs as disturbances, got n_y={p}, n_d={m}")
    P = np.block([[A, B], [C, np.zeros((p, m))]])
    E = np.block([[np.eye(n), np.zeros((n, m))], [np.zeros((p, n + m))]])
    w = scipy.linalg.eigvals(P, E)
    return w[np.isfinite(w) & (np.abs(w) < 1e12)]


# --------------------------------------------------------------------------------- run-time observer


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class InverseDynamicsParams:
    """Observer (eq. 2, 4) sampled every ``h`` seconds (``n`` states, ``n_d`` disturbances, ``n_y`` outputs,
    ``m`` inputs).

    Attributes:
      A: (n, n).  B: (n, n_d) disturbance matrix.  C: (n_y, n).
      Bu: (n, m) input matrix of the known term ``known(u, y) = Bu u`` (m = 0 without inputs; for a nonlinear
        ``known`` take ``Bu = I`` and pass its value as the input).
      K: (n, n_y).  F1, F2: (n_d, n_y).  G1: (n_d, n), G2: (n_d, n), G3: (n_d, n) from :func:`case1_gains` or
        :func:`case2_gains`.
      x0: (n,) the estimate the observer integrates from (``x_hat`` one sample before the first).
      h: () sample time.  lowpass_pole: () in ``[0, 1)`` with ``lowpass_order`` (static) sections.
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    Bu: jax.Array
    K: jax.Array
    F1: jax.Array
    F2: jax.Array
    G1: jax.Array
    G2: jax.Array
    G3: jax.Array
    x0: jax.Array
    h: jax.Array
    lowpass_pole: jax.Array
    lowpass_order: int = dataclasses.field(default=0, metadata=dict(static=True))


class InverseDynamicsState(NamedTuple):
    """State of :data:`inverse_dynamics_observer` between samples.

    Attributes:
      x: (n,) ``x_hat_{k-1}``.
      y_prev: (n_y,) the (filtered) ``y_{k-1}``.
      lowpass: (lowpass_order, n_y) the low-pass filter's sections.
      count: () int32, samples seen.
    """

    x: jax.Array
    y_prev: jax.Array
    lowpass: jax.Array
    count: jax.Array


class InverseDynamicsOutputs(NamedTuple):
    """Per-sample outputs of :data:`inverse_dynamics_observer`.

    Attributes:
      x: (n,) ``x_hat_k``.
      d: (n_d,) ``d_hat_k`` (eq. 4).
      innovation: (n_y,) the output error ``y_k - C x_hat_k`` (the term ``K`` acts on in eq. 2).
      y_dot: (n_y,) the backward difference ``y'_k``.
      x_dot: (n,) ``(x_hat_k - x_hat_{k-1}) / h``.
    """

    x: jax.Array
    d: jax.Array
    innovation: jax.Array
    y_dot: jax.Array
    x_dot: jax.Array


_SHAPES = (
    "A (n, n), B (n, d), C (y, n), Bu (n, m), K (n, y), F1 (d, y), F2 (d, y), G1 (d, n), G2 (d, n), "
    "G3 (d, n), x0 (n,), h (), lowpass_pole ()"
)


def _init(params: InverseDynamicsParams) -> InverseDynamicsState:
    _checks.fields("params", params, _SHAPES)
    p = params.C.shape[-2]
    dtype = params.x0.dtype
    return InverseDynamicsState(
        params.x0, jnp.zeros((p,), dtype), jnp.zeros((params.lowpass_order, p), dtype), jnp.zeros((), jnp.int32)
    )


def _step(params: InverseDynamicsParams, state: InverseDynamicsState, inputs: EstimatorInputs):
    _checks.fields("params", params, _SHAPES)
    A, B, C, K, F1, F2 = params.A, params.B, params.C, params.K, params.F1, params.F2
    n, p, m, dtype = A.shape[-1], C.shape[-2], params.Bu.shape[-1], params.x0.dtype
    h = params.h
    first = state.count == 0
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    gamma = jnp.zeros((n,), dtype)
    if inputs.u_prev is not None:
        u = _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype, what="one entry per column of Bu",
                           check_finite=False)  # fmt: skip
        gamma = params.Bu @ u
    sections = []
    for i in range(params.lowpass_order):
        s = jnp.where(first, y, params.lowpass_pole * state.lowpass[i] + (1 - params.lowpass_pole) * y)
        sections.append(s)
        y = s
    lowpass = jnp.stack(sections) if sections else state.lowpass
    y_dot = jnp.where(first, jnp.zeros_like(y), (y - state.y_prev) / h)
    M_e, A_e = error_dynamics(A, B, C, K, params.G1, params.G2)
    Nw = (gamma + B @ (params.G3 @ gamma)) + B @ (F1 @ y) + K @ y + B @ (F2 @ y_dot)
    x = jnp.linalg.solve(M_e - h * A_e, M_e @ state.x + h * Nw)
    x_dot = (x - state.x) / h
    d = F1 @ y + F2 @ y_dot + params.G1 @ x + params.G2 @ x_dot + params.G3 @ gamma
    new_state = InverseDynamicsState(x, y, lowpass, state.count + 1)
    return new_state, InverseDynamicsOutputs(x, d, y - C @ x, y_dot, x_dot)


inverse_dynamics_observer = Estimator(_init, _step)
"""The sampled inverse-dynamics observer as an :class:`~jaxobs.observers.base.Estimator` over
:class:`InverseDynamicsParams`.

Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (n_y,) and (m,): ``known = Bu u_prev`` is the known term over
the step to sample ``k`` (backward Euler evaluates eq. 2 at ``t_k``; to use the input of sample ``k`` itself,
pass that series as ``u_prev``). Each step checks the inputs against the params while tracing and casts them to
the params' dtype. Outputs: :class:`InverseDynamicsOutputs`."""


def make_inverse_dynamics(
    A,
    B,
    C,
    K,
    F1,
    F2=None,
    *,
    h,
    Bu=None,
    case: int | None = None,
    rho=None,
    x0=None,
    lowpass_pole=0.0,
    lowpass_order: int = 0,
    check_stability: bool = True,
) -> InverseDynamicsParams:
    """Build and validate :class:`InverseDynamicsParams`.

    Args:
      A, B, C: plant of eq. 1 (``B`` is the disturbance matrix, full column rank; ``(A, C)`` observable).
      K: ``(n, n_y)`` state-observer gain.  F1, F2: ``(n_d, n_y)`` disturbance gains (eq. 4).
      h: sample time (seconds).
      Bu: ``(n, m)`` input matrix of the known term ``known(u, y) = Bu u`` (default none).
      case: 1 (Lemma 3.1) or 2 (Lemma 3.3); default 1 when ``C B`` has full column rank, else 2.
        Case 1 with ``F2=None`` takes the minimum-norm ``F2`` with ``F2 C B = I``; Case 2 needs ``F2``.
      rho: ``(n_d, n)`` free parameter of ``B+`` (Case 2 only; default 0).
      x0: ``(n,)`` the estimate the observer integrates from (default zeros).
      lowpass_pole: pole in ``[0, 1)`` of the ``lowpass_order`` first-order sections filtering ``y`` (§4.2).
      check_stability: raise ``ValueError`` when the error dynamics are not exponentially stable
        (eq. 8 Hurwitz in Case 1; :func:`fact35` in Case 2).

    Traceable (for gradient-based tuning of ``K, F1, F2, rho``): with traced arguments the checks are skipped.
    """
    A, B, C, K, F1 = (jnp.atleast_2d(jnp.asarray(M)) for M in (A, B, C, K, F1))
    F2, rho = (None if M is None else jnp.atleast_2d(jnp.asarray(M)) for M in (F2, rho))
    dtype = _checks.float_dtype(A=A, B=B, C=C, K=K, F1=F1, F2=F2, rho=rho, x0=x0, h=h, lowpass_pole=lowpass_pole,
                                Bu=Bu)  # fmt: skip
    _checks.matrix("A", A, square=True)
    n = A.shape[-1]
    _checks.matrix("B", B, shape=(n, None))
    Bu = jnp.zeros((n, 0), dtype) if Bu is None else jnp.atleast_2d(jnp.asarray(Bu))
    _checks.matrix("Bu", Bu, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    nd, ny = B.shape[1], C.shape[0]
    _checks.matrix("K", K, shape=(n, ny))
    _checks.matrix("F1", F1, shape=(nd, ny))
    _checks.positive_scalar("h", h)
    if case is not None:
        case = _checks.count("case", case, minimum=1, maximum=2)
    lowpass_order = _checks.count("lowpass_order", lowpass_order)
    _checks.shape("lowpass_pole", lowpass_pole, (), "one pole shared by the sections")
    x0 = jnp.zeros((n,), dtype) if x0 is None else _checks.vector("x0", x0, n, dtype, what="one entry per state")
    A, B, C, K, F1 = (M.astype(dtype) for M in (A, B, C, K, F1))
    concrete_plant = _checks.is_concrete(A, B, C)
    if concrete_plant:
        Bn, An, Cn = (np.asarray(M, dtype=float) for M in (B, A, C))
        rB = np.linalg.matrix_rank(Bn, tol=1e-10 * max(np.linalg.norm(Bn), 1e-300))
        if rB < nd:
            raise ValueError(f"B must have full column rank (Assumption 2.1 ii), got rank {rB} < n_d = {nd}")
        O = np.asarray(obsv(An, Cn))
        rO = np.linalg.matrix_rank(O, tol=1e-10 * max(np.linalg.norm(O), 1e-300))
        if rO < n:
            raise ValueError(
                f"(A, C) must be observable (Assumption 2.1 iii): the observability matrix has rank {rO} < n = {n}"
            )
    if case is None:
        if not concrete_plant:
            raise ValueError("case must be given (1 or 2) when A, B, C are traced")
        try:
            case1_f2(B, C)
            case = 1
        except ValueError:
            case = 2
    if case == 1:
        if F2 is None:
            if not concrete_plant:
                raise ValueError("F2 must be given for case=1 when B, C are traced")
            F2 = case1_f2(B, C)
        F2 = jnp.atleast_2d(jnp.asarray(F2, dtype))
        _checks.matrix("F2", F2, shape=(nd, ny))
        if concrete_plant:
            case1_f2(B, C)  # raises with the Case 2 hint when no F2 exists
            if _checks.is_concrete(F2):
                res = np.asarray(F2) @ np.asarray(C) @ np.asarray(B) - np.eye(nd)
                if np.max(np.abs(res)) > 1e-8:
                    raise ValueError(
                        f"F2 must satisfy F2 C B = I for case=1 (eq. 5); residual {np.max(np.abs(res)):.3g}"
                    )
        if rho is not None:
            raise ValueError("rho is the free parameter of B+ and only applies to case=2")
        G1, G2, G3 = case1_gains(A, B, C, F1, F2)
    else:
        if F2 is None:
            raise ValueError("F2 must be given for case=2 (Lemma 3.3)")
        F2 = jnp.atleast_2d(jnp.asarray(F2, dtype))
        _checks.matrix("F2", F2, shape=(nd, ny))
        if rho is not None:
            rho = rho.astype(dtype)
            _checks.matrix("rho", rho, shape=(nd, n))
        G1, G2, G3 = case2_gains(A, B, C, F1, F2, rho)
    if check_stability and _checks.is_concrete(A, B, C, K, F1, F2, rho):
        _check_error_dynamics(case, *error_dynamics(A, B, C, K, G1, G2))
    if _checks.is_concrete(lowpass_pole):
        p = float(np.asarray(lowpass_pole))
        if not 0.0 <= p < 1.0:
            raise ValueError(f"lowpass_pole must lie in [0, 1), got {p}")
    return InverseDynamicsParams(
        A, B, C, Bu.astype(dtype), K, F1, F2, G1, G2, G3, x0, jnp.asarray(h, dtype), jnp.asarray(lowpass_pole, dtype),
        lowpass_order,
    )  # fmt: skip


def _check_error_dynamics(case: int, M_e, A_e):
    if case == 1:
        eig = np.linalg.eigvals(np.asarray(A_e))
        if np.max(eig.real) >= 0:
            raise ValueError(
                "K, F1: A - B (F1 C + F2 C A) - K C is not Hurwitz (Lemma 3.1 ii, eq. 8); eigenvalues "
                f"{np.round(eig, 4)}. Plant zeros are fixed poles of eq. 8 (Lemma 3.2): a non-minimum-phase plant "
                "has no stable Case 1 design"
            )
        return
    res = fact35(M_e, A_e)
    if res.rank < M_e.shape[-1] and not bool(res.stable):
        A22 = np.asarray(res.A22)
        if np.linalg.svd(A22, compute_uv=False).min() <= 1e-9 * max(np.abs(np.asarray(A_e)).max(), 1e-300):
            raise ValueError(
                "F1, F2, K, rho: M_e is singular and A22 is singular (eq. 26 has no unique solution): the error "
                "dynamics M_e e' = A_e e are not regular; change F2 or rho"
            )
    if not bool(res.stable):
        raise ValueError(
            "F1, F2, K, rho: the error dynamics M_e e' = A_e e (eq. 16-18) are not exponentially stable "
            f"(rank M_e = {res.rank}; slow poles {np.round(np.asarray(res.poles), 4)}, A22 eigenvalues "
            f"{np.round(np.asarray(res.fast), 4)}; Fact 3.5)"
        )


# ------------------------------------------------------------------------------------- gain design


class DesignResult(NamedTuple):
    """Result of :func:`design_gains`.

    Attributes:
      gains: dict of ``K``, ``F1``, ``F2`` (and ``rho`` in Case 2) as NumPy arrays.
      poles: (n_poles,) complex, the finite poles of the error dynamics at the result.
      objective: float, the user objective at the result (0 without one).
      feasible: bool, every pole has real part ``<= max_real_part`` and the box bounds hold.
    """

    gains: dict
    poles: np.ndarray
    objective: float
    feasible: bool


def _finite_poles(A, B, C, case: int, rank: int | None, g: dict):
    if case == 1:
        G1, G2, _ = case1_gains(A, B, C, g["F1"], g["F2"])
        return jnp.linalg.eigvals(error_dynamics(A, B, C, g["K"], G1, G2)[1])
    G1, G2, _ = case2_gains(A, B, C, g["F1"], g["F2"], g.get("rho"))
    return fact35(*error_dynamics(A, B, C, g["K"], G1, G2), rank=rank).poles


def design_gains(
    A,
    B,
    C,
    init: dict,
    *,
    case: int,
    max_real_part: float,
    objective=None,
    bounds: dict | None = None,
    fixed: tuple = (),
    steps: int = 400,
    optimizer=None,
    penalty: float = 100.0,
) -> DesignResult:
    """Gradient-based choice of ``K, F1, F2`` (and ``rho``, Case 2) under a pole constraint (design time).

    Minimises ``objective(gains) + penalty * sum(relu(Re p - max_real_part + 0.1)^2)`` over the finite poles
    ``p`` of the error dynamics (eq. 8, or Fact 3.5 with the rank of ``M_e`` at ``init``) for ``steps`` steps of
    ``optimizer`` (an ``optax.GradientTransformation``; default ``optax.adam(0.05)``), projecting onto the box
    ``bounds = {name: (lo, hi)}`` after each step. ``init`` holds the starting gains (Case 1:
    ``K, F1`` and ``F2``; Case 2: also ``rho``); names in ``fixed`` are not changed (e.g. ``F2`` in Case 1,
    which must keep ``F2 C B = I``). ``objective(gains) -> scalar`` must be JAX-traceable. The result is
    re-checked with :func:`make_inverse_dynamics`'s tests; ``feasible`` reports the constraints.
    """
    import optax

    A, B, C = (jnp.atleast_2d(jnp.asarray(M, float)) for M in (A, B, C))
    theta0 = {k: jnp.atleast_2d(jnp.asarray(v, A.dtype)) for k, v in init.items() if v is not None}
    for name in ("K", "F1", "F2"):
        if name not in theta0:
            raise ValueError(f"init must contain {name}")
    if case not in (1, 2):
        raise ValueError(f"case must be 1 or 2, got {case!r}")
    rank = None
    if case == 2:
        G1, G2, _ = case2_gains(A, B, C, theta0["F1"], theta0["F2"], theta0.get("rho"))
        rank = fact35(*error_dynamics(A, B, C, theta0["K"], G1, G2)).rank
    bounds = dict(bounds or {})
    for name in bounds:
        if name not in theta0:
            raise ValueError(f"bounds names {name!r}, which is not in init")
    free = {k: v for k, v in theta0.items() if k not in fixed}
    held = {k: v for k, v in theta0.items() if k in fixed}

    def clip(t):
        return {k: jnp.clip(v, *bounds[k]) if k in bounds else v for k, v in t.items()}

    def loss(t):
        g = {**held, **t}
        p = _finite_poles(A, B, C, case, rank, g)
        viol = jax.nn.relu(p.real - max_real_part + 0.1)
        obj = 0.0 if objective is None else objective(g)
        return obj + penalty * jnp.sum(viol**2)

    if optimizer is None:
        optimizer = optax.adam(0.05)
    _checks.optimizer("optimizer", optimizer, "optax.adam(0.05)")
    opt = optax.with_extra_args_support(optimizer)

    @jax.jit
    def update(t, s):
        value, grads = jax.value_and_grad(loss)(t)
        upd, s = opt.update(grads, s, t, value=value, grad=grads, value_fn=loss)
        return clip(optax.apply_updates(t, upd)), s

    t, s = clip(free), opt.init(free)
    for _ in range(steps):
        t, s = update(t, s)
    g = {k: np.asarray(v) for k, v in {**held, **t}.items()}
    poles = np.asarray(_finite_poles(A, B, C, case, rank, g))
    in_box = all(np.all((g[k] >= lo - 1e-12) & (g[k] <= hi + 1e-12)) for k, (lo, hi) in bounds.items())
    obj = 0.0 if objective is None else float(objective({k: jnp.asarray(v) for k, v in g.items()}))
    feasible = bool(poles.size and np.max(poles.real) <= max_real_part and in_box)
    return DesignResult(g, poles, obj, feasible)
