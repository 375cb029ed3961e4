"""Interacting multiple models (IMM, Blom & Bar-Shalom 1988): a combinator over Gaussian estimators, one per mode.

``imm(*estimators)`` (like ``optax.chain`` over transformations) returns an
:class:`~jaxobs.observers.base.Estimator` over :class:`IMMParams`: the modes' params, a Markov mode-transition
matrix and the modes' prior probabilities. Each step mixes the modes' Gaussians ``(x, P)`` (read from and written
to their states' ``x`` and ``P`` fields) with the mixing probabilities, runs every mode's own step, weighs the
modes by their ``log_likelihood`` outputs and combines them. Any estimators whose states carry ``x``, ``P`` and
whose outputs carry ``log_likelihood`` (the Kalman filter, the EKF, the UKF, ...) serve as modes. The equations:
docs/guides/estimation-breadth.md.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs._linalg import symmetrize
from jaxobs.observers.base import Estimator, EstimatorInputs

__all__ = ["IMMParams", "IMMState", "IMMOutputs", "make_imm", "imm", "mix"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class IMMParams:
    """Parameters of an IMM over ``M`` modes (:func:`imm`).

    Attributes:
      modes: a tuple of the ``M`` mode estimators' params, in the order of :func:`imm`'s estimators.
      transition: (M, M) mode-transition probabilities, ``transition[i, j] = P(mode_k = j | mode_{k-1} = i)``
        (rows sum to 1; filterpy's ``M``).
      mode_prior: (M,) probabilities of the modes at the first sample (the first step has no transition, as
        the modes' own first steps have no prediction).
    """

    modes: tuple
    transition: jax.Array
    mode_prior: jax.Array


class IMMState(NamedTuple):
    """State of an IMM between steps.

    Attributes:
      modes: the ``M`` mode estimators' states (each with its a-posteriori ``x`` (n,) and ``P`` (n, n))
      probabilities: (M,) mode probabilities ``mu_{k-1}`` after the last update (the prior before the first)
      started: () bool: a measurement has been processed (the next step mixes)
    """

    modes: tuple
    probabilities: jax.Array
    started: jax.Array


class IMMOutputs(NamedTuple):
    """Outputs of one step of an IMM.

    Attributes:
      x: (n,) combined estimate ``sum_j mu_j x_j``
      P: (n, n) its covariance ``sum_j mu_j (P_j + (x_j - x)(x_j - x)')``
      innovation: (p,) the modes' innovations weighed by the predicted mode probabilities, ``sum_j c_j e_j``
      probabilities: (M,) mode probabilities ``mu_k = P(mode_k = j | y_0..y_k)``
      log_likelihood: () ``log p(y_k | y_0..y_{k-1}) = log sum_j c_j exp(l_j)`` with the modes' ``l_j``
      modes: the ``M`` mode estimators' own outputs
    """

    x: jax.Array
    P: jax.Array
    innovation: jax.Array
    probabilities: jax.Array
    log_likelihood: jax.Array
    modes: tuple


def make_imm(modes, transition, mode_prior=None) -> IMMParams:
    """Build and check :class:`IMMParams`.

    Args:
      modes: a sequence of the ``M >= 2`` mode estimators' params (in the order of :func:`imm`'s estimators).
      transition: (M, M) Markov mode-transition matrix, ``transition[i, j]`` the probability of mode ``j`` after
        mode ``i``: non-negative, rows summing to 1 (checked when concrete).
      mode_prior: (M,) probabilities of the modes at the first sample (default uniform); normalised here.

    Example:
      >>> import jaxobs as jo
      >>> slow, fast = (jo.make_kalman([[1.0]], [[1.0]], [[q]], [[1.0]]) for q in (1e-4, 1.0))
      >>> params = jo.make_imm([slow, fast], [[0.95, 0.05], [0.05, 0.95]])
      >>> _, out = jo.run(jo.imm(jo.kalman_filter, jo.kalman_filter), params, jo.EstimatorInputs(y=jnp.ones((9, 1))))
      >>> out.probabilities.shape, bool(out.probabilities[-1, 0] > 0.5)  # a constant record: the slow mode
      ((9, 2), True)
    """
    modes = tuple(modes)
    count = len(modes)
    if count < 2:
        raise ValueError(f"modes must hold at least two estimators' params, got {count}")
    transition = jnp.asarray(_checks.real_array("transition", transition))
    dtype = jnp.result_type(transition, float)
    _checks.matrix("transition", transition, shape=(count, count), square=True)
    mode_prior = jnp.full((count,), 1.0 / count, dtype) if mode_prior is None else mode_prior
    mode_prior = _checks.vector("mode_prior", mode_prior, count, dtype, what="one probability per mode")
    _checks.positive("transition", transition, allow_zero=True, what="probabilities")
    _checks.positive("mode_prior", mode_prior, allow_zero=True, what="probabilities")
    if _checks.is_concrete(transition, mode_prior):
        rows = jnp.sum(transition, axis=1)
        if not bool(jnp.allclose(rows, 1.0, rtol=0, atol=1e-10)):
            raise ValueError(f"transition: each row must sum to 1 (probabilities of the next mode), got {rows}")
        if not float(jnp.sum(mode_prior)) > 0:
            raise ValueError("mode_prior must have a positive entry")
    return IMMParams(modes, transition.astype(dtype), mode_prior / jnp.sum(mode_prior))


def mix(weights, x, P):
    """Moment matching of Gaussian mixtures: for each column ``j`` of ``weights``, the mean and covariance of
    ``sum_i w_ij N(x_i, P_i)``, ``x_j = sum_i w_ij x_i``, ``P_j = sum_i w_ij (P_i + (x_i - x_j)(x_i - x_j)')``:
    the IMM's mixing (``w_ij`` the mixing probabilities) and combination (one column, the mode probabilities)
    steps (Blom & Bar-Shalom 1988).

    Args:
      weights: (M, K) non-negative weights, each column summing to 1.
      x: (M, n) means.  P: (M, n, n) covariances.

    Returns:
      ``(x_mixed, P_mixed)`` of shapes (K, n) and (K, n, n).
    """
    means = weights.T @ x  # (K, n)
    spread = x[None, :, :] - means[:, None, :]  # (K, M, n)
    second = jnp.einsum("ik,kim,kil->kml", weights, spread, spread)
    return means, symmetrize(jnp.einsum("ik,iml->kml", weights, P) + second)


def _gaussians(states) -> tuple[jax.Array, jax.Array]:
    """The modes' ``(x, P)`` stacked, (M, n) and (M, n, n): each state must be a NamedTuple with the fields ``x``
    and ``P`` of one size ``n`` (checked while tracing)."""
    for j, state in enumerate(states):
        fields = getattr(state, "_fields", ())
        if "x" not in fields or "P" not in fields:
            raise ValueError(f"state.modes[{j}] ({type(state).__name__}) has no fields x and P: an IMM mode must be "
                             "a Gaussian estimator whose state holds its mean and covariance (e.g. kalman_filter, "
                             "extended_kalman_filter, unscented_kalman_filter)")  # fmt: skip
    shapes = [(jnp.shape(s.x), jnp.shape(s.P)) for s in states]
    if len(set(shapes)) != 1:
        raise ValueError(f"the modes' states must have means and covariances of one size n, got {shapes}")
    return jnp.stack([s.x for s in states]), jnp.stack([s.P for s in states])


def _mode_probabilities(mixing_prior, log_likelihoods):
    """``(mu, log p(y_k | ...))`` from the predicted mode probabilities ``c`` and the modes' log-likelihoods
    ``l``: ``mu_j = c_j exp(l_j) / sum_i c_i exp(l_i)``, in logarithms (no underflow for unlikely modes)."""
    positive = mixing_prior > 0
    log_joint = jnp.where(positive, jnp.log(jnp.where(positive, mixing_prior, 1.0)) + log_likelihoods, -jnp.inf)
    total = jax.nn.logsumexp(log_joint)
    return jnp.exp(log_joint - total), total


def _mixing(transition, probabilities, started, x, P):
    """``(c, x0, P0)``: the predicted mode probabilities ``c_j = sum_i T_ij mu_i`` and each mode's mixed prior
    (:func:`mix` with ``w_ij = T_ij mu_i / c_j``; a mode with ``c_j = 0`` keeps its own). Before the first
    measurement nothing moves: ``c`` is the prior and every mode keeps its ``x``, ``P``."""
    mixing_prior = jnp.where(started, probabilities @ transition, probabilities)
    positive = mixing_prior > 0
    weights = transition * probabilities[:, None] / jnp.where(positive, mixing_prior, 1.0)
    weights = jnp.where(positive, weights, jnp.eye(transition.shape[-1], dtype=weights.dtype))
    x0, P0 = mix(weights, x, P)
    return mixing_prior, jnp.where(started, x0, x), jnp.where(started, P0, P)


def _check_params(params: IMMParams, count: int) -> None:
    if not isinstance(params, IMMParams):
        raise ValueError(f"params must be IMMParams (make_imm), got {type(params).__name__}")
    if len(params.modes) != count:
        raise ValueError(f"params.modes holds {len(params.modes)} params for the {count} estimators of this IMM")
    _checks.shape("params.transition", params.transition, (count, count), "one row and column per mode")
    _checks.shape("params.mode_prior", params.mode_prior, (count,), "one probability per mode")


def imm(*estimators: Estimator) -> Estimator:
    """The interacting multiple model estimator over ``estimators``, one per mode (Blom & Bar-Shalom 1988).

    Each step, from the mode probabilities ``mu`` and the modes' Gaussians ``(x_i, P_i)`` of the last one:

    1. predicted mode probabilities ``c_j = sum_i T_ij mu_i`` and mixing probabilities ``w_ij = T_ij mu_i / c_j``;
    2. each mode starts from the mixture ``(x0_j, P0_j)`` of :func:`mix` (written into its state's ``x``, ``P``);
    3. each mode runs its own step on the inputs (its prediction and update), giving ``x_j``, ``P_j`` and its
       log-likelihood ``l_j``;
    4. ``mu_j = c_j exp(l_j) / sum_i c_i exp(l_i)``, and the output is the combination of the modes with ``mu``.

    The first step has no transition and no mixing (the modes' priors are those of ``x_0``, ``c = mode_prior``).
    The modes must have the same state size ``n`` and measurement size ``p``; their states must hold ``x`` and
    ``P`` (propagated by the mode: a Kalman filter with a time-varying gain, an EKF, a UKF; a fixed-gain filter
    propagates no covariance) and their outputs a ``log_likelihood``; every mode reads the same inputs
    (``EstimatorInputs.model`` included). Everything is pure: ``jit``, ``vmap`` (over plants, the params'
    leaves) and ``grad`` (through the transition matrix, the modes' params) apply.

    Args:
      estimators: the ``M >= 2`` mode estimators (may differ, e.g. a Kalman filter and an EKF).

    Returns:
      an :class:`~jaxobs.observers.base.Estimator` over :class:`IMMParams` with :class:`IMMState` and
      :class:`IMMOutputs`.

    Example:
      >>> import jaxobs as jo
      >>> imm_kf = jo.imm(jo.kalman_filter, jo.kalman_filter)
      >>> params = jo.make_imm([jo.make_kalman([[1.0]], [[1.0]], [[q]], [[1.0]]) for q in (1e-4, 1.0)],
      ...                      [[0.9, 0.1], [0.1, 0.9]])
      >>> state, out = jo.run(imm_kf, params, jo.EstimatorInputs(y=jnp.arange(6.0)[:, None] ** 2))
      >>> bool(out.probabilities[-1, 1] > 0.9)  # a fast-growing record: the agile mode
      True
    """
    estimators = tuple(estimators)
    if len(estimators) < 2 or not all(isinstance(e, Estimator) for e in estimators):
        raise ValueError(
            f"imm needs at least two Estimators (one per mode), got {[type(e).__name__ for e in estimators]}"
        )
    count = len(estimators)

    def init(params: IMMParams) -> IMMState:
        _check_params(params, count)
        states = tuple(e.init(p) for e, p in zip(estimators, params.modes, strict=True))
        return IMMState(states, params.mode_prior, jnp.zeros((), bool))

    def step(params: IMMParams, state: IMMState, inputs: EstimatorInputs):
        _check_params(params, count)
        x, P = _gaussians(state.modes)
        mixing_prior, x0, P0 = _mixing(params.transition, state.probabilities, state.started, x, P)
        results = [estimator.step(mode_params, mode_state._replace(x=x0[j], P=P0[j]), inputs)
                   for j, (estimator, mode_params, mode_state)
                   in enumerate(zip(estimators, params.modes, state.modes, strict=True))]  # fmt: skip
        states, outputs = zip(*results, strict=True)
        if any(getattr(out, "log_likelihood", None) is None for out in outputs):
            raise ValueError("an IMM mode's outputs have no log_likelihood: use estimators with a noise model")
        log_likelihoods = jnp.stack([out.log_likelihood for out in outputs])
        probabilities, log_likelihood = _mode_probabilities(mixing_prior, log_likelihoods)
        x_hat, P_hat = mix(probabilities[:, None], *_gaussians(states))
        innovation = mixing_prior @ jnp.stack([out.innovation for out in outputs])
        new_state = IMMState(tuple(states), probabilities, jnp.ones((), bool))
        return new_state, IMMOutputs(x_hat[0], P_hat[0], innovation, probabilities, log_likelihood, tuple(outputs))

    return Estimator(init, step)
