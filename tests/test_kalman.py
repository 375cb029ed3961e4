"""Tests for jaxobs.observers.kalman (classical Kalman filter, seed 000 eq. 27-29) run through
jaxobs.observers.base.run: a plain NumPy reference filter, steady-state gain, missing (NaN) measurements,
transformations (jit, vmap) and gradients."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxobs.observers.base import run
from jaxobs.observers.kalman import (
    KalmanInputs,
    KalmanParams,
    filter_shared_model,
    kalman_filter,
    make_kalman,
    measurement_update,
    with_steady_state_gain,
)
from jaxobs.riccati import dare, kalman_gain, update_covariance


def reference_filter(Phi, Gamma, C, Q, R, x0, P0, u_prev, y):
    """Plain NumPy Kalman filter (seed 000 eq. 27-29): predict x1 = Phi x + Gamma u, P1 = Phi P Phi' + Q;
    K = P1 C' S^{-1}; Joseph update. A non-finite measurement component is left out of the update by using
    only the observed rows of C and the observed block of R; with none observed the update is skipped."""
    n, p = Phi.shape[0], C.shape[0]
    x, P = np.asarray(x0, float), np.asarray(P0, float)
    xs, x1s, innovations, gains = [], [], [], []
    missing = 0
    for u_k, y_k in zip(u_prev, y, strict=True):
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
    """Measurements and states of ``model`` driven by ``u`` from a random initial state."""
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
    return make_kalman(model["Phi"], model["Gamma"], model["C"], model["Q"], model["R"], **kw)


def reference_of(model, params, u, y):
    return reference_filter(
        model["Phi"], model["Gamma"], model["C"], model["Q"], model["R"],
        np.asarray(params.x0), np.asarray(params.P0), u, y,
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------


def test_run_matches_numpy_reference_seed000_eq27_29():
    """run(kalman_filter, ...) equals the NumPy reference filter (eq. 27-29, Joseph form) to 1e-10: estimates,
    a-priori estimates, innovations, gains and the final covariance."""
    model, u, y, _ = make_problem(0)
    x0 = np.array([0.3, -0.2, 0.1])
    params = params_of(model, x0=x0, P0=np.eye(3))
    final, out = run(kalman_filter, params, KalmanInputs(jnp.asarray(u), jnp.asarray(y)))
    xs, x1s, innovations, gains, P, missing = reference_of(model, params, u, y)
    np.testing.assert_allclose(out.x, xs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.x_prior, x1s, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.innovation, innovations, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.gain, gains, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(final.P, P, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(final.x, xs[-1], rtol=1e-10, atol=1e-10)
    assert int(final.missing) == missing == 0


def test_default_initialisation_p0_is_q0_seed000_sec7_2():
    """make_kalman defaults: P_{-1} = Q_0 (seed 000 §7.2) and x0 = 0; the filter's init returns them."""
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
    inputs = KalmanInputs(jnp.asarray(u), jnp.asarray(y))
    tv = params_of(model)
    ss_params = params_of(model, steady_state=True)
    K_ss = kalman_gain(dare(model["Phi"], model["C"], model["Q"], model["R"]).P, model["C"], model["R"])
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
        dare(model["Phi"], model["C"], model["Q"], model["R"]).P, jnp.asarray(model["C"]), jnp.asarray(model["R"])
    )
    final, _ = run(kalman_filter, params, KalmanInputs(jnp.asarray(u), jnp.asarray(y)))
    np.testing.assert_allclose(final.P, P_post, rtol=1e-10)


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
    final, out = run(kalman_filter, params, KalmanInputs(jnp.asarray(u), jnp.asarray(y)))
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
    final, out = run(kalman_filter, params, KalmanInputs(jnp.asarray(u), jnp.asarray(y)))
    xs, x1s, innovations, gains, P, missing = reference_of(model, params, u, y)
    assert int(final.missing) == missing == 3 + 2 + 4
    np.testing.assert_allclose(out.x, xs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.innovation, innovations, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.gain, gains, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(final.P, P, rtol=1e-10, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(out.x)))


def test_measurement_update_one_missing_component_is_exact_conditioning():
    """Single update, 2 outputs, non-diagonal R, second component NaN: x and P equal the Gaussian conditioning
    on the first component alone (row C[0], variance R[0, 0]); the reported gain has a zero column."""
    rng = np.random.default_rng(6)
    G = rng.normal(size=(3, 3))
    P1 = G @ G.T + 0.1 * np.eye(3)
    C = rng.normal(size=(2, 3))
    R = np.array([[0.5, 0.4], [0.4, 0.6]])
    x1 = rng.normal(size=3)
    y = np.array([0.7, np.nan])
    x, P, K, innovation, n_missing = measurement_update(x1, P1, C, R, y)
    c, r = C[0:1], R[0:1, 0:1]
    k = P1 @ c.T / (c @ P1 @ c.T + r)
    np.testing.assert_allclose(x, x1 + k[:, 0] * (0.7 - c @ x1), rtol=1e-12)
    np.testing.assert_allclose(P, P1 - k @ c @ P1, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(K[:, 0], k[:, 0], rtol=1e-12)
    np.testing.assert_array_equal(K[:, 1], 0.0)
    np.testing.assert_allclose(innovation, [0.7 - (c @ x1)[0], 0.0], rtol=1e-12)
    assert int(n_missing) == 1
    # the full (non-missing) update differs: the correlation with the second component matters
    x_full, *_ = measurement_update(x1, P1, C, R, np.array([0.7, 0.1]))
    assert np.max(np.abs(np.asarray(x_full) - np.asarray(x))) > 1e-3


def test_steady_state_gain_with_missing_component():
    """Fixed gain with NaN: documented behaviour: the innovation of the missing component is zeroed, the estimate
    stays finite and the component is counted."""
    model, u, y, _ = make_problem(7, p=2, T=20)
    y = y.copy()
    y[4, 1] = np.nan
    y[8, :] = np.nan
    params = params_of(model, steady_state=True)
    final, out = run(kalman_filter, params, KalmanInputs(jnp.asarray(u), jnp.asarray(y)))
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
    same data: estimates, a-priori estimates, innovations, gains, final estimates, covariances and counts."""
    model, U, Y = _shared_model_batch(13)
    params = params_of(model, x0=np.array([0.2, -0.1, 0.4]))
    inputs = KalmanInputs(jnp.asarray(U), jnp.asarray(Y))
    shared_final, shared = jax.jit(filter_shared_model)(params, inputs)
    final, out = jax.jit(jax.vmap(lambda i: run(kalman_filter, params, i)))(inputs)
    for got, want in ((shared, out), (shared_final, final)):
        for name, a, b in zip(got._fields, got, want, strict=True):
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
    inputs = KalmanInputs(jnp.asarray(U), jnp.asarray(Y))
    final, out = filter_shared_model(params, inputs)
    np.testing.assert_array_equal(final.missing, [2, 2])
    # NumPy: the covariance recursion of eq. 27-29 without missing data, then x = x1 + K_k (y - C x1) masked
    P, gains = np.asarray(params.P0), []
    for _ in range(Y.shape[1]):
        P1 = model["Phi"] @ P @ model["Phi"].T + model["Q"]
        K = P1 @ model["C"].T @ np.linalg.inv(model["C"] @ P1 @ model["C"].T + model["R"])
        IKC = np.eye(3) - K @ model["C"]
        P = IKC @ P1 @ IKC.T + K @ model["R"] @ K.T
        gains.append(K)
    for b in range(Y.shape[0]):
        x = np.asarray(params.x0)
        for k, K in enumerate(gains):
            x1 = model["Phi"] @ x + model["Gamma"] @ U[b, k]
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
    inputs = KalmanInputs(jnp.asarray(u), jnp.asarray(y))
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
    v_inputs = jax.vmap(lambda y_: run_jit(params[0], KalmanInputs(inputs.u_prev, y_)))(ys)
    for i in range(2):
        eager = run(kalman_filter, params[0], KalmanInputs(inputs.u_prev, ys[i]))
        for a, b in zip(jax.tree.leaves(v_inputs), jax.tree.leaves(eager), strict=True):
            np.testing.assert_allclose(a[i], b, rtol=1e-12, atol=1e-13)


def test_grad_of_estimation_error_wrt_noise_scales():
    """check_grads (rev, order 1) of the summed squared estimation error through run (T = 20) w.r.t. a Q scale and
    an R scale; the gradient is nonzero."""
    model, u, y, x_true = make_problem(10, T=20)
    inputs = KalmanInputs(jnp.asarray(u), jnp.asarray(y))
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
    inputs = KalmanInputs(jnp.asarray(u), jnp.asarray(y))
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
        make_kalman(model["Phi"], model["Gamma"], model["C"], -model["Q"], model["R"])
    with pytest.raises(ValueError, match=r"^R\b.*positive definite"):
        make_kalman(model["Phi"], model["Gamma"], model["C"], model["Q"], np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"^P0\b.*\(3, 2\)"):
        make_kalman(model["Phi"], model["Gamma"], model["C"], model["Q"], model["R"], P0=np.ones((3, 2)))
    with pytest.raises(ValueError, match=r"^Gamma\b.*\(4, 1\)"):
        make_kalman(model["Phi"], np.ones((4, 1)), model["C"], model["Q"], model["R"])
    with pytest.raises(ValueError, match=r"^C\b.*\(2, 4\)"):
        make_kalman(model["Phi"], model["Gamma"], np.ones((2, 4)), model["Q"], model["R"])
    with pytest.raises(ValueError, match=r"^Phi\b.*\(3, 2\)"):
        make_kalman(np.ones((3, 2)), model["Gamma"], model["C"], model["Q"], model["R"])
    assert isinstance(params_of(model), KalmanParams)
