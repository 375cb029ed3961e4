"""Liu & Peng 2002 inverse-dynamics observer: Lemmas 3.1-3.6, Fact 3.5, §4.1 eq. 28-30."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.linalg
from jax.test_util import check_grads

from jaxobs.lti import c2d, ss
from jaxobs.observers import inverse_dynamics as ido
from jaxobs.observers.base import EstimatorInputs, run

# §4.2 printed a_i, used here only as a concrete §4.1 plant (eq. 28)
A1, A2, A3, A4 = -9.754, -14.03, 0.5901, -12.622


def siso(a1=A1, a2=A2, a3=A3, a4=A4):
    """Eq. 28: x' = [[a1, a2], [a3, a4]] x + [1, 0]' d, y = x2."""
    return np.array([[a1, a2], [a3, a4]]), np.array([[1.0], [0.0]]), np.array([[0.0, 1.0]])


def case1_plant():
    """Relative degree one (C B = 1), zeros of s^2 + 7 s + 10 at -2, -5, poles of (s + 1)(s^2 + s + 4)."""
    den = np.polymul([1, 1], [1, 1, 4])  # s^3 + 2 s^2 + 5 s + 4
    A = np.array([[0, 1, 0], [0, 0, 1], [-den[3], -den[2], -den[1]]], float)
    return A, np.array([[0.0], [0.0], [1.0]]), np.array([[10.0, 7.0, 1.0]])


def paper_basis(F2, rho):
    """The explicit SVD bases of §4.1 (printed U and V)."""
    f = F2 - rho
    s = np.sqrt(f**2 + 1)
    return np.array([[f, 1], [1, -f]]) / s, np.array([[0.0, 1.0], [1.0, 0.0]])


def simulate(params, A, B, C, d, x0, h):
    """Exact ZOH plant (d held over each sample, no known term Gamma) and the observer; returns (x, outputs)."""
    plant = c2d(ss(A, B, C), h)

    def body(x, dk):
        return plant.A @ x + plant.B @ dk, x

    _, xs = jax.lax.scan(body, jnp.asarray(x0, float), jnp.asarray(d))
    _, out = run(ido.inverse_dynamics_observer, params, EstimatorInputs(y=xs @ C.T))
    return xs, out


def decay_rate(t, err, lo, hi):
    m = (t >= lo) & (t <= hi)
    return np.polyfit(t[m], np.log(err[m]), 1)[0]


# ------------------------------------------------------------------------------------------ §4.1


def test_siso_gains_and_error_matrices_match_section_4_1():
    """§4.1: B+ = [1 rho], G1 = -[a1 + rho a3, F1 + a2 + rho a4], G2 = [1, rho - F2], G3 = [-1, -rho];
    M_e = [[0, F2 - rho], [0, 1]], A_e = [[-rho a3, -k1 - rho a4 - F1], [a3, a4 - k2]] (eq. 12-18), and
    U' A_e V as printed. Exact to 1e-12."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        a1, a2, a3, a4, F1, F2, rho, k1, k2 = rng.normal(size=9) * 3
        A, B, C = siso(a1, a2, a3, a4)
        K = np.array([[k1], [k2]])
        G1, G2, G3 = ido.case2_gains(A, B, C, F1, F2, np.array([[0.0, rho]]))
        np.testing.assert_allclose(ido.left_inverse(B, [[0.0, rho]]), [[1, rho]], atol=1e-12)
        np.testing.assert_allclose(G1, [[-(a1 + rho * a3), -(F1 + a2 + rho * a4)]], atol=1e-12)
        np.testing.assert_allclose(G2, [[1, rho - F2]], atol=1e-12)
        np.testing.assert_allclose(G3, [[-1, -rho]], atol=1e-12)
        M_e, A_e = ido.error_dynamics(A, B, C, K, G1, G2)
        np.testing.assert_allclose(M_e, [[0, F2 - rho], [0, 1]], atol=1e-12)
        np.testing.assert_allclose(A_e, [[-rho * a3, -k1 - rho * a4 - F1], [a3, a4 - k2]], atol=1e-12)
        U, V = paper_basis(F2, rho)
        f, s = F2 - rho, np.sqrt((F2 - rho) ** 2 + 1)
        np.testing.assert_allclose(U @ np.diag([s, 0]) @ V.T, M_e, atol=1e-12)
        printed = np.array(
            [
                [-f * (k1 + rho * a4 + F1) + a4 - k2, a3 - rho * a3 * f],
                [-k1 - F1 - F2 * a4 + F2 * k2 - rho * k2, -a3 * F2],
            ]
        )
        np.testing.assert_allclose(U.T @ np.asarray(A_e) @ V, printed / s, atol=1e-10)


def eq30(a3, F1, F2, rho, k1, k2):
    return (
        rho**3 * (a3 * k2)
        + rho**2 * (a3 * k1 + a3 * F1 - 2 * a3 * F2 * k2)
        + rho * (F2**2 * a3 * k2 - 2 * a3 * F2 * k1 - 2 * a3 * F1 * F2 + a3 * k2)
        + (a3 * k1 + a3 * F1 + a3 * F2**2 * k1 + a3 * F1 * F2**2)
    )


def test_eq29_30_against_eigenvalues():
    """§4.1 eq. 29-30 vs direct eigenvalues, 400 random (a_i, K, F1, F2, rho):
    (a) with the printed U, V, Fact 3.5 as printed (A22, S Hurwitz) <=> eq. 29 and eq. 30;
    (b) the Fact 3.4 matrix [[sigma^-1 A11, sigma^-1 A12], [A21/eps, A22/eps]] (eps = 1e-6) is Hurwitz <=> eq. 29, 30;
    (c) the finite pole of M_e e' = A_e e (scipy eigvals(A_e, M_e)) is < 0 <=> a3 F2 * (eq. 30 LHS) > 0, which is
        weaker than eq. 29-30: eq. 29 (A22 Hurwitz) is not necessary for the descriptor system itself;
    (d) rho = 0: the pole is -(k1 + F1) / F2 (§4.2 text), and eq. 29-30 reduce to a3 F2 > 0, (k1 + F1) / F2 > 0."""
    rng = np.random.default_rng(1)
    n_printed = n_exact = n_gap = 0
    for i in range(400):
        a1, a2, a3, a4, F1, F2, k1, k2 = rng.normal(size=8) * 3
        rho = 0.0 if i % 4 == 0 else rng.normal() * 2
        A, B, C = siso(a1, a2, a3, a4)
        K = np.array([[k1], [k2]])
        M_e, A_e = ido.error_dynamics(A, B, C, K, *ido.case2_gains(A, B, C, F1, F2, [[0.0, rho]])[:2])
        cond29, p30 = a3 * F2 > 0, eq30(a3, F1, F2, rho, k1, k2)
        U, V = paper_basis(F2, rho)
        res = ido.fact35(M_e, A_e, U=U, V=V)
        assert res.rank == 1
        assert bool(res.printed_stable) == (cond29 and p30 > 0)
        T = U.T @ np.asarray(A_e) @ V
        sig = np.sqrt((F2 - rho) ** 2 + 1)
        eps = 1e-6
        reg = np.array([[T[0, 0] / sig, T[0, 1] / sig], [T[1, 0] / eps, T[1, 1] / eps]])
        margin = abs(p30) > 1e-6 * (1 + abs(a3) * (1 + abs(rho)) ** 3 * 30)
        if margin:
            assert (np.linalg.eigvals(reg).real.max() < 0) == (cond29 and p30 > 0)
        w = scipy.linalg.eigvals(np.asarray(A_e), np.asarray(M_e))
        pole = w[np.isfinite(w)]
        assert pole.size == 1
        np.testing.assert_allclose(res.poles, pole, rtol=1e-9, atol=1e-9)
        assert (pole.real[0] < 0) == (a3 * F2 * p30 > 0) or not margin
        assert bool(res.stable) == (pole.real[0] < 0)
        assert bool(ido.fact35(M_e, A_e).stable) == bool(res.stable)  # the exact flag ignores the basis
        if rho == 0.0:
            np.testing.assert_allclose(pole.real[0], -(k1 + F1) / F2, rtol=1e-9)
            assert (cond29 and p30 > 0) == (cond29 and (k1 + F1) / F2 > 0)
        n_printed += cond29 and p30 > 0
        n_exact += pole.real[0] < 0
        n_gap += (pole.real[0] < 0) and not (cond29 and p30 > 0)
    assert n_printed > 50 and n_gap > 50 and n_exact == n_printed + n_gap


def test_fact35_printed_condition_gap_when_rank_above_one():
    """Fact 3.5 as printed omits sigma_M^{-1}: M_e = diag(10, 1, 0) with S = [[-2, 1], [-3, 1]] (Hurwitz) and
    A22 = -1, but sigma^{-1} S = [[-0.2, 0.1], [-3, 1]] has trace 0.8 > 0, so M_e e' = A_e e is unstable.
    Also, flipping the null-space column of U flips A22's sign (the printed A22 test is basis dependent)."""
    M_e = np.diag([10.0, 1.0, 0.0])
    A_e = np.array([[-2.0, 1.0, 0.0], [-3.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    res = ido.fact35(M_e, A_e)
    assert res.rank == 2 and bool(res.printed_stable) and not bool(res.stable)
    w = scipy.linalg.eigvals(A_e, M_e)
    np.testing.assert_allclose(np.sort_complex(w[np.isfinite(w)]), np.sort_complex(np.asarray(res.poles)), atol=1e-12)
    U, V = np.eye(3), np.eye(3)
    assert bool(ido.fact35(M_e, A_e, U=U, V=V).printed_stable)
    U[2, 2] = -1.0
    flipped = ido.fact35(M_e, A_e, U=U, V=V)
    assert not bool(flipped.printed_stable) and not bool(flipped.stable)


# ---------------------------------------------------------------------------------- Lemmas 3.1-3.6


def test_lemma_3_2_plant_zeros_are_error_poles_case1():
    """Lemma 3.2: the zeros of (A, B, C, 0) (-2, -5 here) are eigenvalues of A - B(F1 C + F2 C A) - K C (eq. 8)
    for any F1, K; also for random relative-degree-one plants. Distance < 1e-7."""
    rng = np.random.default_rng(2)
    A, B, C = case1_plant()
    np.testing.assert_allclose(np.sort(ido.plant_zeros(A, B, C).real), [-5, -2], atol=1e-9)
    plants = [(A, B, C)] + [tuple(rng.normal(size=s) for s in ((4, 4), (4, 1), (1, 4))) for _ in range(5)]
    for A_, B_, C_ in plants:
        F2 = ido.case1_f2(B_, C_)
        for _ in range(5):
            F1, K = rng.normal(size=(1, 1)) * 5, rng.normal(size=(A_.shape[0], 1)) * 5
            M_e, A_e = ido.error_dynamics(A_, B_, C_, K, *ido.case1_gains(A_, B_, C_, F1, F2)[:2])
            np.testing.assert_allclose(M_e, np.eye(A_.shape[0]), atol=1e-12)
            eig = np.linalg.eigvals(np.asarray(A_e))
            for z in ido.plant_zeros(A_, B_, C_):
                assert np.min(np.abs(eig - z)) < 1e-7 * (1 + abs(z))


def test_lemma_3_6_nonsingular_M_e():
    """Lemma 3.6: with M_e nonsingular the zeros are eigenvalues of M_e^{-1} A_e. det M_e = det(F2 C B) (B+ B = I),
    so M_e is nonsingular only for plants that meet the Case 1 rank condition; a Case 2 design on the Case 1 plant."""
    rng = np.random.default_rng(3)
    A, B, C = case1_plant()
    for _ in range(10):
        F1, F2 = rng.normal(size=(1, 1)) * 3, rng.normal(size=(1, 1)) * 3
        rho, K = rng.normal(size=(1, 3)), rng.normal(size=(3, 1)) * 5
        M_e, A_e = ido.error_dynamics(A, B, C, K, *ido.case2_gains(A, B, C, F1, F2, rho)[:2])
        np.testing.assert_allclose(np.linalg.det(M_e), np.linalg.det(F2 @ C @ B), rtol=1e-9)
        eig = np.linalg.eigvals(np.linalg.solve(M_e, A_e))
        for z in (-2.0, -5.0):
            assert np.min(np.abs(eig - z)) < 1e-7
    # on the relative-degree-two plant of §4.1, M_e is singular whatever F2 and rho
    A, B, C = siso()
    M_e, _ = ido.error_dynamics(A, B, C, np.ones((2, 1)), *ido.case2_gains(A, B, C, 1.0, 2.0, [[0.3, 0.7]])[:2])
    assert abs(np.linalg.det(M_e)) < 1e-12


def test_lemma_3_1_errors_decay_at_predicted_rate():
    """Lemma 3.1 by simulation (h = 1 ms, exact ZOH plant, d = 1 + sin 3t + 0.5 sin 7t unknown to the observer):
    eq. 8 poles are {-2, -5 (plant zeros), p3}; with p3 = -8 the fitted decay of |e| over 1.5-3.5 s (after the
    non-normal transient) is -2 +- 3 %,
    e_d follows eq. 7 (e_d = -(F1 C + F2 C A) e) to 2e-2, and the late errors sit at the O(h) floor."""
    A, B, C = case1_plant()
    K = np.array([[0.0], [0.0], [3.0]])
    F2 = ido.case1_f2(B, C)
    # third pole: choose F1 so that trace(A_e) = -(2 + 5 + 8)
    G1, *_ = ido.case1_gains(A, B, C, 0.0, F2)
    tr0 = np.trace(A - K @ C + B @ np.asarray(G1))
    F1 = np.array([[(tr0 + 15.0) / (C @ B).item()]])
    params = ido.make_inverse_dynamics(A, B, C, K, F1, h=1e-3)
    M_e, A_e = ido.error_dynamics(A, B, C, K, params.G1, params.G2)
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(A_e).real), [-8, -5, -2], atol=1e-8)
    t = np.arange(4000) * 1e-3
    d = (1 + np.sin(3 * t) + 0.5 * np.sin(7 * t))[:, None]
    xs, out = simulate(params, A, B, C, d, [1.0, -1.0, 2.0], 1e-3)
    e = np.asarray(out.x - xs)
    err = np.linalg.norm(e, axis=1)
    assert decay_rate(t, err, 1.5, 3.5) == pytest.approx(-2.0, rel=0.03)
    e_d = np.asarray(out.d) - d
    pred = -(np.asarray(F1) @ C + F2 @ C @ A) @ e.T
    sl = slice(100, None)
    assert np.max(np.abs(e_d[sl, 0] - pred[0, sl])) < 2e-2 * np.max(np.abs(pred[0, sl]))
    assert err[-1] < 2e-3 * err[0] and np.max(np.abs(e_d[-500:])) < 0.02


@pytest.mark.parametrize("h", [1e-2, 1e-3])
def test_lemma_3_3_siso_errors_decay_at_predicted_rate(h):
    """Lemma 3.3 / §4.1 plant with K = [47, 10], F1 = -10, F2 = 1, rho = 0 (the §4.2 gains): one finite pole
    -(k1 + F1)/F2 = -37 (§4.2 text). Discrete (backward Euler) rate log(1/(1 + 37 h))/h: -31.5 at 100 Hz (the
    paper's rate), -36.3 at 1 kHz; fitted to 2 %. Plant at rest, d = 0.2 sin 3t, observer started at [2, 0.5].

    Erratum: eq. 16 row 2 gives a3 e1 = e2' - (a4 - k2) e2, so e1/e2 = -[k1 + F1 + F2 (a4 - k2)]/(F2 a3) = -24.37;
    the §4.2 text prints it without the minus sign (+24.37). Checked at t = 0.05 s to 1 %."""
    A, B, C = siso()
    K = np.array([[47.0], [10.0]])
    params = ido.make_inverse_dynamics(A, B, C, K, -10.0, 1.0, h=h, case=2, x0=[2.0, 0.5])
    t = np.arange(int(0.6 / h)) * h
    d = (0.2 * np.sin(3 * t))[:, None]
    xs, out = simulate(params, A, B, C, d, [0.0, 0.0], h)
    e = np.asarray(out.x - xs)
    err = np.abs(e[:, 1])
    rate = np.log(1 / (1 + 37 * h)) / h
    assert decay_rate(t, err, 0.02, 0.2) == pytest.approx(rate, rel=0.02)
    printed = (47 - 10 + (A4 - 10)) / A3
    k = int(round(0.05 / h))
    assert e[k, 0] / e[k, 1] == pytest.approx(-printed, rel=0.01)
    # forced error floor (O(h) from the backward differences) once the transient is gone
    assert np.max(np.abs(e[-int(0.1 / h) :])) < 0.1 * h
    assert np.max(np.abs(np.asarray(out.d)[-int(0.1 / h) :] - d[-int(0.1 / h) :])) < 0.5 * h / 1e-2


def test_lemma_3_3_with_rho():
    """Case 2 with rho = 0.5 on the §4.1 plant: the fitted decay matches the pole from fact35 to 3 % (h = 1 ms)."""
    A, B, C = siso()
    K = np.array([[20.0], [5.0]])
    rho = np.array([[0.0, 0.5]])
    params = ido.make_inverse_dynamics(A, B, C, K, 5.0, 2.0, h=1e-3, case=2, rho=rho)
    res = ido.fact35(*ido.error_dynamics(A, B, C, K, params.G1, params.G2))
    lam = float(np.asarray(res.poles).real[0])
    assert bool(res.stable) and lam < -1
    t = np.arange(int(6 / -lam / 1e-3)) * 1e-3
    d = np.full((t.size, 1), 0.4)
    xs, out = simulate(params, A, B, C, d, [1.0, -0.5], 1e-3)
    err = np.linalg.norm(np.asarray(out.x - xs), axis=1)
    assert decay_rate(t, err, 0.5 / -lam, 4 / -lam) == pytest.approx(lam, rel=0.03)


def test_lowpass_and_constant_disturbance_steady_state():
    """Constant d and Gamma: with a 5-section low-pass (pole 0.9) on y the steady state is exact (d_hat = d, x_hat = x
    to 1e-8), since the filter has unit DC gain and the backward-Euler fixed point solves A_e x + N w = 0. Gamma's
    value is the input (Bu = I)."""
    A, B, C = siso()
    K = np.array([[47.0], [10.0]])
    params = ido.make_inverse_dynamics(A, B, C, K, -10.0, 1.0, h=1e-2, Bu=np.eye(2), case=2, lowpass_pole=0.9,
                                       lowpass_order=5)  # fmt: skip
    T = 800
    gamma = jnp.tile(jnp.array([0.3, -0.2]), (T, 1))
    # plant with Gamma: x' = A x + Gamma + B d = A x + [B I] [d; Gamma]
    Bg = np.hstack([B, np.eye(2)])
    dg = np.hstack([np.full((T, 1), 0.7), np.asarray(gamma)])
    plant = c2d(ss(A, Bg, C), 1e-2)
    xs = [np.zeros(2)]
    for k in range(T - 1):
        xs.append(np.asarray(plant.A) @ xs[-1] + np.asarray(plant.B) @ dg[k])
    xs = np.array(xs)
    _, out = run(ido.inverse_dynamics_observer, params, EstimatorInputs(y=jnp.asarray(xs @ C.T), u_prev=gamma))
    np.testing.assert_allclose(out.d[-1], [0.7], atol=1e-8)
    np.testing.assert_allclose(out.x[-1], xs[-1], atol=1e-8)


def test_known_term_is_bu_times_u_prev():
    """Gamma(u, y) = Bu u_prev: an input through Bu (2 x 1) gives what its value Bu u_prev given with Bu = I gives;
    the innovation output is y_k - C x_hat_k."""
    A, B, C, ys, _ = _sequences(T=50)
    K, Bu = np.array([[47.0], [10.0]]), np.array([[0.4], [-1.3]])
    u = jnp.asarray(np.random.default_rng(4).normal(size=(50, 1)))
    through_bu = ido.make_inverse_dynamics(A, B, C, K, -10.0, 1.0, h=1e-2, Bu=Bu, case=2)
    as_value = ido.make_inverse_dynamics(A, B, C, K, -10.0, 1.0, h=1e-2, Bu=np.eye(2), case=2)
    _, a = run(ido.inverse_dynamics_observer, through_bu, EstimatorInputs(y=ys, u_prev=u))
    _, b = run(ido.inverse_dynamics_observer, as_value, EstimatorInputs(y=ys, u_prev=u @ Bu.T))
    _, without = run(ido.inverse_dynamics_observer, through_bu, EstimatorInputs(y=ys))
    np.testing.assert_allclose(a.x, b.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.d, b.d, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.innovation, ys - a.x @ C.T, rtol=1e-12, atol=1e-12)  # y_k - C x_hat_k
    assert np.max(np.abs(np.asarray(a.x - without.x))) > 1e-3  # the input does act


# -------------------------------------------------------------------------------------- transforms


def _sequences(T=200, h=1e-2):
    A, B, C = siso()
    t = np.arange(T) * h
    d = (0.3 + 0.2 * np.sin(3 * t))[:, None]
    plant = c2d(ss(A, B, C), h)
    xs = [np.array([1.0, 0.2])]
    for k in range(T - 1):
        xs.append(np.asarray(plant.A) @ xs[-1] + np.asarray(plant.B) @ d[k])
    return A, B, C, jnp.asarray(np.array(xs) @ C.T), d


@pytest.mark.slow
def test_eager_jit_vmap_agree():
    """step/run eagerly, under jit, and vmap over (K, sequences) vs a Python loop agree to 1e-12."""
    A, B, C, ys, _ = _sequences()
    Ks = [np.array([[47.0], [10.0]]), np.array([[30.0], [2.0]]), np.array([[60.0], [-5.0]])]
    plist = [ido.make_inverse_dynamics(A, B, C, K, -10.0, 1.0, h=1e-2, case=2) for K in Ks]
    inputs = EstimatorInputs(y=ys)
    obs = ido.inverse_dynamics_observer
    eager = [run(obs, p, inputs)[1] for p in plist]
    run_jit = jax.jit(lambda p, i: run(obs, p, i))
    jitted = [run_jit(p, inputs)[1] for p in plist]
    batched_p = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *plist)
    ys_b = jnp.stack([ys, 1.1 * ys, 0.9 * ys])
    batched = jax.vmap(lambda p, y: run(obs, p, EstimatorInputs(y=y))[1])(batched_p, ys_b)
    for i, p in enumerate(plist):
        np.testing.assert_allclose(jitted[i].x, eager[i].x, atol=1e-12)
        np.testing.assert_allclose(jitted[i].d, eager[i].d, atol=1e-12)
        looped = run(obs, p, EstimatorInputs(y=ys_b[i]))[1]
        np.testing.assert_allclose(batched.x[i], looped.x, atol=1e-12)
        np.testing.assert_allclose(batched.d[i], looped.d, atol=1e-12)
    # one step eagerly vs jit
    s0 = obs.init(plist[0])
    a = obs.step(plist[0], s0, EstimatorInputs(y=ys[0]))
    b = jax.jit(obs.step)(plist[0], s0, EstimatorInputs(y=ys[0]))
    np.testing.assert_allclose(a[1].x, b[1].x, atol=1e-14)


@pytest.mark.slow
def test_fact35_traced_flags_and_grads():
    """fact35 with a static rank under jit/vmap gives the eager flags; the disturbance-estimation loss is
    differentiable in (F1, F2, rho) through make_inverse_dynamics (check_grads, order 1)."""
    A, B, C, ys, d = _sequences(T=40)
    K = np.array([[47.0], [10.0]])

    def flags(F1):
        M_e, A_e = ido.error_dynamics(A, B, C, K, *ido.case2_gains(A, B, C, F1, 1.0)[:2])
        r = ido.fact35(M_e, A_e, rank=1)
        return r.stable, r.poles.real[0]

    F1s = jnp.array([-10.0, -60.0, 0.0])
    stable, poles = jax.jit(jax.vmap(flags))(F1s)
    np.testing.assert_array_equal(stable, [True, False, True])
    np.testing.assert_allclose(poles, -(47 + F1s), rtol=1e-10)

    def loss(F1, F2, rho):
        p = ido.make_inverse_dynamics(A, B, C, K, F1, F2, h=1e-2, case=2, rho=jnp.stack([0.0, rho])[None])
        _, out = run(ido.inverse_dynamics_observer, p, EstimatorInputs(y=ys))
        return jnp.mean((out.d[10:] - d[10:]) ** 2)

    check_grads(loss, (-10.0, 1.0, 0.2), order=1, modes=["rev"], atol=1e-5, rtol=1e-4)
    assert np.all(np.isfinite(jax.grad(loss, argnums=(0, 1, 2))(-10.0, 1.0, 0.2)))


# -------------------------------------------------------------------------------------- bad inputs


def test_bad_inputs_raise_clear_errors():
    A, B, C = siso()
    K = np.array([[47.0], [10.0]])
    with pytest.raises(ValueError, match="B must have full column rank"):
        ido.make_inverse_dynamics(np.eye(3), np.zeros((3, 1)), np.eye(3)[:1], np.ones((3, 1)), 0.0, 1.0, h=0.01)
    with pytest.raises(ValueError, match=r"\(A, C\) must be observable"):
        ido.make_inverse_dynamics(*siso(a3=0.0), K, -10.0, 1.0, h=0.01, case=2)
    with pytest.raises(ValueError, match="no F2 satisfies F2 C B = I.*case=2"):
        ido.make_inverse_dynamics(A, B, C, K, -10.0, h=0.01, case=1)
    with pytest.raises(ValueError, match="F2 must satisfy F2 C B = I"):
        ido.make_inverse_dynamics(*case1_plant(), np.ones((3, 1)), 0.0, 2.0, h=0.01, case=1)
    # singular M_e with an unstable slow subsystem: k1 + F1 < 0 with F2 > 0
    with pytest.raises(ValueError, match="not exponentially stable.*Fact 3.5"):
        ido.make_inverse_dynamics(A, B, C, K, -60.0, 1.0, h=0.01, case=2)
    # F2 = rho = 0 makes A22 = 0: the descriptor system is not regular
    with pytest.raises(ValueError, match="A22 is singular"):
        ido.make_inverse_dynamics(A, B, C, K, -10.0, 0.0, h=0.01, case=2)
    # non-minimum-phase Case 1 plant: the zero at +1 is a pole of eq. 8 whatever K, F1 (Lemma 3.2)
    Anm, Bnm, _ = case1_plant()
    with pytest.raises(ValueError, match="not Hurwitz.*Lemma 3.2"):
        ido.make_inverse_dynamics(Anm, Bnm, np.array([[-2.0, 1.0, 1.0]]), np.ones((3, 1)), 50.0, h=0.01)
    with pytest.raises(ValueError, match="lowpass_pole"):
        ido.make_inverse_dynamics(A, B, C, K, -10.0, 1.0, h=0.01, case=2, lowpass_pole=1.0)
    with pytest.raises(ValueError, match="h must be"):
        ido.make_inverse_dynamics(A, B, C, K, -10.0, 1.0, h=0.0, case=2)
    with pytest.raises(ValueError, match="rank must be given"):
        jax.jit(lambda M: ido.fact35(M, M).stable)(jnp.eye(2))
    # default case selection: relative degree one -> case 1 with the minimum-norm F2; §4.1 -> case 2
    p1 = ido.make_inverse_dynamics(*case1_plant(), np.array([[0.0], [0.0], [3.0]]), 20.0, h=0.01)
    np.testing.assert_allclose(p1.G2, 0.0)
    p2 = ido.make_inverse_dynamics(A, B, C, K, -10.0, 1.0, h=0.01)
    assert float(jnp.abs(p2.G2).sum()) > 0


def test_design_gains_meets_pole_and_box_constraints():
    """design_gains (Adam + projection): Case 2 on the §4.1 plant from a slow start (pole -(5 - 1)/0.5 = -8) to
    Re p <= -12 inside |F1| <= 10, 0.05 <= F2 <= 1, |K| <= 50 while shrinking |[k1 + F1 + F2 (a4 - k2)]/F2|
    (the §4.2 objective); Case 1 with F2 held (F2 C B = I) from an unstable third pole to Re p <= -1.5 (the plant
    zeros -2, -5 stay, Lemma 3.2). Both results pass make_inverse_dynamics' stability checks."""
    A, B, C = siso()

    def obj(g):
        return 1e-3 * jnp.sum(
            ((g["K"][0, 0] + g["F1"][0, 0] + g["F2"][0, 0] * (A4 - g["K"][1, 0])) / g["F2"][0, 0]) ** 2
        )

    init = dict(K=[[5.0], [0.0]], F1=[[-1.0]], F2=[[0.5]], rho=[[0.0, 0.0]])
    bounds = dict(F1=(-10, 10), F2=(0.05, 1.0), K=(-50, 50))
    res = ido.design_gains(
        A,
        B,
        C,
        init,
        case=2,
        max_real_part=-12.0,
        objective=obj,
        bounds=bounds,
        fixed=("rho",),
        optimizer=optax.adam(0.2),
    )
    assert ido.design_gains(A, B, C, init, case=2, max_real_part=-12.0, steps=0).feasible is False
    assert res.feasible and np.max(res.poles.real) <= -12.0 and res.objective < 1e-3
    g = res.gains
    ido.make_inverse_dynamics(A, B, C, g["K"], g["F1"], g["F2"], h=0.01, case=2, rho=g["rho"])
    A1_, B1_, C1_ = case1_plant()
    init1 = dict(K=[[0.0], [0.0], [0.0]], F1=[[-20.0]], F2=ido.case1_f2(B1_, C1_))
    res1 = ido.design_gains(A1_, B1_, C1_, init1, case=1, max_real_part=-1.5, fixed=("F2",), optimizer=optax.adam(0.2))
    assert res1.feasible
    for z in (-2.0, -5.0):
        assert np.min(np.abs(res1.poles - z)) < 1e-7
    ido.make_inverse_dynamics(A1_, B1_, C1_, res1.gains["K"], res1.gains["F1"], res1.gains["F2"], h=0.01)
    with pytest.raises(ValueError, match="init must contain F2"):
        ido.design_gains(A, B, C, dict(K=[[1.0], [1.0]], F1=[[1.0]]), case=2, max_real_part=-1.0)
