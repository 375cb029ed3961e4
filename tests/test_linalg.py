"""jaxobs._linalg: the batched small solves and Cholesky factors equal NumPy's on both sides of their unrolling
limits, eagerly, under jit, vmap and grad."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxobs._linalg import FACTOR_UNROLL_MAX, UNROLL_MAX, cho_solve, cholesky, small_solve, solve_lower, solve_spd


def _spd(rng, batch, n):
    G = rng.normal(size=(batch, n, n))
    return G @ np.swapaxes(G, -1, -2) + n * np.eye(n)


@pytest.mark.parametrize("n", [1, 3, UNROLL_MAX, UNROLL_MAX + 1])
def test_small_solve_equals_numpy(n):
    rng = np.random.default_rng(n)
    W = rng.normal(size=(5, n, n)) + n * np.eye(n) * rng.choice([-1.0, 1.0], size=(5, 1, 1))
    W = W[:, rng.permutation(n)]  # rows out of order: partial pivoting matters
    X = rng.normal(size=(5, n, 2 * n))
    for solve in (small_solve, jax.jit(small_solve), jax.vmap(small_solve)):
        np.testing.assert_allclose(solve(W, X), np.linalg.solve(W, X), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("n", [1, FACTOR_UNROLL_MAX, FACTOR_UNROLL_MAX + 1])
def test_cholesky_and_solves_equal_numpy(n):
    rng = np.random.default_rng(n)
    S = _spd(rng, 4, n)
    B, b = rng.normal(size=(4, n, 3)), rng.normal(size=(4, n))
    L_ref = np.linalg.cholesky(S)
    for chol in (cholesky, jax.jit(cholesky), jax.vmap(cholesky)):
        np.testing.assert_allclose(chol(S), L_ref, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(solve_lower(L_ref, B), np.linalg.solve(L_ref, B), rtol=1e-11)
    np.testing.assert_allclose(solve_lower(L_ref, b), np.linalg.solve(L_ref, b[..., None])[..., 0], rtol=1e-11)
    L_T = np.swapaxes(L_ref, -1, -2)
    np.testing.assert_allclose(solve_lower(L_ref, B, transpose=True), np.linalg.solve(L_T, B), rtol=1e-11)
    np.testing.assert_allclose(jax.vmap(cho_solve)(L_ref, B), np.linalg.solve(S, B), rtol=1e-10)
    np.testing.assert_allclose(jax.jit(solve_spd)(S, B), np.linalg.solve(S, B), rtol=1e-10)


def test_cholesky_of_an_indefinite_matrix_is_nan_like_lapack():
    S = np.array([[1.0, 2.0], [2.0, 1.0]])
    assert np.isnan(cholesky(S)[1, 1]) and np.isnan(jnp.linalg.cholesky(S)[1, 1])


@pytest.mark.parametrize("n", [2, FACTOR_UNROLL_MAX + 1])
def test_gradient_of_log_det_and_solve_equals_the_lapack_path(n):
    """d/dS of ``log det S + 1' S^{-1} b`` through the unrolled factor equals the same through LAPACK's."""
    rng = np.random.default_rng(7)
    S, b = _spd(rng, 1, n)[0], rng.normal(size=n)

    def objective(factor, solve):
        def f(S):
            L = factor(S)
            return 2.0 * jnp.sum(jnp.log(jnp.diagonal(L))) + jnp.sum(solve(L, b))

        return f

    ours = jax.grad(objective(cholesky, cho_solve))(S)
    lapack = jax.grad(objective(jnp.linalg.cholesky, lambda L, b: jax.scipy.linalg.cho_solve((L, True), b)))(S)
    # ours reads the lower triangle, LAPACK's path the symmetric part: fold each onto the lower triangle
    fold = lambda G: np.tril(G) + np.triu(G, 1).T
    np.testing.assert_allclose(fold(ours), fold(lapack), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("transpose", [False, True])
def test_solve_lower_derivatives(transpose):
    """The substitution's own derivative rule: forward and reverse mode to second order, and no derivative in the
    upper triangle, which the solve does not read."""
    rng = np.random.default_rng(3)
    L = np.linalg.cholesky(_spd(rng, 2, 3))
    B = rng.normal(size=(2, 3, 2))
    solve = lambda L, B: solve_lower(L, B, transpose=transpose)
    check_grads(solve, (L, B), order=2, modes=("fwd", "rev"))
    upper = jax.grad(lambda L: jnp.sum(jnp.sin(solve(L, B))))(L + np.triu(np.ones(3), 1))
    assert np.all(np.triu(upper, 1) == 0)
