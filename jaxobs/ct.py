"""Continuous-time models as sampled systems: fixed-step explicit integrators over pytrees.

A model ``f(x, u, t) -> dx/dt`` sampled with period ``h`` and the input held over each sample becomes the discrete
map ``x(t + h) = integrate(f, x(t), u, t, h)`` (:func:`integrate`; :func:`trajectory` over many samples), computed
with ``substeps`` fixed steps of explicit Euler or classical Runge-Kutta 4 (Kutta 1901) in one ``lax.scan``; pure
under ``jit``, ``vmap`` and ``grad``, with ``checkpoint=True`` to recompute the substeps in reverse mode.
Derivation and error orders: docs/theory/nonlinear.md; speed against diffrax: ``benchmarks/ct_integration.py``.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from jaxobs import _checks

__all__ = ["euler_step", "rk4_step", "integrate", "discretize", "trajectory", "METHODS"]


def _axpy(a, x, y):
    """``y + a x`` over matching pytrees."""
    return jax.tree_util.tree_map(lambda xi, yi: yi + a * xi, x, y)


def euler_step(f: Callable, x, u, t, dt):
    """One explicit Euler step ``x + dt f(x, u, t)`` (``x`` a pytree, ``t`` and ``dt`` scalars)."""
    _checks.shapes("t (), dt ()", t, dt)
    return _axpy(dt, f(x, u, t), x)


def rk4_step(f: Callable, x, u, t, dt):
    """One step of the classical fourth-order Runge-Kutta rule (``x`` a pytree, ``t`` and ``dt`` scalars, ``u``
    held)."""
    _checks.shapes("t (), dt ()", t, dt)
    half = dt / 2
    k1 = f(x, u, t)
    k2 = f(_axpy(half, k1, x), u, t + half)
    k3 = f(_axpy(half, k2, x), u, t + half)
    k4 = f(_axpy(dt, k3, x), u, t + dt)
    slope = jax.tree_util.tree_map(lambda a, b, c, d: a + 2 * b + 2 * c + d, k1, k2, k3, k4)
    return _axpy(dt / 6, slope, x)


METHODS = {"euler": euler_step, "rk4": rk4_step}
"""The fixed-step rules by name: ``"euler"`` (order 1, one evaluation of ``f`` per substep) and ``"rk4"``
(order 4, four evaluations)."""


def _settings(substeps, method) -> tuple[int, Callable]:
    substeps = _checks.count("substeps", substeps, minimum=1, hint="the number of fixed steps per sample")
    if method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {method!r}")
    return substeps, METHODS[method]


def _check_state(f, x, u, t) -> None:
    """``f(x, u, t)`` must return a pytree of the structure, shapes and dtypes of ``x`` (checked abstractly)."""
    out = jax.eval_shape(f, x, u, t)
    want = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)), x)
    if jax.tree_util.tree_structure(out) != jax.tree_util.tree_structure(want) or any(
        (o.shape, o.dtype) != (w.shape, w.dtype)
        for o, w in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(want), strict=True)
    ):
        shapes = lambda tree: jax.tree_util.tree_map(lambda a: f"{a.dtype}{list(a.shape)}", tree)
        raise ValueError(
            f"f(x, u, t) must return dx/dt with the structure, shapes and dtypes of x: x is {shapes(want)}, "
            f"f returned {shapes(out)}"
        )


def integrate(f: Callable, x, u, t, h, *, substeps: int = 1, method: str = "rk4", checkpoint: bool = False):
    """The state ``x(t + h)`` of ``x' = f(x, u, t)`` from ``x(t) = x``, with ``u`` held over the interval.

    Args:
      f: the model ``f(x, u, t) -> dx/dt``, a pytree of the structure, shapes and dtypes of ``x`` (checked
        abstractly with ``jax.eval_shape`` when the call is traced).
      x: the state at ``t`` (an array or a pytree of arrays).
      u: the input held over ``[t, t + h]`` (any pytree ``f`` accepts, or ``None``).
      t: () start time.  h: () length of the interval (may be traced, e.g. to differentiate by it).
      substeps: number of fixed steps (a static integer >= 1).
      method: ``"rk4"`` (default) or ``"euler"`` (:data:`METHODS`).
      checkpoint: recompute the substeps in reverse mode instead of storing them (``jax.checkpoint``).

    Example:
      >>> import jax.numpy as jnp
      >>> from jaxobs import ct
      >>> x1 = ct.integrate(lambda x, u, t: -x + u, jnp.array([1.0]), 0.0, 0.0, 1.0, substeps=20)
      >>> bool(jnp.abs(x1[0] - jnp.exp(-1.0)) < 1e-7)
      True
    """
    substeps, rule = _settings(substeps, method)
    dtype = jnp.result_type(*jax.tree_util.tree_leaves(x), float)
    t, h = jnp.asarray(t, dtype), jnp.asarray(h, dtype)
    _checks.shape("t", t, (), "a scalar time")
    _checks.shape("h", h, (), "a scalar interval")
    _check_state(f, x, u, t)

    def run(x, u, t, h):
        dt = h / substeps

        def body(x, i):
            return rule(f, x, u, t + i * dt, dt), None

        return jax.lax.scan(body, x, jnp.arange(substeps, dtype=dtype))[0]

    if checkpoint:
        run = jax.checkpoint(run)
    return run(x, u, t, h)


def discretize(f: Callable, h, *, substeps: int = 1, method: str = "rk4", checkpoint: bool = False) -> Callable:
    """The sampled model ``f_d(x, u, t) = x(t + h)`` of ``x' = f(x, u, t)`` under a zero-order hold of ``u``:
    a discrete-time transition in the signature of the discrete filters. Arguments as :func:`integrate`."""
    _settings(substeps, method)
    return lambda x, u, t: integrate(f, x, u, t, h, substeps=substeps, method=method, checkpoint=checkpoint)


def trajectory(f: Callable, x0, u, *, h, t0=0.0, substeps: int = 1, method: str = "rk4", checkpoint: bool = False):
    """The sampled trajectory of ``x' = f(x, u, t)`` under the held inputs ``u``: one ``lax.scan`` over samples.

    Args:
      f: the model ``f(x, u, t) -> dx/dt``.  x0: the state at ``t0``.
      u: inputs with a leading axis of ``T`` samples; ``u[k]`` is held over ``[t0 + k h, t0 + (k + 1) h]``.
      h: () sample period.  t0: () start time.  substeps, method, checkpoint: as :func:`integrate`.

    Returns:
      the states at ``t0, t0 + h, ..., t0 + T h``: every leaf of ``x0`` stacked along a new leading axis of
      length ``T + 1``.
    """
    step = discretize(f, h, substeps=substeps, method=method, checkpoint=checkpoint)
    dtype = jnp.result_type(*jax.tree_util.tree_leaves(x0), float)
    lengths = {jnp.shape(leaf)[0] if jnp.ndim(leaf) else None for leaf in jax.tree_util.tree_leaves(u)}
    if len(lengths) != 1 or None in lengths:
        raise ValueError(f"u must have one leading time axis shared by all its arrays, got leading sizes {lengths}")
    T = lengths.pop()
    times = jnp.asarray(t0, dtype) + jnp.asarray(h, dtype) * jnp.arange(T, dtype=dtype)

    def body(x, inputs):
        u_k, t_k = inputs
        x_next = step(x, u_k, t_k)
        return x_next, x_next

    _, xs = jax.lax.scan(body, x0, (u, times))
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([jnp.asarray(a)[None], b]), x0, xs)
