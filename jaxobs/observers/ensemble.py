"""Ensemble Kalman filters in the estimator protocol: the stochastic EnKF, the ensemble transform Kalman filter
and the ensemble Kalman smoother.

The model is a discrete-time :class:`~jaxobs.nonlinear.NonlinearModel`; the state holds the ensemble (one row per
member) and a PRNG key. Each step forecasts every member through ``f`` with a draw of the process noise and
updates it with the Kalman gain of the ensemble's moments (:func:`jaxobs.kalman_steps.moment_update`): with
perturbed observations (:func:`stochastic_update`; Evensen 1994, Burgers, van Leeuwen & Evensen 1998) or by the
symmetric square-root transform of the anomalies (:func:`transform_update`; Bishop, Etherton & Majumdar 2001,
Hunt, Kostelich & Szunyogh 2007). Either analysis is the forecast ensemble times an (N, N) matrix, which the
ensemble Kalman smoother applies to the earlier ensembles (:func:`ensemble_smoother`; Evensen & van Leeuwen
2000). :func:`make_enkf`, :data:`ensemble_kalman_filter`. The equations: docs/guides/particle-and-ensemble.md.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs._linalg import cholesky, solve_lower, solve_spd, symmetrize
from jaxobs.kalman_steps import Update, moment_update, observed, observed_model
from jaxobs.nonlinear import NonlinearModel, check_discrete_model, gaussian_factor, model_inputs, sample_gaussian
from jaxobs.observers.base import Estimator, EstimatorInputs, run

__all__ = [
    "EnsembleParams",
    "EnsembleState",
    "EnsembleOutputs",
    "make_enkf",
    "ensemble_kalman_filter",
    "METHODS",
    "Analysis",
    "stochastic_update",
    "transform_update",
    "perturbations",
    "SmoothedEnsemble",
    "ensemble_smoother",
]

METHODS = ("stochastic", "transform")
"""The analysis steps of :func:`make_enkf`: perturbed observations or the ensemble transform."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class EnsembleParams:
    """Parameters of :data:`ensemble_kalman_filter` (build them with :func:`make_enkf`).

    Attributes:
      model: the discrete-time :class:`~jaxobs.nonlinear.NonlinearModel`.
      key: the PRNG key the initial ensemble and every step's perturbations descend from.
      inflation: () multiplicative inflation of the forecast anomalies (1: none; Anderson & Anderson 1999).
      Q_sqrt: (n, n) and R_sqrt: (p, p) factors of ``model.Q`` and ``model.R`` (``F F' = M``; :func:`make_enkf`
        computes them once with :func:`jaxobs.nonlinear.gaussian_factor`), with which the draws are made.
      num_members: static ensemble size ``N`` (>= 2).
      method: static, ``"stochastic"`` (:func:`stochastic_update`) or ``"transform"`` (:func:`transform_update`).
      output_ensemble: static; every step also outputs its ensemble and the transform of its analysis (what
        :func:`ensemble_smoother` needs).
    """

    model: NonlinearModel
    key: jax.Array
    inflation: jax.Array
    Q_sqrt: jax.Array
    R_sqrt: jax.Array
    num_members: int = dataclasses.field(metadata=dict(static=True))
    method: str = dataclasses.field(default="stochastic", metadata=dict(static=True))
    output_ensemble: bool = dataclasses.field(default=False, metadata=dict(static=True))


class EnsembleState(NamedTuple):
    """State of :data:`ensemble_kalman_filter` between steps (``N`` members of ``n`` states).

    Attributes:
      ensemble: (N, n) the analysis ensemble after sample ``k - 1`` (draws from the prior before the first step).
      key: the PRNG key of the next step.
      t: () the time of the ensemble.
      started: () bool: a measurement has been processed (the next step forecasts).
      missing: () int32, measurement components skipped so far.
    """

    ensemble: jax.Array
    key: jax.Array
    t: jax.Array
    started: jax.Array
    missing: jax.Array


class EnsembleOutputs(NamedTuple):
    """Outputs of one step of :data:`ensemble_kalman_filter`.

    Attributes:
      x: (n,) mean of the analysis ensemble.  P: (n, n) its sample covariance (divided by ``N - 1``).
      x_prior: (n,) mean of the forecast ensemble.  P_prior: (n, n) its sample covariance.
      innovation: (p,) ``y_k`` minus the mean of ``h`` over the forecast (0 for missing components).
      gain: (n, p) the ensemble's Kalman gain (zero columns for missing components).
      S: (p, p) the innovation covariance: the sample covariance of ``h`` plus ``R`` (1 on a missing diagonal).
      log_likelihood: () ``log N(innovation; 0, S)``, the ensemble's Gaussian approximation of
        ``log p(y_k | y_0..y_{k-1})``.
      ensemble: (N, n) the analysis ensemble (with ``output_ensemble``, else None).
      transform: (N, N) the matrix ``T`` of the analysis, ``ensemble = T forecast`` (with ``output_ensemble``).
    """

    x: jax.Array
    P: jax.Array
    x_prior: jax.Array
    P_prior: jax.Array
    innovation: jax.Array
    gain: jax.Array
    S: jax.Array
    log_likelihood: jax.Array
    ensemble: jax.Array | None = None
    transform: jax.Array | None = None


def make_enkf(model: NonlinearModel, num_members: int, *, key, method: str = "stochastic", inflation=1.0,
              output_ensemble: bool = False) -> EnsembleParams:  # fmt: skip
    """The ensemble Kalman filter of ``model``.

    Args:
      model: a discrete-time :class:`~jaxobs.nonlinear.NonlinearModel` (:func:`jaxobs.nonlinear.nonlinear_model`).
      num_members: the ensemble size ``N`` (an integer >= 2).
      key: a PRNG key (``jax.random.key(seed)`` or ``jax.random.PRNGKey(seed)``).
      method: ``"stochastic"`` (perturbed observations, default) or ``"transform"`` (the ensemble transform
        Kalman filter, no perturbations).
      inflation: multiplicative inflation of the forecast anomalies (>= 1; 1: none).
      output_ensemble: output the ensemble and the analysis transform at every step.

    Example:
      >>> import jax, jax.numpy as jnp
      >>> import jaxobs as jo
      >>> model = jo.nonlinear_model(lambda x, u, t: 0.9 * x, lambda x: x, [[0.1]], [[0.5]], x0=[0.0], P0=[[1.0]])
      >>> params = jo.make_enkf(model, 50, key=jax.random.key(0), method="transform")
      >>> _, out = jo.run(jo.ensemble_kalman_filter, params, jo.EstimatorInputs(y=jnp.ones((20, 1))))
      >>> out.x.shape, out.P.shape
      ((20, 1), (20, 1, 1))
    """
    check_discrete_model(model, "the ensemble filter")
    num_members = _checks.count("num_members", num_members, minimum=2, hint="the ensemble size")
    if method not in METHODS:
        raise ValueError(f"method must be one of {list(METHODS)}, got {method!r}")
    inflation = jnp.asarray(inflation, model.x0.dtype)
    _checks.shape("inflation", inflation, (), "a scalar factor on the forecast anomalies")
    if _checks.is_concrete(inflation) and not float(inflation) >= 1.0:
        raise ValueError(f"inflation must be >= 1 (1: no inflation), got {float(inflation)}")
    Q_sqrt, R_sqrt = gaussian_factor(model.Q), gaussian_factor(model.R)
    return EnsembleParams(model, _checks.key("key", key), inflation, Q_sqrt, R_sqrt, num_members, method,
                          _checks.boolean("output_ensemble", output_ensemble))  # fmt: skip


# --------------------------------------------------------------------------------------------
# The analysis steps (atoms): forecast ensemble -> analysis ensemble


class Analysis(NamedTuple):
    """Result of :func:`stochastic_update` and :func:`transform_update` (``N`` members, ``n`` states, ``p``
    outputs).

    Attributes:
      ensemble: (N, n) the analysis ensemble.
      update: the :class:`~jaxobs.kalman_steps.Update` of the forecast's mean and sample covariance (its gain,
        innovation, ``S``, log-likelihood; its ``P`` is ``P_prior - K S K'``).
      P_prior: (n, n) the forecast's sample covariance.
      transform: (N, N) ``T`` with ``ensemble = T forecast`` (with ``transform=True``, else None).
    """

    ensemble: jax.Array
    update: Update
    P_prior: jax.Array
    transform: jax.Array | None


def _moments(forecast, predicted, R, y) -> tuple:
    """``(anomalies of x, masked anomalies of h, P_prior, Update)`` of the forecast and its predicted
    measurements (N, p): the Kalman update of the sample moments (divided by ``N - 1``)."""
    scale = forecast.shape[0] - 1
    mean, mean_h = jnp.mean(forecast, axis=0), jnp.mean(predicted, axis=0)
    A, B = forecast - mean, predicted - mean_h
    P_prior = symmetrize(A.T @ A / scale)
    update = moment_update(mean, P_prior, A.T @ B / scale, B.T @ B / scale, R, y, mean_h)
    mask = observed(y, forecast.dtype)[0]
    return A, B * mask, P_prior, update


def _check_params(params: EnsembleParams) -> NonlinearModel:
    """``params`` checked at trace time to be one filter (no batch axis: ``vmap``); returns its model."""
    _checks.key("params.key", params.key)
    _checks.fields("params", params, "inflation (), Q_sqrt (n, n), R_sqrt (p, p)")
    return NonlinearModel.check(params.model, "params.model")


def _check_ensemble(forecast, predicted, R, y):
    """The analysis' arrays in one floating dtype, their shapes checked at trace time: forecast (members,
    states), predicted (members, outputs), h of each forecast member."""
    forecast, predicted, R, y = _checks.arrays("forecast (N, n), predicted (N, p), R (p, p), y (p,)",
                                               forecast, predicted, R, y)  # fmt: skip
    n_members = forecast.shape[0]
    if n_members < 2:
        raise ValueError(f"forecast must have at least 2 members (rows), got {n_members}")
    return forecast, predicted, R, y


def stochastic_update(forecast, predicted, R, y, perturbations, *, transform: bool = False) -> Analysis:
    """The EnKF analysis with perturbed observations (Evensen 1994; Burgers, van Leeuwen & Evensen 1998): every
    member moves by the ensemble's Kalman gain times its own innovation, ``x_i + K (y + e_i - h(x_i))``, ``K =
    C_xh S^{-1}``, ``S = C_hh + R`` from the sample (co)variances (``N - 1``) of the forecast and its predicted
    measurements; as filterpy's ``EnsembleKalmanFilter.update``. Missing components of ``y`` are skipped.

    Args:
      forecast: (N, n) the forecast ensemble.  predicted: (N, p) ``h`` of each member.
      R: (p, p) measurement noise covariance.  y: (p,) the measurement.
      perturbations: (N, p) the draws ``e_i ~ N(0, R)``.
      transform: also return ``T = I + D S^{-1} B' / (N - 1)`` (``D`` the perturbed innovations, ``B`` the
        anomalies of ``predicted``), with ``ensemble = T forecast``.

    Returns:
      :class:`Analysis`.
    """
    forecast, predicted, R, y = _check_ensemble(forecast, predicted, R, y)
    (perturbations,) = _checks.float_arrays(perturbations=perturbations)
    _checks.shape("perturbations", perturbations, predicted.shape, "one draw of N(0, R) per member")
    A, B, P_prior, update = _moments(forecast, predicted, R, y)
    mask, y_observed = observed(y, forecast.dtype)
    D = (y_observed + perturbations - predicted) * mask
    T = None
    if transform:
        T = jnp.eye(forecast.shape[0], dtype=A.dtype) + D @ solve_spd(update.S, B.T) / (forecast.shape[0] - 1)
    return Analysis(forecast + D @ update.K.T, update, P_prior, T)


@jax.custom_jvp
def _square_root_correction(E):
    """``F(E) = -(sqrt(I + E) (I + sqrt(I + E)))^{-1}`` of a symmetric positive semidefinite ``E`` (p, p), so that
    ``(I + G G')^{-1/2} = I + G F(G' G) G'`` (eigenvalues ``f(s) = -1 / (r (1 + r))``, ``r = sqrt(1 + s)``)."""
    s, V = jnp.linalg.eigh(E)
    return (V * _correction(s)) @ V.T


def _correction(s):
    r = jnp.sqrt(1 + jnp.maximum(s, 0.0))
    return -1.0 / (r * (1 + r))


@_square_root_correction.defjvp
def _square_root_correction_jvp(primals, tangents):
    """The derivative of a matrix function by divided differences (Daleckii & Krein), finite also where ``E`` has
    repeated eigenvalues (missing components, where the eigenvalue derivative of ``eigh`` divides by zero)."""
    (E,), (dE,) = primals, tangents
    s, V = jnp.linalg.eigh(E)
    f = _correction(s)
    r = jnp.sqrt(1 + jnp.maximum(s, 0.0))
    derivative = (1 + 2 * r) / (2 * r**3 * (1 + r) ** 2)  # f'(s)
    gap = s[:, None] - s[None, :]
    tolerance = jnp.sqrt(jnp.finfo(s.dtype).eps)  # below it, f' at the mean beats the rounding of f_i - f_j
    close = jnp.abs(gap) <= tolerance * (1 + jnp.abs(s[:, None]) + jnp.abs(s[None, :]))
    mean_derivative = 0.5 * (derivative[:, None] + derivative[None, :])
    divided = jnp.where(close, mean_derivative, (f[:, None] - f[None, :]) / jnp.where(close, 1.0, gap))
    return (V * f) @ V.T, V @ ((V.T @ symmetrize(dE) @ V) * divided) @ V.T


def transform_update(forecast, predicted, R, y, *, transform: bool = False) -> Analysis:
    """The ensemble transform Kalman filter's analysis (Bishop, Etherton & Majumdar 2001; Hunt, Kostelich &
    Szunyogh 2007): the mean by the ensemble's Kalman gain, the anomalies by the symmetric square root
    ``A_a = (I + G G')^{-1/2} A``, ``G = B L^{-T} / sqrt(N - 1)`` (``B`` the anomalies of ``predicted``, ``R = L
    L'``). No perturbations: the analysis mean and sample covariance are the Kalman update of the forecast's
    mean and sample covariance, exactly for a linear ``h``. Computed in output space (``p x p`` eigenproblem).

    Args:
      forecast: (N, n).  predicted: (N, p).  R: (p, p).  y: (p,): as :func:`stochastic_update`.
      transform: also return ``T = (I + G G')^{-1/2} + 1 w'`` (``w`` the mean's weights), ``ensemble = T
        forecast``.

    Returns:
      :class:`Analysis`.
    """
    forecast, predicted, R, y = _check_ensemble(forecast, predicted, R, y)
    A, B, P_prior, update = _moments(forecast, predicted, R, y)
    mask = observed(y, forecast.dtype)[0]
    R_observed = observed_model(jnp.zeros((y.shape[-1], 0), R.dtype), R, mask)[1]
    G = solve_lower(cholesky(R_observed), B.T).T / jnp.sqrt(forecast.shape[0] - 1.0)  # (N, p)
    F = _square_root_correction(G.T @ G)
    ensemble = update.x + A + G @ (F @ (G.T @ A))
    T = None
    if transform:
        weights = B @ solve_spd(update.S, update.innovation[:, None])[:, 0] / (forecast.shape[0] - 1)  # mean: + A' w
        T = jnp.eye(forecast.shape[0], dtype=A.dtype) + G @ F @ G.T + weights[None, :]
    return Analysis(ensemble, update, P_prior, T)


def perturbations(params: EnsembleParams, key):
    """The draws of one step of :data:`ensemble_kalman_filter`: ``(next key, W, E)`` with ``W`` (N, n) the
    process noises ``N(0, Q)`` and ``E`` (N, p) the observation perturbations ``N(0, R)``
    (:func:`jaxobs.nonlinear.sample_gaussian` with ``params.Q_sqrt``, ``params.R_sqrt``), from ``key, kw, ke =
    jax.random.split(key, 3)``. Public so that a run can be reproduced member by member (e.g. by another
    implementation fed the same draws)."""
    _check_params(params)
    key, process, observation = jax.random.split(key, 3)
    zero = jnp.zeros((), params.model.x0.dtype)
    W = sample_gaussian(process, zero, params.Q_sqrt, params.num_members)
    E = sample_gaussian(observation, zero, params.R_sqrt, params.num_members)
    return key, W, E


# --------------------------------------------------------------------------------------------
# The filter


def _init(params: EnsembleParams) -> EnsembleState:
    model = _check_params(params)
    key, draw = jax.random.split(params.key)
    ensemble = sample_gaussian(draw, model.x0, gaussian_factor(model.P0), params.num_members)
    return EnsembleState(ensemble, key, model.t0, jnp.zeros((), bool), jnp.zeros((), jnp.int32))


def _sample_covariance(ensemble):
    deviations = ensemble - jnp.mean(ensemble, axis=0)
    return symmetrize(deviations.T @ deviations / (ensemble.shape[0] - 1))


def _step(params: EnsembleParams, state: EnsembleState, inputs: EstimatorInputs):
    model = _check_params(params)
    y, u = model_inputs(model, inputs)
    key, W, E = perturbations(params, state.key)
    first = ~state.started  # the ensemble holds draws of x_0: no forecast before the first update
    propagated = jax.vmap(model.f, (0, None, None))(state.ensemble, u, state.t) + W
    centre = jnp.mean(propagated, axis=0)
    forecast = jnp.where(first, state.ensemble, centre + params.inflation * (propagated - centre))
    predicted = jax.vmap(model.h)(forecast)
    if params.method == "stochastic":
        analysis = stochastic_update(forecast, predicted, model.R, y, E, transform=params.output_ensemble)
    else:
        analysis = transform_update(forecast, predicted, model.R, y, transform=params.output_ensemble)
    result = analysis.update
    t = jnp.where(first, state.t, state.t + model.dt)
    missing = state.missing + result.n_missing.astype(jnp.int32)
    new_state = EnsembleState(analysis.ensemble, key, t, jnp.ones((), bool), missing)
    extra = (analysis.ensemble, analysis.transform) if params.output_ensemble else ()
    outputs = EnsembleOutputs(jnp.mean(analysis.ensemble, axis=0), _sample_covariance(analysis.ensemble),
                              jnp.mean(forecast, axis=0), analysis.P_prior, result.innovation, result.K, result.S,
                              result.log_likelihood, *extra)  # fmt: skip
    return new_state, outputs


ensemble_kalman_filter = Estimator(_init, _step)
"""The ensemble Kalman filter as an :class:`~jaxobs.observers.base.Estimator` over :class:`EnsembleParams`.

Each step (after the first, which only updates the prior draws): draw the step's noises
(:func:`perturbations`), forecast ``x_i = f(x_i, u_{k-1}, t) + w_i``, inflate the anomalies, and update with
:func:`stochastic_update` or :func:`transform_update`; missing components of ``y_k`` are skipped. Inputs:
``EstimatorInputs(y, u_prev)``. State: :class:`EnsembleState`. Outputs: :class:`EnsembleOutputs`."""


class SmoothedEnsemble(NamedTuple):
    """Result of :func:`ensemble_smoother` (leading axis ``T``).

    Attributes:
      ensemble: (T, N, n) the smoothed ensembles.  x: (T, n) their means.  P: (T, n, n) their sample
        covariances.
    """

    ensemble: jax.Array
    x: jax.Array
    P: jax.Array


def ensemble_smoother(params: EnsembleParams, inputs: EstimatorInputs):
    """Filter a record with :data:`ensemble_kalman_filter` and smooth it: the ensemble Kalman smoother of
    Evensen & van Leeuwen (2000), which applies every later analysis to the earlier ensembles, ``X_{k|T} =
    T_{T-1} ... T_{k+1} X_{k|k}`` with each ``T_j`` the transform of the analysis at sample ``j`` (members keep
    their identity through the forecast). ``O(T N^2 (N + n))`` work.

    Args:
      params: :class:`EnsembleParams` (``output_ensemble`` is switched on here).
      inputs: ``EstimatorInputs`` over ``T`` samples.

    Returns:
      ``(outputs, smoothed)``: the filter's :class:`EnsembleOutputs` and :class:`SmoothedEnsemble`.

    Example:
      >>> import jax, jax.numpy as jnp
      >>> import jaxobs as jo
      >>> model = jo.nonlinear_model(lambda x, u, t: 0.9 * x, lambda x: x, [[0.1]], [[0.5]], x0=[0.0], P0=[[1.0]])
      >>> params = jo.make_enkf(model, 50, key=jax.random.key(0))
      >>> filtered, smoothed = jo.ensemble_smoother(params, jo.EstimatorInputs(y=jnp.ones((20, 1))))
      >>> smoothed.ensemble.shape, bool(jnp.allclose(smoothed.x[-1], filtered.x[-1]))
      ((20, 50, 1), True)
    """
    outputs = run(ensemble_kalman_filter, dataclasses.replace(params, output_ensemble=True), inputs)[1]

    def back(later, step):
        ensemble, transform = step
        later = later @ transform
        return later, later @ ensemble

    identity = jnp.eye(params.num_members, dtype=outputs.ensemble.dtype)
    _, earlier = jax.lax.scan(back, identity, (outputs.ensemble[:-1], outputs.transform[1:]), reverse=True)
    ensembles = jnp.concatenate([earlier, outputs.ensemble[-1:]])
    return outputs, SmoothedEnsemble(ensembles, jnp.mean(ensembles, axis=1), jax.vmap(_sample_covariance)(ensembles))
