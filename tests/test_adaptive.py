"""Tests for jaxobs.adaptive: the update laws (regression gradient, normalised gradient, Lyapunov law of Grip 2010
Example 1.1, discrete and continuous RLS with forgetting; the inversion, perturbation-gradient and custom laws of the
perturbation-based observers), the parameter projection of Grip 2010 App. 5.A with its two
inequalities and set invariance, the clipping form, and the excitation measure.

Continuous-time laws are integrated by a fixed-step RK4 written here (``_rk4``), to be replaced by jaxobs.ct."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from jaxobs.adaptive import (
    Ball,
    Box,
    CustomLaw,
    InversionLaw,
    PerturbationGradientLaw,
    check_law,
    clip_step,
    excitation,
    lyapunov_law,
    project,
    regression_gradient_law,
    rls_rate,
    rls_update,
)


def _rk4(f, state, h, steps):
    """Classical fixed-step RK4 of ``state_dot = f(t, state)`` (a pytree) over ``steps`` steps of ``h`` from t = 0;
    returns the final state and the states after every step."""
    add = lambda a, b, s: jax.tree.map(lambda x, y: x + s * y, a, b)

    def step(x, k):
        t = k * h
        k1 = f(t, x)
        k2 = f(t + h / 2, add(x, k1, h / 2))
        k3 = f(t + h / 2, add(x, k2, h / 2))
        k4 = f(t + h, add(x, k3, h))
        x = jax.tree.map(lambda x, a, b, c, d: x + h / 6 * (a + 2 * b + 2 * c + d), x, k1, k2, k3, k4)
        return x, x

    return jax.lax.scan(step, state, jnp.arange(steps))


# ---------------------------------------------------------------------------------------------
# gradient and Lyapunov laws


def test_gradient_laws_descend_the_weighted_parameter_error():
    """The gradient law is Gamma omega e (e = z - omega' theta_hat), the normalised one that over 1 + |omega|^2, and
    both decrease V = theta_tilde' Gamma^{-1} theta_tilde / 2 at the rate |e|^2 (resp. |e|^2 / (1 + |omega|^2)) when
    z = omega' theta: the reason for the law (Grip 2010 §1.3.1). Scalar and (n_theta, q) regressors."""
    rng = np.random.default_rng(0)
    L = rng.normal(size=(3, 3))
    gain = L @ L.T + 0.5 * np.eye(3)
    theta, theta_hat = rng.normal(size=3), rng.normal(size=3)
    for omega in (rng.normal(size=3), rng.normal(size=(3, 2))):
        z = omega.T @ theta
        e = z - omega.T @ theta_hat
        Omega = omega.reshape(3, -1)
        for normalized, m2 in ((False, 1.0), (True, 1 + np.sum(omega**2))):
            rate = np.asarray(regression_gradient_law(theta_hat, omega, z, gain, normalized=normalized))
            np.testing.assert_allclose(rate, gain @ Omega @ np.atleast_1d(e) / m2, rtol=1e-13)
            V_dot = -(theta - theta_hat) @ np.linalg.solve(gain, rate)
            assert V_dot == pytest.approx(-np.sum(e**2) / m2, rel=1e-12)
    assert np.allclose(
        regression_gradient_law(theta_hat, omega[:, 0], z[0], 2.0), 2 * omega[:, 0] * (z[0] - omega[:, 0] @ theta_hat)
    )


def _example_1_1(omega, gain, theta, x0, T, h=0.005):
    """Grip 2010 Example 1.1: x_dot = omega(t)' theta + u, u = -x - omega(t)' theta_hat, theta_hat_dot = Gamma omega x
    (lyapunov_law), with the integral of x^2 carried along; RK4 from theta_hat = 0. Returns the final
    (x, theta_hat, int x^2) and W(t) = x^2 / 2 + theta_tilde' Gamma^{-1} theta_tilde / 2 at t = 0 and T."""
    gain_inv = np.linalg.inv(gain)

    def f(t, s):
        x, theta_hat, _ = s
        w = omega(t)
        u = -x - w @ theta_hat
        return w @ theta + u, lyapunov_law(w, x, gain), x**2

    s0 = (jnp.asarray(x0), jnp.zeros(2), jnp.asarray(0.0))
    (x, theta_hat, energy), _ = jax.jit(lambda s: _rk4(f, s, h, int(round(T / h))))(s0)
    W = lambda x, th: 0.5 * x**2 + 0.5 * (theta - th) @ gain_inv @ (theta - th)
    return float(x), np.asarray(theta_hat), float(energy), W(x0, np.zeros(2)), W(float(x), np.asarray(theta_hat))


def test_example_1_1_constant_regressor_closed_form():
    """Constant omega (Example 1.1 continued): x -> 0 and theta_tilde converges to the null space of omega', to the
    point theta_tilde(inf) = (I - Gamma omega omega' / (omega' Gamma omega)) theta_tilde(0) (from s = omega'
    theta_tilde: s_dot = -(omega' Gamma omega) x, so int x = s(0) / (omega' Gamma omega)); W_dot = -x^2."""
    omega, gain, theta = np.array([1.0, 2.0]), np.array([[2.0, 0.5], [0.5, 1.0]]), np.array([1.0, -1.0])
    x, theta_hat, energy, W0, WT = _example_1_1(lambda t: jnp.asarray(omega), gain, theta, x0=0.5, T=60.0)
    want = (np.eye(2) - np.outer(gain @ omega, omega) / (omega @ gain @ omega)) @ theta
    np.testing.assert_allclose(theta - theta_hat, want, atol=1e-12)  # 6e-14 measured
    assert abs(x) < 1e-12
    assert WT - W0 == pytest.approx(-energy, rel=1e-8)  # RK4 at h = 0.005: 8e-10 measured


def test_example_1_1_persistent_excitation_gives_parameter_convergence():
    """omega(t) = [sin t, cos t] is persistently exciting (its Gram matrix over any 2 pi window is pi I):
    theta_tilde -> 0 (below 1e-7 at t = 100 from |theta_tilde(0)| = 1.4), and W decreases by int x^2."""
    theta, gain = np.array([1.0, -1.0]), np.eye(2)
    omega = lambda t: jnp.stack([jnp.sin(t), jnp.cos(t)])
    x, theta_hat, energy, W0, WT = _example_1_1(omega, gain, theta, x0=0.5, T=100.0)
    assert np.max(np.abs(theta - theta_hat)) < 1e-7 and abs(x) < 1e-7
    assert WT - W0 == pytest.approx(-energy, rel=1e-8)
    t = 0.01 * np.arange(629)
    np.testing.assert_allclose(excitation(np.stack([np.sin(t), np.cos(t)], 1), 0.01)[0], np.pi * np.eye(2), atol=0.02)


# ---------------------------------------------------------------------------------------------
# recursive least squares


def _batch_weighted_ls(Omegas, zs, lam, theta0, P0):
    """The minimiser of sum_i lam^(N-1-i) |z_i - Omega_i' theta|^2 + lam^N (theta - theta0)' P0^{-1} (theta - theta0)
    over the finite z_i (rows dropped where NaN), and the inverse of its Hessian / 2."""
    N = len(Omegas)
    info = lam**N * np.linalg.inv(P0)
    rhs = info @ theta0
    for i, (Omega, z) in enumerate(zip(Omegas, zs, strict=True)):
        seen = np.isfinite(z)
        w = lam ** (N - 1 - i)
        info = info + w * Omega[:, seen] @ Omega[:, seen].T
        rhs = rhs + w * Omega[:, seen] @ z[seen]
    return np.linalg.solve(info, rhs), np.linalg.inv(info)


@jax.jit
def _run_rls(theta0, P0, Omegas, zs, lam):
    def step(carry, data):
        return rls_update(*carry, *data, forgetting=lam), None

    return jax.lax.scan(step, (theta0, P0), (Omegas, zs))[0]


@pytest.mark.parametrize("q", [1, 2])
@pytest.mark.parametrize("lam", [1.0, 0.9])
def test_rls_equals_batch_least_squares(q, lam):
    """After N steps, RLS with forgetting factor lam is the batch weighted least-squares estimate with the prior as
    regulariser, and P the inverse information, to 1e-10 relative (noisy data, 40 samples of 3 parameters, q
    equations per sample; with lam = 0.9 the data and the prior are discounted); NaN targets are dropped exactly."""
    rng = np.random.default_rng(10 * q + int(10 * lam))
    N, p = 40, 3
    theta = rng.normal(size=p)
    Omegas = rng.normal(size=(N, p, q))
    zs = np.einsum("kpq,p->kq", Omegas, theta) + 0.1 * rng.normal(size=(N, q))
    zs[[5, 17], 0] = np.nan
    theta0, P0 = rng.normal(size=p), 10.0 * np.eye(p)
    theta_hat, P = _run_rls(theta0, P0, Omegas, zs, lam)
    want, P_want = _batch_weighted_ls(Omegas, zs, lam, theta0, P0)
    np.testing.assert_allclose(theta_hat, want, rtol=1e-10)
    np.testing.assert_allclose(P, P_want, rtol=1e-10)


def test_rls_with_vague_prior_is_ordinary_least_squares():
    """lam = 1 and P0 = 1e8 I: the regulariser's pull is 1e-8 of the information, so RLS equals np.linalg.lstsq to
    1e-7 relative; the scalar-regressor form (omega (n_theta,), z ()) gives the same as q = 1."""
    rng = np.random.default_rng(4)
    Omegas, zs = rng.normal(size=(30, 2, 1)), rng.normal(size=(30, 1))
    theta_hat, _ = _run_rls(np.zeros(2), 1e8 * np.eye(2), Omegas, zs, 1.0)
    want = np.linalg.lstsq(Omegas[:, :, 0], zs[:, 0], rcond=None)[0]
    np.testing.assert_allclose(theta_hat, want, rtol=1e-7)
    scalar = jax.jit(lambda t, P, omega, z: rls_update(t, P, omega, z))
    got = (np.zeros(2), 1e8 * np.eye(2))
    for k in range(3):
        got = scalar(*got, Omegas[k, :, 0], zs[k, 0])
    np.testing.assert_allclose(got[0], _run_rls(np.zeros(2), 1e8 * np.eye(2), Omegas[:3], zs[:3], 1.0)[0], rtol=1e-12)


def test_continuous_rls_is_weighted_least_squares():
    """Continuous RLS with forgetting rate beta (rls_rate) and its information form (Omega_dot = -beta Omega +
    omega omega', b_dot = -beta b + omega z, theta_hat = Omega^{-1} b) integrated by the same RK4 agree to 1e-9 at
    t = 10, and the estimate has converged to theta (z = omega' theta, omega = [sin t, 1] persistently exciting)."""
    theta, beta, P0 = np.array([0.7, -1.2]), 0.5, 2.0 * np.eye(2)
    omega = lambda t: jnp.stack([jnp.sin(t), jnp.ones_like(t)])

    def f(t, s):
        theta_hat, P, Omega, b = s
        w = omega(t)
        z = w @ theta + 0.1 * jnp.sin(3 * t)  # a disturbance, so that the estimate is a compromise
        rate, P_dot = rls_rate(theta_hat, P, w, z, forgetting=beta)
        return rate, P_dot, -beta * Omega + jnp.outer(w, w), -beta * b + w * z

    s0 = (jnp.zeros(2), jnp.asarray(P0), jnp.linalg.inv(P0), jnp.zeros(2))
    (theta_hat, P, Omega, b), _ = jax.jit(lambda s: _rk4(f, s, 0.005, 2000))(s0)
    np.testing.assert_allclose(theta_hat, np.linalg.solve(Omega, b), rtol=1e-9)
    np.testing.assert_allclose(P, np.linalg.inv(Omega), rtol=1e-9)
    assert np.max(np.abs(theta_hat - theta)) < 0.1


# ---------------------------------------------------------------------------------------------
# projection


def _point(region, direction, level):
    """The point on the ray from the centre of ``region`` along ``direction`` where P = ``level`` (closed form)."""
    if isinstance(region, Ball):
        return region.center + region.radius * np.sqrt(1 + level) * direction / np.linalg.norm(direction)
    middle, half = (region.upper + region.lower) / 2, (region.upper - region.lower) / 2
    t = ((1 + level) / np.sum(direction ** (2 * region.order))) ** (1 / (2 * region.order))
    return middle + half * t * direction


@jax.jit
def _projection_terms(tau, theta_hat, theta, gain, region, epsilon):
    """(theta_tilde' Gamma^-1 Proj - theta_tilde' Gamma^-1 tau, Proj' Gamma^-1 Proj - tau' Gamma^-1 tau,
    grad P' Proj): the two App. 5.A inequalities say the first is >= 0 and the second <= 0."""
    proj = project(tau, theta_hat, gain, region, epsilon)
    tilde = theta - theta_hat
    first = tilde @ jnp.linalg.solve(gain, proj - tau)
    second = proj @ jnp.linalg.solve(gain, proj) - tau @ jnp.linalg.solve(gain, tau)
    return first, second, jax.grad(region)(theta_hat) @ proj


vectors = st.lists(st.floats(-1, 1), min_size=3, max_size=3).map(np.array)


@settings(max_examples=150, deadline=None)
@given(
    kind=st.sampled_from(["ball", "box"]),
    L=st.lists(st.floats(-1, 1), min_size=9, max_size=9).map(lambda v: np.reshape(v, (3, 3))),
    d_theta=vectors,
    d_hat=vectors,
    s_theta=st.floats(-1, 0),
    s_hat=st.floats(-1, 1),
    epsilon=st.floats(0.01, 1.0),
    tau=st.lists(st.floats(-10, 10), min_size=3, max_size=3).map(np.array),
)
def test_projection_inequalities(kind, L, d_theta, d_hat, s_theta, s_hat, epsilon, tau):
    """Grip 2010 App. 5.A (Krstić et al. Lemma E.1), for theta in Pi, theta_hat anywhere in Theta (s_hat: the level
    P(theta_hat) as a fraction of epsilon, negative inside Pi) and any tau, Gamma SPD:
    -theta_tilde' Gamma^{-1} Proj(tau) <= -theta_tilde' Gamma^{-1} tau and Proj' Gamma^{-1} Proj <= tau' Gamma^{-1}
    tau; and on the outer boundary P = epsilon the projected rate never points outwards (grad P' Proj <= 0)."""
    assume(np.linalg.norm(d_theta) > 1e-3 and np.linalg.norm(d_hat) > 1e-3)
    gain = L @ L.T + 0.1 * np.eye(3)
    if kind == "ball":
        region = Ball(center=np.array([0.5, -1.0, 2.0]), radius=np.asarray(1.5))
    else:
        region = Box(lower=np.array([-5.0, 0.0, 1.0]), upper=np.array([5.0, 0.5, 3.0]))
    theta = _point(region, d_theta, s_theta)
    theta_hat = _point(region, d_hat, s_hat * epsilon if s_hat > 0 else s_hat)
    scale = tau @ np.linalg.solve(gain, tau) + np.linalg.norm(theta - theta_hat) * np.linalg.norm(tau) * 10
    tol = 1e-10 * (1 + scale) * np.linalg.cond(gain)
    first, second, _ = _projection_terms(tau, theta_hat, theta, gain, region, epsilon)
    assert float(first) >= -tol
    assert float(second) <= tol
    edge = _point(region, d_hat, epsilon)
    _, _, outward = _projection_terms(tau, edge, theta, gain, region, epsilon)
    assert float(outward) <= tol


@pytest.mark.parametrize(
    "region, gain, half",
    [(Ball(center=np.zeros(2), radius=np.asarray(1.0)), np.array([[2.0, 0.5], [0.5, 1.0]]), np.ones(2)),
     (Box(lower=np.array([-5.0, -1.0]), upper=np.array([5.0, 1.0])), np.diag([0.3, 1.0]), np.array([5.0, 1.0]))],
    ids=["ball", "box"],
)  # fmt: skip
def test_projected_estimate_never_leaves_the_set(region, gain, half):
    """theta_hat_dot = Proj(Gamma (theta_target(t) - theta_hat)), the target circling at 3 times the set's size, from
    the centre, for 20 s: theta_hat reaches the boundary layer and presses on it. The exact solution stays in Theta;
    RK4 leaves it by its own error only: P - epsilon < 1e-3 epsilon at h = 0.01 (measured 5e-5 and 4e-5), shrinking
    as h^2 (a quarter or less at h/2; second order, as Proj is Lipschitz but not smooth)."""
    epsilon = 0.1
    target = lambda t: 3 * half * jnp.stack([jnp.cos(t), jnp.sin(t)])
    f = lambda t, th: project(gain @ (target(t) - th), th, gain, region, epsilon)
    overshoot = {}
    for h in (0.01, 0.005):
        _, path = jax.jit(lambda th, h=h: _rk4(f, th, h, int(round(20 / h))))(jnp.zeros(2))
        levels = np.asarray(jax.vmap(region)(path))
        assert levels.max() > 0.99 * epsilon  # the flow presses on the boundary
        overshoot[h] = levels.max() - epsilon
    assert overshoot[0.01] < 1e-3 * epsilon
    assert overshoot[0.005] <= overshoot[0.01] / 3.5, overshoot


def test_clip_step_keeps_the_box_exactly():
    """The thesis's discrete form: Euler then clipping; the estimate stays in [lower, upper] exactly, and equals the
    Euler step inside."""
    step = jax.jit(clip_step)
    theta = np.array([0.5, 0.5])
    for rate in ([100.0, -3.0], [-100.0, 1.0], [0.1, 0.2]):
        new = np.asarray(step(theta, np.array(rate), 0.01, np.array([0.05, 0.1]), np.array([1.1, 1.0])))
        assert np.all(new >= [0.05, 0.1]) and np.all(new <= [1.1, 1.0])
    np.testing.assert_allclose(new, theta + 0.01 * np.array(rate), rtol=1e-15)


def test_project_jit_vmap_grad():
    """vmap over a batch of estimates equals the loop (eager calls), and the projection is differentiable inside the
    boundary layer (check_grads in tau and theta_hat, away from its switching surfaces)."""
    ball, gain = Ball(center=np.zeros(2), radius=np.asarray(1.0)), np.array([[2.0, 0.5], [0.5, 1.0]])
    hats = np.array([[0.0, 0.0], [1.02, 0.0], [0.0, -1.04], [0.7, 0.74]])
    tau = np.array([1.0, -2.0])
    batched = jax.jit(jax.vmap(lambda th: project(tau, th, gain, ball, 0.1)))(hats)
    for th, got in zip(hats, batched, strict=True):
        np.testing.assert_allclose(got, project(tau, th, gain, ball, 0.1), rtol=1e-14)
    check_grads(lambda t, th: project(t, th, gain, ball, 0.1), (tau, hats[2]), order=1, modes=("rev",))


# ---------------------------------------------------------------------------------------------
# update laws of the perturbation-based observers (one call: law(g, args, phi_hat, theta_hat))


def _g(v, x, theta):
    return theta * x[:1]


ARGS = (jnp.zeros(2), jnp.ones(2))  # (v, x_hat): g = theta at x_1 = 1


def test_inversion_law_pauses_below_threshold_without_nan():
    """Props. 6.1/6.2 with l = 1{|phi_hat| >= threshold}: theta* divides by phi_hat; below the threshold the update
    is exactly zero and neither values nor gradients are NaN; above it the rate is Gamma (theta* - theta_hat)."""
    law = InversionLaw(lambda v, x, phi: jnp.array([1.0 / phi[0]]), adaptation_gain=2.0, threshold=1.0)
    rate = jax.jit(lambda phi: law(_g, ARGS, phi, jnp.array([0.3])))
    np.testing.assert_array_equal(rate(jnp.zeros(1)), [0.0])
    np.testing.assert_allclose(rate(jnp.array([2.0])), [2.0 * (0.5 - 0.3)])
    np.testing.assert_array_equal(jax.grad(lambda phi: rate(phi)[0])(jnp.zeros(1)), [0.0])


def test_inversion_law_weight_of_proposition_6_2():
    """A weight l(v, x_hat, phi_hat) scales the update (Props. 5.2, 6.2); l = 0 stops it; with the threshold, l is
    never evaluated at a phi_hat below it (the stand-in), so an l that divides by phi_hat stays finite."""
    theta_star = lambda v, x, phi: jnp.array([1.0 / phi[0]])  # noqa: E731
    phi, theta_hat = jnp.array([2.0]), jnp.array([0.3])
    plain = InversionLaw(theta_star, 1.0)(_g, ARGS, phi, theta_hat)
    for weight in (0.0, 0.25, 1.0):
        law = InversionLaw(theta_star, 1.0, weight=lambda v, x, p, w=weight: jnp.asarray(w))
        np.testing.assert_allclose(law(_g, ARGS, phi, theta_hat), weight * plain, rtol=1e-15)
    law = InversionLaw(theta_star, 1.0, weight=lambda v, x, p: 1.0 / p[0] ** 2, threshold=1.0)
    rate = jax.jit(lambda p: law(_g, ARGS, p, theta_hat))
    np.testing.assert_allclose(rate(phi), (0.5 - 0.3) / 4.0, rtol=1e-15)
    np.testing.assert_array_equal(rate(jnp.zeros(1)), [0.0])
    assert np.isfinite(jax.grad(lambda p: rate(p)[0])(jnp.zeros(1))).all()
    with pytest.raises(ValueError, match="^weight must be a function"):
        InversionLaw(theta_star, 1.0, weight=0.5)


def test_perturbation_gradient_and_custom_laws_match_their_formulas():
    """PerturbationGradientLaw is Gamma (dg/dtheta)' (phi_hat - g) by default (Remark 5.1) and Gamma M (phi_hat - g)
    with M; CustomLaw is Gamma direction; with a region, each is projected (project), and a law is a pytree that
    jit and vmap see through (its gain batched)."""
    g = lambda t, x, th: jnp.array([th[0] * x[0], th[0] ** 2 + th[1]])  # noqa: E731
    args, phi, theta_hat = (0.0, jnp.array([2.0])), jnp.array([1.0, 3.0]), jnp.array([0.5, 0.2])
    gain = np.array([[2.0, 0.5], [0.5, 1.0]])
    residual = phi - g(*args, theta_hat)
    jacobian = np.array([[2.0, 0.0], [1.0, 1.0]])  # dg/dtheta at theta_hat
    rate = PerturbationGradientLaw(gain)(g, args, phi, theta_hat)
    np.testing.assert_allclose(rate, gain @ jacobian.T @ residual, rtol=1e-14)
    M = np.array([[1.0, 0.0], [0.0, 2.0]])
    rate = PerturbationGradientLaw(gain, M=lambda t, x, th: jnp.asarray(M))(g, args, phi, theta_hat)
    np.testing.assert_allclose(rate, gain @ M @ residual, rtol=1e-14)
    direction = lambda g, args, phi, th: phi - th  # noqa: E731
    np.testing.assert_allclose(CustomLaw(direction, gain)(g, args, phi, theta_hat), gain @ (phi - theta_hat))
    ball = Ball(center=np.zeros(2), radius=np.asarray(0.5))
    edge = np.array([0.5, 0.0])  # P = 0 < epsilon: c = 0, then inside the layer
    for law in (PerturbationGradientLaw(gain, region=ball), CustomLaw(direction, gain, region=ball)):
        unprojected = type(law)(**{**law.__dict__, "region": None})
        for th in (edge, 1.02 * edge):
            want = project(unprojected(g, args, phi, th), th, gain, ball, 0.1)
            np.testing.assert_allclose(law(g, args, phi, th), want, rtol=1e-14)
    laws = jax.vmap(lambda a: PerturbationGradientLaw(a))(jnp.array([1.0, 2.0]))
    rates = jax.jit(jax.vmap(lambda law: law(g, args, phi, theta_hat)))(laws)
    np.testing.assert_allclose(rates[1], 2 * rates[0], rtol=1e-14)


def test_check_law_names_the_field():
    """check_law: a bad adaptation gain, epsilon or threshold, theta0 outside the projection set, or something not
    a law: ValueError naming it."""
    ball = Ball(center=np.zeros(2), radius=np.asarray(1.0))
    star = lambda v, x, phi: phi  # noqa: E731
    cases = [
        ("adaptation_gain", PerturbationGradientLaw(np.diag([1.0, -1.0])), np.zeros(2)),
        ("epsilon", PerturbationGradientLaw(1.0, region=ball, epsilon=0.0), np.zeros(2)),
        ("threshold", InversionLaw(star, 1.0, threshold=-1.0), np.zeros(2)),
        ("theta0", CustomLaw(lambda g, a, p, t: t, 1.0, region=ball), np.array([2.0, 0.0])),
        ("law", "gradient", np.zeros(2)),
    ]
    for name, law, theta0 in cases:
        with pytest.raises(ValueError, match=rf"^{name}\b"):
            check_law(law, theta0)


# ---------------------------------------------------------------------------------------------
# bad input


BAD_GAINS = [np.array([[1.0, 1.0], [0.0, 1.0]]), np.diag([1.0, -1.0]), np.zeros((2, 2)), -1.0, 0.0, np.ones(2)]


@pytest.mark.parametrize("gain", BAD_GAINS, ids=["asymmetric", "indefinite", "singular", "negative", "zero", "1d"])
def test_adaptation_gain_must_be_symmetric_positive_definite(gain):
    ball = Ball(center=np.zeros(2), radius=np.asarray(1.0))
    calls = [
        lambda: regression_gradient_law(np.zeros(2), np.ones(2), 1.0, gain),
        lambda: lyapunov_law(np.ones(2), 1.0, gain),
        lambda: project(np.ones(2), np.zeros(2), gain, ball, 0.1),
    ]
    for call in calls:
        with pytest.raises(ValueError, match=r"^adaptation_gain\b"):
            call()


def test_bad_values_raise_naming_the_argument():
    """dt <= 0, theta_hat(0) outside the projection set (or the clip bounds), epsilon <= 0, a forgetting factor
    outside (0, 1], P not positive definite, and shape mismatches: ValueError naming the argument."""
    ball = Ball(center=np.zeros(2), radius=np.asarray(1.0))
    cases = [
        ("dt", lambda: clip_step(np.zeros(1), np.ones(1), 0.0, -1.0, 1.0)),
        ("dt", lambda: clip_step(np.zeros(1), np.ones(1), -0.01, -1.0, 1.0)),
        ("dt", lambda: excitation(np.ones((5, 2)), 0.0)),
        ("theta_hat", lambda: project(np.ones(2), np.array([1.2, 0.0]), 1.0, ball, 0.1)),
        ("theta_hat", lambda: clip_step(np.array([2.0]), np.ones(1), 0.1, -1.0, 1.0)),
        ("epsilon", lambda: project(np.ones(2), np.zeros(2), 1.0, ball, 0.0)),
        ("epsilon", lambda: project(np.ones(2), np.zeros(2), 1.0, ball, -0.1)),
        ("forgetting", lambda: rls_update(np.zeros(2), np.eye(2), np.ones(2), 1.0, forgetting=0.0)),
        ("forgetting", lambda: rls_update(np.zeros(2), np.eye(2), np.ones(2), 1.0, forgetting=1.5)),
        ("forgetting", lambda: rls_rate(np.zeros(2), np.eye(2), np.ones(2), 1.0, forgetting=-1.0)),
        ("P", lambda: rls_update(np.zeros(2), np.diag([1.0, -1.0]), np.ones(2), 1.0)),
        ("omega", lambda: regression_gradient_law(np.zeros(2), np.ones(3), 1.0, 1.0)),
        ("z", lambda: rls_update(np.zeros(2), np.eye(2), np.ones((2, 3)), np.ones(2))),
        ("tau", lambda: project(np.ones(3), np.zeros(2), 1.0, ball, 0.1)),
    ]
    for name, call in cases:
        with pytest.raises(ValueError, match=rf"^{name}\b"):
            call()


# ---------------------------------------------------------------------------------------------
# the input contract (issue 28): every array argument, every non-finite value; ranges; wrong types; jit

BALL = Ball(center=np.zeros(2), radius=np.asarray(1.0))
BOX = Box(lower=-np.ones(2), upper=np.ones(2))

# (function, its arguments by name (two parameters), the array arguments that must be finite)
CALLS = {
    "regression_gradient_law": (regression_gradient_law, dict(theta_hat=np.zeros(2), omega=np.ones(2), z=1.0,
                                                              adaptation_gain=1.0), ("theta_hat", "omega", "z")),
    "lyapunov_law": (lyapunov_law, dict(omega=np.ones(2), x=0.5, adaptation_gain=2.0), ("omega", "x")),
    "rls_update": (rls_update, dict(theta_hat=np.zeros(2), P=np.eye(2), omega=np.ones(2), z=1.0),
                   ("theta_hat", "P", "omega")),
    "rls_rate": (rls_rate, dict(theta_hat=np.zeros(2), P=np.eye(2), omega=np.ones(2), z=1.0),
                 ("theta_hat", "P", "omega", "z")),
    "project": (project, dict(tau=np.ones(2), theta_hat=np.zeros(2), adaptation_gain=1.0, region=BALL, epsilon=0.1),
                ("tau", "theta_hat")),
    "clip_step": (clip_step, dict(theta_hat=np.zeros(2), rate=np.ones(2), dt=0.1, lower=-1.0, upper=1.0),
                  ("theta_hat", "rate", "lower", "upper")),
    "excitation": (excitation, dict(regressors=np.ones((4, 2)), dt=0.01), ("regressors",)),
}  # fmt: skip
NON_FINITE = {"nan": np.nan, "inf": np.inf, "-inf": -np.inf}


def _with(kwargs, name, bad):
    """``kwargs`` with one entry of ``kwargs[name]`` replaced by ``bad``."""
    value = np.array(kwargs[name], dtype=float)
    value.flat[-1] = bad
    return {**kwargs, name: value}


@pytest.mark.parametrize("bad", NON_FINITE.values(), ids=NON_FINITE)
@pytest.mark.parametrize("function, name", [(f, n) for f, (_, _, names) in CALLS.items() for n in names])
def test_non_finite_arrays_raise_naming_the_argument(function, name, bad):
    """NaN or +-inf anywhere in an array argument: ValueError naming it (before: NaN or inf results, e.g.
    regression_gradient_law(zeros(2), ones(2), nan, 1.0), lyapunov_law(omega, nan, 2.0), rls_rate(z=inf),
    rls_update(th, P, [nan], 1.0) and excitation([[1, nan], [0, 1]], 0.01))."""
    fn, kwargs, _ = CALLS[function]
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        fn(**_with(kwargs, name, bad))


@pytest.mark.parametrize("function, name", [(f, n) for f, (_, kwargs, names) in CALLS.items() for n in names])
def test_strings_raise_naming_the_argument(function, name):
    fn, kwargs, _ = CALLS[function]
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        fn(**{**kwargs, name: "abc"})


BAD_REGIONS = [
    ("ball-radius-negative", Ball(np.zeros(2), np.asarray(-1.0)), "region.radius"),
    ("ball-radius-zero", Ball(np.zeros(2), np.asarray(0.0)), "region.radius"),
    ("ball-radius-nan", Ball(np.zeros(2), np.asarray(np.nan)), "region.radius"),
    ("ball-radius-vector", Ball(np.zeros(2), np.ones(2)), "region.radius"),
    ("ball-center-nan", Ball(np.array([0.0, np.nan]), np.asarray(1.0)), "region.center"),
    ("ball-center-length", Ball(np.zeros(3), np.asarray(1.0)), "region.center"),
    ("box-lower-above-upper", Box(np.ones(2), -np.ones(2)), "region.upper"),
    ("box-empty", Box(np.zeros(2), np.array([1.0, 0.0])), "region.upper"),
    ("box-upper-inf", Box(-np.ones(2), np.array([1.0, np.inf])), "region.upper"),
    ("box-lower-length", Box(-np.ones(3), np.ones(2)), "region.lower"),
    ("box-order-zero", Box(-np.ones(2), np.ones(2), order=0), "region.order"),
    ("box-order-float", Box(-np.ones(2), np.ones(2), order=2.5), "region.order"),
    ("not-callable", "ball", "region"),
]


@pytest.mark.parametrize("region, name", [pytest.param(r, n, id=i) for i, r, n in BAD_REGIONS])
def test_bad_regions_raise_naming_the_field(region, name):
    """A Ball radius <= 0 (before: Ball(radius=-1) acted as radius 1, radius 0 blamed theta_hat) and Box bounds with
    lower >= upper (before: project returned tau unprojected) are refused by project and by the laws' check."""
    with pytest.raises(ValueError, match=rf"^{re.escape(name)}\b"):
        project(np.ones(2), np.zeros(2), 1.0, region, 0.1)
    with pytest.raises(ValueError, match=rf"^{re.escape(name)}\b"):
        check_law(CustomLaw(lambda g, a, p, t: t, 1.0, region=region), np.zeros(2))


def test_traced_invalid_regions_and_bounds_give_nan():
    """Under jit nothing raises, and nothing looks valid: a traced Ball radius <= 0, Box bounds with lower >= upper
    or epsilon <= 0 make project NaN; clip_step bounds with upper < lower make that parameter NaN; non-finite
    regressors make excitation's lambda_min NaN; a non-finite input makes a law's rate non-finite."""
    tau, theta = jnp.ones(2), jnp.array([0.9, 0.0])
    ball = jax.jit(lambda r: project(tau, theta, 1.0, Ball(jnp.zeros(2), r), 0.1))
    assert np.all(np.isfinite(ball(1.0)))
    for r in (-1.0, 0.0, np.nan):
        assert np.all(np.isnan(ball(r)))
    box = jax.jit(lambda lo, hi: project(tau, theta, 1.0, Box(lo, hi), 0.1))
    assert np.all(np.isfinite(box(-jnp.ones(2), jnp.ones(2))))
    assert np.all(np.isnan(box(jnp.ones(2), -jnp.ones(2))))
    eps = jax.jit(lambda e: project(tau, jnp.array([1.04, 0.0]), 1.0, BALL, e))
    assert np.all(np.isnan(eps(-0.1))) and np.all(np.isfinite(eps(0.1)))
    clip = jax.jit(lambda lo, hi: clip_step(jnp.zeros(2), jnp.ones(2), 0.1, lo, hi))
    np.testing.assert_array_equal(clip(jnp.array([-1.0, 1.0]), jnp.array([1.0, -1.0])), [0.1, np.nan])
    low = jax.jit(lambda W: excitation(W, 0.01)[1])
    assert np.isnan(low(jnp.array([[1.0, np.nan], [0.0, 1.0]]))) and low(jnp.eye(2)) > 0
    rate = jax.jit(lambda z: regression_gradient_law(jnp.zeros(2), jnp.ones(2), z, 1.0))
    assert np.all(np.isnan(rate(np.nan)))


def test_traced_non_finite_regressor_is_a_missing_equation():
    """rls_update under jit: a non-finite column of omega drops its equation, as a missing z does (before: NaN
    theta and P), so the estimate and P stay those of the other equations."""
    step = jax.jit(rls_update)
    theta, P = jnp.zeros(2), jnp.eye(2)
    omega = jnp.array([[1.0, np.nan], [0.5, 1.0]])
    got = step(theta, P, omega, jnp.array([1.0, 2.0]))
    want = step(theta, P, omega.at[0, 1].set(0.0), jnp.array([1.0, np.nan]))
    for a, b in zip(got, want, strict=True):
        assert np.all(np.isfinite(a))
        np.testing.assert_array_equal(a, b)
