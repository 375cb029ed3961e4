"""Kalman Active Observer AOB-N (Cortesão 2006 §2-5, the stochastic AOB paper §2-3, the MRAC chapter §6)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from hypothesis import given
from hypothesis import strategies as st
from jax.test_util import check_grads

from jaxobs.closed_loop import simulate
from jaxobs.kalman_steps import predict, update
from jaxobs.observers import ControllerInputs, EstimatorInputs, active, run
from jaxobs.observers.active import active_observer, active_observer_controller
from jaxobs.papers.cortesao.force_control import EXAMPLE1, example1_disturbance, nominal_design, with_feedback
from jaxobs.plants import force_plant

H = EXAMPLE1.h


@pytest.fixture(scope="module")
def plant_and_gain():
    return nominal_design(EXAMPLE1)


def _series(T, key=0, noise=0.1):
    """A random-walk measurement series (T, 1) and a white series (T, 1) for open-loop runs."""
    k1, k2 = jax.random.split(jax.random.PRNGKey(key))
    y = jnp.cumsum(jax.random.normal(k1, (T, 1)), axis=0) * noise
    return y, jax.random.normal(k2, (T, 1))


def _inputs(T, key=0, noise=0.1):
    """Estimator inputs: the measurements and the commands applied before them."""
    y, u_prev = _series(T, key, noise)
    return EstimatorInputs(y=y, u_prev=u_prev)


def _controller_inputs(T, key=0, noise=0.1):
    """Controller inputs: the measurements and the references."""
    y, r = _series(T, key, noise)
    return ControllerInputs(y=y, r=r)


@pytest.mark.parametrize("order, expected", [(1, 1e-3), (2, 4e-6), (3, 2.4e-8)])
def test_evolution_variance_eq84_with_index_n_minus_1(order, expected):
    """Eq. 53-55 with sigma^2 = 1e-3, c = 1/500 evaluated at N - 1 (the conventions note)."""
    assert float(active.evolution_variance(1e-3, order, 1 / 500)) == pytest.approx(expected, rel=1e-12)


def test_theorem1_variance_of_differences():
    """Theorem 1 (eq. 54): var of the j-th difference of white noise = sigma^2 sum C(j,i)^2."""
    xi = np.random.default_rng(0).normal(size=400_000)
    for j in (1, 2, 3):
        empirical = np.var(np.diff(xi, n=j))
        assert empirical == pytest.approx(float(active.evolution_variance(1.0, j + 1)), rel=0.02)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_active_state_model_is_the_ar_process_of_eq10(order):
    """Eq. 10/37: a polynomial of degree N - 1 in k is propagated exactly; all eigenvalues are 1."""
    Phi22 = np.asarray(active.active_state_model(order))
    np.testing.assert_allclose(np.linalg.eigvals(Phi22), np.ones(order), atol=1e-3)
    k = np.arange(order + 5, dtype=float)
    coefficients = [0.5, 0.3, 0.1, 0.01][:order]  # degree N - 1
    p = sum(c * k**j for j, c in enumerate(coefficients))
    window = p[:order]
    for i in range(order, k.size):
        window = Phi22 @ window
        assert window[-1] == pytest.approx(p[i], rel=1e-12)


def test_augmentation_structure_eq48(plant_and_gain):
    """Eq. 48, 41, 24: Phi_12 = Gamma_r [0 .. 0 I], Gamma_n = [Gamma_r; 0], C = [C_r 0] (two inputs)."""
    plant, _ = plant_and_gain
    two_input = dataclasses.replace(plant, B=jnp.concatenate([plant.B, 2 * plant.B], 1), D=jnp.zeros((1, 2)))
    Phi, Gamma, C = active.augment(two_input, 2)
    n = plant.n_states
    assert Phi.shape == (n + 4, n + 4)
    np.testing.assert_array_equal(Phi[:n, n : n + 2], 0.0)
    np.testing.assert_array_equal(Phi[:n, n + 2 :], two_input.B)
    np.testing.assert_array_equal(Phi[n:, :n], 0.0)
    np.testing.assert_array_equal(Gamma[n:], 0.0)
    np.testing.assert_array_equal(C[:, n:], 0.0)


@pytest.mark.parametrize("steady_state", [False, True])
def test_aob_without_active_state_equals_ckf(plant_and_gain, steady_state):
    """The stochastic AOB paper §2.1: eliminating the active state (p = 0, its Q entry 0) gives the CKF exactly."""
    plant, L = plant_and_gain
    T = 300
    D = example1_disturbance(jnp.arange(T) * H)
    noise = 0.1 * jax.random.normal(jax.random.PRNGKey(1), (T, 1))
    r = jnp.full((T,), 1.0)
    aob_off = active.make_aob(plant, 2, 0.021, q_active=1e-3, active=0.0, steady_state=steady_state)
    ckf = active.make_ckf(plant, 0.021, steady_state=steady_state)
    a = simulate(plant, active_observer_controller, with_feedback(aob_off, L), r, disturbance=D, noise=noise)
    b = simulate(plant, active_observer_controller, with_feedback(ckf, L), r, disturbance=D, noise=noise)
    np.testing.assert_allclose(a.u, b.u, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(a.controller.x[:, : plant.n_states], b.controller.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(a.controller.estimator.d, 0.0)


def test_aob_as_estimator_equals_the_estimate_of_the_aob_as_controller(plant_and_gain):
    """The AOB run as a plain estimator on the measurements and commands recorded in a closed loop (the AOB-2 with
    the adaptive strategy of Cortesão, Koeppe, Nunes & Hirzinger, time-varying gain, a mismatched true plant, the
    eq. 81-82 disturbance and sensor noise) reproduces every output of the AOB inside the controller, to rounding:
    the controller only adds u_k = r_k - L x_hat_k (Cortesão 2006 eq. 49-50) around the same estimator."""
    plant, L = plant_and_gain
    T = 200
    aob = active.make_aob(plant, 2, 0.021, q_active=1e-5, alpha=0.3, sigma_floor=1e-4)
    true = force_plant(2.0, 1.2 * EXAMPLE1.Tp, H, 5.5 * H, n_delay=6)
    noise = 0.1 * jax.random.normal(jax.random.PRNGKey(4), (T, 1))
    reference = jnp.full((T,), float(L[0, 0]) * 5.0)
    D = example1_disturbance(jnp.arange(T) * H + 7.5)
    trace = simulate(true, active_observer_controller, with_feedback(aob, L), reference, disturbance=D, noise=noise)
    u_prev = jnp.concatenate([jnp.zeros((1, 1)), trace.u[:-1]])  # the controller starts from u_{-1} = 0
    _, out = run(active_observer, aob, EstimatorInputs(y=trace.y, u_prev=u_prev))
    for name in out._fields:
        if getattr(out, name) is None:  # the covariances, not output by default
            assert getattr(trace.controller.estimator, name) is None, name
            continue
        np.testing.assert_allclose(getattr(out, name), getattr(trace.controller.estimator, name), rtol=1e-12,
                                   atol=1e-14, err_msg=name)  # fmt: skip
    assert float(jnp.max(jnp.abs(out.d))) > 0.1  # the active state is doing work here


def test_run_time_switch_does_not_recompile(plant_and_gain):
    """The MRAC chapter §6.3/§7.1: switching AOB <-> CKF per DOF is a traced value, not a new program."""
    plant, L = plant_and_gain
    traces = []

    @jax.jit
    def final_u(params, inputs):
        traces.append(1)
        return run(active_observer_controller, params, inputs)[1].u[-1]

    aob = active.make_aob(plant, 1, 0.021, q_active=1e-3)
    params = with_feedback(aob, L)
    inputs = _controller_inputs(50)
    on = final_u(params, inputs)
    off = final_u(with_feedback(active.set_active(aob, False), L), inputs)
    assert len(traces) == 1
    assert not np.allclose(on, off)
    # per-DOF switch: a batch of 3 DOFs with different modes in one vmapped call
    batch = jax.tree_util.tree_map(lambda x: jnp.stack([x] * 3), params)
    batch = dataclasses.replace(batch, estimator=active.set_active(batch.estimator, jnp.array([1.0, 0.0, 1.0])))
    u = jax.vmap(final_u, in_axes=(0, None))(batch, inputs)
    np.testing.assert_allclose(u, jnp.array([on, off, on]), rtol=1e-10)


@pytest.mark.parametrize("steady_state", [False, True])
def test_eager_jit_vmap_agree(plant_and_gain, steady_state):
    """The observer run is the same eagerly, under jit, and batched under vmap vs a loop."""
    plant, _ = plant_and_gain
    inputs = _inputs(80)
    qs = [1e-4, 1e-3, 1e-2]
    params = [active.make_aob(plant, 2, 0.021, q_active=q, steady_state=steady_state) for q in qs]
    f = lambda p: run(active_observer, p, inputs)[1].x
    eager = [f(p) for p in params]
    jitted = [jax.jit(f)(p) for p in params]
    batched = jax.vmap(f)(jax.tree_util.tree_map(lambda *x: jnp.stack(x), *params))
    for i in range(len(qs)):
        np.testing.assert_allclose(jitted[i], eager[i], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(batched[i], eager[i], rtol=1e-10, atol=1e-12)


def test_time_varying_gain_converges_to_steady_state(plant_and_gain):
    """K_k from eq. 27-29 with P_{-1} = Q_0 converges to the DARE gain used in Table I."""
    plant, _ = plant_and_gain
    tv = active.make_aob(plant, 2, 0.021, q_active=4e-6)
    ss = active.with_steady_state_gains(tv)
    gains = run(active_observer, tv, _inputs(3000))[1].gain
    np.testing.assert_allclose(gains[-1], ss.gain, rtol=1e-6, atol=1e-9)


def test_steady_state_gain_of_a_locked_active_state_is_the_limit_of_the_recursion(plant_and_gain):
    """A zero ``Q_p`` entry with a zero prior locks the active state (Cortesão 2006 eq. 109): a mode at 1 that
    neither noise nor the measurement reaches, so no DARE has a stabilising solution. The steady-state gain is the
    limit of the time-varying recursion: the plant's filter, with a zero gain on the locked state."""
    plant, _ = plant_and_gain
    base = active.make_aob(plant, 1, 0.021, q_plant=1e-6, q_active=4e-6)
    lock = jnp.ones(base.Q.shape[-1]).at[-1].set(0.0)
    locked = dataclasses.replace(base, Q=base.Q * jnp.outer(lock, lock), P0=base.P0 * jnp.outer(lock, lock))
    ss = active.with_steady_state_gains(locked)

    def riccati_step(P, _):  # P_{k+1|k} from P_{k|k-1}: the filter's recursion without the data
        K = P @ locked.C.T @ jnp.linalg.inv(locked.C @ P @ locked.C.T + locked.R)
        P = locked.Phi @ (P - K @ locked.C @ P) @ locked.Phi.T + locked.Q
        return P, K

    _, gains = jax.lax.scan(riccati_step, locked.P0, None, length=20_000)
    np.testing.assert_allclose(gains[-1], ss.gain, rtol=1e-6, atol=1e-12)
    assert float(jnp.max(jnp.abs(ss.gain[-1]))) == 0.0 and bool(ss.gain_converged)
    ckf = active.with_steady_state_gains(active.make_aob(plant, 1, 0.021, q_plant=1e-6, q_active=4e-6, active=0))
    np.testing.assert_allclose(ss.gain, ckf.gain_passive, rtol=1e-10, atol=1e-14)
    with pytest.raises(ValueError, match="not excited by Q"):  # a locked state the prior leaves uncertain
        active.with_steady_state_gains(dataclasses.replace(locked, P0=base.P0))


@pytest.mark.parametrize("scale", [1e-3, 7.0, 1e4])
def test_qr_scale_invariance_proposition1(plant_and_gain, scale):
    """The MRAC chapter Proposition 1 (eq. 55): (aQ, aR, aP0) gives the same K_k at every step."""
    plant, _ = plant_and_gain
    base = active.make_aob(plant, 1, 0.021, q_active=1e-3)
    scaled = dataclasses.replace(base, Q=base.Q * scale, R=base.R * scale, P0=base.P0 * scale)
    inputs = _inputs(200)
    a = run(active_observer, base, inputs)
    b = run(active_observer, scaled, inputs)
    np.testing.assert_allclose(b[1].gain, a[1].gain, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(b[0].P, scale * a[0].P, rtol=1e-8, atol=1e-20 * scale)


@jax.jit
def _posterior_covariances(params, inputs):
    def body(state, inp):
        state, _ = active_observer.step(params, state, inp)
        return state, state.P

    return jax.lax.scan(body, active_observer.init(params), inputs)[1]


@given(
    order=st.integers(1, 3),
    log_r=st.floats(-6, 1),
    log_q=st.floats(-10, 0),
    seed=st.integers(0, 2**16),
)
def test_covariance_symmetric_psd_along_long_runs(plant_and_gain, order, log_r, log_q, seed):
    """Joseph form keeps P symmetric and PSD over 1500 steps for any Q/R strategy."""
    plant, _ = plant_and_gain
    params = active.make_aob(plant, order, 10.0**log_r, q_active=10.0**log_q)
    Ps = np.asarray(_posterior_covariances(params, _inputs(1500, seed))[::50])
    np.testing.assert_array_equal(Ps, np.swapaxes(Ps, -1, -2))
    scale = np.max(np.abs(Ps), axis=(1, 2))
    assert np.all(np.linalg.eigvalsh(Ps).min(axis=1) >= -1e-9 * scale)


def test_nan_measurement_is_skipped_and_counted(plant_and_gain):
    """A non-finite measurement skips the update (prediction only) and is counted."""
    plant, _ = plant_and_gain
    params = active.make_aob(plant, 1, 0.021, q_active=1e-3)
    inputs = _inputs(30)
    y = inputs.y.at[10].set(jnp.nan).at[20].set(jnp.inf)
    state, out = run(active_observer, params, EstimatorInputs(y=y, u_prev=inputs.u_prev))
    assert int(state.missing) == 2
    assert np.all(np.isfinite(out.x))
    prior = params.Phi @ out.x[9] + params.Gamma @ inputs.u_prev[10]
    np.testing.assert_allclose(out.x[10], prior, rtol=1e-12, atol=1e-14)


def test_adaptive_strategy_eq27_probability():
    """Eq. 20-27: with sigma from eq. 27, P(|w_k| > |w_{k-1}|) = alpha for w_k ~ N(0, sigma^2)."""
    for alpha in (0.05, 0.3173, 0.5, 0.9):
        w_prev = 0.37
        sigma = np.sqrt(float(active.adaptive_variance(w_prev, alpha, 0.0)))
        probability = 2 * scipy.stats.norm.sf(w_prev / sigma)
        assert probability == pytest.approx(alpha, rel=1e-10)
        assert float(active.strategy_alpha(w_prev, sigma**2)) == pytest.approx(alpha, rel=1e-10)  # eq. 34


def test_adaptive_strategy_floor_eq32():
    """Eq. 32: for weak evolutions the alpha of eq. 32 yields sigma ~= sigma*; the floor holds."""
    floor = 1e-3
    w = 1e-9
    alpha = float(active.alpha_for_floor(w, floor))
    assert np.sqrt(float(active.adaptive_variance(w, alpha, 0.0))) == pytest.approx(floor, rel=1e-6)
    assert float(active.adaptive_variance(0.0, 0.5, floor)) == pytest.approx(floor**2)


def test_constant_strategy_eq35_36():
    """Eq. 35-36: Q_k = w^2 / c^2 keeps alpha = 1 - erf(c / sqrt 2) whatever w is."""
    c = 1.3
    for w in (1e-4, 0.2, 5.0):
        alpha = float(active.strategy_alpha(w, active.constant_strategy_variance(w, c)))
        assert alpha == pytest.approx(1 - scipy.special.erf(c / np.sqrt(2)), rel=1e-10)


def test_deviation_variance_eq46_47():
    """Eq. 46-47: beta = 1 - erf(sqrt(2)/2) = 0.3173 makes gamma the standard deviation."""
    assert active.BETA_ONE_SIGMA == pytest.approx(0.3173, abs=5e-5)
    assert float(active.deviation_variance(1e-6)) == pytest.approx(1e-12, rel=1e-10)
    assert float(active.deviation_variance(2.0, 0.05)) == pytest.approx((2.0 / 1.959964) ** 2, rel=1e-5)


def test_adaptive_observer_uses_eq27_variance(plant_and_gain):
    """The step's Q_k for the active state follows eq. 27 (with floor) of the last evolution."""
    plant, _ = plant_and_gain
    params = active.make_aob(plant, 1, 0.021, q_active=1e-5, alpha=0.4, sigma_floor=1e-4)
    _, out = run(active_observer, params, _inputs(100))
    evolution = jnp.diff(jnp.concatenate([jnp.zeros((1, 1)), out.d]), axis=0)
    expected = active.adaptive_variance(jnp.concatenate([jnp.zeros((1, 1)), evolution[:-1]]), 0.4, 1e-4)
    np.testing.assert_allclose(out.q_active, expected, rtol=1e-10)
    assert float(jnp.max(out.q_active)) > 1e-8  # the strategy is actually adapting


@pytest.mark.parametrize("order", [2, 3])
def test_newest_active_state_is_the_one_the_input_channel_feeds(plant_and_gain, order):
    """Eq. 41: Phi_12 = Gamma_r [0 ... 0 I] couples only the newest active state into the plant. The step reports
    that state as d, and the adaptive strategy (the stochastic AOB paper eq. 27) puts its Q_k there: the run equals a
    Kalman filter whose Q has q_active_k on the newest state (the Kalman predict and update with the observer's own
    matrices; the first step updates the prior x0, P0 without a prediction)."""
    plant, _ = plant_and_gain
    params = active.make_aob(plant, order, 0.021, q_active=1e-5, alpha=0.4, sigma_floor=1e-4)
    n = plant.n_states
    fed = np.flatnonzero(np.any(np.asarray(params.Phi[:n, n:]) != 0, axis=0)) + n
    assert fed.tolist() == [n + order - 1]
    inputs = _inputs(40)
    _, out = run(active_observer, params, inputs)
    np.testing.assert_array_equal(out.d[:, 0], out.x[:, fed[0]])
    x, P = params.x0, params.P0
    for k in range(40):
        if k:
            Q = params.Q.at[fed[0], fed[0]].set(out.q_active[k, 0])
            x, P = predict(x, P, params.Phi, Q, params.Gamma, inputs.u_prev[k])
        x, P, *_ = update(x, P, params.C, params.R, inputs.y[k])
        np.testing.assert_allclose(out.x[k], x, rtol=1e-9, atol=1e-12)


def test_strategies(plant_and_gain):
    """Cortesão 2006 §5: the gain magnitude names the strategy (MBA small, SBA -> sensor, HBA between)."""
    plant, _ = plant_and_gain
    C = plant.C
    assert active.classify_strategy(active.sensor_based_gain(C), C) == "SBA"
    np.testing.assert_allclose(active.sensor_based_gain(C)[:, 0], np.eye(1, 7)[0])
    hba = active.make_aob(plant, 1, 0.021, q_active=1e-5, steady_state=True)
    mba = active.make_ckf(plant, 0.021, steady_state=True)
    aug_C = hba.C
    assert active.classify_strategy(hba.gain, aug_C) == "HBA"
    assert active.classify_strategy(mba.gain, C) == "MBA"


@pytest.mark.slow
def test_gradient_through_closed_loop(plant_and_gain):
    """d(tracking cost)/d(log q_active, log R) through the AOB + plant scan matches finite differences."""
    plant, L = plant_and_gain
    T = 60
    D = example1_disturbance(jnp.arange(T) * H + 7.0)
    noise = 0.1 * jax.random.normal(jax.random.PRNGKey(3), (T, 1))

    @jax.jit
    def cost(log_q, log_r):
        params = with_feedback(active.make_aob(plant, 2, jnp.exp(log_r)[None, None], q_active=jnp.exp(log_q)), L)
        tr = simulate(plant, active_observer_controller, params, jnp.ones((T,)), disturbance=D, noise=noise)
        return jnp.mean(tr.y_true**2)

    check_grads(cost, (jnp.log(1e-3), jnp.log(0.021)), order=1, modes=["rev", "fwd"], rtol=1e-4)

    @jax.jit
    def cost_ss(log_q):
        params = active.make_aob(plant, 1, 0.021, q_active=jnp.exp(log_q), steady_state=True)
        return jnp.sum(params.gain**2)

    check_grads(cost_ss, (jnp.log(1e-3),), order=1, modes=["rev", "fwd"], rtol=1e-4)


def test_full_q_replaces_the_block_diagonal_of_eq51(plant_and_gain):
    """``make_aob(..., Q=...)`` with eq. 51-53's own Q is the same observer; another full Q is taken as given."""
    plant, _ = plant_and_gain
    aob = active.make_aob(plant, 2, 0.1, q_plant=1e-6, q_active=1e-3, steady_state=True)
    same = active.make_aob(plant, 2, 0.1, Q=aob.Q, steady_state=True)
    np.testing.assert_array_equal(same.gain, aob.gain)
    coupled = aob.Q.at[0, -1].set(1e-5).at[-1, 0].set(1e-5)
    np.testing.assert_array_equal(active.make_aob(plant, 2, 0.1, Q=coupled).Q, coupled)
    with pytest.raises(ValueError, match="Q must be positive semidefinite"):
        active.make_aob(plant, 2, 0.1, Q=-aob.Q)


def test_bad_inputs(plant_and_gain):
    """Clear ValueErrors naming the argument."""
    plant, L = plant_and_gain
    with pytest.raises(ValueError, match=r"^order\b.*>= 1.*got 0"):
        active.make_aob(plant, 0, 0.021)
    with pytest.raises(ValueError, match=r"^order\b.*>= 1.*got 0"):
        active.active_state_model(0)
    with pytest.raises(ValueError, match=r"^alpha\b.*< 1"):
        active.make_aob(plant, 1, 0.021, alpha=1.5)
    with pytest.raises(ValueError, match=r"^R\b.*positive definite.*smallest eigenvalue 0\)"):
        active.make_aob(plant, 1, 0.0)
    with pytest.raises(ValueError, match=r"^R\b.*positive definite.*smallest eigenvalue -1\)"):
        active.make_aob(plant, 1, -1.0)
    with pytest.raises(ValueError, match=r"^L_r\b.*\(1, 3\)"):
        active.feedback_gain(active.make_aob(plant, 1, 0.021), L[:, :3])
    with pytest.raises(ValueError, match=r"^plant\b.*discrete"):
        active.make_aob(dataclasses.replace(plant, dt=None), 1, 0.021)
    with pytest.raises(ValueError, match=r"^q_active\b.*non-negative.*-1\.0"):
        active.make_aob(plant, 1, 0.021, q_active=-1.0)
    with pytest.raises(ValueError, match=r"^c\b.*positive.*0\.0"):
        active.evolution_variance(1e-3, 2, c=0.0)
