"""Tests for jaxobs.observers.hinf, the a-posteriori H-infinity filter (Hassibi, Sayed & Kailath 1996, IEEE TAC
41(1); Simon 2006 ch. 11): reduction to the Kalman filter as gamma -> inf, the existence check around the bisection
level, the worst-case gain bound (exact singular value of the disturbance-to-error map, gradient ascent and random
disturbances), transformations (jit, vmap, grad) and input validation."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxobs.observers.base import EstimatorInputs, run
from jaxobs.observers.hinf import (
    gamma_bisection,
    hinf_filter,
    hinf_riccati_sequence,
    hinf_steady_state,
    make_hinf,
)
from jaxobs.observers.kalman import kalman_filter, make_kalman

N_STEPS = 30


@jax.jit
def run_hinf(params, inputs):
    """run(hinf_filter, ...) compiled once per shape (params are a pytree, so gamma changes do not recompile)."""
    return run(hinf_filter, params, inputs)


@jax.jit
def run_kalman(params, inputs):
    return run(kalman_filter, params, inputs)


def make_problem(seed=0, n=3, p=2, T=N_STEPS):
    """A random stable plant, correlated R, an estimated combination z = Cz x, and random data (u_prev, y).

    The prior of x_0 is that of x_{-1} ~ (0, I) advanced one step, P0 = Phi Phi' + Q (so the levels are those of the
    earlier convention, a prior of x_{-1} with the identity covariance)."""
    rng = np.random.default_rng(seed)
    Phi = rng.normal(size=(n, n))
    Phi *= 0.97 / np.max(np.abs(np.linalg.eigvals(Phi)))
    Gamma, C = rng.normal(size=(n, 1)), rng.normal(size=(p, n))
    G = rng.normal(size=(n, n)) * 0.3
    Q = G @ G.T + 0.01 * np.eye(n)
    R = np.array([[0.5, 0.2], [0.2, 0.3]])[:p, :p]
    Cz = np.array([[1.0, 0.5, 0.0]])[:, :n]
    P0 = Phi @ Phi.T + Q
    u, y = rng.normal(size=(T, 1)), rng.normal(size=(T, p))
    return dict(Phi=Phi, Gamma=Gamma, C=C, Q=Q, R=R, Cz=Cz, P0=P0), jnp.asarray(u), jnp.asarray(y)


def hinf_params(model, gamma, **kw):
    m = model
    return make_hinf(m["Phi"], m["C"], m["Q"], m["R"], gamma=gamma, Gamma=m["Gamma"], Cz=m["Cz"], P0=m["P0"], **kw)


def kalman_params(model):
    """The Kalman filter of ``model`` with the Joseph-form update, the form of the H-infinity Riccati step."""
    m = model
    return make_kalman(m["Phi"], m["C"], m["Q"], m["R"], Gamma=m["Gamma"], P0=m["P0"], joseph=True)


def optimal_level(model, num_steps=N_STEPS):
    m = model
    return gamma_bisection(m["Phi"], m["C"], m["Q"], m["R"], Cz=m["Cz"], P0=m["P0"], num_steps=num_steps, rtol=1e-8)


@pytest.fixture(scope="module")
def problem():
    model, u, y = make_problem(0)
    return model, u, y, optimal_level(model)


# ---------------------------------------------------------------------------------------------
# reduction to the Kalman filter


@pytest.mark.parametrize("gamma", [np.inf, 1e7])
def test_large_gamma_reproduces_the_kalman_filter(problem, gamma):
    """gamma -> inf: the correction gamma^{-2} P Cz'(I - gamma^{-2} Cz P Cz')^{-1} Cz P vanishes, so estimates, gains
    and the Riccati matrix equal kalman.py's (bit for bit at gamma = inf, O(gamma^{-2}) at gamma = 1e7)."""
    model, u, y, _ = problem
    m = model
    kp = kalman_params(model)
    fk, ok = run_kalman(kp, EstimatorInputs(y=y, u_prev=u))
    fh, oh = run_hinf(hinf_params(model, gamma), EstimatorInputs(y=y, u_prev=u))
    tol = 0.0 if np.isinf(gamma) else 1e-11
    np.testing.assert_allclose(oh.x, ok.x, rtol=0, atol=tol)
    np.testing.assert_allclose(oh.gain, ok.gain, rtol=0, atol=tol)
    np.testing.assert_allclose(fh.P, fk.P, rtol=0, atol=tol)
    np.testing.assert_allclose(oh.z, ok.x @ m["Cz"].T, rtol=0, atol=tol)
    assert int(fh.violations) == 0 and bool(jnp.all(oh.feasible))


def test_correction_inflates_the_riccati_matrix(problem):
    """For finite gamma the H-infinity matrix dominates the Kalman one (Pb_k >= P_k, the -gamma^{-2} Cz'Cz term)
    and the gain differs; the gap shrinks monotonically as gamma grows."""
    model, u, y, gs = problem
    kp = kalman_params(model)
    fk, _ = run_kalman(kp, EstimatorInputs(y=y, u_prev=u))
    gaps = []
    for factor in [1.05, 2.0, 10.0, 100.0]:
        fh, _ = run_hinf(hinf_params(model, factor * gs.gamma), EstimatorInputs(y=y, u_prev=u))
        D = np.asarray(fh.P - fk.P)
        assert np.linalg.eigvalsh(D)[0] > -1e-12
        gaps.append(np.max(np.abs(D)))
    assert all(a > b for a, b in zip(gaps, gaps[1:], strict=False))


# ---------------------------------------------------------------------------------------------
# existence condition and the bisection level


def test_bisection_level_separates_feasible_from_infeasible(problem):
    """gamma_bisection converges (found, bracket within rtol); just below it the filter flags violations, just
    above it none, and the Riccati sequence reports the same."""
    model, u, y, gs = problem
    m = model
    assert bool(gs.found)
    assert float(gs.gamma - gs.lower) <= 1e-8 * float(gs.gamma)
    for factor, expect_ok in [(1 - 1e-4, False), (1 + 1e-4, True), (0.5, False), (3.0, True)]:
        gamma = factor * gs.gamma
        final, out = run_hinf(hinf_params(model, gamma), EstimatorInputs(y=y, u_prev=u))
        seq = hinf_riccati_sequence(m["P0"], m["Phi"], m["C"], m["Cz"], m["Q"], m["R"], gamma, N_STEPS)
        assert (int(final.violations) == 0) == expect_ok
        assert bool(jnp.all(seq.feasible)) == expect_ok
        assert bool(jnp.all(out.feasible)) == expect_ok
        np.testing.assert_array_equal(out.feasible, out.margin > 0)
        assert np.all(np.isfinite(np.asarray(out.x)))  # a violation is flagged, never NaN


def test_bisection_lower_bracket_and_longer_horizon():
    """The level is at least sqrt(lambda_max(Cz P_0 Cz')) (first-step bound; P_0 the first Kalman a-posteriori
    matrix, from the prior P0 without prediction) and grows with the horizon; the steady-state recursion converges
    and is feasible just above the long-horizon level, not below it."""
    model, _, _ = make_problem(1)
    m = model
    short, long = optimal_level(model, 5), optimal_level(model, 400)
    assert float(short.gamma) <= float(long.gamma) * (1 + 1e-7)
    P_first = np.linalg.inv(np.linalg.inv(m["P0"]) + m["C"].T @ np.linalg.solve(m["R"], m["C"]))
    assert float(short.gamma) > np.sqrt(np.max(np.linalg.eigvalsh(m["Cz"] @ P_first @ m["Cz"].T)))
    above = hinf_steady_state(m["Phi"], m["C"], m["Cz"], m["Q"], m["R"], 1.01 * long.gamma, P_init=m["P0"])
    below = hinf_steady_state(m["Phi"], m["C"], m["Cz"], m["Q"], m["R"], 0.99 * long.gamma, P_init=m["P0"])
    assert bool(above.converged) and bool(above.feasible)
    assert not bool(below.feasible)
    with pytest.raises(ValueError, match="gamma"):
        hinf_params(model, 0.99 * long.gamma, steady_state=True)
    ss = hinf_params(model, 1.01 * long.gamma, steady_state=True)
    np.testing.assert_allclose(ss.gain, above.gain)


@pytest.mark.parametrize("gamma", [np.inf, 50.0])
def test_steady_state_converged_means_the_stabilising_solution(gamma):
    """``converged`` of hinf_steady_state means the stabilising solution was found (issue 13): an unstable mode that
    Q does not excite (Phi = diag(1.5, 0.5), C = [[1, 1]], Q = diag(0, 0.01)) gets the stable filter from the default
    positive definite start, flagged converged; an undetectable mode on the unit circle (Phi = diag(1, 0.5),
    C = [[0, 1]]) is flagged not converged (before, both reported converged = True)."""
    R, Cz = np.eye(1), np.eye(2)
    Phi, C, Q = np.diag([1.5, 0.5]), np.array([[1.0, 1.0]]), np.diag([0.0, 0.01])
    sol = hinf_steady_state(Phi, C, Cz, Q, R, gamma)
    filter_matrix = (np.eye(2) - np.asarray(sol.gain) @ C) @ Phi
    assert bool(sol.converged) and np.max(np.abs(np.linalg.eigvals(filter_matrix))) < 1
    undetectable = hinf_steady_state(np.diag([1.0, 0.5]), np.array([[0.0, 1.0]]), Cz, np.eye(2), R, gamma)
    assert not bool(undetectable.converged)


# ---------------------------------------------------------------------------------------------
# worst-case gain


def error_map(model, T=N_STEPS, kalman=False):
    """``errors(d, gamma)``: d = (delta, w_hat, v_hat) -> (z_k - z_hat_k)_k for k = 0 .. T-1 with the state of the
    first measurement x_0 = x0 + P0^{1/2} delta, x_k = Phi x_{k-1} + Q^{1/2} w_hat_k (k >= 1) and
    y_k = C x_k + R^{1/2} v_hat_k, so the denominator of the H-infinity ratio is |d|^2. ``kalman``: the Kalman
    filter instead (gamma ignored)."""
    m = {k: jnp.asarray(v) for k, v in model.items()}
    n, p = m["Phi"].shape[0], m["C"].shape[0]
    S0, Sq, Sr = (jnp.linalg.cholesky(m[k]) for k in ("P0", "Q", "R"))
    base = hinf_params(model, 1.0)
    kp = kalman_params(model)
    u = jnp.zeros((T, 1))

    def errors(d, gamma):
        delta, w, v = d[:n], d[n : n + (T - 1) * n].reshape(T - 1, n), d[n + (T - 1) * n :].reshape(T, p)

        def plant(x, w_k):
            x = m["Phi"] @ x + Sq @ w_k
            return x, x

        x_first = base.x0 + S0 @ delta
        xs = jnp.concatenate([x_first[None], jax.lax.scan(plant, x_first, w)[1]])
        inputs = EstimatorInputs(y=xs @ m["C"].T + v @ Sr.T, u_prev=u)
        if kalman:
            _, out = run(kalman_filter, kp, inputs)
        else:
            _, out = run(hinf_filter, dataclasses.replace(base, gamma=gamma), inputs)
        return ((xs - out.x) @ m["Cz"].T).ravel()

    return errors, n + (T - 1) * n + T * p


def worst_case_ratio(errors, dim, gamma):
    """sigma_max(T)^2 for the (linear) disturbance-to-error map T."""
    T = jax.jit(jax.jacfwd(errors))(jnp.zeros(dim), jnp.asarray(gamma))
    return float(jnp.linalg.norm(T, 2) ** 2)


def test_exact_worst_case_gain_below_gamma_squared(problem):
    """The filter is linear, so sup ratio = sigma_max(T)^2 for the disturbance-to-error Jacobian T: it stays below
    gamma^2 for several gamma above the bisection level, and at gamma = 1.001 gamma* it is squeezed between
    gamma*^2 (no causal filter does better) and gamma^2. The Kalman filter's worst case is at least gamma*^2."""
    model, _, _, gs = problem
    g_star = float(gs.gamma)
    errors, dim = error_map(model)
    jac = jax.jit(jax.jacfwd(errors))
    for factor in [1.001, 1.1, 2.0, 10.0]:
        gamma = factor * g_star
        ratio = float(jnp.linalg.norm(jac(jnp.zeros(dim), jnp.asarray(gamma)), 2) ** 2)
        assert ratio < gamma**2, (factor, ratio, gamma**2)
        if factor == 1.001:
            assert ratio >= g_star**2 * (1 - 1e-6)
    kalman_ratio = worst_case_ratio(*error_map(model, kalman=True), 0.0)
    assert kalman_ratio >= g_star**2 * (1 - 1e-6)


@pytest.mark.slow
def test_adversarial_disturbances_by_gradient_ascent_stay_below_gamma_squared(problem):
    """Random unit-energy disturbances and 40 steps of normalised jax.grad ascent on the ratio
    sum |z - z_hat|^2 / (|x_0 - x0|^2_{P0^{-1}} + sum_{k>=1} |w_k|^2_{Q^{-1}} + sum |v|^2_{R^{-1}}): every ratio stays
    below gamma^2 (gamma = 1.01 gamma*), and the ascent climbs to the exact worst case sigma_max^2."""
    model, _, _, gs = problem
    gamma = 1.01 * float(gs.gamma)
    errors, dim = error_map(model)

    def ratio(d):
        return jnp.sum(errors(d, gamma) ** 2) / jnp.sum(d**2)

    d0 = jax.random.normal(jax.random.PRNGKey(0), (64, dim))
    random_ratios = jax.jit(jax.vmap(ratio))(d0)
    assert float(jnp.max(random_ratios)) < gamma**2

    grad = jax.jit(jax.grad(ratio))

    @jax.jit
    def ascend(d):
        def body(d, _):
            d = d + (0.5 / gamma**2) * grad(d)  # |d| = 1; a power-iteration-like ascent step
            return d / jnp.linalg.norm(d), ratio(d)

        return jax.lax.scan(body, d / jnp.linalg.norm(d), None, length=40)

    d, history = ascend(d0[0])
    assert float(jnp.max(history)) < gamma**2
    exact = worst_case_ratio(errors, dim, gamma)
    assert float(history[-1]) > float(random_ratios[0])
    assert float(history[-1]) > 0.9 * exact
    assert float(history[-1]) <= exact * (1 + 1e-9)


# ---------------------------------------------------------------------------------------------
# transformations


def test_eager_equals_jit(problem):
    model, u, y, gs = problem
    params = hinf_params(model, 1.2 * gs.gamma)
    fe, oe = run(hinf_filter, params, EstimatorInputs(y=y, u_prev=u))
    fj, oj = jax.jit(lambda p, i: run(hinf_filter, p, i))(params, EstimatorInputs(y=y, u_prev=u))
    for a, b in zip(jax.tree_util.tree_leaves((fe, oe)), jax.tree_util.tree_leaves((fj, oj)), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    m = model
    gj = jax.jit(lambda Phi: gamma_bisection(Phi, m["C"], m["Q"], m["R"], Cz=m["Cz"], P0=m["P0"],
                                             num_steps=N_STEPS, rtol=1e-8))(jnp.asarray(m["Phi"]))  # fmt: skip
    np.testing.assert_allclose(gj.gamma, gs.gamma, rtol=1e-12)


def test_vmap_batched_equals_looped(problem):
    """vmap over (gamma, measurement sequence) equals a Python loop, including the violation counts."""
    model, u, y, gs = problem
    gammas = jnp.asarray([0.9, 1.05, 2.0, np.inf]) * gs.gamma
    ys = y[None] + 0.1 * jax.random.normal(jax.random.PRNGKey(1), (4, *y.shape))
    base = hinf_params(model, 1.0)

    def one(gamma, yk):
        return run(hinf_filter, dataclasses.replace(base, gamma=gamma), EstimatorInputs(y=yk, u_prev=u))

    fb, ob = jax.jit(jax.vmap(one))(gammas, ys)
    one_jit = jax.jit(one)
    for i in range(4):
        fl, ol = one_jit(gammas[i], ys[i])
        np.testing.assert_allclose(ob.x[i], ol.x, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(fb.P[i], fl.P, rtol=1e-12, atol=1e-12)
        assert int(fb.violations[i]) == int(fl.violations)
    assert int(fb.violations[0]) > 0 and int(fb.violations[1]) == 0
    m = model
    lev = jax.vmap(lambda s: optimal_level(dict(m, R=s * m["R"])).gamma)(jnp.asarray([1.0, 2.0]))
    np.testing.assert_allclose(lev[0], gs.gamma, rtol=1e-12)
    np.testing.assert_allclose(lev[1], optimal_level(dict(m, R=2.0 * m["R"])).gamma, rtol=1e-12)


def test_grad_finite_and_correct_wrt_gamma_and_q(problem):
    """A tracking loss is differentiable w.r.t. gamma and a Q scale: finite gradients that match finite
    differences (jax.test_util.check_grads) and forward mode equals reverse mode."""
    model, u, y, gs = problem
    base = hinf_params(model, 1.0)

    def loss(gamma, q_scale):
        params = dataclasses.replace(base, gamma=gamma, Q=q_scale * base.Q)
        _, out = run(hinf_filter, params, EstimatorInputs(y=y, u_prev=u))
        return jnp.sum((out.z[:, 0] - y[:, 0]) ** 2)

    args = (1.5 * gs.gamma, jnp.asarray(1.3))
    g = jax.jit(jax.grad(loss, argnums=(0, 1)))(*args)
    assert all(np.isfinite(float(v)) and float(v) != 0.0 for v in g)
    g_fwd = jax.jit(jax.jacfwd(loss, argnums=(0, 1)))(*args)
    np.testing.assert_allclose(g_fwd, g, rtol=1e-10)
    check_grads(jax.jit(loss), args, order=1, modes=("rev",), atol=1e-6, rtol=1e-5)


def test_missing_measurements_are_skipped_and_counted(problem):
    """NaN measurements: skipped as in the Kalman filter (equal at gamma = inf), counted in state.missing."""
    model, u, y, _ = problem
    y = y.at[[3, 7], 0].set(jnp.nan).at[10].set(jnp.nan)
    kp = kalman_params(model)
    fk, ok = run_kalman(kp, EstimatorInputs(y=y, u_prev=u))
    fh, oh = run_hinf(hinf_params(model, np.inf), EstimatorInputs(y=y, u_prev=u))
    assert int(fh.missing) == int(fk.missing) == 4
    np.testing.assert_array_equal(oh.x, ok.x)


# ---------------------------------------------------------------------------------------------
# validation


@pytest.mark.parametrize(
    ("change", "name"),
    [
        (dict(Phi=np.ones((3, 2))), "Phi"),
        (dict(Q=-np.eye(3)), "Q"),
        (dict(R=np.zeros((2, 2))), "R"),
        (dict(C=np.ones((2, 4))), "C"),
        (dict(Cz=np.ones((1, 2))), "Cz"),
        (dict(P0=np.array([[1.0, 2.0, 0], [0, 1, 0], [0, 0, 1]])), "P0"),
        (dict(Gamma=np.ones((2, 1))), "Gamma"),
        (dict(gamma=0.0), "gamma"),
        (dict(gamma=-1.0), "gamma"),
        (dict(gamma=np.nan), "gamma"),
        (dict(gamma=np.ones(2)), "gamma"),
    ],
)
def test_bad_inputs_raise_value_error_naming_the_argument(change, name):
    model, _, _ = make_problem(2)
    args = dict(model, gamma=1.0)
    args.update(change)
    with pytest.raises(ValueError, match=name):
        make_hinf(args["Phi"], args["C"], args["Q"], args["R"], gamma=args["gamma"], Gamma=args["Gamma"], Cz=args["Cz"],
                  P0=args["P0"])  # fmt: skip


def test_gamma_bisection_validates_its_inputs():
    model, _, _ = make_problem(2)
    m = model
    with pytest.raises(ValueError, match="Phi"):
        gamma_bisection(np.ones((3, 2)), m["C"], m["Q"], m["R"])
    with pytest.raises(ValueError, match="rtol"):
        gamma_bisection(m["Phi"], m["C"], m["Q"], m["R"], rtol=0.0)
    with pytest.raises(ValueError, match="num_steps"):
        gamma_bisection(m["Phi"], m["C"], m["Q"], m["R"], num_steps=0)


def test_vehicle_lateral_speed_liu_peng2002_eq31():
    """Liu & Peng 2002 Sec. 4.2, eq. 31: bicycle model (a1..a4 as printed, v_x = 15 m/s), yaw rate measured at 100 Hz,
    disturbance d on the lateral-speed equation, estimated z = v_y. ZOH-discretised; the H-infinity filter at
    1.01 gamma* keeps its exact worst-case ratio below gamma^2 while the Kalman filter's exceeds gamma*^2."""
    import scipy.linalg

    A = np.array([[-9.754, -14.03], [0.5901, -12.622]])
    B = np.array([[2 * 51000 / 1700, 1.0], [2 * 1.14 * 51000 / 3200, 0.0]])  # [B_u, B_d]
    M = scipy.linalg.expm(np.block([[A, B], [np.zeros((2, 4))]]) * 0.01)
    Phi, Gu, Gd = M[:2, :2], M[:2, 2:3], M[:2, 3:4]
    Q = Gd @ Gd.T + 1e-8 * np.eye(2)  # P0 below: the prior of x_0 from x_{-1} with covariance 1e-2 I
    model = dict(Phi=Phi, Gamma=Gu, C=np.array([[0.0, 1.0]]), Q=Q, R=np.array([[1e-4]]), Cz=np.array([[1.0, 0.0]]),
                 P0=1e-2 * Phi @ Phi.T + Q)  # fmt: skip
    T = 150
    gs = optimal_level(model, T)
    assert bool(gs.found)
    gamma = 1.01 * float(gs.gamma)
    ratio = worst_case_ratio(*error_map(model, T), gamma)
    kalman = worst_case_ratio(*error_map(model, T, kalman=True), 0.0)
    assert float(gs.gamma) ** 2 * (1 - 1e-6) <= ratio < gamma**2
    assert kalman > ratio
