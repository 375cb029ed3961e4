"""Time-varying linear-Gaussian models (``Phi_k``, ``Gamma_k``, ``C_k``, ``Q_k``, ``R_k`` per step) through the
Kalman filter, its square-root and parallel forms, the smoother and the likelihood: against a plain NumPy loop,
given in the inputs or by a schedule of the step index, equal to today's results for a constant model, under
jit, vmap (over plants) and grad, and the errors."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxobs as jo
from jaxobs.observers import EstimatorInputs, run
from jaxobs.observers.kalman import (
    SquareRootKalmanParams,
    kalman_filter,
    make_kalman,
    square_root_form,
    square_root_kalman_filter,
    step_model,
)
from jaxobs.smoothing import log_likelihood, parallel_filter, smooth

T, N, M, P = 25, 3, 1, 2


def time_varying_problem(seed=0, missing=True):
    """Per-step matrices of a random model (``Phi_k`` a rotation-and-decay varying with k, every other matrix
    perturbed per step), data simulated from it, and NaN in a few measurement components."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(N, N))
    base *= 0.9 / np.max(np.abs(np.linalg.eigvals(base)))
    Phi = np.stack([base + 0.1 * np.sin(0.3 * k) * np.eye(N) + 0.05 * rng.normal(size=(N, N)) for k in range(T)])
    Gamma = rng.normal(size=(T, N, M))
    C = rng.normal(size=(P, N)) + 0.3 * rng.normal(size=(T, P, N))
    G = 0.3 * rng.normal(size=(T, N, N))
    Q = G @ np.swapaxes(G, 1, 2) + 0.01 * np.eye(N)
    H = 0.3 * rng.normal(size=(T, P, P))
    R = H @ np.swapaxes(H, 1, 2) + 0.2 * np.eye(P)
    model = dict(Phi=Phi, Gamma=Gamma, C=C, Q=Q, R=R)
    u = rng.normal(size=(T, M))
    x = rng.normal(size=N)
    y = np.zeros((T, P))
    for k in range(T):
        if k:
            x = Phi[k] @ x + Gamma[k] @ u[k] + np.linalg.cholesky(Q[k]) @ rng.normal(size=N)
        y[k] = C[k] @ x + np.linalg.cholesky(R[k]) @ rng.normal(size=P)
    if missing:
        y[4, 0] = y[11, :] = y[17, 1] = np.nan
    return model, u, y, np.zeros(N), np.eye(N)


def numpy_filter_and_smoother(model, u, y, x0, P0):
    """The Kalman filter, its log-likelihood and the RTS smoother as a plain NumPy loop with the matrices of each
    step (missing components dropped from the update): filtered means and covariances, per-step
    log-likelihoods, smoothed means and covariances."""
    Phi, Gamma, C, Q, R = (model[k] for k in ("Phi", "Gamma", "C", "Q", "R"))
    x, Pk = x0.astype(float), P0.astype(float)
    xs, Ps, priors, ll = [], [], [], []
    for k in range(T):
        if k:
            x, Pk = Phi[k] @ x + Gamma[k] @ u[k], Phi[k] @ Pk @ Phi[k].T + Q[k]
        priors.append((x, Pk))
        obs = np.isfinite(y[k])
        Co, Ro = C[k][obs], R[k][np.ix_(obs, obs)]
        S = Co @ Pk @ Co.T + Ro
        e = y[k][obs] - Co @ x
        K = Pk @ Co.T @ np.linalg.inv(S)
        ll.append(-0.5 * (obs.sum() * np.log(2 * np.pi) + np.linalg.slogdet(S)[1] + e @ np.linalg.solve(S, e)))
        x, Pk = x + K @ e, Pk - K @ S @ K.T
        xs.append(x)
        Ps.append(Pk)
    xs_s, Ps_s = [xs[-1]], [Ps[-1]]
    for k in range(T - 2, -1, -1):
        x_prior, P_prior = priors[k + 1]
        E = Ps[k] @ Phi[k + 1].T @ np.linalg.inv(P_prior)
        xs_s.insert(0, xs[k] + E @ (xs_s[0] - x_prior))
        Ps_s.insert(0, Ps[k] + E @ (Ps_s[0] - P_prior) @ E.T)
    return np.array(xs), np.array(Ps), np.array(ll), np.array(xs_s), np.array(Ps_s)


def constant_params(model, x0, P0, **kw):
    """Params whose constant fields are the first step's (the shapes and the fields a step does not replace)."""
    return make_kalman(model["Phi"][0], model["C"][0], model["Q"][0], model["R"][0], Gamma=model["Gamma"][0],
                       x0=x0, P0=P0, **kw)  # fmt: skip


def per_step(model):
    return {k: jnp.asarray(v) for k, v in model.items()}


def test_filter_smoother_likelihood_parallel_and_square_root_equal_a_numpy_loop():
    """Per-step matrices in the inputs: the filter (both covariance forms), the square-root filter (per-step
    factors), the parallel filter, the log-likelihood (sequential and parallel) and the smoother (sequential and
    parallel) equal the NumPy loop to 1e-8 relative (measured about 1e-13)."""
    model, u, y, x0, P0 = time_varying_problem()
    xs, Ps, ll, xs_s, Ps_s = numpy_filter_and_smoother(model, u, y, x0, P0)
    inputs = EstimatorInputs(jnp.asarray(y), jnp.asarray(u), per_step(model))
    scale = lambda ref: np.max(np.abs(ref))  # noqa: E731
    for joseph in (False, True):
        params = dataclasses.replace(constant_params(model, x0, P0, joseph=joseph), output_covariance=True)
        for name, out in [("filter", run(kalman_filter, params, inputs)[1]),
                          ("parallel", parallel_filter(params, inputs)[1])]:  # fmt: skip
            assert np.max(np.abs(out.x - xs)) < 1e-8 * scale(xs), (name, joseph)
            assert np.max(np.abs(out.P - Ps)) < 1e-8 * scale(Ps), (name, joseph)
            np.testing.assert_allclose(out.log_likelihood, ll, rtol=1e-8, err_msg=name)
        for parallel in (False, True):
            np.testing.assert_allclose(log_likelihood(kalman_filter, params, inputs, parallel=parallel), ll.sum(),
                                       rtol=1e-10)  # fmt: skip
            _, smoothed = smooth(kalman_filter, params, inputs, parallel=parallel)
            assert np.max(np.abs(smoothed.x - xs_s)) < 1e-8 * scale(xs_s), parallel
            assert np.max(np.abs(smoothed.P - Ps_s)) < 1e-8 * scale(Ps_s), parallel
    factors = {"Q_sqrt": jnp.linalg.cholesky(model["Q"]), "R_sqrt": jnp.linalg.cholesky(model["R"])}
    sqrt_params = square_root_form(constant_params(model, x0, P0))
    sqrt_model = {**{k: per_step(model)[k] for k in ("Phi", "Gamma", "C")}, **factors}
    _, out = run(square_root_kalman_filter, sqrt_params, inputs._replace(model=sqrt_model))
    assert np.max(np.abs(out.x - xs)) < 1e-8 * scale(xs)
    np.testing.assert_allclose(out.log_likelihood, ll, rtol=1e-8)
    _, smoothed = smooth(square_root_kalman_filter, sqrt_params, inputs._replace(model=sqrt_model))
    assert np.max(np.abs(smoothed.x - xs_s)) < 1e-8 * scale(xs_s)


def _schedule(k, Phi0, rate):
    """``Phi_k = Phi0 (1 + rate sin k)`` and ``Q_k = 0.05 (1 + k / 10) I``: a model as a function of the step."""
    return {"Phi": Phi0 * (1.0 + rate * jnp.sin(k)), "Q": 0.05 * (1.0 + k / 10.0) * jnp.eye(Phi0.shape[0])}


def test_schedule_of_the_step_index_equals_the_same_matrices_in_the_inputs():
    """A schedule ``k -> {Phi_k, Q_k}`` with ``model = arange(T)`` equals the same matrices given per step, in the
    filter, the parallel filter and the smoother (to rounding), and the NumPy loop."""
    model, u, y, x0, P0 = time_varying_problem(seed=1)
    Phi0 = jnp.asarray(model["Phi"][0])
    params = constant_params(model, x0, P0, schedule=jax.tree_util.Partial(_schedule, Phi0=Phi0, rate=0.2))
    steps = jnp.arange(T, dtype=float)
    matrices = jax.vmap(lambda k: _schedule(k, Phi0, 0.2))(steps)
    by_schedule = EstimatorInputs(jnp.asarray(y), jnp.asarray(u), steps)
    by_inputs = EstimatorInputs(jnp.asarray(y), jnp.asarray(u), matrices)
    plain = dataclasses.replace(params, schedule=None)
    reference = {**{k: np.broadcast_to(v[0], v.shape) for k, v in model.items()},
                 **{k: np.asarray(v) for k, v in matrices.items()}}  # fmt: skip
    xs, _, ll, xs_s, _ = numpy_filter_and_smoother(reference, u, y, x0, P0)
    _, out = run(kalman_filter, params, by_schedule)
    np.testing.assert_allclose(out.x, run(kalman_filter, plain, by_inputs)[1].x, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(out.x, xs, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(parallel_filter(params, by_schedule)[1].log_likelihood, ll, rtol=1e-9)
    np.testing.assert_allclose(smooth(kalman_filter, params, by_schedule)[1].x, xs_s, rtol=1e-9, atol=1e-10)


def test_constant_model_is_unchanged():
    """A model given per step that is the params' own at every step equals the constant filter to 1e-12 (the
    sequential one and the parallel one), and without ``inputs.model`` the filter runs the same program as
    before (bit for bit)."""
    model, u, y, x0, P0 = time_varying_problem(seed=2)
    params = constant_params(model, x0, P0)
    inputs = EstimatorInputs(jnp.asarray(y), jnp.asarray(u))
    repeated = {k: jnp.broadcast_to(getattr(params, k), (T, *getattr(params, k).shape)) for k in params.model_fields}
    for filt in (lambda i: run(kalman_filter, params, i)[1], lambda i: parallel_filter(params, i)[1]):
        constant, varying = filt(inputs), filt(inputs._replace(model=repeated))
        for name in ("x", "x_prior", "gain", "S", "log_likelihood"):
            np.testing.assert_allclose(getattr(varying, name), getattr(constant, name), rtol=1e-12, atol=1e-14)
    assert step_model(params, None) == {}


def test_jit_vmap_over_plants_and_grad():
    """eager = jit; a vmap over three plants (their schedules' bound rates) equals a loop; the gradient of the
    log-likelihood with respect to the schedule's parameter and to the per-step Q values passes check_grads."""
    model, u, y, x0, P0 = time_varying_problem(seed=3, missing=False)
    Phi0 = jnp.asarray(model["Phi"][0])
    inputs = EstimatorInputs(jnp.asarray(y), jnp.asarray(u), jnp.arange(T, dtype=float))

    def loglik(rate):
        params = constant_params(model, x0, P0, schedule=jax.tree_util.Partial(_schedule, Phi0=Phi0, rate=rate))
        return log_likelihood(kalman_filter, params, inputs)

    np.testing.assert_allclose(jax.jit(loglik)(0.2), loglik(0.2), rtol=1e-13)
    rates = jnp.array([0.0, 0.1, 0.3])
    np.testing.assert_allclose(jax.vmap(loglik)(rates), [loglik(r) for r in rates], rtol=1e-12)
    check_grads(loglik, (0.2,), order=1, modes=("rev",))
    params = constant_params(model, x0, P0)

    def loglik_q(scale):
        per = per_step(model)
        return log_likelihood(kalman_filter, params, EstimatorInputs(inputs.y, inputs.u_prev,
                                                                     {**per, "Q": scale * per["Q"]}))  # fmt: skip

    check_grads(loglik_q, (1.3,), order=1, modes=("fwd", "rev"))


def test_errors_name_the_argument():
    model, u, y, x0, P0 = time_varying_problem(seed=4)
    params = constant_params(model, x0, P0)
    y = jnp.asarray(y)
    with pytest.raises(ValueError, match=r"inputs.model\['Phi'\] must have shape \(3, 3\)"):
        run(kalman_filter, params, EstimatorInputs(y, model={"Phi": jnp.zeros((T, 2, 2))}))
    with pytest.raises(ValueError, match="inputs.model must be a dict of per-step values of"):
        run(kalman_filter, params, EstimatorInputs(y, model={"x0": jnp.zeros((T, 3))}))
    with pytest.raises(ValueError, match="inputs.model is None: params.schedule maps it"):
        run(kalman_filter, dataclasses.replace(params, schedule=jax.tree_util.Partial(lambda k: {})),
            EstimatorInputs(y))  # fmt: skip
    with pytest.raises(ValueError, match="a time-varying model needs the time-varying gain"):
        run(
            kalman_filter,
            jo.make_kalman(model["Phi"][0], model["C"][0], model["Q"][0], model["R"][0], steady_state=True),
            EstimatorInputs(y, model={"Q": jnp.asarray(model["Q"])}),
        )
    with pytest.raises(ValueError, match="has no steady-state gain"):
        constant_params(model, x0, P0, schedule=lambda k: {}, steady_state=True)
    with pytest.raises(ValueError, match=r"inputs.model\['Q'\] must have the leading time axis"):
        parallel_filter(params, EstimatorInputs(y, model={"Q": jnp.asarray(model["Q"])[:5]}))
    with pytest.raises(ValueError, match="params.schedule returns covariances"):
        square_root_form(dataclasses.replace(params, schedule=jax.tree_util.Partial(lambda k: {})))
    sqrt_params = square_root_form(params)
    assert isinstance(sqrt_params, SquareRootKalmanParams)
    with pytest.raises(ValueError, match="must be a dict of per-step values of"):
        run(square_root_kalman_filter, sqrt_params, EstimatorInputs(y, model={"Q": jnp.asarray(model["Q"])}))
    with pytest.raises(ValueError, match="fitting takes a constant model"):
        jo.learning.negative_log_likelihood(kalman_filter, params, EstimatorInputs(y, model={"Q": model["Q"]}))
    with pytest.raises(ValueError, match="filter_shared_model shares one constant model"):
        jo.observers.kalman.filter_shared_model(params, EstimatorInputs(y[None], model={"Q": model["Q"][None]}))
