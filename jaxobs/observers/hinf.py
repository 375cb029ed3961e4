"""Discrete-time suboptimal H-infinity filter (a-posteriori / filtered form, Riccati recursion).

Model (same timing as :mod:`jaxobs.observers.kalman`)::

    x_k = Phi x_{k-1} + Gamma u_{k-1} + w_k,    y_k = C x_k + v_k,    z_k = L x_k

with ``x_{-1}`` the initial state, guessed as ``x0``. The filter returns ``z_hat_k = L x_hat_{k|k}`` from
``y_0 .. y_k`` and guarantees, for every disturbance sequence of finite energy, over every horizon ``N``
on which the existence condition below holds::

    sum_k |z_k - z_hat_k|^2
    ------------------------------------------------------------------------------   <  gamma^2
    |x_{-1} - x0|^2_{P0^{-1}} + sum_k |w_k|^2_{Q^{-1}} + sum_k |v_k|^2_{R^{-1}}

(``|a|^2_M = a' M a``; with a singular ``Q``, ``P0`` the disturbance lives in their range.)

Recursion (Hassibi, Sayed & Kailath, "Linear estimation in Krein spaces -- Part II: Applications",
IEEE Trans. Automatic Control 41(1), 1996, the a-posteriori H-infinity filter; also their book
"Indefinite-Quadratic Estimation and Control", SIAM 1999, ch. 4; D. Simon, "Optimal State Estimation",
Wiley 2006, ch. 11, gives the same Riccati equation in game-theoretic form, with ``theta = gamma^{-2}``,
``S = I``)::

    x1_k = Phi x_{k-1} + Gamma u_{k-1}                    P1_k = Phi Pb_{k-1} Phi' + Q
    K_k  = P1_k C' (C P1_k C' + R)^{-1}                     x_k  = x1_k + K_k (y_k - C x1_k)
    P_k  = (I - K_k C) P1_k (I - K_k C)' + K_k R K_k'      (Joseph form, = (P1_k^{-1} + C' R^{-1} C)^{-1})
    Pb_k = (P_k^{-1} - gamma^{-2} L' L)^{-1}
         = P_k + gamma^{-2} P_k L' (I - gamma^{-2} L P_k L')^{-1} L P_k      (Woodbury; no inverse of P)

starting from ``Pb_{-1} = P0``. The estimate has the Kalman structure; only the Riccati matrix is
inflated by the ``-gamma^{-2} L' L`` term. Existence condition, checked at every step::

    P1_k^{-1} + C' R^{-1} C - gamma^{-2} L' L > 0    <=>    I - gamma^{-2} L P_k L' > 0

(the right-hand form is a Schur complement of the left one and needs no inverse of ``P1_k``). Its
smallest eigenvalue is reported as ``margin``; a step with ``margin <= 0`` is flagged
(``feasible=False``), counted in ``state.violations`` and, so that traced sweeps keep finite numbers, falls
back to the Kalman matrix ``Pb_k = P_k`` for that step; the gamma bound is then not guaranteed.

As ``gamma -> inf`` the correction vanishes and the filter is exactly the Kalman filter
(``gamma=jnp.inf`` is allowed and gives it bit for bit). The smallest ``gamma`` for which the condition
holds over a horizon (the optimal a-posteriori level) is found by :func:`gamma_bisection`; no filter
that estimates ``z_k`` from ``y_0 .. y_k`` achieves a smaller worst-case ratio over that horizon. The
a-priori (one-step predictor, ``z_k`` from ``y_0 .. y_{k-1}``) variant is not implemented here.

Missing data: as in the Kalman filter, non-finite measurement components are skipped exactly and
counted in ``state.missing``. Precision: the condition check compares eigenvalues with zero; near the
optimal gamma use float64 (float32 is fine well above it).
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.observers.base import Observer
from jaxobs.observers.kalman import measurement_update
from jaxobs.riccati import _solve_spd, predict_covariance, symmetrize, update_covariance

__all__ = [
    "HinfParams",
    "HinfState",
    "HinfInputs",
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
    """Parameters of the H-infinity filter. ``gain=None``: time-varying gain from the H-infinity Riccati
    recursion; an ``(n, p)`` array: a fixed (steady-state) gain, no matrix propagation."""

    Phi: jax.Array
    Gamma: jax.Array
    C: jax.Array
    L: jax.Array  # (q, n): the estimated combination z = L x
    Q: jax.Array
    R: jax.Array
    x0: jax.Array
    P0: jax.Array
    gamma: jax.Array  # performance level (> 0; inf gives the Kalman filter)
    gain: jax.Array | None = None


class HinfState(NamedTuple):
    x: jax.Array  # a-posteriori estimate x_hat_{k|k}
    P: jax.Array  # H-infinity Riccati matrix Pb_k (the Kalman covariance when gamma = inf)
    violations: jax.Array  # steps so far at which the existence condition failed
    missing: jax.Array  # measurement components skipped so far


class HinfInputs(NamedTuple):
    u_prev: jax.Array  # input u_{k-1}
    y: jax.Array  # measurement y_k (NaN entries are missing)


class HinfOutputs(NamedTuple):
    x: jax.Array  # a-posteriori estimate x_hat_{k|k}
    z: jax.Array  # z_hat_k = L x_hat_{k|k}
    x_prior: jax.Array  # Phi x_{k-1} + Gamma u_{k-1}
    innovation: jax.Array  # y_k - C x_prior (0 for missing components)
    gain: jax.Array  # K_k
    feasible: jax.Array  # existence condition held at this step
    margin: jax.Array  # smallest eigenvalue of I - gamma^{-2} L P_k L' (> 0 required)


def _check_gamma(gamma):
    if not _checks.is_concrete(gamma):
        return
    a = np.asarray(gamma, dtype=float)
    if a.ndim != 0:
        raise ValueError(f"gamma must be a scalar, got shape {a.shape}")
    if not (a > 0):  # also rejects NaN
        raise ValueError(f"gamma must be positive (inf gives the Kalman filter), got {float(a)}")


def _validate(Phi, C, L, Q, R, P0, gamma=None, Gamma=None):
    n = Phi.shape[-1]
    _checks.matrix("Phi", Phi, shape=(n, n), square=True)
    if Gamma is not None:
        _checks.matrix("Gamma", Gamma, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    _checks.matrix("L", L, shape=(None, n))
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True, size=C.shape[-2])
    _checks.covariance("P0", P0, definite=False, size=n)
    if gamma is not None:
        _check_gamma(gamma)


def _as_matrices(Phi, C, L, Q, R, P0):
    Phi, C = (jnp.atleast_2d(jnp.asarray(M)) for M in (Phi, C))
    L = jnp.eye(Phi.shape[-1], dtype=Phi.dtype) if L is None else jnp.atleast_2d(jnp.asarray(L))
    Q, R = jnp.atleast_2d(jnp.asarray(Q)), jnp.atleast_2d(jnp.asarray(R))
    P0 = Q if P0 is None else jnp.atleast_2d(jnp.asarray(P0))
    return Phi, C, L, Q, R, P0


def make_hinf(Phi, Gamma, C, Q, R, *, gamma, L=None, x0=None, P0=None, steady_state: bool = False) -> HinfParams:
    """Build and validate :class:`HinfParams`.

    ``L`` defaults to the identity (estimate the whole state), ``P0`` to ``Q`` and ``x0`` to zero, as in
    :func:`jaxobs.observers.kalman.make_kalman`; all arrays are cast to their common floating dtype. ``gamma``
    must be positive; ``jnp.inf`` gives the Kalman filter. ``steady_state=True`` fixes the gain to the converged
    recursion (:func:`with_steady_state_gain`) and raises ``ValueError`` (on concrete input) when the recursion
    does not converge or violates the existence condition at that ``gamma``.
    """
    Phi, C, L, Q, R, P0 = _as_matrices(Phi, C, L, Q, R, P0)
    Gamma = jnp.atleast_2d(jnp.asarray(Gamma))
    dtype = _checks.float_dtype(Phi=Phi, Gamma=Gamma, C=C, L=L, Q=Q, R=R, P0=P0, x0=x0, gamma=gamma)
    _validate(Phi, C, L, Q, R, P0, gamma, Gamma)
    n = Phi.shape[-1]
    x0 = jnp.zeros((n,), dtype) if x0 is None else _checks.vector("x0", x0, n, dtype, what="one entry per state")
    Phi, Gamma, C, L, Q, R, P0 = (M.astype(dtype) for M in (Phi, Gamma, C, L, Q, R, P0))
    gamma = jnp.asarray(gamma, dtype)
    params = HinfParams(Phi, Gamma, C, L, Q, R, x0, P0, gamma)
    if not steady_state:
        return params
    sol = hinf_steady_state(Phi, C, L, Q, R, gamma, P_init=P0)
    if _checks.is_concrete(sol.P) and not (bool(sol.converged) and bool(sol.feasible)):
        raise ValueError(
            f"gamma={float(gamma):.6g} admits no steady-state H-infinity filter (converged={bool(sol.converged)}, "
            f"existence condition held={bool(sol.feasible)}); increase gamma above the level from gamma_bisection"
        )
    return dataclasses.replace(params, gain=sol.gain, P0=sol.P)


# --------------------------------------------------------------------------------------------
# Riccati recursion


def hinf_correction(P, L, gamma):
    """``Pb = (P^{-1} - gamma^{-2} L' L)^{-1}`` from the Kalman a-posteriori matrix ``P``, without inverting ``P``.

    Returns ``(Pb, margin, ok)``: ``margin`` is the smallest eigenvalue of ``M = I - gamma^{-2} L P L'``
    and ``ok = margin > 0`` the existence condition. ``Pb = P + gamma^{-2} P L' M^{-1} L P`` (Woodbury, a
    Cholesky solve with ``M``); when ``ok`` is False, ``Pb = P`` (gradients stay finite).
    """
    theta = 1.0 / jnp.square(gamma)  # gamma^{-2}; 0 for gamma = inf
    q = L.shape[-2]
    eye = jnp.eye(q, dtype=P.dtype)
    LP = L @ P
    M = symmetrize(eye - theta * (LP @ L.T))
    margin = jnp.linalg.eigvalsh(jax.lax.stop_gradient(M))[0]
    ok = margin > 0
    M_safe = jnp.where(ok, M, eye)
    correction = theta * (LP.T @ _solve_spd(M_safe, LP))
    Pb = symmetrize(P + jnp.where(ok, correction, jnp.zeros_like(correction)))
    return Pb, margin, ok


def hinf_riccati_step(Pb_prev, Phi, C, L, Q, R, gamma):
    """One step ``Pb_{k-1} -> (Pb_k, K_k, P1_k, margin_k, ok_k)`` of the H-infinity Riccati recursion."""
    P1 = predict_covariance(Pb_prev, Phi, Q)
    P, K = update_covariance(P1, C, R)
    Pb, margin, ok = hinf_correction(P, L, gamma)
    return Pb, K, symmetrize(P1), margin, ok


class HinfSequence(NamedTuple):
    """Stacked over time (leading axis ``num_steps``)."""

    P: jax.Array  # Pb_k
    K: jax.Array  # gains K_k
    P_prior: jax.Array  # P1_k
    margin: jax.Array
    feasible: jax.Array


def hinf_riccati_sequence(P0, Phi, C, L, Q, R, gamma, num_steps: int) -> HinfSequence:
    """``num_steps`` steps of the recursion from ``Pb_{-1} = P0`` (``lax.scan``), with per-step flags, in the
    common floating dtype of the arguments."""
    Phi, C, L, Q, R, P0 = _as_matrices(Phi, C, L, Q, R, P0)
    _validate(Phi, C, L, Q, R, P0, gamma)
    num_steps = _checks.count("num_steps", num_steps)
    dtype = _checks.float_dtype(Phi=Phi, C=C, L=L, Q=Q, R=R, P0=P0, gamma=gamma)
    Phi, C, L, Q, R, P0 = (M.astype(dtype) for M in (Phi, C, L, Q, R, P0))

    def body(Pb, _):
        Pb, K, P1, margin, ok = hinf_riccati_step(Pb, Phi, C, L, Q, R, gamma)
        return Pb, HinfSequence(Pb, K, P1, margin, ok)

    return jax.lax.scan(body, P0, None, length=num_steps)[1]


class HinfSteadyState(NamedTuple):
    P_prior: jax.Array  # steady P1
    P: jax.Array  # steady Pb
    gain: jax.Array  # steady K = P1 C' (C P1 C' + R)^{-1}
    margin: jax.Array  # smallest margin met along the iteration
    converged: jax.Array  # relative change of the last step below tol and finite
    feasible: jax.Array  # existence condition held at every iteration


def hinf_steady_state(Phi, C, L, Q, R, gamma, *, P_init=None, num_iters: int = 1000, tol: float | None = None):
    """Steady state of the H-infinity Riccati recursion by ``num_iters`` fixed-point steps from ``P_init``
    (default ``Q``). A fixed trip count (``lax.scan``), so it is differentiable in both modes.

    ``converged``: the relative change of the last step is below ``tol`` (default ``sqrt(eps)``);
    ``feasible``: the existence condition held at every step. Both flags, never an exception.
    """
    Phi, C, L, Q, R, P_init = _as_matrices(Phi, C, L, Q, R, P_init)
    _validate(Phi, C, L, Q, R, P_init, gamma)
    dtype = jnp.result_type(Phi, C, L, Q, R, P_init, float)
    tol = float(np.sqrt(np.finfo(dtype).eps)) if tol is None else float(tol)
    Phi, C, L, Q, R, P_init = (jnp.asarray(M, dtype) for M in (Phi, C, L, Q, R, P_init))
    return _steady(Phi, C, L, Q, R, jnp.asarray(gamma, dtype), P_init, num_iters=int(num_iters), tol=tol)


@partial(jax.jit, static_argnames=("num_iters", "tol"))
def _steady(Phi, C, L, Q, R, gamma, P_init, *, num_iters, tol):
    dtype = P_init.dtype

    def body(carry, _):
        Pb, margin, ok, _change = carry
        Pb_new, _, _, m, o = hinf_riccati_step(Pb, Phi, C, L, Q, R, gamma)
        change = jnp.max(jnp.abs(Pb_new - Pb)) / jnp.maximum(jnp.max(jnp.abs(Pb_new)), jnp.finfo(dtype).tiny)
        return (Pb_new, jnp.minimum(margin, m), ok & o, change), None

    init = (P_init, jnp.asarray(jnp.inf, dtype), jnp.asarray(True), jnp.asarray(jnp.inf, dtype))
    (Pb, margin, ok, change), _ = jax.lax.scan(body, init, None, length=num_iters)
    P1 = predict_covariance(Pb, Phi, Q)
    _, K = update_covariance(P1, C, R)
    converged = jnp.isfinite(change) & (change < tol) & jnp.all(jnp.isfinite(Pb))
    return HinfSteadyState(P1, Pb, K, margin, converged, ok)


def with_steady_state_gain(params: HinfParams, num_iters: int = 1000) -> HinfParams:
    """Same filter with the fixed steady-state gain of :func:`hinf_steady_state` (``P0`` becomes the steady
    ``Pb``). Under tracing, check the flags of :func:`hinf_steady_state` yourself."""
    sol = hinf_steady_state(params.Phi, params.C, params.L, params.Q, params.R, params.gamma, P_init=params.P0,
                            num_iters=num_iters)  # fmt: skip
    return dataclasses.replace(params, gain=sol.gain, P0=sol.P)


# --------------------------------------------------------------------------------------------
# The observer


def _init(params: HinfParams) -> HinfState:
    zero = jnp.zeros((), jnp.int32)
    return HinfState(params.x0, params.P0, zero, zero)


def _step(params: HinfParams, state: HinfState, inputs: HinfInputs):
    m, p, dtype = params.Gamma.shape[-1], params.C.shape[-2], params.Phi.dtype
    u_prev = _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype, what="one entry per column of Gamma",
                            check_finite=False)  # fmt: skip
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    x1 = params.Phi @ state.x + params.Gamma @ u_prev
    if params.gain is None:
        P1 = predict_covariance(state.P, params.Phi, params.Q)
        x, P, K, innovation, n_missing = measurement_update(x1, P1, params.C, params.R, y)
        Pb, margin, ok = hinf_correction(P, params.L, params.gamma)
    else:
        x, Pb, K, innovation, n_missing = measurement_update(x1, state.P, params.C, params.R, y, params.gain)
        margin, ok = jnp.asarray(jnp.inf, x.dtype), jnp.asarray(True)  # checked at design time
    state = HinfState(x, Pb, state.violations + (~ok).astype(jnp.int32), state.missing + n_missing.astype(jnp.int32))
    return state, HinfOutputs(x, params.L @ x, x1, innovation, K, ok, margin)


hinf_filter = Observer(_init, _step)
"""The a-posteriori H-infinity filter in the (init, step) protocol; inputs are :class:`HinfInputs` ``(u_{k-1}, y_k)`` of
shapes ``(m,)`` and ``(p,)`` (scalars where the size is 1). Each step checks the inputs' shapes against the params
while tracing (a ``ValueError`` naming the field) and casts them to the params' dtype."""


# --------------------------------------------------------------------------------------------
# The optimal level


class GammaSearch(NamedTuple):
    gamma: jax.Array  # smallest level found feasible (upper end of the final bracket)
    lower: jax.Array  # largest level found infeasible
    found: jax.Array  # gamma is feasible and (gamma - lower) <= rtol * gamma
    iterations: jax.Array


def gamma_bisection(Phi, C, Q, R, *, L=None, P0=None, num_steps: int = 200, rtol: float = 1e-6,
                    max_iters: int = 200) -> GammaSearch:  # fmt: skip
    """Smallest ``gamma`` for which the H-infinity Riccati recursion from ``Pb_{-1} = P0`` satisfies the existence
    condition at all of ``num_steps`` steps (the optimal a-posteriori filtering level over that horizon; a
    long horizon approximates the steady-state level). Feasibility is monotone in ``gamma``.

    Bracket: ``lower = sqrt(lambda_max(L P_0 L'))`` with ``P_0`` the first Kalman a-posteriori matrix (the first
    step is infeasible at or below it, whatever ``gamma``), ``upper`` doubled from ``2 lower`` until feasible;
    then bisection until ``upper - lower <= rtol * upper`` or ``max_iters`` evaluations in all. Pure JAX
    (``while_loop``), so it works under ``jit`` and ``vmap``; not differentiable. Returns :class:`GammaSearch`.
    """
    Phi, C, L, Q, R, P0 = _as_matrices(Phi, C, L, Q, R, P0)
    _validate(Phi, C, L, Q, R, P0)
    _checks.positive_scalar("rtol", rtol)
    num_steps = _checks.count("num_steps", num_steps, minimum=1)
    max_iters = _checks.count("max_iters", max_iters, minimum=1)
    dtype = jnp.result_type(Phi, C, L, Q, R, P0, float)
    Phi, C, L, Q, R, P0 = (jnp.asarray(M, dtype) for M in (Phi, C, L, Q, R, P0))
    return _bisect(Phi, C, L, Q, R, P0, num_steps=num_steps, rtol=float(rtol), max_iters=max_iters)


@partial(jax.jit, static_argnames=("num_steps", "rtol", "max_iters"))
def _bisect(Phi, C, L, Q, R, P0, *, num_steps, rtol, max_iters):

    def exists(gamma):
        def body(carry, _):
            Pb, ok = carry
            Pb, _, _, _, o = hinf_riccati_step(Pb, Phi, C, L, Q, R, gamma)
            return (Pb, ok & o), None

        return jax.lax.scan(body, (P0, jnp.asarray(True)), None, length=num_steps)[0][1]

    P_first, _ = update_covariance(predict_covariance(P0, Phi, Q), C, R)
    lam = jnp.linalg.eigvalsh(symmetrize(L @ P_first @ L.T))[-1]
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
