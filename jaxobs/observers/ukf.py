"""The unscented Kalman filter (UKF) with the unscented or the cubature sigma-point rule.

Each map of a :class:`~jaxobs.nonlinear.NonlinearModel` is propagated through ``2n + 1`` sigma points of the
current Gaussian (the scaled unscented transform, Wan & van der Merwe 2000; Julier & Uhlmann 2004; the cubature
rule of Arasaratnam & Haykin 2009 is ``alpha = 1, beta = 0, kappa = 0``), and the step is the Kalman step of
:mod:`jaxobs.nonlinear` on the statistical linear regression. ``P`` must stay positive definite.
:func:`make_ukf`, :data:`unscented_kalman_filter`. The sigma points and weights: docs/theory/nonlinear.md.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs._linalg import cho_solve, cholesky, symmetrize
from jaxobs.nonlinear import GaussianState, Linearization, NonlinearModel, gaussian_init, gaussian_step
from jaxobs.observers.base import Estimator, EstimatorInputs

__all__ = ["UKFParams", "make_ukf", "unscented_kalman_filter", "sigma_points", "unscented", "RULES"]

RULES = {"unscented": (1.0, 2.0, 0.0), "cubature": (1.0, 0.0, 0.0)}
"""Sigma-point rules by name: their default ``(alpha, beta, kappa)``."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class UKFParams:
    """Parameters of the unscented Kalman filter.

    Attributes:
      model: the :class:`~jaxobs.nonlinear.NonlinearModel`.
      alpha: () spread of the sigma points (> 0).  beta: () prior-distribution weight on the centre point
        (2 is optimal for a Gaussian).  kappa: () secondary scaling (``n + kappa > 0``). The three are leaves:
        they may be traced, batched or differentiated.
      iterations: static number of updates per sample (1: the plain UKF).
      joseph: static; ``False``: the standard-form covariance update (faster, positive semidefinite only to
        rounding; :func:`jaxobs.kalman_steps.update_covariance_factors`).
      output_covariance: static; every step also outputs ``P_prior`` and the ``transition`` (the sigma points'
        regression matrix), what the unscented RTS smoother needs (:func:`jaxobs.smoothing.smooth` switches it
        on).
    """

    model: NonlinearModel
    alpha: jax.Array
    beta: jax.Array
    kappa: jax.Array
    iterations: int = dataclasses.field(default=1, metadata=dict(static=True))
    joseph: bool = dataclasses.field(default=True, metadata=dict(static=True))
    output_covariance: bool = dataclasses.field(default=False, metadata=dict(static=True))


def make_ukf(model: NonlinearModel, *, rule: str = "unscented", alpha=None, beta=None, kappa=None,
             iterations: int = 1, joseph: bool = True) -> UKFParams:  # fmt: skip
    """The unscented Kalman filter of ``model`` (:func:`jaxobs.nonlinear.nonlinear_model`).

    Args:
      model: a :class:`~jaxobs.nonlinear.NonlinearModel` with a positive definite ``P0``.
      rule: ``"unscented"`` (defaults ``alpha = 1, beta = 2, kappa = 0``) or ``"cubature"`` (``1, 0, 0``, fixed).
      alpha: sigma-point spread (> 0).  beta: centre weight correction.  kappa: secondary scaling
        (``n + kappa > 0``); each ``None`` for the rule's default.
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
        raise ValueError(f"rule must be one of {sorted(RULES)}, got {rule!r}")
    given = {"alpha": alpha, "beta": beta, "kappa": kappa}
    if rule == "cubature" and any(v is not None for v in given.values()):
        raise ValueError(f"rule='cubature' fixes alpha=1, beta=0, kappa=0; got {given} (use rule='unscented')")
    dtype = model.x0.dtype
    defaults = dict(zip(given, RULES[rule], strict=True))
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
    _checks.covariance("model.P0", model.P0, definite=True)
    iterations = _checks.count("iterations", iterations, minimum=1, hint="updates per sample")
    joseph = _checks.boolean("joseph", joseph)
    return UKFParams(model, values["alpha"], values["beta"], values["kappa"], iterations, joseph)


def sigma_points(m, P, alpha, beta, kappa):
    """Sigma points and weights of ``N(m, P)``.

    Returns:
      ``(X, wm, wc, L)``: (2n+1, n) points (centre first), (2n+1,) mean and covariance weights, and the
      (n, n) lower Cholesky factor of ``P``.
    """
    n = m.shape[0]
    L = cholesky(P)
    c2 = alpha**2 * (n + kappa)
    offsets = jnp.sqrt(c2) * jnp.concatenate([jnp.zeros((1, n), m.dtype), L.T, -L.T])
    wm = jnp.concatenate([jnp.reshape(1 - n / c2, (1,)), jnp.full((2 * n,), 1 / (2 * c2))]).astype(m.dtype)
    wc = wm.at[0].add(1 - alpha**2 + beta)
    return m + offsets, wm, wc, L


def unscented(g, m, P, alpha, beta, kappa) -> Linearization:
    """Statistical linear regression of ``g`` on the sigma points of ``N(m, P)``: ``(g_bar, C' P^{-1}, Cov - G C)``."""
    X, wm, wc, L = sigma_points(m, P, alpha, beta, kappa)
    Y = jax.vmap(g)(X)
    mean = wm @ Y
    dX, dY = X - m, Y - mean
    C = (wc[:, None] * dX).T @ dY  # (n, k) cross-covariance
    cov = (wc[:, None] * dY).T @ dY  # (k, k)
    G = cho_solve(L, C).T
    return Linearization(mean, G, symmetrize(cov - G @ C), C, symmetrize(cov))


def _step(params: UKFParams, state: GaussianState, inputs: EstimatorInputs):
    def linearize(g, m, P):
        return unscented(g, m, P, params.alpha, params.beta, params.kappa)

    return gaussian_step(linearize, params.iterations, params.model, state, inputs, joseph=params.joseph,
                         output_covariance=params.output_covariance)  # fmt: skip


unscented_kalman_filter = Estimator(lambda params: gaussian_init(params.model), _step)
"""The unscented Kalman filter as an :class:`~jaxobs.observers.base.Estimator` over :class:`UKFParams`.

Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (p,) and (m,) (``u_prev=None`` without inputs), checked
against the model while tracing. State: :class:`~jaxobs.nonlinear.GaussianState`. Outputs:
:class:`~jaxobs.nonlinear.GaussianOutputs` (``x``, ``P``, ``x_prior``, ``innovation``, ``gain``,
``log_likelihood``; ``P_prior`` and ``transition`` with ``output_covariance``)."""
