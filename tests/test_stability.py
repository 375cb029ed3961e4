"""jaxobs.stability: eq. 59 and eq. 65-66 (Cortesão 2006 §6), spectral radius and margins against NumPy,
python-control and independent checks."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxobs.closed_loop import simulate
from jaxobs.design import dlqr
from jaxobs.lti import StateSpace, c2d, ss
from jaxobs.observers import FeedbackParams, LinearObserver, active, observer_controller
from jaxobs.observers.active import active_observer_controller
from jaxobs.observers.kalman import kalman_filter, make_kalman
from jaxobs.observers.linear import linear_controller
from jaxobs.papers.cortesao.example1 import aob_params
from jaxobs.papers.cortesao.force_control import EXAMPLE1, nominal_design, with_feedback
from jaxobs.plants import force_plant
from jaxobs.stability import (
    ROBUSTNESS_MARGINS,
    closed_loop_matrix,
    frequency_response,
    loop_transfer,
    robustness_metrics,
    spectral_radius,
    stability_margins,
    unstructured_mismatch,
)

control = pytest.importorskip("control")
margins_jit = jax.jit(stability_margins)  # one compilation per state dimension


def _linear(Phi_n, Gamma_n, C, K, L):
    """The params of the fixed-gain observer-based controller (observer gain K, state feedback L)."""
    return FeedbackParams(LinearObserver(*(jnp.asarray(M) for M in (Phi_n, Gamma_n, C, K))), jnp.asarray(L))


def _aob(plant, L_r, order):
    """The steady-state AOB-N of Example 1 with its state feedback (Cortesão 2006 eq. 49-50)."""
    return with_feedback(aob_params(plant, order), L_r)


def _random_setup(rng, n=5, m=1, p=1):
    Phi_n = rng.normal(size=(n, n)) * 0.3
    Gamma_n = rng.normal(size=(n, m))
    C = rng.normal(size=(p, n))
    K = rng.normal(size=(n, p)) * 0.3
    L = rng.normal(size=(m, n)) * 0.3
    dPhi, dGamma = rng.normal(size=(n, n)) * 0.05, rng.normal(size=(n, m)) * 0.05
    return Phi_n, Gamma_n, C, K, L, dPhi, dGamma


def test_eq59_is_the_closed_loop_in_error_coordinates():
    """Theorem 2: with [x; e] = [x; x - x_hat] the closed-loop matrix is eq. 59 as printed."""
    Phi_n, Gamma_n, C, K, L, dPhi, dGamma = _random_setup(np.random.default_rng(0), m=2, p=2)
    Phi, Gamma = Phi_n + dPhi, Gamma_n + dGamma
    A = np.asarray(closed_loop_matrix(ss(Phi, Gamma, C, dt=1.0), linear_controller, _linear(Phi_n, Gamma_n, C, K, L)))
    n = Phi.shape[0]
    I, Z = np.eye(n), np.zeros((n, n))
    T = np.block([[I, Z], [I, -I]])  # its own inverse
    IKC = I - K @ C
    eq59 = np.block([[Phi - Gamma @ L, Gamma @ L], [IKC @ (dPhi - dGamma @ L), IKC @ (Phi_n + dGamma @ L)]])
    np.testing.assert_allclose(T @ A @ T, eq59, atol=1e-12)


def test_eq66_is_the_loop_in_estimate_error_coordinates():
    """Theorem 3: with [x_hat; e] the loop matrices are eq. 66 and the output matrix [L 0] (eq. 65)."""
    Phi_n, Gamma_n, C, K, L, dPhi, dGamma = _random_setup(np.random.default_rng(1))
    Phi, Gamma = Phi_n + dPhi, Gamma_n + dGamma
    loop = loop_transfer(ss(Phi, Gamma, C, dt=1.0), linear_controller, _linear(Phi_n, Gamma_n, C, K, L))
    n = Phi.shape[0]
    I, Z = np.eye(n), np.zeros((n, n))
    S = np.block([[Z, I], [I, -I]])  # [x_hat; e] = S [x; x_hat]
    S_inv = np.linalg.inv(S)
    KC, IKC = K @ C, np.eye(n) - K @ C
    top = [Phi_n - Gamma_n @ L + KC @ (dPhi + Gamma_n @ L), KC @ Phi]
    phi = np.block([top, [IKC @ (dPhi + Gamma_n @ L), IKC @ Phi]])
    gamma = np.vstack([KC @ Gamma, IKC @ Gamma])
    np.testing.assert_allclose(S @ np.asarray(loop.A) @ S_inv, phi, atol=1e-12)
    np.testing.assert_allclose(S @ np.asarray(loop.B), gamma, atol=1e-12)
    np.testing.assert_allclose(np.asarray(loop.C) @ S_inv, np.hstack([L, np.zeros_like(L)]), atol=1e-12)


def _aob3_loop(Ks, Tp, dead_time):
    plant, L_r = nominal_design()
    true = force_plant(Ks, Tp, EXAMPLE1.h, dead_time, n_delay=9)
    return true, _aob(plant, L_r, 3)


@pytest.mark.slow  # ~10 s of compilation
def test_closed_loop_matrix_is_what_the_simulated_aob_does():
    """The [x; x_hat] recursion of the simulated AOB-3 (closed_loop.simulate) is the matrix of eq. 59,
    also for a true plant with a longer, fractional dead time than the nominal one."""
    true, params = _aob3_loop(1.7, 0.04, 6.4 * EXAMPLE1.h)
    A = np.asarray(closed_loop_matrix(true, active_observer_controller, params))
    x0 = np.zeros(true.n_states)
    x0[0] = 1.0
    trace = simulate(true, active_observer_controller, params, jnp.zeros(60), x0=jnp.asarray(x0))
    z = np.hstack([np.asarray(trace.x), np.asarray(trace.controller.x)])
    np.testing.assert_allclose(z[1:], z[:-1] @ A.T, atol=1e-12)


def test_simulation_diverges_exactly_when_the_spectral_radius_exceeds_one():
    """Theorem 2: over sampled stiffness / time-constant / dead-time mismatches, the simulated AOB-3
    loop grows at the rate of the spectral radius: diverging iff rho > 1."""
    rng = np.random.default_rng(2)
    n = 24
    Ks = np.exp(rng.uniform(np.log(0.3), np.log(30.0), n))
    Tp = EXAMPLE1.Tp * rng.uniform(0.5, 1.5, n)
    dead = rng.uniform(3.0, 8.0, n) * EXAMPLE1.h

    def rho_and_growth(Ks, Tp, dead):
        true, params = _aob3_loop(Ks, Tp, dead)
        rho = spectral_radius(closed_loop_matrix(true, active_observer_controller, params))
        x0 = jnp.zeros(true.n_states).at[0].set(1.0)
        trace = simulate(true, active_observer_controller, params, jnp.zeros(4000), x0=x0)
        size = jnp.linalg.norm(jnp.hstack([trace.x, trace.controller.x]), axis=1)
        return rho, jnp.log(size[-1] / size[-1001]) / 1000.0

    rho, growth = jax.jit(jax.vmap(rho_and_growth))(Ks, Tp, dead)
    rho, growth = np.asarray(rho), np.asarray(growth)
    assert (rho > 1).any() and (rho < 1).any()
    np.testing.assert_allclose(growth, np.log(rho), atol=2e-3)
    clear = np.abs(np.log(rho)) > 3e-3
    assert np.array_equal(growth[clear] > 0, rho[clear] > 1)


def test_spectral_radius_matches_numpy_and_is_differentiable():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(30, 8, 8)) * 0.4
    rho = jax.jit(jax.vmap(spectral_radius))(jnp.asarray(A))
    np.testing.assert_allclose(rho, np.abs(np.linalg.eigvals(A)).max(axis=1), rtol=1e-9)
    check_grads(spectral_radius, (jnp.asarray(A[0]),), order=1, modes=["fwd", "rev"])


def _random_loops(count, seed=4):
    """Random stable discrete SISO loops with their python-control margins, where python-control's
    polynomial method is trustworthy (its crossings verified on the exact response)."""
    rng = np.random.default_rng(seed)
    loops = []
    while len(loops) < count:
        n = int(rng.integers(2, 7))
        A = rng.normal(size=(n, n))
        A *= 0.9 / np.abs(np.linalg.eigvals(A)).max()
        B, C = rng.normal(size=(n, 1)) * rng.uniform(0.5, 5.0), rng.normal(size=(1, n))
        H = lambda w, A=A, B=B, C=C: (C @ np.linalg.solve(np.exp(1j * w * 0.01) * np.eye(len(A)) - A, B)).item()
        if H(np.pi / 0.01).real < 0:
            continue  # python-control ignores a crossing at Nyquist (checked separately below)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                gm, pm, sm, wpc, wgc, wms = control.stability_margins(control.ss(A, B, C, 0, 0.01))
            except Warning:
                continue
        if np.isfinite(wpc) and abs(H(wpc).imag) > 1e-6 * abs(H(wpc)):
            continue  # a spurious root off the unit circle accepted by python-control's tolerance
        if np.isfinite(wgc) and abs(abs(H(wgc)) - 1) > 1e-6:
            continue
        loops.append((A, B, C, (gm, pm, sm, wpc, wgc)))
    return loops


@pytest.mark.slow
def test_margins_agree_with_python_control():
    """Relative 1e-4 on gain/phase margins and crossovers (issue 3 §4); our stability margin is
    never worse than python-control's local minimiser and equals it where that one is global."""
    loops = _random_loops(40)
    for A, B, C, (gm, pm, sm, wpc, wgc) in loops:
        m = margins_jit(ss(A, B, C, dt=0.01))
        for ours, ref in ((m.gain_margin, gm), (m.phase_margin, pm), (m.phase_crossover, wpc), (m.gain_crossover, wgc)):
            ours = float(ours)
            if np.isfinite(ref):
                assert ours == pytest.approx(ref, rel=1e-4)
            else:
                assert not np.isfinite(ours)
        assert float(m.stability_margin) <= sm * (1 + 1e-6)
        dense = np.exp(1j * np.linspace(0, np.pi, 200_001))
        H = np.array([(C @ np.linalg.solve(z * np.eye(len(A)) - A, B)).item() for z in dense[::40]])
        assert float(m.stability_margin) == pytest.approx(np.abs(1 + H).min(), rel=1e-3)


@pytest.mark.slow
def test_gain_margin_puts_a_closed_loop_pole_on_the_unit_circle():
    """Independent of python-control: the loop gain times the gain margin has a closed-loop pole at
    exp(j w_pc dt), including crossings at the Nyquist frequency."""
    rng = np.random.default_rng(5)
    checked = 0
    for _ in range(60):
        n = int(rng.integers(2, 7))
        A = rng.normal(size=(n, n))
        A *= 0.9 / np.abs(np.linalg.eigvals(A)).max()
        B, C = rng.normal(size=(n, 1)) * 2.0, rng.normal(size=(1, n))
        m = margins_jit(ss(A, B, C, dt=0.01))
        if not np.isfinite(float(m.gain_margin)):
            continue
        poles = np.linalg.eigvals(A - float(m.gain_margin) * B @ C)
        target = np.exp(1j * float(m.phase_crossover) * 0.01)
        assert np.abs(poles - target).min() < 1e-7
        checked += 1
    assert checked > 30


@pytest.mark.slow  # ~13 s of compilation
def test_phase_margin_matches_its_definition():
    """|H(w_gc)| = 1 and angle(-H(w_gc)) = phase margin at the reported gain crossover."""
    for A, B, C, _ in _random_loops(15, seed=6):
        sys = ss(A, B, C, dt=0.01)
        m = margins_jit(sys)
        if not np.isfinite(float(m.phase_margin)):
            continue
        H = complex(frequency_response(sys, m.gain_crossover))
        assert abs(H) == pytest.approx(1.0, abs=1e-9)
        assert np.degrees(np.angle(-H)) == pytest.approx(float(m.phase_margin), abs=1e-6)


DT = 0.01


def _response(A, B, C, theta):
    """``H(e^{j theta})`` of the loop ``(A, B, C)`` at the normalised frequencies ``theta``."""
    n = A.shape[0]
    return np.array([(C @ np.linalg.solve(np.exp(1j * t) * np.eye(n) - A, B)).item() for t in np.atleast_1d(theta)])


def _random_loop(rng, size: int, *, radius, gain):
    """A random SISO loop ``(A, B, C)``: ``A``'s spectral radius and ``B``'s scale uniform in the ranges given."""
    A = rng.normal(size=(size, size))
    A *= rng.uniform(*radius) / np.abs(np.linalg.eigvals(A)).max()
    return A, rng.normal(size=(size, 1)) * rng.uniform(*gain), rng.normal(size=(1, size))


def _loops_with_several_gain_crossovers(count, *, nyquist_gain_above_one=False, seed=8, size=4):
    """Random loops, stable when closed, with two or more gain crossovers of which the one setting the delay
    margin is not the phase-margin crossover, python-control's crossovers (returnall=True) verified on the exact
    response, and ``|H(-1)|`` below or above 1 as asked. Returns ``(A, B, C, phase margins [deg], gain crossovers
    [rad/s])``."""
    rng = np.random.default_rng(seed)
    loops = []
    while len(loops) < count:
        A, B, C = _random_loop(rng, size, radius=(0.5, 0.98), gain=(0.5, 5.0))
        if np.abs(np.linalg.eigvals(A - B @ C)).max() > 0.99:
            continue
        if (abs(_response(A, B, C, np.pi)[0]) > 1.0) != nyquist_gain_above_one:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                _, pm, _, _, wgc, _ = control.stability_margins(control.ss(A, B, C, 0, DT), returnall=True)
            except Warning:
                continue
        pm, wgc = np.atleast_1d(pm), np.atleast_1d(wgc)
        if len(wgc) < 2 or np.argmin(np.mod(pm, 360.0) / wgc) == np.argmin(np.abs(pm)):
            continue
        if np.max(np.abs(np.abs(_response(A, B, C, wgc * DT)) - 1.0)) > 1e-9:
            continue
        loops.append((A, B, C, pm, wgc))
    return loops


def _destabilising_samples(A, B, C, samples):
    """Spectral radii of the closed loop with each number of extra input delay samples in ``samples``."""
    radii = []
    for k in samples:
        Ad, Bd, Cd = _with_input_delay(A, B, C, k)
        radii.append(np.abs(np.linalg.eigvals(Ad - Bd @ Cd)).max())
    return radii


def _with_input_delay(A, B, C, samples):
    """The loop ``H(z) z^-samples``: a chain of ``samples`` unit delays in front of the plant input."""
    n = A.shape[0]
    size = n + samples
    Ad, Bd, Cd = np.zeros((size, size)), np.zeros((size, 1)), np.zeros((1, size))
    Ad[:n, :n], Cd[:, :n] = A, C
    if samples == 0:
        Bd[:n] = B
    else:
        Ad[:n, n + samples - 1] = B[:, 0]  # the oldest slot drives the plant
        Ad[n + 1 :, n : n + samples - 1] = np.eye(samples - 1)
        Bd[n, 0] = 1.0
    return Ad, Bd, Cd


def test_delay_margin_is_the_smallest_destabilising_input_delay():
    """The delay margin is min_i mod(pm_i, 360) [rad] / w_i [rad/s] over every gain crossover (from python-control's
    crossovers, returnall=True), in seconds, on loops whose phase-margin crossover does not set it; and it is the
    delay that destabilises the loop: with floor(dm / dt) extra samples of input delay the closed loop is stable,
    with ceil(dm / dt) it is not (whole-sample delays are exact in discrete time)."""
    for A, B, C, pm, wgc in _loops_with_several_gain_crossovers(6):
        m = margins_jit(ss(A, B, C, dt=DT))
        want = np.min(np.radians(np.mod(pm, 360.0)) / wgc)
        assert float(m.delay_margin) == pytest.approx(want, rel=1e-7)
        samples = float(m.delay_margin) / DT
        assert abs(samples - round(samples)) > 1e-3  # the floor / ceil bracket is unambiguous
        below, above = _destabilising_samples(A, B, C, (int(np.floor(samples)), int(np.ceil(samples))))
        assert below < 1.0 < above


def test_one_sample_of_delay_destabilises_a_loop_with_nyquist_gain_above_one():
    """A whole-sample delay multiplies H(-1) by -1: when |H(-1)| > 1 the end of the Nyquist plot jumps across the
    critical point between 0 and 1 sample, so one sample of extra delay destabilises the loop even where every gain
    crossover allows more; the delay margin is then min(python-control formula, dt)."""
    capped = 0
    for A, B, C, pm, wgc in _loops_with_several_gain_crossovers(4, nyquist_gain_above_one=True):
        m = margins_jit(ss(A, B, C, dt=DT))
        formula = np.min(np.radians(np.mod(pm, 360.0)) / wgc)
        assert float(m.delay_margin) == pytest.approx(min(formula, DT), rel=1e-7)
        capped += formula > DT
        stable, one_sample = _destabilising_samples(A, B, C, (0, 1))
        assert stable < 1.0 < one_sample
    assert capped >= 2  # the cap, not a gain crossover, decides on some of these loops


@pytest.mark.slow
def test_margins_under_jit_vmap_and_grad():
    A, B, C, _ = _random_loops(1, seed=7)[0]
    sys = ss(A, B, C, dt=0.01)
    eager = stability_margins(sys)
    scales = jnp.array([0.5, 1.0, 2.0])
    batched = jax.jit(jax.vmap(lambda k: stability_margins(ss(A, B * k, C, dt=0.01))))(scales)
    for field in ("gain_margin", "phase_margin", "stability_margin", "spectral_radius"):
        assert float(getattr(batched, field)[1]) == pytest.approx(float(getattr(eager, field)), rel=1e-12)
    # gain margin of k H is gm / k: d gm / dk = -gm at k = 1
    dgm = jax.grad(lambda k: stability_margins(ss(A, B * k, C, dt=0.01)).gain_margin)(1.0)
    assert float(dgm) == pytest.approx(-float(eager.gain_margin), rel=1e-7)
    if np.isfinite(float(eager.phase_margin)):
        check_grads(lambda k: stability_margins(ss(A, B * k, C, dt=0.01)).phase_margin, (1.0,), order=1, modes=["rev"])


@pytest.mark.slow
def test_aob_relative_stability_decreases_with_the_order():
    """Cortesão 2006 §6.2: more active states, more poles near z = 1, less phase and gain margin."""
    plant, L_r = nominal_design()
    margins = [margins_jit(loop_transfer(plant, active_observer_controller, _aob(plant, L_r, n))) for n in (1, 2, 3)]
    pm = [float(m.phase_margin) for m in margins]
    gm = [float(m.gain_margin) for m in margins]
    assert pm[0] > pm[1] > pm[2] > 0 and gm[0] > gm[1] > gm[2] > 1
    assert all(float(m.spectral_radius) < 1 for m in margins)


@pytest.mark.slow  # a special case of test_closed_loop_matrix_is_what_the_simulated_aob_does
def test_switched_off_active_state_is_the_ckf_loop():
    plant, L_r = nominal_design()
    aob = with_feedback(active.set_active(aob_params(plant, 2), 0.0), L_r)
    ckf = with_feedback(active.make_ckf(plant, EXAMPLE1.R, q_plant=EXAMPLE1.q_plant, steady_state=True), L_r)
    a = margins_jit(loop_transfer(plant, active_observer_controller, aob))
    b = margins_jit(loop_transfer(plant, active_observer_controller, ckf))
    assert float(a.spectral_radius) == pytest.approx(float(b.spectral_radius), rel=1e-9)
    assert float(a.gain_margin) == pytest.approx(float(b.gain_margin), rel=1e-6)


def test_input_gain_mismatch_divides_the_gain_margin():
    """Parametric family: a true input gain g scales the loop transfer function, so GM becomes GM / g."""
    plant, L_r = nominal_design()
    params = _aob(plant, L_r, 1)

    def gm(g):
        true = force_plant(3.0, 0.032, EXAMPLE1.h, 0.04, input_gain=g)
        return margins_jit(loop_transfer(true, active_observer_controller, params)).gain_margin

    assert float(gm(1.7)) == pytest.approx(float(gm(1.0)) / 1.7, rel=1e-9)


def test_unstructured_mismatch_has_the_requested_norms():
    Phi_n, Gamma_n = jnp.eye(4) * 0.5, jnp.ones((4, 1))
    Phi, Gamma = unstructured_mismatch(jax.random.key(0), Phi_n, Gamma_n, 0.1, 0.02)
    assert float(jnp.linalg.norm(Phi - Phi_n, 2)) == pytest.approx(0.1)
    assert float(jnp.linalg.norm(Gamma - Gamma_n, 2)) == pytest.approx(0.02)


def test_bad_input():
    A, B, C = np.eye(2) * 0.5, np.ones((2, 1)), np.ones((1, 2))
    with pytest.raises(ValueError, match="discrete"):
        stability_margins(ss(A, B, C))
    with pytest.raises(ValueError, match="SISO"):
        stability_margins(ss(A, np.ones((2, 2)), C, dt=0.1))
    with pytest.raises(ValueError, match=r"^K\b.*\(3, 1\)"):
        loop_transfer(ss(A, B, C, dt=0.1), linear_controller, _linear(A, B, C, np.ones((3, 1)), np.ones((1, 2))))
    plant, L_r = nominal_design()
    with pytest.raises(ValueError, match="steady-state"):
        loop_transfer(plant, active_observer_controller, with_feedback(active.make_ckf(plant, EXAMPLE1.R), L_r))


def _conditionally_stable_loops(count, seed=11, size=4):
    """Random loops that are open-loop unstable and stable when closed: a gain reduction destabilises them (a lower
    gain margin above 0), and they have an upper one too."""
    rng = np.random.default_rng(seed)
    loops = []
    while len(loops) < count:
        A, B, C = _random_loop(rng, size, radius=(1.02, 1.5), gain=(0.5, 3.0))
        if np.abs(np.linalg.eigvals(A - B @ C)).max() < 0.98:
            loops.append((A, B, C))
    return loops


def test_lower_and_upper_gain_margins_of_conditionally_stable_loops_agree_with_python_control():
    """The stable range of loop gains (lower, upper) is bounded by the phase crossovers nearest to 1 on either side:
    python-control's phase crossovers (returnall=True) plus z = 1 and z = -1 where H is real and negative there
    (python-control leaves those out); and the closed loop is unstable just outside the range, stable just inside."""
    for A, B, C in _conditionally_stable_loops(6):
        m = margins_jit(ss(A, B, C, dt=DT))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gm = np.atleast_1d(control.stability_margins(control.ss(A, B, C, 0, DT), returnall=True)[0])
        ends = _response(A, B, C, [0.0, np.pi]).real  # H is real at z = 1 and z = -1
        gains = np.concatenate([gm, 1.0 / np.abs(ends[ends < 0])])
        lower, upper = gains[gains < 1].max(initial=0.0), gains[gains > 1].min(initial=np.inf)
        assert lower > 0  # open-loop unstable, closed-loop stable: conditionally stable
        assert float(m.gain_margin_lower) == pytest.approx(lower, rel=1e-7)
        assert float(m.gain_margin_upper) == pytest.approx(upper, rel=1e-7)
        assert float(m.gain_margin) in (pytest.approx(float(m.gain_margin_lower)),
                                        pytest.approx(float(m.gain_margin_upper)))  # fmt: skip
        for k, stable in ((0.999 * lower, False), (1.001 * lower, True), (0.999 * upper, True), (1.001 * upper, False)):
            if np.isfinite(k):
                assert (np.abs(np.linalg.eigvals(A - k * B @ C)).max() < 1) == stable, k


def test_a_loop_that_is_not_conditionally_stable_has_lower_gain_margin_zero():
    m = margins_jit(ss([[0.5]], [[1.0]], [[0.4]], dt=DT))  # 0.4 / (z - 0.5): stable for gains in (0, 3.75)
    assert float(m.gain_margin_lower) == 0.0
    assert float(m.gain_margin_upper) == pytest.approx(3.75) == float(m.gain_margin)


def test_a_non_finite_loop_has_nan_margins_not_infinite_ones():
    """Under jit (eagerly such a loop is refused): every margin NaN, whatever entry is non-finite."""
    A, B, C, D = np.eye(2) * 0.5, np.ones((2, 1)), np.ones((1, 2)), np.zeros((1, 1))
    for bad in (np.nan, np.inf):
        for which in range(3):
            matrices = [np.array(M) for M in (A, B, C, D)]
            matrices[which][0, 0] = bad
            m = margins_jit(StateSpace(*map(jnp.asarray, matrices), DT))
            assert all(np.isnan(float(getattr(m, f))) for f in m._fields if f != "truncated"), (bad, which)
            assert not bool(m.truncated)


def _lqg(gain, dead_time):
    """robustness_metrics of an LQG designed on ``1 / (s + 1)`` (h = 0.1, no dead time) on the true plant
    ``gain / (s + 1)`` with ``dead_time`` (two slots: beyond 0.2 s the plant is invalid)."""
    nominal = c2d(ss([[-1.0]], [[1.0]], [[1.0]]), 0.1, 0.0, n_delay=2)
    L = dlqr(nominal.A, nominal.B, jnp.diag(jnp.array([1.0, 0.0, 0.0])), jnp.eye(1))[0]
    kf = make_kalman(nominal.A, nominal.C, 1e-2 * jnp.eye(3), jnp.eye(1), Gamma=nominal.B, steady_state=True)
    true = c2d(ss([[-1.0]], [[gain]], [[1.0]]), 0.1, dead_time, n_delay=2)
    return robustness_metrics(true, observer_controller(kalman_filter), FeedbackParams(kf, L), num_points=128)


def test_robustness_metrics_validity_and_stability_as_data():
    """A dead time beyond the plant's slots is invalid (NaN spectral radius, NaN margins: never inf); an unstable
    loop keeps its spectral radius and has NaN margins; a stable one has stability_margins' margins; jit(vmap) =
    jit of one (eagerly: the slow test below)."""
    gain, dead = jnp.array([1.0, 1.0, 500.0]), jnp.array([0.05, 0.25, 0.05])  # nominal, dead time too long, unstable
    batched = jax.jit(jax.vmap(_lqg))(gain, dead)
    assert batched["valid"].tolist() == [True, False, True]
    assert batched["stable"].tolist() == [True, False, False]
    assert np.isnan(batched["spectral_radius"][1]) and batched["spectral_radius"][2] > 1
    for name in ROBUSTNESS_MARGINS:
        assert not np.isnan(batched[name][0]), name
        assert np.isnan(batched[name][1:]).all(), name
    one = jax.jit(_lqg)(1.0, 0.05)
    for name, value in one.items():
        assert float(value) == pytest.approx(float(batched[name][0]), rel=1e-9), name


@pytest.mark.slow  # op by op
def test_robustness_metrics_eagerly_is_what_it_is_under_jit():
    eager, compiled = _lqg(1.0, 0.05), jax.jit(_lqg)(1.0, 0.05)
    for name, value in eager.items():
        assert float(value) == pytest.approx(float(compiled[name]), rel=1e-9), name


@pytest.mark.slow  # ~10 s of compilation
def test_the_aob_loops_are_conditionally_stable_as_python_control_says():
    """The Example 1 AOB-2 (the sweep's demo): a gain reduction destabilises it, at python-control's phase
    crossover below 1; robustness_metrics reports the same margins as stability_margins; a configuration flagged
    invalid (e.g. a design that did not converge) has none."""
    plant, L_r = nominal_design()
    params = _aob(plant, L_r, 2)
    loop = loop_transfer(plant, active_observer_controller, params)
    m = margins_jit(loop)
    gm = np.atleast_1d(control.stability_margins(control.ss(*map(np.asarray, (loop.A, loop.B, loop.C, loop.D)),
                                                            EXAMPLE1.h), returnall=True)[0])  # fmt: skip
    assert float(m.gain_margin_lower) == pytest.approx(gm[gm < 1].max(), rel=1e-6)
    assert float(m.gain_margin_upper) == pytest.approx(gm[gm > 1].min(), rel=1e-6)
    row = robustness_metrics(plant, active_observer_controller, params)
    for name in ROBUSTNESS_MARGINS:
        assert float(row[name]) == pytest.approx(float(getattr(m, name)), rel=1e-9), name
    flagged = robustness_metrics(plant, active_observer_controller, params, valid=False)
    assert not bool(flagged["valid"]) and np.isnan(float(flagged["gain_margin"]))
