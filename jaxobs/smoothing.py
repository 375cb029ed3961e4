"""Estimation over a whole record: the log-likelihood of a record, Rauch-Tung-Striebel smoothing for every
Kalman-type estimator, and the parallel-in-time filter and smoother (Särkkä & García-Fernández 2021).

:func:`log_likelihood` sums the filter's per-step log-likelihoods (exact with missing data); :func:`smooth` and
:func:`rts_smoother` run the smoother (Rauch, Tung & Striebel 1965) from the outputs of any filter that outputs
its covariances; :func:`parallel_filter` and the parallel smoother use ``jax.lax.associative_scan``
(Lemmas 7-10). The equations and measurements: docs/estimation.md (``benchmarks/parallel_in_time.py``).
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs._linalg import solve_spd, symmetrize
from jaxobs.kalman_steps import observed, observed_model, predict_covariance, update
from jaxobs.observers.base import Estimator, EstimatorInputs, run
from jaxobs.observers.kalman import KalmanOutputs, KalmanParams, KalmanState, kalman_filter, step_model

__all__ = ["Smoothed", "rts_smoother", "smooth", "log_likelihood", "parallel_filter"]


class Smoothed(NamedTuple):
    """The smoothed record (leading axis ``T``): ``x`` (T, n) the means ``x_{k|T-1}``, ``P`` (T, n, n) the
    covariances ``P_{k|T-1}``, ``gain`` (T, n, n) the smoother gains ``E_k`` (zero at the last sample)."""

    x: jax.Array  # (T, n) smoothed means x_{k|T-1}
    P: jax.Array  # (T, n, n) smoothed covariances P_{k|T-1}
    gain: jax.Array  # (T, n, n) smoother gains E_k (zero at the last sample)


# --------------------------------------------------------------------------------------------
# Smoother


class _SmootherElement(NamedTuple):
    """``x_{k|T-1} = E x_{k+1|T-1} + g`` with ``P_{k|T-1} = E P_{k+1|T-1} E' + L``."""

    E: jax.Array
    g: jax.Array
    L: jax.Array


def _smoother_gain(Phi, P, P_prior_next):
    """The gain ``E_k = P_k Phi' P_prior_{k+1}^{-1}`` of sample ``k`` and its transpose, both row-major: ``E A E'``
    is computed as ``(E A) E_t`` (a transposed operand sends XLA's CPU backend to a slower kernel for a batch of
    small products, ``benchmarks/estimation.py``, ``smooth``).

    A state without a-priori variance (a zero diagonal entry of ``P_prior_next``, e.g. an active state switched
    off) gets a unit placeholder in the solve: ``Phi P`` has a zero row there, so its gain column is zero."""
    unit = jnp.diag((jnp.diagonal(P_prior_next) == 0).astype(P.dtype))
    E_t = solve_spd(P_prior_next + unit, Phi @ P)  # P_prior symmetric: E' = P_prior^-1 Phi P
    return jax.lax.optimization_barrier(E_t.T), E_t


def _smoother_element(Phi, x, P, x_prior_next, P_prior_next) -> _SmootherElement:
    """The element of sample ``k`` from its a-posteriori ``(x, P)`` and the a-priori moments of ``k + 1``."""
    E, E_t = _smoother_gain(Phi, P, P_prior_next)
    return _SmootherElement(E, x - E @ x_prior_next, symmetrize(P - E @ P_prior_next @ E_t))


def _smoother_combine(earlier: _SmootherElement, later: _SmootherElement) -> _SmootherElement:
    """The element of ``earlier`` applied after ``later`` (Särkkä & García-Fernández 2021, Lemma 10)."""
    E = earlier.E @ later.E
    g = earlier.E @ later.g + earlier.g
    return _SmootherElement(E, g, symmetrize(earlier.E @ later.L @ earlier.E.T + earlier.L))


def rts_smoother(Phi, filtered, *, parallel: bool = False) -> Smoothed:
    """Rauch-Tung-Striebel smoother of a filtered record.

    With a time-varying ``Phi`` it is the Gaussian RTS smoother of a nonlinear filter (Särkkä 2013, ch. 9-10;
    Särkkä 2008): ``Phi[k]`` is the linearisation of the transition into sample ``k`` (the EKF's
    Jacobian at ``x_{k-1|k-1}``, the UKF's sigma-point regression matrix), so ``P_{k-1} Phi[k]'`` is the
    cross-covariance of ``x_{k-1}`` and ``x_k`` and ``E_{k-1} = P_{k-1} Phi[k]' P_prior_k^{-1}`` the gain.

    Args:
      Phi: (n, n) the filter's state transition, or (T, n, n) with ``Phi[k]`` the transition from sample
        ``k - 1`` to ``k`` (``Phi[0]`` unused): the ``transition`` outputs of a nonlinear filter.
      filtered: the filter's outputs over ``T`` samples with the fields ``x`` (T, n), ``P`` (T, n, n),
        ``x_prior`` (T, n) and ``P_prior`` (T, n, n): those of a Kalman-type estimator run with
        ``output_covariance=True`` (:func:`smooth` does both).
      parallel: combine the samples with ``jax.lax.associative_scan`` (depth ``O(log T)``) instead of
        ``jax.lax.scan``; same result to rounding.

    Returns:
      :class:`Smoothed`. Differentiable; works under ``jit`` and ``vmap``.
    """
    x, P, x_prior, P_prior = (getattr(filtered, name, None) for name in ("x", "P", "x_prior", "P_prior"))
    if P is None or P_prior is None:
        raise ValueError("filtered has no covariances P, P_prior: run the filter with output_covariance=True "
                         "(dataclasses.replace(params, output_covariance=True)) or use smooth()")  # fmt: skip
    _checks.shape("filtered.x", x, (None, None), "(T, n) a-posteriori means")
    T, n = x.shape
    if T == 0:
        raise ValueError("filtered has no samples: give at least one (its x has shape (T, n))")
    _checks.shape("filtered.P", P, (T, n, n), "(T, n, n) a-posteriori covariances")
    _checks.shape("filtered.x_prior", x_prior, (T, n), "(T, n) a-priori means")
    _checks.shape("filtered.P_prior", P_prior, (T, n, n), "(T, n, n) a-priori covariances")
    if np.ndim(Phi) == 3:
        _checks.shape("Phi", Phi, (T, n, n), "(T, n, n) transitions, Phi[k] from sample k - 1 to k")
    _checks.matrix("Phi", Phi, shape=(n, n), square=True, batch=np.ndim(Phi) == 3)
    return _rts(jnp.asarray(Phi, x.dtype), x, P, x_prior, P_prior, parallel=bool(parallel))


@partial(jax.jit, static_argnames=("parallel",))
def _rts(Phi, x, P, x_prior, P_prior, *, parallel: bool) -> Smoothed:
    n = x.shape[-1]
    varying = Phi.ndim == 3
    if parallel:
        elements = jax.vmap(_smoother_element, (0 if varying else None, 0, 0, 0, 0))(
            Phi[1:] if varying else Phi, x[:-1], P[:-1], x_prior[1:], P_prior[1:]
        )
        last = _SmootherElement(jnp.zeros((1, n, n), x.dtype), x[-1:], P[-1:])
        elements = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), elements, last)
        # reverse=True scans from the last sample: the accumulated element is the later one
        combine = jax.vmap(lambda later, earlier: _smoother_combine(earlier, later))
        combined = jax.lax.associative_scan(combine, elements, reverse=True)
        return Smoothed(combined.g, combined.L, elements.E)

    # the sequential recursion in its classic form, 2 n^3 per sample (the elements' form costs twice that):
    # x_{k|T} = x_k + E_k (x_{k+1|T} - x_prior_{k+1}),  P_{k|T} = P_k + E_k (P_{k+1|T} - P_prior_{k+1}) E_k'
    # The scan runs over the whole records (slicing them and joining the last sample back costs a copy of each
    # (T, n, n) array, benchmarks/estimation.py, smooth): at the last
    # sample the carry holds a "later" sample equal to its own prediction (x = x_prior = 0, P = P_prior = I), so
    # the correction is exactly zero and the smoothed moments are the filtered ones.
    # A time-varying Phi is read shifted by one sample, Phi[k + 1] next to sample k (the last one unused).
    def body(later, sample):
        x_later, P_later, x_prior_next, P_prior_next = later
        x_k, P_k, x_prior_k, P_prior_k, *Phi_next = sample
        E_k, E_k_t = _smoother_gain(Phi_next[0] if varying else Phi, P_k, P_prior_next)
        x_smoothed = x_k + E_k @ (x_later - x_prior_next)
        P_smoothed = symmetrize(P_k + E_k @ (P_later - P_prior_next) @ E_k_t)
        return (x_smoothed, P_smoothed, x_prior_k, P_prior_k), (x_smoothed, P_smoothed, E_k)

    zero, unit = jnp.zeros((n,), x.dtype), jnp.eye(n, dtype=x.dtype)
    samples = (x, P, x_prior, P_prior, *((jnp.roll(Phi, -1, axis=0),) if varying else ()))
    _, (xs, Ps, E) = jax.lax.scan(body, (zero, unit, zero, unit), samples, reverse=True)
    return Smoothed(xs, Ps, E.at[-1].set(0.0))


# --------------------------------------------------------------------------------------------
# Parallel filter


class _FilterElement(NamedTuple):
    """``p(x_k | x_j, y_{j+1..k}) = N(A x_j + b, C)`` and ``p(y_{j+1..k} | x_j) ∝ N_I(x_j; eta, J)``."""

    A: jax.Array
    b: jax.Array
    C: jax.Array
    eta: jax.Array
    J: jax.Array


def _filter_element(Phi, Q, C, R, offset, y) -> _FilterElement:
    """The element of a sample ``k >= 1`` (Särkkä & García-Fernández 2021, Lemma 7), with the input's
    contribution ``offset = Gamma u_{k-1}`` and the missing components removed as in
    :func:`jaxobs.kalman_steps.update`."""
    mask, y_observed = observed(y, Phi.dtype)
    C_o, R_o = observed_model(C, R, mask)
    S = symmetrize(C_o @ Q @ C_o.T + R_o)
    CS = jnp.linalg.solve(S, C_o).T  # C' S^{-1}
    K = Q @ CS
    IKC = jnp.eye(Phi.shape[-1], dtype=Phi.dtype) - K @ C_o
    residual = y_observed - C_o @ offset
    Cov = symmetrize(IKC @ Q @ IKC.T + K @ R_o @ K.T)
    return _FilterElement(IKC @ Phi, offset + K @ residual, Cov, Phi.T @ (CS @ residual),
                          symmetrize(Phi.T @ CS @ C_o @ Phi))  # fmt: skip


def _filter_combine(earlier: _FilterElement, later: _FilterElement) -> _FilterElement:
    """Särkkä & García-Fernández (2021), Lemma 8: ``earlier`` then ``later``."""
    n = earlier.b.shape[-1]
    W = jax.scipy.linalg.lu_factor(jnp.eye(n, dtype=earlier.b.dtype) + earlier.C @ later.J)  # one LU, two solves
    right = jax.scipy.linalg.lu_solve(W, jnp.concatenate([earlier.A, (earlier.b + earlier.C @ later.eta)[:, None],
                                                          earlier.C @ later.A.T], axis=1))  # fmt: skip
    left = jax.scipy.linalg.lu_solve(W, jnp.concatenate([(later.eta - later.J @ earlier.b)[:, None],
                                                         later.J @ earlier.A], axis=1), trans=1)  # fmt: skip
    A = later.A @ right[:, :n]
    b = later.A @ right[:, n] + later.b
    Cov = symmetrize(later.A @ right[:, n + 1 :] + later.C)
    eta = earlier.A.T @ left[:, 0] + earlier.eta
    J = symmetrize(earlier.A.T @ left[:, 1:] + earlier.J)
    return _FilterElement(A, b, Cov, eta, J)


def parallel_filter(params: KalmanParams, inputs: EstimatorInputs):
    """The time-varying Kalman filter (:data:`~jaxobs.observers.kalman.kalman_filter`) in parallel over time.

    The a-posteriori moments of every sample come from one ``jax.lax.associative_scan`` over per-sample elements
    (Särkkä & García-Fernández 2021, Lemmas 7-8; the first element holds the prior of ``x_0`` updated with
    ``y_0``, as in the sequential filter); the outputs are then computed from the a-priori moments they imply
    with :func:`jaxobs.kalman_steps.update`, for all samples at once. Equal to ``run(kalman_filter, params,
    inputs)`` to rounding, missing components and time-varying models (``inputs.model``,
    :func:`~jaxobs.observers.kalman.step_model`) included.

    An active observer without its adaptive strategy (``alpha <= 0``) and switched on is the Kalman filter of
    its augmented model: run it in parallel as ``make_kalman(aob.Phi, aob.C, aob.Q, aob.R, Gamma=aob.Gamma,
    x0=aob.x0, P0=aob.P0)``.

    Args:
      params: :class:`~jaxobs.observers.kalman.KalmanParams` with the time-varying gain (``gain`` ``None``).
      inputs: ``EstimatorInputs`` with ``y`` (T, p), ``u_prev`` (T, m) or ``None``, and ``model`` (each leaf with
        the leading axis T) or ``None``.

    Returns:
      ``(final_state, outputs)`` as :func:`~jaxobs.observers.base.run` returns them.
    """
    if params.gain is not None:
        raise ValueError("params has a fixed gain: the parallel filter computes the time-varying one")
    p, m = params.C.shape[-2], params.Gamma.shape[-1]
    y = jnp.asarray(inputs.y)
    _checks.shape("inputs.y", y, (None, p), "(time, outputs) measurements")
    T = y.shape[0]
    if T == 0:
        raise ValueError("inputs.y has no samples: give at least one (its shape is (time, outputs))")
    u_prev = inputs.u_prev
    if u_prev is not None:
        u_prev = jnp.asarray(u_prev)
        _checks.shape("inputs.u_prev", u_prev, (T, m), "(time, inputs) like inputs.y")
    return _parallel_filter(params, y, u_prev, _step_models(params, inputs.model, T))


def _step_models(params, model, T: int) -> dict:
    """The per-step model values of a record (:func:`~jaxobs.observers.kalman.step_model` of every sample), each
    with the leading axis ``T``; ``{}`` for a constant model."""
    if model is None:
        return step_model(params, None)  # {} or the error of a schedule without its argument
    for path, leaf in jax.tree_util.tree_leaves_with_path(model):
        if jnp.ndim(leaf) == 0 or jnp.shape(leaf)[0] != T:
            raise ValueError(f"inputs.model{jax.tree_util.keystr(path)} must have the leading time axis of "
                             f"inputs.y ({T} samples), got shape {jnp.shape(leaf)}")  # fmt: skip
    return jax.vmap(partial(step_model, params))(model)


@jax.jit
def _parallel_filter(params: KalmanParams, y, u_prev, varying: dict):
    n, dtype, T = params.Phi.shape[-1], params.Phi.dtype, y.shape[0]
    y = y.astype(dtype)
    # the model of every sample: a per-step value (axis 0) or the params' constant (broadcast, axis None)
    model = {name: varying.get(name, getattr(params, name)) for name in params.model_fields}
    axes = {name: 0 if name in varying else None for name in model}
    Phi, Gamma, C, Q, R = (model[name][1:] if axes[name] == 0 else model[name] for name in params.model_fields)
    aPhi, aGamma, aC, aQ, aR = (axes[name] for name in params.model_fields)
    if u_prev is None:
        offsets = jnp.zeros((T - 1, n), dtype)
    else:
        offsets = jax.vmap(jnp.matmul, (aGamma, 0))(Gamma, u_prev[1:].astype(dtype))
    first = update(params.x0, params.P0, *(model[k][0] if axes[k] == 0 else model[k] for k in ("C", "R")), y[0],
                   joseph=params.joseph)  # fmt: skip
    zeros = jnp.zeros((n, n), dtype)
    head = _FilterElement(zeros, first.x, first.P, jnp.zeros((n,), dtype), zeros)
    rest = jax.vmap(_filter_element, (aPhi, aQ, aC, aR, 0, 0))(Phi, Q, C, R, offsets, y[1:])
    elements = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), head, rest)
    posterior = jax.lax.associative_scan(jax.vmap(_filter_combine), elements)  # fn sees batches of pairs
    x_prior = jnp.concatenate([params.x0[None], jax.vmap(jnp.matmul, (aPhi, 0))(Phi, posterior.b[:-1]) + offsets])
    P_prior = jax.vmap(predict_covariance, (0, aPhi, aQ))(posterior.C[:-1], Phi, Q)
    P_prior = jnp.concatenate([params.P0[None], P_prior])
    result = jax.vmap(partial(update, joseph=params.joseph), (0, 0, aC, aR, 0))(x_prior, P_prior, model["C"],
                                                                              model["R"], y)  # fmt: skip
    covariances = (result.P, P_prior) if params.output_covariance else ()
    outputs = KalmanOutputs(result.x, x_prior, result.innovation, result.K, jnp.ones((T,), bool), result.S,
                            result.log_likelihood, *covariances)  # fmt: skip
    final = KalmanState(result.x[-1], result.P[-1], jnp.ones((), bool), jnp.sum(result.n_missing).astype(jnp.int32))
    return final, outputs


# --------------------------------------------------------------------------------------------
# Whole-record entry points


def _with_covariances(params):
    if not any(f.name == "output_covariance" for f in dataclasses.fields(params)):
        raise ValueError(f"params ({type(params).__name__}) has no output_covariance switch: smoothing needs a "
                         "Kalman-type estimator that outputs its covariances")  # fmt: skip
    return dataclasses.replace(params, output_covariance=True)


def _filtered(estimator: Estimator, params, inputs, parallel: bool):
    if not parallel:
        return _run(estimator, params, inputs)[1]
    if estimator is not kalman_filter:
        raise ValueError("parallel=True runs the Kalman filter (estimator=kalman_filter with KalmanParams); for an "
                         "active observer see parallel_filter")  # fmt: skip
    return parallel_filter(params, inputs)[1]


_run = jax.jit(run, static_argnums=0)  # one compiled program per estimator and shapes, also for eager calls


def smooth(estimator: Estimator, params, inputs: EstimatorInputs, *, parallel: bool = False):
    """Filter a record and smooth it (:func:`rts_smoother`).

    For the nonlinear filters this is the extended RTS smoother (Särkkä 2013, ch. 9: the transition's Jacobian
    at each filtered mean) or the unscented RTS smoother (Särkkä 2008: the sigma points' cross-covariance,
    through their regression matrix), with the filter's own linearisations (its ``transition`` outputs), so
    missing and gated measurements, iterated updates and continuous-discrete models need nothing more.

    Args:
      estimator: a Kalman-type estimator whose params have an ``output_covariance`` switch and a time-varying
        gain: :data:`~jaxobs.observers.kalman.kalman_filter`,
        :data:`~jaxobs.observers.kalman.square_root_kalman_filter`,
        :data:`~jaxobs.observers.active.active_observer`, :data:`~jaxobs.observers.ekf.extended_kalman_filter`,
        :data:`~jaxobs.observers.ukf.unscented_kalman_filter`.
      params: its params (``output_covariance`` is switched on here).
      inputs: ``EstimatorInputs`` over ``T`` samples.
      parallel: filter (Kalman filter only, :func:`parallel_filter`) and smooth with associative scans.

    Returns:
      ``(outputs, smoothed)``: the filter's outputs (with covariances) and :class:`Smoothed`.

    Example:
      >>> import jaxobs as jo
      >>> params = jo.make_kalman(Phi=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]])
      >>> y = jnp.sin(0.1 * jnp.arange(100.0))[:, None]
      >>> filtered, smoothed = jo.smooth(jo.kalman_filter, params, jo.EstimatorInputs(y=y))
      >>> bool(jnp.all(smoothed.P[:, 0, 0] <= filtered.P[:, 0, 0]))  # smoothing never adds uncertainty
      True
      >>> model = jo.nonlinear_model(lambda x, u, t: x + 0.1 * jnp.sin(x), lambda x: x**3, [[0.01]], [[0.1]],
      ...                            x0=[0.5])
      >>> filtered, smoothed = jo.smooth(jo.extended_kalman_filter, jo.make_ekf(model), jo.EstimatorInputs(y=y))
      >>> smoothed.x.shape, filtered.transition.shape  # the transition: the Jacobian of f, one per sample
      ((100, 1), (100, 1, 1))
    """
    params = _with_covariances(params)
    filtered = _filtered(estimator, params, inputs, parallel)
    Phi = getattr(filtered, "transition", None)  # a nonlinear filter's linearisations, else the model's Phi
    if Phi is None:
        Phi = params.Phi
        if hasattr(params, "model_fields"):  # a Kalman filter's time-varying model: Phi_k of every sample
            Phi = _step_models(params, getattr(inputs, "model", None), jnp.shape(inputs.y)[0]).get("Phi", Phi)
    return filtered, rts_smoother(Phi, filtered, parallel=parallel)


def log_likelihood(estimator: Estimator, params, inputs: EstimatorInputs, *, parallel: bool = False):
    """``log p(y_0 .. y_{T-1})`` of a record under the estimator's model: the sum of its per-sample
    ``log_likelihood`` outputs (exact marginals over the observed components; with a steady-state gain, the
    steady-state approximation; for the EKF and UKF the Gaussian approximation of each predictive density,
    Särkkä 2013, ch. 12). Differentiable in ``params``: the objective for fitting ``Q``, ``R`` or a model to
    data (maximum likelihood), or for comparing models (e.g. active observers of different orders).

    Args:
      estimator: :data:`~jaxobs.observers.kalman.kalman_filter`,
        :data:`~jaxobs.observers.kalman.square_root_kalman_filter`,
        :data:`~jaxobs.observers.active.active_observer`, :data:`~jaxobs.observers.ekf.extended_kalman_filter`,
        :data:`~jaxobs.observers.ukf.unscented_kalman_filter` (any estimator with a ``log_likelihood`` output).
      params: its params.  inputs: ``EstimatorInputs`` over ``T`` samples.
      parallel: use :func:`parallel_filter` (Kalman filter only).

    Example:
      >>> import jaxobs as jo
      >>> y = jnp.cumsum(jnp.ones((200, 1)) * 0.1, axis=0)
      >>> ll = lambda q: jo.log_likelihood(jo.kalman_filter, jo.make_kalman([[1.0]], [[1.0]], [[q]], [[0.1]]),
      ...                                  jo.EstimatorInputs(y=y))
      >>> bool(ll(0.01) > ll(10.0))
      True
      >>> model = lambda g: jo.nonlinear_model(lambda x, u, t: g * x, lambda x: x, [[0.01]], [[0.1]], x0=[0.1])
      >>> ll = lambda g: jo.log_likelihood(jo.unscented_kalman_filter, jo.make_ukf(model(g)), jo.EstimatorInputs(y=y))
      >>> bool(ll(1.0) > ll(0.5)), bool(jnp.isfinite(jax.grad(ll)(1.0)))  # a growing record: g = 1 fits better
      (True, True)
    """
    per_step = getattr(_filtered(estimator, params, inputs, parallel), "log_likelihood", None)
    if per_step is None:
        raise ValueError("estimator has no log_likelihood output: use a Kalman-type estimator (kalman_filter, "
                         "square_root_kalman_filter, active_observer, extended_kalman_filter, "
                         "unscented_kalman_filter) with a noise model")  # fmt: skip
    return jnp.sum(per_step)
