"""Tests for the continuous-time linear observers (jaxobs.observers.ct_linear): Luenberger (Grip 2010 eq. 1.3-1.4),
Kalman-Bucy (eq. 1.7, Riccati differential equation and stationary gain), the output-injection observer (eq. 1.9),
the exosystem augmentation (eq. 1.8) and their sampled runs (as_continuous + continuous_observer).

The pure right-hand sides are checked on the joint plant + observer system integrated by a fixed-step RK4 written
here: the error must follow the linear error dynamics exactly (expm), to RK4's accuracy."""

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from jaxobs.design import place
from jaxobs.observers.base import EstimatorInputs, run
from jaxobs.observers.continuous import continuous_observer
from jaxobs.observers.ct_linear import (
    as_continuous,
    augment,
    luenberger_rate,
    make_kalman_bucy,
    make_luenberger,
    make_output_injection,
    output_injection_rate,
    sinusoid_exosystem,
)


def _rk4(f, state, h, steps):
    add = lambda a, b, s: jax.tree.map(lambda x, y: x + s * y, a, b)

    def step(x, k):
        t = k * h
        k1 = f(t, x)
        k2 = f(t + h / 2, add(x, k1, h / 2))
        k3 = f(t + h / 2, add(x, k2, h / 2))
        k4 = f(t + h, add(x, k3, h))
        return jax.tree.map(lambda x, a, b, c, d: x + h / 6 * (a + 2 * b + 2 * c + d), x, k1, k2, k3, k4), None

    return jax.lax.scan(step, state, jnp.arange(steps))[0]


A = np.array([[0.0, 1.0], [2.0, -0.5]])  # an unstable plant
B, C = np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]])


def test_luenberger_error_follows_a_minus_kc():
    """Plant x' = A x + B u(t), observer (eq. 1.3) from x_hat(0) = 0: x - x_hat = expm((A - K C) t) x(0) (eq. 1.4) to
    1e-12 at t = 3 (2e-14 measured), for any input."""
    K = place(A.T, C.T, [-3.0, -4.0]).T
    params = make_luenberger(A, B, C, K)
    u = lambda t: jnp.array([jnp.sin(3 * t)])

    def f(t, s):
        x, x_hat = s
        return A @ x + B @ u(t), luenberger_rate(params, x_hat, u(t), C @ x, t)

    x0 = np.array([1.0, -0.5])
    x, x_hat = jax.jit(lambda s: _rk4(f, s, 0.001, 3000))((jnp.asarray(x0), jnp.zeros(2)))
    np.testing.assert_allclose(x - x_hat, scipy.linalg.expm((A - K @ C) * 3.0) @ x0, atol=1e-12)


def test_luenberger_rejects_undetectable_pairs_and_unstable_gains():
    """PBH: an unstable mode C does not see raises naming the pair and the eigenvalue; a gain that leaves A - K C
    unstable raises naming K; shapes name their argument."""
    with pytest.raises(ValueError, match=r"^\(C, A\) is not detectable \(PBH\): the mode at eigenvalue 1"):
        make_luenberger(np.diag([1.0, -1.0]), B, [[0.0, 1.0]], [[0.0], [1.0]])
    with pytest.raises(ValueError, match=r"^K must make A - K C Hurwitz"):
        make_luenberger(A, B, C, [[0.0], [0.0]])
    with pytest.raises(ValueError, match=r"^K\b"):
        make_luenberger(A, B, C, np.ones((3, 1)))
    with pytest.raises(ValueError, match=r"^\(C, A\) is not detectable"):
        make_kalman_bucy(np.diag([1.0, -1.0]), B, [[0.0, 1.0]], np.eye(2), np.eye(1))


def test_kalman_bucy_riccati_ode_converges_to_the_stationary_filter():
    """From P0 = 0, the Riccati differential equation of the sampled Kalman-Bucy filter reaches the stationary
    covariance (the filter CARE, care/lqe) to 1e-12 at t = 15 (7e-16 measured); the stationary filter's gain
    equals python-control's lqe (8e-16 measured)."""
    Q, R = np.diag([0.1, 1.0]), np.array([[0.01]])
    stationary = make_kalman_bucy(A, B, C, Q, R, stationary=True)
    L_ctrl, P_ctrl, _ = control.lqe(A, np.eye(2), C, Q, R)
    np.testing.assert_allclose(stationary.K, L_ctrl, rtol=1e-12)
    params = make_kalman_bucy(A, B, C, Q, R, P0=np.zeros((2, 2)))
    filt = as_continuous(params, dt=0.01, substeps=2)
    state, _ = jax.jit(lambda y: run(continuous_observer, filt, EstimatorInputs(y=y, u_prev=np.zeros((1500, 1)))))(
        np.zeros((1500, 1))
    )
    np.testing.assert_allclose(state.x.P, P_ctrl, rtol=1e-12)


def pendulum(y, u):
    """Output-injection terms of the pendulum z1' = z2, z2' = -sin(z1) + u in the form (1.9)."""
    return jnp.stack([jnp.zeros_like(y), -jnp.sin(y) + u[0]])


def test_output_injection_error_dynamics_are_linear():
    """The pendulum in the canonical form (1.9) with gains from the poles -2, -3 (l = (5, 6)): z - z_hat =
    expm([[-5, 1], [-6, 0]] t) (z(0) - z_hat(0)) to 1e-12 at t = 4 (8e-16 measured), although the plant is
    nonlinear."""
    params = make_output_injection(pendulum, 2, poles=[-2.0, -3.0])
    np.testing.assert_allclose(params.l, [5.0, 6.0])
    u = lambda t: jnp.array([0.5 * jnp.cos(t)])

    def f(t, s):
        z, z_hat = s
        return pendulum(z[0], u(t)) + jnp.array([z[1], 0.0]), output_injection_rate(params, z_hat, u(t), z[0], t)

    z0 = np.array([2.5, 0.0])
    z, z_hat = jax.jit(lambda s: _rk4(f, s, 0.001, 4000))((jnp.asarray(z0), jnp.zeros(2)))
    np.testing.assert_allclose(z - z_hat, scipy.linalg.expm(np.array([[-5.0, 1.0], [-6.0, 0.0]]) * 4.0) @ z0,
                               atol=1e-12)  # fmt: skip


def test_exosystem_augmentation_estimates_a_sinusoidal_disturbance():
    """x' = -x + u + d with d = sin(2 t) unknown (eq. 1.8 with a sinusoid exosystem), u = cos(t_k) held over each
    1 ms sample: a Luenberger observer of the augmented system (error poles -3, -4, -5), fed the exact samples of x,
    estimates d to 1e-6 after 8 s (3.5e-7 measured: the linear interpolation of y between samples)."""
    A_w, C_w = sinusoid_exosystem([2.0])
    A_a, B_a, C_a, _ = augment([[-1.0]], [[1.0]], [[1.0]], [[1.0]], A_w, C_w)
    A_a, B_a, C_a = (np.asarray(M) for M in (A_a, B_a, C_a))
    params = make_luenberger(A_a, B_a, C_a, place(A_a.T, C_a.T, [-3.0, -4.0, -5.0]).T)
    dt, T = 0.001, 10000
    block = scipy.linalg.expm(np.block([[A_a, B_a], [np.zeros((1, 4))]]) * dt)
    Phi, Gam = block[:3, :3], block[:3, 3:]
    t = dt * np.arange(T)
    u = np.cos(t)
    z = np.empty((T, 3))
    z[0] = [1.0, 0.0, 1.0]  # x(0) = 1, exosystem state (sin 2t, cos 2t)
    for k in range(1, T):
        z[k] = Phi @ z[k - 1] + Gam[:, 0] * u[k - 1]
    u_prev = np.concatenate([[0.0], u[:-1]])[:, None]
    observer = as_continuous(params, dt=dt, substeps=1)
    _, out = jax.jit(lambda y, u: run(continuous_observer, observer, EstimatorInputs(y=y, u_prev=u)))(z[:, :1], u_prev)
    d_hat = np.asarray(out.x)[:, 1:] @ np.asarray(C_w)[0]
    late = t > 8.0
    np.testing.assert_allclose(z[late, 1], np.sin(2 * t[late]), atol=1e-12)  # the exosystem is the sinusoid
    assert np.max(np.abs(d_hat[late] - np.sin(2 * t[late]))) < 1e-6


def test_sampled_run_missing_measurements_and_vmap():
    """All measurements missing: no injection, the estimate follows the model (x_hat = expm(A t) x0 to RK4
    accuracy) and the innovation is 0; a batch of measurement records under vmap equals one-by-one runs."""
    K = place(A.T, C.T, [-3.0, -4.0]).T
    params = make_luenberger(A, B, C, K, x0=[1.0, 0.0])
    observer = as_continuous(params, dt=0.01)
    go = jax.jit(lambda y: run(continuous_observer, observer, EstimatorInputs(y=y, u_prev=jnp.zeros((200, 1))))[1])
    out = go(np.full((200, 1), np.nan))
    np.testing.assert_allclose(out.x[-1], scipy.linalg.expm(A * 1.99) @ [1.0, 0.0], rtol=1e-9)
    assert np.all(np.asarray(out.innovation) == 0)
    ys = np.random.default_rng(0).normal(size=(3, 200, 1))
    batched = jax.vmap(go)(ys)
    for b in range(3):
        np.testing.assert_allclose(batched.x[b], go(ys[b]).x, rtol=1e-13)


def test_augment_and_output_injection_reject_bad_input():
    A_w, C_w = sinusoid_exosystem([2.0, 5.0])
    assert A_w.shape == (4, 4) and C_w.tolist() == [[1.0, 0.0, 1.0, 0.0]]
    with pytest.raises(ValueError, match=r"^C_w\b"):
        augment([[-1.0]], [[1.0]], [[1.0]], [[1.0]], A_w, np.ones((2, 4)))
    with pytest.raises(ValueError, match=r"^frequencies\b"):
        sinusoid_exosystem([-1.0])
    with pytest.raises(ValueError, match=r"^poles\b"):
        make_output_injection(pendulum, 2, poles=[1.0, -2.0])
    with pytest.raises(ValueError, match=r"^l or poles\b"):
        make_output_injection(pendulum, 2)
    with pytest.raises(ValueError, match=r"^dt\b"):
        as_continuous(make_output_injection(pendulum, 2, l=[5.0, 6.0]), dt=0.0)
    with pytest.raises(ValueError, match=r"^params\b"):
        as_continuous(np.eye(2), dt=0.1)
