"""Tests for the continuous-time Riccati tools: jaxobs.matrix_equations.care (Cayley transform onto the DARE
machinery, then Newton-Kleinman, implicit gradients), jaxobs.matrix_equations.lyapunov, and jaxobs.design.lqr /
lqe / is_detectable.

Oracles: scipy.linalg.solve_continuous_are and python-control on well-conditioned problems; an exact reference (the
stable invariant subspace of the Hamiltonian in 50-digit mpmath arithmetic, rounded once) where SciPy itself loses
digits (precise inputs, R down to 1e-12)."""

import control
import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
import scipy.linalg
import scipy.optimize
from jax.test_util import check_grads

from jaxobs.design import is_detectable, lqe, lqr
from jaxobs.matrix_equations import _care_nominal_shift, _care_shift, care, lyapunov


def rel_err(a, b):
    return float(np.linalg.norm(np.asarray(a) - b) / np.linalg.norm(b))


def reference_care(A, B, Q, R, digits: int = 50):
    """The stabilising CARE solution from the stable eigenvectors ``[U1; U2]`` of the Hamiltonian
    ``[[A, -G], [-Q, -A']]`` in ``digits``-digit arithmetic, ``X = U2 U1^{-1}``, rounded once to float64."""
    with mpmath.workdps(digits):
        n = A.shape[0]
        Am, Bm, Qm, Rm = (mpmath.matrix(np.asarray(M, float).tolist()) for M in (A, B, Q, R))
        Gm = Bm * mpmath.inverse(Rm) * Bm.T
        H = mpmath.matrix(2 * n, 2 * n)
        for i in range(n):
            for j in range(n):
                H[i, j], H[i, n + j] = Am[i, j], -Gm[i, j]
                H[n + i, j], H[n + i, n + j] = -Qm[i, j], -Am[j, i]
        values, vectors = mpmath.eig(H)
        stable = [k for k in range(2 * n) if mpmath.re(values[k]) < 0]
        assert len(stable) == n, "the Hamiltonian has eigenvalues on the imaginary axis"
        U = mpmath.matrix(2 * n, n)
        for c, k in enumerate(stable):
            for i in range(2 * n):
                U[i, c] = vectors[i, k]
        X = U[n:, :] * mpmath.inverse(U[:n, :])
        return np.array([[float(mpmath.re(X[i, j])) for j in range(n)] for i in range(n)])


def random_problem(rng, n, m, r_scale=1.0, shift=0.0):
    """A random CARE ``(A, B, Q, R)``: ``A`` Gaussian plus ``shift I`` (unstable for ``shift > 0``), ``(A, B)`` with a
    well-conditioned controllability matrix, ``Q > 0`` and ``R = r_scale H H'`` with ``H H'`` well conditioned."""
    while True:
        A = rng.normal(size=(n, n)) + shift * np.eye(n)
        B = rng.normal(size=(n, m))
        if np.linalg.cond(control.ctrb(A, B)) < 1e3:
            break
    G = rng.normal(size=(n, n))
    Hm = rng.normal(size=(m, m)) + 2 * np.eye(m)
    return A, B, G @ G.T / n + 0.1 * np.eye(n), r_scale * (Hm @ Hm.T)


def closed_loop_abscissa(A, B, R, X):
    """Largest real part of the eigenvalues of ``A - B R^{-1} B' X``."""
    return float(np.max(np.linalg.eigvals(A - B @ np.linalg.solve(R, B.T) @ np.asarray(X)).real))


# ---------------------------------------------------------------------------------------------
# accuracy


@pytest.mark.parametrize("n, m", [(3, 1), (4, 2)])
def test_care_matches_scipy_on_random_systems(n, m):
    """care(A, B, Q, R).X = scipy.linalg.solve_continuous_are(A, B, Q, R) to 1e-9 relative on 12 random problems per
    shape: stable and unstable A (shifts -2, 0, +2), R from 1 down to 1e-4 of Q; converged, and the closed loop
    A - B K Hurwitz."""
    rng = np.random.default_rng(100 * n + m)
    for shift in (-2.0, 0.0, 2.0):
        for r_scale in (1.0, 1e-2, 1e-4, 1.0):
            A, B, Q, R = random_problem(rng, n, m, r_scale, shift)
            sol = care(A, B, Q, R)
            want = scipy.linalg.solve_continuous_are(A, B, Q, R)
            assert bool(sol.converged), (shift, r_scale)
            assert float(sol.residual) < 1e-12
            assert rel_err(sol.X, want) <= 1e-9, (shift, r_scale, rel_err(sol.X, want))
            assert closed_loop_abscissa(A, B, R, sol.X) < 0


@pytest.mark.parametrize("r_scale", [1e-8, 1e-12])
def test_care_precise_input_against_exact_reference(r_scale):
    """Precise inputs (R = 1e-8 and 1e-12 of Q) on unstable plants, n = 4, m = 2: care equals the exact stabilising
    solution (50 digits, rounded once) to 1e-13 relative, where SciPy's Schur method loses digits (its errors on
    these problems are printed with -s)."""
    rng = np.random.default_rng(7)
    for _ in range(3):
        A, B, Q, R = random_problem(rng, 4, 2, r_scale, shift=1.0)
        sol = care(A, B, Q, R)
        exact = reference_care(A, B, Q, R)
        print(f"R = {r_scale:g} Q: ours {rel_err(sol.X, exact):.1e}, SciPy "
              f"{rel_err(scipy.linalg.solve_continuous_are(A, B, Q, R), exact):.1e}")  # fmt: skip
        assert bool(sol.converged)
        assert rel_err(sol.X, exact) <= 1e-13, rel_err(sol.X, exact)


def test_care_eigenvalue_of_A_at_the_nominal_shift():
    """The nominal Cayley shift (the geometric mean of the Hamiltonian's eigenvalue moduli) can be an eigenvalue of A,
    where A - gamma I is singular: the conditioning test moves the shift, and care still solves the problem.
    Two cases: A = diag(2, -2) with Q = 0 (the nominal shift is |det A|^(1/2) = 2 exactly), and a 3-state A with
    Q > 0 whose real eigenvalue s is placed at the nominal shift of A(s) by root finding (cond(A - gamma I) there
    > 1e10)."""
    # diag(2, -2), Q = 0: the unstable mode is mirrored, the stable one untouched
    A, B, Q, R = np.diag([2.0, -2.0]), np.array([[1.0], [1.0]]), np.zeros((2, 2)), np.eye(1)
    assert float(_care_nominal_shift(A, B @ B.T, Q)) == pytest.approx(2.0, rel=1e-14)
    assert abs(float(_care_shift(A, B @ B.T, Q)) - 2.0) > 0.1
    sol = care(A, B, Q, R)
    assert bool(sol.converged)
    assert rel_err(sol.X, scipy.linalg.solve_continuous_are(A, B, Q, R)) <= 1e-12
    # a generic A(s) = T diag(s, -1, -3) T^-1 with s solving s = nominal shift of A(s)
    rng = np.random.default_rng(3)
    T = rng.normal(size=(3, 3)) + 3 * np.eye(3)
    B, R = rng.normal(size=(3, 1)), np.eye(1)
    Q = np.diag([1.0, 0.5, 0.2])
    A_of = lambda s: T @ np.diag([s, -1.0, -3.0]) @ np.linalg.inv(T)
    nominal = jax.jit(lambda A: _care_nominal_shift(A, jnp.asarray(B @ B.T), jnp.asarray(Q)))
    s = scipy.optimize.brentq(lambda s: s - float(nominal(A_of(s))), 0.05, 50.0, xtol=1e-15)
    A = A_of(s)
    assert np.min(np.abs(np.linalg.eigvals(A) - float(nominal(A)))) < 1e-12
    assert np.linalg.cond(A - float(nominal(A)) * np.eye(3)) > 1e10
    shift = float(_care_shift(jnp.asarray(A), jnp.asarray(B @ B.T), jnp.asarray(Q)))
    assert np.linalg.cond(A - shift * np.eye(3)) < 1e3
    sol = care(A, B, Q, R)
    assert bool(sol.converged)
    assert rel_err(sol.X, reference_care(A, B, Q, R)) <= 1e-13


@pytest.mark.slow
def test_care_float32():
    """In float32 the same program runs in float32 (dtype-polymorphic) and agrees with SciPy's float64 answer to
    1e-6 on a well-conditioned problem."""
    A, B, Q, R = random_problem(np.random.default_rng(5), 3, 1)
    sol = care(*(jnp.asarray(M, jnp.float32) for M in (A, B, Q, R)))
    assert sol.X.dtype == jnp.float32 and bool(sol.converged)
    assert rel_err(sol.X, scipy.linalg.solve_continuous_are(A, B, Q, R)) < 1e-6


# ---------------------------------------------------------------------------------------------
# the converged flag


# (name, A, B, Q, whether a stabilising solution exists); R = 1
FLAG_CASES = [
    ("unstable mode not penalised by Q", np.diag([1.5, -0.5]), [[1.0], [1.0]], np.diag([0.0, 0.01]), True),
    ("unstable mode not moved by B", np.diag([1.0, -1.0]), [[0.0], [1.0]], np.eye(2), False),
    ("imaginary-axis mode not moved by B", np.diag([0.0, -1.0]), [[0.0], [1.0]], np.eye(2), False),
    ("oscillator, Q = 0", [[0.0, 1.0], [-1.0, 0.0]], [[0.0], [1.0]], np.zeros((2, 2)), False),
    ("double integrator, Q = 0", [[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], np.zeros((2, 2)), False),
    ("unstable, Q = 0 (modes mirrored)", [[0.3, 1.0], [0.0, 0.2]], [[0.0], [1.0]], np.zeros((2, 2)), True),
    ("stable, Q = 0 (X = 0)", np.diag([-0.5, -0.3]), [[1.0], [0.0]], np.zeros((2, 2)), True),
    ("stable A 1e-4 from the axis, B = 0", [[-1e-4, 1.0], [-1.0, -1e-4]], [[0.0], [0.0]], np.eye(2), True),
]  # fmt: skip


@pytest.mark.parametrize("case", FLAG_CASES, ids=[c[0] for c in FLAG_CASES])
def test_care_converged_means_stabilising_solution_found(case):
    """converged is True exactly when a stabilising solution exists; then A - B K is Hurwitz and X equals the exact
    solution to 1e-12 relative (1e-12 absolute for X = 0). SciPy is 1e-8 off on the lightly damped oscillator
    (X = 5000 I exactly)."""
    _, A, B, Q, exists = case
    A, B, Q, R = (np.atleast_2d(np.asarray(M, float)) for M in (A, B, Q, [[1.0]]))
    sol = care(A, B, Q, R)
    assert bool(sol.converged) is exists
    if exists:
        assert closed_loop_abscissa(A, B, R, sol.X) < 0
        want = reference_care(A, B, Q, R)
        np.testing.assert_allclose(sol.X, want, rtol=1e-12, atol=1e-12 * max(1.0, np.max(np.abs(want))))


def test_care_jit_and_vmap_equal_eager():
    """The flag is computed inside traced code: a batch of the 2-state flag cases under jit(vmap) gives the eager
    solutions and flags (eager calls run care's compiled core, so this also covers jit)."""
    A, B, Q = (np.stack([np.asarray(c[k], float) for c in FLAG_CASES]) for k in (1, 2, 3))
    R = np.ones((len(FLAG_CASES), 1, 1))
    batched = jax.jit(jax.vmap(care))(A, B, Q, R)
    for i in range(len(FLAG_CASES)):
        eager = care(A[i], B[i], Q[i], R[i])
        got = jax.tree.map(lambda x, i=i: x[i], batched)
        assert bool(got.converged) == bool(eager.converged), FLAG_CASES[i][0]
        if bool(eager.converged):
            np.testing.assert_allclose(got.X, eager.X, rtol=1e-12, atol=1e-15)


# ---------------------------------------------------------------------------------------------
# gradients


def _grad_problem(shift):
    A, B, _, _ = random_problem(np.random.default_rng(11), 3, 1, shift=shift)
    rng = np.random.default_rng(12)
    return A, B, rng.normal(size=(3, 3)), rng.normal(size=(1, 1)) + 2 * np.eye(1)


@jax.jit
def lqr_gain(A, B, Gq, Hr):
    """The LQR gain R^{-1} B' X of the CARE with Q = Gq Gq' + 0.1 I and R = Hr Hr' (compiled once for the module)."""
    R = Hr @ Hr.T
    return jnp.linalg.solve(R, B.T @ care(A, B, Gq @ Gq.T + 0.1 * jnp.eye(3), R).X)


@pytest.mark.parametrize(
    "shift, modes",
    [(2.0, ("rev",)), pytest.param(2.0, ("fwd",), marks=pytest.mark.slow),
     pytest.param(0.0, ("fwd", "rev"), marks=pytest.mark.slow)],
)  # fmt: skip
def test_care_check_grads(shift, modes):
    """check_grads (order 1) of the LQR gain w.r.t. A, B and the factors of Q and R (factored so that perturbed
    covariances stay symmetric), on an unstable plant (A + 2 I) and (slow) a generic one: the implicit-function
    VJP (default) and JVP (slow) of the CARE agree with finite differences."""
    check_grads(lqr_gain, _grad_problem(shift), order=1, modes=modes)


@pytest.mark.slow
def test_care_gradient_is_implicit():
    """Reverse mode does not differentiate through the iterations: the gradient's jaxpr holds the Lyapunov solves of
    the implicit rule (custom_linear_solve), and the flag and residual carry no tangent. (Slow: the default
    check_grads in reverse mode would already fail on a while_loop.)"""
    A, B, Gq, Hr = _grad_problem(0.0)
    Q, R = Gq @ Gq.T, Hr @ Hr.T
    jaxpr = str(jax.make_jaxpr(jax.grad(lambda A: jnp.sum(care(A, B, Q, R).X)))(A))
    assert "custom_lin" in jaxpr or "linear_solve" in jaxpr
    _, tangents = jax.jvp(lambda A: care(A, B, Q, R), (A,), (jnp.ones_like(A),))
    assert float(jnp.max(jnp.abs(tangents.residual))) == 0.0


# ---------------------------------------------------------------------------------------------
# lyapunov, lqr, lqe, is_detectable


def test_lyapunov_matches_scipy():
    """lyapunov(A, E) solves A X + X A' + E = 0 like scipy.linalg.solve_continuous_lyapunov(A, -E), for a Hurwitz A
    with eigenvalues from -0.01 to -100 (a stiff spectrum) and a non-symmetric E."""
    rng = np.random.default_rng(6)
    T = rng.normal(size=(4, 4)) + 2 * np.eye(4)
    A = T @ np.diag([-0.01, -1.0, -10.0, -100.0]) @ np.linalg.inv(T)
    E = rng.normal(size=(4, 4))
    X = np.asarray(lyapunov(A, E))
    want = scipy.linalg.solve_continuous_lyapunov(A, -E)
    assert rel_err(X, want) < 1e-10
    np.testing.assert_allclose(A @ X + X @ A.T, -E, atol=1e-10 * np.max(np.abs(want)))


def test_lqr_and_lqe_match_python_control():
    """lqr returns what control.lqr returns (K = R^{-1} B'S, S the CARE solution, E the eigenvalues of A - B K), and
    lqe what control.lqe returns (the gain P C' RN^{-1}, python-control's L; P the filter CARE's solution)."""
    rng = np.random.default_rng(31)
    A, B, Q, _ = random_problem(rng, 4, 2, shift=0.5)
    R = np.array([[2.0, 0.3], [0.3, 1.0]])
    K, S, E = lqr(A, B, Q, R)
    K_ctrl, S_ctrl, E_ctrl = control.lqr(A, B, Q, R)
    assert rel_err(S, S_ctrl) < 1e-10 and rel_err(K, K_ctrl) < 1e-10
    np.testing.assert_allclose(np.sort_complex(np.asarray(E)), np.sort_complex(E_ctrl), rtol=1e-9)
    G, C = rng.normal(size=(4, 2)), rng.normal(size=(2, 4))
    QN, RN = np.array([[1.0, 0.2], [0.2, 0.5]]), np.array([[0.3, 0.1], [0.1, 0.2]])
    K, P, E = lqe(A, G, C, QN, RN)
    W = G @ QN @ G.T
    L_ctrl, P_ctrl, E_ctrl = control.lqe(A, np.eye(4), C, (W + W.T) / 2, RN)  # its check wants G QN G' symmetric
    assert rel_err(P, P_ctrl) < 1e-10 and rel_err(K, L_ctrl) < 1e-10
    np.testing.assert_allclose(np.sort_complex(np.asarray(E)), np.sort_complex(E_ctrl), rtol=1e-9)


def test_lqr_and_lqe_raise_eagerly_and_give_nan_under_jit_when_no_stabilising_solution():
    """An unstable mode the input cannot move (A = diag(1, -1), B = [0, 1]'): lqr raises naming (A, B) and the
    eigenvalue; under jit(vmap), next to a solvable problem, its gain and S are NaN and the other's equal the eager
    ones. The dual for lqe (a mode C cannot see), and an oscillator that Q = 0 does not penalise."""
    A, B = np.diag([1.0, -1.0]), np.array([[0.0], [1.0]])
    with pytest.raises(ValueError, match=r"^lqr's CARE did not converge: .*\(A, B\) is not stabilisable.*eigenvalue 1"):
        lqr(A, B, np.eye(2), np.eye(1))
    good = np.diag([1.0, -1.0]), np.array([[1.0], [1.0]])
    As, Bs = (np.stack(M) for M in zip(good, (A, B), strict=True))
    K, S, _ = jax.jit(jax.vmap(lqr))(As, Bs, np.stack([np.eye(2)] * 2), np.stack([np.eye(1)] * 2))
    assert np.all(np.isnan(K[1])) and np.all(np.isnan(S[1]))
    K_eager, S_eager, _ = lqr(*good, np.eye(2), np.eye(1))
    np.testing.assert_allclose(K[0], K_eager, rtol=1e-12)
    np.testing.assert_allclose(S[0], S_eager, rtol=1e-12)
    with pytest.raises(ValueError, match=r"^lqe's CARE did not converge: .*\(A, C\) is not detectable"):
        lqe(A, np.eye(2), B.T, np.eye(2), np.eye(1))
    with pytest.raises(ValueError, match=r"imaginary axis is not penalised by Q"):
        lqr([[0.0, 1.0], [-1.0, 0.0]], B, np.zeros((2, 2)), np.eye(1))


def test_is_detectable_pbh():
    """PBH test (Grip 2010 §1.1.1): unobservable modes must be stable, in continuous (Re < 0) or discrete (|z| < 1)
    time; agrees with the rank of the observability matrix on observable pairs."""
    A = np.diag([1.0, -1.0])
    assert is_detectable(A, [[1.0, 0.0]]) and not is_detectable(A, [[0.0, 1.0]])
    assert is_detectable(np.diag([0.5, 0.9]), [[0.0, 1.0]], discrete=True)
    assert not is_detectable(np.diag([1.5, 0.9]), [[0.0, 1.0]], discrete=True)
    assert not is_detectable(np.diag([0.0, -1.0]), [[0.0, 1.0]])  # an unobservable integrator
    A = np.array([[0.0, 1.0], [-2.0, -0.1]])
    assert is_detectable(A, [[1.0, 0.0]]) and np.linalg.matrix_rank(control.obsv(A, [[1.0, 0.0]])) == 2


# ---------------------------------------------------------------------------------------------
# bad input


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(Q=np.array([[1.0, 0.5], [0.0, 1.0]])), "Q"),  # not symmetric
        (dict(Q=np.diag([1.0, -0.5])), "Q"),  # indefinite
        (dict(R=np.zeros((1, 1))), "R"),  # singular
        (dict(R=np.eye(2)), "R"),  # wrong size
        (dict(B=np.ones((3, 1))), "B"),  # wrong number of rows
        (dict(A=np.ones((2, 3))), "A"),  # not square
        (dict(A=np.array([[np.nan, 0.0], [0.0, -1.0]])), "A"),  # not finite
    ],
)
def test_care_and_lqr_reject_bad_input(kwargs, name):
    """Eager validation (DESIGN.md "Errors"): ValueError naming the argument, from care and from lqr."""
    args = dict(A=np.diag([1.0, -1.0]), B=np.array([[1.0], [1.0]]), Q=np.eye(2), R=np.eye(1))
    args.update(kwargs)
    for function in (care, lqr):
        with pytest.raises(ValueError, match=rf"^{name}\b"):
            function(**args)


def test_lqe_rejects_bad_input():
    """lqe names its own arguments: QN not positive semidefinite, RN singular, G with the wrong number of rows."""
    A, C = np.diag([-1.0, -2.0]), np.array([[1.0, 0.0]])
    with pytest.raises(ValueError, match=r"^QN\b"):
        lqe(A, np.eye(2), C, np.diag([1.0, -1.0]), np.eye(1))
    with pytest.raises(ValueError, match=r"^RN\b"):
        lqe(A, np.eye(2), C, np.eye(2), np.zeros((1, 1)))
    with pytest.raises(ValueError, match=r"^G\b"):
        lqe(A, np.eye(3), C, np.eye(3), np.eye(1))
