"""The modular parameter and perturbation estimator of Grip 2010 ch. 5 (Grip, Johansen, Imsland & Kaasa 2010).

For ``x' = f(t, x) + B(t, x) (g(t, x, theta) + v(t, x))`` (5.1) with ``x`` measured, a parameter update law of
:mod:`jaxobs.adaptive` (5.2) and the perturbation estimator (5.8) estimate ``theta`` and ``phi = B g``. Build it
with :func:`make_modular`, run it as :data:`modular_estimator` on samples (through
:mod:`jaxobs.observers.continuous`); :func:`modular_rate`, :func:`parameter_rate`, :func:`perturbation_estimate`
and :func:`perturbation_error_rate` expose its equations and :func:`compensation` the input ``v = -g`` (5.15).
The equations: docs/theory/adaptive.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks, adaptive
from jaxobs.observers.base import Estimator, EstimatorInputs
from jaxobs.observers.continuous import (
    ContinuousObserverParams,
    ContinuousObserverState,
    continuous_observer,
    make_continuous_observer,
)

__all__ = [
    "ModularModel",
    "ModularParams",
    "ModularState",
    "ModularOutputs",
    "make_modular",
    "modular_estimator",
    "modular_rate",
    "parameter_rate",
    "perturbation_estimate",
    "perturbation_error_rate",
    "compensation",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ModularModel:
    """The plant (5.1) and the design of the modular estimator (``n`` states, ``m`` perturbation channels,
    ``n_theta`` parameters, ``r`` applied inputs); build it with :func:`make_modular`.

    Attributes:
      f: ``f(t, x)`` (n,).  B: ``B(t, x)`` (n, m).  g: ``g(t, x, theta)`` (m,).  v: ``v(t, x, u)`` (m,), the known
        input (``u`` (r,) the applied input of the sample), or ``None`` (no known input).  (All
        ``jax.tree_util.Partial``: bound arguments are leaves.)
      law: the update law (:class:`~jaxobs.adaptive.InversionLaw`,
        :class:`~jaxobs.adaptive.PerturbationGradientLaw`, :class:`~jaxobs.adaptive.CustomLaw`).
      K_phi: (n, n) symmetric positive-definite injection gain.
      phi_lower, phi_upper: (n,) saturation bounds of ``phi_hat`` in ``u_theta`` (infinite: none).
    """

    f: Callable
    B: Callable
    g: Callable
    v: Callable | None
    law: Callable
    K_phi: jax.Array
    phi_lower: jax.Array
    phi_upper: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ModularParams:
    """The modular estimator: its ``model`` (:class:`ModularModel`) and ``sampled``, the
    :class:`~jaxobs.observers.continuous.ContinuousObserverParams` that run :func:`modular_rate` on samples."""

    model: ModularModel
    sampled: ContinuousObserverParams


class ModularState(NamedTuple):
    """The continuous state of the modular estimator.

    Attributes:
      z: (n,) the perturbation estimator's state of (5.8).
      theta_hat: (n_theta,) the parameter estimate.
    """

    z: jax.Array
    theta_hat: jax.Array


class ModularOutputs(NamedTuple):
    """Per-sample outputs of :data:`modular_estimator`.

    Attributes:
      x: (n,) ``x_hat = -K_phi^{-1} z`` at the sample.
      theta_hat: (n_theta,) the parameter estimate.
      phi_hat: (n,) the perturbation estimate (5.8c), unsaturated.
      innovation: (n,) ``x_k - x_hat`` (0 for missing components).
    """

    x: jax.Array
    theta_hat: jax.Array
    phi_hat: jax.Array
    innovation: jax.Array


_ARGUMENT_SHAPES = {
    "u": "(r,)",
    "x": "(n,)",
    "x_dot": "(n,)",
    "phi_hat": "(n,)",
    "theta": "(s,)",
    "theta_hat": "(s,)",
    "t": "()",
    "state.z": "(n,)",
    "state.theta_hat": "(s,)",
}


def _arguments(model: ModularModel, **values) -> tuple:
    """``model`` checked to be one (``K_phi`` (n, n), bounds (n,), no batch axis) and ``values`` (named as the
    arguments) as arrays of its dtype with their shapes checked at trace time (lists and scalars accepted)."""
    n = _checks.fields("model", model, "K_phi (n, n), phi_lower (n,), phi_upper (n,)")["n"]
    arrays = _checks.float_arrays(**values)
    _checks.shapes(", ".join(f"{name} {_ARGUMENT_SHAPES[name]}" for name in values).replace("(n,)", f"({n},)"),
                   *arrays)  # fmt: skip
    return tuple(None if a is None else a.astype(model.K_phi.dtype) for a in arrays)


def _phi_hat(model: ModularModel, state: ModularState, t, x):
    return state.z + model.K_phi @ x + model.B(t, x) @ model.g(t, x, state.theta_hat)


def perturbation_estimate(model: ModularModel, state: ModularState, t, x):
    """``phi_hat = z + K_phi x + B(t, x) g(t, x, theta_hat)`` (5.8c), (n,), for the measured ``x`` (n,) at ``t``."""
    z, theta_hat, t, x = _arguments(model, **{"state.z": state.z, "state.theta_hat": state.theta_hat}, t=t, x=x)
    return _phi_hat(model, ModularState(z, theta_hat), t, x)


def _perturbation_model(model: ModularModel, t, x, theta):
    return model.B(t, x) @ model.g(t, x, theta)


def parameter_rate(model: ModularModel, t, x, phi_hat, theta_hat):
    """The update law ``u_theta(t, x, phi_hat, theta_hat)`` (n_theta,) of ``model.law`` (Grip 2010 Props.
    5.1-5.4), with ``phi_hat`` (n,) saturated to ``[phi_lower, phi_upper]`` (Remark 5.2)."""
    t, x, phi_hat, theta_hat = _arguments(model, t=t, x=x, phi_hat=phi_hat, theta_hat=theta_hat)
    phi = jnp.clip(phi_hat, model.phi_lower, model.phi_upper)
    return model.law(jax.tree_util.Partial(_perturbation_model, model), (t, x), phi, theta_hat)


def modular_rate(model: ModularModel, state: ModularState, u, x, t) -> ModularState:
    """The right-hand side ``(z', theta_hat')`` of the estimator (5.8) for the measured state ``x`` (n,) and the
    applied input ``u`` (r,) at time ``t`` (``dg/dtheta u_theta`` by a Jacobian-vector product)."""
    z, theta_hat, u, t, x = _arguments(model, **{"state.z": state.z, "state.theta_hat": state.theta_hat}, u=u, t=t,
                                       x=x)  # fmt: skip
    state = ModularState(z, theta_hat)
    phi_hat = _phi_hat(model, state, t, x)
    u_theta = parameter_rate(model, t, x, phi_hat, state.theta_hat)
    Bm = model.B(t, x)
    g_dot = jax.jvp(lambda th: model.g(t, x, th), (state.theta_hat,), (u_theta,))[1]
    known = model.f(t, x) if model.v is None else model.f(t, x) + Bm @ model.v(t, x, u)
    z_dot = -model.K_phi @ (known + phi_hat) - Bm @ g_dot
    return ModularState(z_dot, u_theta)


def perturbation_error_rate(model: ModularModel, t, x, x_dot, theta, theta_hat):
    """``d(t, x, theta_tilde)`` of (5.10): the time derivative of ``B(t, x) (g(t, x, theta) - g(t, x, theta_hat))``
    along ``x' = x_dot`` (n,) with ``theta`` (n_theta,) and ``theta_hat`` (n_theta,) fixed (one Jacobian-vector
    product)."""
    t, x, x_dot, theta, theta_hat = _arguments(model, t=t, x=x, x_dot=x_dot, theta=theta, theta_hat=theta_hat)
    gap = lambda s, y: model.B(s, y) @ (model.g(s, y, theta) - model.g(s, y, theta_hat))
    return jax.jvp(gap, (t, x), (jnp.ones_like(t), x_dot))[1]


def compensation(model: ModularModel, theta_hat, t, x):
    """The compensating input ``v = -g(t, x, theta_hat)`` (m,) of (5.15); ``theta_hat`` (n_theta,), ``x`` (n,)."""
    theta_hat, t, x = _arguments(model, theta_hat=theta_hat, t=t, x=x)
    return -model.g(t, x, theta_hat)


def _x_hat(model: ModularModel, state: ModularState, u):
    del u
    return -jnp.linalg.solve(model.K_phi, state.z)


def _applied_input(t, x, u):
    del t, x
    return u


def make_modular(f, B, g, *, theta0, K_phi, law, dt, v=None, n_inputs: int = 0, phi_bounds=None, z0=None,
                 t0=0.0, substeps: int = 1, method: str = "rk4", n=None) -> ModularParams:  # fmt: skip
    """Params of the modular estimator (Grip 2010 eq. 5.8) with the checks.

    Args:
      f: ``f(t, x)`` (n,).  B: ``B(t, x)`` (n, m).  g: ``g(t, x, theta)`` (m,).
      theta0: (n_theta,) initial estimate, inside the projection set of ``law`` (if any).
      K_phi: positive scalar or (n, n) symmetric positive definite.
      law: the update law, a law object of :mod:`jaxobs.adaptive` called as ``law(B g, (t, x), phi_hat,
        theta_hat)``: :class:`~jaxobs.adaptive.InversionLaw` (Props. 5.1, 5.2; ``theta_star(t, x, phi)``,
        ``weight(t, x, phi)``), :class:`~jaxobs.adaptive.PerturbationGradientLaw` (Props. 5.3, 5.4; ``M(t, x,
        theta_hat)`` (n_theta, n), default Remark 5.1's ``(dg/dtheta)' B'``) or :class:`~jaxobs.adaptive.CustomLaw`.
      dt: sample period (> 0).
      v: known input ``v(t, x, u)`` (m,) given the applied input ``u`` (``n_inputs``,) of the sample (held over
        it); default ``v = u`` when ``n_inputs = m`` (e.g. the compensation :func:`compensation` applied by a
        controller) and ``v = 0`` when ``n_inputs = 0``.
      n_inputs: the size of ``u`` (default 0).
      phi_bounds: ``(lower, upper)`` (n,) saturation of ``phi_hat`` or ``None``.
      z0: (n,) initial ``z`` (default 0).  t0: time of the first sample.  substeps, method: the integration
        (:func:`jaxobs.ct.integrate`) per sample.  n: the state size (default: the size of ``z0``, else of
        ``K_phi`` when a matrix; required otherwise).

    Example: ``x' = -x + theta`` with ``theta = 2`` from ``x(0) = 0`` (so ``x = 2 (1 - exp(-t))``), sampled every
    10 ms; the inversion law (Prop. 5.1, ``theta* = phi``) finds ``theta`` within 5 s.

      >>> import jax.numpy as jnp
      >>> import jaxobs as jo
      >>> law = jo.adaptive.InversionLaw(lambda t, x, phi: phi, adaptation_gain=5.0)
      >>> params = jo.make_modular(lambda t, x: -x, lambda t, x: jnp.eye(1), lambda t, x, th: th, theta0=[0.0],
      ...     K_phi=10.0, law=law, dt=0.01, n=1)
      >>> x = 2.0 * (1 - jnp.exp(-0.01 * jnp.arange(500)))[:, None]
      >>> _, out = jo.run(jo.modular_estimator, params, jo.EstimatorInputs(y=x))
      >>> bool(jnp.abs(out.theta_hat[-1, 0] - 2.0) < 1e-3)
      True
    """
    f, B, g = (_checks.function(name, fn) for name, fn in (("f", f), ("B", B), ("g", g)))
    theta0 = jnp.atleast_1d(jnp.asarray(theta0))
    _checks.shape("theta0", theta0, (None,), "the initial parameter estimate, a vector")
    dtype = _checks.float_dtype(theta0=theta0, K_phi=K_phi, dt=dt, t0=t0, z0=z0)
    theta0 = theta0.astype(dtype)
    _checks.finite("theta0", theta0)
    n_theta = theta0.shape[0]
    if n is None:
        if z0 is not None:
            n = jnp.shape(z0)[0]
        elif jnp.ndim(K_phi) == 2:
            n = jnp.shape(K_phi)[0]
        else:
            raise ValueError("n is required: the state size follows from z0 or a matrix K_phi, neither was given")
    n = _checks.count("n", n, minimum=1, hint="the size of the measured state x")
    K_phi = _checks.gain("K_phi", K_phi, n, dtype)
    z0 = jnp.zeros(n, dtype) if z0 is None else _checks.vector("z0", z0, n, dtype)
    t_, x_ = jnp.zeros((), dtype), jnp.zeros(n, dtype)
    _checks.returns("f(t, x)", f, (t_, x_), (n,), "dx/dt's known part, one entry per state")
    _checks.returns("B(t, x)", B, (t_, x_), (n, None), "the perturbation's input matrix, one row per state")
    m = jax.eval_shape(B, t_, x_).shape[1]
    _checks.returns("g(t, x, theta)", g, (t_, x_, theta0), (m,), "the perturbation, one entry per column of B")
    n_inputs = _checks.count("n_inputs", n_inputs, hint="the size of the applied input u")
    if v is None:
        if n_inputs not in (0, m):
            raise ValueError(f"n_inputs must be 0 (v = 0) or {m} (v = u) when v is not given, got {n_inputs}")
        v = _applied_input if n_inputs else None
    if v is not None:
        v = _checks.function("v", v)
        _checks.returns("v(t, x, u)", v, (t_, x_, jnp.zeros(n_inputs, dtype)), (m,), "the known input, m entries")
    adaptive.check_law(law, theta0)
    lower, upper = (-jnp.inf, jnp.inf) if phi_bounds is None else phi_bounds
    lower = jnp.broadcast_to(jnp.asarray(lower, dtype), (n,))
    upper = jnp.broadcast_to(jnp.asarray(upper, dtype), (n,))
    if _checks.is_concrete(lower, upper) and not bool(jnp.all(lower < upper)):
        raise ValueError("phi_bounds must be (lower, upper) with lower < upper in every entry")
    model = ModularModel(f, B, g, v, law, K_phi, lower, upper)
    _checks.returns("law(B g, (t, x), phi_hat, theta_hat)", lambda t, x, th: parameter_rate(model, t, x, x, th),
                    (t_, x_, theta0), (n_theta,), "theta_hat_dot, one entry per parameter")  # fmt: skip
    part = jax.tree_util.Partial
    sampled = make_continuous_observer(part(modular_rate, model), part(_x_hat, model), x0=ModularState(z0, theta0),
                                       dt=dt, t0=t0, n_inputs=n_inputs, substeps=substeps, method=method)  # fmt: skip
    return ModularParams(model, sampled)


def _init(params: ModularParams) -> ContinuousObserverState:
    return continuous_observer.init(params.sampled)


def _step(params: ModularParams, state: ContinuousObserverState, inputs: EstimatorInputs):
    state, out = continuous_observer.step(params.sampled, state, inputs)
    estimate = ModularState(*out.x)
    x_hat = _x_hat(params.model, estimate, None)
    x = jnp.where(jnp.isfinite(state.y), state.y, x_hat)  # a missing component: the estimate (no injection)
    phi_hat = _phi_hat(params.model, estimate, state.t, x)
    return state, ModularOutputs(x_hat, estimate.theta_hat, phi_hat, out.innovation)


modular_estimator = Estimator(_init, _step)
"""The modular estimator (Grip 2010 eq. 5.8) as an :class:`~jaxobs.observers.base.Estimator` over
:class:`ModularParams`: inputs ``EstimatorInputs(y=x_k, u_prev=u_{k-1})`` (``u_prev=None`` without inputs), outputs
:class:`ModularOutputs`; ``state.missing`` counts the skipped measurement components."""
