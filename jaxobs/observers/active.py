"""Kalman Active Observer AOB-N (Cortesão 2006, seed 000 §2-5; seed 001; seed 003 §5-6).

A Kalman filter on the plant model augmented with an *active state* ``p_k``: an equivalent input
disturbance modelled as an order-N auto-regressive process (eq. 10, 37) that is estimated and fed
back, ``u_k = r_k - L_r x_hat_{r,k} - p_hat_k`` (eq. 20, 49-50). With the active state removed it
is the classical Kalman filter (CKF) with state feedback (seed 001 §2.1).

State order (eq. 18, 40): ``x = [x_{r,k}, p_{k-N+1}, ..., p_k]`` where each ``p`` block has one entry
per plant input (footnote 3 of seed 000), so ``n_active = N * m``.

The controller step (eq. 47, equivalently eq. 7-9 of seed 001) with ``u_{k-1} = r_{k-1} - L x_hat_{k-1}``::

    x_prior = Phi_n x_hat_{k-1} + Gamma_n u_{k-1}            (= [Phi_{L,n} 0; 0 Phi_22] x_hat + [Gamma_r; 0] r)
    x_hat_k = x_prior + K_k (y_k - C x_prior)                 (K_k from eq. 27-29 with the open-loop Phi_n)
    u_k     = r_k - L x_hat_k

Run-time switches, all traced values (no recompilation): ``active`` (1 = AOB, 0 = CKF: the active
state is locked at 0 and its Q entry zeroed, seed 001 §2.1 / seed 003 §6.3), and the adaptive
strategy of seed 001 §3 (``alpha > 0``).
"""

from __future__ import annotations

import dataclasses
from math import comb
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import erf, erfinv

from jaxobs import _checks
from jaxobs.lti import StateSpace
from jaxobs.observers.base import Observer
from jaxobs.observers.kalman import predict_and_update
from jaxobs.riccati import dare, kalman_gain, require_converged

__all__ = [
    "ActiveObserverParams",
    "ActiveObserverState",
    "ActiveObserverInputs",
    "ActiveObserverOutputs",
    "active_observer",
    "active_state_model",
    "augment",
    "evolution_variance",
    "aob_noise_covariance",
    "make_aob",
    "make_ckf",
    "with_steady_state_gains",
    "set_active",
    "adaptive_variance",
    "alpha_for_floor",
    "strategy_alpha",
    "constant_strategy_variance",
    "deviation_variance",
    "BETA_ONE_SIGMA",
    "sensor_based_gain",
    "classify_strategy",
]


# --------------------------------------------------------------------------------------------
# Active-state model and augmentation


def active_state_model(order: int, n_inputs: int = 1, dtype=jnp.float64):
    """``Phi_22`` of eq. 37 for ``m = n_inputs`` channels: ``kron(companion, I_m)``, shape ``(N m, N m)``.

    The companion row holds ``a_i = (-1)^{i+1} C(N, i)`` (eq. 10), so ``N`` repeated eigenvalues at 1:
    ``p_k`` has zero N-th difference up to the driving noise.
    """
    order = _checks.count("order", order, minimum=1, hint="an active state needs N >= 1")
    n_inputs = _checks.count("n_inputs", n_inputs, minimum=1)
    companion = np.zeros((order, order))
    companion[:-1, 1:] = np.eye(order - 1)
    companion[-1, :] = [(-1) ** (i + 1) * comb(order, i) for i in range(order, 0, -1)]
    return jnp.asarray(np.kron(companion, np.eye(n_inputs)), dtype)


def augment(plant: StateSpace, order: int):
    """Augmented open-loop model (eq. 30, 39, 48, 24): returns ``(Phi_n, Gamma_n, C)``.

    ``Phi_n = [[Phi_r, Phi_12], [0, Phi_22]]`` with ``Phi_12 = Gamma_r [0 ... 0 I]`` (eq. 41: the
    newest active state enters where the input does), ``Gamma_n = [Gamma_r; 0]``, ``C = [C_r 0]``.
    ``order = 0`` returns the plant matrices unchanged (the CKF).
    """
    order = _checks.count("order", order)
    Phi_r, Gamma_r, C_r = plant.A, plant.B, plant.C
    if order == 0:
        return Phi_r, Gamma_r, C_r
    n, m = Gamma_r.shape[-2:]
    na = order * m
    Phi22 = active_state_model(order, m, Phi_r.dtype)
    Phi12 = jnp.zeros((n, na), Phi_r.dtype).at[:, na - m :].set(Gamma_r)
    top = jnp.concatenate([Phi_r, Phi12], axis=1)
    bottom = jnp.concatenate([jnp.zeros((na, n), Phi_r.dtype), Phi22], axis=1)
    Phi_n = jnp.concatenate([top, bottom], axis=0)
    Gamma_n = jnp.concatenate([Gamma_r, jnp.zeros((na, m), Gamma_r.dtype)], axis=0)
    C = jnp.concatenate([C_r, jnp.zeros((C_r.shape[0], na), C_r.dtype)], axis=1)
    return Phi_n, Gamma_n, C


def evolution_variance(sigma2, order: int, c=1.0):
    """Variance of the active-state driving noise ``^{N-1} xi_p`` for an AOB-N (eq. 53-55).

    Theorem 1 (eq. 54) relates the variance of the j-th evolution to ``sigma2 = var(xi_p)``; eq. 55
    adds the factor ``c^j`` (``0 < c <= 1``) for relative stability. Q_Np holds the (N-1)-th
    evolution (eq. 53), so ``j = N - 1``:
    ``sigma2 * sum_{i=0}^{N-1} C(N-1, i)^2 * c^{N-1}``. (Eq. 84 prints the index as N; the Table I
    gains of §7.2 are reproduced only with N - 1: AOB-1 1e-3, AOB-2 4e-6, AOB-3 2.4e-8.)
    """
    order = _checks.count("order", order, minimum=1)
    _checks.positive_scalar("sigma2", sigma2, allow_zero=True)
    _checks.positive_scalar("c", c)
    j = order - 1
    return sigma2 * sum(comb(j, i) ** 2 for i in range(j + 1)) * jnp.asarray(c) ** j


def aob_noise_covariance(n_plant: int, order: int, n_inputs: int, q_plant, q_active):
    """``Q = blockdiag(Q_xr, Q_Np)`` (eq. 51-53), shape ``(n_plant + order n_inputs,)*2``.

    ``q_plant``: scalar or length-``n_plant`` diagonal of ``Q_xr``. ``q_active``: scalar or
    length-``n_inputs`` variance of ``^{N-1} xi_p``, placed on the newest active-state block only.
    """
    n_plant = _checks.count("n_plant", n_plant)
    order = _checks.count("order", order)
    n_inputs = _checks.count("n_inputs", n_inputs, minimum=1)
    dtype = _checks.float_dtype(q_plant=q_plant, q_active=q_active)
    q_plant = _checks.per_entry("q_plant", q_plant, n_plant, dtype, "one variance per plant state")
    q_active = _checks.per_entry("q_active", q_active, n_inputs, dtype, "one variance per plant input")
    diag_active = jnp.zeros((order * n_inputs,), dtype)
    if order:
        diag_active = diag_active.at[-n_inputs:].set(q_active)
    return jnp.diag(jnp.concatenate([q_plant, diag_active]))


# --------------------------------------------------------------------------------------------
# Parameters, state and the controller step


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ActiveObserverParams:
    """An AOB-N (or, with ``n_active = 0``, a CKF) with state feedback.

    ``gain``/``gain_passive``: ``None`` for the time-varying Riccati gain, or the steady-state
    gains of the AOB and of the same filter with the active state switched off
    (:func:`with_steady_state_gains`); ``gain_converged`` says whether both DAREs found their stabilising
    solutions (a boolean array when computed under tracing, reported by every step as
    ``ActiveObserverOutputs.converged``).
    """

    Phi: jax.Array  # augmented open-loop Phi_n (eq. 48)
    Gamma: jax.Array  # [Gamma_r; 0]
    C: jax.Array  # [C_r 0] (eq. 24)
    L: jax.Array  # [L_r, L_Np] (eq. 49-50)
    Q: jax.Array  # eq. 51
    R: jax.Array
    P0: jax.Array  # P_{-1}
    x0: jax.Array
    active: jax.Array  # 1.0 AOB, 0.0 CKF (run-time switch)
    alpha: jax.Array  # adaptive strategy of seed 001 eq. 27 per input; <= 0 keeps Q fixed
    sigma_floor: jax.Array  # sigma* of seed 001 §3.1: minimum std of the active-state evolution
    gain: jax.Array | None = None
    gain_passive: jax.Array | None = None
    gain_converged: jax.Array | None = None
    n_active: int = dataclasses.field(default=0, metadata=dict(static=True))

    @property
    def n_inputs(self) -> int:
        return self.Gamma.shape[-1]


class ActiveObserverState(NamedTuple):
    x: jax.Array  # a-posteriori estimate [x_r, ^N p]
    P: jax.Array  # a-posteriori covariance
    u: jax.Array  # last command u_{k-1}
    evolution: jax.Array  # last active-state evolution w_{k-1} = p_hat_{k-1} - p_hat_{k-2}
    missing: jax.Array  # measurement components skipped so far


class ActiveObserverInputs(NamedTuple):
    y: jax.Array  # measurement y_k (NaN = missing)
    r: jax.Array  # reference r_k


class ActiveObserverOutputs(NamedTuple):
    u: jax.Array  # command u_k = r_k - L x_hat_k
    x: jax.Array  # a-posteriori estimate
    p: jax.Array  # newest active state p_hat_k (zeros for a CKF)
    innovation: jax.Array
    gain: jax.Array  # K_k
    q_active: jax.Array  # variance used for the newest active state at this step
    alpha: jax.Array  # strategy implied by q_active and w_{k-1} (seed 001 eq. 34)
    converged: jax.Array  # the steady-state gains' DAREs converged (True for time-varying gains)


def _active_slice(params: ActiveObserverParams):
    """Indices of the newest active-state block (where the driving noise enters)."""
    n = params.Phi.shape[-1]
    return slice(n - params.n_inputs, n)


def _active_mask(params: ActiveObserverParams):
    """1 on plant states, ``active`` on active states."""
    n = params.Phi.shape[-1]
    n_plant = n - params.n_active
    return jnp.concatenate(
        [jnp.ones((n_plant,), params.Phi.dtype), jnp.broadcast_to(params.active, (params.n_active,))]
    )


def _init(params: ActiveObserverParams) -> ActiveObserverState:
    mask = _active_mask(params)
    m = params.n_inputs
    P0 = params.P0 * jnp.outer(mask, mask)
    zeros = jnp.zeros((m,), params.Phi.dtype)
    return ActiveObserverState(params.x0 * mask, P0, zeros, zeros, jnp.zeros((), jnp.int32))


def _step(params: ActiveObserverParams, state: ActiveObserverState, inputs: ActiveObserverInputs):
    p, dtype = params.C.shape[-2], params.Phi.dtype
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    r = _checks.vector("inputs.r", inputs.r, params.n_inputs, dtype, what="one entry per plant input",
                       check_finite=False)  # fmt: skip
    Q = params.Q
    q_active = alpha = evolution = p_new = jnp.zeros_like(r)
    if params.n_active:  # static: a CKF built without active state skips this bookkeeping
        mask = _active_mask(params)
        newest = _active_slice(params)
        q_adaptive = adaptive_variance(state.evolution, params.alpha, params.sigma_floor)
        q_active = jnp.where(params.alpha > 0, q_adaptive, jnp.diagonal(Q)[newest])
        Q = Q.at[newest, newest].set(jnp.diag(q_active)) * jnp.outer(mask, mask)
        alpha = strategy_alpha(state.evolution, q_active)
    gain = None if params.gain is None else jnp.where(params.active > 0, params.gain, params.gain_passive)
    x, P, K, innovation, n_missing, _ = predict_and_update(
        state.x, state.P, state.u, y, params.Phi, params.Gamma, params.C, Q, params.R, gain
    )
    if params.n_active:
        x = x * mask
        p_new = x[newest]
        evolution = p_new - state.x[newest]
    u = r - params.L @ x
    new_state = ActiveObserverState(x, P, u, evolution, state.missing + n_missing.astype(jnp.int32))
    converged = jnp.asarray(True) if params.gain_converged is None else params.gain_converged
    return new_state, ActiveObserverOutputs(u, x, p_new, innovation, K, q_active, alpha, converged)


active_observer = Observer(_init, _step)
"""AOB-N / CKF observer-based controller in the (init, step) protocol.

Inputs are :class:`ActiveObserverInputs` ``(y_k, r_k)`` of shapes ``(p,)`` and ``(m,)`` (scalars where the size is
1); the output ``u`` is the command to apply. Each step checks the inputs' shapes against the params while tracing (a
``ValueError`` naming the field) and casts them to the params' dtype.
"""


def make_aob(
    plant: StateSpace,
    L_r,
    order: int,
    R,
    *,
    q_plant=1e-12,
    q_active=1e-3,
    P0=None,
    x0=None,
    active=1.0,
    alpha=0.0,
    sigma_floor=0.0,
    steady_state: bool = False,
) -> ActiveObserverParams:
    """Build an AOB-N for a discrete (delay-augmented) plant and state feedback ``L_r``.

    Args:
      plant: discrete nominal model ``(Phi_r, Gamma_r, C_r)``, e.g. from :func:`jaxobs.lti.c2d`.
      L_r: (m, n) state-feedback gain designed on the plant (e.g. :func:`jaxobs.design.acker`).
      order: N >= 1 (use :func:`make_ckf` for the CKF).
      R: measurement noise covariance.
      q_plant: diagonal of ``Q_xr`` (eq. 51), small: the model is trusted, errors go to ``p``.
      q_active: variance of ``^{N-1} xi_p`` (see :func:`evolution_variance`).
      P0: ``P_{-1}``; defaults to ``Q`` (the papers' ``P_{-1} = Q_0``).
      active: 1 for the AOB, 0 to run it as a CKF (traced; switch at run time).
      alpha, sigma_floor: adaptive active-state strategy of seed 001 (``alpha > 0`` enables it).
      steady_state: use the steady-state gains (:func:`with_steady_state_gains`; raises ``ValueError`` with
        the reason when their DARE does not converge, e.g. AOB-3 in float32).
    """
    order = _checks.count("order", order, minimum=1, hint="use make_ckf for the classical filter")
    return _make(plant, L_r, order, R, q_plant, q_active, None, P0, x0, active, alpha, sigma_floor, steady_state)


def make_ckf(plant: StateSpace, L_r, R, *, Q=None, q_plant=1e-12, P0=None, x0=None, steady_state=False):
    """Classical Kalman filter with state feedback ``u = r - L_r x_hat`` (the AOB without active
    state). ``Q`` defaults to ``q_plant * I``."""
    return _make(plant, L_r, 0, R, q_plant, 0.0, Q, P0, x0, 1.0, 0.0, 0.0, steady_state)


def _make(plant, L_r, order, R, q_plant, q_active, Q, P0, x0, active, alpha, sigma_floor, steady_state):
    """Shared by :func:`make_aob` and :func:`make_ckf`. Every array (plant, gains, covariances, switches) is
    cast to their common floating dtype: integers become float, float32 mixed with float64 becomes float64."""
    if not plant.is_discrete:
        raise ValueError("plant must be discrete (use jaxobs.lti.c2d first)")
    n, m = plant.n_states, plant.n_inputs
    L_r = jnp.atleast_2d(jnp.asarray(L_r))
    Q, R, P0 = (None if M is None else jnp.atleast_2d(jnp.asarray(M)) for M in (Q, R, P0))
    dtype = _checks.float_dtype(
        **{"plant.A": plant.A, "plant.B": plant.B, "plant.C": plant.C}, L_r=L_r, R=R, Q=Q, P0=P0, x0=x0,
        q_plant=q_plant, q_active=q_active, active=active, alpha=alpha, sigma_floor=sigma_floor,
    )  # fmt: skip
    _checks.matrix("L_r", L_r, shape=(m, n))
    plant = StateSpace(*(jnp.asarray(M, dtype) for M in (plant.A, plant.B, plant.C, plant.D)), plant.dt)
    Phi, Gamma, C = augment(plant, order)
    na = order * m
    compensation = jnp.zeros((m, na), dtype).at[:, na - m :].set(jnp.eye(m, dtype=dtype))
    L = jnp.concatenate([L_r.astype(dtype), compensation], axis=1)
    if Q is None:
        Q = aob_noise_covariance(n, order, m, jnp.asarray(q_plant, dtype), jnp.asarray(q_active, dtype))
        _checks.positive_scalar("q_active", jnp.min(jnp.asarray(q_active)), allow_zero=True)
    _checks.covariance("Q", Q, definite=False, size=n + na)
    _checks.covariance("R", R, definite=True, size=C.shape[0])
    P0 = Q if P0 is None else P0
    _checks.covariance("P0", P0, definite=False, size=n + na)
    x0 = (
        jnp.zeros((n + na,), dtype)
        if x0 is None
        else _checks.vector("x0", x0, n + na, dtype, what="one entry per state of the augmented model [x_r, p]")
    )
    _checks.shape("active", active, (), "a scalar switch: 1 for the AOB, 0 for the CKF")
    _checks.finite("active", active)
    alpha = _checks.per_entry("alpha", alpha, m, dtype, "one per plant input")
    sigma_floor = _checks.per_entry("sigma_floor", sigma_floor, m, dtype, "one per plant input")
    _checks.positive_scalar("sigma_floor", jnp.min(sigma_floor), allow_zero=True)
    if _checks.is_concrete(alpha) and np.any(np.asarray(alpha) >= 1):
        raise ValueError("alpha must be < 1 (a probability); use alpha <= 0 to keep Q fixed")
    params = ActiveObserverParams(
        Phi, Gamma, C, L, Q.astype(dtype), R.astype(dtype), P0.astype(dtype), x0,
        jnp.asarray(active, dtype), alpha, sigma_floor, n_active=na,
    )  # fmt: skip
    return with_steady_state_gains(params) if steady_state else params


def set_active(params: ActiveObserverParams, on) -> ActiveObserverParams:
    """Switch the active state on (AOB) or off (CKF) at run time (seed 003 §6.3, §7.1).

    ``on`` may be a bool, a number or a traced array, a scalar or of the shape of ``params.active`` (e.g. one
    per DOF of stacked controllers); it is cast to the params' dtype so switching never triggers a recompilation.
    """
    on = jnp.asarray(on)
    if on.shape not in ((), params.active.shape):
        raise ValueError(
            f"on must be a scalar or have the shape {params.active.shape} of params.active, got {on.shape}"
        )
    _checks.finite("on", on)
    return dataclasses.replace(params, active=jnp.broadcast_to(on.astype(params.Phi.dtype), params.active.shape))


def with_steady_state_gains(params: ActiveObserverParams) -> ActiveObserverParams:
    """Fix the gains at their steady state (DARE with the open-loop ``Phi_n``, seed 000 eq. 28/48),
    for the AOB and for the passive (CKF) mode, so ``active`` still switches at run time.

    Eagerly, raises ``ValueError`` with the reason when a DARE has no stabilising solution or did not
    converge (the AOB designs' ``Q`` entries of 1e-12 next to 1e-3 need float64 from AOB-3 on); under
    tracing both flags are stored, combined, in ``gain_converged``.
    """
    n = params.Phi.shape[-1]
    n_plant = n - params.n_active
    label = f"AOB-{params.n_active // params.n_inputs}" if params.n_active else "CKF"
    sol = dare(params.Phi, params.C, params.Q, params.R)
    require_converged(sol, params.Phi, params.C, params.Q, params.R, what=f"the {label} steady-state gain's DARE")
    gain = kalman_gain(sol.P, params.C, params.R)
    converged = sol.converged
    if params.n_active:
        rows = slice(0, n_plant)
        Phi_r, C_r, Q_r = params.Phi[rows, rows], params.C[:, rows], params.Q[rows, rows]
        sol_r = dare(Phi_r, C_r, Q_r, params.R)
        require_converged(sol_r, Phi_r, C_r, Q_r, params.R, what="the passive (CKF) steady-state gain's DARE")
        gain_passive = jnp.zeros_like(gain).at[rows].set(kalman_gain(sol_r.P, C_r, params.R))
        converged = converged & sol_r.converged
    else:
        gain_passive = gain
    return dataclasses.replace(params, gain=gain, gain_passive=gain_passive, gain_converged=converged)


# --------------------------------------------------------------------------------------------
# Stochastic design of Q (seed 001 §3)

BETA_ONE_SIGMA = float(1.0 - erf(np.sqrt(2.0) / 2.0))
"""Seed 001 eq. 47: the probability of a deviation larger than one standard deviation (0.3173)."""


def adaptive_variance(evolution, alpha, sigma_floor):
    """Active-state variance for the strategy ``P(|w_k| > |w_{k-1}|) = alpha`` (seed 001 eq. 20, 27):
    ``sigma = |w_{k-1}| / (sqrt(2) erfinv(1 - alpha))``, floored at ``sigma_floor`` (sigma*, §3.1)
    so the estimate can follow abrupt changes after quiet periods. Returns ``sigma**2``."""
    alpha = jnp.clip(alpha, 1e-12, 1.0 - 1e-12)
    sigma = jnp.abs(evolution) / (jnp.sqrt(2.0) * erfinv(1.0 - alpha))
    return jnp.maximum(sigma, sigma_floor) ** 2


def alpha_for_floor(evolution, sigma_floor):
    """Seed 001 eq. 32: the ``alpha_k`` that yields ``sigma = sigma*`` for weak evolutions,
    ``1 - sqrt(2/pi) |w_{k-1}| / sigma*``."""
    return 1.0 - jnp.sqrt(2.0 / jnp.pi) * jnp.abs(evolution) / sigma_floor


def strategy_alpha(evolution, q):
    """Seed 001 eq. 34: the strategy implied by a variance ``q``, ``1 - erf(|w_{k-1}| / sqrt(2 q))``."""
    q = jnp.maximum(q, jnp.finfo(jnp.result_type(q, float)).tiny)
    return 1.0 - erf(jnp.abs(evolution) / jnp.sqrt(2.0 * q))


def constant_strategy_variance(evolution, c):
    """Seed 001 eq. 35-36: ``Q_k = |w_{k-1}|^2 / c^2`` keeps ``alpha = 1 - erf(c / sqrt 2)`` constant."""
    return jnp.abs(evolution) ** 2 / c**2


def deviation_variance(gamma, beta=BETA_ONE_SIGMA):
    """Seed 001 eq. 45-46: the ``Q_i`` for which ``P(|x_i - E x_i| > gamma) = beta``:
    ``(gamma / (sqrt(2) erfinv(1 - beta)))**2``. With the default beta (eq. 47), ``Q_i = gamma**2``."""
    return (gamma / (jnp.sqrt(2.0) * erfinv(1.0 - beta))) ** 2


# --------------------------------------------------------------------------------------------
# Estimation strategies (seed 000 §5, seed 003 §6.3)


def sensor_based_gain(C):
    """The sensor-based (SBA) limit of a Kalman gain: measured states are replaced by the
    measurements, the others are not corrected (``K = C^+``; for ``C = [1 0 ... 0]``,
    ``K = [1, 0, ..., 0]'``), the "CKF, SBA" of seed 003 §7.4."""
    return jnp.linalg.pinv(jnp.atleast_2d(C))


def classify_strategy(gain, C, *, low: float = 0.01, high: float = 0.9) -> str:
    """Name the estimation strategy of a (steady-state) gain: the fraction of the innovation that
    reaches the measured outputs, ``||C K||_2``, is below ``low`` (model-based, MBA), above ``high``
    (sensor-based, SBA) or in between (hybrid, HBA). The thresholds are this library's convention;
    the papers define the strategies qualitatively. Design-time helper (returns a Python string); ``gain``
    (n, p), ``C`` (p, n)."""
    gain, C = np.atleast_2d(np.asarray(gain, dtype=float)), np.atleast_2d(np.asarray(C, dtype=float))
    _checks.matrix("C", C)
    _checks.matrix("gain", gain, shape=(C.shape[1], C.shape[0]))
    fraction = float(np.linalg.norm(np.asarray(C) @ np.asarray(gain), 2))
    return "MBA" if fraction < low else "SBA" if fraction > high else "HBA"
