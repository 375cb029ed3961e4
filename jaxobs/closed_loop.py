"""Closed-loop simulation: a true discrete plant (which may differ from the observer's nominal
model) under observer-based state feedback, with an input disturbance and measurement noise, in
one ``lax.scan``. Batch it with ``vmap`` over plants, mismatches, Q/R settings and noise seeds.

:func:`simulate` runs the loop ``y_k = C x_k + v_k``, ``u_k = controller(y_k, r_k)``,
``x_{k+1} = A x_k + B (u_k + d_k)`` (Cortesão 2006 eq. 81: ``d_k`` at the plant input); :func:`measurement_noise`
draws the noise. Timing and dead time: docs/theory/analysis.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.lti import StateSpace
from jaxobs.observers.base import Controller, ControllerInputs

__all__ = ["ClosedLoopTrace", "simulate", "ideal_response", "measurement_noise", "rms"]


class ClosedLoopTrace(NamedTuple):
    """Time series of a closed-loop run (leading axis: time).

    Attributes:
      y: (T, p) noisy measurements y_k
      y_true: (T, p) noise-free outputs C x_k
      u: (T, m) commands u_k
      x: (T, n) true plant states x_k
      controller: the controller's outputs stacked over time (e.g. FeedbackOutputs)
    """

    y: jax.Array
    y_true: jax.Array
    u: jax.Array
    x: jax.Array
    controller: object


def _series(name: str, value, num_steps: int | None, size: int, dtype, what: str) -> jax.Array:
    """A per-sample input as ``(T, size)`` in ``dtype``: shape ``(T, size)``, or ``(T,)`` when ``size`` is 1
    (``T = num_steps`` unless None). Shapes checked at trace time (never reshaped or broadcast otherwise),
    finiteness where concrete."""
    value = jnp.asarray(value)
    T = value.shape[0] if num_steps is None and value.ndim else num_steps
    if size == 1 and value.ndim == 1:
        value = value[:, None]
    _checks.shape(name, value, (T, size), what)
    _checks.finite(name, value)
    return value.astype(dtype)


# what feeds each input of the controller in simulate: a shape error names that argument
_SOURCES = {
    "inputs.r": "reference: each row is the controller's",
    "inputs.y": "plant: its outputs are the controller's",
}


def _controller_step(controller: Controller, params, state, inputs: ControllerInputs):
    """``controller.step``; a shape error of its inputs (raised while tracing) is re-raised naming the argument of
    :func:`simulate` that feeds them."""
    try:
        return controller.step(params, state, inputs)
    except ValueError as error:
        field = str(error).split(" ", 1)[0]
        if field in _SOURCES:
            raise ValueError(f"{_SOURCES[field]} {field}, and {error}") from error
        raise


def simulate(
    plant: StateSpace,
    controller: Controller,
    params,
    reference,
    *,
    disturbance=None,
    noise=None,
    x0=None,
) -> ClosedLoopTrace:
    """Simulate ``plant`` under ``controller`` for ``len(reference)`` samples.

    Shapes are checked against the plant at trace time (also under ``jit``); a reference or plant that does not fit
    the controller's inputs raises ``ValueError`` naming ``reference`` or ``plant``. The plant runs in the common
    floating dtype of its matrices and the series (the controller casts its inputs to its own dtype).

    Args:
      plant: true discrete plant (``plant.dt`` set), e.g. ``c2d`` of the mismatched model.
      controller: any :class:`~jaxobs.observers.base.Controller` (e.g.
        :data:`jaxobs.observers.active.active_observer_controller`) whose outputs have ``u`` of shape (m,).
      params: the controller's parameters (built on the nominal model).
      reference: (T, q) references ``r_k`` as the controller takes them (``q = m`` without a reference pre-gain;
        (T,) for ``q = 1``).
      disturbance: (T, m) input disturbance ``d_k`` (or (T,) for one input; default zero).
      noise: (T, p) measurement noise ``v_k`` (or (T,) for one output; default zero; see
        :func:`measurement_noise`).
      x0: (n,) initial true state (default zero).

    Returns:
      :class:`ClosedLoopTrace` (leading axis time).

    Example:
      >>> import jax.numpy as jnp
      >>> from jaxobs.lti import ss, c2d
      >>> from jaxobs.design import acker
      >>> from jaxobs.observers import FeedbackParams, active
      >>> plant = c2d(ss([[0, 1], [0, -31.25]], [[0], [93.75]], [[1, 0]]), 0.008, delay=0.04)
      >>> L_r = acker(plant.A, plant.B, [0.975, 0.975, 0, 0, 0, 0, 0])
      >>> aob = active.make_aob(plant, order=1, R=2.1e-2, steady_state=True)
      >>> params = FeedbackParams(aob, active.feedback_gain(aob, L_r))
      >>> trace = simulate(plant, active.active_observer_controller, params, jnp.full(100, L_r[0, 0] * 10.0))
      >>> trace.y_true.shape
      (100, 1)
    """
    if not StateSpace.check(plant, "plant").is_discrete:
        raise ValueError("plant must be discrete (use jaxobs.lti.c2d)")
    if _checks.is_concrete(plant.D) and np.any(np.asarray(plant.D) != 0):
        raise ValueError("plant.D must be zero: a feedthrough would close an algebraic loop through u_k")
    n, m, p = plant.n_states, plant.n_inputs, plant.n_outputs
    dtype = _checks.float_dtype(
        **{"plant.A": plant.A, "plant.B": plant.B, "plant.C": plant.C}, reference=reference, disturbance=disturbance,
        noise=noise, x0=x0,
    )  # fmt: skip
    A, B, C = (jnp.asarray(M, dtype) for M in (plant.A, plant.B, plant.C))
    reference = jnp.asarray(reference)
    reference = reference[:, None] if reference.ndim == 1 else reference
    _checks.shape("reference", reference, (None, None), "(T, q): one reference vector per sample")
    _checks.finite("reference", reference)
    T = reference.shape[0]
    zeros = lambda size: jnp.zeros((T, size), dtype)
    per_sample = f"one entry per plant input and sample of reference (T = {T})"
    disturbance = zeros(m) if disturbance is None else _series("disturbance", disturbance, T, m, dtype, per_sample)
    per_sample = f"one entry per plant output and sample of reference (T = {T})"
    noise = zeros(p) if noise is None else _series("noise", noise, T, p, dtype, per_sample)
    x0 = jnp.zeros((n,), dtype) if x0 is None else _checks.vector("x0", x0, n, dtype, what="one entry per plant state")

    def body(carry, inputs):
        x, ctrl_state = carry
        r, d, v = inputs
        y_true = C @ x
        y = y_true + v
        ctrl_state, out = _controller_step(controller, params, ctrl_state, ControllerInputs(y, r))
        _checks.shape("params", out.u, (m,), f"the controller's command u must have one entry per plant input, {m}")
        u = out.u.astype(dtype)
        x_next = A @ x + B @ (u + d)
        return (x_next, ctrl_state), ClosedLoopTrace(y, y_true, u, x, out)

    carry = (x0, controller.init(params))
    _, trace = jax.lax.scan(body, carry, (reference, disturbance, noise))
    return trace


def ideal_response(plant: StateSpace, L, reference) -> jax.Array:
    """Output (T, p) of the desired closed loop ``x_k = (Phi - Gamma L) x_{k-1} + Gamma r_{k-1}``
    (Cortesão 2006, eq. 25/43) without disturbance or noise: what the AOB aims to impose. ``L`` (m, n),
    ``reference`` (T, m) (or (T,) for one input); computed in the common floating dtype."""
    n, m = StateSpace.check(plant, "plant").n_states, plant.n_inputs
    L = jnp.atleast_2d(jnp.asarray(L))
    _checks.matrix("L", L, shape=(m, n))
    dtype = _checks.float_dtype(**{"plant.A": plant.A, "plant.B": plant.B, "plant.C": plant.C, "plant.D": plant.D},
                                L=L, reference=reference)  # fmt: skip
    reference = _series("reference", reference, None, m, dtype, "one reference per plant input and sample")
    A, B, C, D = (jnp.asarray(M, dtype) for M in (plant.A, plant.B, plant.C, plant.D))
    A_cl = A - B @ L.astype(dtype)

    def body(x, r):
        return A_cl @ x + B @ r, C @ x + D @ r

    _, y = jax.lax.scan(body, jnp.zeros((n,), dtype), reference)
    return y


def measurement_noise(key, num_steps: int, R) -> jax.Array:
    """Gaussian measurement noise with covariance ``R`` (p, p), positive definite: ``num_steps`` samples drawn
    from the PRNG ``key``, shape (num_steps, p).

    Example:
      >>> import jax
      >>> measurement_noise(jax.random.PRNGKey(0), 100, [[2.1e-2]]).shape
      (100, 1)
    """
    num_steps = _checks.count("num_steps", num_steps)
    R = jnp.atleast_2d(jnp.asarray(R))
    _checks.covariance("R", R, definite=True)
    chol = jnp.linalg.cholesky(R.astype(_checks.float_dtype(R=R)))
    return jax.random.normal(key, (num_steps, R.shape[0]), chol.dtype) @ chol.T


def rms(error, axis=0):
    """Root-mean-square of ``error`` over ``axis`` (default 0, the time axis of a trace): ``sqrt(mean(error^2))``."""
    (error,) = _checks.float_arrays(error=error)
    return jnp.sqrt(jnp.mean(jnp.square(error), axis=axis))
