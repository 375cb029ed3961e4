"""Parameter update laws, parameter projection and the excitation measure: the one home of adaptation in jaxobs.

Gradient and Lyapunov laws for a linear regression ``z = omega' theta`` (:func:`regression_gradient_law`,
:func:`lyapunov_law`), recursive least squares (:func:`rls_update`, :func:`rls_rate`), the laws of the
perturbation-based observers (:class:`InversionLaw`, :class:`PerturbationGradientLaw`, :class:`CustomLaw`), the
parameter projection (:func:`project` with :class:`Ball`, :class:`Box`; :func:`clip_step`) and the excitation
measure (:func:`excitation`), after Grip 2010 §1.3.1 and App. 5.A. The adaptation gain ``adaptation_gain`` (the
thesis's ``Gamma``) is a positive scalar or a symmetric positive-definite (n_theta, n_theta) matrix. Continuous-time
laws return ``theta_hat_dot``, discrete-time ones the next value. Notation and equations:
docs/theory/adaptive.md.

Input contract: shapes are checked at trace time; eagerly, non-finite values, a gain that is not symmetric positive
definite, ``epsilon <= 0``, a :class:`Ball` radius ``<= 0`` and :class:`Box` bounds with ``lower >= upper`` raise
``ValueError`` naming the argument. Under ``jit`` nothing raises: a non-finite input gives a non-finite result, and
an invalid region or box (traced) gives NaN, never a result that looks valid (each function says which).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks

__all__ = [
    "regression_gradient_law",
    "lyapunov_law",
    "rls_update",
    "rls_rate",
    "project",
    "Ball",
    "Box",
    "clip_step",
    "InversionLaw",
    "PerturbationGradientLaw",
    "CustomLaw",
    "check_law",
    "excitation",
]


# --------------------------------------------------------------------------------------------
# validation and shapes


def _estimate(theta_hat, dtype) -> jax.Array:
    """``theta_hat`` as a finite (where concrete) (n_theta,) vector in ``dtype`` (shape checked at trace time)."""
    theta_hat = jnp.asarray(theta_hat, dtype)
    if theta_hat.ndim != 1:
        raise ValueError(f"theta_hat must be a (n_theta,) vector, got shape {theta_hat.shape}")
    _checks.finite("theta_hat", theta_hat)
    return theta_hat


def _regression(theta_hat, omega, z, *, missing: bool = False):
    """``(theta_hat (n_theta,), omega (n_theta, q), z (q,), dtype)`` with the shapes checked at trace time and the
    values finite where concrete (``missing``: non-finite ``z`` allowed, missing data): ``omega`` (n_theta,) with
    ``z`` () is the scalar regression ``q = 1``."""
    dtype = _checks.float_dtype(theta_hat=theta_hat, omega=omega, z=z)
    theta_hat = _estimate(theta_hat, dtype)
    n_theta = theta_hat.shape[0]
    omega, z = jnp.asarray(omega, dtype), jnp.asarray(z, dtype)
    _checks.finite("omega", omega)
    if not missing:
        _checks.finite("z", z)
    if omega.ndim == 1:
        _checks.shape("omega", omega, (n_theta,), "one entry per parameter")
        _checks.shape("z", z, (), "a scalar target for a (n_theta,) regressor")
        return theta_hat, omega[:, None], z[None], dtype
    _checks.shape("omega", omega, (n_theta, None), "one row per parameter")
    _checks.shape("z", z, (omega.shape[1],), "one target per column of omega")
    return theta_hat, omega, z, dtype


def _positive(name: str, value, dtype) -> jax.Array:
    _checks.positive_scalar(name, value)
    return jnp.asarray(value, dtype)


# --------------------------------------------------------------------------------------------
# gradient, Lyapunov and least-squares laws


def lyapunov_law(omega, x, adaptation_gain) -> jax.Array:
    """The Lyapunov-based update law ``theta_hat_dot = Gamma omega x`` (Grip 2010 Example 1.1, ``Gamma`` the
    adaptation gain).

    For ``x_dot = f(t, x) + omega' theta_tilde`` with ``x_dot = f`` stable (Example 1.1: ``x_dot = -x +
    omega'(t) theta_tilde``, eq. 1.12), the law cancels the sign-indefinite term of the derivative of
    ``W = |x|^2 / 2 + theta_tilde' Gamma^{-1} theta_tilde / 2``, which leaves ``W_dot = -|x|^2``.

    Args:
      omega: (n_theta,) regressor for a scalar ``x``, or (n_theta, n) for ``x`` of size n; finite.
      x: () or (n,) the error that the parameter error drives; finite.
      adaptation_gain: positive scalar or (n_theta, n_theta) symmetric positive-definite ``Gamma``.

    Returns:
      (n_theta,) ``theta_hat_dot`` (non-finite where traced inputs are).

    Example:
      >>> import numpy as np
      >>> lyapunov_law(np.array([1.0, 2.0]), 0.5, 2.0).tolist()
      [1.0, 2.0]
    """
    omega = _checks.real_array("omega", omega)
    if omega.ndim not in (1, 2):
        raise ValueError(f"omega must be a (n_theta,) or (n_theta, n) array, got shape {omega.shape}")
    dtype = _checks.float_dtype(omega=omega, x=x)
    n_theta = omega.shape[0]
    omega, x = omega.astype(dtype), jnp.asarray(x, dtype)
    if omega.ndim == 1:
        _checks.shape("x", x, (), "a scalar for a (n_theta,) omega")
    else:
        _checks.shape("x", x, (omega.shape[1],), "one entry per column of omega")
    _checks.finite("omega", omega)
    _checks.finite("x", x)
    gain = _checks.gain("adaptation_gain", adaptation_gain, n_theta, dtype)
    return gain @ (omega * x if omega.ndim == 1 else omega @ x)


def regression_gradient_law(theta_hat, omega, z, adaptation_gain, *, normalized: bool = False) -> jax.Array:
    """The gradient law for the linear regression ``z = omega' theta`` (Grip 2010 §1.3.1, after eq. 1.10).

    With ``Gamma`` the adaptation gain::

        theta_hat_dot = Gamma omega e                        (descent on J = |e|^2 / 2, e = z - omega' theta_hat)
        theta_hat_dot = Gamma omega e / (1 + |omega|^2)      (normalized; |omega|^2 = trace omega' omega)

    Args:
      theta_hat: (n_theta,) estimate.  omega: (n_theta,) regressor, or (n_theta, q) for q equations.
      z: () target, or (q,).  All finite.
      adaptation_gain: positive scalar or (n_theta, n_theta) symmetric positive-definite ``Gamma``.
      normalized: divide by ``1 + |omega|^2`` (bounded rate for unbounded regressors).

    Returns:
      (n_theta,) ``theta_hat_dot`` (non-finite where traced inputs are).

    Example:
      >>> import numpy as np
      >>> regression_gradient_law(np.zeros(2), np.array([1.0, 1.0]), 2.0, 1.0, normalized=True).tolist()
      [0.6666666666666666, 0.6666666666666666]
    """
    theta_hat, omega, z, dtype = _regression(theta_hat, omega, z)
    gain = _checks.gain("adaptation_gain", adaptation_gain, theta_hat.shape[0], dtype)
    rate = gain @ (omega @ (z - omega.T @ theta_hat))
    return rate / (1 + jnp.sum(omega**2)) if _checks.boolean("normalized", normalized) else rate


def rls_update(theta_hat, P, omega, z, forgetting=1.0):
    """One step of recursive least squares with forgetting factor ``lambda`` (Grip 2010 §1.3.1; Åström &
    Wittenmark 1995, Ch. 2).

    It computes::

        K = P omega (lambda I + omega' P omega)^{-1}
        theta_hat+ = theta_hat + K (z - omega' theta_hat),    P+ = (P - K omega' P) / lambda

    After ``k + 1`` steps from ``(theta_0, P_0)``, ``theta_hat`` minimises ``sum_i lambda^(k-i) |z_i - omega_i'
    theta|^2 + lambda^(k+1) (theta - theta_0)' P_0^{-1} (theta - theta_0)``: the batch least-squares estimate with
    exponentially fading memory (``lambda = 1``: ordinary least squares, regularised by the prior). Non-finite
    entries of ``z`` are missing: their equations are dropped (``P`` is still divided by ``lambda``). A non-finite
    column of ``omega`` raises eagerly; under ``jit`` its equation is dropped as missing, so ``theta_hat`` and ``P``
    stay finite.

    Args:
      theta_hat: (n_theta,) finite estimate.  P: (n_theta, n_theta) symmetric positive-definite matrix (``P_0``:
        large for a vague prior).  omega: (n_theta,) finite regressor, or (n_theta, q).  z: () target, or (q,)
        (NaN: missing).
      forgetting: ``lambda`` in (0, 1].

    Returns:
      ``(theta_hat, P)`` after the step.

    Example:
      >>> import numpy as np
      >>> theta, P = np.zeros(1), 1e6 * np.eye(1)
      >>> for omega, z in [(1.0, 2.0), (2.0, 4.0)]:
      ...     theta, P = rls_update(theta, P, np.array([omega]), z)
      >>> round(float(theta[0]), 6)
      2.0
    """
    theta_hat, omega, z, dtype = _regression(theta_hat, omega, z, missing=True)
    n_theta = theta_hat.shape[0]
    _checks.covariance("P", P, definite=True, size=n_theta)
    P = jnp.asarray(P, dtype)
    lam = _forgetting_factor(forgetting, dtype)
    seen = jnp.isfinite(z) & jnp.all(jnp.isfinite(omega), axis=0)
    omega = jnp.where(seen[None, :], omega, 0)  # a missing equation carries no information
    e = jnp.where(seen, z - omega.T @ theta_hat, 0)
    P_omega = P @ omega
    S = lam * jnp.eye(omega.shape[1], dtype=dtype) + omega.T @ P_omega
    K = jnp.linalg.solve(S, P_omega.T).T  # S is symmetric
    P_next = (P - K @ P_omega.T) / lam
    return theta_hat + K @ e, (P_next + P_next.T) / 2


def _forgetting_factor(forgetting, dtype):
    _checks.shapes("forgetting ()", forgetting)
    if _checks.is_concrete(forgetting):
        value = np.asarray(forgetting)
        if value.ndim != 0 or not np.isfinite(value) or not 0 < float(value) <= 1:
            raise ValueError(f"forgetting must be a number in (0, 1], got {forgetting!r}")
    return jnp.asarray(forgetting, dtype)


def rls_rate(theta_hat, P, omega, z, forgetting=0.0):
    """Continuous-time recursive least squares with forgetting rate ``beta >= 0`` (Grip 2010 §1.3.1; Ioannou & Sun
    1996, Ch. 4).

    It returns the rates of::

        theta_hat_dot = P omega e,    P_dot = beta P - P omega omega' P        (e = z - omega' theta_hat)

    ``P^{-1}`` then integrates ``omega omega'`` with the fading memory ``exp(-beta t)``, and ``theta_hat`` is the
    corresponding weighted least-squares estimate of the continuous-time regression.

    Args:
      theta_hat: (n_theta,) estimate.  P: (n_theta, n_theta) symmetric positive-definite matrix.
      omega: (n_theta,) regressor, or (n_theta, q).  z: () target, or (q,).  All finite.
      forgetting: ``beta >= 0``.

    Returns:
      ``(theta_hat_dot, P_dot)`` (non-finite where traced inputs are).

    Example:
      >>> import numpy as np
      >>> rate, P_dot = rls_rate(np.zeros(1), np.eye(1), np.array([1.0]), 2.0)
      >>> rate.tolist(), P_dot.tolist()
      ([2.0], [[-1.0]])
    """
    theta_hat, omega, z, dtype = _regression(theta_hat, omega, z)
    _checks.covariance("P", P, definite=True, size=theta_hat.shape[0])
    _checks.positive_scalar("forgetting", forgetting, allow_zero=True)
    P = jnp.asarray(P, dtype)
    P_omega = P @ omega
    P_dot = jnp.asarray(forgetting, dtype) * P - P_omega @ P_omega.T
    return P_omega @ (z - omega.T @ theta_hat), (P_dot + P_dot.T) / 2


# --------------------------------------------------------------------------------------------
# parameter projection


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Ball:
    """The ball ``|theta - center| <= radius`` as the set ``Pi = {P(theta) <= 0}`` of :func:`project`, with the
    smooth convex ``P(theta) = |theta - center|^2 / radius^2 - 1``; ``Theta = {P <= epsilon}`` is the ball of
    radius ``radius sqrt(1 + epsilon)``.

    Attributes:
      center: (n_theta,) finite centre.  radius: () finite radius ``> 0`` (checked eagerly by :func:`project` and
        :func:`check_law`; a traced radius ``<= 0`` makes ``P`` NaN).
    """

    center: jax.Array
    radius: jax.Array

    def __call__(self, theta) -> jax.Array:
        """``P(theta)``."""
        value = jnp.sum((theta - self.center) ** 2) / self.radius**2 - 1
        return jnp.where(self.radius > 0, value, jnp.nan)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Box:
    """The box ``lower <= theta <= upper`` as the set ``Pi = {P(theta) <= 0}`` of :func:`project`.

    ``P`` is the smooth convex ``P(theta) = sum_i u_i^(2 order) - 1``, ``u = (2 theta - lower - upper) / (upper -
    lower)``: exact for one parameter; for several, a superellipse inside the box that touches its faces and rounds
    its corners (``order`` sets how closely it fills them). ``Theta = {P <= epsilon}`` is ``(1 + epsilon)^(1 / (2
    order))`` times larger about the centre. (For exact boxes in discrete time, see :func:`clip_step`.)

    Attributes:
      lower: (n_theta,) finite lower bounds.  upper: (n_theta,) finite upper bounds, ``> lower`` (checked eagerly by
        :func:`project` and :func:`check_law`; traced bounds with ``upper <= lower`` make ``P`` NaN).
      order: static positive integer.
    """

    lower: jax.Array
    upper: jax.Array
    order: int = dataclasses.field(default=4, metadata=dict(static=True))

    def __call__(self, theta) -> jax.Array:
        """``P(theta)``."""
        u = (2 * theta - self.lower - self.upper) / (self.upper - self.lower)
        return jnp.where(jnp.all(self.upper > self.lower), jnp.sum(u ** (2 * self.order)) - 1, jnp.nan)


def _check_region(region, n_theta: int) -> None:
    """Check a :class:`Ball` or :class:`Box` for ``n_theta`` parameters (shapes always, values where concrete),
    naming the field; any other callable ``P`` is the user's."""
    if isinstance(region, Ball):
        _checks.shape("region.center", region.center, (n_theta,), "one entry per parameter")
        _checks.finite("region.center", region.center)
        _checks.shape("region.radius", region.radius, (), "a scalar")
        _checks.positive_scalar("region.radius", region.radius)
    elif isinstance(region, Box):
        for name in ("lower", "upper"):
            _checks.shape(f"region.{name}", getattr(region, name), (n_theta,), "one bound per parameter")
            _checks.finite(f"region.{name}", getattr(region, name))
        _checks.count("region.order", region.order, minimum=1)
        if _checks.is_concrete(region.lower, region.upper):
            lower, upper = np.asarray(region.lower), np.asarray(region.upper)
            if np.any(upper <= lower):
                raise ValueError(f"region.upper must be > region.lower, got lower {lower}, upper {upper}")


def project(tau, theta_hat, adaptation_gain, region: Callable, epsilon) -> jax.Array:
    r"""The parameter projection ``Proj(tau)`` of Grip 2010 App. 5.A (Krstić, Kanellakopoulos & Kokotović 1995,
    App. E).

    The update law ``theta_hat_dot = Proj(tau)`` keeps ``theta_hat`` in ``Theta = {P(theta_hat) <=
    epsilon}``, a boundary layer ``epsilon`` around the parameter set ``Pi = {P <= 0}`` of the smooth convex
    ``region`` function ``P``::

        Proj(tau) = tau                                          if P(theta_hat) < 0 or grad P' tau <= 0
        Proj(tau) = (I - c Gamma grad P grad P' / |grad P|_Gamma^2) tau     otherwise, in Theta \ Pi°

    with ``c = min(1, P(theta_hat) / epsilon)``, ``Gamma`` the adaptation gain and ``|g|_Gamma^2 = g' Gamma g``. It is
    Lipschitz in ``tau`` and ``theta_hat`` and, for every ``theta`` in ``Pi``, ``theta_hat`` in ``Theta`` (App.
    5.A, Krstić et al. Lemma E.1): ``-theta_tilde' Gamma^{-1} Proj(tau) <= -theta_tilde' Gamma^{-1} tau`` and
    ``Proj(tau)' Gamma^{-1} Proj(tau) <= tau' Gamma^{-1} tau``; on the outer boundary ``P = epsilon`` the projected
    rate is tangent or inward, so a solution that starts in ``Theta`` stays there. (A discretised solution leaves it
    by the integrator's error, second order in the step for RK4 as ``Proj`` is Lipschitz but not smooth; for hard
    bounds in discrete time use :func:`clip_step`.)

    Args:
      tau: (n_theta,) the unprojected rate, e.g. ``Gamma M (phi_hat - B g)`` (Grip 2010 Prop. 5.3); finite.
      theta_hat: (n_theta,) finite estimate, in ``Theta`` (checked when concrete).
      adaptation_gain: ``Gamma``, the gain of the law (positive scalar or (n_theta, n_theta) symmetric positive
        definite).
      region: smooth convex ``P: (n_theta,) -> ()``, e.g. :class:`Ball` or :class:`Box` (differentiated with
        ``jax.grad``).
      epsilon: positive width of the boundary layer, in the units of ``P``.

    Returns:
      (n_theta,) ``Proj(tau)``; NaN where ``P(theta_hat)`` or its gradient is not finite or ``epsilon <= 0``
      (under ``jit``: a non-finite input, a :class:`Ball` radius ``<= 0``, :class:`Box` bounds with ``upper <=
      lower``).

    Example:
      >>> import numpy as np
      >>> ball = Ball(center=np.zeros(2), radius=1.0)
      >>> project(np.array([1.0, 1.0]), np.array([1.0, 0.0]), 1.0, ball, epsilon=0.1).tolist()  # P = 0: c = 0
      [1.0, 1.0]
      >>> np.round(project(np.array([1.0, 1.0]), np.array([1.04, 0.0]), 1.0, ball, epsilon=0.1), 3).tolist()
      [0.184, 1.0]
    """
    dtype = _checks.float_dtype(tau=tau, theta_hat=theta_hat)
    theta_hat = _estimate(theta_hat, dtype)
    n_theta = theta_hat.shape[0]
    tau = _checks.vector("tau", tau, n_theta, dtype, what="one entry per parameter")
    G = _checks.gain("adaptation_gain", adaptation_gain, n_theta, dtype)
    epsilon = _positive("epsilon", epsilon, dtype)
    if not callable(region):
        raise ValueError(f"region must be a callable P(theta) -> (), e.g. jaxobs.adaptive.Ball, got {region!r}")
    _check_region(region, n_theta)
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
    defined = jnp.isfinite(value) & jnp.all(jnp.isfinite(grad)) & (epsilon > 0)
    return jnp.where(defined, tau - jnp.where(active, c * along / norm2, 0) * Gg, jnp.nan)


def clip_step(theta_hat, rate, dt, lower, upper) -> jax.Array:
    """The discrete-time form of a projected update that the thesis's implementations use (Grip 2010 Ch. 2 and 3).

    Forward Euler, then clipping to the parameter bounds::

        theta_hat_{k+1} = min(max(theta_hat_k + dt rate_k, lower), upper)

    Args:
      theta_hat: (n_theta,) finite estimate in ``[lower, upper]`` (checked when concrete).  rate: (n_theta,) finite
        ``theta_hat_dot``.  dt: positive step.  lower: (n_theta,) or () finite lower bounds.  upper: (n_theta,) or ()
        finite upper bounds, ``>= lower``.

    Returns:
      (n_theta,) ``theta_hat_{k+1}``; NaN for the parameters whose traced bounds have ``upper < lower``.

    Example:
      >>> import numpy as np
      >>> clip_step(np.array([0.9]), np.array([5.0]), 0.1, 0.05, 1.1).tolist()
      [1.1]
    """
    dtype = _checks.float_dtype(theta_hat=theta_hat, rate=rate, lower=lower, upper=upper)
    theta_hat = _estimate(theta_hat, dtype)
    n_theta = theta_hat.shape[0]
    rate = _checks.vector("rate", rate, n_theta, dtype, what="one entry per parameter")
    dt = _positive("dt", dt, dtype)
    lower = _checks.per_entry("lower", lower, n_theta, dtype)
    upper = _checks.per_entry("upper", upper, n_theta, dtype)
    if _checks.is_concrete(lower, upper, theta_hat):
        if np.any(np.asarray(upper) < np.asarray(lower)):
            raise ValueError(f"upper must be >= lower, got lower {np.asarray(lower)}, upper {np.asarray(upper)}")
        if np.any((np.asarray(theta_hat) < np.asarray(lower)) | (np.asarray(theta_hat) > np.asarray(upper))):
            raise ValueError(
                f"theta_hat must lie in [lower, upper] = [{np.asarray(lower)}, {np.asarray(upper)}], "
                f"got {np.asarray(theta_hat)}"
            )
    return jnp.where(upper >= lower, jnp.clip(theta_hat + dt * rate, lower, upper), jnp.nan)


# --------------------------------------------------------------------------------------------
# update laws of the perturbation-based observers


def _wrap_functions(law, *names):
    """Store the named callables of a law as ``Partial``s (bound arguments become pytree leaves)."""
    for name in names:
        fn = getattr(law, name)
        if fn is not None:
            object.__setattr__(law, name, _checks.function(name, fn))


def _rate(law, direction, theta_hat) -> jax.Array:
    """``Proj(Gamma direction)`` with the law's adaptation gain ``Gamma`` and projection set (none without a
    ``region``)."""
    tau = _checks.gain("adaptation_gain", law.adaptation_gain, theta_hat.shape[0], theta_hat.dtype) @ direction
    if law.region is None:
        return tau
    return project(tau, theta_hat, law.adaptation_gain, law.region, law.epsilon)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class InversionLaw:
    """The inversion law ``theta_hat' = Proj(l Gamma (theta*(*args, phi_hat) - theta_hat))`` (Grip 2010 Props. 5.1
    and 6.1 with ``l = 1``; Props. 5.2 and 6.2 with a weight ``l >= 0`` whose integral over every window of some
    length stays above a positive bound), times the indicator of ``|phi_hat| >= threshold`` (§6.8: the update
    pauses while the perturbation is too small to invert for ``theta``). Where the update pauses (``l = 0`` or
    ``|phi_hat| < threshold``), ``theta_star`` and ``weight`` see a stand-in ``phi_hat`` of norm ``threshold`` and
    their results are discarded, so an inverse that divides by ``phi_hat`` gives no NaN, in values or gradients.

    Called as every law: ``law(g, args, phi_hat, theta_hat) -> theta_hat'`` (n_theta,), with ``phi_hat`` (k,) the
    perturbation estimate and ``args`` the observer's arguments of ``g`` (``(t, x)`` in
    :mod:`jaxobs.observers.modular`, ``(v, x_hat)`` in :mod:`jaxobs.observers.hgo`).

    Attributes:
      theta_star: ``theta*(*args, phi) -> (n_theta,)``, the parameter solved from ``phi = g(*args, theta)``.
      adaptation_gain: ``Gamma``, a positive scalar or (n_theta, n_theta) symmetric positive-definite matrix.
      weight: ``l(*args, phi) -> ()``, ``>= 0`` (Props. 5.2: in [0, 1], and 6.2), or None for ``l = 1``.
      threshold: () ``>= 0``, the smallest ``|phi_hat|`` the law inverts.
      region: the smooth convex ``P`` of the projection set (:class:`Ball`, :class:`Box`; :func:`project`), or None.
      epsilon: () positive boundary-layer width of the projection.
    """

    theta_star: Callable
    adaptation_gain: jax.Array
    weight: Callable | None = None
    threshold: jax.Array = 0.0
    region: Callable | None = None
    epsilon: jax.Array = 0.1

    def __post_init__(self):
        """Store ``theta_star`` and ``weight`` as ``Partial``s."""
        _wrap_functions(self, "theta_star", "weight")

    def __call__(self, g, args, phi_hat, theta_hat) -> jax.Array:
        """``theta_hat'`` (n_theta,); ``g`` is unused, as ``theta_star`` encodes the model."""
        del g  # the inverse theta* already encodes the model
        above = jnp.linalg.norm(phi_hat) >= self.threshold
        safe = jnp.where(above, phi_hat, self.threshold / jnp.sqrt(phi_hat.shape[0]))
        weight = 1.0 if self.weight is None else self.weight(*args, safe)
        active = above & (weight > 0)
        direction = jnp.where(active, weight * (self.theta_star(*args, safe) - theta_hat), 0.0)
        return _rate(self, direction, theta_hat)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PerturbationGradientLaw:
    """The gradient-type law ``theta_hat' = Proj(Gamma M(*args, theta_hat) (phi_hat - g(*args, theta_hat)))``
    (Grip 2010 Props. 5.3, 5.4, 6.3 and 6.4).

    By default ``M`` is the gradient search ``M = (dg/dtheta)'`` (autodiff; Remark 5.1: steepest descent of
    ``|g(theta) - g(theta_hat)|^2``). Called as every law: ``law(g, args, phi_hat, theta_hat) -> theta_hat'`` (see
    :class:`InversionLaw`). (The gradient law of a linear regression ``z = omega'
    theta`` is :func:`regression_gradient_law`.)

    Attributes:
      adaptation_gain: ``Gamma``, a positive scalar or (n_theta, n_theta) symmetric positive-definite matrix.
      M: ``M(*args, theta_hat) -> (n_theta, k)`` satisfying (5.6) or (5.7) (modular estimator), (6.14) or (6.15)
        (high-gain observer); None for ``(dg/dtheta)'``.
      region: the smooth convex ``P`` of the projection set (:class:`Ball`, :class:`Box`; :func:`project`), or None.
      epsilon: () positive boundary-layer width of the projection.
    """

    adaptation_gain: jax.Array
    M: Callable | None = None
    region: Callable | None = None
    epsilon: jax.Array = 0.1

    def __post_init__(self):
        """Store ``M`` as a ``Partial``."""
        _wrap_functions(self, "M")

    def __call__(self, g, args, phi_hat, theta_hat) -> jax.Array:
        """``theta_hat'`` (n_theta,) along ``M (phi_hat - g(*args, theta_hat))``."""
        if self.M is None:
            M = jax.jacfwd(lambda th: g(*args, th))(theta_hat).T
        else:
            M = self.M(*args, theta_hat)
        return _rate(self, M @ (phi_hat - g(*args, theta_hat)), theta_hat)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CustomLaw:
    """A hand-made law ``theta_hat' = Proj(Gamma direction(g, args, phi_hat, theta_hat))``: laws that combine the
    others per parameter (Grip 2010 Example 5.5) or are designed by hand (the drilling estimator's (5.26)-(5.27)).
    Called as every law: ``law(g, args, phi_hat, theta_hat) -> theta_hat'`` (see :class:`InversionLaw`).

    Attributes:
      direction: ``direction(g, args, phi_hat, theta_hat) -> (n_theta,)``, the rate before the adaptation gain.
      adaptation_gain: ``Gamma``, a positive scalar or (n_theta, n_theta) symmetric positive-definite matrix.
      region: the smooth convex ``P`` of the projection set (:class:`Ball`, :class:`Box`; :func:`project`), or None.
      epsilon: () positive boundary-layer width of the projection.
    """

    direction: Callable
    adaptation_gain: jax.Array = 1.0
    region: Callable | None = None
    epsilon: jax.Array = 0.1

    def __post_init__(self):
        """Store ``direction`` as a ``Partial``."""
        _wrap_functions(self, "direction")

    def __call__(self, g, args, phi_hat, theta_hat) -> jax.Array:
        """``theta_hat'`` (n_theta,) along the user's ``direction``."""
        return _rate(self, self.direction(g, args, phi_hat, theta_hat), theta_hat)


def check_law(law, theta0) -> None:
    """Check eagerly, naming the field, an update law for the start ``theta0`` (n_theta,): a positive-definite
    ``adaptation_gain``, a positive ``epsilon``, a non-negative ``threshold`` and ``theta0`` inside the projection
    set ``Theta = {P <= epsilon}`` (concrete values only); called by the observers' builders."""
    if not isinstance(law, InversionLaw | PerturbationGradientLaw | CustomLaw):
        raise ValueError(
            f"law must be an update law (InversionLaw, PerturbationGradientLaw, CustomLaw), got {law!r} (a hand-made "
            "law is a CustomLaw)"
        )
    theta0 = jnp.asarray(theta0)
    dtype = _checks.float_dtype(theta0=theta0)
    _checks.gain("adaptation_gain", law.adaptation_gain, theta0.shape[0], dtype)
    _checks.positive_scalar("epsilon", law.epsilon)
    if isinstance(law, InversionLaw):
        _checks.positive_scalar("threshold", law.threshold, allow_zero=True)
    if law.region is None:
        return
    if not callable(law.region):
        raise ValueError(f"region must be a callable P(theta) -> (), e.g. jaxobs.adaptive.Box, got {law.region!r}")
    _check_region(law.region, theta0.shape[0])
    _checks.returns("region(theta)", law.region, (theta0,), (), "the scalar P(theta) of the projection set")
    value = law.region(theta0)
    if _checks.is_concrete(value, law.epsilon) and not float(value) <= float(law.epsilon):
        raise ValueError(
            f"theta0 must lie in the projection set {{P(theta) <= epsilon = {float(law.epsilon):.6g}}}, got "
            f"P(theta0) = {float(value):.6g}"
        )


# --------------------------------------------------------------------------------------------
# persistency of excitation


def excitation(regressors, dt):
    """The Gram matrix of a window of sampled regressors and its smallest eigenvalue: the rectangle-rule value of
    ``int_t^{t+T} omega omega' dtau`` of the persistency-of-excitation condition ``>= epsilon I`` (Grip 2010 §1.3.1,
    Example 1.1 continued; Prop. 5.4's ``int S dtau``).

    Args:
      regressors: (N, n_theta) finite regressors ``omega_k`` of the window (rows), or (N, n_theta, q) for
        (n_theta, q) regressors (``sum_k omega_k omega_k'``).
      dt: positive sample period (``T = N dt``).

    Returns:
      ``(gram, lambda_min)``: (n_theta, n_theta) ``dt sum_k omega_k omega_k'`` and its smallest eigenvalue (NaN
      when traced regressors are not finite).

    Example:
      >>> import numpy as np
      >>> t = 0.01 * np.arange(629)
      >>> gram, low = excitation(np.stack([np.sin(t), np.cos(t)], axis=1), 0.01)
      >>> round(float(low), 2)  # int_0^2pi sin^2 = pi
      3.14
    """
    W = _checks.real_array("regressors", regressors)
    if W.ndim == 2:
        W = W[..., None]
    if W.ndim != 3:
        raise ValueError(
            f"regressors must be an (N, n_theta) or (N, n_theta, q) array, got shape {jnp.shape(regressors)}"
        )
    dtype = _checks.float_dtype(regressors=W, dt=dt)
    _checks.finite("regressors", W)
    dt = _positive("dt", dt, dtype)
    W = W.astype(dtype)
    gram = dt * jnp.einsum("kiq,kjq->ij", W, W)
    gram = (gram + gram.T) / 2
    finite = jnp.all(jnp.isfinite(gram))
    return gram, jnp.where(finite, jnp.linalg.eigvalsh(jnp.where(finite, gram, 0))[0], jnp.nan)
