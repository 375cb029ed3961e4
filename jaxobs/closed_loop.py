"""Closed-loop simulation: a true discrete plant (which may differ from the observer's nominal
model) under observer-based state feedback, with an input disturbance and measurement noise, in
one ``lax.scan``. Batch it with ``vmap`` over plants, mismatches, Q/R settings and noise seeds.

At each sample ``k``::

    y_k     = C x_k + v_k                          (strictly proper plant: D = 0)
    u_k     = controller(y_k, r_k)                 (e.g. the AOB of jaxobs.observers.active)
    x_{k+1} = A x_k + B (u_k + d_k)                (d_k: disturbance at the plant input, eq. 81)

For a delay-augmented plant from :func:`jaxobs.lti.c2d` the disturbance enters with the command,
before the dead time; the true plant's dead time may differ from the nominal one (pad with
``n_delay``).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.lti import StateSpace
from jaxobs.observers.active import ActiveObserverInputs, ActiveObserverParams, _active_mask, active_observer
from jaxobs.observers.base import Observer

__all__ = [
    "ClosedLoopTrace",
    "simulate",
    "ideal_response",
    "measurement_noise",
    "rms",
    "LinearController",
    "linear_controller",
    "linear_controller_of",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LinearController:
    """A fixed-gain observer with state feedback: ``x_hat_k = x1 + K (y_k - C x1)`` with
    ``x1 = Phi x_hat_{k-1} + Gamma u_{k-1}`` and ``u_k = r_k - L x_hat_k`` (seed 000 eq. 26, 49-50).

    An AOB or CKF with steady-state gains is one (:func:`linear_controller_of`). All orders share
    one shape after :meth:`padded` (zero states that never move), so designs of different orders
    can be stacked and ``vmap``ped together.
    """

    Phi: jax.Array
    Gamma: jax.Array
    C: jax.Array
    K: jax.Array
    L: jax.Array

    def padded(self, n: int) -> LinearController:
        """The same controller with ``n`` observer states (extra states are identically zero)."""
        extra = _checks.count("n", n, minimum=self.Phi.shape[-1]) - self.Phi.shape[-1]
        rows = lambda M: jnp.pad(M, ((0, extra), (0, 0)))
        cols = lambda M: jnp.pad(M, ((0, 0), (0, extra)))
        return LinearController(rows(cols(self.Phi)), rows(self.Gamma), cols(self.C), rows(self.K), cols(self.L))


def linear_controller_of(params: ActiveObserverParams) -> LinearController:
    """The steady-state AOB/CKF as a :class:`LinearController`. With the active state switched off
    (``set_active(params, 0)``) its rows are zeroed and the passive gain used, as the run-time
    switch does."""
    if params.gain is None:
        raise ValueError("params: a linear controller needs steady-state gains; use with_steady_state_gains")
    mask = _active_mask(params)[:, None]
    gain = jnp.where(params.active > 0, params.gain, params.gain_passive)
    return LinearController(mask * params.Phi, mask * params.Gamma, params.C, mask * gain, params.L)


class LinearControllerOutputs(NamedTuple):
    u: jax.Array
    x: jax.Array


def _linear_init(params: LinearController):
    return jnp.zeros(params.Phi.shape[-1], params.Phi.dtype), jnp.zeros(params.Gamma.shape[-1], params.Phi.dtype)


def _linear_step(params: LinearController, state, inputs: ActiveObserverInputs):
    m, p, dtype = params.Gamma.shape[-1], params.C.shape[-2], params.Phi.dtype
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    r = _checks.vector("inputs.r", inputs.r, m, dtype, what="one entry per column of Gamma", check_finite=False)
    x, u = state
    x1 = params.Phi @ x + params.Gamma @ u
    x = x1 + params.K @ (y - params.C @ x1)
    u = r - params.L @ x
    return (x, u), LinearControllerOutputs(u, x)


linear_controller = Observer(_linear_init, _linear_step)
""":class:`LinearController` in the (init, step) protocol, for :func:`simulate`; inputs ``ActiveObserverInputs(y, r)``
of shapes ``(p,)`` and ``(m,)``, checked and cast as by the observer families."""


class ClosedLoopTrace(NamedTuple):
    """Time series of a closed-loop run (leading axis: time)."""

    y: jax.Array  # noisy measurements y_k
    y_true: jax.Array  # noise-free outputs C x_k
    u: jax.Array  # commands u_k
    x: jax.Array  # true plant states x_k
    controller: object  # the controller's outputs (e.g. ActiveObserverOutputs)


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


def simulate(
    plant: StateSpace,
    controller_params,
    reference,
    *,
    disturbance=None,
    noise=None,
    x0=None,
    controller: Observer = active_observer,
) -> ClosedLoopTrace:
    """Simulate ``plant`` under ``controller`` for ``len(reference)`` samples.

    Shapes are checked against the plant at trace time (also under ``jit``); the plant runs in the common
    floating dtype of its matrices and the series (the controller casts its inputs to its own dtype).

    Args:
      plant: true discrete plant (``plant.dt`` set), e.g. ``c2d`` of the mismatched model.
      controller_params: parameters of ``controller`` (built on the nominal model).
      reference: (T, m) references ``r_k`` (or (T,) for a single-input plant).
      disturbance: (T, m) input disturbance ``d_k`` (or (T,) for one input; default zero).
      noise: (T, p) measurement noise ``v_k`` (or (T,) for one output; default zero; see
        :func:`measurement_noise`).
      x0: (n,) initial true state (default zero).
      controller: an (init, step) pair whose step takes ``ActiveObserverInputs(y, r)`` and whose
        outputs have a field ``u`` of shape (m,).
    """
    if not plant.is_discrete:
        raise ValueError("plant must be discrete (use jaxobs.lti.c2d)")
    if _checks.is_concrete(plant.D) and np.any(np.asarray(plant.D) != 0):
        raise ValueError("plant.D must be zero: a feedthrough would close an algebraic loop through u_k")
    n, m, p = plant.n_states, plant.n_inputs, plant.n_outputs
    dtype = _checks.float_dtype(
        **{"plant.A": plant.A, "plant.B": plant.B, "plant.C": plant.C}, reference=reference, disturbance=disturbance,
        noise=noise, x0=x0,
    )  # fmt: skip
    A, B, C = (jnp.asarray(M, dtype) for M in (plant.A, plant.B, plant.C))
    reference = _series("reference", reference, None, m, dtype, "one reference per plant input and sample")
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
        ctrl_state, out = controller.step(controller_params, ctrl_state, ActiveObserverInputs(y, r))
        _checks.shape("controller_params", out.u, (m,), f"the controller's command u must have one entry per plant "
                      f"input, {m}")  # fmt: skip
        u = out.u.astype(dtype)
        x_next = A @ x + B @ (u + d)
        return (x_next, ctrl_state), ClosedLoopTrace(y, y_true, u, x, out)

    carry = (x0, controller.init(controller_params))
    _, trace = jax.lax.scan(body, carry, (reference, disturbance, noise))
    return trace


def ideal_response(plant: StateSpace, L, reference) -> jax.Array:
    """Output (T, p) of the desired closed loop ``x_k = (Phi - Gamma L) x_{k-1} + Gamma r_{k-1}``
    (Cortesão 2006, eq. 25/43) without disturbance or noise: what the AOB aims to impose. ``L`` (m, n),
    ``reference`` (T, m) (or (T,) for one input); computed in the common floating dtype."""
    n, m = plant.n_states, plant.n_inputs
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
    """Gaussian measurement noise with covariance ``R`` (p, p), positive definite: shape (num_steps, p)."""
    num_steps = _checks.count("num_steps", num_steps)
    R = jnp.atleast_2d(jnp.asarray(R))
    _checks.covariance("R", R, definite=True)
    chol = jnp.linalg.cholesky(R.astype(_checks.float_dtype(R=R)))
    return jax.random.normal(key, (num_steps, R.shape[0]), chol.dtype) @ chol.T


def rms(error, axis=0):
    """Root-mean-square over ``axis``."""
    return jnp.sqrt(jnp.mean(jnp.square(error), axis=axis))
