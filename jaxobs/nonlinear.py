"""Nonlinear Gaussian state-space models and the filter step the extended and unscented Kalman filters share.

:func:`nonlinear_model` builds a :class:`NonlinearModel`: discrete time ``x_k = f(x_{k-1}, u_{k-1}, t_{k-1}) + w_k``
or continuous-discrete (``continuous=True``), with ``y_k = h(x_k) + v_k``. A Gaussian filter replaces each map by
a :class:`Linearization` (Särkkä 2013, ch. 5-6) and takes the linear Kalman step of :mod:`jaxobs.kalman_steps`
(:func:`gaussian_step`), with missing data, an optional innovation gate and iterated updates (Bell & Cathey 1993;
García-Fernández et al. 2015). Each step outputs its log-likelihood and, with ``output_covariance``, the
linearised transition the extended and unscented RTS smoothers reuse (:func:`jaxobs.smoothing.smooth`; Särkkä
2008, 2013). The equations: docs/theory/nonlinear.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp

from jaxobs import _checks, ct
from jaxobs._linalg import symmetrize
from jaxobs.kalman_steps import bierman_update, innovation_gate, moment_update, predict_covariance, ud_factor, update

__all__ = [
    "NonlinearModel",
    "nonlinear_model",
    "Linearization",
    "GaussianState",
    "GaussianOutputs",
    "gaussian_init",
    "gaussian_step",
    "model_inputs",
    "check_discrete_model",
    "gaussian_factor",
    "sample_gaussian",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class NonlinearModel:
    """A nonlinear Gaussian state-space model (``n`` states, ``m`` inputs, ``p`` outputs); build it with
    :func:`nonlinear_model`.

    Attributes:
      f: the transition ``f(x, u, t) -> x_next`` (discrete) or ``-> dx/dt`` (``continuous``), as a
        ``jax.tree_util.Partial``: its bound arguments (model parameters, an MJX model) are leaves of this
        pytree, so ``grad`` and ``vmap`` reach them.
      h: the measurement ``h(x) -> y`` (p,), a ``Partial`` likewise.
      Q: (n, n) process noise covariance (discrete) or spectral density (continuous).
      R: (p, p) measurement noise covariance.  x0: (n,) prior mean of ``x_0``.  P0: (n, n) its covariance.
      dt: () sample period (the time step between measurements).  t0: () time of the first measurement.
      n_inputs: static ``m``; ``f`` receives an (m,) input (an empty one when ``m = 0``).
      continuous: static; ``f`` is the time derivative and the prediction integrates over each sample.
      substeps: static number of fixed integration steps per sample (continuous models).
      method: static integration rule, ``"rk4"`` or ``"euler"`` (:data:`jaxobs.ct.METHODS`).
    """

    f: Callable
    h: Callable
    Q: jax.Array
    R: jax.Array
    x0: jax.Array
    P0: jax.Array
    dt: jax.Array
    t0: jax.Array
    n_inputs: int = dataclasses.field(default=0, metadata=dict(static=True))
    continuous: bool = dataclasses.field(default=False, metadata=dict(static=True))
    substeps: int = dataclasses.field(default=1, metadata=dict(static=True))
    method: str = dataclasses.field(default="rk4", metadata=dict(static=True))


def nonlinear_model(
    f, h, Q, R, *, x0, P0=None, n_inputs: int = 0, dt=1.0, t0=0.0, continuous: bool = False,
    substeps: int = 1, method: str = "rk4",
) -> NonlinearModel:  # fmt: skip
    """Build and check a :class:`NonlinearModel`.

    Args:
      f: transition ``f(x, u, t)``: the next state (discrete) or ``dx/dt`` (``continuous``), shape (n,). A plain
        function or a ``jax.tree_util.Partial`` whose bound arguments should be differentiable or batched.
      h: measurement ``h(x)``, shape (p,) (a function or a ``Partial``).
      Q: (n, n) positive semidefinite (a covariance, or a spectral density for a continuous ``f``).
      R: (p, p) positive definite.  x0: (n,) prior mean of ``x_0``.  P0: (n, n) its covariance (default ``Q``).
      n_inputs: the number of inputs ``m`` (``u`` has shape (m,)).
      dt: sample period (> 0).  t0: time of the first measurement; step ``k`` predicts from ``t0 + (k-1) dt``.
      continuous: ``f`` is a time derivative (continuous-discrete filtering).
      substeps: fixed integration steps per sample.  method: ``"rk4"`` or ``"euler"``.

    The outputs of ``f`` and ``h`` are checked once, abstractly (``jax.eval_shape``). All arrays are cast to their
    common floating dtype.

    Example:
      >>> import jax.numpy as jnp
      >>> from jaxobs.nonlinear import nonlinear_model
      >>> pendulum = lambda x, u, t: jnp.array([x[1], -9.81 * jnp.sin(x[0])])
      >>> model = nonlinear_model(pendulum, lambda x: jnp.sin(x[:1]), 0.01 * jnp.eye(2), [[0.1]],
      ...                         x0=[0.5, 0.0], dt=0.05, continuous=True, substeps=4)
      >>> model.Q.shape, model.R.shape
      ((2, 2), (1, 1))
    """
    f, h = _checks.function("f", f), _checks.function("h", h)
    Q, R = jnp.atleast_2d(_checks.real_array("Q", Q)), jnp.atleast_2d(_checks.real_array("R", R))
    x0 = jnp.atleast_1d(_checks.real_array("x0", x0))
    P0 = Q if P0 is None else jnp.atleast_2d(_checks.real_array("P0", P0))
    dtype = _checks.float_dtype(Q=Q, R=R, x0=x0, P0=P0, dt=dt, t0=t0)
    _checks.shape("x0", x0, (None,), "the prior mean, one entry per state")
    n = x0.shape[0]
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True)
    _checks.covariance("P0", P0, definite=False, size=n)
    _checks.finite("x0", x0)
    _checks.positive_scalar("dt", dt)
    dt, t0 = jnp.asarray(dt, dtype), jnp.asarray(t0, dtype)
    _checks.shape("dt", dt, (), "a scalar sample period")
    _checks.shape("t0", t0, (), "a scalar time")
    _checks.finite("t0", t0)
    n_inputs = _checks.count("n_inputs", n_inputs, hint="the size of the input u of f(x, u, t)")
    continuous = _checks.boolean("continuous", continuous)
    substeps = _checks.count("substeps", substeps, minimum=1, hint="fixed integration steps per sample")
    if method not in ct.METHODS:
        raise ValueError(f"method must be one of {sorted(ct.METHODS)}, got {method!r}")
    p = R.shape[0]
    x, u = jnp.zeros((n,), dtype), jnp.zeros((n_inputs,), dtype)
    what = "dx/dt" if continuous else "the next state"
    _checks.returns("f(x, u, t)", f, (x, u, t0), (n,), f"{what}, one entry per entry of x0")
    _checks.returns("h(x)", h, (x,), (p,), "the measurement, one entry per row of R")
    cast = lambda M: M.astype(dtype)
    return NonlinearModel(f, h, cast(Q), cast(R), cast(x0), cast(P0), dt, t0, n_inputs, continuous, substeps, method)


class Linearization(NamedTuple):
    """``g(x) ~ mean + G (x - m) + e``, ``e ~ N(0, Omega)``, around ``N(m, P)`` (shapes for ``g: (n,) -> (k,)``).

    ``cross`` and ``cov``, when given, are the moments the linearisation implies, computed directly: a
    sigma-point rule has them without ``G`` (``cross = P G'``, ``cov = G P G' + Omega``); the prediction and the
    standard-form update then use them and need no solve with ``P``."""

    mean: jax.Array  # (k,) g_bar
    G: jax.Array  # (k, n) Jacobian (Taylor) or regression matrix (sigma points)
    Omega: jax.Array | None  # (k, k) covariance of the linearisation error; None when zero (Taylor)
    cross: jax.Array | None = None  # (n, k) covariance of x and g(x)
    cov: jax.Array | None = None  # (k, k) covariance of g(x)


class Linearize(Protocol):
    def __call__(self, g: Callable, m: jax.Array, P: jax.Array) -> Linearization:
        """The linearisation of ``g`` around ``N(m, P)``."""


class GaussianState(NamedTuple):
    """State of a Gaussian filter (EKF, UKF) between steps.

    Attributes:
      x: (n,) a-posteriori mean x_hat_{k-1|k-1} (the prior mean before the first step)
      P: (n, n) its covariance
      t: () its time
      started: () bool: a measurement has been processed (the next step predicts)
      missing: () int32, measurement components skipped so far (missing or gated)
      gated: () int32, of those, finite components rejected by the innovation gate
    """

    x: jax.Array
    P: jax.Array
    t: jax.Array
    started: jax.Array
    missing: jax.Array
    gated: jax.Array


class GaussianOutputs(NamedTuple):
    """Outputs of one step of a Gaussian filter (EKF, UKF).

    Attributes:
      x: (n,) a-posteriori mean x_hat_{k|k}
      P: (n, n) its covariance
      x_prior: (n,) a-priori mean x_hat_{k|k-1}
      innovation: (p,) y_k - h_bar around the prior (0 for missing components)
      gain: (n, p) gain of the (last) update (zero columns for missing components)
      log_likelihood: () log N(innovation; 0, S), ``S = H P_prior H' + R + Omega_h`` of the first linearisation
        around the prior: the filter's predictive density of the observed components of ``y_k`` (0 when all
        are missing or gated)
      P_prior: (n, n) a-priori covariance P_{k|k-1} (with output_covariance, else None)
      transition: (n, n) the linearised transition ``F_k`` of the prediction into sample ``k``, whose
        cross-covariance ``Cov(x_{k-1}, x_k) = P_{k-1} F_k'`` the smoother needs: the Jacobian of ``f``
        (EKF), the statistical linear regression matrix (UKF), the flow's sensitivity ``dPhi/dt = F Phi``
        (continuous-discrete); the identity at the first sample (with output_covariance, else None)
      S: (p, p) the innovation covariance ``S`` of ``log_likelihood`` (1 on the diagonal of a missing or gated
        component), what the normalised innovation squared needs (:func:`jaxobs.consistency.nis`)
    """

    x: jax.Array
    P: jax.Array
    x_prior: jax.Array
    innovation: jax.Array
    gain: jax.Array
    log_likelihood: jax.Array
    P_prior: jax.Array | None = None
    transition: jax.Array | None = None
    S: jax.Array | None = None


def gaussian_init(model: NonlinearModel) -> GaussianState:
    """The state before the first measurement: the prior ``(x0, P0)`` at ``t0``."""
    zero = jnp.zeros((), jnp.int32)
    return GaussianState(model.x0, model.P0, model.t0, jnp.zeros((), bool), zero, zero)


def model_inputs(model: NonlinearModel, inputs):
    """``(y, u)`` of ``EstimatorInputs(y, u_prev)`` checked against the model's sizes (at trace time) and cast to
    its dtype; ``u`` is an empty (0,) vector for a model without inputs."""
    p, m, dtype = model.R.shape[-1], model.n_inputs, model.x0.dtype
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of R", check_finite=False)
    if inputs.u_prev is None:
        if m:
            raise ValueError(f"inputs.u_prev is required: the model has n_inputs={m}, got None")
        return y, jnp.zeros((0,), dtype)
    u = _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype, what="n_inputs entries", check_finite=False)
    return y, u


def _predict(linearize: Linearize, model: NonlinearModel, m, P, u, t, transition: bool):
    """``(m_prior, P_prior, F)``: the a-priori moments of the next sample and the linearised transition ``F``
    (:class:`GaussianOutputs`; continuous-discrete only with ``transition``, else None)."""
    if not model.continuous:
        lin = linearize(lambda x: model.f(x, u, t), m, P)
        if lin.cov is not None:
            return lin.mean, lin.cov + model.Q, lin.G
        Q = model.Q if lin.Omega is None else model.Q + lin.Omega
        return lin.mean, predict_covariance(P, lin.G, Q), lin.G

    def moments(state, u, t):  # dm/dt, dP/dt and, with transition, the sensitivity dPhi/dt = F Phi
        m, P, *Phi = state
        lin = linearize(lambda x: model.f(x, u, t), m, P)
        FP = lin.G @ P
        return (lin.mean, FP + FP.T + model.Q, *(lin.G @ S for S in Phi))

    start = (m, P, jnp.eye(m.shape[-1], dtype=m.dtype)) if transition else (m, P)
    m, P, *Phi = ct.integrate(moments, start, u, t, model.dt, substeps=model.substeps, method=model.method)
    return m, symmetrize(P), Phi[0] if transition else None


def gaussian_step(
    linearize: Linearize, iterations: int, model: NonlinearModel, state: GaussianState, inputs, *,
    bierman: bool = False, gate=None, joseph: bool = True, output_covariance: bool = False,
):  # fmt: skip
    """One step of the Gaussian filter with ``linearize`` (the equations of this module).

    Args:
      linearize: ``(g, m, P) -> Linearization``.  iterations: static number of updates (1: no iteration).
      bierman: static; the measurement update by Bierman's U-D algorithm
        (:func:`jaxobs.kalman_steps.bierman_update`) instead of the Joseph form.
      gate: ``None`` or the innovation gate (standard deviations, > 0; the first linearisation's innovation).
      joseph: static; ``False``: the standard-form covariance update (:func:`jaxobs.kalman_steps.update`).
      output_covariance: static; also output ``P_prior`` and ``transition`` (what the smoother needs).
      model: the :class:`NonlinearModel`.  state: the :class:`GaussianState` after sample ``k - 1``.
      inputs: ``EstimatorInputs(y, u_prev)`` of sample ``k``: (p,) and (m,) (``None`` without inputs).

    Returns:
      ``(GaussianState, GaussianOutputs)`` of sample ``k``; its ``log_likelihood`` is that of the first
      linearisation of ``h`` (around the prior), the filter's predictive density of ``y_k``.
    """
    y, u = model_inputs(model, inputs)
    m_pred, P_pred, F = _predict(linearize, model, state.x, state.P, u, state.t, output_covariance)
    first = ~state.started  # the prior is that of x_0: no prediction before the first update
    m_prior, P_prior = jnp.where(first, state.x, m_pred), jnp.where(first, state.P, P_pred)
    t = jnp.where(first, state.t, state.t + model.dt)
    x, P = m_prior, P_prior
    first_update, gated = None, jnp.zeros((), jnp.int32)
    for i in range(iterations):
        lin = linearize(model.h, x, P)
        h_bar = lin.mean if i == 0 else lin.mean + lin.G @ (m_prior - x)
        R = model.R if lin.Omega is None else model.R + lin.Omega
        if i == 0 and gate is not None:
            accepted = innovation_gate(y - h_bar, lin.G, P_prior, R, gate)
            gated = jnp.sum(jnp.isfinite(y) & ~accepted).astype(jnp.int32)
            y = jnp.where(accepted, y, jnp.nan)
        if bierman:
            result = bierman_update(m_prior, P_prior, lin.G, R, y, predicted=h_bar)
        elif lin.cov is not None and not joseph and iterations == 1:
            result = moment_update(m_prior, P_prior, lin.cross, lin.cov, model.R, y, h_bar)
        else:
            result = update(m_prior, P_prior, lin.G, R, y, joseph=joseph, predicted=h_bar)
        x, P = result.x, result.P
        if first_update is None:  # the innovation and its density around the prior, y_k - h_bar(m_prior)
            first_update = result
    missing = state.missing + result.n_missing.astype(jnp.int32)
    new_state = GaussianState(x, P, t, jnp.ones((), bool), missing, state.gated + gated)
    covariances = (None, None)
    if output_covariance:
        covariances = (P_prior, jnp.where(first, jnp.eye(x.shape[-1], dtype=x.dtype), F))
    outputs = GaussianOutputs(x, P, m_prior, first_update.innovation, result.K, first_update.log_likelihood,
                              *covariances, first_update.S)  # fmt: skip
    return new_state, outputs


def check_discrete_model(model, what: str) -> None:
    """``ValueError`` unless ``model`` is a discrete-time :class:`NonlinearModel` (``f`` the next state), as the
    Monte-Carlo filters, which draw the transition, need; ``what`` names the filter in the message."""
    if not isinstance(model, NonlinearModel):
        raise ValueError(f"model must be a NonlinearModel (see jaxobs.nonlinear_model), got {type(model).__name__}")
    if model.continuous:
        raise ValueError(f"model is continuous-time: {what} draws a discrete-time transition; build the model with "
                         "continuous=False (f the next state)")  # fmt: skip


def gaussian_factor(cov):
    """A factor ``F`` (n, n) with ``F F' = cov`` of a symmetric positive semidefinite ``cov``, from
    :func:`jaxobs.kalman_steps.ud_factor` (``F = U diag(d)^(1/2)``), so a singular ``cov`` is no special case;
    differentiable where ``cov`` is definite. The Monte-Carlo filters (particle filters, ensemble Kalman filters)
    draw their noises with it (:func:`sample_gaussian`)."""
    U, d = ud_factor(cov)
    return U * jnp.sqrt(d)


def sample_gaussian(key, mean, factor, num: int):
    """``num`` draws (num, n) of ``N(mean, F F')`` as ``mean + F e``, ``e`` standard normal, for a factor ``F``
    (n, r) such as :func:`gaussian_factor`'s: reparameterised, so differentiable in ``mean`` and ``F``.
    Shapes: ``mean`` (n,); ``num`` static."""
    return mean + jax.random.normal(key, (num, factor.shape[-1]), mean.dtype) @ factor.T
