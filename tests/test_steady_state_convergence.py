"""Eager steady-state design calls act on the DARE's converged flag (issue 13 §1): make_kalman / with_steady_state_gain,
make_aob / make_ckf / with_steady_state_gains and dlqr raise ValueError with the reason when the solve did not
find the stabilising solution; traced code stores the flag in the params (gain_converged) and every filter step
reports it (outputs.converged), so run / simulate traces carry it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.closed_loop import simulate
from jaxobs.design import dlqr
from jaxobs.observers import EstimatorInputs, run
from jaxobs.observers.active import active_observer_controller, make_aob, make_ckf
from jaxobs.observers.kalman import kalman_filter, make_kalman
from jaxobs.papers.cortesao.force_control import EXAMPLE1, nominal_design, with_feedback

R1 = np.eye(1)

# (Phi, C, Q, the reason's wording)
NO_STABILISING_SOLUTION = [
    (np.diag([1.0, 0.5]), [[0.0, 1.0]], np.eye(2), "not detectable"),
    (np.array([[0.0, -1.0], [1.0, 0.0]]), [[0.0, 0.0]], np.eye(2), "not detectable"),
    (np.diag([1.0, 0.5]), [[1.0, 1.0]], np.diag([0.0, 1.0]), "not excited by Q"),
]


@pytest.mark.parametrize("Phi, C, Q, reason", NO_STABILISING_SOLUTION)
def test_make_kalman_steady_state_raises_with_the_reason(Phi, C, Q, reason):
    """No stabilising solution: make_kalman(steady_state=True) raises ValueError naming the DARE and the reason (the
    undetectable mode or the unit-circle mode Q does not excite), instead of returning a filter flagged converged."""
    with pytest.raises(ValueError, match=rf"Kalman filter's DARE did not converge: .*{reason}"):
        make_kalman(Phi, C, Q, R1, steady_state=True)


def test_make_kalman_unexcited_unstable_mode_gets_the_stabilising_gain():
    """Phi = diag(1.5, 0.5), C = [[1, 1]], Q = diag(0, 0.01) (issue 13): the stabilising solution exists and is found
    (the filter Phi (I - K C) is stable, with SciPy's eigenvalues; before, it kept the eigenvalue 1.5), flagged
    converged."""
    import scipy.linalg

    Phi, C, Q = np.diag([1.5, 0.5]), np.array([[1.0, 1.0]]), np.diag([0.0, 0.01])
    params = make_kalman(Phi, C, Q, R1, steady_state=True)
    assert bool(params.gain_converged)
    P = scipy.linalg.solve_discrete_are(Phi.T, C.T, Q, R1)
    K_scipy = P @ C.T / (C @ P @ C.T + R1)
    closed = [Phi @ (np.eye(2) - np.asarray(K) @ C) for K in (params.gain, K_scipy)]  # x_prior -> x_prior
    ours, theirs = (np.sort(np.abs(np.linalg.eigvals(M))) for M in closed)
    assert ours[-1] < 1
    np.testing.assert_allclose(ours, theirs, rtol=1e-12)


def test_traced_steady_state_flag_is_stored_and_reported_by_every_step():
    """Under jit the design does not raise: the flag lands in params.gain_converged (False for the undetectable
    Phi = diag(1, 0.5), C = [[0, 1]], True for a detectable one) and run() reports it at every step."""
    C, Q = np.array([[0.0, 1.0]]), np.eye(2)

    @jax.jit
    def outputs(Phi):
        params = make_kalman(Phi, C, Q, R1, steady_state=True)
        y = jnp.zeros((5, 1))
        return params.gain_converged, run(kalman_filter, params, EstimatorInputs(y=y))[1].converged

    for Phi, want in ((np.diag([1.0, 0.5]), False), (np.diag([0.9, 0.5]), True)):
        flag, per_step = outputs(Phi)
        assert bool(flag) is want
        assert np.asarray(per_step).tolist() == [want] * 5
    # time-varying filters report True (no steady-state solve)
    params = make_kalman(np.diag([0.9, 0.5]), C, Q, R1)
    assert params.gain_converged is None
    _, out = run(kalman_filter, params, EstimatorInputs(y=jnp.zeros((3, 1))))
    assert bool(np.all(out.converged))


@pytest.mark.slow  # ~10 s: float32 and float64 designs
def test_make_aob_float32_raises_and_float64_matches():
    """The AOB designs of Cortesão 2006 Example 1 (Q entries 1e-12 next to 1e-3): AOB-3 built in float32 raises
    ValueError telling to enable float64 (before, it silently got gains of 1e-10 instead of 0.17, 1.95, ...); AOB-1
    in float32 now converges, to its float64 gains within 1e-5 relative."""
    plant, L_r = nominal_design(EXAMPLE1)
    plant32 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32), plant)
    kwargs = dict(q_plant=EXAMPLE1.q_plant, steady_state=True)
    with pytest.raises(ValueError, match=r"AOB-3 steady-state gain's DARE did not converge: float32 .*jax_enable_x64"):
        make_aob(plant32, 3, np.float32(EXAMPLE1.R), q_active=np.float32(2.4e-8), **kwargs)
    aob32 = make_aob(plant32, 1, np.float32(EXAMPLE1.R), q_active=np.float32(1e-3), **kwargs)
    aob64 = make_aob(plant, 1, EXAMPLE1.R, q_active=1e-3, **kwargs)
    assert aob32.gain.dtype == jnp.float32 and bool(aob32.gain_converged)
    np.testing.assert_allclose(aob32.gain, aob64.gain, rtol=1e-5)


def test_aob_flag_travels_through_simulate():
    """A CKF designed under jit with a traced Q reports its flag in simulate()'s controller outputs."""
    plant, L_r = nominal_design(EXAMPLE1)

    @jax.jit
    def trace(q):
        params = with_feedback(make_ckf(plant, EXAMPLE1.R, Q=q * jnp.eye(plant.n_states), steady_state=True), L_r)
        return simulate(plant, active_observer_controller, params, jnp.ones((4,))).controller.estimator.converged

    assert np.asarray(trace(1e-6)).tolist() == [True] * 4


def test_dlqr_gain_stabilises_where_the_input_reaches_the_unstable_mode():
    """The stabilisable neighbour of dlqr's failure case (A = diag(1.2, 0.5), B = [1, 1]'; the failure itself is
    tested in test_design): the returned closed-loop eigenvalues are those of A - B K, inside the unit circle."""
    A, B = np.diag([1.2, 0.5]), np.array([[1.0], [1.0]])
    K, _, E = dlqr(A, B, np.eye(2), R1)
    np.testing.assert_allclose(np.sort(np.abs(E)), np.sort(np.abs(np.linalg.eigvals(A - B @ np.asarray(K)))))
    assert np.max(np.abs(E)) < 1


def test_traced_indefinite_Q_is_never_reported_converged_issue28():
    """The issue's example: jit(make_kalman(diag(.5, .5), [[0, 1]], q, [[.1]], steady_state=True)) at q = diag(1, -1)
    (an indefinite Q that the eager check refuses) reported gain_converged=True with the gain [nan, nan], and every
    step converged; now the flag is False, at every step too. The same for the AOB's CKF and the H-infinity filter's
    steady state (whose covariance had the eigenvalue -0.016 at q = diag(1, -0.01))."""
    from jaxobs.observers.hinf import hinf_steady_state

    Phi, C, R = np.diag([0.5, 0.5]), np.array([[0.0, 1.0]]), np.array([[0.1]])

    @jax.jit
    def kalman(q):
        params = make_kalman(Phi, C, q, R, steady_state=True)
        return params.gain, params.gain_converged, run(kalman_filter, params, EstimatorInputs(y=jnp.zeros((3, 1))))[1]

    gain, flag, out = kalman(np.diag([1.0, -1.0]))
    assert not np.all(np.isfinite(gain)) and not bool(flag)
    assert np.asarray(out.converged).tolist() == [False] * 3
    assert bool(kalman(np.diag([1.0, 1.0]))[1])

    plant = nominal_design(EXAMPLE1)[0]
    ckf = jax.jit(lambda q: make_ckf(plant, EXAMPLE1.R, Q=q, steady_state=True).gain_converged)
    indefinite = np.eye(plant.n_states)
    indefinite[0, 0] = -1.0
    assert not bool(ckf(indefinite))

    hinf = jax.jit(lambda q: hinf_steady_state(Phi, C, np.eye(2), q, R, 10.0))
    for q, want in ((np.diag([1.0, -0.01]), False), (np.diag([1.0, -1.0]), False), (np.eye(2), True)):
        sol = hinf(q)
        assert bool(sol.converged) is want
        if want:
            assert np.min(np.linalg.eigvalsh(sol.P)) > 0
