"""The modular parameter and perturbation estimator of Grip 2010 ch. 5 (Grip, Johansen, Imsland & Kaasa 2010) for
systems with nonlinearly parameterised perturbations and a measured state::

    x' = f(t, x) + B(t, x) (g(t, x, theta) + v(t, x))                                   (5.1)

with ``x`` (n,) measured, ``B`` (n, m), ``g`` (m,) known up to the constant ``theta`` (p,), ``v`` (m,) a known input.
Two modules: a parameter update law ``theta_hat' = u_theta(t, x, phi_hat, theta_hat)`` (5.2), designed as if the
full perturbation ``phi = B g(t, x, theta)`` were measured, and the perturbation estimator (5.8)::

    z'      = -K_phi (f + B v + phi_hat) - B (dg/dtheta)(t, x, theta_hat) u_theta          (5.8a, b)
    phi_hat = z + K_phi x + B g(t, x, theta_hat)                                          (5.8c)

equivalently, with ``x_hat = -K_phi^{-1} z`` (Grip 2010 §5.7), a state observer ``x_hat' = f + B v + phi_hat +
K_phi^{-1} B (dg/dtheta) u_theta`` with ``phi_hat = K_phi (x - x_hat) + B g(t, x, theta_hat)``. Its errors
``phi_tilde = phi - phi_hat``, ``theta_tilde = theta - theta_hat`` obey (5.11)::

    phi_tilde'   = -K_phi phi_tilde + d(t, x, theta_tilde),   d = d/dt [B (g(theta) - g(theta_hat))]|theta_hat fixed
    theta_tilde' = -u_theta(t, x, phi_hat, theta_hat)                                      (5.10, 5.11)

The update laws (``law``), all through the projection of App. 5.A (:func:`jaxobs.adaptive.project`) and with
``phi_hat`` saturated to known bounds inside ``u_theta`` (Remark 5.2):

* ``"inversion"`` (Prop. 5.1): ``Proj(Gamma (theta*(t, x, phi_hat) - theta_hat))``, ``theta*`` the user's inverse of
  ``phi = B g(t, x, theta)``;
* ``"intermittent"`` (Prop. 5.2): ``Proj(l(t, x) Gamma (theta* - theta_hat))`` with ``l`` in [0, 1], where
  ``theta*`` needs to exist only where ``l > 0``;
* ``"gradient"`` (Props. 5.3, 5.4): ``Proj(Gamma M(t, x, theta_hat) (phi_hat - B g(t, x, theta_hat)))``, ``M``
  (p, n) by default ``(dg/dtheta)' B'`` (Remark 5.1: steepest descent of ``|B (g(theta) - g(theta_hat))|^2``);
* ``"custom"``: ``Proj(Gamma direction(t, x, phi_hat, theta_hat))`` for laws that combine the above per parameter
  (Example 5.5) or are designed by hand (the drilling estimator's (5.26)-(5.27)).

``dg/dtheta`` and ``d`` come from automatic differentiation. The compensation ``v = -g(t, x, theta_hat)`` (5.15) is
:func:`compensation`. The estimator runs on sampled measurements through :mod:`jaxobs.observers.continuous`
(``x`` and the applied input held over each sample); a non-finite component of ``x`` is replaced by the estimate
``x_hat`` (no injection in that channel), skipped and counted.
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
    "LAWS",
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

LAWS = ("inversion", "intermittent", "gradient", "custom")
"""The parameter update laws: Grip 2010 Prop. 5.1, Prop. 5.2, Props. 5.3/5.4, and a user direction."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ModularModel:
    """The plant (5.1) and the design of the modular estimator (``n`` states, ``m`` perturbation channels, ``p``
    parameters, ``r`` applied inputs); build it with :func:`make_modular`.

    Attributes:
      f: ``f(t, x)`` (n,).  B: ``B(t, x)`` (n, m).  g: ``g(t, x, theta)`` (m,).  v: ``v(t, x, u)`` (m,), the known
        input (``u`` (r,) the applied input of the sample), or ``None`` (no known input).
        theta_star: ``theta*(t, x, phi)`` (p,) or ``None``.  l: ``l(t, x)`` () in [0, 1] or ``None``.
        M: ``M(t, x, theta_hat)`` (p, n) or ``None`` (Remark 5.1).  direction: ``direction(t, x, phi,
        theta_hat)`` (p,) or ``None``.  (All ``jax.tree_util.Partial``: bound
        arguments are leaves.)
      K_phi: (n, n) symmetric positive-definite injection gain.  Gamma: (p, p) symmetric positive-definite
        adaptation gain.  region: the smooth convex ``P`` of the projection set (:class:`jaxobs.adaptive.Ball`,
        :class:`jaxobs.adaptive.Box`) or ``None`` (no projection).  epsilon: () boundary-layer width.
      phi_lower, phi_upper: (n,) saturation bounds of ``phi_hat`` in ``u_theta`` (infinite: none).
      law: static, one of :data:`LAWS`.
    """

    f: Callable
    B: Callable
    g: Callable
    v: Callable
    theta_star: Callable | None
    l: Callable | None
    M: Callable | None
    direction: Callable | None
    K_phi: jax.Array
    Gamma: jax.Array
    region: Callable | None
    epsilon: jax.Array
    phi_lower: jax.Array
    phi_upper: jax.Array
    law: str = dataclasses.field(default="gradient", metadata=dict(static=True))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ModularParams:
    """The modular estimator: its ``model`` (:class:`ModularModel`) and ``sampled``, the
    :class:`~jaxobs.observers.continuous.ContinuousObserverParams` that run :func:`modular_rate` on samples."""

    model: ModularModel
    sampled: ContinuousObserverParams


class ModularState(NamedTuple):
    z: jax.Array  # (n,) the perturbation estimator's state of (5.8)
    theta_hat: jax.Array  # (p,) parameter estimate


class ModularOutputs(NamedTuple):
    x: jax.Array  # (n,) x_hat = -K_phi^{-1} z at the sample
    theta_hat: jax.Array  # (p,) parameter estimate
    phi_hat: jax.Array  # (n,) perturbation estimate (5.8c), unsaturated
    innovation: jax.Array  # (n,) x_k - x_hat (0 for missing components)


def _phi_hat(model: ModularModel, state: ModularState, t, x):
    return state.z + model.K_phi @ x + model.B(t, x) @ model.g(t, x, state.theta_hat)


def perturbation_estimate(model: ModularModel, state: ModularState, t, x):
    """``phi_hat = z + K_phi x + B(t, x) g(t, x, theta_hat)`` (5.8c), (n,), for the measured ``x`` (n,) at ``t``."""
    return _phi_hat(model, state, t, x)


def parameter_rate(model: ModularModel, t, x, phi_hat, theta_hat):
    """The update law ``u_theta(t, x, phi_hat, theta_hat)`` (p,) of ``model.law`` (Grip 2010 Props. 5.1-5.4), with
    ``phi_hat`` (n,) saturated to ``[phi_lower, phi_upper]`` and the projection of App. 5.A."""
    phi = jnp.clip(phi_hat, model.phi_lower, model.phi_upper)
    if model.law == "gradient":
        Bm = model.B(t, x)
        if model.M is None:  # Remark 5.1: (dg/dtheta)' B'
            M = (Bm @ jax.jacfwd(model.g, argnums=2)(t, x, theta_hat)).T
        else:
            M = model.M(t, x, theta_hat)
        tau = model.Gamma @ (M @ (phi - Bm @ model.g(t, x, theta_hat)))
    elif model.law == "custom":
        tau = model.Gamma @ model.direction(t, x, phi, theta_hat)
    else:
        star = model.theta_star(t, x, phi)
        if model.law == "intermittent":
            weight = jnp.clip(model.l(t, x), 0, 1)
            tau = weight * (model.Gamma @ jnp.where(weight > 0, star - theta_hat, 0))
        else:
            tau = model.Gamma @ (star - theta_hat)
    if model.region is None:
        return tau
    return adaptive.project(tau, theta_hat, model.Gamma, model.region, model.epsilon)


def modular_rate(model: ModularModel, state: ModularState, u, x, t) -> ModularState:
    """The right-hand side ``(z', theta_hat')`` of the estimator (5.8) for the measured state ``x`` (n,) and the
    applied input ``u`` (r,) at time ``t`` (``dg/dtheta u_theta`` by a Jacobian-vector product)."""
    phi_hat = _phi_hat(model, state, t, x)
    u_theta = parameter_rate(model, t, x, phi_hat, state.theta_hat)
    Bm = model.B(t, x)
    g_dot = jax.jvp(lambda th: model.g(t, x, th), (state.theta_hat,), (u_theta,))[1]
    known = model.f(t, x) if model.v is None else model.f(t, x) + Bm @ model.v(t, x, u)
    z_dot = -model.K_phi @ (known + phi_hat) - Bm @ g_dot
    return ModularState(z_dot, u_theta)


def perturbation_error_rate(model: ModularModel, t, x, x_dot, theta, theta_hat):
    """``d(t, x, theta_tilde)`` of (5.10): the time derivative of ``B(t, x) (g(t, x, theta) - g(t, x, theta_hat))``
    along ``x' = x_dot`` (n,) with ``theta`` (p,) and ``theta_hat`` (p,) fixed (one Jacobian-vector product)."""
    gap = lambda s, y: model.B(s, y) @ (model.g(s, y, theta) - model.g(s, y, theta_hat))
    t = jnp.asarray(t, x.dtype)
    return jax.jvp(gap, (t, x), (jnp.ones_like(t), x_dot))[1]


def compensation(model: ModularModel, theta_hat, t, x):
    """The compensating input ``v = -g(t, x, theta_hat)`` (m,) of (5.15)."""
    return -model.g(t, x, theta_hat)


def _x_hat(model: ModularModel, state: ModularState, u):
    del u
    return -jnp.linalg.solve(model.K_phi, state.z)


def _applied_input(t, x, u):
    del t, x
    return u


def make_modular(f, B, g, *, theta0, K_phi, Gamma, dt, law: str = "gradient", v=None, n_inputs: int = 0,
                 theta_star=None, l=None, M=None, direction=None, region=None, epsilon=0.1, phi_bounds=None,
                 z0=None, t0=0.0, substeps: int = 1, method: str = "rk4", n=None) -> ModularParams:  # fmt: skip
    """Params of the modular estimator (Grip 2010 eq. 5.8) with the checks.

    Args:
      f: ``f(t, x)`` (n,).  B: ``B(t, x)`` (n, m).  g: ``g(t, x, theta)`` (m,).
      theta0: (p,) initial estimate, inside the projection set ``{region <= epsilon}``.
      K_phi: positive scalar or (n, n) symmetric positive definite.  Gamma: positive scalar or (p, p) SPD.
      dt: sample period (> 0).  law: ``"inversion"``, ``"intermittent"``, ``"gradient"`` or ``"custom"``
        (:data:`LAWS`).
      v: known input ``v(t, x, u)`` (m,) given the applied input ``u`` (``n_inputs``,) of the sample (held over
        it); default ``v = u`` when ``n_inputs = m`` (e.g. the compensation :func:`compensation` applied by a
        controller) and ``v = 0`` when ``n_inputs = 0``.
      n_inputs: the size of ``u`` (default 0).
      theta_star: ``theta*(t, x, phi)`` (p,), the inverse of ``phi = B g(t, x, theta)`` (inversion laws).
      l: ``l(t, x)`` () in [0, 1] (``"intermittent"``).  M: ``M(t, x, theta_hat)`` (p, n) (``"gradient"``;
        default Remark 5.1's ``(dg/dtheta)' B'``).  direction: ``direction(t, x, phi, theta_hat)`` (p,), the
        unprojected rate before ``Gamma`` (``"custom"``).
      region: the projection set's smooth convex ``P`` (e.g. ``jaxobs.adaptive.Box``) or ``None``.
      epsilon: its boundary layer (> 0).  phi_bounds: ``(lower, upper)`` (n,) saturation of ``phi_hat`` or ``None``.
      z0: (n,) initial ``z`` (default 0).  t0: time of the first sample.  substeps, method: the integration
        (:func:`jaxobs.ct.integrate`) per sample.  n: the state size (default: the size of ``z0``, else of
        ``K_phi`` when a matrix; required otherwise).

    Example: ``x' = -x + theta`` with ``theta = 2`` from ``x(0) = 0`` (so ``x = 2 (1 - exp(-t))``), sampled every
    10 ms; the inversion law (Prop. 5.1, ``theta* = phi``) finds ``theta`` within 5 s.

      >>> import jax.numpy as jnp
      >>> import jaxobs as jo
      >>> params = jo.make_modular(lambda t, x: -x, lambda t, x: jnp.eye(1), lambda t, x, th: th, theta0=[0.0],
      ...     K_phi=10.0, Gamma=5.0, dt=0.01, n=1, law="inversion", theta_star=lambda t, x, phi: phi)
      >>> x = 2.0 * (1 - jnp.exp(-0.01 * jnp.arange(500)))[:, None]
      >>> _, out = jo.run(jo.modular_estimator, params, jo.EstimatorInputs(y=x))
      >>> bool(jnp.abs(out.theta_hat[-1, 0] - 2.0) < 1e-3)
      True
    """
    if law not in LAWS:
        raise ValueError(f"law must be one of {LAWS}, got {law!r}")
    f, B, g = (_checks.function(name, fn) for name, fn in (("f", f), ("B", B), ("g", g)))
    theta0 = jnp.atleast_1d(jnp.asarray(theta0))
    _checks.shape("theta0", theta0, (None,), "the initial parameter estimate, a vector")
    dtype = _checks.float_dtype(theta0=theta0, K_phi=K_phi, Gamma=Gamma, dt=dt, t0=t0, z0=z0)
    theta0 = theta0.astype(dtype)
    _checks.finite("theta0", theta0)
    p = theta0.shape[0]
    if n is None:
        if z0 is not None:
            n = jnp.shape(z0)[0]
        elif jnp.ndim(K_phi) == 2:
            n = jnp.shape(K_phi)[0]
        else:
            raise ValueError("n is required: the state size follows from z0 or a matrix K_phi, neither was given")
    n = _checks.count("n", n, minimum=1, hint="the size of the measured state x")
    K_phi, Gamma = _checks.gain("K_phi", K_phi, n, dtype), _checks.gain("Gamma", Gamma, p, dtype)
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
    if law in ("inversion", "intermittent"):
        if theta_star is None:
            raise ValueError(f"theta_star is required by law={law!r}: the inverse theta*(t, x, phi) of phi = B g")
        theta_star = _checks.function("theta_star", theta_star)
        _checks.returns("theta_star(t, x, phi)", theta_star, (t_, x_, x_), (p,), "one entry per parameter")
    if law == "intermittent":
        if l is None:
            raise ValueError("l is required by law='intermittent': the weight l(t, x) in [0, 1] of Prop. 5.2")
        l = _checks.function("l", l)
        _checks.returns("l(t, x)", l, (t_, x_), (), "a scalar weight in [0, 1]")
    if law == "custom":
        if direction is None:
            raise ValueError("direction is required by law='custom': the rate direction(t, x, phi, theta_hat)")
        direction = _checks.function("direction", direction)
        _checks.returns("direction(t, x, phi, theta_hat)", direction, (t_, x_, x_, theta0), (p,), "one per parameter")
    if M is not None:
        M = _checks.function("M", M)
        _checks.returns("M(t, x, theta_hat)", M, (t_, x_, theta0), (p, n), "a (p, n) matrix")
    epsilon = jnp.asarray(epsilon, dtype)
    _checks.positive_scalar("epsilon", epsilon)
    if region is not None:
        if not callable(region):
            raise ValueError(f"region must be a callable P(theta) -> (), e.g. jaxobs.adaptive.Box, got {region!r}")
        _checks.returns("region(theta)", region, (theta0,), (), "the scalar P(theta) of the projection set")
        value = region(theta0)
        if _checks.is_concrete(value, epsilon) and not float(value) <= float(epsilon):
            raise ValueError(
                f"theta0 must lie in the projection set {{P(theta) <= epsilon = {float(epsilon):.6g}}}, got "
                f"P(theta0) = {float(value):.6g}"
            )
    lower, upper = (-jnp.inf, jnp.inf) if phi_bounds is None else phi_bounds
    lower = jnp.broadcast_to(jnp.asarray(lower, dtype), (n,))
    upper = jnp.broadcast_to(jnp.asarray(upper, dtype), (n,))
    if _checks.is_concrete(lower, upper) and not bool(jnp.all(lower < upper)):
        raise ValueError("phi_bounds must be (lower, upper) with lower < upper in every entry")
    model = ModularModel(f, B, g, v, theta_star, l, M, direction, K_phi, Gamma, region, epsilon, lower, upper, law)
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
