"""Observer-based state feedback: the combinator that turns any estimator into a controller.

Like ``optax.chain``, :func:`observer_controller` takes an :class:`~jaxobs.observers.base.Estimator` and
returns a :class:`~jaxobs.observers.base.Controller` that commands ``u_k = N r_k - L x_hat_k`` (Cortesão 2006
eq. 49-50), feeding the estimator ``y_k`` and its own previous command. For an AOB, ``L = [L_r, 0, ..., 0, I]``
(:func:`jaxobs.observers.active.feedback_gain`) adds the active-state compensation. Details:
docs/theory/estimators.md.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.observers.base import Controller, ControllerInputs, Estimator, EstimatorInputs, LinearObserver

__all__ = ["FeedbackParams", "FeedbackState", "FeedbackOutputs", "observer_controller"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FeedbackParams:
    """Parameters of an observer-based controller.

    Attributes:
      estimator: the estimator's params (any family).
      L: (m, n) state feedback on the estimator's state ``x_hat`` (n entries).
      N: (m, q) reference pre-gain, or ``None`` for ``u = r - L x_hat`` with ``r`` of shape (m,).
    """

    estimator: Any
    L: jax.Array
    N: jax.Array | None = None

    @property
    def n_inputs(self) -> int:
        """Number of plant inputs ``m``."""
        return self.L.shape[-2]

    def padded(self, n: int) -> FeedbackParams:
        """The same controller with ``n`` estimator states (extra states identically zero), for a fixed-gain
        :class:`~jaxobs.observers.base.LinearObserver` estimator: designs of different orders then stack."""
        if not isinstance(self.estimator, LinearObserver):
            raise ValueError("padded needs a LinearObserver estimator; take the controller's linear form first")
        estimator = self.estimator.padded(n)
        return FeedbackParams(estimator, jnp.pad(self.L, ((0, 0), (0, n - self.L.shape[-1]))), self.N)


class FeedbackState(NamedTuple):
    """State of :func:`observer_controller` between steps.

    Attributes:
      estimator: the estimator's state
      u: (m,) the last command u_{k-1}
    """

    estimator: Any
    u: jax.Array


class FeedbackOutputs(NamedTuple):
    """Outputs of one step of :func:`observer_controller`.

    Attributes:
      u: (m,) command u_k = N r_k - L x_hat_k
      x: (n,) the estimate x_hat_k used
      estimator: the estimator's outputs at sample k
    """

    u: jax.Array
    x: jax.Array
    estimator: Any


def _reference(params: FeedbackParams, r):
    m = params.n_inputs
    if params.N is None:
        return _checks.vector("inputs.r", r, m, params.L.dtype, what="one entry per input (no pre-gain N)",
                              check_finite=False)  # fmt: skip
    q = params.N.shape[-1]
    return params.N @ _checks.vector("inputs.r", r, q, params.L.dtype, what="one entry per column of N",
                                     check_finite=False)  # fmt: skip


def observer_controller(estimator: Estimator) -> Controller:
    """The controller ``u_k = N r_k - L x_hat_k`` around ``estimator`` (params: :class:`FeedbackParams`).

    The controller's ``linear`` form exists when the estimator's does (fixed gain): the same controller as
    :class:`FeedbackParams` around the estimator's :class:`~jaxobs.observers.base.LinearObserver`, i.e. the
    params of :data:`jaxobs.observers.linear.linear_controller`, which :mod:`jaxobs.stability` analyses.

    Example:
      >>> import jax.numpy as jnp
      >>> from jaxobs.observers import ControllerInputs, feedback, kalman, run
      >>> est = kalman.make_kalman(Phi=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]], Gamma=[[0.1]])
      >>> ctrl = feedback.observer_controller(kalman.kalman_filter)
      >>> params = feedback.FeedbackParams(est, L=jnp.array([[2.0]]))
      >>> _, out = run(ctrl, params, ControllerInputs(y=jnp.ones((20, 1)), r=jnp.zeros((20, 1))))
      >>> out.u.shape
      (20, 1)
    """

    def init(params: FeedbackParams) -> FeedbackState:
        return FeedbackState(estimator.init(params.estimator), jnp.zeros((params.n_inputs,), params.L.dtype))

    def step(params: FeedbackParams, state: FeedbackState, inputs: ControllerInputs):
        r = _reference(params, inputs.r)
        est_state, out = estimator.step(params.estimator, state.estimator, EstimatorInputs(inputs.y, state.u))
        _checks.shape("L", params.L, (params.n_inputs, out.x.shape[-1]), "one column per estimator state")
        u = r - params.L @ out.x
        return FeedbackState(est_state, u), FeedbackOutputs(u, out.x, out)

    linear = None
    if estimator.linear is not None:

        def linear(params: FeedbackParams) -> FeedbackParams:
            return FeedbackParams(estimator.linear(params.estimator), params.L, params.N)

    return Controller(init, step, linear)
