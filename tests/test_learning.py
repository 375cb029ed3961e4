"""Tests for jaxobs.learning: maximum-likelihood fits with optax and EM for the linear-Gaussian model on data drawn
from known models (recovery within the Fisher information's standard errors, EM and the gradient fit at the same
optimum, EM's log-likelihood never decreasing, missing data), the fitted filter's one-step prediction error against
the true model's, jit/vmap, and the errors of the entry points. The error-against-T evidence (T = 10^3 .. 10^4,
several seeds) is benchmarks/learning.py, run by the slow test at the end."""

import dataclasses
import importlib.util
import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jaxobs.learning import FitSettings, als, covariance_model, em, fit, negative_log_likelihood, sample
from jaxobs.nonlinear import nonlinear_model
from jaxobs.observers import EstimatorInputs, run
from jaxobs.observers.ekf import extended_kalman_filter, make_ekf
from jaxobs.observers.kalman import kalman_filter, make_kalman
from jaxobs.observers.ukf import make_ukf, unscented_kalman_filter
from jaxobs.smoothing import log_likelihood
from jaxobs.tuning import cholesky_covariance, cholesky_parameters, unit_interval, unit_interval_parameters
from tests import ROOT
from tests._nonlinear_models import GRAVITY, pendulum, pendulum_f, pendulum_h

TRUE_SCALAR = dict(Phi=0.8, Q=0.5, R=0.3)  # x_k = 0.8 x_{k-1} + w, y = x + v
B, T = 4, 250


def scalar_model(base, theta):
    """``Phi`` in (0, 1), ``Q`` and ``R`` positive: the tuner's parameterisations."""
    return dataclasses.replace(base, Phi=unit_interval(theta["phi"])[None, None],
                               Q=cholesky_covariance(theta["Q"]), R=cholesky_covariance(theta["R"]))  # fmt: skip


@pytest.fixture(scope="module")
def scalar_data():
    truth = make_kalman([[TRUE_SCALAR["Phi"]]], [[1.0]], [[TRUE_SCALAR["Q"]]], [[TRUE_SCALAR["R"]]], P0=[[1.0]])
    keys = jax.random.split(jax.random.PRNGKey(3), B)
    _, y = jax.vmap(lambda k: sample(truth, k, T))(keys)
    return truth, y


@pytest.fixture(scope="module")
def scalar_fit(scalar_data):
    truth, y = scalar_data
    base = make_kalman([[0.5]], [[1.0]], [[1.0]], [[1.0]], P0=[[1.0]])
    build = jax.tree_util.Partial(scalar_model, base)
    theta0 = {"phi": unit_interval_parameters(0.5), "Q": cholesky_parameters(base.Q), "R": cholesky_parameters(base.R)}
    return base, build, fit(kalman_filter, build, theta0, EstimatorInputs(y=y), progress=False)


def _hessian(f, x, h):
    """Central second differences of ``f`` at ``x`` (error O(h^2)); one compiled forward function, no second
    derivative to compile."""
    n = len(x)
    H = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            ei, ej = np.eye(n)[i] * h, np.eye(n)[j] * h
            H[i, j] = H[j, i] = (f(x + ei + ej) - f(x + ei - ej) - f(x - ei + ej) + f(x - ei - ej)) / (4 * h * h)
    return H


def test_fit_recovers_the_model_within_its_standard_errors(scalar_data, scalar_fit):
    """Phi, Q, R fitted from 4 x 250 samples lie within 4 standard errors of the truth, the standard errors from the
    observed Fisher information (the Hessian of -log p(Y) at the fit, in (Phi, log Q, log R) coordinates); the
    loss curve ends at its minimum, the fit stopped early, and the returned theta is the best iterate."""
    truth, y = scalar_data
    _, build, result = scalar_fit
    assert result.stopped == "converged" and len(result.loss) < FitSettings().steps
    assert result.best_loss == result.loss.min() and result.loss[-1] <= result.loss[0]
    fitted = np.array([result.params.Phi[0, 0], math.log(result.params.Q[0, 0]), math.log(result.params.R[0, 0])])

    @jax.jit
    def nll(v):  # -log p(Y) in (Phi, log Q, log R)
        params = dataclasses.replace(truth, Phi=v[0][None, None], Q=jnp.exp(v[1])[None, None],
                                     R=jnp.exp(v[2])[None, None])  # fmt: skip
        return negative_log_likelihood(kalman_filter, params, EstimatorInputs(y=y)) * y.size

    information = _hessian(lambda v: float(nll(jnp.asarray(v))), fitted, 1e-3)
    standard_errors = np.sqrt(np.diag(np.linalg.inv(np.asarray(information))))
    true = np.array([TRUE_SCALAR["Phi"], math.log(TRUE_SCALAR["Q"]), math.log(TRUE_SCALAR["R"])])
    z = np.abs(fitted - true) / standard_errors
    assert np.all(z < 4), (fitted, true, standard_errors)
    assert np.all(standard_errors < 0.3)  # the data do identify the model


def test_em_and_gradient_fit_agree_at_the_optimum(scalar_data, scalar_fit):
    """EM (Phi, Q, R) from the same start reaches the fit's optimum: equal parameters to 1e-4 (EM converges
    linearly) and log-likelihoods to 1e-8 relative; EM's log-likelihood never decreases."""
    _, y = scalar_data
    base, _, result = scalar_fit
    by_em = em(base, EstimatorInputs(y=y), iterations=2000, update=("Phi", "Q", "R"), tolerance=1e-13)
    n = int(by_em.iterations)
    ll = np.asarray(by_em.log_likelihood[:n])
    assert bool(by_em.converged) and np.all(np.diff(ll) >= -1e-10 * np.abs(ll[1:]))
    for name in ("Phi", "Q", "R"):
        np.testing.assert_allclose(getattr(by_em.params, name), getattr(result.params, name), atol=1e-4)
    np.testing.assert_allclose(ll[-1], -result.best_loss * y.size, rtol=1e-8)


def test_fitted_filter_predicts_as_well_as_the_true_model(scalar_data, scalar_fit):
    """On a fresh record of 20000 samples the fitted filter's mean squared one-step prediction error equals the
    true filter's within 2 standard errors of the latter (its innovations are white)."""
    truth, _ = scalar_data
    _, _, result = scalar_fit
    _, y = sample(truth, jax.random.PRNGKey(99), 20000)
    innovation = jax.jit(lambda params: run(kalman_filter, params, EstimatorInputs(y=y))[1].innovation[:, 0])
    e_fit, e_true = np.asarray(innovation(result.params)) ** 2, np.asarray(innovation(truth)) ** 2
    standard_error = e_true.std() / math.sqrt(e_true.size)
    assert abs(e_fit.mean() - e_true.mean()) < 2 * standard_error
    assert e_fit.mean() >= e_true.mean() - 2 * standard_error


def _pendulum_model(make, base, theta):
    """The EKF or UKF (``make``) of the pendulum ``base`` of tests/_nonlinear_models.py with the gravity
    ``theta["g"]`` and the measurement noise variance ``exp(theta["log_r"])``."""
    f = jax.tree_util.Partial(lambda g, x, u, t: pendulum_f(x, u, t, g), theta["g"])
    model = nonlinear_model(f, pendulum_h, base.Q, jnp.exp(theta["log_r"]) * jnp.eye(1), x0=base.x0, P0=base.P0,
                            n_inputs=1)  # fmt: skip
    return make(model)


@pytest.mark.parametrize("name", ["ekf", pytest.param("ukf", marks=pytest.mark.slow)])
def test_fit_learns_a_nonlinear_model_through_the_filter_likelihood(name):
    """The pendulum's gravity and measurement noise (true 9.81 and R = 0.09) fitted by maximising the EKF's (UKF's)
    log-likelihood of 4 x 200 samples from a start at g = 7, R = 0.3: the fit converges and lies within 3 standard
    errors of the truth, the standard errors from the Hessian of -log p(Y) at the fit (measured: EKF g = 9.06 +-
    0.51, R = 0.088; UKF g = 9.97 +- 0.53, R = 0.084); the gradient reaches g through f's Partial and R."""
    estimator, make = {"ekf": (extended_kalman_filter, make_ekf), "ukf": (unscented_kalman_filter, make_ukf)}[name]
    records = [pendulum(T=200, seed=seed) for seed in range(4)]
    inputs = EstimatorInputs(jnp.stack([r.y for r in records]), jnp.stack([r.u_prev for r in records]))
    build = partial(_pendulum_model, make, records[0])
    result = fit(estimator, build, {"g": 7.0, "log_r": math.log(0.3)}, inputs, progress=False)
    assert result.stopped == "converged" and result.best_loss < result.loss[0]
    fitted = np.array([float(result.theta["g"]), float(result.theta["log_r"])])
    count = int(np.sum(np.isfinite(inputs.y)))
    nll = jax.jit(lambda v: negative_log_likelihood(estimator, build({"g": v[0], "log_r": v[1]}), inputs) * count)
    information = _hessian(lambda v: float(nll(jnp.asarray(v))), fitted, 1e-3)
    standard_errors = np.sqrt(np.diag(np.linalg.inv(information)))
    z = np.abs(fitted - np.array([GRAVITY, math.log(0.09)])) / standard_errors
    assert np.all(z < 3), (fitted, standard_errors)
    assert np.all(standard_errors < [1.0, 0.1])  # the data do identify g and R


def test_progress_bar_and_adam(scalar_data, capsys):
    """A first-order optimizer of the tuner (adam) with the progress bar: the loss decreases."""
    _, y = scalar_data
    build, theta0 = covariance_model(make_kalman([[0.8]], [[1.0]], [[2.0]], [[2.0]], P0=[[1.0]]))
    settings = FitSettings(optimizer=optax.adam(0.02), steps=40, patience=40)
    result = fit(kalman_filter, build, theta0, EstimatorInputs(y=y), settings)
    assert result.loss[-1] < result.loss[0] and len(result.loss) == 40 and result.stopped == "steps"
    assert "fit" in capsys.readouterr().err


def _model_with_inputs():
    Phi = [[0.9, 0.2], [-0.1, 0.7]]
    R = [[0.3, 0.1], [0.1, 0.2]]
    return make_kalman(Phi, [[1.0, 0.0], [0.5, 1.0]], [[0.4, 0.1], [0.1, 0.2]], R, Gamma=[[0.0], [1.0]],
                       x0=[0.5, -0.2], P0=[[1.0, 0.2], [0.2, 0.5]])  # fmt: skip


def _data_with_missing(key, sequences=3, steps=60):
    truth = _model_with_inputs()
    ku, kx = jax.random.split(key)
    u = jax.random.normal(ku, (sequences, steps, 1))
    _, y = jax.vmap(lambda k, uu: sample(truth, k, steps, uu))(jax.random.split(kx, sequences), u)
    y = np.array(y)
    y[:, 3::7, 0] = np.nan  # one component missing
    y[:, 5::11, :] = np.nan  # both missing
    return EstimatorInputs(y=jnp.asarray(y), u_prev=u)


@pytest.fixture(scope="module")
def missing_data():
    return _data_with_missing(jax.random.PRNGKey(0), sequences=2, steps=100)


def test_em_never_decreases_the_likelihood_with_missing_data(missing_data):
    """EM over every field (Phi, Gamma, C, Q, R, x0, P0) from a wrong start, on 2 sequences with inputs, a correlated R
    and missing components (one or both): the log-likelihood rises at every iteration, and the learned covariances
    stay symmetric positive definite."""
    start = make_kalman(np.eye(2) * 0.5, np.eye(2), np.eye(2), np.eye(2), Gamma=[[0.3], [0.3]], P0=np.eye(2))
    result = em(start, missing_data, iterations=25, update=("Phi", "Gamma", "C", "Q", "R", "x0", "P0"), tolerance=0.0)
    ll = np.asarray(result.log_likelihood)
    assert int(result.iterations) == 25 and np.all(np.isfinite(ll))
    assert np.all(np.diff(ll) >= -1e-10 * np.abs(ll[1:])), np.diff(ll)
    assert ll[-1] > ll[0] + 10
    for name in ("Q", "R", "P0"):
        M = np.asarray(getattr(result.params, name))
        np.testing.assert_allclose(M, M.T)
        assert np.linalg.eigvalsh(M).min() > 0


def test_em_fixed_point_is_a_stationary_point_with_missing_data(missing_data):
    """With missing components and a correlated R, EM's fixed point in (Q, R) is a stationary point of the exact
    log-likelihood (the missing components are handled exactly in the M-step): the gradient there is below 1e-5 of
    its size at the start."""
    start = dataclasses.replace(_model_with_inputs(), Q=jnp.eye(2), R=jnp.eye(2))
    result = em(start, missing_data, iterations=3000, tolerance=1e-15)

    def loss(theta, params):
        model = dataclasses.replace(params, Q=cholesky_covariance(theta["Q"]), R=cholesky_covariance(theta["R"]))
        return negative_log_likelihood(kalman_filter, model, missing_data)

    grad = jax.jit(jax.grad(loss))

    def gradient(params):
        theta = {"Q": cholesky_parameters(params.Q), "R": cholesky_parameters(params.R)}
        return np.concatenate([np.ravel(g) for g in jax.tree.leaves(grad(theta, params))])

    assert np.linalg.norm(gradient(result.params)) < 1e-5 * np.linalg.norm(gradient(start))


def test_missing_data_loss_is_per_observed_component(missing_data):
    """The loss is -log p(observed Y) divided by the number of observed components; a NaN-filled record adds
    nothing."""
    params = _model_with_inputs()
    total = sum(float(log_likelihood(kalman_filter, params, EstimatorInputs(missing_data.y[b], missing_data.u_prev[b])))
                for b in range(2))  # fmt: skip
    count = int(np.sum(np.isfinite(np.asarray(missing_data.y))))
    padded = EstimatorInputs(jnp.concatenate([missing_data.y, jnp.full((1, 100, 2), jnp.nan)]),
                             jnp.concatenate([missing_data.u_prev, jnp.zeros((1, 100, 1))]))  # fmt: skip
    np.testing.assert_allclose(negative_log_likelihood(kalman_filter, params, padded), -total / count, rtol=1e-12)


def test_jit_and_vmap(missing_data):
    """negative_log_likelihood and em under jit and vmap over two data sets equal the eager calls (em stopping at a
    relative change of 1e-12, well above rounding, so that both stop at the same iteration)."""
    datasets = [missing_data, missing_data._replace(y=missing_data.y[::-1] * 0.9)]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *datasets)
    params = dataclasses.replace(_model_with_inputs(), Q=jnp.eye(2), R=jnp.eye(2))
    eager = [negative_log_likelihood(kalman_filter, params, d) for d in datasets]
    batched = jax.jit(jax.vmap(lambda d: negative_log_likelihood(kalman_filter, params, d)))(stacked)
    np.testing.assert_allclose(batched, eager, rtol=1e-12)
    each = [em(params, d, iterations=3000, tolerance=1e-12) for d in datasets]
    together = jax.jit(jax.vmap(lambda d: em(params, d, iterations=3000, tolerance=1e-12)))(stacked)
    for i, single in enumerate(each):
        assert 10 < int(single.iterations) < 3000
        assert int(single.iterations) == int(together.iterations[i])
        for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(jax.tree.map(lambda x, i=i: x[i], together)),
                        strict=True):  # fmt: skip
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


def test_sample_has_the_model_statistics():
    """sample from the stationary prior of x_k = 0.8 x_{k-1} + w, y = x + v (Var x = 0.5 / (1 - 0.64), Var v = 0.3,
    lag-one correlation 0.8) over 40000 samples: the moments agree within 4 standard errors."""
    stationary = 0.5 / (1 - 0.64)
    params = make_kalman([[0.8]], [[1.0]], [[0.5]], [[0.3]], P0=[[stationary]])
    x, y = sample(params, jax.random.PRNGKey(7), 40000)
    x, v = np.asarray(x[:, 0]), np.asarray(y[:, 0] - x[:, 0])
    effective = x.size * (1 - 0.64) / (1 + 0.64)  # samples of the AR(1) variance's estimate
    assert abs(x.var() / stationary - 1) < 4 * math.sqrt(2 / effective)
    assert abs(v.var() / 0.3 - 1) < 4 * math.sqrt(2 / v.size)
    assert abs(np.corrcoef(x[1:], x[:-1])[0, 1] - 0.8) < 4 * math.sqrt((1 - 0.64) / x.size)
    assert abs(np.corrcoef(x, v)[0, 1]) < 4 / math.sqrt(x.size)


def test_bad_inputs_raise_naming_the_argument(scalar_data):
    _, y = scalar_data
    params = make_kalman([[0.8]], [[1.0]], [[0.5]], [[0.3]])
    build, theta0 = covariance_model(params)
    inputs = EstimatorInputs(y=y)
    ekf = make_ekf(nonlinear_model(lambda x, u, t: 0.8 * x, lambda x: x, [[0.5]], [[0.3]], x0=[0.0]))
    cases = [
        (lambda: fit(kalman_filter, build, theta0, inputs, FitSettings(optimizer="newton")), "settings.optimizer"),
        (lambda: fit(kalman_filter, build, theta0, inputs, FitSettings(steps=0)), "settings.steps"),
        (lambda: fit(kalman_filter, build, theta0, inputs, FitSettings(tolerance=-1.0)), "settings.tolerance"),
        (lambda: fit(kalman_filter, build, theta0, inputs, {"steps": 3}), "settings"),
        (lambda: fit("kalman", build, theta0, inputs), "estimator"),
        (lambda: fit(kalman_filter, "build", theta0, inputs), "build_params"),
        (lambda: fit(kalman_filter, build, {"Q": jnp.full((1, 1), jnp.nan), "R": theta0["R"]}, inputs), "theta0"),
        (lambda: fit(kalman_filter, build, theta0, EstimatorInputs(y=y[..., None])), "inputs.y"),
        (lambda: fit(kalman_filter, build, theta0, y), "inputs"),
        (lambda: em(params, EstimatorInputs(y=jnp.full((2, 5, 1), jnp.nan))), "inputs.y"),
        (lambda: em(params, EstimatorInputs(y=y, u_prev=jnp.zeros((B, T - 1, 0)))), "inputs.u_prev"),
        (lambda: em(params, inputs, update=("Q", "S")), "update"),
        (lambda: em(params, inputs, update=("Gamma",)), "update"),
        (lambda: em(params, inputs, iterations=0), "iterations"),
        (lambda: em(params, inputs, tolerance=-1.0), "tolerance"),
        (lambda: em(make_kalman([[0.8]], [[1.0]], [[0.5]], [[0.3]], steady_state=True), inputs), "params"),
        (lambda: em(params, EstimatorInputs(y=y[:, :1])), "inputs.y"),
        (lambda: covariance_model(params, ("Q", "S")), "names"),
        (lambda: covariance_model(ekf, ("model.Q", "model.S")), "names"),
        (lambda: negative_log_likelihood(extended_kalman_filter, ekf, EstimatorInputs(y=y[..., None])), "inputs.y"),
        (lambda: covariance_model(dataclasses.replace(params, Q=jnp.zeros((1, 1)))), "params.Q"),
        (lambda: sample(params, jax.random.PRNGKey(0), 0), "num_steps"),
        (lambda: sample(jo_aob(), jax.random.PRNGKey(0), 4), "params"),
        (lambda: sample(params, jax.random.PRNGKey(0), 4, jnp.zeros((4, 2))), "u_prev"),
    ]
    for call, name in cases:
        with pytest.raises(ValueError, match=rf"^{name}\b|\b{name}\b"):
            call()


def test_initial_point_with_non_finite_loss_is_an_error(scalar_data, scalar_fit):
    _, y = scalar_data
    _, build, result = scalar_fit
    theta0 = {**result.theta, "R": jnp.full((1, 1), 800.0)}  # R = exp(800)^2 overflows to inf
    with pytest.raises(ValueError, match="theta0"):
        fit(kalman_filter, build, theta0, EstimatorInputs(y=y), progress=False)


def jo_aob():
    from jaxobs.lti import c2d, ss
    from jaxobs.observers.active import make_aob

    return make_aob(c2d(ss([[0.0]], [[1.0]], [[1.0]]), 0.01), 1, [[0.2]])


@pytest.mark.slow
def test_errors_shrink_as_one_over_root_T(tmp_path):
    """benchmarks/learning.py at T = 10^3 and 10^4 over 5 seeds (full Q and R of a 2-state, 2-output model): the
    RMS relative errors of Q and R fall with a log-log slope between -0.8 and -0.3 (theory -0.5), the gradient fit
    and EM agree to 1e-3, and on fresh data the fitted filter's one-step prediction error is within 2 standard
    errors of the true model's in every case."""
    spec = importlib.util.spec_from_file_location("bench_learning", ROOT / "benchmarks" /
                                                  "learning.py")  # fmt: skip
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    result = bench.main(["--out", str(tmp_path), "--lengths", "1000", "10000", "--seeds", "5"])
    for name, slope in result["slope"].items():
        assert -0.8 < slope < -0.3, (name, slope)
    for case in result["cases"]:
        assert case["max_difference_fit_em"] < 1e-3 and case["fit_stopped"] == "converged"
        assert abs(case["mse_fitted"] - case["mse_true"]) < 2 * case["se_true"], case


# --------------------------------------------------------------------------------------------
# Autocovariance least squares

ALS_SEEDS, ALS_T, ALS_BURN_IN = 50, 2000, 100
ALS_CASES = {
    # position-velocity model driven by one acceleration noise through G, one output: Q (1x1) and R (1x1)
    "noise input": dict(Phi=[[1.0, 0.1], [0.0, 0.95]], C=[[1.0, 0.0]], G=[[0.005], [0.1]], Q=[[2.0]], R=[[0.1]]),
    # two outputs, full symmetric Q and R (3 + 3 unknowns)
    "full": dict(Phi=[[0.9, 0.2], [-0.1, 0.7]], C=[[1.0, 0.0], [0.5, 1.0]], G=None,
                 Q=[[0.5, 0.1], [0.1, 0.3]], R=[[0.2, 0.05], [0.05, 0.1]]),
}  # fmt: skip


@pytest.mark.parametrize("case", list(ALS_CASES))
def test_als_recovers_q_and_r_within_the_sampling_error(case):
    """Autocovariance least squares (Odelson, Rajamani & Rawlings 2006) on the innovations of a steady-state filter
    designed with a wrong guess of Q and R (5x off): across 50 simulated records of 2000 samples, the mean of
    every estimated entry of Q and R lies within 3 standard errors of the truth (measured: at most 1.5), and the
    standard errors are small (the test has power: below 10 % of each diagonal entry)."""
    c = ALS_CASES[case]
    Phi, C, Q, R = (jnp.asarray(c[k]) for k in ("Phi", "C", "Q", "R"))
    G = jnp.eye(2) if c["G"] is None else jnp.asarray(c["G"])
    true = make_kalman(Phi, C, G @ Q @ G.T, R)
    guess = make_kalman(Phi, C, 0.2 * G @ Q @ G.T, 5.0 * R, steady_state=True)

    def innovations(key):
        _, y = sample(true, key, ALS_T)
        return run(kalman_filter, guess, EstimatorInputs(y))[1].innovation[ALS_BURN_IN:]

    e = jax.jit(jax.vmap(innovations))(jax.random.split(jax.random.PRNGKey(7), ALS_SEEDS))
    result = jax.vmap(lambda e: als(guess, e, lags=10, G=c["G"]))(e)
    assert bool(jnp.all(result.identifiable))
    for name, truth in (("Q", Q), ("R", R)):
        estimates = np.asarray(getattr(result, name)).reshape(ALS_SEEDS, -1)
        mean, se = estimates.mean(0), estimates.std(0, ddof=1) / math.sqrt(ALS_SEEDS)
        assert np.all(np.abs(mean - np.ravel(truth)) < 3 * se), (name, mean, se)
        assert np.all(np.diagonal(se.reshape(truth.shape)) < 0.1 * np.diagonal(truth)), (name, se)


def test_als_jit_vmap_structure_and_errors():
    """eager = jit; a vmap over records and one over plants (the filter's gain) equal loops; with Q known to be
    diagonal there are fewer unknowns and a singular structure (a full 2x2 Q from one output) is reported as not
    identifiable; errors name the argument."""
    c = ALS_CASES["noise input"]
    true = make_kalman(c["Phi"], c["C"], np.asarray(c["G"]) @ c["Q"] @ np.asarray(c["G"]).T, c["R"])
    guess = make_kalman(c["Phi"], c["C"], np.eye(2) * 1e-3, [[1.0]], steady_state=True)
    _, y = jax.vmap(lambda k: sample(true, k, 400))(jax.random.split(jax.random.PRNGKey(1), 3))
    e = jax.vmap(lambda y: run(kalman_filter, guess, EstimatorInputs(y))[1].innovation)(y)[:, 50:]
    eager = als(guess, e[0], lags=8, G=c["G"])
    np.testing.assert_allclose(jax.jit(partial(als, lags=8, G=c["G"]), static_argnums=())(guess, e[0]).Q, eager.Q,
                               rtol=1e-10)  # fmt: skip
    batched = jax.vmap(lambda e: als(guess, e, lags=8, G=c["G"]))(e)
    np.testing.assert_allclose(batched.R[1], als(guess, e[1], lags=8, G=c["G"]).R, rtol=1e-10)
    gains = jnp.stack([guess.gain, 0.9 * guess.gain])  # two plants' filters (a vmap over params)
    plants = jax.vmap(lambda K: als(dataclasses.replace(guess, gain=K), e[0], lags=8, G=c["G"]))(gains)
    np.testing.assert_allclose(plants.Q[1], als(dataclasses.replace(guess, gain=gains[1]), e[0], lags=8,
                                                G=c["G"]).Q, rtol=1e-10)  # fmt: skip
    assert bool(eager.identifiable) and not bool(als(guess, e[0], lags=8).identifiable)
    diagonal = als(guess, e[0], lags=8, diagonal=("Q",))
    assert float(diagonal.Q[0, 1]) == 0.0 and bool(diagonal.identifiable)
    with pytest.raises(ValueError, match="params must be KalmanParams with the fixed gain"):
        als(make_kalman(c["Phi"], c["C"], np.eye(2), [[1.0]]), e[0])
    with pytest.raises(ValueError, match="innovation must have shape"):
        als(guess, e[0, :, 0], lags=3)
    with pytest.raises(ValueError, match="lags must be an integer in"):
        als(guess, e[0, :5], lags=8)
    with pytest.raises(ValueError, match="diagonal must name among"):
        als(guess, e[0], diagonal=("P0",))
    with pytest.raises(ValueError, match="G has shape"):
        als(guess, e[0], G=np.ones((3, 1)))
    unstable = dataclasses.replace(guess, gain=jnp.zeros((2, 1)), Phi=jnp.array([[1.1, 0.0], [0.0, 0.5]]))
    with pytest.raises(ValueError, match="does not stabilise the predictor"):
        als(unstable, e[0])
