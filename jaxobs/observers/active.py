"""Kalman Active Observer AOB-N (Cortesão 2006 §2-5; Cortesão, Koeppe, Nunes & Hirzinger, "Stochastic
Active Observers"; Cortesão, MRAC chapter §5-6) as an estimator.

A Kalman filter on the plant model augmented with an *active state*: an equivalent input disturbance modelled as
an order-N auto-regressive process (eq. 10, 37) whose newest value ``p_hat_k`` is the disturbance estimate ``d``.
With the active state removed (``active = 0``) it is the classical Kalman filter (CKF). :func:`make_aob`,
:func:`make_ckf` and :data:`active_observer`; as a controller :data:`active_observer_controller` with
:func:`feedback_gain` (eq. 20, 49-50). State order, prior and run-time switches: docs/theory/estimators.md.
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from math import comb
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import erf, erfinv

from jaxobs import _checks
from jaxobs._jit import jit
from jaxobs._linalg import symmetrize
from jaxobs.kalman_steps import kalman_gain, predict, update
from jaxobs.lti import StateSpace
from jaxobs.matrix_equations import dare, require_converged
from jaxobs.observers.base import Estimator, EstimatorInputs, LinearObserver
from jaxobs.observers.feedback import observer_controller

__all__ = [
    "ActiveObserverParams",
    "ActiveObserverState",
    "ActiveObserverOutputs",
    "active_observer",
    "active_observer_controller",
    "disturbance",
    "feedback_gain",
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


def active_state_model(order: int, n_channels: int = 1, dtype=jnp.float64):
    """``Phi_22`` of eq. 37 for ``q = n_channels`` channels: ``kron(companion, I_q)``, shape ``(N q, N q)``.

    The companion row holds ``a_i = (-1)^{i+1} C(N, i)`` (eq. 10), so ``N`` repeated eigenvalues at 1:
    ``p_k`` has zero N-th difference up to the driving noise.
    """
    order = _checks.count("order", order, minimum=1, hint="an active state needs N >= 1")
    n_channels = _checks.count("n_channels", n_channels, minimum=1)
    companion = np.zeros((order, order))
    companion[:-1, 1:] = np.eye(order - 1)
    companion[-1, :] = [(-1) ** (i + 1) * comb(order, i) for i in range(order, 0, -1)]
    return jnp.asarray(np.kron(companion, np.eye(n_channels)), dtype)


def augment(plant: StateSpace, order: int, disturbance_input=None):
    """Augmented open-loop model (eq. 30, 39, 48, 24): returns ``(Phi_n, Gamma_n, C)``.

    ``Phi_n = [[Phi_r, Phi_12], [0, Phi_22]]`` with ``Phi_12 = G_d [0 ... 0 I]`` (eq. 41: the newest active
    state enters where the disturbance does), ``Gamma_n = [Gamma_r; 0]``, ``C = [C_r 0]``. ``G_d``
    (``disturbance_input``, (n, q)) defaults to ``Gamma_r``: the papers' equivalent input disturbance, which
    state feedback can cancel. ``order = 0`` returns the plant matrices unchanged (the CKF).
    """
    order = _checks.count("order", order)
    Phi_r, Gamma_r, C_r = StateSpace.check(plant, "plant").A, plant.B, plant.C
    if order == 0:
        return Phi_r, Gamma_r, C_r
    G_d = Gamma_r if disturbance_input is None else jnp.atleast_2d(jnp.asarray(disturbance_input, Phi_r.dtype))
    n, m = Gamma_r.shape[-2:]
    _checks.matrix("disturbance_input", G_d, shape=(n, None))
    q = G_d.shape[-1]
    na = order * q
    Phi22 = active_state_model(order, q, Phi_r.dtype)
    Phi12 = jnp.zeros((n, na), Phi_r.dtype).at[:, na - q :].set(G_d)
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


def aob_noise_covariance(n_plant: int, order: int, n_channels: int, q_plant, q_active):
    """``Q = blockdiag(Q_xr, Q_Np)`` (eq. 51-53), shape ``(n_plant + order n_channels,)*2``.

    ``q_plant``: scalar or length-``n_plant`` diagonal of ``Q_xr``. ``q_active``: scalar or
    length-``n_channels`` variance of ``^{N-1} xi_p``, placed on the newest active-state block only.
    """
    n_plant = _checks.count("n_plant", n_plant)
    order = _checks.count("order", order)
    n_channels = _checks.count("n_channels", n_channels, minimum=1)
    dtype = _checks.float_dtype(q_plant=q_plant, q_active=q_active)
    q_plant = _checks.per_entry("q_plant", q_plant, n_plant, dtype, "one variance per plant state")
    q_active = _checks.per_entry("q_active", q_active, n_channels, dtype, "one variance per active-state channel")
    diag_active = jnp.zeros((order * n_channels,), dtype)
    if order:
        diag_active = diag_active.at[-n_channels:].set(q_active)
    return jnp.diag(jnp.concatenate([q_plant, diag_active]))


# --------------------------------------------------------------------------------------------
# Parameters, state and the estimator step


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ActiveObserverParams:
    """An AOB-N (or, with ``order = 0``, a CKF) for a plant with ``n`` states and ``m`` inputs, with ``q``
    active-state channels (``q = m`` for the papers' equivalent input disturbance); shapes with
    ``n_aug = n + n_active``, ``n_active = N q``.

    Attributes:
      Phi: (n_aug, n_aug) augmented open-loop ``Phi_n`` (eq. 48).  Gamma: (n_aug, m) ``[Gamma_r; 0]``.
      C: (p, n_aug) ``[C_r 0]`` (eq. 24).  Q: (n_aug, n_aug) eq. 51.  R: (p, p).
      x0: (n_aug,), P0: (n_aug, n_aug): prior of ``x_0``.
      active: () 1.0 for the AOB, 0.0 for the CKF (run-time switch).
      alpha: (q,) adaptive strategy of the stochastic AOB paper (eq. 27) per channel; <= 0 keeps Q fixed.
      sigma_floor: (q,) ``sigma*`` of that paper (§3.1): minimum std of the active-state evolution.
      gain, gain_passive: ``None`` for the time-varying Riccati gain, or the (n_aug, p) steady-state gains of
        the AOB and of the same filter with the active state switched off (:func:`with_steady_state_gains`).
      gain_converged: () whether both DAREs behind the steady-state gains found their stabilising solutions
        (an array when computed under tracing, reported by every step as ``ActiveObserverOutputs.converged``).
      order: static AOB order N (0 for the CKF).  n_channels: static q.
      matched: static; True when the active state enters where the input does (``G_d = Gamma_r``), so that
        :func:`feedback_gain` can cancel it.
      output_covariance: static; every step also outputs the covariances ``P``, ``P_prior`` (what the smoothers of
        :mod:`jaxobs.smoothing` read; ``2 T n_aug^2`` more numbers over ``T`` steps). Time-varying gains only.
    """

    Phi: jax.Array
    Gamma: jax.Array
    C: jax.Array
    Q: jax.Array
    R: jax.Array
    P0: jax.Array
    x0: jax.Array
    active: jax.Array
    alpha: jax.Array
    sigma_floor: jax.Array
    gain: jax.Array | None = None
    gain_passive: jax.Array | None = None
    gain_converged: jax.Array | None = None
    order: int = dataclasses.field(default=0, metadata=dict(static=True))
    n_channels: int = dataclasses.field(default=1, metadata=dict(static=True))
    matched: bool = dataclasses.field(default=True, metadata=dict(static=True))
    output_covariance: bool = dataclasses.field(default=False, metadata=dict(static=True))

    @property
    def n_inputs(self) -> int:
        """Number of plant inputs ``m``."""
        return self.Gamma.shape[-1]

    @property
    def n_active(self) -> int:
        """Number of active states ``q`` (order times channels)."""
        return self.order * self.n_channels


class ActiveObserverState(NamedTuple):
    """State of :data:`active_observer` between steps (``n_aug = n + q`` states: the plant's and the active states).

    Attributes:
      x: (n_aug,) a-posteriori estimate [x_r, p] (the prior mean before the first step)
      P: (n_aug, n_aug) its covariance
      evolution: (q,) last active-state evolution w_{k-1} = p_hat_{k-1} - p_hat_{k-2}
      started: () bool: a measurement has been processed (the next step predicts)
      missing: () int32, measurement components skipped so far
    """

    x: jax.Array
    P: jax.Array
    evolution: jax.Array
    started: jax.Array
    missing: jax.Array


class ActiveObserverOutputs(NamedTuple):
    """Outputs of one step of :data:`active_observer`.

    Attributes:
      x: (n_aug,) a-posteriori estimate
      d: (q,) newest active state p_hat_k: the equivalent input disturbance (zeros for a CKF)
      x_prior: (n_aug,) a-priori estimate
      innovation: (p,) y_k - C x_prior (0 for missing components)
      gain: (n_aug, p) K_k
      q_active: (q,) variance used for the newest active state at this step
      alpha: (q,) strategy implied by q_active and w_{k-1} (stochastic AOB paper, eq. 34)
      converged: () the steady-state gains' DAREs converged (True for time-varying gains)
      S: (p, p) innovation covariance of the observed components (1 on a missing diagonal)
      log_likelihood: () log p(y_k | y_0..y_{k-1}) under the active-state model (0 when all are missing)
      P: (n_aug, n_aug) a-posteriori covariance (with output_covariance, else None)
      P_prior: (n_aug, n_aug) a-priori covariance (with output_covariance, else None)
    """

    x: jax.Array
    d: jax.Array
    x_prior: jax.Array
    innovation: jax.Array
    gain: jax.Array
    q_active: jax.Array
    alpha: jax.Array
    converged: jax.Array
    S: jax.Array
    log_likelihood: jax.Array
    P: jax.Array | None = None
    P_prior: jax.Array | None = None


_SHAPES = (
    "Phi (n, n), Gamma (n, m), C (p, n), Q (n, n), R (p, p), P0 (n, n), x0 (n,), active (), alpha (q,), "
    "sigma_floor (q,), gain (n, p), gain_passive (n, p), gain_converged ()"
)


def _check_params(params) -> ActiveObserverParams:
    """``params``, checked at trace time to be one AOB (:class:`ActiveObserverParams`, no batch axis: ``vmap``)."""
    if not isinstance(params, ActiveObserverParams):
        raise ValueError(f"params must be ActiveObserverParams (make_aob, make_ckf), got {type(params).__name__}")
    _checks.fields("params", params, _SHAPES)
    return params


def _active_slice(params: ActiveObserverParams):
    """Indices of the newest active-state block (where the driving noise enters)."""
    n = params.Phi.shape[-1]
    return slice(n - params.n_channels, n)


def _active_mask(params: ActiveObserverParams):
    """1 on plant states, ``active`` on active states."""
    n = params.Phi.shape[-1]
    n_plant = n - params.n_active
    return jnp.concatenate(
        [jnp.ones((n_plant,), params.Phi.dtype), jnp.broadcast_to(params.active, (params.n_active,))]
    )


def _init(params: ActiveObserverParams) -> ActiveObserverState:
    _check_params(params)
    mask = _active_mask(params)
    zeros = jnp.zeros((params.n_channels,), params.Phi.dtype)
    P0 = params.P0 * jnp.outer(mask, mask)
    return ActiveObserverState(params.x0 * mask, P0, zeros, jnp.zeros((), bool), jnp.zeros((), jnp.int32))


def _step(params: ActiveObserverParams, state: ActiveObserverState, inputs: EstimatorInputs):
    _check_params(params)
    p, m, dtype = params.C.shape[-2], params.n_inputs, params.Phi.dtype
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    u_prev = inputs.u_prev
    if u_prev is not None:
        u_prev = _checks.vector("inputs.u_prev", u_prev, m, dtype, what="one entry per plant input",
                                check_finite=False)  # fmt: skip
    Q = params.Q
    q_active = alpha = evolution = d = jnp.zeros((params.n_channels,), dtype)
    mask = _active_mask(params)
    if params.n_active:  # static: a CKF built without active state skips this bookkeeping
        newest = _active_slice(params)
        q_adaptive = adaptive_variance(state.evolution, params.alpha, params.sigma_floor)
        q_active = jnp.where(params.alpha > 0, q_adaptive, jnp.diagonal(Q)[newest])
        Q = Q.at[newest, newest].set(jnp.diag(q_active)) * jnp.outer(mask, mask)
        alpha = strategy_alpha(state.evolution, q_active)
    gain = None if params.gain is None else jnp.where(params.active > 0, params.gain, params.gain_passive)
    if gain is not None and params.output_covariance:
        raise ValueError("params.output_covariance: steady-state gains propagate no covariance; use the time-varying "
                         "gain (params.gain None)")  # fmt: skip
    P = None if gain is not None else state.P
    x_prior, P_prior = predict(state.x, P, params.Phi, Q, params.Gamma, u_prev, skip=~state.started)
    P_prior = state.P if P_prior is None else P_prior
    result = update(x_prior, P_prior, params.C, params.R, y, gain)
    x = result.x * mask if params.n_active else result.x
    if params.n_active:
        d = x[newest]
        evolution = d - state.x[newest]
    missing = state.missing + result.n_missing.astype(jnp.int32)
    new_state = ActiveObserverState(x, result.P, evolution, jnp.ones((), bool), missing)
    converged = jnp.asarray(True) if params.gain_converged is None else params.gain_converged
    covariances = (result.P, P_prior) if params.output_covariance else ()
    outputs = ActiveObserverOutputs(x, d, x_prior, result.innovation, result.K, q_active, alpha, converged, result.S,
                                    result.log_likelihood, *covariances)  # fmt: skip
    return new_state, outputs


def disturbance(params: ActiveObserverParams, x):
    """The newest active state ``p_k`` (..., q) of augmented states ``x`` (..., n_aug): the disturbance estimate
    ``d`` of any record of states, e.g. the smoothed ones of :func:`jaxobs.smoothing.smooth` (zeros for a CKF)."""
    _check_params(params)
    (x,) = _checks.float_arrays(x=x)
    _checks.shape("x", x, (*x.shape[:-1], params.Phi.shape[-1]), "augmented states, any leading axes")
    if not params.n_active:
        return jnp.zeros((*jnp.shape(x)[:-1], params.n_channels), jnp.result_type(x))
    return x[..., _active_slice(params)]


def _linear(params: ActiveObserverParams) -> LinearObserver:
    """The steady-state AOB/CKF as a fixed-gain linear observer; with the active state switched off its rows
    are zeroed and the passive gain used, as the run-time switch does."""
    if params.gain is None:
        raise ValueError("params: the linear form needs steady-state gains; use with_steady_state_gains")
    mask = _active_mask(params)[:, None]
    gain = jnp.where(params.active > 0, params.gain, params.gain_passive)
    return LinearObserver(mask * params.Phi, mask * params.Gamma, params.C, mask * gain)


active_observer = Estimator(_init, _step, _linear)
"""The AOB-N / CKF as an :class:`~jaxobs.observers.base.Estimator` over :class:`ActiveObserverParams`.

Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (p,) and (m,), ``u_prev`` the command actually applied over
the last interval; each step checks them against the params while tracing and casts them to the params'
dtype. Outputs: :class:`ActiveObserverOutputs` (``d`` is the active-state estimate ``p_hat_k``).
"""

active_observer_controller = observer_controller(active_observer)
"""The AOB-N / CKF with state feedback ``u_k = N r_k - L x_hat_k`` (Cortesão 2006 eq. 49-50); params:
:class:`~jaxobs.observers.feedback.FeedbackParams` with ``L = feedback_gain(aob, L_r)``."""


def feedback_gain(params: ActiveObserverParams, L_r):
    """``L = [L_r, 0, ..., 0, I]`` (Cortesão 2006 eq. 49-50) for the AOB ``params``: the plant's state feedback
    ``L_r`` (m, n) plus the compensation of the newest active state, on the augmented state (m, n + n_active);
    the ``L`` of :class:`~jaxobs.observers.feedback.FeedbackParams` for :data:`active_observer_controller`."""
    _check_params(params)
    if not params.matched:
        raise ValueError(
            "params: the active state enters through disturbance_input, not the plant input, so state feedback "
            "cannot cancel it; build the L of your controller from L_r yourself"
        )
    m, n_aug = params.n_inputs, params.Phi.shape[-1]
    n = n_aug - params.n_active
    L_r = jnp.atleast_2d(jnp.asarray(L_r))
    _checks.matrix("L_r", L_r, shape=(m, n))
    L = jnp.zeros((m, n_aug), params.Phi.dtype).at[:, :n].set(L_r)
    if params.n_active:
        L = L.at[:, n_aug - m :].set(jnp.eye(m, dtype=params.Phi.dtype))
    return L


def make_aob(
    plant: StateSpace,
    order: int,
    R,
    *,
    q_plant=1e-12,
    q_active=1e-3,
    Q=None,
    P0=None,
    x0=None,
    active=1.0,
    alpha=0.0,
    sigma_floor=0.0,
    disturbance_input=None,
    steady_state: bool = False,
) -> ActiveObserverParams:
    """Build an AOB-N for a discrete (delay-augmented) plant.

    Args:
      plant: discrete nominal model ``(Phi_r, Gamma_r, C_r)``, e.g. from :func:`jaxobs.lti.c2d`.
      order: N >= 1 (use :func:`make_ckf` for the CKF).
      R: (p, p) measurement noise covariance (a scalar for one output).
      q_plant: diagonal of ``Q_xr`` (eq. 51), small: the model is trusted, errors go to ``p``.
      q_active: variance of ``^{N-1} xi_p`` (see :func:`evolution_variance`), scalar or one per input.
      Q: (n_aug, n_aug) full process noise covariance replacing eq. 51-53's ``blockdiag(Q_xr, Q_Np)`` (then
        ``q_plant`` and ``q_active`` are not used), e.g. a tuned :func:`jaxobs.tuning.cholesky_covariance`.
      P0: (n_aug, n_aug) prior covariance of ``x_0``; defaults to ``Phi_n Q Phi_n' + Q`` (the papers'
        ``P_{-1} = Q_0`` advanced one step; with ``active = 0`` the active block of ``Q`` is zeroed first, so the
        switched-off AOB starts from the CKF's prior).
      x0: (n_aug,) prior mean of ``x_0`` (default zeros).
      active: 1 for the AOB, 0 to run it as a CKF (traced; switch at run time).
      alpha, sigma_floor: adaptive active-state strategy of the stochastic AOB paper (``alpha > 0`` enables it),
        scalars or one per channel.
      disturbance_input: (n, q) matrix ``G_d`` through which the active state enters (default ``Gamma_r``, the
        papers' equivalent input disturbance, ``q = m``): e.g. a known disturbance direction to estimate.
      steady_state: use the steady-state gains (:func:`with_steady_state_gains`; raises ``ValueError`` with
        the reason when their DARE does not converge, e.g. AOB-3 in float32).

    Example:
      >>> from jaxobs.lti import ss, c2d
      >>> from jaxobs.observers import active
      >>> plant = c2d(ss([[0, 1], [0, -31.25]], [[0], [93.75]], [[1, 0]]), 0.008, delay=0.04)
      >>> aob = active.make_aob(plant, order=2, R=2.1e-2, q_active=4e-6, steady_state=True)
      >>> aob.Phi.shape, aob.gain.shape
      ((9, 9), (9, 1))
    """
    order = _checks.count("order", order, minimum=1, hint="use make_ckf for the classical filter")
    return _make(plant, order, R, q_plant, q_active, Q, P0, x0, active, alpha, sigma_floor, disturbance_input,
                 steady_state)  # fmt: skip


def make_ckf(plant: StateSpace, R, *, Q=None, q_plant=1e-12, P0=None, x0=None, steady_state=False):
    """The classical Kalman filter (CKF) on the plant model: the AOB without active state, in the AOB's params so
    that both run in the same sweeps and controllers.

    Args:
      plant: discrete nominal model.  R: (p, p) measurement noise covariance.
      Q: (n, n) process noise covariance; default ``q_plant * I``.
      q_plant: scalar or (n,) diagonal of the default ``Q``.
      P0: (n, n) prior covariance of ``x_0``; default ``Phi Q Phi' + Q``.  x0: (n,) prior mean (default zeros).
      steady_state: use the steady-state gain.
    """
    return _make(plant, 0, R, q_plant, 0.0, Q, P0, x0, 1.0, 0.0, 0.0, None, steady_state)


def _make(plant, order, R, q_plant, q_active, Q, P0, x0, active, alpha, sigma_floor, disturbance_input, steady_state):
    """Shared by :func:`make_aob` and :func:`make_ckf`. Every array (plant, covariances, switches) is
    cast to their common floating dtype: integers become float, float32 mixed with float64 becomes float64."""
    if not StateSpace.check(plant, "plant").is_discrete:
        raise ValueError("plant must be discrete (use jaxobs.lti.c2d first)")
    n = plant.n_states
    R = jnp.atleast_2d(_checks.real_array("R", R))
    Q, P0 = (None if M is None else jnp.atleast_2d(_checks.real_array(k, M)) for k, M in (("Q", Q), ("P0", P0)))
    dtype = _checks.float_dtype(
        **{"plant.A": plant.A, "plant.B": plant.B, "plant.C": plant.C}, R=R, Q=Q, P0=P0, x0=x0,
        q_plant=q_plant, q_active=q_active, active=active, alpha=alpha, sigma_floor=sigma_floor,
        disturbance_input=disturbance_input,
    )  # fmt: skip
    A, B, C_r = (jnp.asarray(M, dtype) for M in (plant.A, plant.B, plant.C))
    G_d = B if disturbance_input is None else jnp.atleast_2d(jnp.asarray(disturbance_input, dtype))
    _checks.matrix("disturbance_input", G_d, shape=(n, None))
    q = G_d.shape[-1]
    na = order * q
    given_Q = Q is not None
    if given_Q:
        _checks.covariance("Q", Q, definite=False, size=n + na)
    else:
        _checks.per_entry("q_plant", q_plant, n, dtype, "one variance per plant state")
        _checks.per_entry("q_active", q_active, q, dtype, "one variance per active-state channel")
        _checks.positive_scalar("q_active", jnp.min(jnp.asarray(q_active)), allow_zero=True)
    _checks.shape("active", active, (), "a scalar switch: 1 for the AOB, 0 for the CKF")
    _checks.finite("active", active)
    Q = Q.astype(dtype) if given_Q else None
    q_plant, q_active, active = (jnp.asarray(v, dtype) for v in (q_plant, q_active, active))
    Phi, Gamma, C, Q, P0_default = _assemble(A, B, C_r, G_d, Q, q_plant, q_active, active, order=order)
    if not given_Q:
        _checks.covariance("Q", Q, definite=False, size=n + na)
    _checks.covariance("R", R, definite=True, size=C.shape[0])
    P0 = P0_default if P0 is None else P0
    _checks.covariance("P0", P0, definite=False, size=n + na)
    x0 = (
        jnp.zeros((n + na,), dtype)
        if x0 is None
        else _checks.vector("x0", x0, n + na, dtype, what="one entry per state of the augmented model [x_r, p]")
    )
    alpha = _checks.per_entry("alpha", alpha, q, dtype, "one per active-state channel")
    sigma_floor = _checks.per_entry("sigma_floor", sigma_floor, q, dtype, "one per active-state channel")
    _checks.positive_scalar("sigma_floor", jnp.min(sigma_floor), allow_zero=True)
    if _checks.is_concrete(alpha) and np.any(np.asarray(alpha) >= 1):
        raise ValueError("alpha must be < 1 (a probability); use alpha <= 0 to keep Q fixed")
    params = ActiveObserverParams(
        Phi, Gamma, C, Q, R.astype(dtype), P0.astype(dtype), x0,
        jnp.asarray(active, dtype), alpha, sigma_floor, order=order, n_channels=q, matched=disturbance_input is None,
    )  # fmt: skip
    return with_steady_state_gains(params) if _checks.boolean("steady_state", steady_state) else params


@partial(jit, static_argnames=("order",), what="make_aob")
def _assemble(A, B, C, G_d, Q, q_plant, q_active, active, *, order: int):
    """The augmented model (eq. 30-48), its ``Q`` (eq. 51-53, unless given) and the default prior: the papers'
    ``P_{-1} = Q_0`` with the switch applied, advanced one step (switched off: the CKF's prior). One compiled
    program, so eager constructions cost one dispatch."""
    plant = StateSpace(A, B, C, jnp.zeros((C.shape[0], B.shape[1]), A.dtype), 1.0)
    Phi, Gamma, C_aug = augment(plant, order, G_d)
    n, q = A.shape[-1], G_d.shape[-1]
    if Q is None:
        Q = aob_noise_covariance(n, order, q, q_plant, q_active)
    mask = jnp.concatenate([jnp.ones((n,), A.dtype), jnp.broadcast_to(active, (order * q,))])
    Q_switched = Q * jnp.outer(mask, mask)
    return Phi, Gamma, C_aug, Q, symmetrize(Phi @ Q_switched @ Phi.T + Q_switched)


def set_active(params: ActiveObserverParams, on) -> ActiveObserverParams:
    """Switch the active state on (AOB) or off (CKF) at run time (Cortesão, MRAC chapter §6.3, §7.1).

    ``on`` may be a bool, a number or a traced array, a scalar or of the shape of ``params.active`` (e.g. one
    per DOF of stacked controllers); it is cast to the params' dtype so switching never triggers a recompilation.
    The prior ``P0`` is kept: a time-varying AOB switched off before its first sample starts from the AOB's default
    prior, not the CKF's (``make_aob(..., active=0)`` gives that). ``params`` may be stacked (a leading axis per
    DOF, as :func:`jaxobs.mjx.compliant_6dof.stack_controllers` builds them).
    """
    if not isinstance(params, ActiveObserverParams):
        raise ValueError(f"params must be ActiveObserverParams (make_aob, make_ckf), got {type(params).__name__}")
    on = jnp.asarray(on)
    if on.shape not in ((), params.active.shape):
        raise ValueError(
            f"on must be a scalar or have the shape {params.active.shape} of params.active, got {on.shape}"
        )
    _checks.finite("on", on)
    return dataclasses.replace(params, active=jnp.broadcast_to(on.astype(params.Phi.dtype), params.active.shape))


def with_steady_state_gains(params: ActiveObserverParams) -> ActiveObserverParams:
    """Fix the gains at their steady state (DARE with the open-loop ``Phi_n``, Cortesão 2006 eq. 28/48),
    for the AOB and for the passive (CKF) mode, so ``active`` still switches at run time.

    The passive DARE is the plant's, embedded at the augmented size with the active states' rows and columns
    zero (its solution is ``blockdiag(P_r, 0)``, its gain ``[K_r; 0]``), so both are one batched solve: one
    compiled program per model size. States that stay exactly known (no noise in ``Q``, none in the prior ``P0``,
    and moved only by such states: the active states locked by a zero ``Q_p`` entry, Cortesão 2006 eq. 109) keep
    zero covariance and gain in the time-varying filter; they are embedded the same way, so the gain is the limit
    of the filter's recursion from ``P0`` (a locked constant is a mode at 1 that no DARE could stabilise).

    Eagerly, raises ``ValueError`` with the reason when a DARE has no
    stabilising solution or did not converge (the AOB designs' ``Q`` entries of 1e-12 next to 1e-3 need float64
    from AOB-3 on); under tracing both flags are stored, combined, in ``gain_converged``.
    """
    _check_params(params)
    n_plant = params.Phi.shape[-1] - params.n_active
    gain, gain_passive, sol, masks = _steady_state_gains(
        params.Phi, params.C, params.Q, params.R, params.P0, n_plant=n_plant
    )
    label = f"AOB-{params.order}" if params.order else "CKF"
    for i, what in enumerate((f"the {label} steady-state gain's DARE", "the passive (CKF) steady-state gain's DARE")):
        if i and not params.n_active:
            break
        if not _checks.is_concrete(masks):
            break
        kept = np.flatnonzero(np.asarray(masks[i]))
        Phi, C, Q = params.Phi[np.ix_(kept, kept)], params.C[:, kept], params.Q[np.ix_(kept, kept)]
        require_converged(jax.tree.map(lambda a, i=i: a[i], sol), Phi.T, C.T, Q, params.R, what=what, estimation=True)
    return dataclasses.replace(params, gain=gain, gain_passive=gain_passive, gain_converged=jnp.all(sol.converged))


def _exactly_known_states(Phi, Q, P0):
    """Mask (bool, ``(n,)``) of the states the filter knows exactly forever: no noise in ``Q`` or ``P0`` and
    moved only by such states, so their covariance rows stay zero. A fixed point of ``n`` shrinking steps."""
    known = (jnp.diagonal(Q) == 0) & (jnp.diagonal(P0) == 0)

    def shrink(_, known):
        moved_by_unknown = jnp.any((Phi != 0) & ~known[None, :], axis=1)
        return known & ~moved_by_unknown

    return jax.lax.fori_loop(0, Phi.shape[-1], shrink, known)


@partial(jit, static_argnames=("n_plant",), what="make_aob (steady state)")
def _steady_state_gains(Phi, C, Q, R, P0, *, n_plant: int):
    """``(gain, gain_passive, solutions, masks)`` of :func:`with_steady_state_gains`: the AOB's and the embedded
    plant's filter DAREs in one ``vmap``, each on the states in its row of ``masks`` (the others exactly known or
    switched off: zero rows and columns)."""
    estimated = ~_exactly_known_states(Phi, Q, P0)
    plant = jnp.arange(Phi.shape[-1]) < n_plant
    masks = jnp.stack([estimated, estimated & plant])
    weights = masks.astype(Phi.dtype)
    keep = weights[:, :, None] * weights[:, None, :]
    sol = jax.vmap(lambda keep: dare(Phi.T * keep, C.T, Q * keep, R))(keep)
    gains = jax.vmap(lambda X: kalman_gain(X, C, R))(sol.X) * weights[:, :, None]
    return gains[0], gains[1], sol, masks


# --------------------------------------------------------------------------------------------
# Stochastic design of Q (Cortesão, Koeppe, Nunes & Hirzinger, stochastic AOB paper §3)

BETA_ONE_SIGMA = 1.0 - math.erf(math.sqrt(2.0) / 2.0)  # plain Python: importing jaxobs starts no JAX backend
"""The stochastic AOB paper eq. 47: the probability of a deviation larger than one standard deviation (0.3173)."""


def adaptive_variance(evolution, alpha, sigma_floor):
    """Active-state variance for the strategy ``P(|w_k| > |w_{k-1}|) = alpha`` (stochastic AOB paper, eq. 20, 27):
    ``sigma = |w_{k-1}| / (sqrt(2) erfinv(1 - alpha))``, floored at ``sigma_floor`` (sigma*, §3.1)
    so the estimate can follow abrupt changes after quiet periods. Returns ``sigma**2``. Elementwise (any shapes
    that broadcast)."""
    evolution, alpha, sigma_floor = _checks.float_arrays(evolution=evolution, alpha=alpha, sigma_floor=sigma_floor)
    alpha = jnp.clip(alpha, 1e-12, 1.0 - 1e-12)
    sigma = jnp.abs(evolution) / (jnp.sqrt(2.0) * erfinv(1.0 - alpha))
    return jnp.maximum(sigma, sigma_floor) ** 2


def alpha_for_floor(evolution, sigma_floor):
    """The stochastic AOB paper eq. 32: the ``alpha_k`` that yields ``sigma = sigma*`` for weak evolutions,
    ``1 - sqrt(2/pi) |w_{k-1}| / sigma*``. Elementwise."""
    evolution, sigma_floor = _checks.float_arrays(evolution=evolution, sigma_floor=sigma_floor)
    return 1.0 - jnp.sqrt(2.0 / jnp.pi) * jnp.abs(evolution) / sigma_floor


def strategy_alpha(evolution, q):
    """The stochastic AOB paper eq. 34: the strategy implied by a variance ``q``, ``1 - erf(|w_{k-1}| / sqrt(2 q))``.
    Elementwise."""
    evolution, q = _checks.float_arrays(evolution=evolution, q=q)
    q = jnp.maximum(q, jnp.finfo(q.dtype).tiny)
    return 1.0 - erf(jnp.abs(evolution) / jnp.sqrt(2.0 * q))


def constant_strategy_variance(evolution, c):
    """The stochastic AOB paper, eq. 35-36: ``Q_k = |w_{k-1}|^2 / c^2`` keeps ``alpha = 1 - erf(c / sqrt 2)``
    constant. Elementwise."""
    evolution, c = _checks.float_arrays(evolution=evolution, c=c)
    return jnp.abs(evolution) ** 2 / c**2


def deviation_variance(gamma, beta=BETA_ONE_SIGMA):
    """The stochastic AOB paper eq. 45-46: the ``Q_i`` for which ``P(|x_i - E x_i| > gamma) = beta``:
    ``(gamma / (sqrt(2) erfinv(1 - beta)))**2``. With the default beta (eq. 47), ``Q_i = gamma**2``. Elementwise."""
    gamma, beta = _checks.float_arrays(gamma=gamma, beta=beta)
    return (gamma / (jnp.sqrt(2.0) * erfinv(1.0 - beta))) ** 2


# --------------------------------------------------------------------------------------------
# Estimation strategies (Cortesão 2006 §5; MRAC chapter §6.3)


def sensor_based_gain(C):
    """The sensor-based (SBA) limit of a Kalman gain: measured states are replaced by the
    measurements, the others are not corrected (``K = C^+``; for ``C = [1 0 ... 0]``,
    ``K = [1, 0, ..., 0]'``), the "CKF, SBA" of the MRAC chapter §7.4. ``C`` (p, n); returns (n, p)."""
    (C,) = _checks.float_arrays(C=C)
    C = jnp.atleast_2d(C)
    _checks.matrix("C", C)
    return jnp.linalg.pinv(C)


@_checks.design_time()
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
