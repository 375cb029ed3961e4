"""Closed-loop simulation (Cortesão 2006 eq. 20, 43, 47, 59 setting): plant + AOB + state feedback, and every estimator
family as a controller."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.closed_loop import ideal_response, measurement_noise, rms, simulate
from jaxobs.design import acker, reference_gain
from jaxobs.lti import c2d, ss
from jaxobs.observers import (
    EstimatorInputs,
    FeedbackParams,
    LinearObserver,
    active,
    hinf,
    inverse_dynamics,
    kalman,
    linear,
    observer_controller,
    run,
)
from jaxobs.observers.active import active_observer_controller
from jaxobs.papers.cortesao.force_control import EXAMPLE1, example1_disturbance, nominal_design, with_feedback
from jaxobs.plants import force_plant

H = EXAMPLE1.h


@pytest.fixture(scope="module")
def nominal():
    return nominal_design(EXAMPLE1)


def _numpy_reference(plant, params, r, d, v):
    """Plain NumPy loop of eq. 47 (time-varying K from eq. 27-29, Joseph form) around the plant; the first sample
    updates the prior (x0, P0) of x_0 without a prediction."""
    A, B, C = (np.asarray(M) for M in (plant.A, plant.B, plant.C))
    aob = params.estimator
    Phi, Gam, Ca, L = (np.asarray(M) for M in (aob.Phi, aob.Gamma, aob.C, params.L))
    Q, R = np.asarray(aob.Q), np.asarray(aob.R)
    x = np.zeros(A.shape[0])
    xh = np.asarray(aob.x0)
    P = np.asarray(aob.P0)
    u = np.zeros(1)
    us = []
    for k in range(len(r)):
        y = C @ x + v[k]
        x1, P1 = (xh, P) if k == 0 else (Phi @ xh + Gam @ u, Phi @ P @ Phi.T + Q)
        K = P1 @ Ca.T @ np.linalg.inv(Ca @ P1 @ Ca.T + R)
        xh = x1 + K @ (y - Ca @ x1)
        IKC = np.eye(len(xh)) - K @ Ca
        P = IKC @ P1 @ IKC.T + K @ R @ K.T
        u = np.array([r[k]]) - L @ xh
        us.append(u[0])
        x = A @ x + B @ (u + d[k])
    return np.array(us)


def test_simulate_matches_numpy_reference(nominal):
    """The scan equals a hand-written loop of eq. 47 + plant to 1e-10."""
    plant, L = nominal
    T = 150
    params = with_feedback(active.make_aob(plant, 2, 0.021, q_active=1e-3), L)
    r = np.full(T, 1.15)
    d = np.asarray(example1_disturbance(jnp.arange(T) * H + 7.5))
    v = np.asarray(measurement_noise(jax.random.PRNGKey(0), T, 0.021))
    trace = simulate(plant, active_observer_controller, params, r, disturbance=d, noise=v)
    np.testing.assert_allclose(trace.u[:, 0], _numpy_reference(plant, params, r, d, v), rtol=1e-9, atol=1e-10)


def test_aob_imposes_the_desired_closed_loop_without_disturbance(nominal):
    """Eq. 25/43: without disturbance and noise the loop follows the desired closed loop exactly."""
    plant, L = nominal
    T = 1000  # 25 closed-loop time constants
    r = jnp.full((T,), float(L[0, 0]) * 5.0)
    trace = simulate(plant, active_observer_controller, with_feedback(active.make_aob(plant, 1, 0.021), L), r)
    np.testing.assert_allclose(trace.y_true[:, 0], ideal_response(plant, L, r)[:, 0], atol=1e-9)
    assert float(trace.y_true[-1, 0]) == pytest.approx(5.0, rel=1e-8)  # unit DC gain with r = L_1 F_d


def test_aob_rejects_constant_input_disturbance(nominal):
    """An active state of order 1 removes the steady-state error of a step input disturbance."""
    plant, L = nominal
    T = 1500
    r = jnp.full((T,), float(L[0, 0]) * 5.0)
    d = jnp.where(jnp.arange(T) > 300, 1.5, 0.0)
    params = with_feedback(active.make_aob(plant, 1, 0.021, q_active=1e-3), L)
    trace = simulate(plant, active_observer_controller, params, r, disturbance=d)
    assert abs(float(trace.y_true[-1, 0]) - 5.0) < 1e-6
    assert float(trace.controller.estimator.d[-1, 0]) == pytest.approx(1.5, rel=1e-6)


def test_vmap_over_mismatched_plants_and_noise_seeds(nominal):
    """Batched over true stiffness and dead time (padded slots) and noise seeds = Python loop."""
    plant, L = nominal
    params = with_feedback(active.make_aob(plant, 1, 0.021, q_active=1e-3, steady_state=True), L)
    T = 200
    r = jnp.full((T,), float(L[0, 0]))
    Ks = jnp.array([1.5, 3.0, 6.0])
    delays = jnp.array([4.0, 5.0, 6.5]) * H
    keys = jax.random.split(jax.random.PRNGKey(2), 3)

    def error(ks, delay, key):
        true = force_plant(ks, EXAMPLE1.Tp, H, delay, n_delay=7)
        noise = measurement_noise(key, T, 0.021)
        return rms(simulate(true, active_observer_controller, params, r, noise=noise).y_true[:, 0] - 1.0)

    batched = jax.jit(jax.vmap(error))(Ks, delays, keys)
    looped = jnp.array([error(*args) for args in zip(Ks, delays, keys, strict=True)])
    np.testing.assert_allclose(batched, looped, rtol=1e-10)
    assert np.all(np.isfinite(batched))


def test_feedthrough_plant_rejected(nominal):
    plant, L = nominal
    import dataclasses

    bad = dataclasses.replace(plant, D=jnp.ones((1, 1)))
    with pytest.raises(ValueError, match="plant.D"):
        simulate(bad, active_observer_controller, with_feedback(active.make_aob(plant, 1, 0.021), L), jnp.zeros(5))


# --------------------------------------------------------------------------------------------
# Every family as an estimator and as a controller (observer_controller)

_A = jnp.array([[0.0, 1.0], [-2.0, -0.6]])  # a lightly damped second-order plant, x' = A x + B (u + d)
_B = jnp.array([[0.0], [1.0]])
_C = jnp.array([[1.0, 0.5]])  # C B != 0: Case 1 of Liu & Peng 2002 (relative degree one)
_H = 0.05


def _family(name, plant, L_r):
    """``(estimator, its params, L)`` of one family, designed on ``plant`` (the discretised ``(_A, _B, _C)``)."""
    Q, R = 1e-3 * jnp.eye(2), jnp.array([[1e-2]])
    if name == "kalman":
        return kalman.kalman_filter, kalman.make_kalman(plant.A, plant.C, Q, R, Gamma=plant.B), L_r
    if name == "active":
        aob = active.make_aob(plant, 1, R, q_plant=1e-3, q_active=1e-2)
        return active.active_observer, aob, active.feedback_gain(aob, L_r)
    if name == "hinf":
        return hinf.hinf_filter, hinf.make_hinf(plant.A, plant.C, Q, R, gamma=2.0, Gamma=plant.B), L_r
    if name == "inverse_dynamics":
        params = inverse_dynamics.make_inverse_dynamics(_A, _B, _C, [[4.0], [2.0]], [[3.0]], h=_H, Bu=_B)
        return inverse_dynamics.inverse_dynamics_observer, params, L_r
    K = acker(plant.A.T, plant.C.T, [0.5, 0.6]).T  # a fixed-gain observer by dual pole placement
    return linear.linear_observer, LinearObserver(plant.A, plant.B, plant.C, K), L_r


@pytest.mark.parametrize("name", ["kalman", "active", "hinf", "inverse_dynamics", "linear"])
def test_every_family_is_an_estimator_and_a_controller(name):
    """observer_controller turns each family into a controller: in a closed loop (a step input disturbance, sensor
    noise, a nonzero initial state) it commands u_k = N r_k - L x_hat_k of its own estimate (Cortesão 2006 eq. 49-50,
    with the reference pre-gain N), and that estimate is what the family computes as a plain estimator fed the
    recorded measurements and the commands applied before them (u_{-1} = 0), to rounding."""
    plant = c2d(ss(_A, _B, _C), _H)
    L_r = acker(plant.A, plant.B, [0.85, 0.9])
    N = reference_gain(plant, L_r)
    estimator, params, L = _family(name, plant, L_r)
    T = 80
    r = jnp.ones((T, 1))
    noise = 0.1 * jax.random.normal(jax.random.PRNGKey(0), (T, 1))
    disturbance = jnp.where(jnp.arange(T) >= 20, 0.5, 0.0)
    trace = simulate(plant, observer_controller(estimator), FeedbackParams(params, L, N), r, disturbance=disturbance,
                     noise=noise, x0=jnp.array([0.5, -0.2]))  # fmt: skip
    assert np.all(np.isfinite(trace.x))
    np.testing.assert_allclose(trace.u, r @ N.T - trace.controller.x @ L.T, rtol=1e-12, atol=1e-13)
    u_prev = jnp.concatenate([jnp.zeros((1, 1)), trace.u[:-1]])
    _, out = run(estimator, params, EstimatorInputs(y=trace.y, u_prev=u_prev))
    np.testing.assert_allclose(trace.controller.x, out.x, rtol=1e-12, atol=1e-14)
    for field, ours, theirs in zip(out._fields, out, trace.controller.estimator, strict=True):
        if ours is None:  # optional outputs (the Kalman-type covariances) are off by default
            assert theirs is None, field
            continue
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-14, err_msg=field)
