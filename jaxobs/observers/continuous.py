"""Continuous-time observers ``x_hat' = F(x_hat, u, y, t)`` run as ordinary sampled estimators.

A digital implementation of a continuous-time observer sees the input and the measurement only at the samples
``t_k = t0 + k dt`` and holds both over each sample (zero-order hold). Step ``k`` integrates the observer over
``[t_{k-1}, t_k]`` with ``u_{k-1}`` and ``y_{k-1}`` held (:func:`jaxobs.ct.integrate`, fixed Euler or RK4
substeps) and outputs ``x_hat(t_k)``; ``y_k`` then drives the next interval. So the estimate at ``t_k`` is that
of the continuous observer fed the sampled-and-held measurement, and ``y_k`` acts from ``t_k`` on (the first
step outputs ``x0`` unchanged). The innovation is ``y_k - h(x_hat(t_k))``.

Missing data: a non-finite component of ``y_k`` is replaced, over the next interval, by the observer's own
prediction ``h(x_hat(t))``, so an output-injection term ``L (y - h(x_hat))`` is exactly zero in that channel;
such components are counted in ``state.missing`` and their innovation is zero.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks, ct
from jaxobs.observers.base import Estimator, EstimatorInputs

__all__ = [
    "ContinuousObserverParams",
    "ContinuousObserverState",
    "ContinuousObserverOutputs",
    "make_continuous_observer",
    "continuous_observer",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ContinuousObserverParams:
    """A continuous-time observer (``n`` states, ``m`` inputs, ``p`` outputs); build it with
    :func:`make_continuous_observer`.

    Attributes:
      F: the observer ``F(x_hat, u, y, t) -> dx_hat/dt`` (n,), a ``jax.tree_util.Partial`` (its bound arguments,
        e.g. gains and model parameters, are leaves: ``grad`` and ``vmap`` reach them).
      h: its output ``h(x_hat) -> y_hat`` (p,), a ``Partial`` likewise.
      x0: (n,) estimate at ``t0``.  dt: () sample period.  t0: () time of the first sample.
      n_inputs: static ``m``.  substeps: static fixed steps per sample.  method: static ``"rk4"`` or ``"euler"``.
    """

    F: Callable
    h: Callable
    x0: jax.Array
    dt: jax.Array
    t0: jax.Array
    n_inputs: int = dataclasses.field(default=0, metadata=dict(static=True))
    substeps: int = dataclasses.field(default=1, metadata=dict(static=True))
    method: str = dataclasses.field(default="rk4", metadata=dict(static=True))

    @property
    def n_outputs(self) -> int:
        return jax.eval_shape(self.h, self.x0).shape[0]


class ContinuousObserverState(NamedTuple):
    x: jax.Array  # (n,) estimate x_hat(t_{k-1})
    y: jax.Array  # (p,) measurement y_{k-1}, held over [t_{k-1}, t_k] (NaN where missing)
    t: jax.Array  # () t_{k-1}
    started: jax.Array  # () bool: a sample has been processed (the next step integrates)
    missing: jax.Array  # () int32, measurement components skipped so far


class ContinuousObserverOutputs(NamedTuple):
    x: jax.Array  # (n,) estimate x_hat(t_k)
    innovation: jax.Array  # (p,) y_k - h(x_hat(t_k)) (0 for missing components)


def make_continuous_observer(F, h, *, x0, dt, t0=0.0, n_inputs: int = 0, substeps: int = 1,
                             method: str = "rk4") -> ContinuousObserverParams:  # fmt: skip
    """Build and check :class:`ContinuousObserverParams`.

    Args:
      F: the observer ``F(x_hat, u, y, t)`` returning ``dx_hat/dt`` (n,) (a function or a ``Partial``).
      h: its output map ``h(x_hat)`` (p,) (a function or a ``Partial``).
      x0: (n,) estimate at ``t0``.  dt: sample period (> 0).  t0: time of the first sample.
      n_inputs: the number of inputs ``m``.  substeps: fixed steps per sample.  method: ``"rk4"`` or ``"euler"``.

    Example: a double-integrator observer with poles at -2, -2 fed a constant position of 1 for 6 s.

      >>> import jax.numpy as jnp
      >>> import jaxobs as jo
      >>> F = lambda x, u, y, t: jnp.array([x[1], 0.0]) + jnp.array([4.0, 4.0]) * (y[0] - x[0])
      >>> params = jo.make_continuous_observer(F, lambda x: x[:1], x0=jnp.zeros(2), dt=0.01)
      >>> _, out = jo.run(jo.continuous_observer, params, jo.EstimatorInputs(y=jnp.ones((600, 1))))
      >>> bool(jnp.abs(out.x[-1, 0] - 1.0) < 1e-3)
      True
    """
    F, h = _checks.function("F", F), _checks.function("h", h)
    x0 = jnp.atleast_1d(jnp.asarray(x0))
    dtype = _checks.float_dtype(x0=x0, dt=dt, t0=t0)
    _checks.shape("x0", x0, (None,), "the initial estimate, one entry per state")
    _checks.finite("x0", x0)
    _checks.positive_scalar("dt", dt)
    x0, dt, t0 = x0.astype(dtype), jnp.asarray(dt, dtype), jnp.asarray(t0, dtype)
    _checks.shape("dt", dt, (), "a scalar sample period")
    _checks.shape("t0", t0, (), "a scalar time")
    n_inputs = _checks.count("n_inputs", n_inputs, hint="the size of the input u of F(x_hat, u, y, t)")
    substeps = _checks.count("substeps", substeps, minimum=1, hint="fixed integration steps per sample")
    if method not in ct.METHODS:
        raise ValueError(f"method must be one of {sorted(ct.METHODS)}, got {method!r}")
    _checks.returns("h(x_hat)", h, (x0,), (None,), "the output estimate, a vector")
    u, y = jnp.zeros((n_inputs,), dtype), jnp.zeros(jax.eval_shape(h, x0).shape, dtype)
    _checks.returns("F(x_hat, u, y, t)", F, (x0, u, y, t0), x0.shape, "dx_hat/dt, one entry per entry of x0")
    return ContinuousObserverParams(F, h, x0, dt, t0, n_inputs, substeps, method)


def _init(params: ContinuousObserverParams) -> ContinuousObserverState:
    y = jnp.full((params.n_outputs,), jnp.nan, params.x0.dtype)
    return ContinuousObserverState(params.x0, y, params.t0, jnp.zeros((), bool), jnp.zeros((), jnp.int32))


def _step(params: ContinuousObserverParams, state: ContinuousObserverState, inputs: EstimatorInputs):
    dtype, p, m = params.x0.dtype, params.n_outputs, params.n_inputs
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per output of h", check_finite=False)
    if inputs.u_prev is None:
        if m:
            raise ValueError(f"inputs.u_prev is required: the observer has n_inputs={m}, got None")
        u = jnp.zeros((0,), dtype)
    else:
        u = _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype, what="n_inputs entries", check_finite=False)
    observed_before = jnp.isfinite(state.y)
    held = jnp.where(observed_before, state.y, 0.0)

    def rhs(x, u, t):  # a missing channel sees the observer's own prediction
        return params.F(x, u, jnp.where(observed_before, held, params.h(x)), t)

    x_next = ct.integrate(rhs, state.x, u, state.t, params.dt, substeps=params.substeps, method=params.method)
    x = jnp.where(state.started, x_next, state.x)
    t = jnp.where(state.started, state.t + params.dt, state.t)
    observed = jnp.isfinite(y)
    innovation = jnp.where(observed, jnp.where(observed, y, 0.0) - params.h(x), 0.0)
    missing = state.missing + jnp.sum(~observed).astype(jnp.int32)
    return ContinuousObserverState(x, y, t, jnp.ones((), bool), missing), ContinuousObserverOutputs(x, innovation)


continuous_observer = Estimator(_init, _step)
"""A continuous-time observer run as a sampled :class:`~jaxobs.observers.base.Estimator` over
:class:`ContinuousObserverParams`.

Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (p,) and (m,) (``u_prev=None`` without inputs). Outputs:
:class:`ContinuousObserverOutputs`."""
