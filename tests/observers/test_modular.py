"""Tests for jaxobs.observers.modular, the modular estimator of Grip 2010 ch. 5: the error dynamics (5.11) along a
closed-loop trajectory (with the compensation (5.15)), Prop. 5.1's exponential parameter error with an exact
perturbation estimate, the update laws against hand-written forms (Remark 5.1, Example 5.6, Prop. 5.2), the
sampled estimator under jit/vmap/grad with missing measurements, and bad inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from jaxobs import ct
from jaxobs.adaptive import Ball, Box, InversionLaw, PerturbationGradientLaw
from jaxobs.observers import EstimatorInputs, run
from jaxobs.observers.modular import (
    ModularState,
    compensation,
    make_modular,
    modular_estimator,
    modular_rate,
    parameter_rate,
    perturbation_error_rate,
)

# a two-state plant whose B and g depend on t and x, so d (5.10) has both partial derivatives
THETA = jnp.array([0.7, -0.4])


def f2(t, x):
    return jnp.array([-x[0] + x[1], -2.0 * x[1] + jnp.sin(t)])


def B2(t, x):
    return jnp.array([[1.0, 0.0], [0.2 * jnp.cos(x[0]), 1.0 + 0.1 * jnp.sin(t)]])


def g2(t, x, th):
    return jnp.array([jnp.exp(jnp.sin(t) * th[0]), th[1] * x[0] + th[0] ** 2 * jnp.cos(x[1])])


def closed_loop(model, theta):
    """Plant (5.1) with the compensation v = -g(t, x, theta_hat) (5.15) and the estimator (5.8), one ODE."""

    def rate(s, u, t):
        x, est = s
        v = compensation(model, est.theta_hat, t, x)
        x_dot = model.f(t, x) + model.B(t, x) @ (model.g(t, x, theta) + v)
        return x_dot, modular_rate(model, est, v, x, t)

    return rate


def test_error_dynamics_5_11_along_a_closed_loop_trajectory():
    """Along the trajectory, d/dt phi_tilde (by a JVP of phi_tilde(t, x, z, theta_hat) along the joint vector field)
    equals -K_phi phi_tilde + d(t, x, theta_tilde) (5.11a) with d from perturbation_error_rate, theta_tilde' =
    -u_theta(phi_hat) (5.11b), and x_hat = -K_phi^{-1} z obeys the observer form of Grip 2010 §5.7; all to 1e-12."""
    K = jnp.array([[6.0, 1.0], [1.0, 4.0]])
    law = PerturbationGradientLaw(jnp.diag(jnp.array([2.0, 3.0])), region=Ball(jnp.zeros(2), 3.0))
    params = make_modular(f2, B2, g2, theta0=jnp.zeros(2), K_phi=K, law=law, dt=0.01, n_inputs=2)
    model = params.model
    rate = closed_loop(model, THETA)
    s0 = (jnp.array([0.5, -1.0]), ModularState(jnp.array([0.3, 0.1]), jnp.array([0.2, 0.1])))
    xs, ests = jax.jit(lambda s: ct.trajectory(rate, s, jnp.zeros(300), h=0.01, substeps=2))(s0)

    def phi_tilde(t, x, est):
        return model.B(t, x) @ model.g(t, x, THETA) - (
            est.z + model.K_phi @ x + model.B(t, x) @ model.g(t, x, est.theta_hat)
        )

    def check(t, x, est):
        x_dot, est_dot = rate((x, est), None, t)
        tangent = jax.jvp(phi_tilde, (t, x, est), (jnp.ones_like(t), x_dot, est_dot))[1]
        e = phi_tilde(t, x, est)
        d = perturbation_error_rate(model, t, x, x_dot, THETA, est.theta_hat)
        phi_hat = model.B(t, x) @ model.g(t, x, THETA) - e
        u_theta = parameter_rate(model, t, x, phi_hat, est.theta_hat)
        g_dot = jax.jvp(lambda th: model.g(t, x, th), (est.theta_hat,), (u_theta,))[1]
        v = compensation(model, est.theta_hat, t, x)
        x_hat_form = model.f(t, x) + model.B(t, x) @ v + phi_hat + jnp.linalg.solve(K, model.B(t, x) @ g_dot)
        return (tangent - (-K @ e + d), est_dot.theta_hat - u_theta, -jnp.linalg.solve(K, est_dot.z) - x_hat_form,
                jnp.linalg.norm(d))  # fmt: skip

    times = 0.01 * jnp.arange(0, 301, 25)
    idx = np.arange(0, 301, 25)
    along = jax.tree.map(lambda a: a[idx], ests)
    res_phi, res_theta, res_xhat, d_norm = jax.jit(jax.vmap(check))(times, xs[idx], along)
    assert float(jnp.max(jnp.abs(res_phi))) < 1e-12
    assert float(jnp.max(jnp.abs(res_theta))) < 1e-14
    assert float(jnp.max(jnp.abs(res_xhat))) < 1e-12
    assert float(jnp.min(d_norm[:-1])) > 1e-3  # d is not trivially zero along the way


def test_d_by_autodiff_equals_the_closed_form_of_example_5_6():
    """d = (theta e^{sin(t) theta} - theta_hat e^{sin(t) theta_hat}) cos t for g = exp(sin(t) theta) (Grip 2010
    Example 5.6)."""
    params = make_modular(lambda t, x: -x, lambda t, x: jnp.ones((1, 1)), lambda t, x, th: jnp.exp(jnp.sin(t) * th),
                          theta0=[0.0], K_phi=10.0, law=PerturbationGradientLaw(3.0), dt=0.001, n=1)  # fmt: skip
    t, th, th_hat = 0.8, jnp.array([2.0]), jnp.array([-1.0])
    d = perturbation_error_rate(params.model, t, jnp.array([0.3]), jnp.array([5.0]), th, th_hat)
    expected = (2.0 * np.exp(np.sin(t) * 2.0) + np.exp(-np.sin(t))) * np.cos(t)
    np.testing.assert_allclose(d, [expected], rtol=1e-13)


def exp_cubic(t, x, th):
    return jnp.array([jnp.exp(th[0]), th[1] + th[0] ** 3])


def exp_cubic_inverse(t, x, phi):
    a = jnp.log(phi[0])
    return jnp.array([a, phi[1] - a**3])


def test_prop_5_1_inversion_gives_exponential_parameter_error():
    """With phi_hat(0) = phi (z(0) chosen so) and d = 0 (g independent of t and x, B constant), phi_tilde stays 0 and
    the inversion law gives theta_tilde(t) = expm(-Gamma t) theta_tilde(0) (Prop. 5.1; a non-diagonal adaptation gain
    Gamma), to 1e-9 over 3 s with RK4 at 10 ms (measured 3.8e-11)."""
    gain = jnp.array([[2.0, 0.5], [0.5, 1.0]])
    theta, theta0, x0 = jnp.array([0.3, -0.5]), jnp.zeros(2), jnp.array([1.0, -1.0])
    K = 5.0 * jnp.eye(2)
    z0 = exp_cubic(0, x0, theta) - exp_cubic(0, x0, theta0) - K @ x0
    params = make_modular(lambda t, x: -x + jnp.array([jnp.sin(t), jnp.cos(t)]), lambda t, x: jnp.eye(2), exp_cubic,
                          theta0=theta0, K_phi=K, dt=0.01, z0=z0,
                          law=InversionLaw(exp_cubic_inverse, gain, region=Ball(jnp.zeros(2), 10.0)))  # fmt: skip
    model = params.model

    def rate(s, u, t):
        x, est = s
        return model.f(t, x) + model.B(t, x) @ model.g(t, x, theta), modular_rate(model, est, None, x, t)

    _, ests = jax.jit(lambda s: ct.trajectory(rate, s, jnp.zeros(300), h=0.01))((x0, ModularState(z0, theta0)))
    t = 0.01 * np.arange(301)
    expected = np.stack([scipy.linalg.expm(-np.asarray(gain) * s) @ np.asarray(theta - theta0) for s in t])
    np.testing.assert_allclose(theta - ests.theta_hat, expected, atol=1e-9)


def test_update_laws_against_their_hand_written_forms():
    """Remark 5.1's default M = (dg/dtheta)' B' and Example 5.6's M = sin t (5.22); Prop. 5.2's weight l switches the
    inversion off (rate 0) and on (Gamma (theta* - theta_hat)); the phi_hat saturation bounds what the law sees;
    Example 5.5's combined law as a custom direction."""
    g = lambda t, x, th: jnp.exp(jnp.sin(t) * th)
    common = dict(theta0=[0.5], K_phi=10.0, dt=0.001, n=1)
    t, x, phi_hat, th = 0.7, jnp.array([0.2]), jnp.array([1.9]), jnp.array([0.5])
    default = make_modular(lambda t, x: -x, lambda t, x: jnp.ones((1, 1)), g, law=PerturbationGradientLaw(3.0),
                           **common).model  # fmt: skip
    s = np.sin(t)
    np.testing.assert_allclose(parameter_rate(default, t, x, phi_hat, th),
                               3.0 * s * np.exp(s * 0.5) * (1.9 - np.exp(s * 0.5)), rtol=1e-13)  # fmt: skip
    M = lambda t, x, th: jnp.sin(t)[None, None]
    law = PerturbationGradientLaw(3.0, M=M, region=Box(jnp.array([-5.0]), jnp.array([5.0])))
    example = make_modular(lambda t, x: -x, lambda t, x: jnp.ones((1, 1)), g, law=law, **common).model
    np.testing.assert_allclose(
        parameter_rate(example, t, x, phi_hat, th), 3.0 * s * (1.9 - np.exp(s * 0.5)), rtol=1e-13
    )
    saturated = make_modular(lambda t, x: -x, lambda t, x: jnp.ones((1, 1)), g, law=PerturbationGradientLaw(3.0, M=M),
                             phi_bounds=(0.0, 1.5), **common).model  # fmt: skip
    np.testing.assert_allclose(
        parameter_rate(saturated, t, x, phi_hat, th), 3.0 * s * (1.5 - np.exp(s * 0.5)), rtol=1e-13
    )
    law = InversionLaw(lambda t, x, phi: jnp.log(phi) / jnp.sin(t), 3.0,
                       weight=lambda t, x, phi: (jnp.abs(jnp.sin(t)) >= 0.3).astype(float))  # fmt: skip
    intermittent = make_modular(lambda t, x: -x, lambda t, x: jnp.ones((1, 1)), g, law=law, **common).model
    assert float(parameter_rate(intermittent, 0.1, x, phi_hat, th)[0]) == 0.0  # |sin t| < 0.3: off
    np.testing.assert_allclose(
        parameter_rate(intermittent, t, x, phi_hat, th), 3.0 * (np.log(1.9) / s - 0.5), rtol=1e-13
    )


def example_5_6_samples(T=400, dt=0.01, theta=2.0):
    """Samples of x' = -x + exp(sin(t) theta) from x(0) = 0 (Example 5.6 without compensation)."""
    rate = lambda x, u, t: -x + jnp.exp(jnp.sin(t) * theta)
    return ct.trajectory(rate, jnp.zeros(1), jnp.zeros(T - 1), h=dt, substeps=4)


def example_params(K_phi=10.0, dt=0.01):
    return make_modular(lambda t, x: -x, lambda t, x: jnp.ones((1, 1)), lambda t, x, th: jnp.exp(jnp.sin(t) * th),
                        theta0=[0.0], K_phi=K_phi, dt=dt, n=1,
                        law=PerturbationGradientLaw(3.0, M=lambda t, x, th: jnp.sin(t)[None, None],
                                                    region=Box(jnp.array([-5.0]), jnp.array([5.0]))))  # fmt: skip


def test_sampled_estimator_jit_vmap_grad_and_missing_measurements():
    """The sampled estimator finds theta = 2 of Example 5.6 (|theta_tilde| < 0.05 after 4 s at 10 ms; 0.0074
    measured, the bias of the held samples); vmap over records equals one-by-one runs; the reverse-mode gradient
    w.r.t. K_phi equals a central difference to 1e-6 (2e-11 measured); NaN samples are skipped (counted in
    state.missing, outputs stay finite, innovation 0)."""
    xs = example_5_6_samples()
    go = jax.jit(lambda K, y: run(modular_estimator, example_params(K), EstimatorInputs(y=y)))
    state, out = go(10.0, xs)
    assert abs(float(out.theta_hat[-1, 0]) - 2.0) < 0.05
    batch = jnp.stack([xs, 1.1 * xs])
    batched = jax.vmap(lambda y: go(10.0, y)[1].theta_hat)(batch)
    np.testing.assert_allclose(batched[1], go(10.0, batch[1])[1].theta_hat, rtol=1e-12, atol=1e-14)
    loss = jax.jit(lambda K: jnp.sum(go(K, xs[:60])[1].theta_hat ** 2))
    step = 1e-4
    central = (loss(10.0 + step) - loss(10.0 - step)) / (2 * step)
    np.testing.assert_allclose(jax.grad(loss)(10.0), central, rtol=1e-6)  # central difference: O(step^2) error
    holes = xs.at[100:110].set(jnp.nan)
    state, out = go(10.0, holes)
    assert int(state.missing) == 10
    assert bool(jnp.all(jnp.isfinite(out.theta_hat))) and bool(jnp.all(jnp.isfinite(out.phi_hat)))
    assert bool(jnp.all(out.innovation[100:110] == 0))


BALL = Ball(jnp.zeros(2), 3.0)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (dict(law=PerturbationGradientLaw(jnp.array([[1.0, 2.0], [2.0, 1.0]]))), r"^adaptation_gain must be positive"),
        (dict(K_phi=jnp.array([[1.0, 0.0], [1.0, 1.0]])), r"^K_phi must be symmetric"),
        (dict(K_phi=-1.0), r"^K_phi must be a finite positive number"),
        (dict(dt=0.0), r"^dt must be a finite positive number"),
        (dict(theta0=jnp.array([4.0, 0.0])), r"^theta0 must lie in the projection set"),
        (dict(f=lambda t, x: x[:1]), r"^f\(t, x\) must return"),
        (dict(g=lambda t, x, th: th[:1]), r"^g\(t, x, theta\) must return"),
        (dict(law="inversion"), r"^law must be an update law"),
        (dict(law=PerturbationGradientLaw(1.0, region=BALL, epsilon=0.0)), r"^epsilon must be a finite positive"),
        (dict(law=InversionLaw(lambda t, x, phi: jnp.ones(3), 1.0)), r"^law\(B g, \(t, x\), phi_hat, theta_hat\)"),
        (dict(law=PerturbationGradientLaw(1.0, M=lambda t, x, th: jnp.ones((2, 3)))), r"^law\(B g, \(t, x\)"),
    ],
)
def test_bad_inputs_raise_naming_the_argument(change, match):
    args = dict(f=f2, B=B2, g=g2, theta0=jnp.zeros(2), K_phi=5.0, dt=0.01, n=2,
                law=PerturbationGradientLaw(jnp.eye(2), region=BALL))  # fmt: skip
    args.update(change)
    f, B, g = args.pop("f"), args.pop("B"), args.pop("g")
    with pytest.raises(ValueError, match=match):
        make_modular(f, B, g, **args)
