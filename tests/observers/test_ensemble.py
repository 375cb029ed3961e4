"""Tests for jaxobs.observers.ensemble: filterpy's EnsembleKalmanFilter on a fixed ensemble with the same draws,
the transform update against the Kalman update of the ensemble's moments, the ensemble Kalman smoother against
the RTS smoother, convergence to the Kalman filter as the ensemble grows, missing data, jit/vmap/grad and bad
inputs."""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxobs as jo
from jaxobs.kalman_steps import update
from jaxobs.observers import ensemble
from tests._nonlinear_models import linear_problem, pendulum

filterpy_enkf = pytest.importorskip("filterpy.kalman.ensemble_kalman_filter")


def test_equals_filterpy_on_a_fixed_ensemble(monkeypatch):
    """filterpy's EnsembleKalmanFilter started from our initial ensemble and fed our draws (its
    ``multivariate_normal`` replaced by the process noises and observation perturbations of
    :func:`~jaxobs.observers.ensemble.perturbations`, in the order it asks for them) on the pendulum with a
    2-output measurement: the ensembles, means, gains, innovation covariances and forecast covariances agree
    to 1e-8 at every sample (measured 2e-15)."""
    problem = pendulum(T=25)
    f = lambda x, u, t: problem.f(x, jnp.zeros(1), t)  # the pendulum without its torque input
    h = lambda x: jnp.array([jnp.sin(x[0]), x[0] * x[1]])
    R = np.diag([0.1, 0.2])
    model = jo.nonlinear_model(f, h, problem.Q, R, x0=problem.x0, P0=problem.P0)
    y = np.random.default_rng(0).normal(size=(25, 2))
    params = jo.make_enkf(model, 20, key=jax.random.key(3), output_ensemble=True)
    state = jo.ensemble_kalman_filter.init(params)
    _, out = jo.run(jo.ensemble_kalman_filter, params, jo.EstimatorInputs(y=jnp.asarray(y)), state)
    key, draws, perturbations = state.key, [], jax.jit(ensemble.perturbations)
    for k in range(25):
        key, W, E = perturbations(params, key)
        draws += ([np.asarray(W)] if k else []) + [np.asarray(E)]  # no forecast before the first update
    f_numpy = jax.jit(jax.vmap(lambda x: f(x, None, 0.0)))  # filterpy maps one member at a time: NumPy twins
    h_numpy = lambda x: np.array([np.sin(x[0]), x[0] * x[1]])
    peer = filterpy_enkf.EnsembleKalmanFilter(x=problem.x0, P=problem.P0, dim_z=2, dt=1.0, N=20, hx=h_numpy,
                                              fx=lambda x, dt: np.asarray(f_numpy(x[None]))[0])  # fmt: skip
    peer.Q, peer.R = problem.Q, R
    peer.sigmas, peer.x = np.array(state.ensemble), np.mean(state.ensemble, axis=0)
    supply = iter(draws)
    monkeypatch.setattr(filterpy_enkf, "multivariate_normal", lambda mean, cov, size: next(supply))
    for k in range(25):
        if k:
            peer.predict()
            np.testing.assert_allclose(out.P_prior[k], peer.P_prior, rtol=0, atol=1e-8)
        peer.update(y[k])
        for ours, theirs in ((out.ensemble[k], peer.sigmas), (out.x[k], peer.x), (out.gain[k], peer.K),
                             (out.S[k], peer.S)):  # fmt: skip
            np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-8)


@pytest.mark.parametrize("method", ensemble.METHODS)
def test_transform_reproduces_the_analysis(method):
    """Both analyses are the forecast times their (N, N) transform, missing components included; the ensemble
    transform's mean and sample covariance are exactly the Kalman update of the forecast's sample moments."""
    rng = np.random.default_rng(1)
    X, C = jnp.asarray(rng.normal(size=(12, 4))), jnp.asarray(rng.normal(size=(3, 4)))
    R, y = jnp.diag(jnp.array([0.3, 0.5, 0.2])), jnp.array([0.4, jnp.nan, -1.0])
    if method == "stochastic":
        perturbations = jnp.asarray(rng.normal(size=(12, 3)))
        analysis = jax.jit(partial(ensemble.stochastic_update, transform=True))(X, X @ C.T, R, y, perturbations)
    else:
        analysis = jax.jit(partial(ensemble.transform_update, transform=True))(X, X @ C.T, R, y)
        kalman = jax.jit(partial(update, joseph=False))(jnp.mean(X, axis=0), jnp.cov(X.T), C, R, y)
        np.testing.assert_allclose(jnp.mean(analysis.ensemble, axis=0), kalman.x, rtol=1e-12)
        np.testing.assert_allclose(jnp.cov(analysis.ensemble.T), kalman.P, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(analysis.transform @ X, analysis.ensemble, rtol=1e-12, atol=1e-13)
    np.testing.assert_array_equal(analysis.update.K[:, 1], 0.0)


def test_transform_smoother_without_process_noise_is_the_rts_smoother():
    """Without process noise, a linear model keeps the ensemble in the span of its first draws, and the
    ensemble transform filter and the ensemble Kalman smoother are exactly the Kalman filter and the RTS smoother
    started from the sample mean and covariance of the initial ensemble (to rounding: 1e-10), with an input and
    missing components. The transition is a scaled rotation: the RTS smoother's gain is then its inverse, whose
    norm (1 / 0.98) does not amplify the rounding errors of the backward pass."""
    problem, _, B, C = linear_problem(T=20)
    A = 0.98 * np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))[0]
    f = lambda x, u, t: jnp.asarray(A) @ x + jnp.asarray(B) @ u
    model = jo.nonlinear_model(f, problem.h, np.zeros((3, 3)), problem.R, x0=problem.x0, P0=problem.P0, n_inputs=1)
    params = jo.make_enkf(model, 8, key=jax.random.key(0), method="transform")
    filtered, smoothed = jax.jit(lambda p: jo.ensemble_smoother(p, problem.inputs()))(params)
    first = jo.ensemble_kalman_filter.init(params).ensemble
    kf = jo.make_kalman(A, C, np.zeros((3, 3)), problem.R, Gamma=B, x0=jnp.mean(first, axis=0), P0=jnp.cov(first.T))
    kf_filtered, kf_smoothed = jo.smooth(jo.kalman_filter, kf, problem.inputs())
    pairs = [(filtered, kf_filtered, "x"), (filtered, kf_filtered, "P"), (filtered, kf_filtered, "log_likelihood"),
             (smoothed, kf_smoothed, "x"), (smoothed, kf_smoothed, "P")]  # fmt: skip
    for ours, exact, name in pairs:
        np.testing.assert_allclose(getattr(ours, name), getattr(exact, name), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("method", ensemble.METHODS)
def test_large_ensemble_approaches_the_kalman_filter(method):
    """On a linear model with an input and missing data, the EnKF converges to the Kalman filter as the ensemble
    grows (Monte-Carlo error ~ 1 / sqrt(N)): with 10 000 members the means are within 0.15 posterior standard
    deviations and the covariances within 10 % at every sample, and both errors are below a quarter of those
    of 100 members (expected: a tenth)."""
    problem, A, B, C = linear_problem(T=20)
    kf = jo.make_kalman(A, C, problem.Q, problem.R, Gamma=B, x0=problem.x0, P0=problem.P0)
    exact = jo.run(jo.kalman_filter, dataclasses.replace(kf, output_covariance=True), problem.inputs())[1]
    sd = np.sqrt(np.diagonal(np.asarray(exact.P), axis1=1, axis2=2))

    def errors(members):
        params = jo.make_enkf(problem.model(), members, key=jax.random.key(4), method=method)
        out = jax.jit(lambda p: jo.run(jo.ensemble_kalman_filter, p, problem.inputs())[1])(params)
        return np.max(np.abs(out.x - exact.x) / sd), np.max(np.abs(out.P - exact.P) / np.abs(exact.P).max())

    large, small = errors(10_000), errors(100)
    assert large[0] < 0.15 and large[1] < 0.1, large
    assert large[0] < small[0] / 4 and large[1] < small[1] / 4, (large, small)


def _enkf_log_likelihood(problem, method):
    """The ensemble filter's log-likelihood of ``problem`` as a function of ``(Q scale, R scale)`` and the key."""

    def log_likelihood(scales, key):
        model = jo.nonlinear_model(problem.f, problem.h, scales[0] * problem.Q, scales[1] * problem.R,
                                   x0=problem.x0, P0=problem.P0, n_inputs=1)  # fmt: skip
        params = jo.make_enkf(model, 6, key=key, method=method, inflation=1.05)
        return jnp.sum(jo.run(jo.ensemble_kalman_filter, params, problem.inputs())[1].log_likelihood)

    return log_likelihood


@pytest.mark.parametrize("method", ensemble.METHODS)
def test_gradient_matches_central_differences(method):
    """For a fixed key the ensemble filter is a smooth function of the model: the gradient of its
    log-likelihood with respect to the noise scales (missing components included; through the transform's
    matrix square root for ``"transform"``) equals central differences to 1e-6 relative."""
    log_likelihood = jax.jit(_enkf_log_likelihood(linear_problem(T=12)[0], method))
    scales, key, step = jnp.array([1.0, 0.8]), jax.random.key(1), 1e-5
    gradient = jax.jit(jax.grad(log_likelihood))(scales, key)
    for i in range(2):
        e = step * jnp.eye(2)[i]
        central = (log_likelihood(scales + e, key) - log_likelihood(scales - e, key)) / (2 * step)
        np.testing.assert_allclose(gradient[i], central, rtol=1e-6)


def test_vmap_over_plants_equals_a_loop():
    """Three plants (noise scales and keys) filtered and smoothed (transform filter, ensemble Kalman smoother):
    ``vmap`` equals a loop, eager equals jit."""
    problem = linear_problem(T=12)[0]

    def smoothed(scales, key):
        model = jo.nonlinear_model(problem.f, problem.h, scales[0] * problem.Q, scales[1] * problem.R,
                                   x0=problem.x0, P0=problem.P0, n_inputs=1)  # fmt: skip
        return jo.ensemble_smoother(jo.make_enkf(model, 6, key=key, method="transform"), problem.inputs())

    scales, keys = jnp.array([[1.0, 1.0], [0.5, 2.0], [2.0, 0.5]]), jax.random.split(jax.random.key(2), 3)
    batched = jax.tree.leaves(jax.jit(jax.vmap(smoothed))(scales, keys))
    for i in range(3):
        single = jax.tree.leaves(jax.jit(smoothed)(scales[i], keys[i]))
        for got, want in zip(batched, single, strict=True):
            np.testing.assert_allclose(got[i], want, rtol=1e-10, atol=1e-12)
    eager = jax.tree.leaves(smoothed(scales[1], keys[1]))
    for got, want in zip(eager, jax.tree.leaves(jax.jit(smoothed)(scales[1], keys[1])), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


def test_bad_inputs_raise_naming_the_argument():
    problem = linear_problem(T=12)[0]
    model, key = problem.model(), jax.random.key(0)
    with pytest.raises(ValueError, match="method must be one of"):
        jo.make_enkf(model, 10, key=key, method="square-root")
    with pytest.raises(ValueError, match="num_members must be an integer >= 2"):
        jo.make_enkf(model, 1, key=key)
    with pytest.raises(ValueError, match="inflation must be >= 1"):
        jo.make_enkf(model, 10, key=key, inflation=0.9)
    with pytest.raises(ValueError, match="key must be a PRNG key"):
        jo.make_enkf(model, 10, key=np.zeros(3))
    with pytest.raises(ValueError, match="model is continuous-time"):
        jo.make_enkf(problem.model(continuous=True), 10, key=key)
    with pytest.raises(ValueError, match="model has a feedthrough"):
        jo.make_enkf(dataclasses.replace(model, feedthrough=True), 10, key=key)
    with pytest.raises(ValueError, match="output_ensemble must be a bool"):
        jo.make_enkf(model, 10, key=key, output_ensemble=1)
    X, R = jnp.zeros((5, 3)), jnp.eye(2)
    with pytest.raises(ValueError, match=r"predicted must have shape \(N, p\) = \(5, p\), got \(4, 2\)"):
        ensemble.transform_update(X, jnp.zeros((4, 2)), R, jnp.zeros(2))
    with pytest.raises(ValueError, match=r"perturbations must have shape \(5, 2\)"):
        ensemble.stochastic_update(X, jnp.zeros((5, 2)), R, jnp.zeros(2), jnp.zeros((5, 3)))
    with pytest.raises(ValueError, match="forecast must have at least 2 members"):
        ensemble.transform_update(X[:1], jnp.zeros((1, 2)), R, jnp.zeros(2))
    params = jo.make_enkf(model, 10, key=key)
    with pytest.raises(ValueError, match="inputs.u_prev is required"):
        jo.run(jo.ensemble_kalman_filter, params, jo.EstimatorInputs(y=jnp.ones((5, 2))))
