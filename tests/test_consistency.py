"""Tests for jaxobs.consistency: the chi-square quantile against SciPy, NEES and NIS of consistent and
inconsistent Kalman filters over Monte-Carlo runs (values against NumPy, missing components, the EKF's outputs),
the whiteness test of optimal and mistuned filters, and jit/vmap/grad and bad inputs."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from jax.test_util import check_grads

import jaxobs as jo
from jaxobs.consistency import autocovariance, chi2_quantile, nees, nis, whiteness

PHI = np.array([[1.0, 0.1], [0.0, 0.98]])
C = np.array([[1.0, 0.0]])
Q = np.array([[1e-3, 0.0], [0.0, 4e-3]])
R = np.array([[0.05]])
RUNS, T = 40, 150


def test_chi2_quantile_equals_scipy_and_traces():
    qs = np.array([1e-4, 0.025, 0.5, 0.975, 0.9999])
    dofs = np.array([1.0, 2.0, 3.0, 10.5, 300.0, 2e4])
    got = chi2_quantile(qs[:, None], dofs[None, :])
    np.testing.assert_allclose(got, scipy.stats.chi2.ppf(qs[:, None], dofs[None, :]), rtol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.vmap(chi2_quantile, (None, 0)))(0.975, dofs), got[3], rtol=1e-14)
    assert float(chi2_quantile(0.5, 0.0)) == 0.0


@pytest.fixture(scope="module")
def monte_carlo():
    """``RUNS`` records of a constant-velocity-like model (true states and measurements)."""
    params = jo.make_kalman(PHI, C, Q, R, x0=np.zeros(2), P0=np.eye(2))
    return jax.vmap(lambda k: jo.sample(params, k, T))(jax.random.split(jax.random.PRNGKey(0), RUNS))


def _filtered(q_scale, y):
    params = jo.make_kalman(PHI, C, q_scale * Q, R, x0=np.zeros(2), P0=np.eye(2))
    params = dataclasses.replace(params, output_covariance=True)
    return jax.vmap(lambda y: jo.run(jo.kalman_filter, params, jo.EstimatorInputs(y))[1])(y)


def test_nees_and_nis_accept_a_consistent_filter_and_reject_an_overconfident_one(monte_carlo):
    """The filter of the true model: about 95 % of the per-sample averages over 40 runs lie in their two-sided
    95 % bands (binomially, at least 85 % of 150 samples), and the NIS time average (of white innovations) in its
    band; with Q 100 times too small (overconfident) the NEES and NIS time averages lie far above their upper
    bands. The statistics equal the NumPy quadratic forms."""
    x, y = monte_carlo
    consistent = _filtered(1.0, y)
    for test in (nees(consistent, x), nis(consistent)):
        assert float(test.fraction_inside) >= 0.85
    test = nis(consistent)
    assert test.time_band[0] <= test.time_average <= test.time_band[1]
    overconfident = _filtered(0.01, y)
    for test in (nees(overconfident, x), nis(overconfident)):
        assert float(test.time_average) > 1.5 * float(test.time_band[1])
        assert float(test.fraction_inside) < 0.5
    error = np.asarray(x - consistent.x)
    expected = np.einsum("rti,rtij,rtj->rt", error, np.linalg.inv(consistent.P), error)
    np.testing.assert_allclose(nees(consistent, x).statistic, expected, rtol=1e-10)
    band = scipy.stats.chi2.ppf([0.025, 0.975], RUNS * 2) / RUNS
    np.testing.assert_allclose(nees(consistent, x).lower, band[0], rtol=1e-12)
    np.testing.assert_allclose(nees(consistent, x).upper, band[1], rtol=1e-12)


def test_nis_with_missing_components_and_of_the_ekf():
    """With missing components NIS sums the observed ones and counts them as its degrees of freedom (against
    NumPy); the EKF's outputs carry S, so NIS takes them too (on a linear model equal to the Kalman filter's)."""
    rng = np.random.default_rng(2)
    y = rng.normal(size=(30, 2))
    y[[3, 8], 0] = np.nan
    y[12] = np.nan
    C2, R2 = np.array([[1.0, 0.0], [0.0, 1.0]]), np.diag([0.2, 0.3])
    params = jo.make_kalman(PHI, C2, Q, R2, x0=np.zeros(2), P0=np.eye(2))
    _, out = jo.run(jo.kalman_filter, params, jo.EstimatorInputs(jnp.asarray(y)))
    test = nis(out, y)
    observed = np.isfinite(y)
    expected = [e[o] @ np.linalg.solve(S[np.ix_(o, o)], e[o]) if o.any() else 0.0
                for e, S, o in zip(np.asarray(out.innovation), np.asarray(out.S), observed, strict=True)]  # fmt: skip
    np.testing.assert_allclose(test.statistic[0], expected, rtol=1e-10, atol=1e-14)
    np.testing.assert_array_equal(test.dof[0], observed.sum(1))
    model = jo.nonlinear_model(lambda x, u, t: jnp.asarray(PHI) @ x, lambda x: jnp.asarray(C2) @ x, Q, R2,
                               x0=np.zeros(2), P0=np.eye(2))  # fmt: skip
    _, ekf = jo.run(jo.extended_kalman_filter, jo.make_ekf(model), jo.EstimatorInputs(jnp.asarray(y)))
    np.testing.assert_allclose(nis(ekf, y).statistic, test.statistic, rtol=1e-9, atol=1e-12)


def test_whiteness_accepts_the_optimal_filter_and_rejects_a_mistuned_one(monte_carlo):
    """The steady-state filter of the true model leaves white innovations (about 95 % of the autocorrelations
    inside their band); a filter with R 100 times too large leaves strongly correlated ones. The autocovariance
    equals NumPy's lagged products."""
    _, y = monte_carlo
    optimal = jo.make_kalman(PHI, C, Q, R, steady_state=True)
    mistuned = jo.make_kalman(PHI, C, Q, 100 * R, steady_state=True)
    innovations = {}
    for name, params in (("optimal", optimal), ("mistuned", mistuned)):
        innovations[name] = jax.vmap(lambda y, p=params: jo.run(jo.kalman_filter, p, jo.EstimatorInputs(y))[1])(y)
    white = whiteness(innovations["optimal"].innovation[:, 20:], lags=10)
    coloured = whiteness(innovations["mistuned"].innovation[:, 20:], lags=10)
    assert float(white.fraction_inside) >= 0.8
    assert float(coloured.fraction_inside) <= 0.2
    e = np.asarray(innovations["optimal"].innovation[:, 20:])
    lag2 = np.mean([np.mean(run[2:, 0] * run[:-2, 0]) for run in e])
    np.testing.assert_allclose(autocovariance(e, 3)[2, 0, 0], lag2, rtol=1e-12)


def test_jit_vmap_and_grad(monte_carlo):
    """eager = jit for NEES, NIS and whiteness; a vmap over three R scales (plants) equals a loop; the NIS time
    average is differentiable in R (check_grads, reverse mode)."""
    x, y = monte_carlo
    y = y[:3, :30]

    def average_nis(r_scale):
        params = jo.make_kalman(PHI, C, Q, r_scale * R, x0=np.zeros(2), P0=np.eye(2))
        out = jax.vmap(lambda y: jo.run(jo.kalman_filter, params, jo.EstimatorInputs(y))[1])(y)
        return nis(out).time_average

    np.testing.assert_allclose(jax.jit(average_nis)(1.3), average_nis(1.3), rtol=1e-12)
    scales = jnp.array([0.5, 1.0, 2.0])
    np.testing.assert_allclose(jax.vmap(average_nis)(scales), [average_nis(s) for s in scales], rtol=1e-12)
    check_grads(jax.jit(average_nis), (1.3,), order=1, modes=("rev",))
    out = _filtered(1.0, y)
    np.testing.assert_allclose(jax.jit(nees)(out, x[:3, :30]).statistic, nees(out, x[:3, :30]).statistic, rtol=1e-13)
    np.testing.assert_allclose(jax.jit(whiteness, static_argnums=1)(out.innovation, 5).autocorrelation,
                               whiteness(out.innovation, 5).autocorrelation, rtol=1e-12)  # fmt: skip


def test_bad_inputs_raise_naming_the_argument(monte_carlo):
    x, y = monte_carlo
    out = _filtered(1.0, y[:2, :10])
    with pytest.raises(ValueError, match="x_true must have shape"):
        nees(out, x[:2, :10, :1])
    with pytest.raises(ValueError, match="outputs has no covariance P"):
        nees(out._replace(P=None), x[:2, :10])
    with pytest.raises(ValueError, match="outputs has no innovation covariance S"):
        nis(out._replace(S=None))
    with pytest.raises(ValueError, match="y must have shape"):
        nis(out, y[:2, :9])
    with pytest.raises(ValueError, match="lags must be an integer in"):
        whiteness(out.innovation, 10)
    with pytest.raises(ValueError, match="innovation must have shape"):
        autocovariance(jnp.ones(5), 2)
