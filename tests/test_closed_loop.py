"""Closed-loop simulation (seed 000 eq. 20, 43, 47, 59 setting): plant + AOB + state feedback."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.closed_loop import ideal_response, measurement_noise, rms, simulate
from jaxobs.observers import active
from jaxobs.papers.force_control import EXAMPLE1, example1_disturbance, force_plant, nominal_design

H = EXAMPLE1.h


@pytest.fixture(scope="module")
def nominal():
    return nominal_design(EXAMPLE1)


def _numpy_reference(plant, params, r, d, v):
    """Plain NumPy loop of eq. 47 (time-varying K from eq. 27-29, Joseph form) around the plant."""
    A, B, C = (np.asarray(M) for M in (plant.A, plant.B, plant.C))
    Phi, Gam, Ca, L = (np.asarray(M) for M in (params.Phi, params.Gamma, params.C, params.L))
    Q, R = np.asarray(params.Q), np.asarray(params.R)
    x = np.zeros(A.shape[0])
    xh = np.zeros(Phi.shape[0])
    P = np.asarray(params.P0)
    u = np.zeros(1)
    us = []
    for k in range(len(r)):
        y = C @ x + v[k]
        x1 = Phi @ xh + Gam @ u
        P1 = Phi @ P @ Phi.T + Q
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
    params = active.make_aob(plant, L, 2, 0.021, q_active=1e-3)
    r = np.full(T, 1.15)
    d = np.asarray(example1_disturbance(jnp.arange(T) * H + 7.5))
    v = np.asarray(measurement_noise(jax.random.PRNGKey(0), T, 0.021))
    trace = simulate(plant, params, r, disturbance=d, noise=v)
    np.testing.assert_allclose(trace.u[:, 0], _numpy_reference(plant, params, r, d, v), rtol=1e-9, atol=1e-10)


def test_aob_imposes_the_desired_closed_loop_without_disturbance(nominal):
    """Eq. 25/43: without disturbance and noise the loop follows the desired closed loop exactly."""
    plant, L = nominal
    T = 1000  # 25 closed-loop time constants
    r = jnp.full((T,), float(L[0, 0]) * 5.0)
    trace = simulate(plant, active.make_aob(plant, L, 1, 0.021), r)
    np.testing.assert_allclose(trace.y_true[:, 0], ideal_response(plant, L, r)[:, 0], atol=1e-9)
    assert float(trace.y_true[-1, 0]) == pytest.approx(5.0, rel=1e-8)  # unit DC gain with r = L_1 F_d


def test_aob_rejects_constant_input_disturbance(nominal):
    """An active state of order 1 removes the steady-state error of a step input disturbance."""
    plant, L = nominal
    T = 1500
    r = jnp.full((T,), float(L[0, 0]) * 5.0)
    d = jnp.where(jnp.arange(T) > 300, 1.5, 0.0)
    trace = simulate(plant, active.make_aob(plant, L, 1, 0.021, q_active=1e-3), r, disturbance=d)
    assert abs(float(trace.y_true[-1, 0]) - 5.0) < 1e-6
    assert float(trace.controller.p[-1, 0]) == pytest.approx(1.5, rel=1e-6)


def test_vmap_over_mismatched_plants_and_noise_seeds(nominal):
    """Batched over true stiffness and dead time (padded slots) and noise seeds = Python loop."""
    plant, L = nominal
    params = active.make_aob(plant, L, 1, 0.021, q_active=1e-3, steady_state=True)
    T = 200
    r = jnp.full((T,), float(L[0, 0]))
    Ks = jnp.array([1.5, 3.0, 6.0])
    delays = jnp.array([4.0, 5.0, 6.5]) * H
    keys = jax.random.split(jax.random.PRNGKey(2), 3)

    def error(ks, delay, key):
        true = force_plant(ks, EXAMPLE1.Tp, H, delay, n_delay=7)
        noise = measurement_noise(key, T, 0.021)
        return rms(simulate(true, params, r, noise=noise).y_true[:, 0] - 1.0)

    batched = jax.jit(jax.vmap(error))(Ks, delays, keys)
    looped = jnp.array([error(*args) for args in zip(Ks, delays, keys, strict=True)])
    np.testing.assert_allclose(batched, looped, rtol=1e-10)
    assert np.all(np.isfinite(batched))


def test_feedthrough_plant_rejected(nominal):
    plant, L = nominal
    import dataclasses

    bad = dataclasses.replace(plant, D=jnp.ones((1, 1)))
    with pytest.raises(ValueError, match="plant.D"):
        simulate(bad, active.make_aob(plant, L, 1, 0.021), jnp.zeros(5))
