"""Tests for jaxobs.observers.particle: the likelihood estimate against the exact Kalman likelihood (unbiased), its
stop-gradient derivative against the Kalman likelihood's gradient, the backward-simulation smoother against the
RTS smoother, missing data, jit/vmap/grad and bad inputs."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxobs as jo
from jaxobs.observers.particle import ParticleState
from tests._nonlinear_models import linear_problem


@pytest.fixture(scope="module")
def linear():
    """A 3-state linear model with an input and missing measurement components over 15 samples, its exact
    log-likelihood, the Kalman filter's outputs (with covariances) and the filter's matrices."""
    problem, A, B, C = linear_problem(T=15)
    kf = jo.make_kalman(A, C, problem.Q, problem.R, Gamma=B, x0=problem.x0, P0=problem.P0)
    exact = jo.log_likelihood(jo.kalman_filter, kf, problem.inputs())
    outputs = jo.run(jo.kalman_filter, dataclasses.replace(kf, output_covariance=True), problem.inputs())[1]
    return problem, float(exact), outputs, (A, C, problem.Q, problem.R, B)


def _likelihood_ratios(problem, exact, seeds, **options):
    """``exp(log Z_hat - log Z)`` over ``seeds`` independent runs (one vmap)."""

    def log_z(key):
        params = jo.make_particle_filter(problem.model(), options.pop("N", 100), key=key, **options)
        return jnp.sum(jo.run(jo.particle_filter, params, problem.inputs())[1].log_likelihood)

    keys = jax.random.split(jax.random.key(7), seeds)
    return np.exp(np.asarray(jax.jit(jax.vmap(lambda key: log_z(key)))(keys)) - exact)


def _assert_unbiased(ratios):
    mean, error = ratios.mean(), ratios.std() / np.sqrt(len(ratios))
    assert abs(mean - 1) < 3 * error, (mean, error)
    assert error < 0.05  # a test with the power to see a bias of 15 %


def test_likelihood_estimate_is_unbiased(linear):
    """The particle filter's estimate of the likelihood ``p(y)`` (not of its logarithm, which is biased low by
    Jensen's inequality) is unbiased (Del Moral 2004): over 400 seeds, ``mean(exp(log Z_hat - log Z))`` is 1
    within 3 standard errors, ``Z`` the Kalman filter's exact likelihood of a linear-Gaussian model with an
    input and missing components (bootstrap filter, systematic resampling when the ESS drops below N / 2)."""
    problem, exact = linear[:2]
    _assert_unbiased(_likelihood_ratios(problem, exact, 400))


@pytest.mark.slow
@pytest.mark.parametrize("scheme", ["multinomial", "stratified", "systematic", "residual"])
@pytest.mark.parametrize("auxiliary", [False, True], ids=["bootstrap", "auxiliary"])
@pytest.mark.parametrize("ess_threshold", [1.0, 0.5], ids=["always", "adaptive"])
def test_likelihood_estimate_is_unbiased_for_every_scheme(linear, scheme, auxiliary, ess_threshold):
    """As :func:`test_likelihood_estimate_is_unbiased` (``E[exp(log Z_hat)] = Z``, not ``E[log Z_hat] = log
    Z``) for every resampling scheme, the bootstrap and the auxiliary filter, resampling at every step or
    adaptively: 1000 seeds each."""
    problem, exact = linear[:2]
    ratios = _likelihood_ratios(problem, exact, 1000, scheme=scheme, auxiliary=auxiliary, ess_threshold=ess_threshold)
    _assert_unbiased(ratios)


def _ar1(theta):
    """The AR(1) model ``x_k = phi x_{k-1} + w``, ``y = x + v`` with ``theta = (phi, q, r)``: as a nonlinear
    model (``phi`` bound into ``f``, so gradients reach it) and as a Kalman filter."""
    phi, q, r = theta
    f = jax.tree_util.Partial(lambda x, u, t, a: a * x, a=phi)
    model = jo.nonlinear_model(f, lambda x: x, q * jnp.eye(1), r * jnp.eye(1), x0=[0.0], P0=[[1.0]])
    return model, jo.make_kalman(phi * jnp.eye(1), [[1.0]], q * jnp.eye(1), r * jnp.eye(1), x0=[0.0], P0=[[1.0]])


def _ar1_data(T=20):
    rng = np.random.default_rng(0)
    x, y = rng.normal(), []
    for k in range(T):
        x = 0.9 * x + np.sqrt(0.3) * rng.normal() if k else x
        y.append(x + np.sqrt(0.5) * rng.normal())
    return jo.EstimatorInputs(y=jnp.asarray(y)[:, None])


@pytest.mark.slow
@pytest.mark.parametrize("auxiliary", [False, True], ids=["bootstrap", "auxiliary"])
def test_gradient_agrees_with_the_kalman_gradient(auxiliary):
    """The derivative of the log-likelihood estimate with stop-gradient resampling (Ścibior & Wood 2021: the
    Fisher-identity score estimate over the genealogy, consistent as N grows) against the exact gradient of the
    Kalman log-likelihood with respect to (phi, q, r) of an AR(1) model: the mean over 400 seeds of N = 1000
    particles within 3 standard errors of it in every component (measured: at most 0.96 standard errors; the
    estimator's bias is visible at N = 200, up to 3 standard errors for r)."""
    inputs, theta = _ar1_data(), jnp.array([0.9, 0.3, 0.5])
    exact = jax.grad(lambda th: jo.log_likelihood(jo.kalman_filter, _ar1(th)[1], inputs))(theta)
    scheme = "stratified" if auxiliary else "systematic"

    def log_z(th, key):
        params = jo.make_particle_filter(_ar1(th)[0], 1000, key=key, scheme=scheme, auxiliary=auxiliary)
        return jnp.sum(jo.run(jo.particle_filter, params, inputs)[1].log_likelihood)

    keys = jax.random.split(jax.random.key(1), 400)
    grads = np.asarray(jax.jit(jax.vmap(jax.grad(log_z), (None, 0)))(theta, keys))
    error = grads.std(axis=0) / np.sqrt(len(keys))
    assert np.all(np.abs(grads.mean(axis=0) - exact) < 3 * error), (grads.mean(axis=0), exact, error)


def test_without_resampling_the_gradient_is_the_derivative():
    """With ``ess_threshold=0`` the filter never resamples: the estimate is a smooth function of the parameters
    for a fixed key (importance sampling with reparameterised draws), and its autodiff gradient passes
    check_grads (forward and reverse), missing data and all."""
    inputs = _ar1_data(8)
    inputs = inputs._replace(y=inputs.y.at[3].set(jnp.nan))

    def log_z(theta):
        params = jo.make_particle_filter(_ar1(theta)[0], 16, key=jax.random.key(3), ess_threshold=0.0)
        return jnp.sum(jo.run(jo.particle_filter, params, inputs)[1].log_likelihood)

    check_grads(jax.jit(log_z), (jnp.array([0.9, 0.3, 0.5]),), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


def test_missing_sample_keeps_the_weights(linear):
    """An all-missing sample adds nothing (to rounding) to the log-likelihood and leaves the weights as they
    were; the missing components are counted."""
    problem = linear[0]
    params = jo.make_particle_filter(problem.model(), 64, key=jax.random.key(0), ess_threshold=0.0,
                                     output_particles=True)  # fmt: skip
    state, out = jax.jit(lambda p: jo.run(jo.particle_filter, p, problem.inputs()))(params)
    assert abs(float(out.log_likelihood[7])) < 1e-14  # y[7] is all NaN
    np.testing.assert_allclose(out.log_weights[7], out.log_weights[6], rtol=0, atol=1e-14)
    assert int(state.missing) == 4 and not bool(jnp.any(out.resampled))
    np.testing.assert_allclose(jnp.sum(jnp.exp(out.log_weights), axis=1), 1.0, rtol=1e-12)


def test_filter_approaches_the_kalman_filter(linear):
    """With 20 000 particles (auxiliary filter) the filtered means are within 0.1 posterior standard deviations
    of the Kalman filter's at every sample (the Monte-Carlo error is about 1 / sqrt(ESS)), the variances within
    10 %."""
    problem, kf = linear[0], linear[2]
    params = jo.make_particle_filter(problem.model(), 20_000, key=jax.random.key(1), auxiliary=True)
    _, out = jax.jit(lambda p: jo.run(jo.particle_filter, p, problem.inputs()))(params)
    variances = np.diagonal(np.asarray(kf.P), axis1=1, axis2=2)
    assert np.max(np.abs(out.x - kf.x) / np.sqrt(variances)) < 0.1
    assert np.max(np.abs(np.diagonal(np.asarray(out.P), axis1=1, axis2=2) / variances - 1)) < 0.1


def test_smoother_approaches_the_rts_smoother(linear):
    """Backward simulation (Godsill, Doucet & West 2004) from 2000 particles, 400 paths: the mean of the paths
    is within 0.2 smoothed standard deviations of the RTS smoother's mean at every sample and their standard
    deviations within 20 % (paths drawn from one particle system: the Monte-Carlo error is that of the filter
    plus that of the 400 draws)."""
    problem = linear[0]
    A, C, Q, R, B = linear[3]
    kf = jo.make_kalman(A, C, Q, R, Gamma=B, x0=problem.x0, P0=problem.P0)
    smoothed = jo.smooth(jo.kalman_filter, kf, problem.inputs())[1]
    params = jo.make_particle_filter(problem.model(), 2000, key=jax.random.key(2))
    smooth = jax.jit(lambda p, key: jo.particle_smoother(p, problem.inputs(), key=key, num_paths=400))
    _, paths = smooth(params, jax.random.key(3))
    sd = np.sqrt(np.diagonal(np.asarray(smoothed.P), axis1=1, axis2=2))
    assert paths.paths.shape == (15, 400, 3)
    assert np.max(np.abs(paths.x - smoothed.x) / sd) < 0.2
    assert np.max(np.abs(np.sqrt(np.diagonal(np.asarray(paths.P), axis1=1, axis2=2)) / sd - 1)) < 0.2


def test_jit_equals_eager_and_vmap_over_plants_equals_a_loop(linear):
    """Three plants with different process noise and keys, filtered (auxiliary filter, residual resampling) and
    smoothed: ``vmap`` over their params equals a loop, and an eager run equals the jitted one."""
    problem = linear[0]
    scales, keys = jnp.array([0.5, 1.0, 2.0]), jax.random.split(jax.random.key(5), 3)

    def smoothed(scale, key):
        model = jo.nonlinear_model(problem.f, problem.h, scale * problem.Q, problem.R, x0=problem.x0,
                                   P0=problem.P0, n_inputs=1)  # fmt: skip
        params = jo.make_particle_filter(model, 32, key=key, scheme="residual", auxiliary=True)
        return jo.particle_smoother(params, problem.inputs(), key=jax.random.fold_in(key, 1), num_paths=4)

    batched = jax.tree.leaves(jax.jit(jax.vmap(smoothed))(scales, keys))
    for i in range(3):
        single = jax.tree.leaves(jax.jit(smoothed)(scales[i], keys[i]))
        for got, want in zip(batched, single, strict=True):
            np.testing.assert_allclose(got[i], want, rtol=1e-12, atol=1e-12)
    eager = jax.tree.leaves(smoothed(scales[0], keys[0]))
    for got, want in zip(eager, jax.tree.leaves(jax.jit(smoothed)(scales[0], keys[0])), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_bad_inputs_raise_naming_the_argument(linear):
    problem = linear[0]
    model, key = problem.model(), jax.random.key(0)
    with pytest.raises(ValueError, match="scheme must be one of"):
        jo.make_particle_filter(model, 10, key=key, scheme="optimal")
    with pytest.raises(ValueError, match="num_particles must be an integer >= 1"):
        jo.make_particle_filter(model, 0, key=key)
    with pytest.raises(ValueError, match="ess_threshold must be in"):
        jo.make_particle_filter(model, 10, key=key, ess_threshold=1.5)
    with pytest.raises(ValueError, match="key must be a PRNG key"):
        jo.make_particle_filter(model, 10, key=0)
    with pytest.raises(ValueError, match="model must be a NonlinearModel"):
        jo.make_particle_filter(problem, 10, key=key)
    with pytest.raises(ValueError, match="model is continuous-time"):
        jo.make_particle_filter(problem.model(continuous=True), 10, key=key)
    with pytest.raises(ValueError, match="auxiliary must be a bool"):
        jo.make_particle_filter(model, 10, key=key, auxiliary="yes")
    params = jo.make_particle_filter(model, 10, key=key)
    with pytest.raises(ValueError, match=r"inputs.y must have shape \(2,\)"):
        jo.run(jo.particle_filter, params, jo.EstimatorInputs(y=jnp.ones((5, 3)), u_prev=jnp.ones((5, 1))))
    with pytest.raises(ValueError, match="inputs.u_prev is required"):
        jo.run(jo.particle_filter, params, jo.EstimatorInputs(y=jnp.ones((5, 2))))
    with pytest.raises(ValueError, match="num_paths must be an integer >= 1"):
        jo.particle_smoother(params, problem.inputs(), key=key, num_paths=0)
    singular = jo.nonlinear_model(problem.f, problem.h, np.diag([1.0, 0.0, 1.0]), problem.R, x0=problem.x0,
                                  n_inputs=1)  # fmt: skip
    with pytest.raises(ValueError, match="params.model.Q must be positive definite"):
        jo.particle_smoother(jo.make_particle_filter(singular, 10, key=key), problem.inputs(), key=key, num_paths=2)
    assert isinstance(jo.particle_filter.init(params), ParticleState)
