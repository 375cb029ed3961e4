"""Discrete-time suboptimal H-infinity filter (a-posteriori / filtered form, Riccati recursion).

For the model of :mod:`jaxobs.observers.kalman` with the estimated output ``z_k = Cz x_k``, the filter
guarantees an energy gain from disturbances to the error of ``z_hat_k`` below ``gamma^2`` wherever its existence
condition holds (Hassibi, Sayed & Kailath 1996; Simon 2006, ch. 11). :func:`make_hinf`, :data:`hinf_filter`,
the recursion :func:`hinf_riccati_step` / :func:`hinf_riccati_sequence`, its steady state
(:func:`hinf_steady_state`) and the optimal level (:func:`gamma_bisection`); ``gamma = inf`` is the Kalman
filter. The bound, the recursion and the existence condition: docs/theory/estimators.md.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs._jit import jit
from jaxobs._linalg import is_positive_semidefinite, solve_spd, symmetrize
from jaxobs.kalman_steps import predict, predict_covariance, update, update_covariance
from jaxobs.matrix_equations import is_stable
from jaxobs.observers.base import Estimator, EstimatorInputs, LinearObserver

__all__ = [
    "HinfParams",
    "HinfState",
    "HinfOutputs",
    "HinfSequence",
    "HinfSteadyState",
    "GammaSearch",
    "hinf_filter",
    "make_hinf",
    "hinf_correction",
    "hinf_riccati_step",
    "hinf_riccati_sequence",
    "hinf_steady_state",
    "with_steady_state_gain",
    "gamma_bisection",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class HinfParams:
    """Parameters of the H-infinity filter (``n`` states, ``m`` inputs, ``p`` outputs).

    Attributes:
      Phi: (n, n).  Gamma: (n, m) (m = 0 without inputs).  C: (p, n).
      Cz: (q, n) the estimated combination ``z = Cz x`` (the filter's performance output).
      Cd: (r, n) read-out of the disturbance states, ``d_hat = Cd x_hat`` (r = 0 for a model without them).
      Q: (n, n).  R: (p, p).  x0: (n,), P0: (n, n) prior of ``x_0``.
      gamma: () performance level (> 0; inf gives the Kalman filter).
      gain: ``None`` for the time-varying gain of the H-infinity Riccati recursion, or a fixed (n, p) gain
        (steady state, no matrix propagation).
    """

    Phi: jax.Array
    Gamma: jax.Array
    C: jax.Array
    Cz: jax.Array
    Cd: jax.Array
    Q: jax.Array
    R: jax.Array
    x0: jax.Array
    P0: jax.Array
    gamma: jax.Array
    gain: jax.Array | None = None


class HinfState(NamedTuple):
    """State of :data:`hinf_filter` between steps.

    Attributes:
      x: (n,) a-posteriori estimate x_hat_{k-1|k-1} (the prior mean before the first step)
      P: (n, n) H-infinity Riccati matrix Pb_{k-1} (the prior P0 before the first step)
      started: () bool: a measurement has been processed (the next step predicts)
      violations: () steps so far at which the existence condition failed
      missing: () measurement components skipped so far
    """

    x: jax.Array
    P: jax.Array
    started: jax.Array
    violations: jax.Array
    missing: jax.Array


class HinfOutputs(NamedTuple):
    """Outputs of one step of :data:`hinf_filter`.

    Attributes:
      x: (n,) a-posteriori estimate x_hat_{k|k}
      z: (q,) z_hat_k = Cz x_hat_{k|k}
      d: (r,) disturbance estimate Cd x_hat_{k|k}
      x_prior: (n,) x_hat_{k|k-1}
      innovation: (p,) y_k - C x_prior (0 for missing components)
      gain: (n, p) K_k
      feasible: () existence condition held at this step
      margin: () smallest eigenvalue of I - gamma^{-2} Cz P_k Cz' (> 0 required; a flag's measure, with no gradient)
    """

    x: jax.Array
    z: jax.Array
    d: jax.Array
    x_prior: jax.Array
    innovation: jax.Array
    gain: jax.Array
    feasible: jax.Array
    margin: jax.Array


def _check_gamma(gamma):
    _checks.shapes("gamma ()", gamma)
    if not _checks.is_concrete(gamma):
        return
    a = np.asarray(gamma, dtype=float)
    if a.ndim != 0:
        raise ValueError(f"gamma must be a scalar, got shape {a.shape}")
    if not (a > 0):  # also rejects NaN
        raise ValueError(f"gamma must be positive (inf gives the Kalman filter), got {float(a)}")


def _validate(Phi, C, Cz, Q, R, P0, gamma=None, Gamma=None):
    n = Phi.shape[-1]
    _checks.matrix("Phi", Phi, shape=(n, n), square=True)
    if Gamma is not None:
        _checks.matrix("Gamma", Gamma, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    _checks.matrix("Cz", Cz, shape=(None, n))
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True, size=C.shape[-2])
    _checks.covariance("P0", P0, definite=False, size=n)
    if gamma is not None:
        _check_gamma(gamma)


def _as_matrices(Phi, C, Cz, Q, R, P0):
    Phi, C, Cz, Q, R, P0 = (None if M is None else jnp.atleast_2d(M)
                            for M in _checks.float_arrays(Phi=Phi, C=C, Cz=Cz, Q=Q, R=R, P0=P0))  # fmt: skip
    Cz = jnp.eye(Phi.shape[-1], dtype=Phi.dtype) if Cz is None else Cz
    P0 = Q if P0 is None else P0
    return Phi, C, Cz, Q, R, P0


def make_hinf(Phi, C, Q, R, *, gamma, Gamma=None, Cz=None, Cd=None, x0=None, P0=None,
              steady_state: bool = False) -> HinfParams:  # fmt: skip
    """Build and check :class:`HinfParams`.

    Args:
      Phi: (n, n).  C: (p, n).  Q: (n, n).  R: (p, p).
      gamma: performance level, positive; ``jnp.inf`` gives the Kalman filter.
      Gamma: (n, m) input matrix; ``None`` for a model without inputs.
      Cz: (q, n) estimated combination (default the identity: the whole state).
      Cd: (r, n) read-out of disturbance states for the ``d`` output (default none).
      x0: (n,) prior mean of ``x_0`` (default zeros).  P0: (n, n) its covariance (default ``Q``).
      steady_state: fix the gain to the converged recursion (:func:`with_steady_state_gain`); raises
        ``ValueError`` (on concrete input) when the recursion does not converge or violates the existence
        condition at that ``gamma``.

    All arrays are cast to their common floating dtype.
    """
    Phi, C, Cz, Q, R, P0 = _as_matrices(Phi, C, Cz, Q, R, P0)
    dtype = _checks.float_dtype(Phi=Phi, Gamma=Gamma, C=C, Cz=Cz, Cd=Cd, Q=Q, R=R, P0=P0, x0=x0, gamma=gamma)
    n = Phi.shape[-1]
    Gamma = jnp.zeros((n, 0), dtype) if Gamma is None else jnp.atleast_2d(jnp.asarray(Gamma))
    Cd = jnp.zeros((0, n), dtype) if Cd is None else jnp.atleast_2d(jnp.asarray(Cd))
    _validate(Phi, C, Cz, Q, R, P0, gamma, Gamma)
    _checks.matrix("Cd", Cd, shape=(None, n))
    x0 = jnp.zeros((n,), dtype) if x0 is None else _checks.vector("x0", x0, n, dtype, what="one entry per state")
    Phi, Gamma, C, Cz, Cd, Q, R, P0 = (M.astype(dtype) for M in (Phi, Gamma, C, Cz, Cd, Q, R, P0))
    gamma = jnp.asarray(gamma, dtype)
    params = HinfParams(Phi, Gamma, C, Cz, Cd, Q, R, x0, P0, gamma)
    if not steady_state:
        return params
    sol = hinf_steady_state(Phi, C, Cz, Q, R, gamma, P_init=P0)
    if _checks.is_concrete(sol.P) and not (bool(sol.converged) and bool(sol.feasible)):
        raise ValueError(
            f"gamma={float(gamma):.6g} admits no steady-state H-infinity filter (converged={bool(sol.converged)}, "
            f"existence condition held={bool(sol.feasible)}); increase gamma above the level from gamma_bisection"
        )
    return dataclasses.replace(params, gain=sol.gain, P0=sol.P)


# --------------------------------------------------------------------------------------------
# Riccati recursion


def hinf_correction(P, Cz, gamma):
    """``Pb = (P^{-1} - gamma^{-2} Cz' Cz)^{-1}`` from the Kalman a-posteriori matrix ``P``, without inverting ``P``.

    Returns ``(Pb, margin, ok)``: ``margin`` is the smallest eigenvalue of ``M = I - gamma^{-2} Cz P Cz'``
    and ``ok = margin > 0`` the existence condition (``margin`` is a flag's measure: its gradient is stopped, as
    the eigenvalue's derivative is undefined where eigenvalues repeat). ``Pb = P + gamma^{-2} P Cz' M^{-1} Cz P``
    (Woodbury, a Cholesky solve with ``M``); when ``ok`` is False, ``Pb = P`` (gradients stay finite).
    """
    P, Cz, gamma = _checks.arrays("P (n, n), Cz (q, n), gamma ()", P, Cz, gamma)
    theta = 1.0 / jnp.square(gamma)  # gamma^{-2}; 0 for gamma = inf
    q = Cz.shape[-2]
    eye = jnp.eye(q, dtype=P.dtype)
    LP = Cz @ P
    M = symmetrize(eye - theta * (LP @ Cz.T))
    margin = jnp.linalg.eigvalsh(jax.lax.stop_gradient(M))[0]
    ok = margin > 0
    M_safe = jnp.where(ok, M, eye)
    correction = theta * (LP.T @ solve_spd(M_safe, LP))
    Pb = symmetrize(P + jnp.where(ok, correction, jnp.zeros_like(correction)))
    return Pb, margin, ok


def hinf_riccati_step(Pb_prev, Phi, C, Cz, Q, R, gamma, *, first=False):
    """One step ``Pb_{k-1} -> (Pb_k, K_k, P1_k, margin_k, ok_k)`` of the H-infinity Riccati recursion; with
    ``first`` (a traced bool) ``Pb_prev`` is the prior ``P0`` of ``x_0`` and is used as ``P1_0`` (no prediction).
    Shapes: ``Pb_prev`` (n, n), ``Phi`` (n, n), ``C`` (p, n), ``Cz`` (q, n), ``Q`` (n, n), ``R`` (p, p), ``gamma``
    ()."""
    Pb_prev, Phi, C, Cz, Q, R, gamma = _checks.arrays(
        "Pb_prev (n, n), Phi (n, n), C (p, n), Cz (q, n), Q (n, n), R (p, p), gamma ()",
        Pb_prev,
        Phi,
        C,
        Cz,
        Q,
        R,
        gamma,
    )
    P1 = jnp.where(first, Pb_prev, predict_covariance(Pb_prev, Phi, Q))
    P, K = update_covariance(P1, C, R)
    Pb, margin, ok = hinf_correction(P, Cz, gamma)
    return Pb, K, symmetrize(P1), margin, ok


class HinfSequence(NamedTuple):
    """Stacked over time (leading axis ``num_steps``).

    Attributes:
      P: (T, n, n) Pb_k
      K: (T, n, p) gains K_k
      P_prior: (T, n, n) P1_k
      margin: (T,) smallest eigenvalue of I - gamma^{-2} Cz P_k Cz' (no gradient)
      feasible: (T,) the existence condition held at step k
    """

    P: jax.Array
    K: jax.Array
    P_prior: jax.Array
    margin: jax.Array
    feasible: jax.Array


def hinf_riccati_sequence(P0, Phi, C, Cz, Q, R, gamma, num_steps: int) -> HinfSequence:
    """``num_steps`` steps of the recursion from the prior ``P1_0 = P0`` (``lax.scan``), with per-step flags, in
    the common floating dtype of the arguments."""
    Phi, C, Cz, Q, R, P0 = _as_matrices(Phi, C, Cz, Q, R, P0)
    _validate(Phi, C, Cz, Q, R, P0, gamma)
    num_steps = _checks.count("num_steps", num_steps)
    dtype = _checks.float_dtype(Phi=Phi, C=C, Cz=Cz, Q=Q, R=R, P0=P0, gamma=gamma)
    Phi, C, Cz, Q, R, P0 = (M.astype(dtype) for M in (Phi, C, Cz, Q, R, P0))

    def body(Pb, first):
        Pb, K, P1, margin, ok = hinf_riccati_step(Pb, Phi, C, Cz, Q, R, gamma, first=first)
        return Pb, HinfSequence(Pb, K, P1, margin, ok)

    return jax.lax.scan(body, P0, jnp.arange(num_steps) == 0)[1]


class HinfSteadyState(NamedTuple):
    """Steady state of the H-infinity Riccati recursion (:func:`hinf_steady_state`).

    Attributes:
      P_prior: (n, n) steady P1
      P: (n, n) steady Pb
      gain: (n, p) steady K = P1 C' (C P1 C' + R)^{-1}
      margin: () smallest margin met along the iteration (no gradient)
      converged: () last relative change below tol, P and P_prior finite and positive semidefinite, the gain
        finite, and the steady filter stable
      feasible: () existence condition held at every iteration
    """

    P_prior: jax.Array
    P: jax.Array
    gain: jax.Array
    margin: jax.Array
    converged: jax.Array
    feasible: jax.Array


def hinf_steady_state(Phi, C, Cz, Q, R, gamma, *, P_init=None, num_iters: int = 1000, tol: float | None = None):
    """Steady state of the H-infinity Riccati recursion by ``num_iters`` steps of :func:`hinf_riccati_sequence`'s
    recursion from the prior ``P_init`` of ``x_0`` (the first step has no prediction; default ``Q + I``, positive
    definite, from which the recursion reaches the stabilising solution where one exists). A fixed trip count
    (``lax.scan``), so it is differentiable in both modes.

    ``converged``: the relative change of the last step is below ``tol`` (default ``sqrt(eps)``), the covariances
    are finite and positive semidefinite (traced ``Q``, ``R`` are not checked otherwise), the gain is finite, and
    the steady filter's error dynamics ``(I - K C) Phi`` are stable (the stabilising solution); ``feasible``: the
    existence condition held at every step. Both flags, never an exception.
    """
    default_start = P_init is None
    Phi, C, Cz, Q, R, P_init = _as_matrices(Phi, C, Cz, Q, R, P_init)
    if default_start:
        P_init = P_init + jnp.eye(P_init.shape[-1], dtype=P_init.dtype)
    _validate(Phi, C, Cz, Q, R, P_init, gamma)
    dtype = jnp.result_type(Phi, C, Cz, Q, R, P_init, float)
    tol = float(np.sqrt(np.finfo(dtype).eps)) if tol is None else float(tol)
    Phi, C, Cz, Q, R, P_init = (jnp.asarray(M, dtype) for M in (Phi, C, Cz, Q, R, P_init))
    return _steady(Phi, C, Cz, Q, R, jnp.asarray(gamma, dtype), P_init, num_iters=int(num_iters), tol=tol)


@partial(jit, static_argnames=("num_iters", "tol"), what="make_hinf (steady state)")
def _steady(Phi, C, Cz, Q, R, gamma, P_init, *, num_iters, tol):
    dtype = P_init.dtype

    def body(carry, first):
        Pb, margin, ok, _change = carry
        Pb_new, _, _, m, o = hinf_riccati_step(Pb, Phi, C, Cz, Q, R, gamma, first=first)
        change = jnp.max(jnp.abs(Pb_new - Pb)) / jnp.maximum(jnp.max(jnp.abs(Pb_new)), jnp.finfo(dtype).tiny)
        return (Pb_new, jnp.minimum(margin, m), ok & o, change), None

    init = (P_init, jnp.asarray(jnp.inf, dtype), jnp.asarray(True), jnp.asarray(jnp.inf, dtype))
    (Pb, margin, ok, change), _ = jax.lax.scan(body, init, jnp.arange(num_iters) == 0)
    P1 = predict_covariance(Pb, Phi, Q)
    _, K = update_covariance(P1, C, R)
    n = Phi.shape[-1]
    stable = is_stable((jnp.eye(n, dtype=dtype) - K @ C) @ Phi)  # the steady filter's error dynamics
    covariances = is_positive_semidefinite(Pb) & is_positive_semidefinite(P1) & jnp.all(jnp.isfinite(K))
    converged = jnp.isfinite(change) & (change < tol) & covariances & stable
    return HinfSteadyState(P1, Pb, K, margin, converged, ok)


def with_steady_state_gain(params: HinfParams, num_iters: int = 1000) -> HinfParams:
    """Same filter with the fixed steady-state gain of :func:`hinf_steady_state` (``P0`` becomes the steady
    ``Pb``). Under tracing, check the flags of :func:`hinf_steady_state` yourself."""
    _checks.fields("params", params, _SHAPES)
    sol = hinf_steady_state(params.Phi, params.C, params.Cz, params.Q, params.R, params.gamma, P_init=params.P0,
                            num_iters=num_iters)  # fmt: skip
    return dataclasses.replace(params, gain=sol.gain, P0=sol.P)


# --------------------------------------------------------------------------------------------
# The observer


_SHAPES = (
    "Phi (n, n), Gamma (n, m), C (p, n), Cz (q, n), Cd (r, n), Q (n, n), R (p, p), x0 (n,), P0 (n, n), gamma (), "
    "gain (n, p)"
)


def _init(params: HinfParams) -> HinfState:
    _checks.fields("params", params, _SHAPES)
    zero = jnp.zeros((), jnp.int32)
    return HinfState(params.x0, params.P0, jnp.zeros((), bool), zero, zero)


def _step(params: HinfParams, state: HinfState, inputs: EstimatorInputs):
    _checks.fields("params", params, _SHAPES)
    m, p, dtype = params.Gamma.shape[-1], params.C.shape[-2], params.Phi.dtype
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    u_prev = inputs.u_prev
    if u_prev is not None:
        u_prev = _checks.vector("inputs.u_prev", u_prev, m, dtype, what="one entry per column of Gamma",
                                check_finite=False)  # fmt: skip
    P = None if params.gain is not None else state.P
    x1, P1 = predict(state.x, P, params.Phi, params.Q, params.Gamma, u_prev, skip=~state.started)
    if params.gain is None:
        result = update(x1, P1, params.C, params.R, y)
        Pb, margin, ok = hinf_correction(result.P, params.Cz, params.gamma)
    else:
        result = update(x1, state.P, params.C, params.R, y, params.gain)
        Pb, margin, ok = result.P, jnp.asarray(jnp.inf, dtype), jnp.asarray(True)  # checked at design time
    x = result.x
    violations = state.violations + (~ok).astype(jnp.int32)
    state = HinfState(x, Pb, jnp.ones((), bool), violations, state.missing + result.n_missing.astype(jnp.int32))
    return state, HinfOutputs(x, params.Cz @ x, params.Cd @ x, x1, result.innovation, result.K, ok, margin)


def _linear(params: HinfParams) -> LinearObserver:
    if params.gain is None:
        raise ValueError(
            "params: the linear form needs a fixed gain; use with_steady_state_gain (or steady_state=True)"
        )
    return LinearObserver(params.Phi, params.Gamma, params.C, params.gain)


hinf_filter = Estimator(_init, _step, _linear)
"""The a-posteriori H-infinity filter as an :class:`~jaxobs.observers.base.Estimator` over :class:`HinfParams`.

Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (p,) and (m,) (``u_prev=None`` without inputs); each step
checks them against the params while tracing and casts them to the params' dtype. Outputs: :class:`HinfOutputs`.
"""


# --------------------------------------------------------------------------------------------
# The optimal level


class GammaSearch(NamedTuple):
    """Result of the bisection over the attenuation level (:func:`gamma_bisection`).

    Attributes:
      gamma: () smallest level found feasible (upper end of the final bracket)
      lower: () largest level found infeasible
      found: () gamma is feasible and (gamma - lower) <= rtol * gamma
      iterations: () recursions evaluated
    """

    gamma: jax.Array
    lower: jax.Array
    found: jax.Array
    iterations: jax.Array


def gamma_bisection(Phi, C, Q, R, *, Cz=None, P0=None, num_steps: int = 200, rtol: float = 1e-6,
                    max_iters: int = 200) -> GammaSearch:  # fmt: skip
    """Smallest ``gamma`` for which the H-infinity Riccati recursion from the prior ``P0`` satisfies the existence
    condition at all of ``num_steps`` steps (the optimal a-posteriori filtering level over that horizon; a
    long horizon approximates the steady-state level). Feasibility is monotone in ``gamma``.

    Bracket: ``lower = sqrt(lambda_max(Cz P_0 Cz'))`` with ``P_0`` the first Kalman a-posteriori matrix (the first
    step is infeasible at or below it, whatever ``gamma``), ``upper`` doubled from ``2 lower`` until feasible;
    then bisection until ``upper - lower <= rtol * upper`` or ``max_iters`` evaluations in all. Pure JAX
    (``while_loop``), so it works under ``jit`` and ``vmap``; not differentiable. Returns :class:`GammaSearch`.
    """
    Phi, C, Cz, Q, R, P0 = _as_matrices(Phi, C, Cz, Q, R, P0)
    _validate(Phi, C, Cz, Q, R, P0)
    _checks.positive_scalar("rtol", rtol)
    num_steps = _checks.count("num_steps", num_steps, minimum=1)
    max_iters = _checks.count("max_iters", max_iters, minimum=1)
    dtype = jnp.result_type(Phi, C, Cz, Q, R, P0, float)
    Phi, C, Cz, Q, R, P0 = (jnp.asarray(M, dtype) for M in (Phi, C, Cz, Q, R, P0))
    return _bisect(Phi, C, Cz, Q, R, P0, num_steps=num_steps, rtol=float(rtol), max_iters=max_iters)


@partial(jit, static_argnames=("num_steps", "rtol", "max_iters"), what="make_hinf (gamma search)")
def _bisect(Phi, C, Cz, Q, R, P0, *, num_steps, rtol, max_iters):

    def exists(gamma):
        def body(carry, first):
            Pb, ok = carry
            Pb, _, _, _, o = hinf_riccati_step(Pb, Phi, C, Cz, Q, R, gamma, first=first)
            return (Pb, ok & o), None

        return jax.lax.scan(body, (P0, jnp.asarray(True)), jnp.arange(num_steps) == 0)[0][1]

    P_first, _ = update_covariance(P0, C, R)
    lam = jnp.linalg.eigvalsh(symmetrize(Cz @ P_first @ Cz.T))[-1]
    lo = jnp.sqrt(jnp.maximum(lam, 0.0))
    hi = jnp.where(lo > 0, 2.0 * lo, jnp.ones_like(lo))

    def cond(carry):
        lo, hi, hi_ok, it = carry
        return (it < max_iters) & (~hi_ok | (hi - lo > rtol * hi))

    def body(carry):
        lo, hi, hi_ok, it = carry
        mid = jnp.where(hi_ok, 0.5 * (lo + hi), 2.0 * hi)
        ok = exists(mid)
        lo = jnp.where(hi_ok, jnp.where(ok, lo, mid), hi)
        hi = jnp.where(hi_ok, jnp.where(ok, mid, hi), mid)
        return lo, hi, hi_ok | ok, it + 1

    ok0 = exists(hi)
    lo, hi, hi_ok, it = jax.lax.while_loop(cond, body, (lo, hi, ok0, jnp.asarray(1)))
    return GammaSearch(hi, lo, hi_ok & (hi - lo <= rtol * hi), it)
