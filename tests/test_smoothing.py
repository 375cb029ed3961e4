"""Tests for jaxobs.smoothing: the log-likelihood of a record, the RTS smoother and the parallel-in-time filter and
smoother, against exact dense Gaussian conditioning (missing values included), dynamax, cuthbert and filterpy,
with gradients, transformations and the errors of the entry points.

Prior conventions: jaxobs, dynamax take the prior of x_0 (the state at the first measurement); filterpy and cuthbert
start one step earlier (they predict before the first update), so they are given the prior of x_{-1} and jaxobs its
prediction (as in tests/observers/test_kalman.py)."""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from jax.test_util import check_grads

import jaxobs as jo
from jaxobs.closed_loop import simulate
from jaxobs.lti import c2d, ss
from jaxobs.observers import EstimatorInputs, LinearObserver, active, run
from jaxobs.observers.active import active_observer, active_observer_controller
from jaxobs.observers.kalman import kalman_filter, make_kalman, square_root_form, square_root_kalman_filter
from jaxobs.observers.linear import linear_observer
from jaxobs.papers.cortesao.force_control import EXAMPLE1, example1_disturbance, nominal_design, with_feedback
from jaxobs.smoothing import log_likelihood, parallel_filter, rts_smoother, smooth
from tests._nonlinear_models import (
    bearings,
    dynamax_params,
    linear_problem,
    pendulum,
    pendulum_f,
    relative_error,
    van_loan,
    without_dynamax_regularisation,
)
from tests.observers.test_kalman import make_problem, params_of, peer_problem


def dense_posterior(model, x0, P0, u, y):
    """Exact Gaussian conditioning of all states on all observed measurement components, by building the joint
    distribution of the stacked states and measurements of a short record: returns the filtered means and
    covariances (conditioned on y_0..y_k), the smoothed ones (on the whole record) and log p(observed y)."""
    Phi, Gamma, C, Q, R = (np.asarray(model[k]) for k in ("Phi", "Gamma", "C", "Q", "R"))
    T, n, p = y.shape[0], Phi.shape[0], C.shape[0]
    mean = [np.asarray(x0, float)]
    for k in range(1, T):
        mean.append(Phi @ mean[-1] + Gamma @ u[k])
    mean = np.concatenate(mean)
    B = np.zeros((T * n, T * n))  # x = mean + B z, z = (x_0 - x0, w_1, ..., w_{T-1})
    for k in range(T):
        for i in range(k + 1):
            B[k * n : (k + 1) * n, i * n : (i + 1) * n] = np.linalg.matrix_power(Phi, k - i)
    Sxx = B @ np.kron(np.eye(T), Q) @ B.T
    Sxx[:, :] += B[:, :n] @ (np.asarray(P0) - Q) @ B[:, :n].T
    Cbig = np.kron(np.eye(T), C)
    Syy = Cbig @ Sxx @ Cbig.T + np.kron(np.eye(T), R)
    flat, times = y.reshape(-1), np.repeat(np.arange(T), p)
    obs = np.isfinite(flat)

    def condition(rows):
        Sxy = Sxx @ Cbig[rows].T
        gain = Sxy @ np.linalg.inv(Syy[np.ix_(rows, rows)])
        m = mean + gain @ (flat[rows] - Cbig[rows] @ mean)
        return m.reshape(T, n), (Sxx - gain @ Sxy.T)

    blocks = lambda S: np.stack([S[k * n : (k + 1) * n, k * n : (k + 1) * n] for k in range(T)])
    filtered_x, filtered_P = [], []
    for k in range(T):
        m, S = condition(obs & (times <= k))
        filtered_x.append(m[k])
        filtered_P.append(blocks(S)[k])
    smoothed_x, S = condition(obs)
    ll = scipy.stats.multivariate_normal(Cbig[obs] @ mean, Syy[np.ix_(obs, obs)]).logpdf(flat[obs])
    return np.array(filtered_x), np.array(filtered_P), smoothed_x, blocks(S), ll


def _missing(y):
    y = y.copy()
    y[[1, 4], 0] = np.nan
    y[2, 1] = np.nan
    y[5, :] = np.nan
    return y


@pytest.mark.parametrize("with_missing", [False, True], ids=["complete", "missing"])
def test_filter_smoother_likelihood_equal_dense_conditioning(with_missing):
    """On a short record (T = 8, n = 3, p = 2, correlated R, an input), with and without missing components (one
    of two, both), the filter's means and covariances, the smoother's, and the summed log-likelihood equal exact
    Gaussian conditioning of the stacked states on the observed components to 1e-10 (1e-12 for the likelihood; the
    parallel forms equal these sequential ones, test_parallel_equals_sequential)."""
    model, u, y, _ = make_problem(20, T=8)
    y = _missing(y) if with_missing else y
    x0, P0 = np.array([0.2, -0.1, 0.3]), 2.0 * model["Q"]
    params = params_of(model, x0=x0, P0=P0)
    fx, fP, sx, sP, ll = dense_posterior(model, x0, P0, u, y)
    inputs = EstimatorInputs(y=jnp.asarray(y), u_prev=jnp.asarray(u))
    filtered, smoothed = smooth(kalman_filter, params, inputs)
    for name, got, want in (("filtered x", filtered.x, fx), ("filtered P", filtered.P, fP),
                            ("smoothed x", smoothed.x, sx), ("smoothed P", smoothed.P, sP)):  # fmt: skip
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12, err_msg=name)
    assert float(jnp.sum(filtered.log_likelihood)) == pytest.approx(ll, rel=1e-12)
    assert float(log_likelihood(kalman_filter, params, inputs)) == pytest.approx(ll, rel=1e-12)


def _dynamax_params(lgssm, model, x0, P0, with_inputs=True):
    m = model["Gamma"].shape[1] if with_inputs else 0
    return lgssm.ParamsLGSSM(
        initial=lgssm.ParamsLGSSMInitial(mean=jnp.asarray(x0), cov=jnp.asarray(P0)),
        dynamics=lgssm.ParamsLGSSMDynamics(weights=jnp.asarray(model["Phi"]), bias=jnp.zeros(3),
                                           input_weights=jnp.asarray(model["Gamma"][:, :m]),
                                           cov=jnp.asarray(model["Q"])),
        emissions=lgssm.ParamsLGSSMEmissions(weights=jnp.asarray(model["C"]), bias=jnp.zeros(2),
                                             input_weights=jnp.zeros((2, m)), cov=jnp.asarray(model["R"])),
    )  # fmt: skip


def test_equals_dynamax_filter_smoother_and_likelihood(monkeypatch):
    """Filtered and smoothed means and covariances and the log marginal likelihood equal dynamax's lgssm_smoother to
    1e-9 relative (T = 40, with an input; dynamax has no missing values). dynamax adds 1e-9 I to every matrix it solves
    with (psd_solve), a regulariser of that size; it is set to 0 here so that the algorithms are compared."""
    lgssm = pytest.importorskip("dynamax.linear_gaussian_ssm")
    inference = pytest.importorskip("dynamax.linear_gaussian_ssm.inference")
    from dynamax.utils.utils import psd_solve

    monkeypatch.setattr(inference, "psd_solve", partial(psd_solve, diagonal_boost=0.0))
    model, u, y, x_prev, P_prev = peer_problem(True)
    Phi, Gamma, Q = model["Phi"], model["Gamma"], model["Q"]
    x0, P0 = Phi @ x_prev + Gamma @ u[0], Phi @ P_prev @ Phi.T + Q
    post = jax.jit(lgssm.lgssm_smoother)(_dynamax_params(lgssm, model, x0, P0), jnp.asarray(y), jnp.asarray(u))
    params = params_of(model, x0=x0, P0=P0)
    inputs = EstimatorInputs(y=jnp.asarray(y), u_prev=jnp.asarray(u))
    filtered, smoothed = smooth(kalman_filter, params, inputs)
    pairs = (
        ("filtered x", filtered.x, post.filtered_means),
        ("filtered P", filtered.P, post.filtered_covariances),
        ("smoothed x", smoothed.x, post.smoothed_means),
        ("smoothed P", smoothed.P, post.smoothed_covariances),
    )
    for name, got, want in pairs:
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12, err_msg=name)
    assert float(jnp.sum(filtered.log_likelihood)) == pytest.approx(float(post.marginal_loglik), rel=1e-9)


@pytest.mark.parametrize("with_missing", [False, True], ids=["complete", "missing"])
def test_equals_cuthbert_with_and_without_missing_values(with_missing):
    """cuthbert's square-root Kalman filter and smoother handle NaN measurement components: filtered and smoothed
    means and covariances and the log normalizing constant equal jaxobs' to 1e-9 relative, with missing components
    (one of two, both) and without. cuthbert's prior is that of x_{-1} (filterpy's convention)."""
    cuthbert = pytest.importorskip("cuthbert")
    model, u, y, x_prev, P_prev = peer_problem(True, seed=21, T=40)
    y = _missing(y) if with_missing else y
    Phi, Gamma, C, Q, R = (jnp.asarray(model[k]) for k in ("Phi", "Gamma", "C", "Q", "R"))
    chol_Q, chol_R = jnp.linalg.cholesky(Q), jnp.linalg.cholesky(R)
    filt = cuthbert.gaussian.kalman.build_filter(
        m0=jnp.asarray(x_prev), chol_P0=jnp.linalg.cholesky(jnp.asarray(P_prev)),
        get_dynamics_params=lambda inp: (Phi, Gamma @ inp[0], chol_Q),
        get_observation_params=lambda inp: (C, jnp.zeros(2), chol_R, inp[1]),
    )  # fmt: skip
    model_inputs = (jnp.asarray(u), jnp.asarray(y))
    states = cuthbert.filter(filt, model_inputs, filt.init_prepare())
    smoother = cuthbert.gaussian.kalman.build_smoother(lambda inp: (Phi, Gamma @ inp[0], chol_Q))
    smoothed_states = cuthbert.smoother(smoother, states, model_inputs)
    gram = lambda F: F @ jnp.swapaxes(F, -1, -2)
    x0, P0 = Phi @ x_prev + Gamma @ u[0], Phi @ P_prev @ Phi.T + Q
    filtered, smoothed = smooth(kalman_filter, params_of(model, x0=x0, P0=P0),
                                EstimatorInputs(y=jnp.asarray(y), u_prev=jnp.asarray(u)))  # fmt: skip
    pairs = (("filtered x", filtered.x, states.mean[1:]), ("filtered P", filtered.P, gram(states.chol_cov[1:])),
             ("smoothed x", smoothed.x, smoothed_states.mean[1:]),
             ("smoothed P", smoothed.P, gram(smoothed_states.chol_cov[1:])))  # fmt: skip
    for name, got, want in pairs:
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12, err_msg=name)
    ll = float(jnp.sum(filtered.log_likelihood))
    assert ll == pytest.approx(float(states.log_normalizing_constant[-1]), rel=1e-9)


def test_equals_filterpy_likelihood_innovation_covariance_and_rts():
    """filterpy (a model without inputs: its RTS smoother has none): per-step log-likelihood and innovation
    covariance S of KalmanFilter.update, and filterpy.kalman.rts_smoother's means and covariances, to 1e-10."""
    filterpy_kalman = pytest.importorskip("filterpy.kalman")
    model, u, y, x_prev, P_prev = peer_problem(False)
    Phi, C, Q, R = (model[k] for k in ("Phi", "C", "Q", "R"))
    kf = filterpy_kalman.KalmanFilter(dim_x=3, dim_z=2)
    kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = x_prev.copy(), P_prev.copy(), Phi, C, Q, R
    lls, Ss, xs, Ps = [], [], [], []
    for y_k in y:
        kf.predict()
        kf.update(y_k)
        lls.append(kf.log_likelihood)
        Ss.append(kf.S.copy())
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    sx, sP, *_ = filterpy_kalman.rts_smoother(np.array(xs), np.array(Ps), [Phi] * len(y), [Q] * len(y))
    params = make_kalman(Phi, C, Q, R, x0=Phi @ x_prev, P0=Phi @ P_prev @ Phi.T + Q)
    filtered, smoothed = smooth(kalman_filter, params, EstimatorInputs(y=jnp.asarray(y)))
    np.testing.assert_allclose(filtered.log_likelihood, lls, rtol=1e-10)
    np.testing.assert_allclose(filtered.S, np.array(Ss), rtol=1e-10)
    np.testing.assert_allclose(smoothed.x, sx, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(smoothed.P, sP, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("T", [40, pytest.param(1000, marks=pytest.mark.slow)])
def test_parallel_equals_sequential(T):
    """With missing components (10 % single components, a run of whole samples): the parallel filter's outputs
    (means, covariances, gains, S, log-likelihoods) and the parallel smoother's equal the sequential ones to 1e-10
    relative to each array's scale; so does the final state of parallel_filter."""
    model, u, y, _ = make_problem(22, T=T)
    y = y.copy()
    rng = np.random.default_rng(22)
    y[rng.random(y.shape) < 0.1] = np.nan
    y[T // 2 : T // 2 + T // 50 + 2] = np.nan
    params = params_of(model, x0=np.ones(3))
    inputs = EstimatorInputs(y=jnp.asarray(y), u_prev=jnp.asarray(u))
    sequential, parallel = smooth(kalman_filter, params, inputs), smooth(kalman_filter, params, inputs, parallel=True)
    for seq, par in zip(sequential, parallel, strict=True):
        for name in seq._fields:
            a, b = np.asarray(getattr(seq, name), float), np.asarray(getattr(par, name), float)
            assert np.max(np.abs(a - b)) <= 1e-10 * max(np.max(np.abs(a)), 1e-300), name
    final = parallel_filter(dataclasses.replace(params, output_covariance=True), inputs)[0]
    np.testing.assert_allclose(final.x, sequential[0].x[-1], rtol=1e-10)
    assert int(final.missing) == int(np.sum(~np.isfinite(y)))


def _gradient_problem():
    """Scales ``(q, r)`` of Q (and P0) and R -> (log-likelihood, squared error of the smoothed means), T = 8 with
    missing components."""
    model, u, y, x_true = make_problem(20, T=8)
    base = params_of(model)
    inputs = EstimatorInputs(y=jnp.asarray(_missing(y)), u_prev=jnp.asarray(u))

    def objectives(q, r, parallel=False):
        params = dataclasses.replace(base, Q=q * base.Q, R=r * base.R, P0=q * base.Q)
        filtered, smoothed = smooth(kalman_filter, params, inputs, parallel=parallel)
        return jnp.sum(filtered.log_likelihood), jnp.sum((smoothed.x - x_true) ** 2)

    return objectives


def test_gradients_through_likelihood_and_smoother():
    """check_grads (reverse mode, order 1) of the log-likelihood and of a loss on the smoothed means with respect to
    scales of Q and R, with missing components; both depend on both scales (the check is not vacuous)."""
    objectives = _gradient_problem()
    check_grads(objectives, (1.3, 0.8), order=1, modes=("rev",))
    for shift in ((1e-3, 0.0), (0.0, 1e-3)):
        plus, minus = objectives(1.3 + shift[0], 0.8 + shift[1]), objectives(1.3 - shift[0], 0.8 - shift[1])
        assert all(abs(float(a - b)) > 1e-8 for a, b in zip(plus, minus, strict=True))


@pytest.mark.slow
def test_parallel_gradients_equal_sequential():
    """The gradients of the same objectives through the parallel filter and smoother equal the sequential ones to
    1e-9 relative."""
    objectives = _gradient_problem()
    g_seq, g_par = (jax.jit(jax.jacrev(partial(objectives, parallel=parallel), (0, 1)))(1.3, 0.8)
                    for parallel in (False, True))  # fmt: skip
    np.testing.assert_allclose(np.array(g_par), np.array(g_seq), rtol=1e-9)


def test_smooth_square_root_filter_and_vmap():
    """smooth works with the square-root filter (same result as the covariance form to 1e-10), under vmap over a
    batch of records (each equal to its own eager call) and under jit."""
    model, u, y, _ = make_problem(20, T=8)
    params = params_of(model)
    inputs = EstimatorInputs(y=jnp.asarray(_missing(y)), u_prev=jnp.asarray(u))
    _, reference = smooth(kalman_filter, params, inputs)
    _, root = smooth(square_root_kalman_filter, square_root_form(params), inputs)
    np.testing.assert_allclose(root.x, reference.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(root.P, reference.P, rtol=1e-10, atol=1e-12)
    ys = jnp.stack([inputs.y, 2.0 * inputs.y])
    batched = jax.jit(jax.vmap(lambda y_: smooth(kalman_filter, params, EstimatorInputs(y_, inputs.u_prev))[1]))(ys)
    for i in range(2):
        one = smooth(kalman_filter, params, EstimatorInputs(ys[i], inputs.u_prev))[1]
        np.testing.assert_allclose(batched.x[i], one.x, rtol=1e-12, atol=1e-13)


def test_entry_points_reject_what_they_cannot_do():
    """ValueError naming the argument: rts_smoother without covariances, a smoother or covariance outputs with a
    fixed gain, parallel=True for another estimator than the Kalman filter, wrong shapes."""
    model, u, y, _ = make_problem(20, T=8)
    params = params_of(model)
    inputs = EstimatorInputs(y=jnp.asarray(y), u_prev=jnp.asarray(u))
    _, out = run(kalman_filter, params, inputs)
    with pytest.raises(ValueError, match=r"^filtered has no covariances"):
        rts_smoother(params.Phi, out)
    steady = params_of(model, steady_state=True)
    with pytest.raises(ValueError, match=r"^params\.output_covariance"):
        smooth(kalman_filter, steady, inputs)
    with pytest.raises(ValueError, match=r"^params has a fixed gain"):
        parallel_filter(steady, inputs)
    with pytest.raises(ValueError, match=r"^parallel=True"):
        smooth(square_root_kalman_filter, square_root_form(params), inputs, parallel=True)
    with pytest.raises(ValueError, match=r"^inputs\.y must have shape \(\*, 2\)"):
        parallel_filter(params, EstimatorInputs(y=jnp.zeros((10, 3))))
    out = smooth(kalman_filter, params, inputs)[0]
    with pytest.raises(ValueError, match=r"^Phi has shape \(2, 2\)"):
        rts_smoother(np.eye(2), out)
    with pytest.raises(ValueError, match=r"^filtered has no samples"):
        rts_smoother(
            params.Phi, out._replace(x=out.x[:0], P=out.P[:0], x_prior=out.x_prior[:0], P_prior=out.P_prior[:0])
        )
    with pytest.raises(ValueError, match=r"^inputs\.y has no samples"):
        parallel_filter(params, EstimatorInputs(y=jnp.zeros((0, 2))))
    observer = LinearObserver(params.Phi, params.Gamma, params.C, np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"^estimator has no log_likelihood output"):
        log_likelihood(linear_observer, observer, inputs)
    with pytest.raises(ValueError, match=r"^params \(LinearObserver\) has no output_covariance"):
        smooth(linear_observer, observer, inputs)


# --------------------------------------------------------------------------------------------
# The Kalman Active Observer: smoothing its augmented model


@pytest.fixture(scope="module")
def aob_record():
    """A recorded closed-loop run of the AOB-2 (Cortesão 2006 §7.2 force plant, eq. 81-82 input disturbance D
    through the step at 8 s, sensor noise of variance R): the AOB's params, its estimator inputs, and D."""
    plant, L = nominal_design(EXAMPLE1)
    T = 300
    aob = active.make_aob(plant, 2, EXAMPLE1.R, q_active=EXAMPLE1.sigma2_active)
    noise = np.sqrt(EXAMPLE1.R) * jax.random.normal(jax.random.PRNGKey(4), (T, 1))
    reference = jnp.full((T,), float(L[0, 0]) * 5.0)
    D = example1_disturbance(jnp.arange(T) * EXAMPLE1.h + 7.5)
    trace = simulate(plant, active_observer_controller, with_feedback(aob, L), reference, disturbance=D, noise=noise)
    u_prev = jnp.concatenate([jnp.zeros((1, 1)), trace.u[:-1]])  # the controller starts from u_{-1} = 0
    return aob, EstimatorInputs(y=trace.y, u_prev=u_prev), np.asarray(D)


def test_aob_smoother_is_the_kalman_smoother_of_its_augmented_model(aob_record):
    """The AOB (no adaptive strategy) is the Kalman filter of its augmented model, so smooth(active_observer) equals
    smooth(kalman_filter) on (Phi, Gamma, C, Q, R, x0, P0) of the AOB, with missing measurements: filtered and
    smoothed moments and per-step log-likelihoods to 1e-10 of each array's scale, the summed one to 1e-12."""
    aob, inputs, _ = aob_record
    y = np.array(inputs.y)
    y[[3, 40, 41, 42, 200]] = np.nan
    inputs = inputs._replace(y=jnp.asarray(y))
    kalman = make_kalman(aob.Phi, aob.C, aob.Q, aob.R, Gamma=aob.Gamma, x0=aob.x0, P0=aob.P0)
    filtered, smoothed = smooth(active_observer, aob, inputs)
    k_filtered, k_smoothed = smooth(kalman_filter, kalman, inputs)
    pairs = (("filtered x", filtered.x, k_filtered.x), ("filtered P", filtered.P, k_filtered.P),
             ("smoothed x", smoothed.x, k_smoothed.x), ("smoothed P", smoothed.P, k_smoothed.P),
             ("log-likelihoods", filtered.log_likelihood, k_filtered.log_likelihood))  # fmt: skip
    for name, got, want in pairs:
        scale = np.max(np.abs(np.asarray(want)))
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * scale, err_msg=name)
    assert float(log_likelihood(active_observer, aob, inputs)) == pytest.approx(
        float(jnp.sum(k_filtered.log_likelihood)), rel=1e-12
    )


def test_aob_smoothed_active_state_reconstructs_the_input_disturbance(aob_record):
    """Offline reconstruction of the input disturbance from the recorded run: the smoothed newest active state
    tracks D with less than half the RMS error of the filtered one at its best lag of up to 15 samples (the filter
    lags the dead time and the step; measured: 0.55 against 1.87); the smoothed variance of d is below the
    filtered one at every sample."""
    aob, inputs, D = aob_record
    filtered, smoothed = smooth(active_observer, aob, inputs)
    d_filtered = np.asarray(active.disturbance(aob, filtered.x))[:, 0]
    d_smoothed = np.asarray(active.disturbance(aob, smoothed.x))[:, 0]
    window = slice(20, -20)  # away from the start-up transient and the end of the record
    rms = lambda e: float(np.sqrt(np.mean(e**2)))
    smoothed_error = rms(d_smoothed[window] - D[window])
    filtered_error = min(rms(np.roll(d_filtered, -lag)[window] - D[window]) for lag in range(16))
    assert smoothed_error < 0.5 * filtered_error, (smoothed_error, filtered_error)
    assert smoothed_error < 0.15 * rms(D[window])
    variance = lambda P: np.asarray(active.disturbance(aob, jnp.diagonal(P, axis1=-2, axis2=-1)))
    assert np.all(variance(smoothed.P) <= variance(filtered.P) * (1 + 1e-12))


def test_aob_likelihood_scores_the_active_state_model(aob_record):
    """On the run with an input disturbance, the record is far more likely under the AOB-2's active-state model than
    under the CKF's (the same plant without active states, Cortesão 2006 §5), which cannot explain the
    disturbance (measured: -241 against -3.6e6): the likelihood compares observer models on data."""
    aob, inputs, _ = aob_record
    plant, _ = nominal_design(EXAMPLE1)
    ckf = active.make_ckf(plant, EXAMPLE1.R)
    ll_aob, ll_ckf = (float(log_likelihood(active_observer, params, inputs)) for params in (aob, ckf))
    assert np.isfinite(ll_aob) and np.isfinite(ll_ckf)
    assert ll_aob > ll_ckf + 100.0, (ll_aob, ll_ckf)


# --------------------------------------------------------------------------------------------
# Nonlinear models: the extended and unscented RTS smoothers and the Gaussian filters' likelihood

NONLINEAR_FILTERS = {  # name -> (estimator, params of a NonlinearModel, dynamax's filter/smoother and its settings)
    "ekf": (jo.extended_kalman_filter, jo.make_ekf, "extended_kalman_smoother", None),
    "ukf": (jo.unscented_kalman_filter, partial(jo.make_ukf, alpha=float(np.sqrt(3.0)), beta=2.0, kappa=1.0),
            "unscented_kalman_smoother", (float(np.sqrt(3.0)), 2.0, 1.0)),
    "cubature": (jo.unscented_kalman_filter, partial(jo.make_ukf, rule="cubature"), "unscented_kalman_smoother",
                 (1.0, 0.0, 0.0)),
}  # fmt: skip


@pytest.mark.parametrize("make_problem", [pendulum, bearings], ids=["pendulum", "bearings"])
@pytest.mark.parametrize("name", list(NONLINEAR_FILTERS))
def test_nonlinear_smoothers_and_likelihoods_equal_dynamax(name, make_problem, monkeypatch):
    """dynamax's extended_kalman_smoother and unscented_kalman_smoother (its default sigma points (sqrt 3, 2, 1) and
    the cubature rule (1, 0, 0)) on the pendulum with a torque input and the bearings-only model
    (tests/_nonlinear_models.py), the same prior and inputs (dynamax's ``inputs[t]`` drives the transition into
    ``t``, our ``u_prev``), its 1e-9 I regularisation removed: the log marginal likelihood and the smoothed means
    and covariances agree to 1e-10 relative (the same algorithms; measured 0 to 3e-16 for the likelihoods, 2e-16
    to 5e-15 for the smoothed moments; with the regularisation left in, up to 1.6e-8 and 8e-7, its size)."""
    nlgssm = pytest.importorskip("dynamax.nonlinear_gaussian_ssm")
    without_dynamax_regularisation(monkeypatch)
    estimator, make, peer, sigma = NONLINEAR_FILTERS[name]
    problem = make_problem()
    params = make(problem.model())
    filtered, smoothed = smooth(estimator, params, problem.inputs())
    inputs = None if problem.u_prev is None else jnp.asarray(problem.u_prev)
    extra = () if sigma is None else (nlgssm.UKFHyperParams(*sigma),)
    post = getattr(nlgssm, peer)(dynamax_params(problem), jnp.asarray(problem.y), *extra, inputs=inputs)
    assert float(log_likelihood(estimator, params, problem.inputs())) == pytest.approx(
        float(post.marginal_loglik), rel=1e-10
    )
    assert relative_error(smoothed.x, post.smoothed_means) < 1e-10
    assert relative_error(smoothed.P, post.smoothed_covariances) < 1e-10
    assert relative_error(filtered.P, post.filtered_covariances) < 1e-10


@pytest.mark.parametrize("name", ["ekf", "ukf"])
def test_nonlinear_smoother_on_a_linear_model_is_the_kalman_smoother(name):
    """On a linear model with missing components (one of two, both, an infinite one) the EKF's and the UKF's
    smoothed moments and per-step log-likelihoods equal the Kalman smoother's and filter's (themselves equal to
    exact Gaussian conditioning, above) to 1e-10 relative; a missing sample contributes exactly 0. The parallel
    smoother over the filters' transitions equals the sequential one."""
    estimator, make, _, _ = NONLINEAR_FILTERS[name]
    problem, A, B, C = linear_problem()
    filtered, smoothed = smooth(estimator, make(problem.model()), problem.inputs())
    kf = make_kalman(A, C, problem.Q, problem.R, Gamma=B, x0=problem.x0, P0=problem.P0)
    k_filtered, k_smoothed = smooth(kalman_filter, kf, problem.inputs())
    for label, got, want in (("smoothed x", smoothed.x, k_smoothed.x), ("smoothed P", smoothed.P, k_smoothed.P),
                             ("log-likelihoods", filtered.log_likelihood, k_filtered.log_likelihood),
                             ("P_prior", filtered.P_prior, k_filtered.P_prior)):  # fmt: skip
        assert relative_error(got, want) < 1e-10, label
    assert float(filtered.log_likelihood[7]) == 0.0  # y[7] is missing
    np.testing.assert_array_equal(filtered.transition[0], np.eye(3))  # no prediction before the first sample
    assert relative_error(filtered.transition[1:], np.broadcast_to(A, (39, 3, 3))) < 1e-10
    parallel = rts_smoother(filtered.transition, filtered, parallel=True)
    assert relative_error(parallel.x, smoothed.x) < 1e-10 and relative_error(parallel.P, smoothed.P) < 1e-10


def test_continuous_discrete_smoother_equals_the_exact_discretisation():
    """Continuous-discrete EKF smoother of ``x' = A x + B u + w`` (spectral density Qc): the transition is the
    sensitivity of the moment equations, ``dPhi/dt = F Phi`` (integrated with them by RK4), so the smoother equals
    the Kalman smoother of the exact discretisation up to the integration error, and the transitions equal
    ``e^{A h}`` (measured with 40 substeps of a 0.1 s sample: 2.3e-10 for the smoothed means, 5.7e-11 for their
    covariances, 2.1e-11 for the log-likelihoods, 1.2e-12 for the transitions; 16 times more with 20 substeps, the
    fourth order of RK4); the same for the cubature filter's sigma-point moment equations."""
    A, B, C = jnp.array([[0.0, 1.0], [-4.0, -0.6]]), jnp.array([[0.0], [1.0]]), jnp.array([[1.0, 0.0]])
    Qc, R, h = jnp.diag(jnp.array([0.01, 0.2])), jnp.array([[0.05]]), 0.1
    rng = np.random.default_rng(3)
    inputs = EstimatorInputs(jnp.asarray(rng.normal(size=(30, 1))), jnp.asarray(rng.normal(size=(30, 1))))
    plant = c2d(ss(A, B, C), h)
    kf = make_kalman(plant.A, C, van_loan(A, Qc, h), R, Gamma=plant.B, x0=[1.0, 0.0], P0=jnp.eye(2))
    k_filtered, k_smoothed = smooth(kalman_filter, kf, inputs)
    model = jo.nonlinear_model(lambda x, u, t: A @ x + B @ u, lambda x: C @ x, Qc, R, x0=[1.0, 0.0], P0=jnp.eye(2),
                               n_inputs=1, dt=h, continuous=True, substeps=40)  # fmt: skip
    for estimator, params in ((jo.extended_kalman_filter, jo.make_ekf(model)),
                              (jo.unscented_kalman_filter, jo.make_ukf(model, rule="cubature"))):  # fmt: skip
        filtered, smoothed = smooth(estimator, params, inputs)
        assert relative_error(filtered.transition[1:], np.broadcast_to(plant.A, (29, 2, 2))) < 1e-9
        assert relative_error(smoothed.x, k_smoothed.x) < 1e-9
        assert relative_error(smoothed.P, k_smoothed.P) < 1e-9
        assert relative_error(filtered.log_likelihood, k_filtered.log_likelihood) < 1e-9


def test_nonlinear_likelihood_and_smoother_under_jit_vmap_and_grad():
    """The EKF's and the UKF's log-likelihood and smoother: eager = jit; vmap over three records = a loop; check_grads
    (forward and reverse) of the log-likelihood and of a loss on the smoothed means with respect to the pendulum's
    gravity (bound in a Partial) and the measurement noise, with missing samples."""
    problem = pendulum(T=10)
    y = problem.y.copy()
    y[[2, 6]] = np.nan
    inputs = EstimatorInputs(jnp.asarray(y), jnp.asarray(problem.u_prev))
    truth = jnp.asarray(problem.x)

    def objectives(g, r, estimator, make):
        f = jax.tree_util.Partial(lambda g, x, u, t: pendulum_f(x, u, t, g), g)
        model = jo.nonlinear_model(f, problem.h, problem.Q, r * jnp.eye(1), x0=problem.x0, P0=problem.P0,
                                   n_inputs=1)  # fmt: skip
        params = make(model)
        _, smoothed = smooth(estimator, params, inputs)
        return log_likelihood(estimator, params, inputs), jnp.sum((smoothed.x - truth) ** 2)

    for name in ("ekf", "ukf"):
        estimator, make = NONLINEAR_FILTERS[name][:2]
        f = partial(objectives, estimator=estimator, make=make)
        eager, compiled = f(9.81, 0.09), jax.jit(f)(9.81, 0.09)
        np.testing.assert_allclose(np.array(compiled), np.array(eager), rtol=1e-12)
        check_grads(jax.jit(f), (9.81, 0.09), order=1, modes=("fwd", "rev"))
        batched = jax.jit(jax.vmap(f))(jnp.array([9.0, 9.81, 10.5]), jnp.array([0.05, 0.09, 0.2]))
        for i, (g, r) in enumerate([(9.0, 0.05), (9.81, 0.09), (10.5, 0.2)]):
            np.testing.assert_allclose([batched[0][i], batched[1][i]], np.array(f(g, r)), rtol=1e-11)


def test_nonlinear_entry_points_reject_what_they_cannot_do():
    """parallel=True is for the Kalman filter; a time-varying Phi must have one transition per sample."""
    problem = pendulum(T=6)
    params = jo.make_ekf(problem.model())
    with pytest.raises(ValueError, match=r"^parallel=True"):
        smooth(jo.extended_kalman_filter, params, problem.inputs(), parallel=True)
    filtered, _ = smooth(jo.extended_kalman_filter, params, problem.inputs())
    with pytest.raises(ValueError, match=r"^Phi must have shape \(6, 2, 2\)"):
        rts_smoother(filtered.transition[1:], filtered)
