"""Parameter update laws, parameter projection and the excitation measure: the one home of adaptation in jaxobs.

Notation (Grip 2010 §1.3.1): unknown constant parameters ``theta`` (p,), estimate ``theta_hat``, error
``theta_tilde = theta - theta_hat``; the linear regression model ``z = phi' theta`` with regressor ``phi`` (p,) and
target ``z`` (), or ``phi`` (p, q) and ``z`` (q,) for ``q`` equations at once; the prediction error
``e = z - phi' theta_hat``. Gains ``Gamma`` are a positive scalar or a symmetric positive-definite (p, p) matrix.

Continuous-time laws return the derivative ``theta_hat_dot`` (and ``P_dot``): integrate them with any fixed-step
method, e.g. as part of a continuous-time observer's right-hand side. Discrete-time laws return the next value.
Every function is pure and works under ``jit``, ``vmap`` and ``grad``; concrete arguments are validated eagerly
(``ValueError`` naming the argument), traced ones are not.

* :func:`gradient_law`: gradient and normalised-gradient laws.
* :func:`lyapunov_law`: the Lyapunov-based law of Grip 2010 Example 1.1.
* :func:`rls_update` (discrete, forgetting factor) and :func:`rls_rate` (continuous, forgetting rate): recursive
  least squares.
* :func:`project` with the sets :class:`Ball` and :class:`Box` (or any smooth convex function): the parameter
  projection of Grip 2010 App. 5.A (after Krstić, Kanellakopoulos & Kokotović 1995, App. E); :func:`clip_step`,
  the Euler step with clipping that the thesis's discrete-time implementations use.
* :func:`excitation`: the Gram matrix of a window of regressors and its smallest eigenvalue (the persistency of
  excitation condition); :mod:`jaxobs.observers.pe_monitor` runs it over time as an estimator.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks

__all__ = [
    "gradient_law",
    "lyapunov_law",
    "rls_update",
    "rls_rate",
    "project",
    "Ball",
    "Box",
    "clip_step",
    "excitation",
]


# --------------------------------------------------------------------------------------------
# validation and shapes


def _regression(theta_hat, phi, z):
    """``(theta_hat (p,), phi (p, q), z (q,), dtype)`` with the shapes checked at trace time: ``phi`` (p,) with
    ``z`` () is the scalar regression ``q = 1``."""
    dtype = _checks.float_dtype(theta_hat=theta_hat, phi=phi, z=z)
    theta_hat = jnp.asarray(theta_hat, dtype)
    if theta_hat.ndim != 1:
        raise ValueError(f"theta_hat must be a (p,) vector, got shape {theta_hat.shape}")
    p = theta_hat.shape[0]
    phi, z = jnp.asarray(phi, dtype), jnp.asarray(z, dtype)
    if phi.ndim == 1:
        _checks.shape("phi", phi, (p,), "one entry per parameter")
        _checks.shape("z", z, (), "a scalar target for a (p,) regressor")
        return theta_hat, phi[:, None], z[None], dtype
    _checks.shape("phi", phi, (p, None), "one row per parameter")
    _checks.shape("z", z, (phi.shape[1],), "one target per column of phi")
    return theta_hat, phi, z, dtype


def _positive(name: str, value, dtype) -> jax.Array:
    _checks.positive_scalar(name, value)
    return jnp.asarray(value, dtype)


# --------------------------------------------------------------------------------------------
# gradient, Lyapunov and least-squares laws


def lyapunov_law(omega, x, Gamma) -> jax.Array:
    """The Lyapunov-based update law ``theta_hat_dot = Gamma omega x`` (Grip 2010 Example 1.1).

    For ``x_dot = f(t, x) + omega' theta_tilde`` with ``x_dot = f`` stable (Example 1.1: ``x_dot = -x +
    omega'(t) theta_tilde``, eq. 1.12), the law cancels the sign-indefinite term of the derivative of
    ``W = |x|^2 / 2 + theta_tilde' Gamma^{-1} theta_tilde / 2``, which leaves ``W_dot = -|x|^2``.

    Args:
      omega: (p,) regressor for a scalar ``x``, or (p, n) for ``x`` of size n.
      x: () or (n,) the error that the parameter error drives.
      Gamma: positive scalar or (p, p) symmetric positive-definite gain.

    Returns:
      (p,) ``theta_hat_dot``.

    Example:
      >>> import numpy as np
      >>> lyapunov_law(np.array([1.0, 2.0]), 0.5, 2.0).tolist()
      [1.0, 2.0]
    """
    omega = jnp.asarray(omega)
    if omega.ndim not in (1, 2):
        raise ValueError(f"omega must be a (p,) or (p, n) array, got shape {omega.shape}")
    dtype = _checks.float_dtype(omega=omega, x=x)
    p = omega.shape[0]
    omega, x = omega.astype(dtype), jnp.asarray(x, dtype)
    if omega.ndim == 1:
        _checks.shape("x", x, (), "a scalar for a (p,) omega")
    else:
        _checks.shape("x", x, (omega.shape[1],), "one entry per column of omega")
    return _checks.gain("Gamma", Gamma, p, dtype) @ (omega * x if omega.ndim == 1 else omega @ x)


def gradient_law(theta_hat, phi, z, Gamma, *, normalized: bool = False) -> jax.Array:
    """The gradient law for the regression ``z = phi' theta`` (Grip 2010 §1.3.1, after eq. 1.10)::

        theta_hat_dot = Gamma phi e                      (descent on J = |e|^2 / 2, e = z - phi' theta_hat)
        theta_hat_dot = Gamma phi e / (1 + |phi|^2)      (normalized; |phi|^2 = trace phi' phi)

    Args:
      theta_hat: (p,) estimate.  phi: (p,) regressor, or (p, q) for q equations.  z: () target, or (q,).
      Gamma: positive scalar or (p, p) symmetric positive-definite gain.
      normalized: divide by ``1 + |phi|^2`` (bounded rate for unbounded regressors).

    Returns:
      (p,) ``theta_hat_dot``.

    Example:
      >>> import numpy as np
      >>> gradient_law(np.zeros(2), np.array([1.0, 1.0]), 2.0, 1.0, normalized=True).tolist()
      [0.6666666666666666, 0.6666666666666666]
    """
    theta_hat, phi, z, dtype = _regression(theta_hat, phi, z)
    rate = _checks.gain("Gamma", Gamma, theta_hat.shape[0], dtype) @ (phi @ (z - phi.T @ theta_hat))
    return rate / (1 + jnp.sum(phi**2)) if normalized else rate


def rls_update(theta_hat, P, phi, z, forgetting=1.0):
    """One step of recursive least squares with forgetting factor ``lambda`` (Grip 2010 §1.3.1; Åström &
    Wittenmark 1995, Ch. 2)::

        K = P phi (lambda I + phi' P phi)^{-1}
        theta_hat+ = theta_hat + K (z - phi' theta_hat),    P+ = (P - K phi' P) / lambda

    After ``k + 1`` steps from ``(theta_0, P_0)``, ``theta_hat`` minimises ``sum_i lambda^(k-i) |z_i - phi_i'
    theta|^2 + lambda^(k+1) (theta - theta_0)' P_0^{-1} (theta - theta_0)``: the batch least-squares estimate with
    exponentially fading memory (``lambda = 1``: ordinary least squares, regularised by the prior). Non-finite
    entries of ``z`` are missing: their equations are dropped (``P`` is still divided by ``lambda``).

    Args:
      theta_hat: (p,) estimate.  P: (p, p) symmetric positive-definite matrix (``P_0``: large for a vague prior).
      phi: (p,) regressor, or (p, q).  z: () target, or (q,).  forgetting: ``lambda`` in (0, 1].

    Returns:
      ``(theta_hat, P)`` after the step.

    Example:
      >>> import numpy as np
      >>> theta, P = np.zeros(1), 1e6 * np.eye(1)
      >>> for phi, z in [(1.0, 2.0), (2.0, 4.0)]:
      ...     theta, P = rls_update(theta, P, np.array([phi]), z)
      >>> round(float(theta[0]), 6)
      2.0
    """
    theta_hat, phi, z, dtype = _regression(theta_hat, phi, z)
    p = theta_hat.shape[0]
    _checks.covariance("P", P, definite=True, size=p)
    P = jnp.asarray(P, dtype)
    lam = _forgetting_factor(forgetting, dtype)
    seen = jnp.isfinite(z)
    phi = jnp.where(seen[None, :], phi, 0)  # a missing equation carries no information
    e = jnp.where(seen, z - phi.T @ theta_hat, 0)
    Pphi = P @ phi
    S = lam * jnp.eye(phi.shape[1], dtype=dtype) + phi.T @ Pphi
    K = jnp.linalg.solve(S, Pphi.T).T  # S is symmetric
    P_next = (P - K @ Pphi.T) / lam
    return theta_hat + K @ e, (P_next + P_next.T) / 2


def _forgetting_factor(forgetting, dtype):
    if _checks.is_concrete(forgetting):
        value = np.asarray(forgetting)
        if value.ndim != 0 or not np.isfinite(value) or not 0 < float(value) <= 1:
            raise ValueError(f"forgetting must be a number in (0, 1], got {forgetting!r}")
    return jnp.asarray(forgetting, dtype)


def rls_rate(theta_hat, P, phi, z, forgetting=0.0):
    """Continuous-time recursive least squares with forgetting rate ``beta >= 0`` (Grip 2010 §1.3.1; Ioannou & Sun
    1996, Ch. 4)::

        theta_hat_dot = P phi e,    P_dot = beta P - P phi phi' P        (e = z - phi' theta_hat)

    ``P^{-1}`` then integrates ``phi phi'`` with the fading memory ``exp(-beta t)``, and ``theta_hat`` is the
    corresponding weighted least-squares estimate of the continuous-time regression.

    Args:
      theta_hat: (p,) estimate.  P: (p, p) symmetric positive-definite matrix.  phi: (p,) regressor, or (p, q).
      z: () target, or (q,).  forgetting: ``beta >= 0``.

    Returns:
      ``(theta_hat_dot, P_dot)``.

    Example:
      >>> import numpy as np
      >>> rate, P_dot = rls_rate(np.zeros(1), np.eye(1), np.array([1.0]), 2.0)
      >>> rate.tolist(), P_dot.tolist()
      ([2.0], [[-1.0]])
    """
    theta_hat, phi, z, dtype = _regression(theta_hat, phi, z)
    _checks.covariance("P", P, definite=True, size=theta_hat.shape[0])
    _checks.positive_scalar("forgetting", forgetting, allow_zero=True)
    P = jnp.asarray(P, dtype)
    Pphi = P @ phi
    P_dot = jnp.asarray(forgetting, dtype) * P - Pphi @ Pphi.T
    return Pphi @ (z - phi.T @ theta_hat), (P_dot + P_dot.T) / 2


# --------------------------------------------------------------------------------------------
# parameter projection


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Ball:
    """The ball ``|theta - center| <= radius`` as the set ``Pi = {P(theta) <= 0}`` of :func:`project`, with the
    smooth convex ``P(theta) = |theta - center|^2 / radius^2 - 1``; ``Theta = {P <= epsilon}`` is the ball of
    radius ``radius sqrt(1 + epsilon)``.

    Attributes:
      center: (p,) centre.  radius: () positive radius.
    """

    center: jax.Array
    radius: jax.Array

    def __call__(self, theta) -> jax.Array:
        """``P(theta)``."""
        return jnp.sum((theta - self.center) ** 2) / self.radius**2 - 1


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Box:
    """The box ``lower <= theta <= upper`` as the set ``Pi = {P(theta) <= 0}`` of :func:`project`, through the smooth
    convex ``P(theta) = sum_i u_i^(2 order) - 1``, ``u = (2 theta - lower - upper) / (upper - lower)``: exact for
    one parameter; for several, a superellipse inside the box that touches its faces and rounds its corners
    (``order`` sets how closely it fills them). ``Theta = {P <= epsilon}`` is ``(1 + epsilon)^(1 / (2 order))``
    times larger about the centre. (For exact boxes in discrete time, see :func:`clip_step`.)

    Attributes:
      lower: (p,) lower bounds.  upper: (p,) upper bounds, ``> lower``.  order: static positive integer.
    """

    lower: jax.Array
    upper: jax.Array
    order: int = dataclasses.field(default=4, metadata=dict(static=True))

    def __call__(self, theta) -> jax.Array:
        """``P(theta)``."""
        u = (2 * theta - self.lower - self.upper) / (self.upper - self.lower)
        return jnp.sum(u ** (2 * self.order)) - 1


def project(tau, theta_hat, Gamma, region: Callable, epsilon) -> jax.Array:
    """The parameter projection ``Proj(tau)`` of Grip 2010 App. 5.A (Krstić, Kanellakopoulos & Kokotović 1995,
    App. E): the update law ``theta_hat_dot = Proj(tau)`` keeps ``theta_hat`` in ``Theta = {P(theta_hat) <=
    epsilon}``, a boundary layer ``epsilon`` around the parameter set ``Pi = {P <= 0}`` of the smooth convex
    ``region`` function ``P``::

        Proj(tau) = tau                                          if P(theta_hat) < 0 or grad P' tau <= 0
        Proj(tau) = (I - c Gamma grad P grad P' / |grad P|_Gamma^2) tau     otherwise, in Theta \\ Pi°

    with ``c = min(1, P(theta_hat) / epsilon)`` and ``|g|_Gamma^2 = g' Gamma g``. It is Lipschitz in ``tau`` and
    ``theta_hat`` and, for every ``theta`` in ``Pi``, ``theta_hat`` in ``Theta`` (App. 5.A, Krstić et al. Lemma E.1):
    ``-theta_tilde' Gamma^{-1} Proj(tau) <= -theta_tilde' Gamma^{-1} tau`` and
    ``Proj(tau)' Gamma^{-1} Proj(tau) <= tau' Gamma^{-1} tau``; on the outer boundary ``P = epsilon`` the projected
    rate is tangent or inward, so a solution that starts in ``Theta`` stays there. (A discretised solution leaves it
    by the integrator's error, second order in the step for RK4 as ``Proj`` is Lipschitz but not smooth; for hard
    bounds in discrete time use :func:`clip_step`.)

    Args:
      tau: (p,) the unprojected rate, e.g. ``Gamma M (phi_hat - B g)`` (Grip 2010 Prop. 5.3).
      theta_hat: (p,) estimate, in ``Theta`` (checked when concrete).
      Gamma: the gain of the law (positive scalar or (p, p) symmetric positive definite).
      region: smooth convex ``P: (p,) -> ()``, e.g. :class:`Ball` or :class:`Box` (differentiated with ``jax.grad``).
      epsilon: positive width of the boundary layer, in the units of ``P``.

    Returns:
      (p,) ``Proj(tau)``.

    Example:
      >>> import numpy as np
      >>> ball = Ball(center=np.zeros(2), radius=1.0)
      >>> project(np.array([1.0, 1.0]), np.array([1.0, 0.0]), 1.0, ball, epsilon=0.1).tolist()  # P = 0: c = 0
      [1.0, 1.0]
      >>> np.round(project(np.array([1.0, 1.0]), np.array([1.04, 0.0]), 1.0, ball, epsilon=0.1), 3).tolist()
      [0.184, 1.0]
    """
    dtype = _checks.float_dtype(tau=tau, theta_hat=theta_hat)
    theta_hat = jnp.asarray(theta_hat, dtype)
    if theta_hat.ndim != 1:
        raise ValueError(f"theta_hat must be a (p,) vector, got shape {theta_hat.shape}")
    p = theta_hat.shape[0]
    tau = _checks.vector("tau", tau, p, dtype, what="one entry per parameter")
    G = _checks.gain("Gamma", Gamma, p, dtype)
    epsilon = _positive("epsilon", epsilon, dtype)
    value, grad = jax.value_and_grad(lambda t: jnp.asarray(region(t), dtype))(theta_hat)
    if _checks.is_concrete(value, epsilon) and not float(value) <= float(epsilon) * (1 + 1e-9):
        raise ValueError(
            f"theta_hat must lie in the projection set Theta = {{P(theta_hat) <= epsilon = {float(epsilon):.6g}}}, "
            f"got P(theta_hat) = {float(value):.6g}; start the estimate inside it"
        )
    along = grad @ tau
    active = (value > 0) & (along > 0)
    Gg = G @ grad
    norm2 = jnp.where(active, grad @ Gg, 1)
    c = jnp.minimum(1, value / epsilon)
    return tau - jnp.where(active, c * along / norm2, 0) * Gg


def clip_step(theta_hat, rate, dt, lower, upper) -> jax.Array:
    """The discrete-time form of a projected update that the thesis's implementations use (Grip 2010 Ch. 2 and 3:
    forward Euler, then clipping to the parameter bounds)::

        theta_hat_{k+1} = min(max(theta_hat_k + dt rate_k, lower), upper)

    Args:
      theta_hat: (p,) estimate in ``[lower, upper]`` (checked when concrete).  rate: (p,) ``theta_hat_dot``.
      dt: positive step.  lower: (p,) or () lower bounds.  upper: (p,) or () upper bounds, ``>= lower``.

    Returns:
      (p,) ``theta_hat_{k+1}``.

    Example:
      >>> import numpy as np
      >>> clip_step(np.array([0.9]), np.array([5.0]), 0.1, 0.05, 1.1).tolist()
      [1.1]
    """
    dtype = _checks.float_dtype(theta_hat=theta_hat, rate=rate, lower=lower, upper=upper)
    theta_hat = jnp.asarray(theta_hat, dtype)
    if theta_hat.ndim != 1:
        raise ValueError(f"theta_hat must be a (p,) vector, got shape {theta_hat.shape}")
    p = theta_hat.shape[0]
    rate = _checks.vector("rate", rate, p, dtype, what="one entry per parameter")
    dt = _positive("dt", dt, dtype)
    lower = _checks.per_entry("lower", lower, p, dtype)
    upper = _checks.per_entry("upper", upper, p, dtype)
    if _checks.is_concrete(lower, upper, theta_hat):
        if np.any(np.asarray(upper) < np.asarray(lower)):
            raise ValueError(f"upper must be >= lower, got lower {np.asarray(lower)}, upper {np.asarray(upper)}")
        if np.any((np.asarray(theta_hat) < np.asarray(lower)) | (np.asarray(theta_hat) > np.asarray(upper))):
            raise ValueError(
                f"theta_hat must lie in [lower, upper] = [{np.asarray(lower)}, {np.asarray(upper)}], "
                f"got {np.asarray(theta_hat)}"
            )
    return jnp.clip(theta_hat + dt * rate, lower, upper)


# --------------------------------------------------------------------------------------------
# persistency of excitation


def excitation(regressors, dt):
    """The Gram matrix of a window of sampled regressors and its smallest eigenvalue: the rectangle-rule value of
    ``int_t^{t+T} omega omega' dtau`` of the persistency-of-excitation condition ``>= epsilon I`` (Grip 2010 §1.3.1,
    Example 1.1 continued; Prop. 5.4's ``int S dtau``).

    Args:
      regressors: (N, p) the regressors ``omega_k`` of the window (rows), or (N, p, q) for (p, q) regressors
        (``sum_k omega_k omega_k'``).
      dt: positive sample period (``T = N dt``).

    Returns:
      ``(gram, lambda_min)``: (p, p) ``dt sum_k omega_k omega_k'`` and its smallest eigenvalue.

    Example:
      >>> import numpy as np
      >>> t = 0.01 * np.arange(629)
      >>> gram, low = excitation(np.stack([np.sin(t), np.cos(t)], axis=1), 0.01)
      >>> round(float(low), 2)  # int_0^2pi sin^2 = pi
      3.14
    """
    W = jnp.asarray(regressors)
    if W.ndim == 2:
        W = W[..., None]
    if W.ndim != 3:
        raise ValueError(f"regressors must be an (N, p) or (N, p, q) array, got shape {jnp.shape(regressors)}")
    dtype = _checks.float_dtype(regressors=W, dt=dt)
    dt = _positive("dt", dt, dtype)
    W = W.astype(dtype)
    gram = dt * jnp.einsum("kiq,kjq->ij", W, W)
    gram = (gram + gram.T) / 2
    return gram, jnp.linalg.eigvalsh(gram)[0]
