"""A masked observability-Gramian reconstruction as an estimator (the observer of Grip 2010, ch. 8, sampled).

The state of ``x' = A x + B u``, ``y = sat(C x)`` is reconstructed by least squares from the outputs that are
not saturated (each channel weighted by ``1 - |y_i|``, the masked Gramian of (8.5)), in an information form
transported to the current sample so that it can run forever; the estimate ``Y^{-1} q`` is returned once
``cond(Y) <= cond_max``. :func:`make_gramian`, :data:`gramian_estimator`. The recursion:
docs/theory/estimators.md.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.observers.base import Estimator, EstimatorInputs

__all__ = ["GramianParams", "GramianState", "GramianOutputs", "make_gramian", "gramian_estimator", "WEIGHTS"]

WEIGHTS = ("saturation", "valid")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GramianParams:
    """Parameters of the masked-Gramian estimator; build with :func:`make_gramian`.

    Attributes:
      Phi: (n, n) ``exp(A dt)``.  Phi_inv: (n, n) ``exp(-A dt)``.  Gamma: (n, m) zero-order-hold input matrix.
      C: (p, n).  dt: () sample period.  forget: () ``exp(-lambda dt)``.  level: (p,) saturation levels.
      cond_max: () largest condition number inverted.  x0: (n,) the estimate before the Gramian is ready.
      weights: static ``"saturation"`` or ``"valid"``.
    """

    Phi: jax.Array
    Phi_inv: jax.Array
    Gamma: jax.Array
    C: jax.Array
    dt: jax.Array
    forget: jax.Array
    level: jax.Array
    cond_max: jax.Array
    x0: jax.Array
    weights: str = dataclasses.field(metadata=dict(static=True))


class GramianState(NamedTuple):
    """State of :data:`gramian_estimator` between steps.

    Attributes:
      Y: (n, n) information matrix (masked Gramian in current-state coordinates)
      q: (n,) information vector, Y x = q for consistent data
      x: (n,) the last estimate
    """

    Y: jax.Array
    q: jax.Array
    x: jax.Array


class GramianOutputs(NamedTuple):
    """Outputs of one step of :data:`gramian_estimator`.

    Attributes:
      x: (n,) Y^{-1} q when ready, else the open-loop prediction
      innovation: (p,) y - C x_prior (0 for a missing entry)
      ready: () bool: cond(Y) <= cond_max
      condition: () condition number of Y (inf while singular)
      weights: (p,) the weights w_i of this sample
    """

    x: jax.Array
    innovation: jax.Array
    ready: jax.Array
    condition: jax.Array
    weights: jax.Array


def make_gramian(A, B, C, *, dt, forgetting=0.0, weights: str = "saturation", level=1.0, cond_max=1e10, x0=None):
    """Build :class:`GramianParams` from the continuous-time plant.

    Args:
      A: (n, n).  B: (n, m) (``m`` may be 0).  C: (p, n).  dt: () sample period ``> 0``.
      forgetting: () ``lambda >= 0`` (1/s); 0 is the thesis's (8.5), without forgetting.
      weights: ``"saturation"`` (``w_i = 1 - |y_i| / level_i``) or ``"valid"`` (1 for every finite sample).
      level: () or (p,) saturation level(s) ``> 0``.  cond_max: () ``> 1``.  x0: (n,) estimate before ready.

    Example:
      >>> import jax.numpy as jnp
      >>> from jaxobs.observers import EstimatorInputs, run
      >>> params = make_gramian([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], dt=0.1)
      >>> t = 0.1 * jnp.arange(5.0)
      >>> y = (0.2 + 0.5 * t)[:, None]  # x1 = 0.2 + 0.5 t, x2 = 0.5, never saturated
      >>> _, out = run(gramian_estimator, params, EstimatorInputs(y=y, u_prev=jnp.zeros((5, 1))))
      >>> bool(out.ready[-1]), [round(float(v), 6) for v in out.x[-1]]
      (True, [0.4, 0.5])
    """
    _checks.matrix("A", A, square=True)
    dtype = _checks.float_dtype(A=A, B=B, C=C)
    A, B, C = (jnp.asarray(M, dtype) for M in (A, B, C))
    n = A.shape[0]
    _checks.matrix("B", B, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    _checks.positive_scalar("dt", dt)
    _checks.positive_scalar("forgetting", forgetting, allow_zero=True)
    _checks.positive_scalar("cond_max", cond_max)
    if weights not in WEIGHTS:
        raise ValueError(f"weights must be one of {WEIGHTS}, got {weights!r}")
    p, m = C.shape[0], B.shape[1]
    level = _checks.per_entry("level", level, p, dtype, "the saturation level of each output")
    if _checks.is_concrete(level) and np.any(np.asarray(level) <= 0):
        raise ValueError(f"level must be positive, got {np.asarray(level)}")
    x0 = jnp.zeros(n, dtype) if x0 is None else _checks.vector("x0", x0, n, dtype)
    dt = jnp.asarray(dt, dtype)
    big = jnp.zeros((n + m, n + m), dtype).at[:n, :n].set(A).at[:n, n:].set(B)
    E = jax.scipy.linalg.expm(big * dt)
    Phi, Gamma = E[:n, :n], E[:n, n:]
    forget = jnp.exp(-jnp.asarray(forgetting, dtype) * dt)
    Phi_inv = jax.scipy.linalg.expm(-A * dt)
    return GramianParams(Phi, Phi_inv, Gamma, C, dt, forget, level, jnp.asarray(cond_max, dtype), x0, weights)


_SHAPES = "Phi (n, n), Phi_inv (n, n), Gamma (n, m), C (p, n), dt (), forget (), level (p,), cond_max (), x0 (n,)"


def _init(params: GramianParams) -> GramianState:
    _checks.fields("params", params, _SHAPES)
    n = params.Phi.shape[0]
    # x carries the estimate at the previous sample; one step back from x0 so that the first prediction is x0
    return GramianState(jnp.zeros((n, n), params.Phi.dtype), jnp.zeros(n, params.Phi.dtype), params.Phi_inv @ params.x0)


def _step(params: GramianParams, state: GramianState, inputs: EstimatorInputs):
    _checks.fields("params", params, _SHAPES)
    n, p, m = params.Phi.shape[0], params.C.shape[0], params.Gamma.shape[1]
    dtype = params.Phi.dtype
    y = _checks.vector("inputs.y", inputs.y, p, dtype, check_finite=False)
    u = jnp.zeros(m, dtype) if inputs.u_prev is None else _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype)
    valid = jnp.isfinite(y)
    y0 = jnp.where(valid, y, 0)
    if params.weights == "saturation":
        w = jnp.maximum(0, 1 - jnp.abs(y0) / params.level)
    else:
        w = jnp.ones(p, dtype)
    w = jnp.where(valid, w, 0)
    Pi = params.Phi_inv
    Y = params.forget * Pi.T @ state.Y @ Pi + params.dt * (params.C.T * w) @ params.C
    q = params.forget * Pi.T @ (state.q + state.Y @ (Pi @ (params.Gamma @ u))) + params.dt * params.C.T @ (w * y0)
    Y = (Y + Y.T) / 2
    eig = jnp.linalg.eigvalsh(Y)
    condition = jnp.where(eig[0] > 0, eig[-1] / jnp.where(eig[0] > 0, eig[0], 1), jnp.inf)
    ready = (condition <= params.cond_max) & jnp.all(jnp.isfinite(Y))
    x_prior = params.Phi @ state.x + params.Gamma @ u
    x = jnp.where(ready, jnp.linalg.solve(jnp.where(ready, Y, jnp.eye(n, dtype=dtype)), q), x_prior)
    innovation = jnp.where(valid, y0 - params.C @ x_prior, 0)
    return GramianState(Y, q, x), GramianOutputs(x, innovation, ready, condition, w)


gramian_estimator = Estimator(init=_init, step=_step)
"""The masked observability-Gramian estimator (:func:`make_gramian`)."""
