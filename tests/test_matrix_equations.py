"""Tests for jaxobs.matrix_equations: the DARE (doubling + implicit gradients) against SciPy and as the limit of the
Kalman covariance sequence, the Stein solver, and Q/R scale invariance (the MRAC chapter Proposition 1). The
covariance steps themselves are tested in tests/test_kalman_steps.py."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from jaxobs.design import dlqe, dlqr
from jaxobs.kalman_steps import covariance_sequence, kalman_gain
from jaxobs.matrix_equations import care, dare, filter_dare, lyapunov, stein


def random_system(rng, n, m, rho=None, r_min=None):
    """A random filter model ``(Phi, C, Q, R)``: spectral radius ``rho`` (default uniform in [0.5, 1.2], so some
    systems are unstable), generic C (detectable), Q > 0 (stabilisable), R > 0 (smallest eigenvalue ``r_min``
    relative to its largest when given: nearly singular R)."""
    Phi = rng.normal(size=(n, n))
    rho = rng.uniform(0.5, 1.2) if rho is None else rho
    Phi *= rho / np.max(np.abs(np.linalg.eigvals(Phi)))
    C = rng.normal(size=(m, n))
    G = rng.normal(size=(n, n))
    Q = G @ G.T / n + 0.1 * np.eye(n)
    if r_min is None:
        Hm = rng.normal(size=(m, m))
        R = Hm @ Hm.T / m + 0.1 * np.eye(m)
    else:
        U, _ = np.linalg.qr(rng.normal(size=(m, m)))
        R = U @ np.diag(np.geomspace(1.0, r_min, m) if m > 1 else [r_min]) @ U.T
        R = (R + R.T) / 2
    return Phi, C, Q, R


# Compiled once per shape. Eager ``dare``/``covariance_sequence`` retrace their loop bodies on every call
# (~0.3 s each), so the property tests use these; eager == jit is checked in its own test below.
filter_dare_jit = jax.jit(lambda Phi, C, Q, R: dare(Phi.T, C.T, Q, R))  # the filter DARE of (Phi, C)
sequence_jit = jax.jit(covariance_sequence, static_argnums=5)


def rel_err(a, b):
    return np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b))


# ---------------------------------------------------------------------------------------------
# DARE against SciPy


@pytest.mark.parametrize("n, m", [(1, 1), (5, 2), (20, 4)])
def test_dare_matches_scipy(n, m):
    """dare(Phi.T, C.T, Q, R).X = scipy.linalg.solve_discrete_are(Phi', C', Q, R) (filter DARE) to 1e-9 relative, with
    converged True and a small residual, on random stabilisable/detectable systems (some unstable). The systematic
    comparison against an exact reference is tests/benchmarks/test_dare_accuracy.py."""
    Phi, C, Q, R = random_system(np.random.default_rng(1000 * n + m), n, m)
    sol = dare(Phi.T, C.T, Q, R)
    want = scipy.linalg.solve_discrete_are(Phi.T, C.T, Q, R)
    assert bool(sol.converged)
    assert float(sol.residual) < 1e-14
    assert rel_err(sol.X, want) <= 1e-9


@given(n=st.integers(1, 3), m=st.integers(1, 2), seed=st.integers(0, 2**32 - 1), rho=st.floats(0.1, 1.3))
def test_dare_matches_scipy_property(n, m, seed, rho):
    """Property: for random stabilisable/detectable systems the DARE solution equals SciPy's to 1e-9 relative and
    satisfies its own equation (residual flag)."""
    Phi, C, Q, R = random_system(np.random.default_rng(seed), n, m, rho=rho)
    sol = filter_dare_jit(Phi, C, Q, R)
    want = scipy.linalg.solve_discrete_are(Phi.T, C.T, Q, R)
    assert bool(sol.converged)
    assert rel_err(sol.X, want) <= 1e-9


def test_dare_example1_table1_noise_cortesao2006():
    """Example 1 model (Cortesão 2006 §7, Td = 5h) with Table I noise Q = 1e-12 I, R = 2.1e-2: a badly scaled DARE
    (closed-loop pole 1 - 7e-6). dare converges with a residual at rounding level and agrees with SciPy to 1e-6
    (SciPy's own error is 2e-7 on this problem, ours 2e-12: benchmarks/dare_accuracy.py, case "CKF")."""
    from jaxobs.lti import c2d, ss

    Tp, h = 0.032, 0.008
    sysd = c2d(ss([[0.0, 1.0], [0.0, -1.0 / Tp]], [[0.0], [3.0 / Tp]], [[1.0, 0.0]]), h, 5 * h)
    Phi, C = np.asarray(sysd.A), np.asarray(sysd.C)
    Q, R = 1e-12 * np.eye(7), np.array([[2.1e-2]])
    sol = dare(Phi.T, C.T, Q, R)
    assert bool(sol.converged)
    assert float(sol.residual) < 1e-14
    assert rel_err(sol.X, scipy.linalg.solve_discrete_are(Phi.T, C.T, Q, R)) < 1e-6


def test_dare_precise_sensor_issue13():
    """The precise-sensor example of issue 13: Phi = [[-0.5, 0.2], [-1.2, -0.9]], C = [[1.1, -0.9]], Q = g g' with
    g = [2.2, -1.7]: for R from 1 down to 1e-12 the solution equals the plain Riccati recursion's limit (iterated in
    float64 from the answer, 200 steps) to 1e-14 relative; the doubling alone was off by 1e-3 at R = 1e-12."""
    Phi = np.array([[-0.5, 0.2], [-1.2, -0.9]])
    C = np.array([[1.1, -0.9]])
    g = np.array([[2.2], [-1.7]])
    Q = g @ g.T
    for r in (1.0, 1e-4, 1e-8, 1e-12):
        R = np.array([[r]])
        sol = dare(Phi.T, C.T, Q, R)
        assert bool(sol.converged), r
        P = np.asarray(sol.X)
        for _ in range(200):  # P <- Phi P_post Phi' + Q with the Joseph-form P_post: contracting at the solution
            K = P @ C.T / (C @ P @ C.T + R)
            IKC = np.eye(2) - K @ C
            P = Phi @ (IKC @ P @ IKC.T + K @ R @ K.T) @ Phi.T + Q
        assert rel_err(sol.X, P) < 1e-14, r


def filter_spectral_radius(Phi, C, R, P):
    """Spectral radius of the steady-state filter Phi - K_p C, K_p = Phi P C' (C P C' + R)^{-1}."""
    P = np.asarray(P)
    Kp = Phi @ P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    return float(np.max(np.abs(np.linalg.eigvals(Phi - Kp @ C))))


# (name, Phi, C, Q, R, whether a stabilising solution exists)
FLAG_CASES = [
    ("unstable mode not excited by Q (issue 13)", np.diag([1.5, 0.5]), [[1.0, 1.0]], np.diag([0.0, 0.01]), True),
    ("undetectable mode on the unit circle (issue 13)", np.diag([1.0, 0.5]), [[0.0, 1.0]], np.eye(2), False),
    ("rotation with C = 0 (issue 13)", [[0.0, -1.0], [1.0, 0.0]], [[0.0, 0.0]], np.eye(2), False),
    ("unstable undetectable mode", np.diag([1.5, 0.5]), [[0.0, 1.0]], np.eye(2), False),
    ("unit-circle mode not excited by Q", np.diag([1.0, 0.5]), [[1.0, 1.0]], np.diag([0.0, 1.0]), False),
    ("integrator without process noise", [[1.0]], [[1.0]], [[0.0]], False),
    ("unstable, no process noise", [[1.0 + 1e-6]], [[1.0]], [[0.0]], True),
    ("stable, no process noise (P = 0)", np.diag([0.5, -0.3]), [[1.0, 0.0]], np.zeros((2, 2)), True),
    ("stable closed loop 1e-4 from the unit circle", 0.9999 * np.array([[0.6, -0.8], [0.8, 0.6]]), [[0.0, 0.0]],
     np.eye(2), True),
]  # fmt: skip


@pytest.mark.parametrize("case", FLAG_CASES, ids=[c[0] for c in FLAG_CASES])
def test_dare_converged_means_stabilising_solution_found(case):
    """converged is True exactly when a stabilising solution exists, and then the returned filter is stable and
    agrees with SciPy to 1e-8 (SciPy is 3e-9 off on the rotation; where SciPy returns a non-stabilising matrix or
    fails, converged is False). Before,
    the first three cases reported converged=True with the eigenvalue 1.5 kept, P = 1.8e17 and a rotation kept."""
    _, Phi, C, Q, exists = case
    Phi, C, Q, R = (np.atleast_2d(np.asarray(M, float)) for M in (Phi, C, Q, [[1.0]]))
    sol = dare(Phi.T, C.T, Q, R)
    assert bool(sol.converged) is exists
    if exists:
        assert filter_spectral_radius(Phi, C, R, sol.X) < 1
        want = scipy.linalg.solve_discrete_are(Phi.T, C.T, Q, R)
        np.testing.assert_allclose(sol.X, want, rtol=1e-8, atol=1e-12 * max(1.0, np.max(np.abs(want))))


def test_dare_flags_under_jit_and_vmap_equal_eager():
    """The flag is computed inside traced code: a batch mixing problems with and without a stabilising solution
    gives the eager flags under jit(vmap), with the same solutions where they exist."""
    cases = [c for c in FLAG_CASES if np.shape(c[1]) == (2, 2) and np.shape(c[2]) == (1, 2)]
    Phi, C, Q = (np.stack([np.asarray(c[k], float) for c in cases]) for k in (1, 2, 3))
    R = np.ones((len(cases), 1, 1))
    batched = jax.jit(jax.vmap(lambda Phi, C, Q, R: dare(Phi.T, C.T, Q, R)))(Phi, C, Q, R)
    for i, case in enumerate(cases):
        eager = dare(Phi[i].T, C[i].T, Q[i], R[i])
        assert bool(batched.converged[i]) is bool(eager.converged) is case[4], case[0]
        if case[4]:
            np.testing.assert_allclose(batched.X[i], eager.X, rtol=1e-13, atol=1e-15 * np.max(np.abs(eager.X)))


def test_closed_loop_test_by_squaring_near_the_unit_circle():
    """The GPU-friendly stability test (powers of the closed loop by repeated squaring, no eigenvalue solver) on
    200 random non-normal 6 x 6 matrices per spectral radius: all stable ones flagged stable and all unstable ones
    unstable for |rho - 1| >= 1e-14 (at 1e-15 and below rounding decides), also for a rotation (rho = 1 exactly:
    unstable) and a Jordan block with a 1e6 transient."""
    from jaxobs.matrix_equations import _smith

    rng = np.random.default_rng(7)
    M = rng.normal(size=(200, 6, 6))
    M /= np.max(np.abs(np.linalg.eigvals(M)), axis=-1)[:, None, None]
    decays = jax.jit(jax.vmap(lambda A: _smith(A, jnp.eye(6, dtype=A.dtype), 64)[1]))
    for k in (1, 4, 8, 12, 14):
        assert bool(np.all(decays(M * (1 - 10.0**-k)))), k
        assert not bool(np.any(decays(M * (1 + 10.0**-k)))), k
    special = np.stack([np.eye(6)[[1, 2, 3, 4, 5, 0]], 0.5 * np.eye(6) + 1e6 * np.eye(6, k=1)])
    assert decays(special).tolist() == [False, True]


# ---------------------------------------------------------------------------------------------
# gradients


def _grad_system():
    rng = np.random.default_rng(2)
    n, m = 3, 2
    Phi, C, _, _ = random_system(rng, n, m, rho=0.95)
    G = rng.normal(size=(n, n)) / np.sqrt(n)
    Hm = rng.normal(size=(m, m)) / np.sqrt(m) + 0.5 * np.eye(m)
    return Phi, C, G, Hm


def test_dare_gain_check_grads():
    """check_grads (fwd and rev, order 1) of the steady-state gain kalman_gain(dare(Phi.T, C.T, Q, R).X, C, R) w.r.t.
    Phi and the factors of Q = G G' and R = H H' (factored so the perturbed covariances stay symmetric): the
    implicit-function JVP/VJP of the DARE agrees with finite differences."""
    Phi, C, G, Hm = _grad_system()

    @jax.jit
    def gain(Phi, G, Hm):
        R = Hm @ Hm.T
        return kalman_gain(dare(Phi.T, C.T, G @ G.T + 0.1 * jnp.eye(3), R).X, C, R)

    check_grads(gain, (Phi, G, Hm), order=1, modes=("fwd", "rev"))


def test_dare_check_grads_precise_sensor_unstable_plant():
    """check_grads (fwd and rev) of the gain w.r.t. Phi and G with a precise sensor on an unstable plant (R = 1e-8
    H H', spectral radius 1.5), the regime where the refinement matters: the implicit rule at the refined solution
    agrees with finite differences."""
    Phi, C, G, Hm = _grad_system()
    Phi = Phi * 1.5 / np.max(np.abs(np.linalg.eigvals(Phi)))
    R = 1e-8 * (Hm @ Hm.T)

    @jax.jit
    def gain(Phi, G):
        return kalman_gain(dare(Phi.T, C.T, G @ G.T + 0.1 * jnp.eye(3), R).X, C, R)

    check_grads(gain, (Phi, G), order=1, modes=("fwd", "rev"), eps=1e-6)


def test_dare_gradient_is_implicit():
    """Reverse mode does not differentiate through the iterations: the gradient's jaxpr holds the Stein solves of the
    implicit rule (custom_linear_solve) and no transposed while loop, and the flag and residual carry no tangent."""
    Phi, C, G, Hm = _grad_system()
    R = Hm @ Hm.T
    loss = lambda Phi: jnp.sum(dare(Phi.T, C.T, G @ G.T, R).X)
    jaxpr = str(jax.make_jaxpr(jax.grad(loss))(Phi))
    assert "custom_lin" in jaxpr or "linear_solve" in jaxpr
    _, tangents = jax.jvp(lambda Phi: dare(Phi.T, C.T, G @ G.T, R), (Phi,), (jnp.ones_like(Phi),))
    assert float(jnp.max(jnp.abs(tangents.residual))) == 0.0


def test_dare_implicit_gradient_equals_unrolled_recursion():
    """The implicit DARE gradient equals backpropagation through 2000 unrolled Riccati steps (last gain of
    covariance_sequence), w.r.t. Phi, G (Q = GG') and H (R = HH'), to 1e-8."""
    Phi, C, G, Hm = _grad_system()
    W = jnp.asarray(np.random.default_rng(3).normal(size=(3, 2)))

    def implicit(Phi, G, Hm):
        Q, R = G @ G.T, Hm @ Hm.T
        return jnp.sum(W * kalman_gain(dare(Phi.T, C.T, Q, R).X, C, R))

    def unrolled(Phi, G, Hm):
        Q, R = G @ G.T, Hm @ Hm.T
        return jnp.sum(W * covariance_sequence(Q, Phi, C, Q, R, 2000).K[-1])

    g_imp = jax.jit(jax.grad(implicit, argnums=(0, 1, 2)))(Phi, G, Hm)
    g_unr = jax.jit(jax.grad(unrolled, argnums=(0, 1, 2)))(Phi, G, Hm)
    for a, b in zip(g_imp, g_unr, strict=True):
        assert np.max(np.abs(np.asarray(b))) > 1e-3
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8)


# ---------------------------------------------------------------------------------------------
# covariance_sequence


def test_covariance_sequence_converges_to_dare():
    """Iterating eq. 27-29 from P_{-1} = Q_0 converges to the DARE: last a-priori P equals dare().X and the last
    gain equals the steady-state gain kalman_gain(dare().X, C, R)."""
    rng = np.random.default_rng(4)
    Phi, C, Q, R = random_system(rng, 4, 2, rho=1.1)
    seq = covariance_sequence(Q, Phi, C, Q, R, 400)
    sol = dare(Phi.T, C.T, Q, R)
    assert seq.P.shape == (400, 4, 4) and seq.K.shape == (400, 4, 2) and seq.P_prior.shape == (400, 4, 4)
    np.testing.assert_allclose(seq.P_prior[-1], sol.X, rtol=1e-10)
    np.testing.assert_allclose(seq.K[-1], kalman_gain(sol.X, C, R), rtol=1e-10)
    # the first step starts from P_init: P1_0 = Phi P_init Phi' + Q
    np.testing.assert_allclose(seq.P_prior[0], Phi @ Q @ Phi.T + Q, rtol=1e-13)


@given(seed=st.integers(0, 2**32 - 1), log_alpha=st.floats(-3.0, 3.0))
def test_kalman_gain_scale_invariance_mrac_chapter_prop1(seed, log_alpha):
    """The MRAC chapter Proposition 1 (eq. 55): scaling Q, R and P_{-1} by alpha > 0 leaves every gain K_k unchanged and
    scales every covariance by alpha."""
    alpha = 10.0**log_alpha
    Phi, C, Q, R = random_system(np.random.default_rng(seed), 3, 2)
    base = sequence_jit(Q, Phi, C, Q, R, 50)
    scaled = sequence_jit(alpha * Q, Phi, C, alpha * Q, alpha * R, 50)
    np.testing.assert_allclose(scaled.K, base.K, rtol=1e-9, atol=1e-12 * np.max(np.abs(base.K)))
    np.testing.assert_allclose(scaled.P, alpha * base.P, rtol=1e-9, atol=1e-12 * alpha * np.max(np.abs(base.P)))
    np.testing.assert_allclose(scaled.P_prior, alpha * base.P_prior, rtol=1e-9)


def test_dare_and_sequence_jit_vmap_equal_eager():
    """Transformation test: dare and covariance_sequence give the same results eagerly, under jit, and under vmap
    over a batch of Phi (vs a Python loop)."""
    rng = np.random.default_rng(5)
    systems = [random_system(rng, 3, 2, rho=r) for r in (0.6, 0.9, 1.15)]
    C, Q, R = systems[0][1:]
    Phis = jnp.asarray(np.stack([s[0] for s in systems]))
    dare_j = jax.jit(lambda Phi: dare(Phi.T, C.T, Q, R))
    dare_v = jax.jit(jax.vmap(lambda Phi: dare(Phi.T, C.T, Q, R)))(Phis)
    seq_j = jax.jit(lambda Phi: covariance_sequence(Q, Phi, C, Q, R, 30))
    seq_v = jax.jit(jax.vmap(lambda Phi: covariance_sequence(Q, Phi, C, Q, R, 30)))(Phis)
    for i in range(3):
        eager = dare(Phis[i].T, C.T, Q, R)
        for got in (dare_j(Phis[i]), jax.tree.map(lambda x, i=i: x[i], dare_v)):
            np.testing.assert_allclose(got.X, eager.X, rtol=1e-12)
            assert bool(got.converged) == bool(eager.converged) is True
            assert float(got.residual) < 1e-10
        seq = covariance_sequence(Q, Phis[i], C, Q, R, 30)
        for got in (seq_j(Phis[i]), jax.tree.map(lambda x, i=i: x[i], seq_v)):
            for a, b in zip(got, seq, strict=True):
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


def test_double_word_products_are_exact_to_working_precision_squared():
    """The DARE residual's double-word products (jaxobs.matrix_equations._dot2: exact slice products summed by TwoSum)
    under jit, for entries spanning 16 orders of magnitude: error below 1e-18 of |a| |b| in float64 (the float64
    product errs by 1e-16) and below 1e-10 in float32, checked against exact rational arithmetic. Guards the
    compiler against re-associating the error-free transformations."""
    from fractions import Fraction

    from jaxobs.matrix_equations import _dot2

    rng = np.random.default_rng(11)
    for dtype, bound in ((np.float64, 1e-18), (np.float32, 1e-10)):
        a = (rng.normal(size=(6, 5)) * 10.0 ** rng.integers(-8, 8, size=(6, 5))).astype(dtype)
        b = rng.normal(size=(5, 4)).astype(dtype)
        hi, lo = (np.asarray(M) for M in jax.jit(_dot2)(a, b))
        assert hi.dtype == dtype
        for i in range(6):
            for j in range(4):
                exact = sum(Fraction(float(a[i, k])) * Fraction(float(b[k, j])) for k in range(5))
                scale = float(np.abs(a[i]).astype(float) @ np.abs(b[:, j]).astype(float))
                assert abs(float(Fraction(float(hi[i, j])) + Fraction(float(lo[i, j])) - exact)) <= bound * scale


def test_stein_matches_scipy():
    """stein solves X = A X A' + E (Smith doubling) like scipy.linalg.solve_discrete_lyapunov."""
    rng = np.random.default_rng(6)
    A = rng.normal(size=(4, 4))
    A *= 0.9 / np.max(np.abs(np.linalg.eigvals(A)))
    E = rng.normal(size=(4, 4))
    X = np.asarray(stein(A, E))
    np.testing.assert_allclose(X, scipy.linalg.solve_discrete_lyapunov(A, E), rtol=1e-10)
    np.testing.assert_allclose(X, A @ X @ A.T + E, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("solver", ["stein", "lyapunov"])
def test_stein_and_lyapunov_reverse_mode_is_the_adjoint_solve_issue46(solver):
    """Reverse-mode gradients of stein and lyapunov (implicit: the adjoint Stein/Lyapunov equation of A', no
    backpropagation through the while loop) equal central differences to 1e-6, in A and in E, eagerly and under
    jit; forward mode agrees."""
    rng = np.random.default_rng(46)
    A = rng.normal(size=(3, 3))
    A = 0.8 * A / np.max(np.abs(np.linalg.eigvals(A))) if solver == "stein" else A - 4.0 * np.eye(3)
    E, W = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    solve = {"stein": stein, "lyapunov": lyapunov}[solver]
    for argnum in (0, 1):
        x, d = (A, E)[argnum], rng.normal(size=(3, 3))

        def loss(x, argnum=argnum):
            args = [A, E]
            args[argnum] = x
            return jnp.sum(W * solve(*args))

        central = (loss(x + 1e-6 * d) - loss(x - 1e-6 * d)) / 2e-6
        for grad in (jax.grad(loss), jax.jit(jax.grad(loss))):
            np.testing.assert_allclose(np.vdot(grad(x), d), central, rtol=1e-6)
        np.testing.assert_allclose(jax.jvp(loss, (x,), (d,))[1], central, rtol=1e-6)


def test_riccati_solvers_take_nested_lists_eagerly_and_under_jit_issue46():
    """dare, care, dlqr and dlqe read nested lists (also of traced scalars under jit) as arrays, as make_kalman and
    ss do: the same solution as from arrays."""
    A, B = [[1.0, 0.1], [0.0, 1.0]], [[0.0], [0.1]]
    want = dare(np.array(A), np.array(B), np.eye(2), np.eye(1)).X
    np.testing.assert_allclose(dare(A, B, [[1.0, 0.0], [0.0, 1.0]], [[1.0]]).X, want, rtol=1e-12)
    under_jit = jax.jit(lambda q: dare(A, B, [[q, 0.0], [0.0, q]], [[1.0]]).X)(1.0)
    np.testing.assert_allclose(under_jit, want, rtol=1e-12)
    Ac = [[0.0, 1.0], [2.0, -1.0]]
    np.testing.assert_allclose(care(Ac, B, [[1.0, 0.0], [0.0, 1.0]], [[1.0]]).X,
                               care(np.array(Ac), np.array(B), np.eye(2), np.eye(1)).X, rtol=1e-12)  # fmt: skip
    K_list, _, _ = dlqr(A, B, [[1.0, 0.0], [0.0, 1.0]], [[1.0]])
    np.testing.assert_allclose(K_list, dlqr(np.array(A), np.array(B), np.eye(2), np.eye(1))[0], rtol=1e-12)
    L_list = jax.jit(lambda r: dlqe(A, [[0.0], [1.0]], [[1.0, 0.0]], [[r]], [[1.0]])[0])(0.5)
    np.testing.assert_allclose(L_list, dlqe(np.array(A), np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]]),
                                            0.5 * np.eye(1), np.eye(1))[0], rtol=1e-12)  # fmt: skip


@pytest.mark.parametrize("name", ["A", "B", "Q", "R"])
def test_dare_refuses_a_batch_axis_naming_the_argument_issue46(name):
    """A leading batch axis on any argument of dare (documented: single matrices; vmap for a batch) raises a
    ValueError naming that argument, also under jit."""
    args = dict(zip("ABQR", (np.diag([0.9, 0.5]), np.array([[1.0], [0.0]]), np.eye(2), np.eye(1)), strict=True))
    args[name] = np.stack([args[name]] * 3)
    with pytest.raises(ValueError, match=rf"^{name} must be a 2-D matrix; one matrix, not a batch"):
        dare(**args)
    with pytest.raises(ValueError, match=rf"^{name} "):
        jax.jit(lambda a: dare(**a))(args)


# ---------------------------------------------------------------------------------------------
# bad input


def _good():
    return np.diag([0.9, 0.5]), np.array([[1.0, 0.0]]), np.eye(2), np.eye(1)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(Q=np.array([[1.0, 0.5], [0.0, 1.0]])), "Q"),  # not symmetric
        (dict(Q=np.diag([1.0, -0.5])), "Q"),  # indefinite
        (dict(R=np.zeros((1, 1))), "R"),  # singular
        (dict(R=np.eye(2)), "R"),  # wrong size
        (dict(Q=np.eye(3)), "Q"),  # wrong size
        (dict(C=np.ones((1, 3))), "C"),  # wrong number of columns
        (dict(Phi=np.ones((2, 3))), "Phi"),  # not square
        (dict(Phi=np.array([[np.nan, 0.0], [0.0, 0.5]])), "Phi"),  # not finite
    ],
)
def test_dare_rejects_bad_input(kwargs, name):
    """Eager validation of dare (DESIGN.md "Errors"): ValueError naming the argument, in dare's control form
    ``(A, B) = (Phi', C')`` and in the filter form of filter_dare."""
    args = dict(zip(("Phi", "C", "Q", "R"), _good(), strict=True))
    args.update(kwargs)
    control_name = {"Phi": "A", "C": "B"}.get(name, name)
    with pytest.raises(ValueError, match=rf"^{control_name}\b"):
        dare(args["Phi"].T, args["C"].T, args["Q"], args["R"])
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        filter_dare(args["Phi"], args["C"], args["Q"], args["R"])


# ---------------------------------------------------------------------------------------------
# Traced flags that never lie (issue 28): Q and R are checked eagerly only, so under jit an indefinite Q or R
# reaches the solvers; converged must then stay False unless the answer is a finite PSD solution.

care_jit = jax.jit(lambda A, B, Q, R: care(A, B, Q, R))


def _indefinite(rng, n, lowest):
    """A random symmetric (n, n) matrix with the smallest eigenvalue ``lowest`` (< 0) and the others in [0.1, 2]."""
    U, _ = np.linalg.qr(rng.normal(size=(n, n)))
    eig = np.concatenate([[lowest], rng.uniform(0.1, 2.0, n - 1)])
    return (U * eig) @ U.T


def _well_posed(X, B, R):
    """X finite and positive semidefinite (to 1e-7 of its size) and R + B'XB positive definite."""
    X = np.asarray(X)
    if not np.all(np.isfinite(X)):
        return False
    lowest = np.min(np.linalg.eigvalsh((X + X.T) / 2))
    return lowest >= -1e-7 * max(np.max(np.abs(X)), 1.0) and np.min(np.linalg.eigvalsh(R + B.T @ X @ B)) > 0


def test_traced_dare_with_indefinite_Q_is_not_converged_issue28():
    """The issue's example: jit(dare) of the filter DARE of Phi = diag(0.5, 0.5), C = [[0, 1]], Q = diag(1, -1),
    R = 0.1 returned an X with the eigenvalue -0.97 flagged converged; now converged is False (and a PSD Q still
    converges under jit)."""
    Phi, C, R = np.diag([0.5, 0.5]), np.array([[0.0, 1.0]]), np.array([[0.1]])
    bad = filter_dare_jit(Phi, C, np.diag([1.0, -1.0]), R)
    assert np.min(np.linalg.eigvalsh(bad.X)) < -0.9
    assert not bool(bad.converged)
    assert bool(filter_dare_jit(Phi, C, np.diag([1.0, 1.0]), R).converged)


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 3), m=st.integers(1, 2), seed=st.integers(0, 2**32 - 1), lowest=st.floats(-2.0, -1e-3),
       bad_R=st.booleans())  # fmt: skip
def test_traced_riccati_flags_never_report_an_indefinite_solution_property(n, m, seed, lowest, bad_R):
    """Property: under jit, with Q indefinite (or R indefinite), dare and care report converged only with a finite
    positive semidefinite X and R + B'XB (care: R) positive definite."""
    rng = np.random.default_rng(seed)
    Phi, C, Q, R = random_system(rng, n, m)
    if bad_R:
        R = _indefinite(rng, m, lowest)
    else:
        Q = _indefinite(rng, n, lowest)
    sol = filter_dare_jit(Phi, C, Q, R)
    assert not bool(sol.converged) or _well_posed(sol.X, C.T, R)
    sol = care_jit(Phi - np.eye(n), C.T, Q, R)
    assert not bool(sol.converged) or _well_posed(sol.X, np.zeros_like(C.T), R)
    if bad_R:  # an indefinite R is never a valid problem
        assert not bool(sol.converged)
