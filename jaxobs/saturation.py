"""Estimation and control through saturations (Grip 2010, ch. 8 and 9).

Chapter 8 (Grip, Saberi & Wang): the sampled hybrid controller that stabilises ``x' = A x + B u``,
``y = sat(C x)`` globally (:func:`saturated_output_design`, :func:`interval_map`,
:func:`simulate_saturated_outputs`). Chapter 9 (Grip, Saberi, Stoorvogel, Wang & Roy): which input explains a
window of a saturated system's output (:func:`hypothesis_residual`, :func:`explains`,
:func:`sandwich_detectors`), the low-gain ARE (:func:`low_gain_are`) and the three-stage controller of §9.4
(:func:`simulate_sandwich`). The equations: docs/theory/analysis.md.

Input contract: shapes and types are checked at trace time, values (finite arrays, ``T``, ``h``, ``eps > 0``,
``rho > 1``, ``cond_max >= 1``) where concrete, ``ValueError`` naming the argument; an eager design whose matrix
exponentials overflow (``T`` too long for the working precision) raises naming ``T``. Under ``jit`` nothing raises:
such a design has non-finite constants, a window model at a step ``h <= 0`` is NaN, and a ``cond_max`` below 1 (or
NaN) flags every interval ``ill_conditioned``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks, ct
from jaxobs.lti import controllability_rank, observability_rank
from jaxobs.matrix_equations import care

__all__ = [
    "ALPHA_NORMS",
    "sat",
    "require_controllable_observable",
    "SaturatedOutputDesign",
    "saturated_output_design",
    "interval_map",
    "SaturatedOutputTrace",
    "simulate_saturated_outputs",
    "WindowModel",
    "window_model",
    "forced_response",
    "Residual",
    "hypothesis_residual",
    "Hypothesis",
    "hypothesis",
    "explains",
    "sandwich_hypotheses",
    "DetectorResult",
    "sandwich_detectors",
    "SandwichDesign",
    "sandwich_design",
    "low_gain_are",
    "SandwichTrace",
    "simulate_sandwich",
    "CLASSES",
]


def sat(v):
    """The standard saturation ``sign(v) min(1, |v|)``, componentwise (``v`` any real array)."""
    return jnp.clip(_checks.real_array("v", v), -1.0, 1.0)


def require_controllable_observable(A, B, C, *, names: tuple[str, str] = ("(A, B)", "(C, A)")) -> None:
    """Raise ``ValueError`` naming the pair and its rank when ``(A, B)`` is not controllable or ``(C, A)`` not
    observable (Assumption 8.1, 9.1); eager (skipped on tracers)."""
    if not _checks.is_concrete(A, B, C):
        return
    n = np.shape(A)[0]
    for name, rank, what in ((names[0], controllability_rank(A, B), "controllable"),
                             (names[1], observability_rank(A, C), "observable")):  # fmt: skip
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


def _finite_result(name: str, given, **values) -> None:
    """Eagerly, ``ValueError`` naming the argument ``name`` (whose value was ``given``) when one of the concrete
    ``values`` it sets is not finite, e.g. a matrix exponential that overflows."""
    for label, value in values.items():
        if _checks.is_concrete(value, given) and not np.all(np.isfinite(np.asarray(value))):
            dtype = np.asarray(value).dtype
            raise ValueError(f"{name} = {float(given):g} is too large: {label} is not finite in {dtype}; lower {name}")


def _design(name: str, value, kind) -> None:
    """``value`` checked to be one ``kind`` (a design, window model or hypothesis of this module, no batch axis:
    ``vmap`` over a batch), its fields' shapes at trace time, naming ``name.field``."""
    if not isinstance(value, kind):
        raise ValueError(f"{name} must be a {kind.__name__} (see {kind.__name__.lower()}), got {type(value).__name__}")
    if kind is Hypothesis:
        _design(f"{name}.fine", value.fine, WindowModel)
        _design(f"{name}.coarse", value.coarse, WindowModel)
    else:
        _checks.fields(name, value, _SHAPES[kind])


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
      T: () interval length ``> 0`` (``exp(A T)`` must not overflow).  rho: () finite ``> 1``, ``alpha = rho
        ||exp(A T)||``.
      H: (p, n) the vectors ``h_i`` as rows, each with ``C_i h_i > 0``; default ``C`` (``h_i = C_i'``, §8.4).
      alpha_norm: the matrix norm of ``||exp(A T)||``: ``"2"`` (spectral, the default), ``"1"``, ``"inf"`` or
        ``"fro"`` (the thesis does not say which; ``grip2010-saturated-outputs`` compares them).

    ``Bbar`` is computed exactly as a block of one matrix exponential (Van Loan 1978). Eager: the assumptions are
    checked on concrete values and raise ``ValueError`` naming the argument, as does a ``T`` for which ``exp(A T)``,
    ``alpha`` or ``Bbar^{-1}`` is not finite; under ``jit`` such constants are returned non-finite.

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
            raise ValueError(
                f"H: C_i h_i must be > 0 for every output, got C_i h_i = {ch[bad[0]]:.6g} for i = {bad[0]}"
            )
    T = jnp.asarray(T, dtype)
    expAT = jax.scipy.linalg.expm(A * T)
    alpha = jnp.asarray(rho, dtype) * jnp.linalg.norm(expAT, ord=ALPHA_NORMS[alpha_norm])
    Bbar = _van_loan(A, B @ B.T, T)
    Bbar_inv = jnp.linalg.inv(Bbar)
    _finite_result("T", T, **{"exp(A T)": expAT, "alpha": alpha, "Bbar": Bbar, "Bbar^-1": Bbar_inv})
    return SaturatedOutputDesign(A, B, C, T, alpha, H, expAT, Bbar, Bbar_inv)


def interval_map(design: SaturatedOutputDesign, x, U):
    """``x(kT + T) = exp(A T) x(kT) - Bbar U_k`` (8.7): the exact state one interval later under (8.2); ``x`` and
    ``U`` (n,)."""
    _design("design", design, SaturatedOutputDesign)
    n, dtype = design.A.shape[0], design.A.dtype
    x = _checks.vector("x", x, n, dtype)
    U = _checks.vector("U", U, n, dtype)
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
    """Condition number of a symmetric positive semidefinite matrix (inf when singular)."""
    eig = jnp.linalg.eigvalsh((D + D.T) / 2)
    low = eig[0]
    return jnp.where(low > 0, jnp.max(jnp.abs(eig)) / jnp.where(low > 0, low, 1), jnp.inf)


def _rk4(rhs, z, d):
    """One classical RK4 step of the autonomous ``z' = rhs(z)`` (a pytree) over ``d`` (:func:`jaxobs.ct.rk4_step`)."""
    return ct.rk4_step(lambda z, _u, _t: rhs(z), z, None, 0.0, d)


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
      design: :func:`saturated_output_design`.  x0: (n,) the finite initial state.
      num_intervals: static number of intervals ``K`` (>= 1).  substeps: static RK4 steps per interval (>= 1).
      cond_max: the largest condition number of ``D`` that is inverted, finite ``>= 1`` (a traced value below 1 or NaN
        inverts none: every interval whose outputs were all unsaturated is flagged ``ill_conditioned``).

    Returns: a :class:`SaturatedOutputTrace`. Pure; works under ``jit`` and ``vmap`` over ``x0``.
    """
    _design("design", design, SaturatedOutputDesign)
    num_intervals = _checks.count("num_intervals", num_intervals, minimum=1)
    substeps = _checks.count("substeps", substeps, minimum=1)
    _checks.positive_scalar("cond_max", cond_max)
    if _checks.is_concrete(cond_max) and float(cond_max) < 1:
        raise ValueError(f"cond_max must be >= 1 (a condition number), got {float(cond_max)}")
    A, B, C, H = design.A, design.B, design.C, design.H
    n, p = A.shape[0], C.shape[0]
    dtype = A.dtype
    x0 = _checks.vector("x0", x0, n, dtype)
    d = design.T / substeps

    def rhs(z):
        x, mu, v, Psi, sigma, xi, D = z
        u = -B.T @ v
        y = sat(C @ x)
        w = 1 - jnp.abs(y)
        PC = Psi.T @ C.T  # exp(A' t) C'
        return (A @ x + B @ u, A @ mu + B @ u, -A.T @ v, A @ Psi, w, PC @ (w * (y - C @ mu)), (PC * w) @ PC.T)

    def interval(carry, k):
        x, mu, Psi, sigma, xi, D = carry
        cond = _condition(D)
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


# ---------------------------------------------------------------------------------------------------- chapter 9


class WindowModel(NamedTuple):
    """The constants of one window hypothesis at one sample step (:func:`window_model`).

    Attributes:
      H: (p, nf) output matrix.  E: (nf, nf) ``exp(F h)``.  G0, G1: (nf, m) the response over one step to the
      input at its start and to its slope (piecewise-linear input).  h: () the step.
    """

    H: jax.Array
    E: jax.Array
    G0: jax.Array
    G1: jax.Array
    h: jax.Array


def window_model(F, Bf, H, h) -> WindowModel:
    """The hypothesis "``y = H w``, ``w' = F w + Bf u``" sampled at step ``h``: one matrix exponential (computed once,
    outside any loop over windows).

    Args:
      F: (nf, nf).  Bf: (nf, m).  H: (p, nf).  h: () the step, finite and ``> 0`` (checked where concrete; a
        traced ``h <= 0`` gives a NaN model).
    """
    dtype, (F, Bf, H) = _matrices(F=F, Bf=Bf, H=H)
    nf = F.shape[0]
    _checks.matrix("F", F, square=True)
    _checks.matrix("Bf", Bf, shape=(nf, None))
    _checks.matrix("H", H, shape=(None, nf))
    _checks.positive_scalar("h", h)
    m = Bf.shape[1]
    h = jnp.asarray(h, dtype)
    _checks.shape("h", h, (), "a scalar step")
    Z = jnp.zeros((nf + 2 * m, nf + 2 * m), dtype)
    Z = Z.at[:nf, :nf].set(F).at[:nf, nf : nf + m].set(Bf).at[nf : nf + m, nf + m :].set(jnp.eye(m, dtype=dtype))
    X = jnp.where(h > 0, jax.scipy.linalg.expm(Z * h), jnp.nan)
    _finite_result("h", h, **{"exp(F h)": X})
    return WindowModel(H, X[:nf, :nf], X[:nf, nf : nf + m], X[:nf, nf + m :], jnp.where(h > 0, h, jnp.nan))


def forced_response(model: WindowModel, u):
    """States ``v(tau_j)``, ``tau_j = j h``, of ``v' = F v + Bf u``, ``v(0) = 0``, for the finite input ``u`` (N + 1,
    m) sampled at ``tau_j`` and linear in between (exact for piecewise-linear inputs): ``u_s*`` of (9.4) for a
    constant input, ``u_0*`` of §9.3.1 for the plant's input. ``model``: :func:`window_model`."""
    _design("model", model, WindowModel)
    u = _samples("u", u, model.G0.shape[1], model.E.dtype, "the input at the samples")

    def step(v, pair):
        u0, u1 = pair
        v = model.E @ v + model.G0 @ u0 + model.G1 @ ((u1 - u0) / model.h)
        return v, v

    zero = jnp.zeros(model.E.shape[0], model.E.dtype)
    _, vs = jax.lax.scan(step, zero, (u[:-1], u[1:]))
    return jnp.concatenate([zero[None], vs])


def _samples(name: str, value, width: int, dtype, what: str, length: int | None = None) -> jax.Array:
    """A record ``value`` of shape (N + 1, width) (``length`` rows when given, at least 2) as a finite (where concrete)
    array in ``dtype``; ``ValueError`` naming ``name`` otherwise (no broadcast)."""
    value = _checks.real_array(name, value)
    _checks.shape(name, value, (length, width), what)
    if value.shape[0] < 2:
        raise ValueError(f"{name} must have at least 2 samples (rows), got shape {value.shape}")
    _checks.finite(name, value)
    return value.astype(dtype)


def _row_norms(x):
    """Euclidean norms of the rows of ``x``, with a zero derivative at a zero row (where ``norm``'s is NaN: the
    residual at ``tau = 0`` is always zero)."""
    squares = jnp.sum(jnp.square(x), axis=-1)
    positive = squares > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squares, 1)), 0)


def _adjugate(D):
    """``det(D)`` and ``adj(D)`` of a symmetric positive semidefinite ``D`` from its eigenvalues (exact when ``D`` is
    singular, where ``det(D) D^{-1}`` is not defined)."""
    s, V = jnp.linalg.eigh((D + D.T) / 2)
    k = s.shape[0]
    others = jnp.where(jnp.eye(k, dtype=bool), 1, s[None, :])  # row i: s with s_i replaced by 1
    return jnp.prod(s), (V * jnp.prod(others, axis=1)) @ V.T


class Residual(NamedTuple):
    """Result of :func:`hypothesis_residual`.

    Attributes:
      statistic: () int_0^T ||r(tau)|| dtau (trapezoid)
      scale: () the size of the data in the same integral: of det(D) (|y| + |H v|) and of the second term
      norms: (N + 1,) ||r(tau_j)||
      w0: (nf,) D^{-1}(T) (xi(T) - S(T)), the hypothesis's state at the window start (9.7)
      w_end: (nf,) exp(F T) w0 + v(T), its state at the window end (9.11b)
      condition: () condition number of D(T)
    """

    statistic: jax.Array
    scale: jax.Array
    norms: jax.Array
    w0: jax.Array
    w_end: jax.Array
    condition: jax.Array


def hypothesis_residual(model: WindowModel, y, u) -> Residual:
    """The consistency statistic of Grip (2010) (9.6)-(9.8) for one hypothesis on a window.

    The hypothesis is "over this window ``y(tau) = H exp(F tau) w0 + H v(tau)`` for some ``w0``", ``v`` the
    response to the known input ``u`` (:func:`forced_response`)::

        r(tau) = det(D(tau)) (y(tau) - H v(tau)) - H exp(F tau) adj(D(tau)) (xi(tau) - S(tau))
        D(tau) = int_0^tau exp(F' g) H' H exp(F g) dg,  xi(tau) - S(tau) = int_0^tau exp(F' g) H' (y - H v)(g) dg

    Both integrals are taken with the same cumulative trapezoid rule over the samples, so ``xi - S = D w0`` holds
    exactly at every sample when the samples are consistent with the hypothesis: ``r`` is then zero up to the error
    of the samples themselves and of ``v`` (exact for a piecewise-linear ``u``), and ``w0`` is the exact
    least-squares reconstruction even when ``D`` is poorly conditioned (a short window). Theorem 9.1 needs
    ``(H, F)`` observable.

    Args:
      model: :func:`window_model` of ``(F, Bf, H)`` at the sample step ``h``.
      y: (N + 1, p) finite outputs at ``tau_j = j h``.  u: (N + 1, m) the hypothesis's finite input at the same
        times.
    """
    _design("model", model, WindowModel)
    H, h = model.H, model.h
    nf = model.E.shape[0]
    y = _samples("y", y, H.shape[0], model.E.dtype, "one column per row of the hypothesis's H")
    u = _samples("u", u, model.G0.shape[1], model.E.dtype, "the input at the samples of y", length=y.shape[0])
    v = forced_response(model, u)
    e = y - v @ H.T

    def step(carry, e_pair):
        E, D, xs = carry
        E1 = E @ model.E
        HE0, HE1 = H @ E, H @ E1
        D1 = D + h / 2 * (HE0.T @ HE0 + HE1.T @ HE1)
        xs1 = xs + h / 2 * (HE0.T @ e_pair[0] + HE1.T @ e_pair[1])
        return (E1, D1, xs1), (E1, D1, xs1)

    zero = jnp.zeros((nf, nf), y.dtype)
    init = (jnp.eye(nf, dtype=y.dtype), zero, jnp.zeros(nf, y.dtype))
    _, (Es, Ds, xss) = jax.lax.scan(step, init, (e[:-1], e[1:]))
    Es = jnp.concatenate([init[0][None], Es])
    Ds = jnp.concatenate([zero[None], Ds])
    xss = jnp.concatenate([init[2][None], xss])
    det, adj = jax.vmap(_adjugate)(Ds)
    first = det[:, None] * e
    second = jnp.einsum("pi,jik,jkl,jl->jp", H, Es, adj, xss)
    norms = _row_norms(first - second)
    trap = lambda f: h * (jnp.sum(f) - (f[0] + f[-1]) / 2)
    scale = trap(jnp.abs(det) * (_row_norms(y) + _row_norms(v @ H.T)) + _row_norms(second))
    D_T = (Ds[-1] + Ds[-1].T) / 2
    w0 = jnp.linalg.solve(D_T, xss[-1])
    condition = _condition(D_T)
    return Residual(trap(norms), scale, norms, w0, Es[-1] @ w0 + v[-1], condition)


class Hypothesis(NamedTuple):
    """A window hypothesis at the sample step ``h`` (``fine``) and ``2 h`` (``coarse``): :func:`hypothesis`."""

    fine: WindowModel
    coarse: WindowModel


def hypothesis(F, Bf, H, h) -> Hypothesis:
    """The hypothesis "the window's output is ``H w`` with ``w' = F w + Bf u``" for :func:`explains`.

    Args:
      F: (nf, nf).  Bf: (nf, m).  H: (p, nf), ``(H, F)`` observable.  h: () the sample step of the windows, ``> 0``.
    """
    fine = window_model(F, Bf, H, h)
    return Hypothesis(fine, window_model(F, Bf, H, 2 * fine.h))


def explains(hyp: Hypothesis, y, u, *, ratio=3.0, rtol=1e-9, rounding=64.0):
    """Whether the hypothesis explains the window, relative to the quadrature accuracy.

    The statistic of :func:`hypothesis_residual` is computed at step ``h`` (``e_h``) and from every other sample
    (``e_2h``). For a true hypothesis it is the error of the input's piecewise-linear interpolation, ``e_h ~ c h^2``,
    so halving the step divides it by 4, or it is at rounding level; for a false one it tends to a positive limit
    and halving the step changes it little. Accepted when ``e_2h >= ratio e_h`` (default 3), or when ``e_h`` is at the
    precision to which it can vanish: below ``max(rtol, rounding eps cond(D(T)))`` times the size of the data in
    the same integral (``eps`` the machine epsilon; ``adj(D) xi`` loses ``cond(D)`` in rounding, and a short window
    has a poorly conditioned ``D``).

    Args:
      hyp: :func:`hypothesis`.  y: (N + 1, p) finite outputs at ``j h``, ``N`` even, ``p`` the rows of the
        hypothesis's ``H`` (no broadcast).  u: (N + 1, m) the finite input.
      ratio: () ``> 1``.  rtol, rounding: () ``>= 0``: the acceptance rule above.

    Returns ``(accepted, e_h, e_2h, residual)`` with ``residual`` the :class:`Residual` at step ``h``.
    """
    _design("hyp", hyp, Hypothesis)
    dtype = hyp.fine.E.dtype
    y = _samples("y", y, hyp.fine.H.shape[0], dtype, "one column per row of the hypothesis's H")
    if y.shape[0] % 2 != 1 or y.shape[0] < 5:
        raise ValueError(f"y must have an odd number N + 1 >= 5 of samples (N even), got {y.shape[0]}")
    u = _samples("u", u, hyp.fine.G0.shape[1], dtype, "the input at the samples of y", length=y.shape[0])
    _checks.positive_scalar("ratio", ratio)
    if _checks.is_concrete(ratio) and float(ratio) <= 1:
        raise ValueError(f"ratio must be > 1 (halving the step divides a true statistic by 4), got {ratio}")
    _checks.positive_scalar("rtol", rtol, allow_zero=True)
    _checks.positive_scalar("rounding", rounding, allow_zero=True)
    fine = hypothesis_residual(hyp.fine, y, u)
    coarse = hypothesis_residual(hyp.coarse, y[::2], u[::2])
    floor = jnp.maximum(rtol, rounding * jnp.finfo(y.dtype).eps * fine.condition) * fine.scale
    accepted = (coarse.statistic >= ratio * fine.statistic) | (fine.statistic <= floor)
    return accepted, fine.statistic, coarse.statistic, fine


CLASSES = ("positive", "negative", "linear", "mixed")
"""Window classes of Theorem 9.1: ``z >= 1`` on the whole window, ``z <= -1``, ``|z| <= 1`` with ``|z| < 1``
somewhere, and none of these (the saturation both active and inactive)."""


class DetectorResult(NamedTuple):
    """The three detectors of Grip (2010) §9.3.1 on one window.

    Attributes:
      e_plus, e_minus, e_zero: () the statistics ``e_k+``, ``e_k-``, ``e_k0``.
      coarse: (3,) the same statistics from every other sample (:func:`explains` compares them).
      cls: () int index into :data:`CLASSES`.
      chi_end: (n + m,) the deadbeat estimate (9.11b) of ``chi`` at the window end (valid when ``cls`` is linear).
    """

    e_plus: jax.Array
    e_minus: jax.Array
    e_zero: jax.Array
    coarse: jax.Array
    cls: jax.Array
    chi_end: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SandwichDesign:
    """The sandwich system (9.1) and the three-stage controller of §9.4; build with :func:`sandwich_design`.

    Attributes:
      A: (n, n).  B: (n, 1).  C: (1, n): ``L1``.  M: (m, m).  N: (m, 1).  G: (p, m): ``L2``.
      AA: (n + m, n + m).  BB: (n + m, 1).  CC: (p, n + m): the merged model (9.2).
      T: () detection interval.  alpha: () the stage-2 growth ``alpha > exp(2 Tbar ||A||)``.
      h: (n,) stage-2 direction (``C h > 0``).  beta_inv: (n, n) ``beta(Tbar)^{-1}``.  expATbar: (n, n).
      K: (1, n + m) the stage-3 gain ``[F, 0] - BB' P_eps`` (9.12).  P: (n + m, n + m) ``P_eps``.
      q: static number of detection intervals per stage-2 interval (``Tbar = q T``).
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    M: jax.Array
    N: jax.Array
    G: jax.Array
    AA: jax.Array
    BB: jax.Array
    CC: jax.Array
    T: jax.Array
    alpha: jax.Array
    h: jax.Array
    beta_inv: jax.Array
    expATbar: jax.Array
    K: jax.Array
    P: jax.Array
    q: int = dataclasses.field(metadata=dict(static=True))


def _merged(A, B, C, M, N, G):
    n, m = A.shape[0], M.shape[0]
    AA = jnp.block([[A, jnp.zeros((n, m), A.dtype)], [N @ C, M]])
    BB = jnp.concatenate([B, jnp.zeros((m, B.shape[1]), A.dtype)])
    CC = jnp.concatenate([jnp.zeros((G.shape[0], n), A.dtype), G], axis=1)
    return AA, BB, CC


def low_gain_are(A, B, C, M, N, F, eps):
    """``P_eps`` of the low-gain ARE of Grip (2010) §9.4 (Wang et al. 2009).

    It solves::

        AF' P + P AF - P diag(B B', 0) P + eps I = 0,   AF = [[A + B F, 0], [N C, M]]

    solved by :func:`jaxobs.matrix_equations.care` (``Q = eps I``, ``R = 1``). Returns the
    :class:`jaxobs.matrix_equations.CareSolution` ``(X, residual, converged)``. ``P_eps -> 0`` as ``eps -> 0``
    (linearly when ``AF`` is Hurwitz).

    Args:
      A: (n, n).  B: (n, 1).  C: (1, n).  M: (m, m).  N: (m, 1).  F: (1, n) with ``A + B F`` Hurwitz.
      eps: () ``> 0``.
    """
    _checks.positive_scalar("eps", eps)
    dtype, (A, B, C, M, N, F) = _matrices(A=A, B=B, C=C, M=M, N=N, F=F)
    AF, BB, _ = _merged(A + B @ F, B, C, M, N, jnp.zeros((1, M.shape[0]), dtype))
    size = AF.shape[0]
    return care(AF, BB, jnp.asarray(eps, dtype) * jnp.eye(size, dtype=dtype), jnp.eye(1, dtype=dtype))


def sandwich_design(A, B, C, M, N, G, *, T, Tbar_intervals: int, rho, h=None, F, eps) -> SandwichDesign:
    """Check Assumptions 9.1-9.2 and the design rules and precompute the three-stage controller of §9.4.

    Args:
      A: (n, n).  B: (n, 1).  C: (1, n).  M: (m, m).  N: (m, 1).  G: (p, m): the sandwich system (9.1).
      T: () detection interval ``> 0``.  Tbar_intervals: static ``q >= 1``, the stage-2 interval ``Tbar = q T``.
      rho: () ``> 1``: ``alpha = rho exp(2 Tbar ||A||_2)``.  h: (n,) with ``C h > 0`` (default ``C'``).
      F: (1, n) with ``A + B F`` Hurwitz.  eps: () ``> 0`` the low-gain parameter of (9.12).

    Eagerly, a ``Tbar`` for which ``alpha``, ``exp(A Tbar)`` or ``beta(Tbar)^{-1}`` is not finite raises naming
    ``T``; under ``jit`` those constants are returned non-finite.
    """
    dtype, (A, B, C, M, N, G, F) = _matrices(A=A, B=B, C=C, M=M, N=N, G=G, F=F)
    n, m = A.shape[0], M.shape[0]
    _checks.matrix("A", A, square=True)
    _checks.matrix("B", B, shape=(n, 1))
    _checks.matrix("C", C, shape=(1, n))
    _checks.matrix("M", M, square=True)
    _checks.matrix("N", N, shape=(m, 1))
    _checks.matrix("G", G, shape=(None, m))
    _checks.matrix("F", F, shape=(1, n))
    _checks.positive_scalar("T", T)
    q = _checks.count("Tbar_intervals", Tbar_intervals, minimum=1)
    _checks.positive_scalar("rho", rho)
    if _checks.is_concrete(rho) and float(rho) <= 1:
        raise ValueError(f"rho must be > 1 (alpha must exceed exp(2 Tbar ||A||)), got {float(rho)}")
    _checks.positive_scalar("eps", eps)
    h = C[0] if h is None else _checks.vector("h", h, n, dtype)
    AA, BB, CC = _merged(A, B, C, M, N, G)
    require_controllable_observable(AA, BB, CC, names=("(AA, BB) of (9.2)", "(CC, AA) of (9.2)"))
    if _checks.is_concrete(A, B, C, M, N, G, F, h):
        if float(C[0] @ h) <= 0:
            raise ValueError(f"h: C h must be > 0, got {float(C[0] @ h):.6g}")
        if np.linalg.matrix_rank(np.asarray(G)) < G.shape[0]:
            raise ValueError(f"G must have full row rank {G.shape[0]}, got rank {np.linalg.matrix_rank(np.asarray(G))}")
        if np.max(np.linalg.eigvals(np.asarray(M)).real) > 1e-12:
            raise ValueError("M must have its eigenvalues in the closed left half-plane (Assumption 9.2)")
        rosenbrock = np.block([[np.asarray(M), np.asarray(N)], [np.asarray(G), np.zeros((G.shape[0], 1))]])
        if np.linalg.matrix_rank(rosenbrock) < m + 1:
            raise ValueError(
                "(G, M, N) must have no invariant zero at the origin (Assumption 9.2): "
                f"rank [[M, N], [G, 0]] = {np.linalg.matrix_rank(rosenbrock)} < m + 1 = {m + 1}"
            )
        if np.max(np.linalg.eigvals(np.asarray(A + B @ F)).real) >= 0:
            raise ValueError("F: A + B F must be Hurwitz")
    T = jnp.asarray(T, dtype)
    Tbar = q * T
    alpha = jnp.asarray(rho, dtype) * jnp.exp(2 * Tbar * jnp.linalg.norm(A, 2))
    beta = _van_loan(A, B @ B.T, Tbar)
    sol = low_gain_are(A, B, C, M, N, F, eps)
    K = jnp.concatenate([F, jnp.zeros((1, m), dtype)], axis=1) - BB.T @ sol.X
    beta_inv, expATbar = jnp.linalg.inv(beta), jax.scipy.linalg.expm(A * Tbar)
    _finite_result("T", T, **{"alpha (Tbar = Tbar_intervals T)": alpha, "beta(Tbar)^-1": beta_inv,
                              "exp(A Tbar)": expATbar})  # fmt: skip
    return SandwichDesign(A, B, C, M, N, G, AA, BB, CC, T, alpha, h, beta_inv, expATbar, K, sol.X, q)


def sandwich_hypotheses(design: SandwichDesign, h) -> tuple[Hypothesis, Hypothesis]:
    """The two models of the detectors at sample step ``h``: ``L2`` alone (driven by ``+-1``) and the merged
    linear model (9.2) driven by ``u``."""
    _design("design", design, SandwichDesign)
    return hypothesis(design.M, design.N, design.G, h), hypothesis(design.AA, design.BB, design.CC, h)


def sandwich_detectors(design: SandwichDesign, y, u, h, *, z_margin=1e-2, hypotheses=None) -> DetectorResult:
    """The detectors ``e_k+``, ``e_k-``, ``e_k0`` of Grip (2010) §9.3.1 on one window and its class (Theorem 9.1).

    Hypotheses (:func:`explains`): ``L2`` driven by the constant ``+1`` (positive saturation), by ``-1``, and the
    merged linear model (9.2) driven by the plant's input ``u``. The class is positive or negative when that
    hypothesis is accepted, linear when only the linear one is and its deadbeat reconstruction has ``|z| <= 1 +
    z_margin`` at both ends of the window (part of the hypothesis), mixed when none is.

    Args:
      design: :func:`sandwich_design`.  y: (N + 1, p) outputs at ``j h`` over the window.  u: (N + 1,) or
        (N + 1, 1) the input at the same times.  h: () sample step (``N h = T``; ``N`` even).
      z_margin: () tolerance of the consistency check ``|z| <= 1``.
      hypotheses: :func:`sandwich_hypotheses` at ``h`` (computed when not given; give them inside a loop).
    """
    _design("design", design, SandwichDesign)
    y = _checks.real_array("y", y)
    u = _checks.real_array("u", u)
    if u.ndim == 1 and y.ndim == 2:
        u = u[:, None]
    _checks.positive_scalar("z_margin", z_margin, allow_zero=True)
    l2, merged = sandwich_hypotheses(design, h) if hypotheses is None else hypotheses
    one = jnp.ones_like(u)
    plus, minus, zero = explains(l2, y, one), explains(l2, y, -one), explains(merged, y, u)
    n = design.A.shape[0]
    z_ends = jnp.stack([design.C[0] @ zero[3].w0[:n], design.C[0] @ zero[3].w_end[:n]])
    linear = zero[0] & jnp.all(jnp.abs(z_ends) <= 1 + z_margin)
    cls = jnp.where(plus[0], 0, jnp.where(minus[0], 1, jnp.where(linear, 2, 3)))
    return DetectorResult(plus[1], minus[1], zero[1], jnp.stack([plus[2], minus[2], zero[2]]), cls, zero[3].w_end)


class SandwichTrace(NamedTuple):
    """One entry per detection interval ``(kT, kT + T]`` of :func:`simulate_sandwich` (leading axis ``K``).

    Attributes:
      stage: (K,) the stage applied on the interval.  cls: (K,) its detector class (:data:`CLASSES`).
      e: (K, 3) ``(e_k+, e_k-, e_k0)``.  z_min, z_max: (K,) extremes of ``z = C x`` at the inner nodes.
      chi_end: (K, n + m) the state at ``kT + T``.  chi_hat_end: (K, n + m) the stage-3 estimate (zeros before).
      u_max: (K,) ``max |u|`` over the interval.
    """

    stage: jax.Array
    cls: jax.Array
    e: jax.Array
    z_min: jax.Array
    z_max: jax.Array
    chi_end: jax.Array
    chi_hat_end: jax.Array
    u_max: jax.Array


_SHAPES = {
    SaturatedOutputDesign: "A (n, n), B (n, m), C (p, n), T (), alpha (), H (p, n), expAT (n, n), Bbar (n, n), "
    "Bbar_inv (n, n)",
    WindowModel: "H (p, f), E (f, f), G0 (f, m), G1 (f, m), h ()",
    SandwichDesign: "A (n, n), B (n, 1), C (1, n), M (m, m), N (m, 1), G (p, m), AA (k, k), BB (k, 1), CC (p, k), "
    "T (), alpha (), h (n,), beta_inv (n, n), expATbar (n, n), K (1, k), P (k, k)",
}
"""The shapes of the fields of this module's designs and window models (checked by :func:`_design`)."""


def simulate_sandwich(design: SandwichDesign, chi0, num_intervals: int, *, substeps: int = 50) -> SandwichTrace:
    """The sandwich system (9.1) under the three-stage controller of Grip (2010) §9.4.

    Stage 1: ``u = 0`` until a window is classified (not mixed). Stage 2 (9.10): on intervals of ``Tbar = q T``,
    ``u = -B' exp(-A' tau) U_j`` with ``U_j = alpha^j beta(Tbar)^{-1} (alpha h - exp(A Tbar) h) delta`` and ``delta``
    the sign of the stage-1 window (+1, -1, or 0 if it was linear). Stage 3 from the first linear window: the deadbeat
    estimate (9.11b) at its end, integrated with the model (9.1) (9.11a), and ``u = K chi_hat`` (9.12). Each window
    is integrated with ``substeps`` RK4 steps (even); the detectors read ``y`` and ``u`` at those nodes.

    Args:
      design: :func:`sandwich_design`.  chi0: (n + m,) ``col(x(0), omega(0))``.
      num_intervals: static ``K``.  substeps: static even number of RK4 steps per window.

    Returns: a :class:`SandwichTrace`. Pure; ``jit`` and ``vmap`` over ``chi0``.
    """
    _design("design", design, SandwichDesign)
    num_intervals = _checks.count("num_intervals", num_intervals, minimum=1)
    substeps = _checks.count("substeps", substeps, minimum=4)
    if substeps % 2:
        raise ValueError(f"substeps must be even (the detectors halve the grid), got {substeps}")
    A, B, C, M, N, G = design.A, design.B, design.C, design.M, design.N, design.G
    n, m = A.shape[0], M.shape[0]
    dtype = A.dtype
    chi0 = _checks.vector("chi0", chi0, n + m, dtype)
    d = design.T / substeps
    hypotheses = sandwich_hypotheses(design, d)

    def f(chi, u):
        x, w = chi[:n], chi[n:]
        return jnp.concatenate([A @ x + B[:, 0] * u, M @ w + N[:, 0] * sat(C[0] @ x)])

    def control(z, stage):
        _, chi_hat, v = z
        return jnp.where(stage == 2, -B[:, 0] @ v, jnp.where(stage == 3, design.K[0] @ chi_hat, 0.0))

    def interval(carry, k):
        chi, chi_hat, v, stage, delta, k1 = carry
        in_stage2 = k - k1
        j = in_stage2 // design.q
        U = design.alpha**j * (design.beta_inv @ (design.alpha * design.h - design.expATbar @ design.h)) * delta
        v = jnp.where((stage == 2) & (in_stage2 % design.q == 0), U, v)

        def rhs(z):
            u = control(z, stage)
            return (f(z[0], u), f(z[1], u), -A.T @ z[2])

        def sub(z, _):
            z1 = _rk4(rhs, z, d)
            return z1, (C[0] @ z1[0][:n], G @ z1[0][n:], control(z1, stage))

        z = (chi, chi_hat, v)
        z_end, (zs, ys, us) = jax.lax.scan(sub, z, None, length=substeps)
        zs = jnp.concatenate([(C[0] @ chi[:n])[None], zs])
        ys = jnp.concatenate([(G @ chi[n:])[None], ys])
        us = jnp.concatenate([control(z, stage)[None], us])
        det = sandwich_detectors(design, ys, us, d, hypotheses=hypotheses)
        chi1, chi_hat1, v1 = z_end
        to3 = (stage < 3) & (det.cls == 2)
        to2 = (stage == 1) & (det.cls < 2)
        new_delta = jnp.where(to2, jnp.where(det.cls == 0, 1.0, -1.0), delta)
        new_stage = jnp.where(to3, 3, jnp.where(to2, 2, stage))
        chi_hat1 = jnp.where(to3, det.chi_end, chi_hat1)
        k1 = jnp.where(to2, k + 1, k1)
        e = jnp.stack([det.e_plus, det.e_minus, det.e_zero])
        chi_hat_out = jnp.where((stage == 3) | to3, chi_hat1, 0)
        out = SandwichTrace(stage, det.cls, e, jnp.min(zs), jnp.max(zs), chi1, chi_hat_out, jnp.max(jnp.abs(us)))
        return (chi1, chi_hat1, v1, new_stage, new_delta, k1), out

    carry = (chi0, jnp.zeros(n + m, dtype), jnp.zeros(n, dtype), jnp.asarray(1), jnp.asarray(0.0, dtype),
             jnp.asarray(0, jnp.int32))  # fmt: skip
    return jax.lax.scan(interval, carry, jnp.arange(num_intervals, dtype=jnp.int32))[1]
