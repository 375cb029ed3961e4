"""Sigma-point Gaussian filters: the unscented Kalman filter (UKF) and the cubature and Gauss-Hermite filters.

Each map of a :class:`~jaxobs.nonlinear.NonlinearModel` is propagated through the sigma points of the current
Gaussian, by one of :data:`RULES`: the ``2n + 1`` points of the scaled unscented transform (Wan & van der Merwe
2000; Julier & Uhlmann 2004), the ``2n`` points of the spherical-radial cubature rule (Arasaratnam & Haykin 2009)
or the ``order^n`` points of the Gauss-Hermite product rule (Ito & Xiong 2000); the step is the Kalman step of
:mod:`jaxobs.nonlinear` on the statistical linear regression. ``P`` must stay positive definite.
:func:`make_ukf`, :data:`unscented_kalman_filter`. The sigma points and weights: docs/theory/nonlinear.md.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs._linalg import cho_solve, cholesky, symmetrize
from jaxobs.nonlinear import GaussianState, Linearization, NonlinearModel, gaussian_init, gaussian_step
from jaxobs.observers.base import Estimator, EstimatorInputs

__all__ = [
    "UKFParams",
    "make_ukf",
    "unscented_kalman_filter",
    "sigma_points",
    "unit_points",
    "unscented",
    "RULES",
    "UNSCENTED_DEFAULTS",
]

RULES = ("unscented", "cubature", "gauss_hermite")
"""The sigma-point rules by name (:func:`sigma_points`)."""

UNSCENTED_DEFAULTS = (1.0, 2.0, 0.0)
"""The unscented rule's default ``(alpha, beta, kappa)``."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class UKFParams:
    """Parameters of the unscented Kalman filter.

    Attributes:
      model: the :class:`~jaxobs.nonlinear.NonlinearModel`.
      alpha: () spread of the sigma points (> 0).  beta: () prior-distribution weight on the centre point
        (2 is optimal for a Gaussian).  kappa: () secondary scaling (``n + kappa > 0``). The three are leaves:
        they may be traced, batched or differentiated; ``None`` for the rules without them.
      iterations: static number of updates per sample (1: the plain UKF).
      joseph: static; ``False``: the standard-form covariance update (faster, positive semidefinite only to
        rounding; :func:`jaxobs.kalman_steps.update_covariance_factors`).
      output_covariance: static; every step also outputs ``P_prior`` and the ``transition`` (the sigma points'
        regression matrix), what the unscented RTS smoother needs (:func:`jaxobs.smoothing.smooth` switches it
        on).
      rule: static; the sigma-point rule, one of :data:`RULES` (:func:`sigma_points`).
      order: static; the Gauss-Hermite rule's points per dimension (``order^n`` in all).
    """

    model: NonlinearModel
    alpha: jax.Array | None
    beta: jax.Array | None
    kappa: jax.Array | None
    iterations: int = dataclasses.field(default=1, metadata=dict(static=True))
    joseph: bool = dataclasses.field(default=True, metadata=dict(static=True))
    output_covariance: bool = dataclasses.field(default=False, metadata=dict(static=True))
    rule: str = dataclasses.field(default="unscented", metadata=dict(static=True))
    order: int = dataclasses.field(default=3, metadata=dict(static=True))


def make_ukf(model: NonlinearModel, *, rule: str = "unscented", alpha=None, beta=None, kappa=None, order=None,
             iterations: int = 1, joseph: bool = True) -> UKFParams:  # fmt: skip
    """The sigma-point Kalman filter of ``model`` (:func:`jaxobs.nonlinear.nonlinear_model`) with the point rule
    ``rule``: the unscented, the cubature or the Gauss-Hermite Kalman filter.

    Args:
      model: a :class:`~jaxobs.nonlinear.NonlinearModel` with a positive definite ``P0``.
      rule: ``"unscented"`` (defaults ``alpha = 1, beta = 2, kappa = 0``), ``"cubature"`` (``2n`` points) or
        ``"gauss_hermite"`` (``order^n`` points); see :func:`sigma_points`.
      alpha: sigma-point spread (> 0).  beta: centre weight correction.  kappa: secondary scaling
        (``n + kappa > 0``); each ``None`` for the rule's default (the unscented rule only).
      order: the Gauss-Hermite rule's points per dimension, an integer >= 2 (default 3: exact for polynomials up
        to degree 5); ``None`` for the other rules.
      iterations: number of updates per sample (an integer >= 1; 1 is the plain UKF).
      joseph: the covariance update in Joseph form (default); ``False``: the standard form, fewer operations per
        step, positive semidefinite only to rounding.

    Example:
      >>> import jax.numpy as jnp
      >>> import jaxobs as jo
      >>> f = lambda x, u, t: jnp.array([x[0] + 0.1 * x[1], x[1] - 0.1 * jnp.sin(x[0])])
      >>> model = jo.nonlinear_model(f, lambda x: x[:1], 1e-4 * jnp.eye(2), [[0.01]], x0=[0.3, 0.0])
      >>> params = jo.make_ukf(model, rule="cubature")
      >>> _, out = jo.run(jo.unscented_kalman_filter, params, jo.EstimatorInputs(y=jnp.ones((20, 1))))
      >>> out.x.shape
      (20, 2)
    """
    if not isinstance(model, NonlinearModel):
        raise ValueError(f"model must be a NonlinearModel (see jaxobs.nonlinear_model), got {type(model).__name__}")
    if rule not in RULES:
        raise ValueError(f"rule must be one of {list(RULES)}, got {rule!r}")
    given = {"alpha": alpha, "beta": beta, "kappa": kappa}
    if rule != "unscented" and any(v is not None for v in given.values()):
        raise ValueError(f"rule={rule!r} has no alpha, beta, kappa; got {given} (use rule='unscented')")
    if rule != "gauss_hermite" and order is not None:
        raise ValueError(f"order is the Gauss-Hermite rule's; rule={rule!r} takes none, got {order!r}")
    order = 3 if order is None else _checks.count("order", order, minimum=2, hint="Gauss-Hermite points per axis")
    iterations = _checks.count("iterations", iterations, minimum=1, hint="updates per sample")
    joseph = _checks.boolean("joseph", joseph)
    _checks.covariance("model.P0", model.P0, definite=True)
    if rule != "unscented":
        return UKFParams(model, None, None, None, iterations, joseph, rule=rule, order=order)
    dtype = model.x0.dtype
    defaults = dict(zip(given, UNSCENTED_DEFAULTS, strict=True))
    values = {k: jnp.asarray(defaults[k] if v is None else v, dtype) for k, v in given.items()}
    for name, value in values.items():
        _checks.shape(name, value, (), "a scalar")
        _checks.finite(name, value)
    n = model.x0.shape[0]
    if _checks.is_concrete(values["alpha"], values["kappa"]):
        if float(values["alpha"]) <= 0:
            raise ValueError(f"alpha must be positive, got {float(values['alpha'])}")
        if n + float(values["kappa"]) <= 0:
            raise ValueError(f"kappa must exceed -n = {-n} (the sigma points' spread is alpha^2 (n + kappa)), "
                             f"got {float(values['kappa'])}")  # fmt: skip
    return UKFParams(model, values["alpha"], values["beta"], values["kappa"], iterations, joseph)


def unit_points(n: int, rule: str, order: int = 3):
    """The cubature or Gauss-Hermite points of ``N(0, I_n)`` and their weights, as NumPy constants.

    ``"cubature"``: the ``2n`` points ``+-sqrt(n) e_i`` with weights ``1 / (2n)``, the third-degree
    spherical-radial rule (Arasaratnam & Haykin 2009). ``"gauss_hermite"``: the ``order^n`` points of
    the product of the one-dimensional rule (the roots of the probabilists' Hermite polynomial of degree
    ``order``), weights the products of its weights, exact for polynomials of degree ``2 order - 1`` in each
    coordinate (Ito & Xiong 2000; Särkkä 2013, §6.3).

    Returns:
      ``(xi, w)``: (N, n) points and (N,) weights summing to 1.
    """
    if rule == "cubature":
        return math.sqrt(n) * np.concatenate([np.eye(n), -np.eye(n)]), np.full(2 * n, 1.0 / (2 * n))
    if rule != "gauss_hermite":
        raise ValueError(
            f"rule must be 'cubature' or 'gauss_hermite' (the unscented rule has parameters), got {rule!r}"
        )
    nodes, weights = np.polynomial.hermite_e.hermegauss(order)
    xi = np.array(list(itertools.product(nodes, repeat=n)))
    w = np.prod(np.array(list(itertools.product(weights / math.sqrt(2.0 * math.pi), repeat=n))), axis=1)
    return xi, w


def sigma_points(m, P, alpha=1.0, beta=2.0, kappa=0.0, *, rule: str = "unscented", order: int = 3):
    """Sigma points and weights of ``N(m, P)`` by the rule ``rule`` (:data:`RULES`).

    ``"unscented"``: the ``2n + 1`` points of the scaled unscented transform with ``alpha``, ``beta``, ``kappa``
    (default :data:`UNSCENTED_DEFAULTS`); ``"cubature"`` and ``"gauss_hermite"``: ``m + L xi`` for the points
    ``xi`` of :func:`unit_points` (``order`` per dimension for Gauss-Hermite; ``alpha``, ``beta``, ``kappa``
    unused), with equal mean and covariance weights.

    Returns:
      ``(X, wm, wc, L)``: (N, n) points (the unscented centre first), (N,) mean and covariance weights, and the
      (n, n) lower Cholesky factor of ``P``.
    """
    n = m.shape[0]
    L = cholesky(P)
    if rule != "unscented":
        xi, w = unit_points(n, rule, order)
        w = jnp.asarray(w, m.dtype)
        return m + jnp.asarray(xi, m.dtype) @ L.T, w, w, L
    c2 = alpha**2 * (n + kappa)
    offsets = jnp.sqrt(c2) * jnp.concatenate([jnp.zeros((1, n), m.dtype), L.T, -L.T])
    wm = jnp.concatenate([jnp.reshape(1 - n / c2, (1,)), jnp.full((2 * n,), 1 / (2 * c2))]).astype(m.dtype)
    wc = wm.at[0].add(1 - alpha**2 + beta)
    return m + offsets, wm, wc, L


def unscented(g, m, P, alpha=1.0, beta=2.0, kappa=0.0, *, rule: str = "unscented", order: int = 3) -> Linearization:
    """Statistical linear regression of ``g`` on the sigma points of ``N(m, P)`` by any rule of
    :func:`sigma_points`: ``(g_bar, C' P^{-1}, Cov - G C)`` (Särkkä 2013, §5.6)."""
    X, wm, wc, L = sigma_points(m, P, alpha, beta, kappa, rule=rule, order=order)
    Y = jax.vmap(g)(X)
    mean = wm @ Y
    dX, dY = X - m, Y - mean
    C = (wc[:, None] * dX).T @ dY  # (n, k) cross-covariance
    cov = (wc[:, None] * dY).T @ dY  # (k, k)
    G = cho_solve(L, C).T
    return Linearization(mean, G, symmetrize(cov - G @ C), C, symmetrize(cov))


def _step(params: UKFParams, state: GaussianState, inputs: EstimatorInputs):
    def linearize(g, m, P):
        return unscented(g, m, P, params.alpha, params.beta, params.kappa, rule=params.rule, order=params.order)

    return gaussian_step(linearize, params.iterations, params.model, state, inputs, joseph=params.joseph,
                         output_covariance=params.output_covariance)  # fmt: skip


unscented_kalman_filter = Estimator(lambda params: gaussian_init(params.model), _step)
"""The sigma-point Kalman filter (unscented, cubature or Gauss-Hermite, ``UKFParams.rule``) as an
:class:`~jaxobs.observers.base.Estimator` over :class:`UKFParams`.

Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (p,) and (m,) (``u_prev=None`` without inputs), checked
against the model while tracing. State: :class:`~jaxobs.nonlinear.GaussianState`. Outputs:
:class:`~jaxobs.nonlinear.GaussianOutputs` (``x``, ``P``, ``x_prior``, ``innovation``, ``gain``,
``log_likelihood``; ``P_prior`` and ``transition`` with ``output_covariance``)."""
