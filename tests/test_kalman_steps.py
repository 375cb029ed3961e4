"""Tests for jaxobs.kalman_steps: the Riccati covariance step (Cortesão 2006 eq. 27-29, Joseph form) and its
sequence, the measurement update's innovation covariance and log-likelihood (exact
marginals over the observed components, NaN-safe gradients, fixed gains), the square-root predict and update, and
the triangularisation ``tria`` with its derivative at rank-deficient factors."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from hypothesis import given
from hypothesis import strategies as st
from jax.test_util import check_grads

from jaxobs.kalman_steps import (
    Update,
    bierman_update,
    covariance_sequence,
    innovation_log_likelihood,
    kalman_gain,
    moment_update,
    predict,
    predict_covariance,
    riccati_step,
    square_root_predict,
    square_root_update,
    tria,
    ud_factor,
    update,
    update_covariance,
)
from jaxobs.matrix_equations import filter_dare
from tests.test_matrix_equations import random_system, sequence_jit


def _problem(seed=6, n=3, p=2):
    rng = np.random.default_rng(seed)
    G = rng.normal(size=(n, n))
    P1 = G @ G.T + 0.1 * np.eye(n)
    C = rng.normal(size=(p, n))
    R = np.array([[0.5, 0.4], [0.4, 0.6]]) if p == 2 else np.diag(rng.uniform(0.2, 0.6, p))
    return P1, C, R, rng.normal(size=n)


def test_update_one_missing_component_is_exact_conditioning():
    """Single update, 2 outputs, non-diagonal R, second component NaN: x and P equal the Gaussian conditioning on
    the first component alone (row C[0], variance R[0, 0]); the reported gain has a zero column; S is that
    component's innovation variance with the unit placeholder on the missing one, and the log-likelihood is the
    scalar normal log density of the observed component."""
    P1, C, R, x1 = _problem()
    y = np.array([0.7, np.nan])
    x, P, K, innovation, n_missing, S, ll = update(x1, P1, C, R, y)
    c, r = C[0:1], R[0:1, 0:1]
    s = (c @ P1 @ c.T + r)[0, 0]
    k = P1 @ c.T / s
    np.testing.assert_allclose(x, x1 + k[:, 0] * (0.7 - c @ x1), rtol=1e-12)
    np.testing.assert_allclose(P, P1 - k @ c @ P1, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(K[:, 0], k[:, 0], rtol=1e-12)
    np.testing.assert_array_equal(K[:, 1], 0.0)
    np.testing.assert_allclose(innovation, [0.7 - (c @ x1)[0], 0.0], rtol=1e-12)
    assert int(n_missing) == 1
    np.testing.assert_allclose(S, [[s, 0.0], [0.0, 1.0]], rtol=1e-12, atol=0)
    assert float(ll) == pytest.approx(scipy.stats.norm(c @ x1, np.sqrt(s)).logpdf(0.7)[0], rel=1e-13)
    # the full (non-missing) update differs: the correlation with the second component matters
    x_full, *_ = update(x1, P1, C, R, np.array([0.7, 0.1]))
    assert np.max(np.abs(np.asarray(x_full) - np.asarray(x))) > 1e-3


@pytest.mark.parametrize("pattern", ["none", "first", "middle", "last", "all"])
def test_log_likelihood_is_the_marginal_of_the_observed_components(pattern):
    """Four outputs with a dense R: for every pattern of missing components the log-likelihood equals SciPy's
    multivariate normal log density of the observed ones (mean C_o x_prior, covariance C_o P C_o' + R_oo) to
    1e-13, and all missing gives exactly 0; the missing components' placeholder adds exactly nothing (the
    log-likelihood of a measurement with its missing entries set to other finite values but masked is the same)."""
    rng = np.random.default_rng(3)
    n, p = 3, 4
    G = rng.normal(size=(n, n))
    P1 = G @ G.T + 0.2 * np.eye(n)
    C = rng.normal(size=(p, n))
    H = rng.normal(size=(p, p))
    R = H @ H.T + 0.3 * np.eye(p)
    x1, y = rng.normal(size=n), rng.normal(size=p)
    missing = {"none": [], "first": [0], "middle": [1, 2], "last": [3], "all": [0, 1, 2, 3]}[pattern]
    y[missing] = np.nan
    result = update(x1, P1, C, R, y)
    obs = np.isfinite(y)
    if not obs.any():
        assert float(result.log_likelihood) == 0.0
        np.testing.assert_array_equal(result.S, np.eye(p))
        return
    Co = C[obs]
    expected = scipy.stats.multivariate_normal(Co @ x1, Co @ P1 @ Co.T + R[np.ix_(obs, obs)]).logpdf(y[obs])
    assert float(result.log_likelihood) == pytest.approx(expected, rel=1e-13)
    np.testing.assert_allclose(innovation_log_likelihood(result.innovation, result.S, obs.sum()), expected,
                               rtol=1e-13)  # fmt: skip


def test_log_likelihood_gradients_are_finite_with_missing_components():
    """Gradients of the log-likelihood with respect to the prior mean, covariance and R pass check_grads (forward
    and reverse) with one component missing, and are finite (exactly zero) with all missing: no NaN reaches a
    gradient."""
    P1, C, R, x1 = _problem(7)

    def ll(x, P, R_, y):
        return update(x, P, C, R_, y).log_likelihood

    for y in (np.array([0.3, np.nan]), np.array([np.nan, np.nan])):
        f = lambda x, P, R_, y=y: ll(x, P, R_, y)
        check_grads(f, (x1, P1, R), order=1, modes=("fwd", "rev"))
        grads = jax.grad(f, argnums=(0, 1, 2))(x1, P1, R)
        assert all(np.all(np.isfinite(g)) for g in grads)
    grads = jax.grad(lambda x, P, R_: ll(x, P, R_, np.array([np.nan, np.nan])), argnums=(0, 1, 2))(x1, P1, R)
    assert all(np.all(np.asarray(g) == 0.0) for g in grads)


def test_fixed_gain_innovation_covariance_is_the_steady_state_one():
    """With the steady-state gain, S = (I - C K)^{-1} R equals C X C' + R of the filter DARE's a-priori solution X to
    1e-12, its log-likelihood equals the update's from X, and a missing component gives its marginal (the observed
    block of S)."""
    rng = np.random.default_rng(8)
    Phi = rng.normal(size=(3, 3))
    Phi *= 0.9 / np.max(np.abs(np.linalg.eigvals(Phi)))
    _, C, R, x1 = _problem(8)
    Q = np.diag([0.3, 0.1, 0.2])
    X = np.asarray(filter_dare(Phi, C, Q, R).X)
    K = kalman_gain(X, C, R)
    y = np.array([0.4, -0.2])
    fixed, optimal = update(x1, None, C, R, y, gain=K), update(x1, X, C, R, y)
    np.testing.assert_allclose(fixed.S, C @ X @ C.T + R, rtol=1e-12)
    assert float(fixed.log_likelihood) == pytest.approx(float(optimal.log_likelihood), rel=1e-12)
    np.testing.assert_allclose(fixed.x, optimal.x, rtol=1e-12)
    half = update(x1, None, C, R, np.array([0.4, np.nan]), gain=K)
    np.testing.assert_allclose(half.S, [[(C @ X @ C.T + R)[0, 0], 0.0], [0.0, 1.0]], rtol=1e-12)
    assert update(x1, None, C, None, y, gain=K).log_likelihood is None  # no noise model, no likelihood


@pytest.mark.parametrize("missing", [[], [1], [0, 1]])
def test_square_root_steps_equal_the_covariance_steps(missing):
    """square_root_predict/update on Cholesky factors give the mean, gain, innovation, log-likelihood of predict/
    update and factors of their covariances (P_sqrt P_sqrt', S_sqrt S_sqrt') to 1e-12, lower triangular, with and
    without missing components; a rank-1 factor of Q (the noise input matrix) is accepted."""
    P1, C, R, x1 = _problem(9)
    rng = np.random.default_rng(9)
    Phi, Gamma, u = rng.normal(size=(3, 3)) * 0.5, rng.normal(size=(3, 1)), rng.normal(size=1)
    g = rng.normal(size=(3, 1))
    x_prior, P_prior = predict(x1, P1, Phi, g @ g.T, Gamma, u)
    xs_prior, Ps_prior = square_root_predict(x1, np.linalg.cholesky(P1), Phi, g, Gamma, u)
    np.testing.assert_allclose(xs_prior, x_prior, rtol=1e-13)
    np.testing.assert_allclose(Ps_prior @ Ps_prior.T, P_prior, rtol=1e-12, atol=1e-13)
    y = np.array([0.4, -0.2])
    y[missing] = np.nan
    cov, sq = update(x_prior, P_prior, C, R, y), square_root_update(xs_prior, Ps_prior, C, np.linalg.cholesky(R), y)
    for name in ("x", "K", "innovation", "log_likelihood", "n_missing"):
        np.testing.assert_allclose(getattr(sq, name), getattr(cov, name), rtol=1e-12, atol=1e-13, err_msg=name)
    np.testing.assert_allclose(sq.P_sqrt @ sq.P_sqrt.T, cov.P, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(sq.S_sqrt @ sq.S_sqrt.T, cov.S, rtol=1e-12, atol=1e-13)
    for M in (Ps_prior, sq.P_sqrt, sq.S_sqrt):
        np.testing.assert_array_equal(np.triu(M, 1), 0.0)


def _plain_tria(A):
    """tria through JAX's own QR derivative (which divides by the diagonal of R)."""
    return jnp.linalg.qr(A.T, mode="r").T


def test_tria_factor_and_derivative():
    """tria(A) is lower triangular with tria(A) tria(A)' = A A'. Full rank: its derivative passes check_grads
    (forward and reverse). Rank deficient (a singular covariance): the derivative of tria(A) tria(A)' (what every
    use depends on) passes check_grads and is finite, where JAX's QR derivative gives NaN."""
    rng = np.random.default_rng(10)
    A = rng.normal(size=(3, 5))
    T = tria(A)
    np.testing.assert_array_equal(np.triu(T, 1), 0.0)
    np.testing.assert_allclose(T @ T.T, A @ A.T, rtol=1e-12)
    check_grads(tria, (A,), order=1, modes=("fwd", "rev"))
    B = A.copy()
    B[2] = B[0] - 2 * B[1]  # rank 2
    gram = lambda M: tria(M) @ tria(M).T
    check_grads(gram, (B,), order=1, modes=("fwd", "rev"))
    Z = np.zeros((3, 5))
    Z[0, 0] = 1.0  # rank 1 with zero rows
    loss = lambda f: lambda M: jnp.sum(jnp.sin(f(M)))
    assert np.all(np.isfinite(jax.grad(loss(tria))(Z)))
    assert not np.all(np.isfinite(jax.grad(loss(_plain_tria))(Z)))  # the test is not vacuous
    with pytest.raises(ValueError, match="at least as many columns"):
        tria(np.ones((3, 2)))


# --------------------------------------------------------------------------------------------
# Bierman's U-D update

_bierman = jax.jit(bierman_update)
_joseph = jax.jit(update)


def test_ud_factor_reproduces_the_matrix_singular_included():
    """``U diag(d) U' = P`` with ``U`` unit upper triangular and ``d >= 0``, for a definite and for a singular ``P``
    (a zero pivot leaves a zero column above the diagonal)."""
    P1, _, _, _ = _problem(n=4, p=2)
    G = np.random.default_rng(3).normal(size=(4, 2))
    for P in (P1, G @ G.T):
        U, d = ud_factor(P)
        np.testing.assert_allclose(U @ np.diag(d) @ U.T, P, atol=1e-12 * np.abs(P).max())
        np.testing.assert_array_equal(np.tril(U, -1), 0.0)
        np.testing.assert_array_equal(np.diagonal(U), 1.0)
        assert np.all(np.asarray(d) >= 0)


@pytest.mark.parametrize("missing", [False, True], ids=["all", "one_missing"])
def test_bierman_update_equals_the_joseph_update(missing):
    """Non-diagonal R (whitened), 2 outputs, optionally one missing: every field of :class:`Update` equals the
    Joseph form's to ~1e-12 (relative to the scale of each field)."""
    P1, C, R, x1 = _problem(n=3, p=2)
    y = np.array([0.7, np.nan if missing else -0.4])
    joseph, bierman = _joseph(x1, P1, C, R, y), _bierman(x1, P1, C, R, y)
    for name in Update._fields:
        a, b = np.asarray(getattr(joseph, name)), np.asarray(getattr(bierman, name))
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * max(np.abs(a).max(), 1.0), err_msg=name)
    assert int(bierman.n_missing) == int(missing)


def test_bierman_stays_definite_as_r_goes_to_zero():
    """Prior with a condition number 1e6, two precise measurements R = 10^-k I: the standard form
    ``(I - K C) P_prior`` turns indefinite (a negative eigenvalue) from k = 8 on, while Bierman's U-D update keeps a
    positive definite covariance down to k = 16 (its smallest eigenvalue about R / 3, the variance left in the
    measured directions) and agrees with the Joseph form to 1e-12 relative."""
    rng = np.random.default_rng(1)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    P1 = Q @ np.diag([1e4, 1.0, 1e-2]) @ Q.T
    C = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 1.0]])
    x1, y = np.zeros(3), np.ones(2)
    standard_indefinite = []
    for k in range(8, 17, 2):
        R = 10.0**-k * np.eye(2)
        K = P1 @ C.T @ np.linalg.inv(C @ P1 @ C.T + R)
        standard = P1 - K @ C @ P1
        standard_indefinite.append(np.linalg.eigvalsh((standard + standard.T) / 2).min() < 0)
        bierman = _bierman(x1, P1, C, R, y)
        smallest = np.linalg.eigvalsh(np.asarray(bierman.P)).min()
        assert 0.1 * 10.0**-k < smallest < 10.0**-k, (k, smallest)
        np.testing.assert_allclose(bierman.P, _joseph(x1, P1, C, R, y).P, rtol=0, atol=1e-12 * 1e4)
    assert all(standard_indefinite)


def test_bierman_update_jit_vmap_grad():
    """Eager = jit, vmap over a batch of measurements = the loop, and reverse-mode gradients through the U-D
    factorisation and the scalar updates (w.r.t. the prior covariance, R and y) match finite differences."""
    P1, C, R, x1 = _problem(n=3, p=2)
    ys = np.random.default_rng(2).normal(size=(3, 2))
    eager = bierman_update(x1, P1, C, R, ys[0])
    np.testing.assert_allclose(eager.P, _bierman(x1, P1, C, R, ys[0]).P, atol=1e-14)
    batched = jax.vmap(_bierman, in_axes=(None, None, None, None, 0))(x1, P1, C, R, ys)
    for i, y in enumerate(ys):
        np.testing.assert_allclose(batched.x[i], _bierman(x1, P1, C, R, y).x, atol=1e-14)

    def loss(P, R, y):
        out = bierman_update(x1, P, C, R, y)
        return jnp.sum(out.x**2) + jnp.sum(out.P) + out.log_likelihood

    check_grads(jax.jit(loss), (P1, R, ys[0]), order=1, modes=["rev"], atol=1e-6, rtol=1e-6)


_standard = jax.jit(partial(update, joseph=False))


@pytest.mark.parametrize("missing", [False, True], ids=["all", "one_missing"])
def test_standard_form_update_equals_the_joseph_update(missing):
    """``joseph=False`` (``P1 - W' W``, ``W = L^{-1} C P1``): every field of :class:`Update` equals the Joseph
    form's to ~1e-12 on a well-conditioned prior, with and without a missing component."""
    P1, C, R, x1 = _problem(n=3, p=2)
    y = np.array([0.7, np.nan if missing else -0.4])
    joseph, standard = _joseph(x1, P1, C, R, y), _standard(x1, P1, C, R, y)
    for name in Update._fields:
        a, b = np.asarray(getattr(joseph, name)), np.asarray(getattr(standard, name))
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * max(np.abs(a).max(), 1.0), err_msg=name)


@pytest.mark.parametrize("missing", [False, True], ids=["all", "one_missing"])
def test_moment_update_is_the_standard_form_update_of_a_linear_map(missing):
    """The moments of ``C x``, ``x ~ N(x1, P1)`` (``cross = P1 C'``, ``cov = C P1 C'``, mean ``C x1``): every field of
    :class:`Update` equals ``update(..., joseph=False)``, with and without a missing component; under vmap too."""
    P1, C, R, x1 = _problem(n=3, p=2)
    y = np.array([0.7, np.nan if missing else -0.4])
    moments = jax.jit(moment_update)(x1, P1, P1 @ C.T, C @ P1 @ C.T, R, y, C @ x1)
    standard = _standard(x1, P1, C, R, y)
    for name in Update._fields:
        a, b = np.asarray(getattr(standard, name)), np.asarray(getattr(moments, name))
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * max(np.abs(a).max(), 1.0), err_msg=name)
    ys = np.stack([y, -y])
    batched = jax.vmap(moment_update, in_axes=(None,) * 5 + (0, None))(x1, P1, P1 @ C.T, C @ P1 @ C.T, R, ys, C @ x1)
    np.testing.assert_allclose(batched.x[0], moments.x, atol=1e-14)


def test_standard_form_loses_definiteness_where_the_joseph_form_keeps_it():
    """Why Joseph is the default: a prior of condition number 1e6 and two measurements of variance 1e-14, where the
    kept variance in the measured directions is about 3e-15. The standard form returns a negative eigenvalue of
    -3.4e-13 (measured), a hundred times that variance; the Joseph form keeps the covariance positive definite."""
    rng = np.random.default_rng(1)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    P1 = Q @ np.diag([1e4, 1.0, 1e-2]) @ Q.T
    C, R = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 1.0]]), 1e-14 * np.eye(2)
    x1, y = np.zeros(3), np.ones(2)
    smallest = {name: np.linalg.eigvalsh(np.asarray(f(x1, P1, C, R, y).P)).min()
                for name, f in (("joseph", _joseph), ("standard", _standard))}  # fmt: skip
    assert smallest["standard"] < -1e-13, smallest
    assert smallest["joseph"] > 0, smallest


# ---------------------------------------------------------------------------------------------
# one step


def test_riccati_step_equations_cortesao2006_eq27_29():
    """One step: P1 = Phi P Phi' + Q (eq. 28), K = P1 C'(C P1 C' + R)^{-1} (eq. 27), Joseph-form P (eq. 29),
    which for the optimal K equals (I - K C) P1."""
    rng = np.random.default_rng(0)
    Phi, C, Q, R = random_system(rng, 4, 2)
    P_prev = np.eye(4) * 0.3 + 0.05
    P, K, P1 = riccati_step(P_prev, Phi, C, Q, R)
    P1_ref = Phi @ P_prev @ Phi.T + Q
    K_ref = P1_ref @ C.T @ np.linalg.inv(C @ P1_ref @ C.T + R)
    P_ref = (np.eye(4) - K_ref @ C) @ P1_ref
    np.testing.assert_allclose(P1, P1_ref, rtol=1e-13)
    np.testing.assert_allclose(K, K_ref, rtol=1e-11)
    np.testing.assert_allclose(P, P_ref, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(predict_covariance(P_prev, Phi, Q), P1_ref, rtol=1e-13)
    P_u, K_u = update_covariance(P1_ref, C, R)
    np.testing.assert_allclose(P_u, P_ref, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(kalman_gain(P1_ref, C, R), K_ref, rtol=1e-11)


@pytest.mark.parametrize("n, m", [(3, 2), (6, 1), (10, 2)])  # explicit I - K C, and rank-m corrections
def test_update_covariance_is_joseph_form_eq29(n, m):
    """update_covariance returns the Joseph expression (I-KC)P1(I-KC)' + KRK' (eq. 29 in Joseph form), written out
    here with the gain it reports."""
    rng = np.random.default_rng(1)
    _, C, Q, R = random_system(rng, n, m)
    P, K = update_covariance(Q, C, R)
    K = np.asarray(K)
    IKC = np.eye(n) - K @ C
    np.testing.assert_allclose(P, IKC @ Q @ IKC.T + K @ R @ K.T, rtol=1e-12, atol=1e-15)


@given(
    n=st.sampled_from([2, 3, 6]),
    m=st.sampled_from([1, 2]),
    seed=st.integers(0, 2**32 - 1),
    r_exp=st.integers(0, 10),
    zero_init=st.booleans(),
)
def test_joseph_covariance_stays_symmetric_psd(n, m, seed, r_exp, zero_init):
    """Property (Joseph form, eq. 29, symmetrised): along 300 steps every a-priori and a-posteriori covariance is
    exactly symmetric and PSD (min eigenvalue >= -1e-10 * scale), also for nearly singular R (condition up to
    1e10) and P_init = 0."""
    rng = np.random.default_rng(seed)
    Phi, C, Q, R = random_system(rng, n, m, r_min=10.0**-r_exp)
    P_init = np.zeros((n, n)) if zero_init else Q
    seq = sequence_jit(P_init, Phi, C, Q, R, 300)
    for P in (np.asarray(seq.P), np.asarray(seq.P_prior)):
        assert np.all(np.isfinite(P))
        np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
        scale = np.max(np.abs(P), axis=(-1, -2))
        assert np.all(np.linalg.eigvalsh(P).min(axis=-1) >= -1e-10 * scale)


@pytest.mark.parametrize("n, m", [(3, 3), (6, 1), (6, 2)])  # explicit I - K C, and rank-m corrections
def test_joseph_update_stays_psd_for_very_precise_measurements(n, m):
    """The reason for the Joseph form (eq. 29): with very precise measurements (R / P1 ~ 1e-16) the posterior
    covariance is small in the measured directions, computed from O(1) quantities. One update with
    P1 ~ 1e8, R ~ 1e-8, and 50 Riccati steps with Q ~ 1, R ~ 1e-16, must stay finite, exactly symmetric and PSD
    (min eigenvalue >= -1e-10 * scale)."""
    failures = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        Phi, C, Q, _ = random_system(rng, n, m, rho=0.9)
        Hm = rng.normal(size=(m, m))
        R = 1e-16 * (Hm @ Hm.T + 0.1 * np.eye(m))
        G = rng.normal(size=(n, n))
        P_one, _ = update_covariance(1e8 * (G @ G.T + 0.1 * np.eye(n)), C, 1e8 * R)
        seq = sequence_jit(Q, Phi, C, Q, R, 50)
        for label, P in (("one update", np.asarray(P_one)[None]), ("sequence", np.asarray(seq.P))):
            assert np.all(np.isfinite(P)), (seed, label)
            np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
            lowest = np.linalg.eigvalsh(P).min(axis=-1) / np.max(np.abs(P), axis=(-1, -2))
            if np.any(lowest < -1e-10):
                failures.append((seed, label, float(lowest.min())))
    assert not failures, f"indefinite covariances (seed, where, min eig / scale): {failures}"


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(P_init=np.array([[1.0, 0.5], [0.0, 1.0]])), "P_init"),
        (dict(Q=np.array([[1.0, 0.5], [0.0, 1.0]])), "Q"),
        (dict(Q=np.diag([1.0, -0.5])), "Q"),
        (dict(R=np.zeros((1, 1))), "R"),
        (dict(R=np.eye(2)), "R"),
        (dict(Q=np.eye(3)), "Q"),
        (dict(C=np.ones((1, 3))), "C"),
        (dict(Phi=np.ones((3, 2))), "Phi"),
    ],
)
def test_covariance_sequence_rejects_bad_input(kwargs, name):
    """Eager validation of covariance_sequence (DESIGN.md "Errors": shapes, symmetry, definiteness): ValueError
    naming the argument."""
    Phi, C, Q, R = np.diag([0.9, 0.5]), np.array([[1.0, 0.0]]), np.eye(2), np.eye(1)
    args = dict(P_init=np.eye(2), Phi=Phi, C=C, Q=Q, R=R)
    args.update(kwargs)
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        covariance_sequence(args["P_init"], args["Phi"], args["C"], args["Q"], args["R"], 5)


def test_joseph_covariance_of_any_gain():
    """The error covariance of a fixed-gain update: the Kalman gain gives the update's own ``P`` (both branches: rank-p
    correction for p < n / 2, full congruence otherwise); any other gain gives more (in the PSD order); the closed form
    matches the mean outer product of the errors it describes (Monte Carlo)."""
    from jaxobs.kalman_steps import joseph_covariance, update_covariance

    rng = np.random.default_rng(3)
    for n, p in ((5, 2), (3, 2)):
        A = rng.normal(size=(n, n))
        P1, C, R = A @ A.T + np.eye(n), rng.normal(size=(p, n)), np.diag(rng.uniform(0.5, 2.0, p))
        P, K = update_covariance(P1, C, R)
        np.testing.assert_allclose(joseph_covariance(P1, C, R, K), P, rtol=1e-12, atol=1e-12)
        other = joseph_covariance(P1, C, R, K + 0.1 * rng.normal(size=K.shape))
        assert np.min(np.linalg.eigvalsh(np.asarray(other) - np.asarray(P))) > -1e-12
    x = rng.multivariate_normal(np.zeros(n), P1, 200_000)
    v = rng.multivariate_normal(np.zeros(p), R, 200_000)
    G = 0.3 * rng.normal(size=(n, p))
    errors = x - (x @ C.T + v) @ G.T  # x - G y
    np.testing.assert_allclose(errors.T @ errors / len(errors), joseph_covariance(P1, C, R, G), atol=0.06)
