"""Continuous-time observers ``x_hat' = F(x_hat, u, y, t)`` run as ordinary sampled estimators: the one home
for sampling a continuous-time observer (the linear ones of :mod:`jaxobs.observers.ct_linear` and the modular
estimator of :mod:`jaxobs.observers.modular` are right-hand sides run here).

Step ``k`` integrates the observer over ``[t_{k-1}, t_k]`` with ``u_{k-1}`` held (:func:`jaxobs.ct.integrate`) and
the measurement held or interpolated (``measurement="hold"`` or ``"linear"``); :func:`make_continuous_observer`,
:data:`continuous_observer`. Timing and missing data: docs/theory/estimators.md.
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
    """A continuous-time observer (``m`` inputs, ``p`` outputs); build it with :func:`make_continuous_observer`.

    Attributes:
      F: the observer ``F(x_hat, u, y, t) -> dx_hat/dt`` (a pytree like ``x0``), a ``jax.tree_util.Partial`` (its
        bound arguments, e.g. gains and model parameters, are leaves: ``grad`` and ``vmap`` reach them).
      h: its output ``h(x_hat, u) -> y_hat`` (p,), a ``Partial`` likewise.
      x0: estimate at ``t0``, an (n,) array or a pytree of arrays.  dt: () sample period.  t0: () time of the
        first sample.  n_inputs: static ``m``.  substeps: static fixed steps per sample.  method: static ``"rk4"``
        or ``"euler"``.  measurement: static ``"hold"`` or ``"linear"`` (the measurement between samples).
    """

    F: Callable
    h: Callable
    x0: jax.Array
    dt: jax.Array
    t0: jax.Array
    n_inputs: int = dataclasses.field(default=0, metadata=dict(static=True))
    substeps: int = dataclasses.field(default=1, metadata=dict(static=True))
    method: str = dataclasses.field(default="rk4", metadata=dict(static=True))
    measurement: str = dataclasses.field(default="hold", metadata=dict(static=True))

    @property
    def dtype(self):
        """The floating dtype of the estimate."""
        return jnp.result_type(*jax.tree_util.tree_leaves(self.x0))

    @property
    def n_outputs(self) -> int:
        """Number of measured outputs ``p`` (from the shape of ``h``)."""
        return jax.eval_shape(self.h, self.x0, jnp.zeros((self.n_inputs,), self.dtype)).shape[0]


class ContinuousObserverState(NamedTuple):
    """State of a continuous-time observer run as a sampled estimator.

    Attributes:
      x: estimate x_hat(t_{k-1}) (the pytree of x0)
      y: (p,) measurement y_{k-1} (NaN where missing)
      t: () t_{k-1}
      started: () bool: a sample has been processed (the next step integrates)
      missing: () int32, measurement components skipped so far
    """

    x: jax.Array
    y: jax.Array
    t: jax.Array
    started: jax.Array
    missing: jax.Array


class ContinuousObserverOutputs(NamedTuple):
    """Outputs of one sample of a continuous-time observer.

    Attributes:
      x: estimate x_hat(t_k) (the pytree of x0)
      innovation: (p,) y_k - h(x_hat(t_k), u_{k-1}) (0 for missing components)
    """

    x: jax.Array
    innovation: jax.Array


def make_continuous_observer(F, h, *, x0, dt, t0=0.0, n_inputs: int = 0, substeps: int = 1, method: str = "rk4",
                             measurement: str = "hold") -> ContinuousObserverParams:  # fmt: skip
    """Build and check :class:`ContinuousObserverParams`.

    Args:
      F: the observer ``F(x_hat, u, y, t)`` returning ``dx_hat/dt`` of the structure and shapes of ``x0`` (a
        function or a ``Partial``).
      h: its output map ``h(x_hat, u)`` (p,) (a function or a ``Partial``).
      x0: estimate at ``t0``: an (n,) array or a pytree of arrays.  dt: sample period (> 0).  t0: time of the
        first sample.  n_inputs: the number of inputs ``m``.  substeps: fixed steps per sample.  method:
        ``"rk4"`` or ``"euler"``.  measurement: ``"hold"`` (zero-order) or ``"linear"`` (first-order
        interpolation between the samples).

    Example: a double-integrator observer with poles at -2, -2 fed a constant position of 1 for 6 s.

      >>> import jax.numpy as jnp
      >>> import jaxobs as jo
      >>> F = lambda x, u, y, t: jnp.array([x[1], 0.0]) + jnp.array([4.0, 4.0]) * (y[0] - x[0])
      >>> params = jo.make_continuous_observer(F, lambda x, u: x[:1], x0=jnp.zeros(2), dt=0.01)
      >>> _, out = jo.run(jo.continuous_observer, params, jo.EstimatorInputs(y=jnp.ones((600, 1))))
      >>> bool(jnp.abs(out.x[-1, 0] - 1.0) < 1e-3)
      True
    """
    F, h = _checks.function("F", F), _checks.function("h", h)
    if not isinstance(x0, (dict, tuple)):  # a pytree estimate, e.g. (x_hat, P); anything else is a vector
        x0 = jnp.atleast_1d(jnp.asarray(x0))
        _checks.shape("x0", x0, (None,), "the initial estimate, one entry per state")
    leaves = jax.tree_util.tree_leaves(x0)
    dtype = _checks.float_dtype(dt=dt, t0=t0, **{f"x0[{i}]": leaf for i, leaf in enumerate(leaves)})
    for leaf in leaves:
        _checks.finite("x0", leaf)
    _checks.positive_scalar("dt", dt)
    x0 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), x0)
    dt, t0 = jnp.asarray(dt, dtype), jnp.asarray(t0, dtype)
    _checks.shape("dt", dt, (), "a scalar sample period")
    _checks.shape("t0", t0, (), "a scalar time")
    n_inputs = _checks.count("n_inputs", n_inputs, hint="the size of the input u of F(x_hat, u, y, t)")
    substeps = _checks.count("substeps", substeps, minimum=1, hint="fixed integration steps per sample")
    if method not in ct.METHODS:
        raise ValueError(f"method must be one of {sorted(ct.METHODS)}, got {method!r}")
    if measurement not in ("hold", "linear"):
        raise ValueError(f"measurement must be 'hold' or 'linear', got {measurement!r}")
    u = jnp.zeros((n_inputs,), dtype)
    _checks.returns("h(x_hat, u)", h, (x0, u), (None,), "the output estimate, a vector")
    y = jnp.zeros(jax.eval_shape(h, x0, u).shape, dtype)
    _check_rate(F, (x0, u, y, t0), x0)
    return ContinuousObserverParams(F, h, x0, dt, t0, n_inputs, substeps, method, measurement)


def _check_rate(F, args, x0) -> None:
    """``F(*args)`` must return a pytree of the structure, shapes and dtypes of ``x0`` (checked abstractly)."""
    try:
        out = jax.eval_shape(F, *args)
    except Exception as exc:  # the user's function failed on arguments of the expected shapes
        raise ValueError(f"F(x_hat, u, y, t) failed on x_hat, u, y, t of the shapes of x0, u, y: {exc}") from exc
    spec = lambda tree: jax.tree_util.tree_map(lambda a: (tuple(jnp.shape(a)), str(jnp.result_type(a))), tree)
    if spec(out) != spec(x0):
        raise ValueError(
            f"F(x_hat, u, y, t) must return dx_hat/dt with the structure, shapes and dtypes of x0: x0 is {spec(x0)}, "
            f"F returned {spec(out)}"
        )


def _init(params: ContinuousObserverParams) -> ContinuousObserverState:
    _checks.fields("params", params, "dt (), t0 ()")
    y = jnp.full((params.n_outputs,), jnp.nan, params.dtype)
    return ContinuousObserverState(params.x0, y, params.t0, jnp.zeros((), bool), jnp.zeros((), jnp.int32))


def _step(params: ContinuousObserverParams, state: ContinuousObserverState, inputs: EstimatorInputs):
    _checks.fields("params", params, "dt (), t0 ()")
    dtype, p, m = params.dtype, params.n_outputs, params.n_inputs
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per output of h", check_finite=False)
    if inputs.u_prev is None:
        if m:
            raise ValueError(f"inputs.u_prev is required: the observer has n_inputs={m}, got None")
        u = jnp.zeros((0,), dtype)
    else:
        u = _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype, what="n_inputs entries", check_finite=False)
    observed = jnp.isfinite(y)
    if params.measurement == "linear":  # the line from y_{k-1} to y_k, where both ends are measured
        used = jnp.isfinite(state.y) & observed
        start, end = jnp.where(used, state.y, 0.0), jnp.where(used, y, 0.0)
        measured = lambda t: start + (t - state.t) / params.dt * (end - start)
    else:
        used = jnp.isfinite(state.y)
        measured = lambda t: jnp.where(used, state.y, 0.0)

    def rhs(x, u, t):  # a missing channel sees the observer's own prediction
        return params.F(x, u, jnp.where(used, measured(t), params.h(x, u)), t)

    x_next = ct.integrate(rhs, state.x, u, state.t, params.dt, substeps=params.substeps, method=params.method)
    x = jax.tree_util.tree_map(lambda a, b: jnp.where(state.started, a, b), x_next, state.x)
    t = jnp.where(state.started, state.t + params.dt, state.t)
    innovation = jnp.where(observed, jnp.where(observed, y, 0.0) - params.h(x, u), 0.0)
    missing = state.missing + jnp.sum(~observed).astype(jnp.int32)
    return ContinuousObserverState(x, y, t, jnp.ones((), bool), missing), ContinuousObserverOutputs(x, innovation)


continuous_observer = Estimator(_init, _step)
"""A continuous-time observer run as a sampled :class:`~jaxobs.observers.base.Estimator` over
:class:`ContinuousObserverParams`.

Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (p,) and (m,) (``u_prev=None`` without inputs). Outputs:
:class:`ContinuousObserverOutputs`."""
