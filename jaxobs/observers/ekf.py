"""The extended Kalman filter (EKF): discrete time or continuous-discrete, with an iterated-update option.

The maps of a :class:`~jaxobs.nonlinear.NonlinearModel` are replaced by their first-order Taylor series around
the current mean (Jacobians by ``jax.jacfwd``) and the step is the Kalman step of :mod:`jaxobs.nonlinear`: Joseph
form, or Bierman's U-D update with ``bierman=True`` (Grip 2010 §2.9); ``iterations > 1`` is the Gauss-Newton
iterated EKF (Bell & Cathey 1993); ``gate`` skips outlying components. :func:`make_ekf`,
:data:`extended_kalman_filter`. The equations: docs/theory/nonlinear.md.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.nonlinear import GaussianState, Linearization, Manifold, NonlinearModel, gaussian_init, gaussian_step
from jaxobs.observers.base import Estimator, EstimatorInputs

__all__ = ["EKFParams", "make_ekf", "extended_kalman_filter", "taylor"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class EKFParams:
    """Parameters of the extended Kalman filter.

    Attributes:
      model: the :class:`~jaxobs.nonlinear.NonlinearModel`.
      iterations: static number of Gauss-Newton updates per sample (1: the plain EKF).
      bierman: static; measurement updates by Bierman's U-D algorithm instead of the Joseph form.
      gate: ``None`` (no gate) or the innovation gate in standard deviations (a leaf).
      joseph: static; ``False``: the standard-form covariance update (faster, positive semidefinite only to
        rounding; :func:`jaxobs.kalman_steps.update_covariance_factors`).
      output_covariance: static; every step also outputs ``P_prior`` and the ``transition`` Jacobian, what the
        extended RTS smoother needs (:func:`jaxobs.smoothing.smooth` switches it on).
    """

    model: NonlinearModel
    iterations: int = dataclasses.field(default=1, metadata=dict(static=True))
    bierman: bool = dataclasses.field(default=False, metadata=dict(static=True))
    gate: jax.Array | None = None
    joseph: bool = dataclasses.field(default=True, metadata=dict(static=True))
    output_covariance: bool = dataclasses.field(default=False, metadata=dict(static=True))


def make_ekf(model: NonlinearModel, *, iterations: int = 1, bierman: bool = False, gate=None,
             joseph: bool = True) -> EKFParams:  # fmt: skip
    """The extended Kalman filter of ``model`` (:func:`jaxobs.nonlinear.nonlinear_model`).

    Args:
      model: a :class:`~jaxobs.nonlinear.NonlinearModel`, discrete or continuous.
      iterations: number of Gauss-Newton updates per sample (an integer >= 1; 1 is the plain EKF).
      bierman: use Bierman's U-D measurement update (:func:`jaxobs.kalman_steps.bierman_update`); equal to the
        default Joseph form in exact arithmetic, positive semidefinite as ``R -> 0``.
      gate: ``None`` (default, every finite measurement is used) or a threshold (> 0, in standard deviations):
        a component whose innovation exceeds ``gate sqrt(S_ii)``, ``S = H P_prior H' + R``, is skipped as an
        outlier (:func:`jaxobs.kalman_steps.innovation_gate`) and counted in ``state.gated``.
      joseph: the covariance update in Joseph form (default); ``False``: the standard form, fewer operations per
        step, positive semidefinite only to rounding. Not with ``bierman``.

    Example:
      >>> import jax.numpy as jnp
      >>> import jaxobs as jo
      >>> f = lambda x, u, t: jnp.array([x[0] + 0.1 * x[1], x[1] - 0.1 * jnp.sin(x[0])])
      >>> model = jo.nonlinear_model(f, lambda x: x[:1], 1e-4 * jnp.eye(2), [[0.01]], x0=[0.3, 0.0])
      >>> _, out = jo.run(jo.extended_kalman_filter, jo.make_ekf(model), jo.EstimatorInputs(y=jnp.ones((20, 1))))
      >>> out.x.shape, out.P.shape
      ((20, 2), (20, 2, 2))
    """
    NonlinearModel.check(model, "model")
    iterations = _checks.count("iterations", iterations, minimum=1, hint="Gauss-Newton updates per sample")
    bierman, joseph = _checks.boolean("bierman", bierman), _checks.boolean("joseph", joseph)
    if bierman and not joseph:
        raise ValueError("bierman=True and joseph=False: choose one covariance update (Bierman's keeps its factors)")
    if gate is not None:
        _checks.positive("gate", gate, what="an innovation gate in standard deviations")
    return EKFParams(model, iterations, bierman, gate, joseph)


def taylor(g, m, P, *, output: Manifold | None = None) -> Linearization:
    """First-order Taylor linearisation of ``g`` at ``m``: ``(g(m), dg/dx (m), None)``; one forward-mode pass
    evaluates ``g`` and its Jacobian together. ``P`` is unused. With ``output`` (the :class:`~jaxobs.nonlinear.Manifold`
    of ``g``'s values) the Jacobian is that of ``output.difference(g(x), g(m))``, on the tangent space at ``g(m)``.
    ``m`` (n,); ``P`` (n, n)."""
    m, _ = _checks.arrays("m (n,), P (n, n)", m, P)

    def value_twice(x):
        value = g(x)
        if output is None:
            return value, value
        # at x = m the reference equals the value, so this is d/dx (g(x) - g(m)) on the tangent space at g(m)
        return output.difference(value, jax.lax.stop_gradient(value)), value

    G, mean = jax.jacfwd(value_twice, has_aux=True)(m)
    # jacfwd stacks the Jacobian's columns; without the barrier XLA folds that transpose into the products
    # F P F' and H P, whose transposed operands its CPU backend multiplies by a slower kernel
    # (benchmarks/estimation.py)
    G = jax.lax.optimization_barrier(jnp.reshape(G, (G.shape[0], m.shape[0])))
    return Linearization(mean, G, None)


def _step(params: EKFParams, state: GaussianState, inputs: EstimatorInputs):
    NonlinearModel.check(params.model, "params.model")
    return gaussian_step(taylor, params.iterations, params.model, state, inputs, bierman=params.bierman,
                         gate=params.gate, joseph=params.joseph,
                         output_covariance=params.output_covariance)  # fmt: skip


extended_kalman_filter = Estimator(
    lambda params: gaussian_init(NonlinearModel.check(params.model, "params.model")), _step
)
"""The extended Kalman filter as an :class:`~jaxobs.observers.base.Estimator` over :class:`EKFParams`.

Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (p,) and (m,) (``u_prev=None`` without inputs), checked
against the model while tracing. State: :class:`~jaxobs.nonlinear.GaussianState`. Outputs:
:class:`~jaxobs.nonlinear.GaussianOutputs` (``x``, ``P``, ``x_prior``, ``innovation``, ``gain``,
``log_likelihood``; ``P_prior`` and ``transition`` with ``output_covariance``)."""
