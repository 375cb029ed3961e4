"""Nonlinear Gaussian state-space models and the filter step the extended and unscented Kalman filters share.

:func:`nonlinear_model` builds a :class:`NonlinearModel`: discrete time ``x_k = f(x_{k-1}, u_{k-1}, t_{k-1}) + w_k``
or continuous-discrete (``continuous=True``), with ``y_k = h(x_k) + v_k`` (``h(x_k, u_{k-1})`` with
``feedthrough``). A state or a measurement on a :class:`Manifold` (rotations, a MuJoCo ``qpos`` with quaternions)
has its errors, covariances and noise in the tangent space: ``+`` is its ``retract`` and ``-`` its ``difference``
(the error-state form of Sola 2017). A Gaussian filter replaces each map by a :class:`Linearization` (Särkkä 2013,
ch. 5-6) and takes the linear Kalman step of :mod:`jaxobs.kalman_steps` (:func:`gaussian_step`), with missing data,
an optional innovation gate and iterated updates (Bell & Cathey 1993; García-Fernández et al. 2015). Each step
outputs its log-likelihood and, with ``output_covariance``, the linearised transition the extended and unscented
RTS smoothers reuse (:func:`jaxobs.smoothing.smooth`; Särkkä 2008, 2013). The equations: docs/theory/nonlinear.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp

from jaxobs import _checks, ct
from jaxobs._linalg import symmetrize
from jaxobs.kalman_steps import bierman_update, innovation_gate, moment_update, predict_covariance, ud_factor, update

__all__ = [
    "Manifold",
    "NonlinearModel",
    "nonlinear_model",
    "Linearization",
    "GaussianState",
    "GaussianOutputs",
    "gaussian_init",
    "gaussian_step",
    "difference",
    "retract",
    "residual",
    "model_inputs",
    "check_discrete_model",
    "gaussian_factor",
    "sample_gaussian",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Manifold:
    """A space whose points are not added and subtracted as vectors: a rotation, a MuJoCo ``qpos`` with quaternions.

    Its errors live in a ``dim``-dimensional tangent space, reached by two maps,
    ``difference(a, b) -> (dim,)``: the tangent vector at ``b`` that leads to ``a`` (``a - b``);
    ``retract(b, delta) -> point``: the point ``delta`` away from ``b`` (``b + delta``),

    with ``retract(b, difference(a, b)) = a`` and ``difference(b, b) = 0``. A filter keeps its mean a point and its
    covariance, process and measurement noise on the tangent space (Sola 2017, the error-state form; MuJoCo's
    ``mj_integratePos`` and ``mj_differentiatePos`` are such a pair, :mod:`jaxobs.mjx.manifold`). ``None`` in
    place of a manifold means a vector space (``a - b``, ``b + delta``).

    Attributes:
      difference: ``difference(a, b)``, a ``jax.tree_util.Partial`` (bound arguments are leaves).
      retract: ``retract(b, delta)``, a ``Partial``.
      dim: static, the tangent dimension (the size of a covariance on this space).
      size: static, the number of entries of a point.
    """

    difference: Callable
    retract: Callable
    dim: int = dataclasses.field(metadata=dict(static=True))
    size: int = dataclasses.field(metadata=dict(static=True))


def difference(manifold: Manifold | None, a, b):
    """``a - b`` on ``manifold`` (its ``difference``; vectors subtract when it is ``None``)."""
    return a - b if manifold is None else manifold.difference(a, b)


def retract(manifold: Manifold | None, b, delta):
    """``b + delta`` on ``manifold`` (its ``retract``; vectors add when it is ``None``)."""
    return b + delta if manifold is None else manifold.retract(b, delta)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class NonlinearModel:
    """A nonlinear Gaussian state-space model (``n`` states, ``m`` inputs, ``p`` outputs); build it with
    :func:`nonlinear_model`.

    Attributes:
      f: the transition ``f(x, u, t) -> x_next`` (discrete) or ``-> dx/dt`` (``continuous``), as a
        ``jax.tree_util.Partial``: its bound arguments (model parameters, an MJX model) are leaves of this
        pytree, so ``grad`` and ``vmap`` reach them.
      h: the measurement ``h(x) -> y`` (p,), or ``h(x, u)`` with ``feedthrough``; a ``Partial`` likewise.
      Q: (d, d) process noise covariance (discrete) or spectral density (continuous), on the state's tangent
        space (``d = n`` for a vector state).
      R: (r, r) measurement noise covariance (``r = p`` for a vector measurement, else the tangent dimension).
      x0: (n,) prior mean of ``x_0``.  P0: (d, d) its covariance.
      dt: () sample period (the time step between measurements).  t0: () time of the first measurement.
      n_inputs: static ``m``; ``f`` receives an (m,) input (an empty one when ``m = 0``).
      continuous: static; ``f`` is the time derivative and the prediction integrates over each sample.
      substeps: static number of fixed integration steps per sample (continuous models).
      method: static integration rule, ``"rk4"`` or ``"euler"`` (:data:`jaxobs.ct.METHODS`).
      manifold: the state's :class:`Manifold`, or ``None`` for a vector state.
      measurement_manifold: the measurement's :class:`Manifold` (innovations ``y - h`` on its tangent space), or
        ``None``.
      feedthrough: static; ``h`` takes the input too, ``y_k = h(x_k, u_{k-1})``: the input held over the sample
        that ends at ``t_k`` acts on the measurement (an accelerometer, a force sensor).
    """

    f: Callable
    h: Callable
    Q: jax.Array
    R: jax.Array
    x0: jax.Array
    P0: jax.Array
    dt: jax.Array
    t0: jax.Array
    n_inputs: int = dataclasses.field(default=0, metadata=dict(static=True))
    continuous: bool = dataclasses.field(default=False, metadata=dict(static=True))
    substeps: int = dataclasses.field(default=1, metadata=dict(static=True))
    method: str = dataclasses.field(default="rk4", metadata=dict(static=True))
    manifold: Manifold | None = None
    measurement_manifold: Manifold | None = None
    feedthrough: bool = dataclasses.field(default=False, metadata=dict(static=True))

    def measure(self, u) -> Callable:
        """``x -> h(x)``, or ``x -> h(x, u)`` with ``feedthrough``."""
        return (lambda x: self.h(x, u)) if self.feedthrough else self.h

    def check(self, name: str = "model") -> NonlinearModel:
        """``self``, checked at trace time to be one model: ``Q`` (d, d), ``R`` (r, r), ``x0`` (n,), ``P0`` (d, d),
        ``dt`` and ``t0`` (), no leading batch axis (``vmap`` over a batch of models); a ``ValueError`` naming
        ``name.Q`` ... otherwise (``name``: the argument that holds it)."""
        if not isinstance(self, NonlinearModel):
            raise ValueError(f"{name} must be a NonlinearModel (jaxobs.nonlinear.nonlinear_model), got {self!r}")
        d = "n" if self.manifold is None else "d"  # covariances live in the tangent space of a manifold state
        shapes = (
            f"{name}.Q ({d}, {d}), {name}.R (r, r), {name}.x0 (n,), {name}.P0 ({d}, {d}), {name}.dt (), {name}.t0 ()"
        )
        _checks.shapes(shapes, self.Q, self.R, self.x0, self.P0, self.dt, self.t0)
        return self


def nonlinear_model(
    f, h, Q, R, *, x0, P0=None, n_inputs: int = 0, dt=1.0, t0=0.0, continuous: bool = False,
    substeps: int = 1, method: str = "rk4", manifold: Manifold | None = None,
    measurement_manifold: Manifold | None = None, feedthrough: bool = False,
) -> NonlinearModel:  # fmt: skip
    """Build and check a :class:`NonlinearModel`.

    Args:
      f: transition ``f(x, u, t)``: the next state (discrete) or ``dx/dt`` (``continuous``), shape (n,). A plain
        function or a ``jax.tree_util.Partial`` whose bound arguments should be differentiable or batched.
      h: measurement ``h(x)`` (``h(x, u)`` with ``feedthrough``), shape (p,) (a function or a ``Partial``).
      Q: (d, d) positive semidefinite (a covariance, or a spectral density for a continuous ``f``), ``d`` the
        tangent dimension of ``manifold`` (``n`` without one).
      R: (r, r) positive definite, ``r`` the tangent dimension of ``measurement_manifold`` (``p`` without one).
      x0: (n,) prior mean of ``x_0``.  P0: (d, d) its covariance (default ``Q``).
      n_inputs: the number of inputs ``m`` (``u`` has shape (m,)).
      dt: sample period (> 0).  t0: time of the first measurement; step ``k`` predicts from ``t0 + (k-1) dt``.
      continuous: ``f`` is a time derivative (continuous-discrete filtering; vector states only).
      substeps: fixed integration steps per sample.  method: ``"rk4"`` or ``"euler"``.
      manifold, measurement_manifold: the :class:`Manifold` of the state and of the measurement (``None``:
        vectors). The filters then linearise in the tangent spaces, keep means on the manifolds and report
        innovations, gains and covariances in tangent coordinates.
      feedthrough: ``h`` takes the input as well, ``y_k = h(x_k, u_{k-1})``.

    The outputs of ``f`` and ``h`` are checked once, abstractly (``jax.eval_shape``). All arrays are cast to their
    common floating dtype.

    Example:
      >>> import jax.numpy as jnp
      >>> from jaxobs.nonlinear import nonlinear_model
      >>> pendulum = lambda x, u, t: jnp.array([x[1], -9.81 * jnp.sin(x[0])])
      >>> model = nonlinear_model(pendulum, lambda x: jnp.sin(x[:1]), 0.01 * jnp.eye(2), [[0.1]],
      ...                         x0=[0.5, 0.0], dt=0.05, continuous=True, substeps=4)
      >>> model.Q.shape, model.R.shape
      ((2, 2), (1, 1))
    """
    f, h = _checks.function("f", f), _checks.function("h", h)
    Q, R = jnp.atleast_2d(_checks.real_array("Q", Q)), jnp.atleast_2d(_checks.real_array("R", R))
    x0 = jnp.atleast_1d(_checks.real_array("x0", x0))
    P0 = Q if P0 is None else jnp.atleast_2d(_checks.real_array("P0", P0))
    dtype = _checks.float_dtype(Q=Q, R=R, x0=x0, P0=P0, dt=dt, t0=t0)
    _checks.shape("x0", x0, (None,), "the prior mean, one entry per state")
    n = x0.shape[0]
    for name, space in (("manifold", manifold), ("measurement_manifold", measurement_manifold)):
        if space is not None and not isinstance(space, Manifold):
            raise ValueError(f"{name} must be a jaxobs.nonlinear.Manifold or None, got {type(space).__name__}")
    d = n if manifold is None else manifold.dim
    _checks.covariance("Q", Q, definite=False, size=d)
    _checks.covariance("R", R, definite=True)
    _checks.covariance("P0", P0, definite=False, size=d)
    _checks.finite("x0", x0)
    _checks.positive_scalar("dt", dt)
    dt, t0 = jnp.asarray(dt, dtype), jnp.asarray(t0, dtype)
    _checks.shape("dt", dt, (), "a scalar sample period")
    _checks.shape("t0", t0, (), "a scalar time")
    _checks.finite("t0", t0)
    n_inputs = _checks.count("n_inputs", n_inputs, hint="the size of the input u of f(x, u, t)")
    continuous = _checks.boolean("continuous", continuous)
    substeps = _checks.count("substeps", substeps, minimum=1, hint="fixed integration steps per sample")
    if method not in ct.METHODS:
        raise ValueError(f"method must be one of {sorted(ct.METHODS)}, got {method!r}")
    if continuous and manifold is not None:
        raise ValueError("continuous=True integrates dx/dt as a vector: a state on a manifold needs a discrete f")
    feedthrough = _checks.boolean("feedthrough", feedthrough)
    x, u = jnp.zeros((n,), dtype), jnp.zeros((n_inputs,), dtype)
    _check_manifold("manifold", manifold, x)
    what = "dx/dt" if continuous else "the next state"
    _checks.returns("f(x, u, t)", f, (x, u, t0), (n,), f"{what}, one entry per entry of x0")
    call, args = ("h(x, u)", (x, u)) if feedthrough else ("h(x)", (x,))
    if measurement_manifold is None:
        _checks.returns(call, h, args, (R.shape[0],), "the measurement, one entry per row of R")
    else:
        _checks.returns(call, h, args, (None,), "the measurement, a point of measurement_manifold")
        _check_manifold("measurement_manifold", measurement_manifold, jax.eval_shape(h, *args))
        if measurement_manifold.dim != R.shape[0]:
            raise ValueError(f"R must be ({measurement_manifold.dim}, {measurement_manifold.dim}), the tangent "
                             f"dimension of measurement_manifold, got {R.shape}")  # fmt: skip
    cast = lambda M: M.astype(dtype)
    return NonlinearModel(f, h, cast(Q), cast(R), cast(x0), cast(P0), dt, t0, n_inputs, continuous, substeps, method,
                          manifold, measurement_manifold, feedthrough)  # fmt: skip


def _check_manifold(name: str, manifold: Manifold | None, point) -> None:
    """Check abstractly that ``manifold``'s maps take and return points shaped like ``point`` and tangent vectors of
    its ``dim``."""
    if manifold is None:
        return
    if point.shape != (manifold.size,):
        raise ValueError(f"{name} holds points of {manifold.size} entries, got {point.shape} (x0 or h's value)")
    point = jnp.zeros(point.shape, point.dtype)
    tangent = jnp.zeros((manifold.dim,), point.dtype)
    _checks.returns(f"{name}.difference(a, b)", manifold.difference, (point, point), (manifold.dim,),
                    f"a tangent vector of its dim ({manifold.dim})")  # fmt: skip
    _checks.returns(f"{name}.retract(b, delta)", manifold.retract, (point, tangent), point.shape,
                    f"a point shaped like {point.shape}")  # fmt: skip


class Linearization(NamedTuple):
    """``g(x) ~ mean + G (x - m) + e``, ``e ~ N(0, Omega)``, around ``N(m, P)`` (shapes for ``g: (n,) -> (k,)``; for
    values on a :class:`Manifold` ``mean`` is a point and ``k`` the tangent dimension, ``+`` its retraction).

    ``cross`` and ``cov``, when given, are the moments the linearisation implies, computed directly: a
    sigma-point rule has them without ``G`` (``cross = P G'``, ``cov = G P G' + Omega``); the prediction and the
    standard-form update then use them and need no solve with ``P``."""

    mean: jax.Array  # (k,) g_bar
    G: jax.Array  # (k, n) Jacobian (Taylor) or regression matrix (sigma points)
    Omega: jax.Array | None  # (k, k) covariance of the linearisation error; None when zero (Taylor)
    cross: jax.Array | None = None  # (n, k) covariance of x and g(x)
    cov: jax.Array | None = None  # (k, k) covariance of g(x)


class Linearize(Protocol):
    def __call__(self, g: Callable, m: jax.Array, P: jax.Array, *, output: Manifold | None = None) -> Linearization:
        """The linearisation of ``g`` around ``N(m, P)``; with ``output``, ``g``'s values are points of that manifold:
        the mean is a point, ``G``, ``Omega`` and the moments live on its tangent space at the mean."""


class GaussianState(NamedTuple):
    """State of a Gaussian filter (EKF, UKF) between steps.

    Attributes:
      x: (n,) a-posteriori mean x_hat_{k-1|k-1} (the prior mean before the first step)
      P: (n, n) its covariance
      t: () its time
      started: () bool: a measurement has been processed (the next step predicts)
      missing: () int32, measurement components skipped so far (missing or gated)
      gated: () int32, of those, finite components rejected by the innovation gate
    """

    x: jax.Array
    P: jax.Array
    t: jax.Array
    started: jax.Array
    missing: jax.Array
    gated: jax.Array


class GaussianOutputs(NamedTuple):
    """Outputs of one step of a Gaussian filter (EKF, UKF).

    Attributes:
      x: (n,) a-posteriori mean x_hat_{k|k}
      P: (n, n) its covariance
      x_prior: (n,) a-priori mean x_hat_{k|k-1}
      innovation: (p,) y_k - h_bar around the prior (0 for missing components)
      gain: (n, p) gain of the (last) update (zero columns for missing components)
      log_likelihood: () log N(innovation; 0, S), ``S = H P_prior H' + R + Omega_h`` of the first linearisation
        around the prior: the filter's predictive density of the observed components of ``y_k`` (0 when all
        are missing or gated)
      P_prior: (n, n) a-priori covariance P_{k|k-1} (with output_covariance, else None)
      transition: (n, n) the linearised transition ``F_k`` of the prediction into sample ``k``, whose
        cross-covariance ``Cov(x_{k-1}, x_k) = P_{k-1} F_k'`` the smoother needs: the Jacobian of ``f``
        (EKF), the statistical linear regression matrix (UKF), the flow's sensitivity ``dPhi/dt = F Phi``
        (continuous-discrete); the identity at the first sample (with output_covariance, else None)
      S: (p, p) the innovation covariance ``S`` of ``log_likelihood`` (1 on the diagonal of a missing or gated
        component), what the normalised innovation squared needs (:func:`jaxobs.consistency.nis`)
    """

    x: jax.Array
    P: jax.Array
    x_prior: jax.Array
    innovation: jax.Array
    gain: jax.Array
    log_likelihood: jax.Array
    P_prior: jax.Array | None = None
    transition: jax.Array | None = None
    S: jax.Array | None = None


def gaussian_init(model: NonlinearModel) -> GaussianState:
    """The state before the first measurement: the prior ``(x0, P0)`` at ``t0``."""
    model = NonlinearModel.check(model)
    zero = jnp.zeros((), jnp.int32)
    return GaussianState(model.x0, model.P0, model.t0, jnp.zeros((), bool), zero, zero)


def model_inputs(model: NonlinearModel, inputs):
    """``(y, u)`` of ``EstimatorInputs(y, u_prev)`` checked against the model's sizes (at trace time) and cast to
    its dtype; ``u`` is an empty (0,) vector for a model without inputs. With a ``measurement_manifold``, ``y`` is
    a point of it (its ``size`` entries, e.g. 4 per quaternion)."""
    model = NonlinearModel.check(model)
    m, dtype = model.n_inputs, model.x0.dtype
    p, what = model.R.shape[-1], "one entry per row of R"
    if model.measurement_manifold is not None:
        p, what = model.measurement_manifold.size, "a point of measurement_manifold"
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what=what, check_finite=False)
    if inputs.u_prev is None:
        if m:
            raise ValueError(f"inputs.u_prev is required: the model has n_inputs={m}, got None")
        return y, jnp.zeros((0,), dtype)
    u = _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype, what="n_inputs entries", check_finite=False)
    return y, u


def _predict(linearize: Linearize, model: NonlinearModel, m, P, u, t, transition: bool):
    """``(m_prior, P_prior, F)``: the a-priori moments of the next sample and the linearised transition ``F``
    (:class:`GaussianOutputs`; continuous-discrete only with ``transition``, else None)."""
    if not model.continuous:
        lin = _linearize(linearize, lambda x: model.f(x, u, t), m, P, model.manifold, model.manifold)
        if lin.cov is not None:
            return lin.mean, lin.cov + model.Q, lin.G
        Q = model.Q if lin.Omega is None else model.Q + lin.Omega
        return lin.mean, predict_covariance(P, lin.G, Q), lin.G

    def moments(state, u, t):  # dm/dt, dP/dt and, with transition, the sensitivity dPhi/dt = F Phi
        m, P, *Phi = state
        lin = linearize(lambda x: model.f(x, u, t), m, P)
        FP = lin.G @ P
        return (lin.mean, FP + FP.T + model.Q, *(lin.G @ S for S in Phi))

    start = (m, P, jnp.eye(m.shape[-1], dtype=m.dtype)) if transition else (m, P)
    m, P, *Phi = ct.integrate(moments, start, u, t, model.dt, substeps=model.substeps, method=model.method)
    return m, symmetrize(P), Phi[0] if transition else None


def _vector(model: NonlinearModel) -> bool:
    return model.manifold is None and model.measurement_manifold is None


def _linearize(linearize: Linearize, g: Callable, m, P, space_in, space_out) -> Linearization:
    """The linearisation of ``g`` around ``N(m, P)`` in tangent coordinates: that of ``delta -> g(m + delta)``
    (``space_in``'s retraction) around ``N(0, P)``, with its mean a point of ``space_out`` and ``G``, ``Omega`` and
    the moments on that space's tangent space; two vector spaces (``None``) give the plain linearisation."""
    if space_in is None and space_out is None:
        return linearize(g, m, P)
    if space_in is None:
        return linearize(g, m, P, output=space_out)
    on_tangent = lambda delta: g(space_in.retract(m, delta))  # noqa: E731
    return linearize(on_tangent, jnp.zeros((space_in.dim,), m.dtype), P, output=space_out)


def residual(manifold: Manifold | None, y, y_bar):
    """``y - y_bar`` on ``manifold`` (a measurement's innovation), NaN on the tangent entries of a missing
    (non-finite) component of ``y``; a missing component is replaced by ``y_bar`` before the difference, so no NaN
    reaches a derivative."""
    y, y_bar = jnp.asarray(y), jnp.asarray(y_bar)
    if manifold is None:
        return y - y_bar
    e = manifold.difference(jnp.where(jnp.isfinite(y), y, y_bar), y_bar)
    missing = ~jnp.isfinite(jax.lax.stop_gradient(manifold.difference(y, y_bar)))
    return jnp.where(missing, jnp.nan, e)


def _update_problem(model: NonlinearModel, y, lin: Linearization, m_prior, x, *, first: bool):
    """``(x_in, y_in, predicted)``, the arguments of the Kalman update around the iterate ``x`` (the prior mean at
    the first iteration). Vectors: the prior mean, ``y`` and ``h_bar = h(x) + G (m_prior - x)``. On manifolds the
    update runs in the tangent space at the prior mean: 0, ``y - h(x)`` (:func:`residual`) and ``G (m_prior - x)``.
    """
    if _vector(model):
        return m_prior, y, lin.mean if first else lin.mean + lin.G @ (m_prior - x)
    y_in = residual(model.measurement_manifold, y, lin.mean)
    predicted = jnp.zeros_like(y_in) if first else lin.G @ difference(model.manifold, m_prior, x)
    return jnp.zeros((lin.G.shape[-1],), m_prior.dtype), y_in, predicted


def _posterior_mean(model: NonlinearModel, m_prior, x_out):
    """The a-posteriori mean from the update's: itself for vectors, else the prior mean moved by the correction."""
    return x_out if _vector(model) else retract(model.manifold, m_prior, x_out)


def gaussian_step(
    linearize: Linearize, iterations: int, model: NonlinearModel, state: GaussianState, inputs, *,
    bierman: bool = False, gate=None, joseph: bool = True, output_covariance: bool = False,
):  # fmt: skip
    """One step of the Gaussian filter with ``linearize`` (the equations of this module).

    Args:
      linearize: ``(g, m, P) -> Linearization``.  iterations: static number of updates (1: no iteration).
      bierman: static; the measurement update by Bierman's U-D algorithm
        (:func:`jaxobs.kalman_steps.bierman_update`) instead of the Joseph form.
      gate: ``None`` or the innovation gate (standard deviations, > 0; the first linearisation's innovation).
      joseph: static; ``False``: the standard-form covariance update (:func:`jaxobs.kalman_steps.update`).
      output_covariance: static; also output ``P_prior`` and ``transition`` (what the smoother needs).
      model: the :class:`NonlinearModel`.  state: the :class:`GaussianState` after sample ``k - 1``.
      inputs: ``EstimatorInputs(y, u_prev)`` of sample ``k``: (p,) and (m,) (``None`` without inputs).

    Returns:
      ``(GaussianState, GaussianOutputs)`` of sample ``k``; its ``log_likelihood`` is that of the first
      linearisation of ``h`` (around the prior), the filter's predictive density of ``y_k``.
    """
    y, u = model_inputs(model, inputs)
    m_pred, P_pred, F = _predict(linearize, model, state.x, state.P, u, state.t, output_covariance)
    first = ~state.started  # the prior is that of x_0: no prediction before the first update
    m_prior, P_prior = jnp.where(first, state.x, m_pred), jnp.where(first, state.P, P_pred)
    t = jnp.where(first, state.t, state.t + model.dt)
    x, P = m_prior, P_prior
    first_update, gated, accepted = None, jnp.zeros((), jnp.int32), None
    for i in range(iterations):
        lin = _linearize(linearize, model.measure(u), x, P, model.manifold, model.measurement_manifold)
        x_in, y_in, predicted = _update_problem(model, y, lin, m_prior, x, first=i == 0)
        R = model.R if lin.Omega is None else model.R + lin.Omega
        if i == 0 and gate is not None:
            accepted = innovation_gate(y_in - predicted, lin.G, P_prior, R, gate)
            gated = jnp.sum(jnp.isfinite(y_in) & ~accepted).astype(jnp.int32)
        if accepted is not None:  # a gated component stays out of every iteration
            y_in = jnp.where(accepted, y_in, jnp.nan)
        if bierman:
            result = bierman_update(x_in, P_prior, lin.G, R, y_in, predicted=predicted)
        elif lin.cov is not None and not joseph and iterations == 1:
            result = moment_update(x_in, P_prior, lin.cross, lin.cov, model.R, y_in, predicted)
        else:
            result = update(x_in, P_prior, lin.G, R, y_in, joseph=joseph, predicted=predicted)
        x, P = _posterior_mean(model, m_prior, result.x), result.P
        if first_update is None:  # the innovation and its density around the prior, y_k - h_bar(m_prior)
            first_update = result
    missing = state.missing + result.n_missing.astype(jnp.int32)
    new_state = GaussianState(x, P, t, jnp.ones((), bool), missing, state.gated + gated)
    covariances = (None, None)
    if output_covariance:
        covariances = (P_prior, jnp.where(first, jnp.eye(P.shape[-1], dtype=P.dtype), F))
    outputs = GaussianOutputs(x, P, m_prior, first_update.innovation, result.K, first_update.log_likelihood,
                              *covariances, first_update.S)  # fmt: skip
    return new_state, outputs


def check_discrete_model(model, what: str) -> None:
    """``ValueError`` unless ``model`` is a discrete-time :class:`NonlinearModel` (``f`` the next state) on vector
    states and measurements without feedthrough, as the Monte-Carlo filters, which draw the transition, need;
    ``what`` names the filter in the message."""
    NonlinearModel.check(model, "model")
    if model.continuous:
        raise ValueError(f"model is continuous-time: {what} draws a discrete-time transition; build the model with "
                         "continuous=False (f the next state)")  # fmt: skip
    for field in ("manifold", "measurement_manifold", "feedthrough"):
        if getattr(model, field):
            raise ValueError(f"model has a {field}: {what} works on vector states and measurements h(x); the EKF and "
                             "UKF take manifolds and feedthrough")  # fmt: skip


def gaussian_factor(cov):
    """A factor ``F`` (n, n) with ``F F' = cov`` of a symmetric positive semidefinite ``cov``, from
    :func:`jaxobs.kalman_steps.ud_factor` (``F = U diag(d)^(1/2)``), so a singular ``cov`` is no special case;
    differentiable where ``cov`` is definite. The Monte-Carlo filters (particle filters, ensemble Kalman filters)
    draw their noises with it (:func:`sample_gaussian`)."""
    (cov,) = _checks.arrays("cov (n, n)", cov)
    U, d = ud_factor(cov)
    return U * jnp.sqrt(d)


def sample_gaussian(key, mean, factor, num: int):
    """``num`` draws (num, n) of ``N(mean, F F')`` as ``mean + F e``, ``e`` standard normal, for a factor ``F``
    (n, r) such as :func:`gaussian_factor`'s: reparameterised, so differentiable in ``mean`` and ``F``.
    Shapes: ``mean`` (n,) (or a scalar, the same for every entry), ``factor`` (n, r); ``num`` static."""
    mean, factor = _checks.float_arrays(mean=mean, factor=factor)
    if mean.ndim:
        _checks.shapes("mean (n,), factor (n, r)", mean, factor)
    else:
        _checks.shapes("factor (n, r)", factor)
    num = _checks.count("num", num)
    return mean + jax.random.normal(key, (num, factor.shape[-1]), mean.dtype) @ factor.T
