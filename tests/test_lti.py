"""Tests for jaxobs.lti: c2d with dead time (Cortesão 2006 eq. 11-18, the stochastic AOB paper eq. 51-52), tf2ss,
ctrb, obsv, dcgain."""

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.signal

from jaxobs.lti import (
    StateSpace,
    c2d,
    controllability_rank,
    ctrb,
    dcgain,
    is_spr,
    observability_rank,
    obsv,
    ss,
    tf2ss,
    unobservable_modes,
)

# Example 1 force plant (the MRAC chapter eq. 57-61, Cortesão 2006 §7): G(s) = k1 / (s (s + p1)) e^{-s Td}
KS, TP = 3.0, 0.032
K1, P1 = KS / TP, 1.0 / TP
H = 0.008


def force_plant(Ks=KS, Tp=TP):
    return ss(jnp.array([[0.0, 1.0], [0.0, -1.0 / Tp]]), jnp.array([[0.0], [Ks / Tp]]), jnp.array([[1.0, 0.0]]))


def zoh_closed_form(t):
    """``(e^{At}, int_0^t e^{As} ds B)`` of the force plant in closed form (the stochastic AOB paper eq. 51-52)."""
    e = np.exp(-P1 * t)
    Phi = np.array([[1.0, (1.0 - e) / P1], [0.0, e]])
    Gam = K1 / P1 * np.array([[t + (e - 1.0) / P1], [1.0 - e]])
    return Phi, Gam


def simulate_discrete(sysd: StateSpace, u):
    """Outputs y_k = C x_k + D u_k of x_{k+1} = A x_k + B u_k from x_0 = 0, k = 0..N-1."""
    A, B, C, D = (np.asarray(M) for M in (sysd.A, sysd.B, sysd.C, sysd.D))
    x = np.zeros(A.shape[0])
    ys = []
    for uk in u:
        ys.append(C @ x + D @ uk)
        x = A @ x + B @ uk
    return np.array(ys)


def simulate_fine(A, B, C, D, h, tau, u, factor=1000):
    """Independent reference: integrate x' = A x + B u(t - tau) on a grid ``factor`` times finer than ``h``.

    ``u(t) = u_j`` on ``[jh, (j+1)h)`` (zero-order hold) and ``u(t) = 0`` for ``t < 0``; ``tau`` must be a whole
    number of fine steps, so the delayed input is constant on every fine step and each step is exact
    (its own matrix exponential). Returns ``y(kh) = C x(kh) + D u(kh - tau)`` for k = 0..N-1.
    """
    A, B, C, D = (np.asarray(M, float) for M in (A, B, C, D))
    n, m = B.shape
    dt = h / factor
    shift = round(tau / dt)
    assert abs(shift * dt - tau) < 1e-12 * h, "tau must lie on the fine grid"
    block = np.zeros((n + m, n + m))
    block[:n, :n], block[:n, n:] = A, B
    E = scipy.linalg.expm(block * dt)
    Ad, Bd = E[:n, :n], E[:n, n:]
    N = len(u)

    def u_at_fine(j):  # held input at fine index j (time j dt), delayed by `shift` fine steps
        j = j - shift
        return u[j // factor] if j >= 0 else np.zeros(m)

    x = np.zeros(n)
    ys = []
    for k in range(N):
        ys.append(C @ x + D @ u_at_fine(k * factor))
        for j in range(k * factor, (k + 1) * factor):
            x = Ad @ x + Bd @ u_at_fine(j)
    return np.array(ys)


# ---------------------------------------------------------------------------------------------
# c2d: structure of the Example 1 model


def test_c2d_example1_structure_cortesao2006_eq11_18():
    """Td = 5h: Phi_r is 7x7 with Phi_1 = e^{Ah} (eq. 15) in closed form, Gamma_1 = full ZOH matrix in the
    column of slot 1 (eq. 17; the stochastic AOB paper eq. 51-52), Gamma_0 = 0 (eq. 16, tau' = h), a shift register
    for the delayed inputs and Gamma_r = e_7 (eq. 18/22)."""
    sysd = c2d(force_plant(), H, 5 * H)
    Phi, Gam, C, D = (np.asarray(M) for M in (sysd.A, sysd.B, sysd.C, sysd.D))
    assert Phi.shape == (7, 7) and Gam.shape == (7, 1) and C.shape == (1, 7) and D.shape == (1, 1)
    assert sysd.dt == H
    Phi1, Gamma1 = zoh_closed_form(H)
    e = np.exp(-P1 * H)
    np.testing.assert_allclose(Phi1, [[1.0, (1 - e) / P1], [0.0, e]])
    np.testing.assert_allclose(Phi[:2, :2], Phi1, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(Phi[:2, 2:3], Gamma1, rtol=1e-12, atol=1e-15)  # slot 1: u_{k-6}
    np.testing.assert_array_equal(Phi[:2, 3:], 0.0)  # Gamma_0 = 0 and nothing else
    shift = np.zeros((5, 5))
    shift[np.arange(4), np.arange(1, 5)] = 1.0
    np.testing.assert_array_equal(Phi[2:, 2:], shift)
    np.testing.assert_array_equal(Phi[2:, :2], 0.0)
    np.testing.assert_array_equal(Gam[:, 0], np.eye(7)[6])
    np.testing.assert_array_equal(C, np.eye(7)[:1])
    np.testing.assert_array_equal(D, 0.0)


def test_c2d_fractional_delay_gamma0_gamma1_cortesao2006_eq16_17():
    """tau = 2.5h = (d - 1)h + tau' with d = 3, tau' = h/2: Gamma_0 = int_0^{h-tau'} e^{As} ds B on u_{k-3}
    (eq. 16) and Gamma_1 = e^{A(h-tau')} int_0^{tau'} e^{As} ds B on u_{k-4} (eq. 17), in closed form."""
    tau_p = 0.5 * H
    sysd = c2d(force_plant(), H, 2.5 * H)
    Phi = np.asarray(sysd.A)
    assert Phi.shape == (5, 5)
    _, Gamma0 = zoh_closed_form(H - tau_p)
    _, F_tau = zoh_closed_form(tau_p)
    Phi_rest, _ = zoh_closed_form(H - tau_p)
    Gamma1 = Phi_rest @ F_tau
    np.testing.assert_allclose(Phi[:2, 2:3], Gamma1, rtol=1e-12)
    np.testing.assert_allclose(Phi[:2, 3:4], Gamma0, rtol=1e-12)
    np.testing.assert_array_equal(Phi[:2, 4], 0.0)
    # Gamma_0 + Gamma_1 is the full ZOH input matrix (the two pieces of one sample interval)
    np.testing.assert_allclose(Gamma0 + Gamma1, zoh_closed_form(H)[1], rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(sysd.B)[:, 0], np.eye(5)[4])


def test_c2d_zero_delay_matches_scipy_cont2discrete():
    """tau = 0: c2d is the plain ZOH discretisation, equal to scipy.signal.cont2discrete(method='zoh')."""
    rng = np.random.default_rng(0)
    A, B = rng.normal(size=(3, 3)), rng.normal(size=(3, 2))
    C, D = rng.normal(size=(2, 3)), rng.normal(size=(2, 2))
    Ad, Bd, Cd, Dd, _ = scipy.signal.cont2discrete((A, B, C, D), 0.1, method="zoh")
    sysd = c2d(ss(A, B, C, D), 0.1)
    for got, want in zip((sysd.A, sysd.B, sysd.C, sysd.D), (Ad, Bd, Cd, Dd), strict=True):
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12, atol=1e-14)
    # same for the force plant
    sp = force_plant()
    Ad, Bd, *_ = scipy.signal.cont2discrete((sp.A, sp.B, sp.C, sp.D), H, method="zoh")
    sysd = c2d(sp, H, 0.0)
    np.testing.assert_allclose(np.asarray(sysd.A), Ad, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(sysd.B), Bd, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("tau_over_h", [0.0, 0.3, 1.0, 2.5, 4.0])
def test_c2d_delay_matches_fine_grid_simulation(tau_over_h):
    """Cortesão 2006 eq. 11-18: the delay-augmented model reproduces, at the sampling instants, the continuous plant
    driven by a zero-order-held input delayed by tau (independent 1000x finer integration)."""
    rng = np.random.default_rng(int(10 * tau_over_h))
    u = rng.normal(size=(25, 1))
    sp = force_plant()
    tau = tau_over_h * H
    y = simulate_discrete(c2d(sp, H, tau), u)
    y_ref = simulate_fine(sp.A, sp.B, sp.C, sp.D, H, tau, u)
    scale = np.max(np.abs(y_ref))
    assert scale > 0
    np.testing.assert_allclose(y, y_ref, rtol=0, atol=1e-9 * scale)


def test_c2d_mimo_with_feedthrough_and_delay_matches_fine_grid():
    """MIMO plant with D != 0: c2d routes D u(t - tau) to the slot holding that input (Cortesão 2006 eq. 18),
    and the output response equals the fine-grid simulation for fractional and whole-sample delays, with the
    minimal and with a padded (n_delay = 4) delay line."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(3, 3)) - 2.0 * np.eye(3)
    B, C, D = rng.normal(size=(3, 2)), rng.normal(size=(2, 3)), rng.normal(size=(2, 2))
    h = 0.05
    u = rng.normal(size=(20, 2))
    for tau in (0.4 * h, 1.7 * h, 2 * h):
        y_ref = simulate_fine(A, B, C, D, h, tau, u)
        for n_delay in (None, 4):  # minimal and padded delay line
            y = simulate_discrete(c2d(ss(A, B, C, D), h, tau, n_delay=n_delay), u)
            np.testing.assert_allclose(y, y_ref, rtol=0, atol=1e-9 * np.max(np.abs(y_ref)))


@pytest.mark.parametrize("tau_over_h", [0.0, 0.3, 1.0, 2.5, 4.0])
def test_c2d_padding_keeps_input_output_response(tau_over_h):
    """n_delay = 7 extra slots (traced-delay representation) have the same input-output response as the
    minimal model with ceil(tau/h) slots."""
    rng = np.random.default_rng(1)
    sysc = force_plant()
    tau = tau_over_h * H
    minimal = c2d(sysc, H, tau)
    padded = c2d(sysc, H, tau, n_delay=7)
    assert padded.A.shape == (2 + 7, 2 + 7)
    assert minimal.A.shape[0] < padded.A.shape[0]
    u = rng.normal(size=(40, 1))
    y_min, y_pad = simulate_discrete(minimal, u), simulate_discrete(padded, u)
    np.testing.assert_allclose(y_pad, y_min, rtol=1e-12, atol=1e-12 * np.max(np.abs(y_min)))


@pytest.mark.slow
def test_c2d_traced_delay_jit_and_vmap_equal_eager():
    """A traced dead time (fixed n_delay = 6): ``jax.jit(lambda tau: c2d(sys, h, tau, n_delay=6))`` equals eager,
    and vmap over an array of delays equals a Python loop, for every matrix of the model (Cortesão 2006 eq. 11-18).
    The limit tau <= n_delay * h is tested on both sides in test_c2d_delay_limit_is_n_delay_samples_on_both_sides."""
    sp = force_plant()
    taus = jnp.array([0.0, 0.3, 1.0, 2.5, 4.0, 5.7, 6.0]) * H
    jitted = jax.jit(lambda tau: c2d(sp, H, tau, n_delay=6))
    batched = jax.jit(jax.vmap(lambda tau: c2d(sp, H, tau, n_delay=6)))(taus)
    for i, tau in enumerate(taus):
        eager = c2d(sp, H, float(tau), n_delay=6)
        traced = jitted(tau)
        for name in "ABCD":
            np.testing.assert_allclose(getattr(traced, name), getattr(eager, name), rtol=1e-13, atol=1e-15)
            np.testing.assert_allclose(getattr(batched, name)[i], getattr(eager, name), rtol=1e-13, atol=1e-15)


def test_c2d_delay_limit_is_n_delay_samples_on_both_sides():
    """Documented contract at its boundary tau = n_delay * h (n_delay = 6): a traced tau just inside it (relative
    1e-9 below, and exactly on it) gives the same finite model as eager c2d; just outside it (relative 1e-8 above,
    past the 1e-9 rounding allowance) gives NaN matrices when traced and a ValueError naming n_delay when eager."""
    sp = force_plant()
    limit = 6 * H
    jitted = jax.jit(lambda tau: c2d(sp, H, tau, n_delay=6))
    for tau in (limit * (1 - 1e-9), limit):
        traced, eager = jitted(tau), c2d(sp, H, tau, n_delay=6)
        for name in "ABCD":
            assert np.all(np.isfinite(np.asarray(getattr(traced, name))))
            np.testing.assert_allclose(getattr(traced, name), getattr(eager, name), rtol=1e-13, atol=1e-15)
    outside = limit * (1 + 1e-8)
    for name in "ABCD":
        assert np.all(np.isnan(np.asarray(getattr(jitted(outside), name))))
    with pytest.raises(ValueError, match=r"needs more than n_delay=6 slots"):
        c2d(sp, H, outside, n_delay=6)


def _central_difference(f, x, step):
    return (f(x + step) - f(x - step)) / (2 * step)


def test_c2d_grad_wrt_delay_and_plant_parameters_matches_finite_differences():
    """d/dtau at fractional delays (through Gamma_0, Gamma_1 of eq. 16-17) and d/dKs, d/dTp (through a function
    building A, B of the force plant) of the delay-augmented model equal central finite differences."""
    rng = np.random.default_rng(2)
    WA, WB = jnp.asarray(rng.normal(size=(8, 8))), jnp.asarray(rng.normal(size=(8, 1)))

    def f(Ks, Tp, tau):
        sysd = c2d(force_plant(Ks, Tp), H, tau, n_delay=6)
        return jnp.sum(WA * sysd.A) + jnp.sum(WB * sysd.B)

    grad_f = jax.jit(jax.grad(f, argnums=(0, 1, 2)))
    for tau in (0.3 * H, 2.5 * H, 4.6 * H):
        gKs, gTp, gtau = grad_f(KS, TP, tau)
        fd_tau = _central_difference(lambda t: f(KS, TP, t), tau, 1e-4 * H)
        fd_Ks = _central_difference(lambda k, tau=tau: f(k, TP, tau), KS, 1e-5 * KS)
        fd_Tp = _central_difference(lambda t, tau=tau: f(KS, t, tau), TP, 1e-5 * TP)
        assert abs(float(gtau)) > 0
        np.testing.assert_allclose(gtau, fd_tau, rtol=1e-6)
        np.testing.assert_allclose(gKs, fd_Ks, rtol=1e-7)
        np.testing.assert_allclose(gTp, fd_Tp, rtol=1e-7)


def test_c2d_rejects_bad_input():
    """Eager validation: discrete sys, non-positive h, negative delay, too few slots, traced delay without
    n_delay -> ValueError naming the argument."""
    sp = force_plant()
    with pytest.raises(ValueError, match=r"^sys\b.*already discrete"):
        c2d(c2d(sp, H), H)
    with pytest.raises(ValueError, match=r"^h\b.*positive.*0\.0"):
        c2d(sp, 0.0)
    with pytest.raises(ValueError, match=r"^delay\b.*non-negative.*-0\.008"):
        c2d(sp, H, -H)
    with pytest.raises(ValueError, match=r"needs more than n_delay=2 slots"):
        c2d(sp, H, 3 * H, n_delay=2)
    with pytest.raises(ValueError, match=r"^n_delay must be given when delay is traced"):
        jax.jit(lambda tau: c2d(sp, H, tau).A)(H)


def test_ss_validates_shapes():
    """ss() checks shapes eagerly and names the offending matrix; D defaults to zeros."""
    sys = ss(np.eye(2), np.ones((2, 1)), np.ones((3, 2)))
    assert sys.D.shape == (3, 1) and not sys.is_discrete
    assert (sys.n_states, sys.n_inputs, sys.n_outputs) == (2, 1, 3)
    with pytest.raises(ValueError, match=r"^A\b.*square.*\(2, 3\)"):
        ss(np.ones((2, 3)), np.ones((2, 1)), np.ones((1, 2)))
    with pytest.raises(ValueError, match=r"^B\b.*\(3, 1\)"):
        ss(np.eye(2), np.ones((3, 1)), np.ones((1, 2)))
    with pytest.raises(ValueError, match=r"^C\b.*\(1, 3\)"):
        ss(np.eye(2), np.ones((2, 1)), np.ones((1, 3)))
    with pytest.raises(ValueError, match=r"^D\b.*\(2, 2\)"):
        ss(np.eye(2), np.ones((2, 1)), np.ones((1, 2)), np.ones((2, 2)))
    with pytest.raises(ValueError, match=r"^dt\b.*positive.*-1\.0"):
        ss(np.eye(2), np.ones((2, 1)), np.ones((1, 2)), dt=-1.0)


# ---------------------------------------------------------------------------------------------
# tf2ss


def _freq_response(sys: StateSpace, s):
    A, B, C, D = (np.asarray(M) for M in (sys.A, sys.B, sys.C, sys.D))
    return C @ np.linalg.solve(s * np.eye(A.shape[0]) - A, B) + D


S_POINTS = (1j, 0.5 + 2j, -3.0 + 0.1j, 10.0, -0.7 - 5j)


@pytest.mark.parametrize(
    "num, den",
    [
        ([2.0, 3.0, 1.0], [1.0, 4.0, 6.0, 4.0]),  # strictly proper
        ([3.0, 1.0, 2.0], [2.0, 1.0, 5.0]),  # biproper, non-monic denominator: D != 0
        ([5.0], [1.0, 0.0]),  # integrator
        ([0.0, 0.0, 1.0], [0.5, 0.3, 1.0]),  # leading zeros in the numerator
    ],
)
def test_tf2ss_siso_frequency_response(num, den):
    """C (sI - A)^{-1} B + D = num(s) / den(s) at several complex s."""
    sys = tf2ss(num, den)
    assert sys.n_states == len(np.trim_zeros(np.asarray(den), "f")) - 1
    for s in S_POINTS:
        want = np.polyval(num, s) / np.polyval(den, s)
        np.testing.assert_allclose(_freq_response(sys, s)[0, 0], want, rtol=1e-12)


def test_tf2ss_mimo_2x3_frequency_response():
    """A 2x3 transfer matrix with different denominators per entry: every entry matches at complex s, and the
    order is the sum of the entry orders (documented non-minimal stacking)."""
    num = [
        [[1.0], [2.0, 1.0], [1.0, 0.0, 3.0]],
        [[0.5, 1.0], [4.0], [-1.0, 2.0]],
    ]
    den = [
        [[1.0, 1.0], [1.0, 3.0, 2.0], [1.0, 2.0, 5.0]],
        [[1.0, 0.2, 1.0], [2.0, 1.0], [1.0, 4.0]],
    ]
    sys = tf2ss(num, den, dt=None)
    assert (sys.n_outputs, sys.n_inputs) == (2, 3)
    assert sys.n_states == 1 + 2 + 2 + 2 + 1 + 1
    for s in S_POINTS:
        G = _freq_response(sys, s)
        for i in range(2):
            for j in range(3):
                want = np.polyval(num[i][j], s) / np.polyval(den[i][j], s)
                np.testing.assert_allclose(G[i, j], want, rtol=1e-12)


def test_tf2ss_rejects_improper_and_ragged():
    """Improper entries and inconsistent row lengths -> ValueError."""
    with pytest.raises(ValueError, match="improper"):
        tf2ss([1.0, 0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="improper"):
        tf2ss([[[1.0], [1.0, 2.0, 3.0]]], [[[1.0, 1.0], [1.0, 1.0]]])
    with pytest.raises(ValueError, match="row 1"):
        tf2ss([[[1.0], [1.0]], [[1.0]]], [[[1.0, 1.0], [1.0, 2.0]], [[1.0, 3.0]]])
    with pytest.raises(ValueError, match="rows"):
        tf2ss([[[1.0]], [[1.0]]], [[[1.0, 1.0]]])
    with pytest.raises(ValueError, match="den"):
        tf2ss([1.0], [0.0, 0.0])


# ---------------------------------------------------------------------------------------------
# ctrb, obsv, dcgain


def test_ctrb_obsv_against_numpy_and_python_control():
    """ctrb = [B, AB, ..., A^{n-1}B] (Cortesão 2006 eq. 46) and obsv = [C; CA; ...; CA^{n-1}], by hand and as
    control.ctrb / control.obsv."""
    rng = np.random.default_rng(4)
    A, B, C = rng.normal(size=(4, 4)), rng.normal(size=(4, 2)), rng.normal(size=(3, 4))
    by_hand_c = np.hstack([np.linalg.matrix_power(A, k) @ B for k in range(4)])
    by_hand_o = np.vstack([C @ np.linalg.matrix_power(A, k) for k in range(4)])
    np.testing.assert_allclose(ctrb(A, B), by_hand_c, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(obsv(A, C), by_hand_o, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ctrb(A, B), control.ctrb(A, B), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(obsv(A, C), control.obsv(A, C), rtol=1e-12, atol=1e-12)


def test_ctrb_obsv_dcgain_jit_vmap_equal_eager():
    """Transformation test: jit and vmap (batched matrices vs a loop) equal eager."""
    rng = np.random.default_rng(6)
    As = jnp.asarray(rng.normal(size=(3, 3, 3)) - 3 * np.eye(3))
    Bs, Cs = jnp.asarray(rng.normal(size=(3, 3, 2))), jnp.asarray(rng.normal(size=(3, 2, 3)))
    vc, vo = jax.vmap(ctrb)(As, Bs), jax.vmap(obsv)(As, Cs)
    vdc = jax.vmap(lambda A, B, C: dcgain(StateSpace(A, B, C, jnp.zeros((2, 2)))))(As, Bs, Cs)
    for i in range(3):
        np.testing.assert_allclose(vc[i], ctrb(As[i], Bs[i]), rtol=1e-13)
        np.testing.assert_allclose(vo[i], obsv(As[i], Cs[i]), rtol=1e-13)
        np.testing.assert_allclose(jax.jit(ctrb)(As[i], Bs[i]), ctrb(As[i], Bs[i]), rtol=1e-13)
        sys = ss(As[i], Bs[i], Cs[i])
        np.testing.assert_allclose(vdc[i], dcgain(sys), rtol=1e-12)
        np.testing.assert_allclose(jax.jit(dcgain)(sys), dcgain(sys), rtol=1e-12)


def test_dcgain_against_numpy_and_python_control():
    """dcgain: -C A^{-1} B + D (continuous) and C (I - A)^{-1} B + D (discrete), as control.dcgain."""
    rng = np.random.default_rng(7)
    A = rng.normal(size=(3, 3)) - 3 * np.eye(3)
    B, C, D = rng.normal(size=(3, 2)), rng.normal(size=(2, 3)), rng.normal(size=(2, 2))
    cont = ss(A, B, C, D)
    want_c = -C @ np.linalg.solve(A, B) + D
    np.testing.assert_allclose(dcgain(cont), want_c, rtol=1e-12)
    np.testing.assert_allclose(dcgain(cont), control.dcgain(control.ss(A, B, C, D)), rtol=1e-10)

    Ad = 0.3 * rng.normal(size=(3, 3))
    disc = ss(Ad, B, C, D, dt=0.1)
    want_d = C @ np.linalg.solve(np.eye(3) - Ad, B) + D
    np.testing.assert_allclose(dcgain(disc), want_d, rtol=1e-12)
    np.testing.assert_allclose(dcgain(disc), control.dcgain(control.ss(Ad, B, C, D, 0.1)), rtol=1e-10)

    # the ZOH discretisation preserves the DC gain (no delay effect at DC)
    stable = ss(A, B, C, D)
    np.testing.assert_allclose(dcgain(c2d(stable, 0.05, 0.12)), want_c, rtol=1e-10)


# --- is_spr (Khalil 2002, Lemma 6.1) ------------------------------------------------------------------------------


def _tf(num, den):
    sys = tf2ss(num, den)
    return sys.A, sys.B, sys.C, sys.D


@pytest.mark.parametrize(
    "num, den, expected",
    [
        ([1.0], [1.0, 1.0], True),  # 1 / (s + 1)
        ([1.0], [1.0, 0.0], False),  # 1 / s: positive real, not strictly (pole on the axis)
        ([1.0], [1.0, 1.0, 1.0], False),  # relative degree 2: Re G < 0 at high frequency
        ([1.0, 2.0], [1.0, 3.0, 1.0], True),  # (s + a) / (s^2 + b s + c) with a < b: SPR
        ([1.0, 1.0], [1.0, 1.0, 1.0], False),  # a = b: Re G = 1 / |den|^2, w^2 Re G -> 0 (boundary)
        ([1.0, 4.0], [1.0, 3.0, 1.0], False),  # a > b: Re G < 0 at high frequency
        ([1.0, 2.0], [1.0, 1.0], True),  # (s + 2) / (s + 1): biproper, Re G >= 1
        ([1.0, -1.0], [1.0, 1.0], False),  # (s - 1) / (s + 1): Re G(0) = -1
        ([1.0], [1.0, -1.0], False),  # unstable pole
    ],
)
def test_is_spr_textbook_cases(num, den, expected):
    assert is_spr(*_tf(num, den)) is expected


@pytest.mark.parametrize("c, expected", [(0.05, True), (0.2, False)])
def test_is_spr_sees_a_dip_between_zero_and_infinity(c, expected):
    """``G = 1 - c s / (s^2 + 0.1 s + 1)``: ``Re G = 1`` at 0 and infinity, ``1 - 10 c`` at ``w = 1`` (the
    Hamiltonian/pencil part of the test, not the end points)."""
    A = [[0.0, 1.0], [-1.0, -0.1]]
    assert is_spr(A, [[0.0], [1.0]], [[0.0, -c]], [[1.0]]) is expected


def test_is_spr_mimo():
    """``diag(1/(s+1), 2/(s+3))`` and ``I - diag(0.5/(s+1), 2/(s+3))`` are SPR, ``I - diag(1/(s+1), 4/(s+3))``
    is not (``G(0)`` singular, indefinite); ``C / (s + 1)`` with a non-symmetric ``C B`` is not (``G + G^*`` has
    eigenvalues ``(2 +- 2 w) / (1 + w^2)``)."""
    assert is_spr(-np.diag([1.0, 3.0]), np.eye(2), np.diag([1.0, 2.0]))
    assert is_spr(-np.diag([1.0, 3.0]), np.eye(2), -np.diag([0.5, 2.0]), 1.0)  # 1 - c/(s+p): Re >= 1 - c/p > 0
    assert not is_spr(-np.diag([1.0, 3.0]), np.eye(2), -np.diag([1.0, 4.0]), 1.0)  # 1 - 4/(s+3): Re G(0) < 0
    assert not is_spr(-np.eye(2), np.eye(2), np.array([[1.0, 1.0], [-1.0, 1.0]]))


def test_is_spr_agrees_with_a_frequency_grid():
    """Random stable biproper SISO systems: the verdict equals ``min Re G(jw) > 0`` on a dense grid wherever the
    grid's minimum is clear of 0."""
    rng = np.random.default_rng(0)
    w = np.concatenate([[0.0], np.logspace(-3, 3, 4000)])
    checked = 0
    for _ in range(40):
        A = rng.normal(size=(3, 3))
        A -= (np.max(np.linalg.eigvals(A).real) + rng.uniform(0.1, 1.0)) * np.eye(3)
        B, C, D = rng.normal(size=(3, 1)), rng.normal(size=(1, 3)), rng.uniform(0.2, 2.0, size=(1, 1))
        G = np.array([(C @ np.linalg.solve(1j * wk * np.eye(3) - A, B) + D)[0, 0] for wk in w])
        low = G.real.min()
        if abs(low) > 1e-2:
            checked += 1
            assert is_spr(A, B, C, D) is bool(low > 0)
    assert checked > 20


def test_is_spr_rejects_bad_input():
    with pytest.raises(ValueError, match="C"):
        is_spr([[-1.0]], [[1.0]], [[1.0, 2.0]])
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(lambda a: is_spr(a, [[1.0]], [[1.0]]))(jnp.array([[-1.0]]))


def test_ranks_and_unobservable_modes_match_python_control():
    """controllability_rank / observability_rank are the ranks of python-control's ctrb / obsv; the mode at 2 that
    C does not see is the one unobservable_modes reports (Hautus test), the stable one at -1 is outside the region."""
    A = np.diag([2.0, -1.0, 0.5])
    B = np.array([[1.0], [0.0], [1.0]])
    C = np.array([[0.0, 1.0, 1.0]])
    assert controllability_rank(A, B) == np.linalg.matrix_rank(control.ctrb(A, B)) == 2
    assert observability_rank(A, C) == np.linalg.matrix_rank(control.obsv(A, C)) == 2
    assert unobservable_modes(A, C, lambda lam: lam.real >= 0) == [2.0]
    assert unobservable_modes(A, C, lambda lam: lam.real < 0) == []
