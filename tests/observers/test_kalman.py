"""Tests for jaxobs.observers.kalman (classical Kalman filter, Cortesão 2006 eq. 27-29) run through
jaxobs.observers.base.run: a plain NumPy reference filter, filterpy and dynamax on the same data and prior,
steady-state gain, missing (NaN) measurements, transformations (jit, vmap) and gradients.

Prior convention: ``x0, P0`` are the prior of ``x_0``, the state at the first measurement; the first step
updates without predicting."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxobs.kalman_steps import kalman_gain, update_covariance
from jaxobs.matrix_equations import dare
from jaxobs.observers.base import EstimatorInputs, run
from jaxobs.observers.kalman import (
    KalmanParams,
    SquareRootKalmanParams,
    filter_shared_model,
    kalman_filter,
    make_kalman,
    square_root_form,
    square_root_kalman_filter,
    with_steady_state_gain,
)


def reference_filter(Phi, Gamma, C, Q, R, x0, P0, u_prev, y):
    """Plain NumPy Kalman filter (Cortesão 2006 eq. 27-29) from the prior ``(x0, P0)`` of ``x_0``: the first
    step uses the prior as the prediction, every later one predicts x1 = Phi x + Gamma u_{k-1},
    P1 = Phi P Phi' + Q (``u_prev[0]`` is not used); K = P1 C' S^{-1}; Joseph update. A non-finite measurement
    component is left out of the update by using only the observed rows of C and the observed block of R; with
    none observed the update is skipped."""
    n, p = Phi.shape[0], C.shape[0]
    x, P = np.asarray(x0, float), np.asarray(P0, float)
    xs, x1s, innovations, gains = [], [], [], []
    missing = 0
    for k, (u_k, y_k) in enumerate(zip(u_prev, y, strict=True)):
        if k == 0:
            x1, P1 = x, P
        else:
            x1 = Phi @ x + Gamma @ np.atleast_1d(u_k)
            P1 = Phi @ P @ Phi.T + Q
        y_k = np.atleast_1d(y_k)
        obs = np.isfinite(y_k)
        missing += int(np.sum(~obs))
        K_full, innovation = np.zeros((n, p)), np.zeros(p)
        if obs.any():
            Co, Ro = C[obs], R[np.ix_(obs, obs)]
            S = Co @ P1 @ Co.T + Ro
            K = P1 @ Co.T @ np.linalg.inv(S)
            e = y_k[obs] - Co @ x1
            x = x1 + K @ e
            IKC = np.eye(n) - K @ Co
            P = IKC @ P1 @ IKC.T + K @ Ro @ K.T
            K_full[:, obs], innovation[obs] = K, e
        else:
            x, P = x1, P1
        xs.append(x)
        x1s.append(x1)
        innovations.append(innovation)
        gains.append(K_full)
    return np.array(xs), np.array(x1s), np.array(innovations), np.array(gains), P, missing


def make_problem(seed=0, n=3, m=1, p=2, T=60):
    """A random stable plant with correlated measurement noise, and data simulated from it."""
    rng = np.random.default_rng(seed)
    Phi = rng.normal(size=(n, n))
    Phi *= 0.97 / np.max(np.abs(np.linalg.eigvals(Phi)))
    Gamma, C = rng.normal(size=(n, m)), rng.normal(size=(p, n))
    G = rng.normal(size=(n, n)) * 0.3
    Q = G @ G.T + 0.01 * np.eye(n)
    R = np.array([[0.5, 0.2], [0.2, 0.3]])[:p, :p] if p <= 2 else np.eye(p) * 0.4
    model = dict(Phi=Phi, Gamma=Gamma, C=C, Q=Q, R=R)
    u = rng.normal(size=(T, m))
    y, x = simulate(model, u, rng)
    return model, u, y, x


def simulate(model, u, rng):
    """Measurements and states of ``model`` driven by ``u`` (``u[k]`` is ``u_{k-1}``) from a random ``x_{-1}``."""
    Phi, Gamma, C = model["Phi"], model["Gamma"], model["C"]
    Lq, Lr = np.linalg.cholesky(model["Q"]), np.linalg.cholesky(model["R"])
    x = rng.normal(size=Phi.shape[0])
    xs, ys = [], []
    for u_k in u:
        x = Phi @ x + Gamma @ u_k + Lq @ rng.normal(size=x.size)
        xs.append(x)
        ys.append(C @ x + Lr @ rng.normal(size=C.shape[0]))
    return np.array(ys), np.array(xs)


def params_of(model, **kw):
    return make_kalman(model["Phi"], model["C"], model["Q"], model["R"], Gamma=model["Gamma"], **kw)


def inputs_of(u, y):
    return EstimatorInputs(y=jnp.asarray(y), u_prev=jnp.asarray(u))


def reference_of(model, params, u, y):
    return reference_filter(
        model["Phi"], model["Gamma"], model["C"], model["Q"], model["R"],
        np.asarray(params.x0), np.asarray(params.P0), u, y,
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------


def test_run_matches_numpy_reference_eq27_29():
    """run(kalman_filter, ...) equals the NumPy reference filter (eq. 27-29, Joseph form) to 1e-10: estimates,
    a-priori estimates, innovations, gains and the final covariance."""
    model, u, y, _ = make_problem(0)
    x0 = np.array([0.3, -0.2, 0.1])
    params = params_of(model, x0=x0, P0=np.eye(3))
    final, out = run(kalman_filter, params, inputs_of(u, y))
    xs, x1s, innovations, gains, P, missing = reference_of(model, params, u, y)
    np.testing.assert_allclose(out.x_prior[0], x0, rtol=0, atol=0)  # the first step does not predict
    np.testing.assert_allclose(out.x, xs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.x_prior, x1s, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.innovation, innovations, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.gain, gains, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(final.P, P, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(final.x, xs[-1], rtol=1e-10, atol=1e-10)
    assert int(final.missing) == missing == 0


def test_default_prior_is_zero_mean_with_covariance_q():
    """make_kalman defaults: the prior of x_0 is x0 = 0, P0 = Q; the filter's init returns them."""
    model, _, _, _ = make_problem(1)
    params = params_of(model)
    np.testing.assert_array_equal(params.P0, model["Q"])
    np.testing.assert_array_equal(params.x0, np.zeros(3))
    state = kalman_filter.init(params)
    np.testing.assert_array_equal(state.P, model["Q"])
    assert int(state.missing) == 0


def test_steady_state_filter_converges_to_time_varying():
    """The steady-state gain (DARE) variant uses K_ss at every step; the time-varying filter's gain converges to
    K_ss and after a long run both give the same estimates."""
    model, u, y, _ = make_problem(2, T=400)
    inputs = inputs_of(u, y)
    tv = params_of(model)
    ss_params = params_of(model, steady_state=True)
    K_ss = kalman_gain(dare(model["Phi"].T, model["C"].T, model["Q"], model["R"]).X, model["C"], model["R"])
    np.testing.assert_allclose(ss_params.gain, K_ss, rtol=1e-12)
    _, out_tv = run(kalman_filter, tv, inputs)
    _, out_ss = run(kalman_filter, ss_params, inputs)
    np.testing.assert_allclose(out_ss.gain, np.broadcast_to(K_ss, out_ss.gain.shape), rtol=1e-12)
    np.testing.assert_allclose(out_tv.gain[-1], K_ss, rtol=1e-10)
    diff = np.max(np.abs(np.asarray(out_tv.x) - np.asarray(out_ss.x)), axis=1)
    scale = np.max(np.abs(np.asarray(out_tv.x)))
    assert diff[0] > 1e-6 * scale  # they do differ at the start ...
    assert np.max(diff[-50:]) < 1e-10 * scale  # ... and agree after the transient


def test_steady_state_covariance_is_the_dare_posterior():
    """Documented in with_steady_state_gain: 'P is then set to the steady-state a-posteriori covariance' (the
    Joseph update of the DARE a-priori covariance), so the filter state carries that P."""
    model, u, y, _ = make_problem(3, T=5)
    params = with_steady_state_gain(params_of(model))
    P_post, _ = update_covariance(
        dare(model["Phi"].T, model["C"].T, model["Q"], model["R"]).X, jnp.asarray(model["C"]), jnp.asarray(model["R"])
    )
    final, _ = run(kalman_filter, params, inputs_of(u, y))
    np.testing.assert_allclose(final.P, P_post, rtol=1e-10)


# ---------------------------------------------------------------------------------------------
# peers: filterpy and dynamax on the same data and prior


@jax.jit
def run_with_covariances(params, inputs):
    """run(kalman_filter, ...) that also stacks the a-posteriori covariance of every step."""

    def body(state, step_inputs):
        state, out = kalman_filter.step(params, state, step_inputs)
        return state, (out, state.P)

    return jax.lax.scan(body, kalman_filter.init(params), inputs)[1]


def peer_problem(with_inputs, seed=15, T=40):
    """A model with one input (or none: no Gamma), data simulated from it, and the prior ``(x_prev, P_prev)`` of
    ``x_{-1}`` that filterpy starts from (it predicts before every update)."""
    model, u, y, _ = make_problem(seed, T=T)
    rng = np.random.default_rng(seed + 1)
    if not with_inputs:
        model = dict(model, Gamma=np.zeros((3, 1)))
        u = np.zeros_like(u)
        y = simulate(model, u, rng)[0]
    G = rng.normal(size=(3, 3))
    return model, u, y, rng.normal(size=3), G @ G.T + 0.5 * np.eye(3)


@pytest.mark.parametrize("with_inputs", [True, False], ids=["inputs", "no-inputs"])
def test_equals_filterpy_and_dynamax_on_the_same_data_and_prior(with_inputs):
    """The Kalman filter equals filterpy's KalmanFilter (to 1e-10) and dynamax's lgssm_filter (to 1e-8: dynamax adds
    1e-9 I to the innovation covariance it solves with) on the same data: estimates and covariances at every step
    (and filterpy's a-priori estimates, innovations and gains), with one input and, without inputs, as the plain
    filter (no Gamma, EstimatorInputs(y=...) only).

    Priors: filterpy predicts then updates at every step, so it starts from a prior of x_{-1}, (x_prev, P_prev);
    jaxobs and dynamax take the prior of x_0, that prior advanced one step: x0 = Phi x_prev + Gamma u_{-1},
    P0 = Phi P_prev Phi' + Q. dynamax's transition into x_t uses inputs[t], so its inputs are jaxobs' u_prev."""
    filterpy_kalman = pytest.importorskip("filterpy.kalman")
    lgssm = pytest.importorskip("dynamax.linear_gaussian_ssm")
    model, u, y, x_prev, P_prev = peer_problem(with_inputs)
    Phi, Gamma, C, Q, R = (model[k] for k in ("Phi", "Gamma", "C", "Q", "R"))
    x0, P0 = Phi @ x_prev + Gamma @ u[0], Phi @ P_prev @ Phi.T + Q
    if with_inputs:
        params = params_of(model, x0=x0, P0=P0)
        inputs = EstimatorInputs(y=jnp.asarray(y), u_prev=jnp.asarray(u))
    else:
        params = make_kalman(Phi, C, Q, R, x0=x0, P0=P0)
        inputs = EstimatorInputs(y=jnp.asarray(y))
    out, P = run_with_covariances(params, inputs)

    kf = filterpy_kalman.KalmanFilter(dim_x=3, dim_z=2, dim_u=1 if with_inputs else 0)
    kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = x_prev.copy(), P_prev.copy(), Phi, C, Q, R
    kf.B = Gamma if with_inputs else None
    fp = {name: [] for name in ("x", "P", "x_prior", "y", "K")}
    for u_k, y_k in zip(u, y, strict=True):
        kf.predict(u=u_k if with_inputs else None)
        kf.update(y_k)
        for name, values in fp.items():
            values.append(np.array(getattr(kf, name)))
    for name, got in (("x", out.x), ("P", P), ("x_prior", out.x_prior), ("y", out.innovation), ("K", out.gain)):
        np.testing.assert_allclose(got, np.stack(fp[name]), rtol=1e-10, atol=1e-10, err_msg=f"filterpy {name}")

    dx_params = lgssm.ParamsLGSSM(
        initial=lgssm.ParamsLGSSMInitial(mean=jnp.asarray(x0), cov=jnp.asarray(P0)),
        dynamics=lgssm.ParamsLGSSMDynamics(weights=jnp.asarray(Phi), bias=jnp.zeros(3),
                                           input_weights=jnp.asarray(Gamma if with_inputs else np.zeros((3, 0))),
                                           cov=jnp.asarray(Q)),
        emissions=lgssm.ParamsLGSSMEmissions(weights=jnp.asarray(C), bias=jnp.zeros(2),
                                             input_weights=jnp.zeros((2, 1 if with_inputs else 0)),
                                             cov=jnp.asarray(R)),
    )  # fmt: skip
    post = lgssm.lgssm_filter(dx_params, jnp.asarray(y), jnp.asarray(u) if with_inputs else None)
    # dynamax adds 1e-9 I to the innovation covariance before each solve (its psd_solve), so it agrees to ~1e-9
    np.testing.assert_allclose(out.x, post.filtered_means, rtol=1e-8, atol=1e-8, err_msg="dynamax means")
    np.testing.assert_allclose(P, post.filtered_covariances, rtol=1e-8, atol=1e-8, err_msg="dynamax covariances")


def test_plain_filter_without_inputs_takes_y_only():
    """A model without inputs (no Gamma): Gamma has shape (n, 0), run, filter_shared_model and the steady-state
    filter take EstimatorInputs(y=...) only; the estimates equal the NumPy reference with a zero input, and an
    input given to such a model is rejected."""
    model, _, y, _ = make_problem(16, T=30)
    Phi, C, Q, R = (model[k] for k in ("Phi", "C", "Q", "R"))
    x0 = np.array([0.5, -0.3, 0.2])
    params = make_kalman(Phi, C, Q, R, x0=x0, P0=2.0 * Q)
    assert params.Gamma.shape == (3, 0)
    run_y = jax.jit(lambda p, y_: run(kalman_filter, p, EstimatorInputs(y=y_)))
    final, out = run_y(params, jnp.asarray(y))
    reference = lambda y_: reference_filter(Phi, np.zeros((3, 1)), C, Q, R, x0, 2.0 * Q, np.zeros((30, 1)), y_)
    xs, *_, P, _ = reference(y)
    np.testing.assert_allclose(out.x, xs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(final.P, P, rtol=1e-10, atol=1e-12)
    shared_final, shared = jax.jit(filter_shared_model)(params, EstimatorInputs(y=jnp.stack([y, -y])))
    np.testing.assert_allclose(shared.x[0], out.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(shared.x[1], reference(-y)[0], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(shared_final.P[1], P, rtol=1e-10, atol=1e-12)
    ss = make_kalman(Phi, C, Q, R, steady_state=True)
    _, out_ss = run_y(ss, jnp.asarray(y))
    assert out_ss.x.shape == (30, 3) and np.all(np.isfinite(np.asarray(out_ss.x)))
    assert kalman_filter.linear(ss).Gamma.shape == (3, 0)
    with pytest.raises(ValueError, match=r"^inputs\.u_prev\b"):
        run(kalman_filter, params, EstimatorInputs(y=jnp.asarray(y), u_prev=jnp.zeros((30, 1))))


# ---------------------------------------------------------------------------------------------
# missing data


def test_nan_measurements_skip_the_update_single_output():
    """Single output with NaN samples: the result equals a reference that skips those updates (predict only),
    and final_state.missing counts the NaN samples."""
    model, u, y, _ = make_problem(4, p=1, T=50)
    model["R"] = np.array([[0.4]])
    y = y.copy()
    nan_steps = [0, 3, 4, 5, 17, 30, 49]
    y[nan_steps, 0] = np.nan
    params = params_of(model, x0=np.ones(3))
    final, out = run(kalman_filter, params, inputs_of(u, y))
    xs, x1s, innovations, gains, P, missing = reference_of(model, params, u, y)
    assert missing == len(nan_steps) == int(final.missing)
    np.testing.assert_allclose(out.x, xs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.gain, gains, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(final.P, P, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(out.x)[nan_steps], np.asarray(out.x_prior)[nan_steps])
    np.testing.assert_array_equal(np.asarray(out.innovation)[nan_steps], 0.0)


def test_partial_nan_conditions_on_observed_components():
    """Two outputs, correlated R: a NaN component is marginalised exactly, i.e. the update equals conditioning
    on the observed component only (observed row of C, R[obs, obs]); whole-NaN vectors skip the update;
    missing counts NaN components."""
    model, u, y, _ = make_problem(5, p=2, T=40)
    y = y.copy()
    y[[2, 9, 10], 0] = np.nan
    y[[5, 20], 1] = np.nan
    y[[13, 14], :] = np.nan
    params = params_of(model)
    final, out = run(kalman_filter, params, inputs_of(u, y))
    xs, x1s, innovations, gains, P, missing = reference_of(model, params, u, y)
    assert int(final.missing) == missing == 3 + 2 + 4
    np.testing.assert_allclose(out.x, xs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.innovation, innovations, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.gain, gains, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(final.P, P, rtol=1e-10, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(out.x)))


def test_steady_state_gain_with_missing_component():
    """Fixed gain with NaN: documented behaviour: the innovation of the missing component is zeroed, the estimate
    stays finite and the component is counted."""
    model, u, y, _ = make_problem(7, p=2, T=20)
    y = y.copy()
    y[4, 1] = np.nan
    y[8, :] = np.nan
    params = params_of(model, steady_state=True)
    final, out = run(kalman_filter, params, inputs_of(u, y))
    assert int(final.missing) == 3
    innov = np.asarray(out.innovation)
    assert innov[4, 1] == 0.0 and np.all(innov[8] == 0.0)
    np.testing.assert_array_equal(np.asarray(out.x)[8], np.asarray(out.x_prior)[8])
    x_prior, K = np.asarray(out.x_prior)[4], np.asarray(params.gain)
    np.testing.assert_allclose(out.x[4], x_prior + K[:, 0] * (y[4, 0] - model["C"][0] @ x_prior), rtol=1e-12)
    assert np.all(np.isfinite(np.asarray(out.x)))


# ---------------------------------------------------------------------------------------------
# one model, a batch of sequences


def _shared_model_batch(seed, p=2, T=40, batch=3):
    """One model and ``batch`` input and measurement sequences simulated from it: ``(model, U, Y)`` with U, Y of
    shapes (batch, T, m) and (batch, T, p)."""
    model, u, y, _ = make_problem(seed, p=p, T=T)
    rng = np.random.default_rng(seed + 1)
    U, Y = [u], [y]
    for _ in range(batch - 1):
        U.append(rng.normal(size=u.shape))
        Y.append(simulate(model, U[-1], rng)[0])
    return model, np.stack(U), np.stack(Y)


def test_filter_shared_model_equals_vmapped_run():
    """filter_shared_model (one Riccati recursion for the batch) returns what vmap(run(kalman_filter)) returns on the
    same data: estimates, a-priori estimates, innovations, gains, S, log-likelihoods, final estimates, covariances
    and counts (neither outputs the per-step covariances P, P_prior by default)."""
    model, U, Y = _shared_model_batch(13)
    params = params_of(model, x0=np.array([0.2, -0.1, 0.4]))
    inputs = inputs_of(U, Y)
    shared_final, shared = jax.jit(filter_shared_model)(params, inputs)
    final, out = jax.jit(jax.vmap(lambda i: run(kalman_filter, params, i)))(inputs)
    for got, want in ((shared, out), (shared_final, final)):
        for name, a, b in zip(got._fields, got, want, strict=True):
            if name in ("P", "P_prior") and got is shared:
                assert a is None and b is None, name
                continue
            assert a.shape == b.shape, name
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12, err_msg=name)


def test_filter_shared_model_missing_data_keeps_the_schedule():
    """Documented: the gain schedule assumes every measurement present, so a non-finite component has its innovation
    zeroed, the other components use the scheduled gain K_k, and it is counted in state.missing; the exact (per
    sequence) treatment is vmap(run) and differs."""
    model, U, Y = _shared_model_batch(14, T=30, batch=2)
    Y = Y.copy()
    Y[0, [4, 11], 1] = np.nan
    Y[1, 7, :] = np.nan
    params = params_of(model)
    inputs = inputs_of(U, Y)
    final, out = filter_shared_model(params, inputs)
    np.testing.assert_array_equal(final.missing, [2, 2])
    # NumPy: the covariance recursion of eq. 27-29 without missing data, then x = x1 + K_k (y - C x1) masked
    # (no prediction at the first step: the prior of x_0 is the first a-priori estimate)
    P, gains = np.asarray(params.P0), []
    for k in range(Y.shape[1]):
        P1 = P if k == 0 else model["Phi"] @ P @ model["Phi"].T + model["Q"]
        K = P1 @ model["C"].T @ np.linalg.inv(model["C"] @ P1 @ model["C"].T + model["R"])
        IKC = np.eye(3) - K @ model["C"]
        P = IKC @ P1 @ IKC.T + K @ model["R"] @ K.T
        gains.append(K)
    for b in range(Y.shape[0]):
        x = np.asarray(params.x0)
        for k, K in enumerate(gains):
            x1 = x if k == 0 else model["Phi"] @ x + model["Gamma"] @ U[b, k]
            innovation = np.where(np.isfinite(Y[b, k]), Y[b, k] - model["C"] @ x1, 0.0)
            x = x1 + K @ innovation
            np.testing.assert_allclose(out.x[b, k], x, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(out.innovation[b, k], innovation, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(out.gain[b, k], K, rtol=1e-10, atol=1e-12)
    _, exact = jax.vmap(lambda i: run(kalman_filter, params, i))(inputs)
    assert np.max(np.abs(np.asarray(exact.x[0, 4:]) - np.asarray(out.x[0, 4:]))) > 1e-6


# ---------------------------------------------------------------------------------------------
# transformations and gradients


@pytest.mark.slow
def test_run_eager_jit_vmap_agree():
    """Transformation test: eager run = jit(run) = vmap over batched params (vs a Python loop), and vmap over
    batched inputs."""
    model, u, y, _ = make_problem(8, T=30)
    y = y.copy()
    y[7, 0] = np.nan
    inputs = inputs_of(u, y)
    scales, x0s = (0.5, 1.0, 3.0), np.random.default_rng(9).normal(size=(3, 3))
    params = [params_of(dict(model, Q=s * model["Q"]), x0=x0) for s, x0 in zip(scales, x0s, strict=True)]
    batched = jax.tree.map(lambda *xs: jnp.stack(xs), *params)
    run_jit = jax.jit(lambda p, i: run(kalman_filter, p, i))
    v_params = jax.jit(jax.vmap(lambda p: run(kalman_filter, p, inputs)))(batched)
    for i, p in enumerate(params):
        eager = run(kalman_filter, p, inputs)
        for got in (run_jit(p, inputs), jax.tree.map(lambda a, i=i: a[i], v_params)):
            for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(eager), strict=True):
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-13)
    ys = jnp.stack([inputs.y, 2.0 * inputs.y])
    v_inputs = jax.vmap(lambda y_: run_jit(params[0], EstimatorInputs(y=y_, u_prev=inputs.u_prev)))(ys)
    for i in range(2):
        eager = run(kalman_filter, params[0], EstimatorInputs(y=ys[i], u_prev=inputs.u_prev))
        for a, b in zip(jax.tree.leaves(v_inputs), jax.tree.leaves(eager), strict=True):
            np.testing.assert_allclose(a[i], b, rtol=1e-12, atol=1e-13)


def test_grad_of_estimation_error_wrt_noise_scales():
    """check_grads (rev, order 1) of the summed squared estimation error through run (T = 20) w.r.t. a Q scale and
    an R scale; the gradient is nonzero."""
    model, u, y, x_true = make_problem(10, T=20)
    inputs = inputs_of(u, y)
    base = params_of(model)

    @jax.jit
    def loss(q, r):
        params = dataclasses.replace(base, Q=q * base.Q, R=r * base.R, P0=q * base.Q)
        _, out = run(kalman_filter, params, inputs)
        return jnp.sum((out.x - x_true) ** 2)

    check_grads(loss, (1.3, 0.8), order=1, modes=("rev",))
    g = jax.grad(loss, argnums=(0, 1))(1.3, 0.8)
    assert all(abs(float(gi)) > 1e-8 for gi in g)


def test_grad_with_missing_measurements_is_finite_and_correct():
    """NaN measurements do not leak into gradients: with missing components the loss gradient w.r.t. the Q scale
    is finite and passes check_grads (rev, order 1)."""
    model, u, y, x_true = make_problem(12, T=20)
    y = y.copy()
    y[[3, 11], 0] = np.nan
    y[15, :] = np.nan
    inputs = inputs_of(u, y)
    base = params_of(model)

    @jax.jit
    def loss(q):
        _, out = run(kalman_filter, dataclasses.replace(base, Q=q * base.Q), inputs)
        return jnp.sum((out.x - x_true) ** 2)

    g = jax.grad(loss)(1.1)
    assert np.isfinite(float(g)) and abs(float(g)) > 1e-8
    check_grads(loss, (1.1,), order=1, modes=("rev",))


def test_make_kalman_rejects_bad_input():
    """Eager validation in make_kalman: ValueError naming the argument."""
    model, _, _, _ = make_problem(11)
    with pytest.raises(ValueError, match=r"^Q\b.*positive semidefinite"):
        make_kalman(model["Phi"], model["C"], -model["Q"], model["R"], Gamma=model["Gamma"])
    with pytest.raises(ValueError, match=r"^R\b.*positive definite"):
        make_kalman(model["Phi"], model["C"], model["Q"], np.zeros((2, 2)), Gamma=model["Gamma"])
    with pytest.raises(ValueError, match=r"^P0\b.*\(3, 2\)"):
        make_kalman(model["Phi"], model["C"], model["Q"], model["R"], Gamma=model["Gamma"], P0=np.ones((3, 2)))
    with pytest.raises(ValueError, match=r"^Gamma\b.*\(4, 1\)"):
        make_kalman(model["Phi"], model["C"], model["Q"], model["R"], Gamma=np.ones((4, 1)))
    with pytest.raises(ValueError, match=r"^C\b.*\(2, 4\)"):
        make_kalman(model["Phi"], np.ones((2, 4)), model["Q"], model["R"], Gamma=model["Gamma"])
    with pytest.raises(ValueError, match=r"^Phi\b.*\(3, 2\)"):
        make_kalman(np.ones((3, 2)), model["C"], model["Q"], model["R"], Gamma=model["Gamma"])
    with pytest.raises(ValueError, match="joseph must be a bool"):
        params_of(model, joseph="no")
    assert isinstance(params_of(model), KalmanParams)


def test_standard_form_filter_equals_the_joseph_filter_under_jit_and_grad():
    """The default, ``joseph=False``, runs the same filter as ``joseph=True`` (means, innovation covariances,
    log-likelihood to 1e-10), and under jit its log-likelihood gradient in a Q scale equals the Joseph filter's (a
    static flag: the transformations are those of the default filter, tested above)."""
    model, u, y, _ = make_problem(12, T=25)
    inputs = inputs_of(u, y)
    fields = ("Phi", "Gamma", "C", "Q", "R", "x0", "P0")
    assert params_of(model).joseph is False and KalmanParams(*(model.get(k, 0) for k in fields)).joseph is False

    def log_likelihood(q, joseph):
        params = params_of(dict(model, Q=q * model["Q"]), joseph=joseph)
        return jnp.sum(run(kalman_filter, params, inputs)[1].log_likelihood)

    joseph, standard = (run(kalman_filter, params_of(model, joseph=j), inputs)[1] for j in (True, False))
    for name in ("x", "S", "log_likelihood"):
        np.testing.assert_allclose(getattr(standard, name), getattr(joseph, name), rtol=1e-10, atol=1e-12)
    grads = {j: jax.jit(jax.grad(log_likelihood), static_argnums=1)(1.3, j) for j in (True, False)}
    np.testing.assert_allclose(grads[False], grads[True], rtol=1e-8)


def test_square_root_filter_gradients_finite_with_singular_covariances():
    """The square-root filter's log-likelihood with an exactly known initial state (P0_sqrt = 0) and a rank-1
    process noise (Q_sqrt = g, (3, 1)): the covariances are singular for the first steps, the gradient with respect
    to g and R_sqrt is finite and equals the covariance form's (Q = g g', R = R_sqrt R_sqrt'; its gradients pass
    check_grads above) to 1e-8."""
    model, u, y, _ = make_problem(30, T=12)
    g0, R_sqrt0 = np.array([[0.3], [-0.2], [0.5]]), np.linalg.cholesky(model["R"])
    inputs = inputs_of(u, y)

    def root_ll(g, R_sqrt):
        params = SquareRootKalmanParams(*(jnp.asarray(model[k]) for k in ("Phi", "Gamma", "C")), g, R_sqrt,
                                        jnp.zeros(3), jnp.zeros((3, 3)))  # fmt: skip
        return jnp.sum(run(square_root_kalman_filter, params, inputs)[1].log_likelihood)

    def covariance_ll(g, R_sqrt):
        params = dataclasses.replace(params_of(model, P0=np.zeros((3, 3))), Q=g @ g.T, R=R_sqrt @ R_sqrt.T)
        return jnp.sum(run(kalman_filter, params, inputs)[1].log_likelihood)

    root_grad = jax.grad(root_ll, (0, 1))(g0, R_sqrt0)
    assert all(np.all(np.isfinite(g)) and np.any(g != 0) for g in root_grad)
    for got, want in zip(root_grad, jax.grad(covariance_ll, (0, 1))(g0, R_sqrt0), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10)


def test_square_root_form_gradient_at_repeated_eigenvalues_equals_the_filters_issue46():
    """Q = q I (and R, P0 scalar multiples of I: every eigenvalue repeated): the gradient in q of a loss through
    square_root_form equals that through kalman_filter to 1e-8 (the factor's derivative is Cholesky's, not an
    eigendecomposition's, whose derivative divides by the zero gaps and gave NaN), eagerly, under jit and vmap."""
    Phi, C = np.array([[1.0, 0.1], [0.0, 0.9]]), np.array([[1.0, 0.0]])
    inputs = EstimatorInputs(y=np.sin(0.3 * np.arange(40))[:, None])

    def loss(q, square_root):
        params = make_kalman(Phi, C, q * jnp.eye(2), [[0.5]])
        if square_root:
            out = run(square_root_kalman_filter, square_root_form(params), inputs)[1]
        else:
            out = run(kalman_filter, params, inputs)[1]
        return jnp.sum(out.x**2) - jnp.sum(out.log_likelihood)

    want = jax.grad(loss)(0.01, False)
    assert np.isfinite(want)
    np.testing.assert_allclose(jax.grad(loss)(0.01, True), want, rtol=1e-8)
    np.testing.assert_allclose(jax.jit(jax.grad(loss), static_argnums=1)(0.01, True), want, rtol=1e-8)
    qs = jnp.array([0.01, 0.03])
    np.testing.assert_allclose(jax.vmap(jax.grad(loss), (0, None))(qs, True),
                               jax.vmap(jax.grad(loss), (0, None))(qs, False), rtol=1e-8)  # fmt: skip


@pytest.mark.slow
def test_float32_square_root_form_drifts_less_than_covariance_form():
    """The AOB-2 of Cortesão 2006 Example 1 (9 states, q_plant = 1e-12: a nearly singular covariance) as the Kalman
    filter of its augmented model over 5000 float32 samples: both forms stay finite, and the square-root form's
    largest error of the estimate against the float64 run is under half the covariance form's (measured with
    benchmarks/parallel_in_time.py over 20000 samples: 1.3e-5 against 4.6e-5 relative)."""
    from jaxobs.observers import active
    from jaxobs.papers.cortesao.force_control import EXAMPLE1, nominal_design

    aob = active.make_aob(nominal_design(EXAMPLE1)[0], 2, EXAMPLE1.R, q_active=EXAMPLE1.sigma2_active)
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    y, u_prev = jnp.cumsum(jax.random.normal(k1, (5000, 1)), axis=0) * 0.1, jax.random.normal(k2, (5000, 1))

    def estimates(estimator, form, dtype):
        params = make_kalman(*(jnp.asarray(M, dtype) for M in (aob.Phi, aob.C, aob.Q, aob.R)),
                             Gamma=jnp.asarray(aob.Gamma, dtype), P0=jnp.asarray(aob.P0, dtype))  # fmt: skip
        inputs = EstimatorInputs(y=y.astype(dtype), u_prev=u_prev.astype(dtype))
        return np.asarray(jax.jit(run, static_argnums=0)(estimator, form(params), inputs)[1].x, np.float64)

    reference = estimates(kalman_filter, lambda p: p, jnp.float64)
    errors = {}
    for name, estimator, form in (("covariance", kalman_filter, lambda p: p),
                                  ("square root", square_root_kalman_filter, square_root_form)):  # fmt: skip
        x = estimates(estimator, form, jnp.float32)
        assert np.all(np.isfinite(x)), name
        errors[name] = np.max(np.abs(x - reference)) / np.max(np.abs(reference))
    assert errors["square root"] < 0.5 * errors["covariance"], errors
