"""The estimator and controller protocols, the fixed-gain linear form, and :func:`run`.

An :class:`Estimator` is a pair of pure functions over pytrees, ``state = init(params)`` and
``state, out = step(params, state, EstimatorInputs(y=y_k, u_prev=u_km1))`` (``out.x``, ``out.innovation``, and
``out.d`` for disturbance observers); a :class:`Controller` is the same pair over :class:`ControllerInputs` with
``out.u``. Fixed-gain families also give their :class:`LinearObserver` form. Running over time is ``lax.scan``
(:func:`run`), batching is ``vmap``. Conventions shared by every family: docs/theory/estimators.md.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp

from jaxobs import _checks

__all__ = [
    "EstimatorInputs",
    "ControllerInputs",
    "Estimator",
    "Controller",
    "LinearObserver",
    "run",
]


class EstimatorInputs(NamedTuple):
    """What an estimator reads at sample ``k``.

    Attributes:
      y: (p,) measurement ``y_k``; NaN (or inf) entries are missing.
      u_prev: (m,) input ``u_{k-1}`` held over the interval that ends at sample ``k``; ``None`` for a model
        without inputs.
      model: the model of sample ``k`` for the estimators of a time-varying linear model (the Kalman filter and
        its square-root and parallel forms): a dict of per-step values of their params' model fields, e.g.
        ``{"Phi": Phi_k, "Q": Q_k}``, or the argument of the params' ``schedule`` (e.g. the step index ``k``);
        ``None`` for a constant model (:func:`jaxobs.observers.kalman.step_model`). Other estimators ignore it.
    """

    y: jax.Array
    u_prev: jax.Array | None = None
    model: Any = None


class ControllerInputs(NamedTuple):
    """What a controller reads at sample ``k``.

    Attributes:
      y: (p,) measurement ``y_k``; NaN (or inf) entries are missing.
      r: (m,) reference ``r_k`` (in output units when the controller has a reference pre-gain).
    """

    y: jax.Array
    r: jax.Array


class InitFn(Protocol):
    def __call__(self, params: Any) -> Any:
        """The state before the first sample."""


class EstimatorStepFn(Protocol):
    def __call__(self, params: Any, state: Any, inputs: EstimatorInputs) -> tuple[Any, Any]:
        """``(state_k, outputs_k)`` from ``state_{k-1}`` and the inputs of sample ``k``."""


class ControllerStepFn(Protocol):
    def __call__(self, params: Any, state: Any, inputs: ControllerInputs) -> tuple[Any, Any]:
        """``(state_k, outputs_k)`` with ``outputs_k.u`` the command of sample ``k``."""


class LinearFormFn(Protocol):
    def __call__(self, params: Any) -> Any:
        """The fixed-gain linear form of ``params`` (raises ``ValueError`` if it has none)."""


class Estimator(NamedTuple):
    """An estimator: ``init(params) -> state``, ``step(params, state, EstimatorInputs) -> (state, outputs)``.

    ``linear``: for linear estimators with a fixed gain, ``params -> LinearObserver`` (else ``None``).
    """

    init: InitFn
    step: EstimatorStepFn
    linear: LinearFormFn | None = None


class Controller(NamedTuple):
    """A controller: ``init(params) -> state``, ``step(params, state, ControllerInputs) -> (state, outputs)``.

    ``linear``: for linear controllers, ``params ->`` the params of the same controller around a
    :class:`LinearObserver` (see :func:`jaxobs.observers.feedback.observer_controller`).
    """

    init: InitFn
    step: ControllerStepFn
    linear: LinearFormFn | None = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LinearObserver:
    """A fixed-gain linear observer (predictor-corrector form, Cortesão 2006 eq. 26).

    Each step computes::

        x_prior = Phi x_hat_{k-1} + Gamma u_{k-1}
        x_hat_k = x_prior + K (y_k - C x_prior)

    Attributes:
      Phi: (n, n) state transition.  Gamma: (n, m) input matrix.  C: (p, n) output matrix.
      K: (n, p) observer gain.
    """

    Phi: jax.Array
    Gamma: jax.Array
    C: jax.Array
    K: jax.Array

    def padded(self, n: int) -> LinearObserver:
        """The same observer with ``n >= n_states`` states; the extra states are identically zero, so
        observers of different orders can be stacked and ``vmap``-ped together."""
        n = _checks.count("n", n, minimum=self.Phi.shape[-1], hint="the padded observer keeps all its states")
        extra = n - self.Phi.shape[-1]
        rows = lambda M: jnp.pad(M, ((0, extra), (0, 0)))
        cols = lambda M: jnp.pad(M, ((0, 0), (0, extra)))
        return LinearObserver(rows(cols(self.Phi)), rows(self.Gamma), cols(self.C), rows(self.K))


def _time_length(inputs) -> int:
    """The common leading (time) axis of every leaf of ``inputs``; ``ValueError`` if they differ."""
    lengths = {}
    for path, leaf in jax.tree_util.tree_leaves_with_path(inputs):
        if jnp.ndim(leaf) == 0:
            raise ValueError(f"inputs{jax.tree_util.keystr(path)} must have a leading time axis, got a scalar")
        lengths[jax.tree_util.keystr(path)] = jnp.shape(leaf)[0]
    if not lengths:
        raise ValueError("inputs has no arrays: give at least the measurements y with a leading time axis")
    if len(set(lengths.values())) > 1:
        listing = ", ".join(f"inputs{k}: {v}" for k, v in lengths.items())
        raise ValueError(f"inputs: every series must have the same number of samples (leading axis), got {listing}")
    return next(iter(lengths.values()))


def run(system: Estimator | Controller, params, inputs, state=None):
    """Run an estimator or controller over a sequence of inputs (one ``lax.scan``).

    Args:
      system: an :class:`Estimator` or :class:`Controller`.
      params: its parameters.
      inputs: :class:`EstimatorInputs` or :class:`ControllerInputs` whose arrays have a leading time axis of
        length ``T`` (e.g. ``y`` of shape (T, p)).
      state: the initial state; defaults to ``system.init(params)``.

    Returns:
      ``(final_state, outputs)`` with every output stacked over time (leading axis ``T``).

    Example:
      >>> import jax.numpy as jnp
      >>> from jaxobs.observers import kalman, EstimatorInputs, run
      >>> params = kalman.make_kalman(Phi=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]])
      >>> _, out = run(kalman.kalman_filter, params, EstimatorInputs(y=jnp.ones((50, 1))))
      >>> out.x.shape
      (50, 1)
    """
    _time_length(inputs)
    if state is None:
        state = system.init(params)

    def body(carry, inp):
        return system.step(params, carry, inp)

    return jax.lax.scan(body, state, inputs)
