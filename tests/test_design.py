"""Tests for jaxobs.design: acker (Cortesão 2006 eq. 45-46, Example 1 eq. 83), place, dlqr, critically_damped_poles,
dc_compensation."""

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from jax.test_util import check_grads
from scipy.optimize import linear_sum_assignment

from jaxobs.design import acker, critically_damped_poles, dc_compensation, dlqe, dlqr, place
from jaxobs.lti import c2d, ctrb, ss
from jaxobs.matrix_equations import dare


def assert_same_spectrum(actual, target, atol):
    """The multisets ``actual`` and ``target`` agree to ``atol`` (optimal pairing, robust to sort order)."""
    actual, target = np.asarray(actual, complex), np.asarray(target, complex)
    assert actual.shape == target.shape
    dist = np.abs(actual[:, None] - target[None, :])
    rows, cols = linear_sum_assignment(dist)
    worst = dist[rows, cols].max()
    assert worst <= atol, f"eigenvalues {np.sort_complex(actual)} differ from {np.sort_complex(target)} by {worst}"


def random_siso(rng, n, max_cond=1e4):
    """A random controllable single-input (Phi, Gamma) with a well-conditioned controllability matrix."""
    while True:
        Phi = rng.normal(size=(n, n)) / np.sqrt(n)
        Gamma = rng.normal(size=(n, 1))
        if np.linalg.cond(np.asarray(ctrb(Phi, Gamma))) < max_cond:
            return Phi, Gamma


def random_poles(rng, n):
    """n well-separated target poles inside the unit circle, with one complex-conjugate pair when n >= 2."""
    if n >= 2:
        r, th = rng.uniform(0.3, 0.8), rng.uniform(0.3, 1.2)
        pair = [r * np.exp(1j * th), r * np.exp(-1j * th)]
        real = list(np.linspace(-0.6, 0.6, n - 2) + rng.uniform(-0.05, 0.05, n - 2)) if n > 2 else []
        return np.array(pair + real, complex)
    return np.array([rng.uniform(-0.8, 0.8)], complex)


# Example 1 (Cortesão 2006 §7): force plant Ks = 3 N/mm, Tp = 32 ms, h = 8 ms, Td = 5h
KS, TP, H = 3.0, 0.032, 0.008


def example1_model():
    plant = ss([[0.0, 1.0], [0.0, -1.0 / TP]], [[0.0], [KS / TP]], [[1.0, 0.0]])
    return c2d(plant, H, 5 * H)


# ---------------------------------------------------------------------------------------------
# acker


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5])
def test_acker_places_poles_on_random_systems(n):
    """Ackermann (Cortesão 2006 eq. 45-46): eig(Phi - Gamma L) equals the target poles to 1e-8."""
    rng = np.random.default_rng(100 + n)
    for _ in range(3):
        Phi, Gamma = random_siso(rng, n)
        poles = random_poles(rng, n)
        L = np.asarray(acker(Phi, Gamma, poles))
        assert L.shape == (1, n)
        assert_same_spectrum(np.linalg.eigvals(Phi - Gamma @ L), poles, atol=1e-8)


def test_acker_matches_python_control():
    """acker equals control.acker on random controllable systems (same formula, independent code)."""
    rng = np.random.default_rng(7)
    for n in (2, 3, 4):
        Phi, Gamma = random_siso(rng, n)
        poles = random_poles(rng, n)
        want = np.atleast_2d(np.asarray(control.acker(Phi, Gamma, poles), float))
        np.testing.assert_allclose(acker(Phi, Gamma, poles), want, rtol=1e-8, atol=1e-10)


def test_acker_example1_gain_cortesao2006_eq83():
    """Cortesão 2006 eq. 83: Example 1 (Td = 5h), double pole at exp(-h / (10 Tp)) and five poles at 0 gives the
    printed L_r = [0.1148, -0.0717, -0.0615, -0.0797, -0.1031, -0.1332, -0.1718] (4 decimals: tolerance 5e-5)."""
    sysd = example1_model()
    poles = critically_damped_poles(H, 10 * TP, 5)
    L = np.asarray(acker(sysd.A, sysd.B, poles))[0]
    printed = np.array([0.1148, -0.0717, -0.0615, -0.0797, -0.1031, -0.1332, -0.1718])
    np.testing.assert_allclose(L, printed, rtol=0, atol=5e-5)
    # the closed loop has the requested characteristic polynomial (its eigenvalues are a 5-fold pole at 0,
    # perturbed by eps^(1/5) ~ 1e-3 in floating point, so compare polynomial coefficients, not eigenvalues)
    Phi, Gamma = np.asarray(sysd.A), np.asarray(sysd.B)
    char = np.poly(Phi - Gamma @ L[None])
    np.testing.assert_allclose(char, np.real(np.poly(np.asarray(poles))), atol=1e-10)


def test_critically_damped_poles_cortesao2006_sec7_2():
    """Cortesão 2006 §7.2: a double pole at exp(-h / tau_c) and n_fast poles at the origin."""
    p = np.asarray(critically_damped_poles(H, 10 * TP, 5))
    z = np.exp(-H / (10 * TP))
    np.testing.assert_allclose(p, [z, z, 0, 0, 0, 0, 0], rtol=1e-15)


def test_acker_jit_vmap_equal_eager():
    """Transformation test: jit(acker) and vmap over a batch of Phi equal eager calls."""
    rng = np.random.default_rng(11)
    n = 4
    Gamma = rng.normal(size=(n, 1))
    Phis = [Phi for Phi in rng.normal(size=(8, n, n)) / 2.0 if np.linalg.cond(np.asarray(ctrb(Phi, Gamma))) < 1e4]
    assert len(Phis) >= 3
    Phis = jnp.asarray(np.stack(Phis[:3]))
    poles = jnp.array([0.1, 0.2, -0.3, 0.5])
    batched = jax.jit(jax.vmap(acker, in_axes=(0, None, None)))(Phis, Gamma, poles)
    vmapped_eager = jax.vmap(acker, in_axes=(0, None, None))(Phis, Gamma, poles)
    jitted = jax.jit(acker)
    for i in range(Phis.shape[0]):
        eager = acker(Phis[i], Gamma, poles)
        np.testing.assert_allclose(jitted(Phis[i], Gamma, poles), eager, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(batched[i], eager, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(vmapped_eager[i], eager, rtol=1e-10, atol=1e-12)


def test_acker_grad_wrt_pole_location():
    """acker is differentiable in a pole location: jax.test_util.check_grads (fwd and rev, order 1)."""
    rng = np.random.default_rng(12)
    Phi, Gamma = random_siso(rng, 3)
    others = jnp.array([0.2, -0.4])

    def gain(p):
        return acker(Phi, Gamma, jnp.concatenate([jnp.atleast_1d(p), others]))[0]

    check_grads(gain, (0.5,), order=1, modes=("fwd", "rev"))
    check_grads(lambda p: acker(Phi, Gamma, p)[0], (jnp.array([0.5, 0.2, -0.4]),), order=1, modes=("rev",))


def test_acker_rejects_bad_input():
    """Uncontrollable pair, wrong number of poles, non-square Phi, NaN in Phi, unpaired complex poles ->
    ValueError naming the argument."""
    Phi = np.diag([0.5, 0.9])
    with pytest.raises(ValueError, match="Phi, Gamma"):
        acker(Phi, np.array([[1.0], [0.0]]), [0.1, 0.2])  # second mode not actuated
    with pytest.raises(ValueError, match="poles"):
        acker(Phi, np.ones((2, 1)), [0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="Phi"):
        acker(np.ones((2, 3)), np.ones((2, 1)), [0.1, 0.2])
    with pytest.raises(ValueError, match="Phi"):
        acker(np.array([[np.nan, 0.0], [0.0, 1.0]]), np.ones((2, 1)), [0.1, 0.2])
    with pytest.raises(ValueError, match="Gamma"):
        acker(Phi, np.ones((3, 1)), [0.1, 0.2])
    with pytest.raises(ValueError, match="poles"):
        acker(Phi, np.ones((2, 1)), [0.1 + 0.2j, 0.3])


# ---------------------------------------------------------------------------------------------
# place


def test_place_random_mimo_system():
    """place (SciPy place_poles) on a random 4-state, 2-input system: eig(Phi - Gamma L) equals the targets."""
    rng = np.random.default_rng(21)
    Phi, Gamma = rng.normal(size=(4, 4)), rng.normal(size=(4, 2))
    poles = np.array([0.1, 0.3, -0.2, 0.5])
    L = place(Phi, Gamma, poles)
    assert L.shape == (2, 4)
    assert_same_spectrum(np.linalg.eigvals(Phi - Gamma @ L), poles, atol=1e-8)
    L_k = place(Phi, Gamma, poles, method="KNV0")
    assert_same_spectrum(np.linalg.eigvals(Phi - Gamma @ L_k), poles, atol=1e-8)
    complex_poles = np.array([0.2 + 0.3j, 0.2 - 0.3j, 0.1, -0.4])
    L_c = place(Phi, Gamma, complex_poles)
    assert_same_spectrum(np.linalg.eigvals(Phi - Gamma @ L_c), complex_poles, atol=1e-8)


def test_place_zero_input_columns_cortesao2006_sec8_4():
    """Cortesão 2006 §8.4: inputs listed in zero_input_columns are left out of the design; their rows of L are zero
    and the remaining inputs still place every pole (MIMO path and the single-input/acker path)."""
    rng = np.random.default_rng(22)
    Phi, Gamma = rng.normal(size=(4, 4)), rng.normal(size=(4, 3))
    poles = np.array([0.1, 0.3, -0.2, 0.5])
    L = place(Phi, Gamma, poles, zero_input_columns=(1,))
    assert L.shape == (3, 4)
    np.testing.assert_array_equal(L[1], 0.0)
    assert_same_spectrum(np.linalg.eigvals(Phi - Gamma @ L), poles, atol=1e-8)
    L1 = place(Phi, Gamma, poles, zero_input_columns=(0, 2))
    np.testing.assert_array_equal(L1[[0, 2]], 0.0)
    np.testing.assert_allclose(L1[1:2], acker(Phi, Gamma[:, 1:2], poles), rtol=1e-12)
    assert_same_spectrum(np.linalg.eigvals(Phi - Gamma @ L1), poles, atol=1e-8)


def test_place_rejects_bad_input():
    """place: pole count, out-of-range zero column, uncontrollable actuated pair -> ValueError."""
    Phi, Gamma = np.diag([0.5, 0.9, 0.1]), np.eye(3)[:, :2]
    with pytest.raises(ValueError, match="poles"):
        place(Phi, np.eye(3), [0.1, 0.2])
    with pytest.raises(ValueError, match="zero_input_columns"):
        place(Phi, np.eye(3), [0.1, 0.2, 0.3], zero_input_columns=(5,))
    with pytest.raises(ValueError, match="controllable"):
        place(Phi, Gamma, [0.1, 0.2, 0.3])


# ---------------------------------------------------------------------------------------------
# dlqr


def test_dlqr_matches_python_control_and_scipy():
    """dlqr returns what control.dlqr returns: K = (B'SB + R)^{-1} B'SA, S the control DARE solution (as
    scipy.linalg.solve_discrete_are) and the closed-loop eigenvalues E of A - B K."""
    rng = np.random.default_rng(31)
    A, B = 1.1 * rng.normal(size=(4, 4)) / 2.0, rng.normal(size=(4, 2))
    G = rng.normal(size=(4, 4))
    Q, R = G @ G.T + 0.1 * np.eye(4), np.array([[2.0, 0.3], [0.3, 1.0]])
    K, S, E = dlqr(A, B, Q, R)
    S_ref = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K_ctrl, S_ctrl, E_ctrl = control.dlqr(A, B, Q, R)
    np.testing.assert_allclose(S, S_ref, rtol=1e-9)
    np.testing.assert_allclose(S, S_ctrl, rtol=1e-9)
    np.testing.assert_allclose(K, K_ctrl, rtol=1e-9, atol=1e-12)
    assert_same_spectrum(E, E_ctrl, atol=1e-8)
    sol = dare(A, B, Q, R)  # the control DARE itself, as SciPy's
    assert bool(sol.converged)
    np.testing.assert_allclose(sol.X, S_ref, rtol=1e-9)


def test_dlqe_matches_python_control():
    """dlqe returns what control.dlqe returns: the predictor gain A P C' (C P C' + RN)^{-1}, the a-priori covariance
    P (the filter DARE of (A, C) with process noise G QN G') and the eigenvalues of A - K C."""
    rng = np.random.default_rng(32)
    A, G, C = 1.1 * rng.normal(size=(4, 4)) / 2.0, rng.normal(size=(4, 2)), rng.normal(size=(2, 4))
    QN, RN = np.array([[1.0, 0.2], [0.2, 0.5]]), np.array([[0.3, 0.1], [0.1, 0.2]])
    K, P, E = dlqe(A, G, C, QN, RN)
    K_ctrl, P_ctrl, E_ctrl = control.dlqe(A, G, C, QN, RN)
    np.testing.assert_allclose(P, P_ctrl, rtol=1e-9)
    np.testing.assert_allclose(K, K_ctrl, rtol=1e-9, atol=1e-12)
    assert_same_spectrum(E, E_ctrl, atol=1e-8)


def test_dlqr_and_dlqe_raise_eagerly_and_give_nan_under_jit_when_no_stabilising_solution():
    """An unstable mode the input cannot move (A = diag(1.2, 0.5), B = [0, 1]'): dlqr raises naming (A, B); under
    jit its gain and S are NaN. The dual for dlqe: a mode C cannot see."""
    A, B, Q, R = np.diag([1.2, 0.5]), np.array([[0.0], [1.0]]), np.eye(2), np.eye(1)
    with pytest.raises(ValueError, match=r"^dlqr's DARE did not converge: .*\(A, B\) is not stabilisable"):
        dlqr(A, B, Q, R)
    K, S, _ = jax.jit(dlqr)(A, B, Q, R)
    assert np.all(np.isnan(K)) and np.all(np.isnan(S))
    with pytest.raises(ValueError, match=r"^dlqe's DARE did not converge: .*not detectable"):
        dlqe(A, np.eye(2), B.T, Q, R)
    K, P, _ = jax.jit(dlqe)(A, np.eye(2), B.T, Q, R)
    assert np.all(np.isnan(K)) and np.all(np.isnan(P))


# ---------------------------------------------------------------------------------------------
# dc_compensation


def test_dc_compensation_cortesao2006_eq102_104():
    """Cortesão 2006 eq. 102-104: L_c = DC_closed^{-1} DC_target, so DC_closed L_c = DC_target; a singular closed-loop
    DC gain -> ValueError naming dc_closed_loop."""
    M = np.array([[2.0, 0.5], [0.1, 1.5]])
    T = np.array([[1.0, 0.2], [0.0, 1.0]])
    Lc = np.asarray(dc_compensation(T, M))
    np.testing.assert_allclose(M @ Lc, T, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(dc_compensation(2.0, 4.0), [[0.5]], rtol=1e-15)
    with pytest.raises(ValueError, match="dc_closed_loop"):
        dc_compensation(T, np.array([[1.0, 2.0], [2.0, 4.0]]))
