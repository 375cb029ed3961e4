"""The Kalman building blocks every Kalman-type estimator shares: prediction, the Joseph-form measurement
update with missing data, the innovation and the gain.

Model (Cortesão 2006 eq. 27-29)::

    x_k = Phi x_{k-1} + Gamma u_{k-1} + w_k,    y_k = C x_k + v_k,    E[w w'] = Q,  E[v v'] = R

    x_prior = Phi x_{k-1} + Gamma u_{k-1}            P_prior = Phi P_{k-1} Phi' + Q          (predict)
    K_k     = P_prior C' S_k^{-1},  S_k = C P_prior C' + R                                   (gain)
    x_k     = x_prior + K_k (y_k - C x_prior)                                                (update)
    P_k     = (I - K_k C) P_prior (I - K_k C)' + K_k R K_k'                                  (Joseph form)

Missing data: a non-finite component of ``y_k`` is missing. Its row of ``C`` and its correlations in ``R``
are removed for that step, an exact marginalisation, so the update uses only the finite components; when all
are missing the update leaves the prediction unchanged. The covariance algebra itself lives in
:mod:`jaxobs.riccati`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs.riccati import predict_covariance, update_covariance

__all__ = ["Update", "predict", "update"]


class Update(NamedTuple):
    """Result of :func:`update` (shapes for ``n`` states and ``p`` outputs)."""

    x: jax.Array  # (n,) a-posteriori mean
    P: jax.Array  # (n, n) a-posteriori covariance (the given one when a fixed gain is used)
    K: jax.Array  # (n, p) gain used (zero columns for missing components)
    innovation: jax.Array  # (p,) y_k - C x_prior, 0 for missing components
    n_missing: jax.Array  # () number of missing components


def predict(x, P, Phi, Q, Gamma=None, u_prev=None, *, skip=None):
    """A-priori mean and covariance: ``(Phi x + Gamma u_prev, Phi P Phi' + Q)``.

    ``P`` may be ``None`` (fixed-gain filters propagate no covariance); ``Gamma``/``u_prev`` ``None`` for a
    model without inputs. ``skip`` (a traced bool) returns ``(x, P)`` unchanged instead: the first step of a
    filter whose prior is that of ``x_0`` (the state at the first measurement) has no prediction.
    Shapes: ``x`` (n,), ``P`` (n, n), ``Gamma`` (n, m), ``u_prev`` (m,).
    """
    x_prior = Phi @ x
    if u_prev is not None:
        x_prior = x_prior + Gamma @ u_prev
    P_prior = None if P is None else predict_covariance(P, Phi, Q)
    if skip is not None:
        x_prior = jnp.where(skip, x, x_prior)
        P_prior = None if P is None else jnp.where(skip, P, P_prior)
    return x_prior, P_prior


def update(x_prior, P_prior, C, R, y, gain=None) -> Update:
    """Measurement update of ``(x_prior, P_prior)`` with ``y`` (p,); non-finite components are missing.

    With ``gain=None`` the gain comes from ``P_prior`` and the Joseph form updates the covariance; with a
    fixed ``gain`` (n, p) the covariance is returned unchanged and the innovation of missing components is
    zero (so they do not move the estimate).
    """
    observed = jnp.isfinite(y)
    mask = observed.astype(x_prior.dtype)
    y_observed = jnp.where(observed, y, 0.0)  # before the subtraction: no NaN reaches a gradient
    innovation = (y_observed - C @ x_prior) * mask
    if gain is None:
        # drop the missing rows of C and their correlations in R (unit variance placeholder)
        R_obs = R * jnp.outer(mask, mask) + jnp.diag(1.0 - mask)
        P, K = update_covariance(P_prior, C * mask[:, None], R_obs)
    else:
        P, K = P_prior, gain
    return Update(x_prior + K @ innovation, P, K, innovation, jnp.sum(~observed))
