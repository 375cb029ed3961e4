"""The fixed-gain linear observer (Luenberger observer in predictor-corrector form) as an estimator.

Its params are the :class:`~jaxobs.observers.base.LinearObserver` matrices (Cortesão 2006 eq. 26)::

    x_prior = Phi x_hat_{k-1} + Gamma u_{k-1}
    x_hat_k = x_prior + K (y_k - C x_prior)

It is also what every fixed-gain family reduces to (their ``linear`` form), so designs of different families
and orders can be padded to one size, stacked and run under one ``vmap``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.observers.base import Estimator, EstimatorInputs, LinearObserver
from jaxobs.observers.feedback import observer_controller

__all__ = ["LinearObserver", "LinearObserverState", "LinearObserverOutputs", "linear_observer", "linear_controller"]


class LinearObserverState(NamedTuple):
    x: jax.Array  # (n,) a-posteriori estimate x_hat_{k-1}
    missing: jax.Array  # () measurement components skipped so far


class LinearObserverOutputs(NamedTuple):
    x: jax.Array  # (n,) a-posteriori estimate x_hat_k
    x_prior: jax.Array  # (n,) a-priori estimate
    innovation: jax.Array  # (p,) y_k - C x_prior (0 for missing components)


def _init(params: LinearObserver) -> LinearObserverState:
    return LinearObserverState(jnp.zeros(params.Phi.shape[-1], params.Phi.dtype), jnp.zeros((), jnp.int32))


def _step(params: LinearObserver, state: LinearObserverState, inputs: EstimatorInputs):
    dtype = params.Phi.dtype
    p, m = params.C.shape[-2], params.Gamma.shape[-1]
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    x_prior = params.Phi @ state.x
    if inputs.u_prev is not None:
        u = _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype, what="one entry per column of Gamma",
                           check_finite=False)  # fmt: skip
        x_prior = x_prior + params.Gamma @ u
    observed = jnp.isfinite(y)
    innovation = jnp.where(observed, y - params.C @ x_prior, 0.0)
    x = x_prior + params.K @ innovation
    missing = state.missing + jnp.sum(~observed).astype(jnp.int32)
    return LinearObserverState(x, missing), LinearObserverOutputs(x, x_prior, innovation)


linear_observer = Estimator(_init, _step, linear=lambda params: params)
"""The fixed-gain linear observer; params: :class:`~jaxobs.observers.base.LinearObserver`."""

linear_controller = observer_controller(linear_observer)
"""The fixed-gain linear observer with state feedback; params: :class:`~jaxobs.observers.feedback.FeedbackParams`
around a :class:`~jaxobs.observers.base.LinearObserver`, e.g. the linear form ``controller.linear(params)`` of any
fixed-gain controller, padded with :meth:`~jaxobs.observers.feedback.FeedbackParams.padded` to stack designs."""
