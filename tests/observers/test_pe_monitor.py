"""Tests for the persistency-of-excitation monitor (jaxobs.observers.pe_monitor): the windowed Gram matrix and its
smallest eigenvalue against NumPy, the excitation flag on the two regressors of Grip 2010 Example 1.1 (constant:
not exciting; [sin t, cos t]: exciting), the window's least-squares estimate, missing samples, jit/vmap, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.observers.base import EstimatorInputs, run
from jaxobs.observers.pe_monitor import make_pe_monitor, pe_monitor

DT, N = 0.01, 629  # a window of about 2 pi

run_monitor = jax.jit(lambda params, y: run(pe_monitor, params, EstimatorInputs(y=y))[1])


def _signals(T=2000, seed=0):
    """[omega; z] for omega = [sin t, cos t] up to t = 10 and the constant [1, 2] after, z = omega' theta +
    noise; returns y (T, 3), omega (T, 2), z (T,)."""
    t = DT * np.arange(T)
    omega = np.where((t <= 10.0)[:, None], np.stack([np.sin(t), np.cos(t)], 1), [1.0, 2.0])
    z = omega @ np.array([2.0, -1.0]) + 0.01 * np.random.default_rng(seed).normal(size=T)
    return np.column_stack([omega, z]), omega, z


def test_gram_lambda_min_and_estimate_match_numpy():
    """At every sample the Gram matrix is dt sum omega omega' over the last N samples (fewer before the window
    fills), lambda_min its smallest eigenvalue, and, while excited, x the least-squares fit of the window
    (np.linalg.lstsq) to 1e-10."""
    y, omega, z = _signals()
    out = run_monitor(make_pe_monitor(2, N, DT, 1.0), y)
    for k in (10, N - 1, N + 40, 1000, 1300, 1999):
        rows = slice(max(0, k - N + 1), k + 1)
        gram = DT * omega[rows].T @ omega[rows]
        np.testing.assert_allclose(out.gram[k], gram, rtol=1e-12, atol=1e-14)
        assert float(out.lambda_min[k]) == pytest.approx(np.linalg.eigvalsh(gram)[0], rel=1e-10, abs=1e-13)
        if bool(out.excited[k]):
            want = np.linalg.lstsq(omega[rows], z[rows], rcond=None)[0]
            np.testing.assert_allclose(out.x[k], want, rtol=1e-10)


def test_excitation_flag_follows_the_regressor():
    """[sin t, cos t] over a 2 pi window: lambda_min = pi (1e-2) and excited from the sample that fills the window;
    once the regressor turns constant (rank one), the flag drops within one window and lambda_min decays to 0;
    the estimate is then held at the last exciting window's (near theta = (2, -1))."""
    y, _, _ = _signals()
    out = run_monitor(make_pe_monitor(2, N, DT, 1.0), y)
    excited = np.asarray(out.excited)
    assert not excited[: N - 1].any() and excited[N - 1 : 1000 + 1].all()
    assert float(out.lambda_min[1000]) == pytest.approx(np.pi, abs=1e-2)
    off = int(np.argmin(excited[N:])) + N
    assert 1000 < off <= 1000 + N and not excited[off:].any()
    assert float(out.lambda_min[-1]) < 1e-12
    np.testing.assert_allclose(out.x[-1], out.x[off - 1], rtol=0)
    np.testing.assert_allclose(out.x[-1], [2.0, -1.0], atol=2e-3)


def test_missing_samples_are_dropped_and_counted():
    """A sample with a NaN entry contributes nothing (its row of the window is zero) and is counted; the innovation
    there is 0."""
    y, omega, _ = _signals(T=700)
    y[[100, 650]] = np.nan
    params = make_pe_monitor(2, N, DT, 1.0)
    state, out = jax.jit(lambda y: run(pe_monitor, params, EstimatorInputs(y=y)))(y)
    assert int(state.missing) == 2
    kept = omega.copy()
    kept[[100, 650]] = 0.0
    rows = slice(700 - N, 700)
    np.testing.assert_allclose(out.gram[-1], DT * kept[rows].T @ kept[rows], rtol=1e-12)
    assert float(out.innovation[650, 0]) == 0.0


def test_jit_vmap_equal_eager_steps():
    """A batch of three signals under jit(vmap(run)) equals the eager step-by-step run of each."""
    ys = np.stack([_signals(T=40, seed=s)[0] for s in range(3)])
    params = make_pe_monitor(2, 16, DT, 1e-3)
    batched = jax.jit(jax.vmap(lambda y: run(pe_monitor, params, EstimatorInputs(y=y))[1]))(ys)
    for b in range(3):
        state = pe_monitor.init(params)
        for k in range(ys.shape[1]):
            state, out = pe_monitor.step(params, state, EstimatorInputs(y=ys[b, k]))
        np.testing.assert_allclose(batched.gram[b, -1], out.gram, rtol=1e-13)
        np.testing.assert_allclose(batched.x[b, -1], out.x, rtol=1e-12)
        assert bool(batched.excited[b, -1]) == bool(out.excited)


def test_lambda_min_is_differentiable_in_the_signal():
    """d lambda_min / d amplitude for omega = a [sin t, cos t] over a full window is 2 lambda_min / a."""
    t = DT * np.arange(N)
    params = make_pe_monitor(2, N, DT, 1.0)

    def lowest(a):
        y = jnp.column_stack([a * jnp.sin(t), a * jnp.cos(t), jnp.zeros(N)])
        return run(pe_monitor, params, EstimatorInputs(y=y))[1].lambda_min[-1]

    a = 1.5
    assert float(jax.grad(lowest)(a)) == pytest.approx(2 * float(lowest(a)) / a, rel=1e-10)


def test_bad_input_raises_naming_the_argument():
    cases = [
        ("dt", lambda: make_pe_monitor(2, 10, 0.0, 1.0)),
        ("dt", lambda: make_pe_monitor(2, 10, -0.1, 1.0)),
        ("window", lambda: make_pe_monitor(2, 0, 0.1, 1.0)),
        ("window", lambda: make_pe_monitor(2, 2.5, 0.1, 1.0)),
        ("threshold", lambda: make_pe_monitor(2, 10, 0.1, 0.0)),
        ("n_regressors", lambda: make_pe_monitor(0, 10, 0.1, 1.0)),
    ]
    for name, call in cases:
        with pytest.raises(ValueError, match=rf"^{name}\b"):
            call()
    params = make_pe_monitor(2, 10, 0.1, 1.0)
    with pytest.raises(ValueError, match=r"^inputs\.y\b"):
        pe_monitor.step(params, pe_monitor.init(params), EstimatorInputs(y=np.ones(2)))
