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
        extra = n - self.Phi.shape[-1]
        if extra < 0:
            raise ValueError(f"n must be >= {self.Phi.shape[-1]}, got {n}")
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
    x, u = state
    x1 = params.Phi @ x + params.Gamma @ u
    x = x1 + params.K @ (jnp.atleast_1d(inputs.y) - params.C @ x1)
    u = jnp.atleast_1d(inputs.r) - params.L @ x
    return (x, u), LinearControllerOutputs(u, x)


linear_controller = Observer(_linear_init, _linear_step)
""":class:`LinearController` in the (init, step) protocol, for :func:`simulate`."""


class ClosedLoopTrace(NamedTuple):
    """Time series of a closed-loop run (leading axis: time)."""

    y: jax.Array  # noisy measurements y_k
    y_true: jax.Array  # noise-free outputs C x_k
    u: jax.Array  # commands u_k
    x: jax.Array  # true plant states x_k
    controller: object  # the controller's outputs (e.g. ActiveObserverOutputs)


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

    Args:
      plant: true discrete plant (``plant.dt`` set), e.g. ``c2d`` of the mismatched model.
      controller_params: parameters of ``controller`` (built on the nominal model).
      reference: (T, m) or (T,) references ``r_k``.
      disturbance: (T, m) or (T,) input disturbance ``d_k`` (default zero).
      noise: (T, p) or (T,) measurement noise ``v_k`` (default zero; see :func:`measurement_noise`).
      x0: initial true state (default zero).
      controller: an (init, step) pair whose step takes ``ActiveObserverInputs(y, r)`` and whose
        outputs have a field ``u``.
    """
    if not plant.is_discrete:
        raise ValueError("plant must be discrete (use jaxobs.lti.c2d)")
    if _checks.is_concrete(plant.D) and np.any(np.asarray(plant.D) != 0):
        raise ValueError("plant.D must be zero: a feedthrough would close an algebraic loop through u_k")
    m, p = plant.n_inputs, plant.n_outputs
    reference = jnp.asarray(reference, plant.A.dtype).reshape(-1, m)
    T = reference.shape[0]
    disturbance = jnp.zeros((T, m), plant.A.dtype) if disturbance is None else jnp.asarray(disturbance).reshape(T, m)
    noise = jnp.zeros((T, p), plant.A.dtype) if noise is None else jnp.asarray(noise).reshape(T, p)
    x0 = jnp.zeros((plant.n_states,), plant.A.dtype) if x0 is None else jnp.asarray(x0)

    def body(carry, inputs):
        x, ctrl_state = carry
        r, d, v = inputs
        y_true = plant.C @ x
        y = y_true + v
        ctrl_state, out = controller.step(controller_params, ctrl_state, ActiveObserverInputs(y, r))
        u = out.u
        x_next = plant.A @ x + plant.B @ (u + d)
        return (x_next, ctrl_state), ClosedLoopTrace(y, y_true, u, x, out)

    carry = (x0, controller.init(controller_params))
    _, trace = jax.lax.scan(body, carry, (reference, disturbance, noise))
    return trace


def ideal_response(plant: StateSpace, L, reference) -> jax.Array:
    """Output of the desired closed loop ``x_k = (Phi - Gamma L) x_{k-1} + Gamma r_{k-1}``
    (seed 000 eq. 25/43) without disturbance or noise: what the AOB aims to impose."""
    m = plant.n_inputs
    reference = jnp.asarray(reference, plant.A.dtype).reshape(-1, m)
    A_cl = plant.A - plant.B @ jnp.atleast_2d(L)

    def body(x, r):
        return A_cl @ x + plant.B @ r, plant.C @ x + plant.D @ r

    _, y = jax.lax.scan(body, jnp.zeros((plant.n_states,), plant.A.dtype), reference)
    return y


def measurement_noise(key, num_steps: int, R) -> jax.Array:
    """Gaussian measurement noise with covariance ``R``: shape (num_steps, p)."""
    R = jnp.atleast_2d(jnp.asarray(R))
    chol = jnp.linalg.cholesky(R)
    return jax.random.normal(key, (num_steps, R.shape[0]), R.dtype) @ chol.T


def rms(error, axis=0):
    """Root-mean-square over ``axis``."""
    return jnp.sqrt(jnp.mean(jnp.square(error), axis=axis))
