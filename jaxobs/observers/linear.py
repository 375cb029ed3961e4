"""The fixed-gain linear observer (Luenberger observer in predictor-corrector form) as an estimator.

Its params are the :class:`~jaxobs.observers.base.LinearObserver` matrices (Cortesão 2006 eq. 26)::

    x_prior = Phi x_hat_{k-1} + Gamma u_{k-1}
    x_hat_k = x_prior + K (y_k - C x_prior)

It is also what every fixed-gain family reduces to (their ``linear`` form), so designs of different families
and orders can be padded to one size, stacked and run under one ``vmap``. As in the Kalman-type families, the
first sample has no prediction: ``x_hat_0 = x_prior_0 + K (y_0 - C x_prior_0)`` with ``x_prior_0 = 0``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.kalman_steps import predict, update
from jaxobs.observers.base import Estimator, EstimatorInputs, LinearObserver
from jaxobs.observers.feedback import observer_controller

__all__ = ["LinearObserver", "LinearObserverState", "LinearObserverOutputs", "linear_observer", "linear_controller"]


class LinearObserverState(NamedTuple):
    """State of :data:`linear_observer` between steps.

    Attributes:
      x: (n,) a-posteriori estimate x_hat_{k-1} (zero before the first sample)
      started: () bool: a measurement has been processed (the next step predicts)
      missing: () measurement components skipped so far
    """

    x: jax.Array
    started: jax.Array
    missing: jax.Array


class LinearObserverOutputs(NamedTuple):
    """Outputs of one step of :data:`linear_observer`.

    Attributes:
      x: (n,) a-posteriori estimate x_hat_k
      x_prior: (n,) a-priori estimate
      innovation: (p,) y_k - C x_prior (0 for missing components)
    """

    x: jax.Array
    x_prior: jax.Array
    innovation: jax.Array


_SHAPES = "Phi (n, n), Gamma (n, m), C (p, n), K (n, p)"


def _init(params: LinearObserver) -> LinearObserverState:
    _checks.fields("params", params, _SHAPES)
    zero = jnp.zeros((), jnp.int32)
    return LinearObserverState(jnp.zeros(params.Phi.shape[-1], params.Phi.dtype), jnp.zeros((), bool), zero)


def _step(params: LinearObserver, state: LinearObserverState, inputs: EstimatorInputs):
    _checks.fields("params", params, _SHAPES)
    dtype = params.Phi.dtype
    p, m = params.C.shape[-2], params.Gamma.shape[-1]
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    u = inputs.u_prev
    if u is not None:
        u = _checks.vector("inputs.u_prev", u, m, dtype, what="one entry per column of Gamma", check_finite=False)
    x_prior, _ = predict(state.x, None, params.Phi, None, params.Gamma, u, skip=~state.started)
    result = update(x_prior, None, params.C, None, y, gain=params.K)
    missing = state.missing + result.n_missing.astype(jnp.int32)
    new_state = LinearObserverState(result.x, jnp.ones((), bool), missing)
    return new_state, LinearObserverOutputs(result.x, x_prior, result.innovation)


linear_observer = Estimator(_init, _step, linear=lambda params: params)
"""The fixed-gain linear observer; params: :class:`~jaxobs.observers.base.LinearObserver`."""

linear_controller = observer_controller(linear_observer)
"""The fixed-gain linear observer with state feedback; params: :class:`~jaxobs.observers.feedback.FeedbackParams`
around a :class:`~jaxobs.observers.base.LinearObserver`, e.g. the linear form ``controller.linear(params)`` of any
fixed-gain controller, padded with :meth:`~jaxobs.observers.feedback.FeedbackParams.padded` to stack designs."""
