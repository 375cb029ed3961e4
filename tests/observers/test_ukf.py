"""Tests for jaxobs.observers.ukf: dynamax's unscented Kalman filter on a pendulum and a bearings-only model (the
unscented rule and the cubature rule), cuthbert's quadrature linearisation and Kalman steps (the cubature and
Gauss-Hermite filters), the Kalman filter on linear models (discrete and continuous-discrete), the sigma-point
moments, the iterated posterior linearisation, missing measurements, jit/vmap/grad and bad inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxobs as jo
from jaxobs.lti import c2d, ss
from jaxobs.observers.ukf import sigma_points, unit_points, unscented
from tests._nonlinear_models import (
    bearings,
    bearings_h,
    dynamax_params,
    linear_problem,
    pendulum,
    relative_error,
    van_loan,
    without_dynamax_regularisation,
)

RULES = {"dynamax default": dict(alpha=float(np.sqrt(3.0)), beta=2.0, kappa=1.0), "cubature": dict(rule="cubature")}


@pytest.mark.parametrize("make_problem", [pendulum, bearings], ids=["pendulum", "bearings"])
def test_equals_dynamax_ukf(make_problem, monkeypatch):
    """dynamax's unscented_kalman_filter on the same data and prior, with its default (alpha, beta, kappa) =
    (sqrt 3, 2, 1) and with (1, 0, 0), the cubature rule; its 1e-9 I regularisation removed: means and covariances
    agree to 1e-9 relative (measured 2e-15 / 3e-15 on the pendulum; 2.8e-9 / 1.2e-8 with the regularisation), and
    so does the standard covariance form (its update from the sigma points' moments)."""
    nlgssm = pytest.importorskip("dynamax.nonlinear_gaussian_ssm")
    without_dynamax_regularisation(monkeypatch)
    problem = make_problem()
    inputs = None if problem.u_prev is None else jnp.asarray(problem.u_prev)
    hyper = {"dynamax default": nlgssm.UKFHyperParams(), "cubature": nlgssm.UKFHyperParams(1.0, 0.0, 0.0)}
    standard = ("dynamax default", RULES["dynamax default"], False)  # joseph=False: the moments' update
    cases = [(name, rule, True) for name, rule in RULES.items()] + [standard]
    for name, rule, joseph in cases:
        params = jo.make_ukf(problem.model(), **rule, joseph=joseph)
        _, out = jo.run(jo.unscented_kalman_filter, params, problem.inputs())
        post = nlgssm.unscented_kalman_filter(dynamax_params(problem), jnp.asarray(problem.y), hyper[name], inputs)
        assert relative_error(out.x, post.filtered_means) < 1e-9, (name, joseph)
        assert relative_error(out.P, post.filtered_covariances) < 1e-9, (name, joseph)


def cuthbert_quadrature_filter(problem, quadrature):
    """cuthbert's quadrature filter on ``problem``: at each sample its statistical linear regression of ``f`` and
    then ``h`` (``cuthbertlib.quadrature.functional``) around the current Gaussian, then its square-root Kalman
    predict and update (``cuthbertlib.kalman.filtering``), from the prior of ``x_0`` (no prediction at the first
    sample, as jaxobs). Returns the filtered means, covariances and per-step log-likelihoods."""
    from cuthbertlib.kalman import filtering
    from cuthbertlib.quadrature import functional

    Q, R = jnp.asarray(problem.Q), jnp.asarray(problem.R)
    u_prev = np.zeros((len(problem.y), 0)) if problem.u_prev is None else problem.u_prev

    def step(carry, inputs):
        m, chol_P, first = carry
        u, y = inputs
        F, c, Q_lin = functional(lambda x: problem.f(x, u, 0.0), Q, m, chol_P @ chol_P.T, quadrature)
        m_pred, chol_pred = filtering.predict(m, chol_P, F, c, jnp.linalg.cholesky(Q_lin))
        m, chol_P = jnp.where(first, m, m_pred), jnp.where(first, chol_P, chol_pred)
        H, d, R_lin = functional(problem.h, R, m, chol_P @ chol_P.T, quadrature)
        (m, chol_P), ell = filtering.update(m, chol_P, H, d, jnp.linalg.cholesky(R_lin), y)
        return (m, chol_P, False), (m, chol_P @ chol_P.T, ell)

    start = (jnp.asarray(problem.x0), jnp.linalg.cholesky(jnp.asarray(problem.P0)), True)
    _, out = jax.lax.scan(step, start, (jnp.asarray(u_prev), jnp.asarray(problem.y)))
    return out


QUADRATURES = {"cubature": {}, "gauss_hermite": {"order": 3}, "gauss_hermite order 5": {"order": 5}}


@pytest.mark.parametrize("make_problem", [pendulum, pytest.param(bearings, marks=pytest.mark.slow)],
                         ids=["pendulum", "bearings"])  # fmt: skip
def test_cubature_and_gauss_hermite_equal_cuthbert(make_problem):
    """The cubature (Arasaratnam & Haykin 2009) and Gauss-Hermite (orders 3 and 5) filters equal cuthbert's
    quadrature linearisation with its square-root Kalman steps: means, covariances and per-step log-likelihoods
    to 1e-8 relative, in both covariance updates."""
    from cuthbertlib.quadrature import cubature, gauss_hermite

    problem = make_problem(T=40)
    n = problem.x0.shape[0]
    for name, kw in QUADRATURES.items():
        rule = name.split()[0]
        quadrature = cubature.weights(n) if rule == "cubature" else gauss_hermite.weights(n, **kw)
        means, covariances, ell = cuthbert_quadrature_filter(problem, quadrature)
        for joseph in (True, False):
            params = jo.make_ukf(problem.model(), rule=rule, joseph=joseph, **kw)
            _, out = jo.run(jo.unscented_kalman_filter, params, problem.inputs())
            assert relative_error(out.x, means) < 1e-8, (name, joseph)
            assert relative_error(out.P, covariances) < 1e-8, (name, joseph)
            assert relative_error(out.log_likelihood, ell) < 1e-8, (name, joseph)


def test_quadrature_points_integrate_polynomials():
    """The cubature points are cuthbert's and integrate every polynomial of degree 3 exactly; the Gauss-Hermite
    points of order k integrate x_i^(2k - 2) exactly (its Gaussian moment (2k - 3)!!) and sum to one; the rule of
    order 3 equals cuthbert's points and weights."""
    from cuthbertlib.quadrature import cubature, gauss_hermite

    n = 3
    xi, w = unit_points(n, "cubature")
    reference = cubature.weights(n)
    np.testing.assert_allclose(xi, reference.xi, rtol=1e-15)
    np.testing.assert_allclose(w, reference.wm, rtol=1e-15)
    np.testing.assert_allclose(w @ (xi[:, 0] ** 2 * xi[:, 1] + xi[:, 2] ** 3), 0.0, atol=1e-15)
    np.testing.assert_allclose(w @ (xi**2), np.ones(n), rtol=1e-14)
    for order in (2, 3, 4):
        xi, w = unit_points(n, "gauss_hermite", order)
        assert xi.shape == (order**n, n)
        np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-14)
        double_factorial = np.prod(np.arange(2 * order - 3, 0, -2))
        np.testing.assert_allclose(w @ xi[:, 1] ** (2 * order - 2), double_factorial, rtol=1e-12)
    reference = gauss_hermite.weights(n, 3)
    xi, w = unit_points(n, "gauss_hermite", 3)
    np.testing.assert_allclose(xi, reference.xi, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(w, reference.wm, rtol=1e-14)


def test_quadrature_filters_under_jit_vmap_and_grad():
    """The Gauss-Hermite filter's estimation error: eager = jit, a vmap over three measurement-noise levels (the
    plants) equals a loop, and its gradient passes check_grads."""
    problem = pendulum(T=8)
    truth = jnp.asarray(problem.x)

    def error(r):
        model = jo.nonlinear_model(problem.f, problem.h, problem.Q, r * jnp.eye(1), x0=problem.x0, P0=problem.P0,
                                   n_inputs=1)  # fmt: skip
        x = jo.run(jo.unscented_kalman_filter, jo.make_ukf(model, rule="gauss_hermite"), problem.inputs())[1].x
        return jnp.sum((x - truth) ** 2)

    np.testing.assert_allclose(jax.jit(error)(0.09), error(0.09), rtol=1e-12)
    levels = jnp.array([0.05, 0.09, 0.2])
    np.testing.assert_allclose(jax.jit(jax.vmap(error))(levels), [error(r) for r in levels], rtol=1e-12)
    check_grads(jax.jit(error), (0.09,), order=1, modes=("rev",))


def test_linear_model_equals_the_kalman_filter():
    """The unscented transform is exact for linear maps: on a linear model the UKF is the Kalman filter, missing
    components included (to rounding), in both covariance forms, its per-step log-likelihoods too."""
    problem, A, B, C = linear_problem()
    for joseph in (True, False):
        params = jo.make_ukf(problem.model(), joseph=joseph)
        state, out = jo.run(jo.unscented_kalman_filter, params, problem.inputs())
        kf = jo.make_kalman(A, C, problem.Q, problem.R, Gamma=B, x0=problem.x0, P0=problem.P0)
        kf_state, kf_out = jo.run(jo.kalman_filter, kf, problem.inputs())
        for name in ("x", "x_prior", "innovation", "gain", "log_likelihood"):
            np.testing.assert_allclose(getattr(out, name), getattr(kf_out, name), rtol=1e-10, atol=1e-12,
                                       err_msg=name)  # fmt: skip
        np.testing.assert_allclose(state.P, kf_state.P, rtol=1e-10, atol=1e-13)
        assert int(state.missing) == int(kf_state.missing) == 4


def test_continuous_discrete_linear_model_equals_the_exact_discretisation():
    """The sigma-point moment equations (Särkkä 2007) of a linear model are the exact ones: with 40 RK4 substeps
    the continuous-discrete UKF equals the Kalman filter of the exact discretisation to 1e-9."""
    A, B, C = jnp.array([[0.0, 1.0], [-4.0, -0.6]]), jnp.array([[0.0], [1.0]]), jnp.array([[1.0, 0.0]])
    Qc, R, h = jnp.diag(jnp.array([0.01, 0.2])), jnp.array([[0.05]]), 0.1
    rng = np.random.default_rng(3)
    inputs = jo.EstimatorInputs(jnp.asarray(rng.normal(size=(30, 1))), jnp.asarray(rng.normal(size=(30, 1))))
    plant = c2d(ss(A, B, C), h)
    kf = jo.make_kalman(plant.A, C, van_loan(A, Qc, h), R, Gamma=plant.B, x0=[1.0, 0.0], P0=jnp.eye(2))
    _, exact = jo.run(jo.kalman_filter, kf, inputs)
    model = jo.nonlinear_model(lambda x, u, t: A @ x + B @ u, lambda x: C @ x, Qc, R, x0=[1.0, 0.0], P0=jnp.eye(2),
                               n_inputs=1, dt=h, continuous=True, substeps=40)  # fmt: skip
    _, out = jo.run(jo.unscented_kalman_filter, jo.make_ukf(model, rule="cubature"), inputs)
    assert relative_error(out.x, exact.x) < 1e-9
    assert relative_error(out.gain, exact.gain) < 1e-9


def test_sigma_points_match_the_moments():
    """The sigma points reproduce the mean and covariance, and the unscented mean of a quadratic is exact
    (E[x'Ax + b'x] = tr(A P) + m'Am + b'm), for both rules; cubature weights are 0 (centre) and 1/(2n)."""
    rng = np.random.default_rng(0)
    n = 3
    m = jnp.asarray(rng.normal(size=n))
    G = rng.normal(size=(n, n))
    P = jnp.asarray(G @ G.T + 0.1 * np.eye(n))
    Aq, b = jnp.asarray(rng.normal(size=(n, n))), jnp.asarray(rng.normal(size=n))
    for alpha, beta, kappa in [(1.0, 0.0, 0.0), (0.5, 2.0, 1.0), (np.sqrt(3.0), 2.0, 1.0)]:
        X, wm, wc, _ = sigma_points(m, P, alpha, beta, kappa)
        np.testing.assert_allclose(wm @ X, m, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose((wc[:, None] * (X - m)).T @ (X - m), P, rtol=1e-13, atol=1e-14)
        lin = unscented(lambda x: jnp.atleast_1d(x @ Aq @ x + b @ x), m, P, alpha, beta, kappa)
        np.testing.assert_allclose(lin.mean[0], jnp.trace(Aq @ P) + m @ Aq @ m + b @ m, rtol=1e-12)
    _, wm, wc, _ = sigma_points(m, P, 1.0, 0.0, 0.0)
    np.testing.assert_allclose(wm, np.r_[0.0, np.full(2 * n, 1 / (2 * n))], atol=1e-15)
    np.testing.assert_allclose(wc, wm, atol=1e-15)


def test_iterated_posterior_linearisation_reaches_a_fixed_point():
    """Iterated posterior linearisation (García-Fernández et al. 2015) on the bearings measurement from a wide
    prior: the iterations move the estimate far from the plain UKF's, then converge geometrically (the step from
    11 to 12 iterations is 2e-10 of the first update's, measured; required < 1e-8): a fixed point. On a linear
    measurement iterations change nothing."""
    problem = bearings()
    m, P = jnp.array([0.5, -0.5, 1.0, 0.0]), jnp.diag(jnp.array([1.0, 1.0, 0.5, 0.5]))
    model = jo.nonlinear_model(problem.f, problem.h, problem.Q, problem.R, x0=m, P0=P)
    y = jo.EstimatorInputs(jnp.asarray(problem.y[0]))

    # one step: eager dispatch is cheaper than compiling one program per iteration count
    def estimate(params):
        return jo.unscented_kalman_filter.step(params, jo.unscented_kalman_filter.init(params), y)[1].x

    plain, eleven, twelve = (estimate(jo.make_ukf(model, rule="cubature", iterations=i)) for i in (1, 11, 12))
    first = float(jnp.linalg.norm(plain - m))
    assert float(jnp.linalg.norm(eleven - plain)) > 0.1 * first  # the iterations do move the estimate
    assert float(jnp.linalg.norm(twelve - eleven)) < 1e-8 * first
    linear, *_ = linear_problem(missing=True)
    _, one = jo.run(jo.unscented_kalman_filter, jo.make_ukf(linear.model()), linear.inputs())
    _, three = jo.run(jo.unscented_kalman_filter, jo.make_ukf(linear.model(), iterations=3), linear.inputs())
    np.testing.assert_allclose(three.x, one.x, rtol=1e-9, atol=1e-11)


def test_missing_component_equals_the_model_without_it():
    problem = bearings(T=30)
    y = problem.y.copy()
    y[:, 1] = np.nan
    reduced = jo.nonlinear_model(problem.f, lambda x: bearings_h(x)[:1], problem.Q, problem.R[:1, :1],
                                 x0=problem.x0, P0=problem.P0)  # fmt: skip
    for joseph in (True, False):
        params = jo.make_ukf(problem.model(), joseph=joseph)
        state, out = jo.run(jo.unscented_kalman_filter, params, jo.EstimatorInputs(jnp.asarray(y)))
        _, ref = jo.run(jo.unscented_kalman_filter, jo.make_ukf(reduced, joseph=joseph),
                        jo.EstimatorInputs(jnp.asarray(y[:, :1])))  # fmt: skip
        np.testing.assert_allclose(out.x, ref.x, rtol=1e-11, atol=1e-13)
        np.testing.assert_allclose(out.P, ref.P, rtol=1e-11, atol=1e-13)
        np.testing.assert_allclose(out.log_likelihood, ref.log_likelihood, rtol=1e-11)  # contributes nothing
        np.testing.assert_array_equal(out.innovation[:, 1], 0.0)
        assert int(state.missing) == 30


def _sigma_point_error():
    """The squared estimation error of the UKF on a short pendulum run as a jitted function of ``(alpha, r)``."""
    problem = pendulum(T=8)
    truth = jnp.asarray(problem.x)

    @jax.jit
    def error(alpha, r):
        model = jo.nonlinear_model(problem.f, problem.h, problem.Q, r * jnp.eye(1), x0=problem.x0, P0=problem.P0,
                                   n_inputs=1)  # fmt: skip
        x = jo.run(jo.unscented_kalman_filter, jo.make_ukf(model, alpha=alpha), problem.inputs())[1].x
        return jnp.sum((x - truth) ** 2)

    return error


def test_vmap_over_sigma_point_parameters():
    """alpha, beta, kappa are leaves: a vmap over three settings of alpha equals a loop."""
    error = _sigma_point_error()
    alphas = jnp.array([0.5, 1.0, 1.5])
    batched = jax.vmap(error, in_axes=(0, None))(alphas, 0.09)
    np.testing.assert_allclose(batched, [error(a, 0.09) for a in alphas], rtol=1e-12)


@pytest.mark.slow
def test_gradients_with_respect_to_alpha_and_the_measurement_noise():
    """check_grads (forward and reverse) of the estimation error with respect to alpha and the measurement noise
    (the filter step shared with the EKF is checked in the default set by tests/observers/test_ekf.py)."""
    check_grads(_sigma_point_error(), (1.2, 0.09), order=1, modes=("fwd", "rev"))


def test_bad_inputs_raise_naming_the_argument():
    problem = pendulum(T=5)
    model = problem.model()
    with pytest.raises(ValueError, match="rule must be one of"):
        jo.make_ukf(model, rule="gauss-hermite")
    with pytest.raises(ValueError, match="rule='cubature' has no alpha, beta, kappa"):
        jo.make_ukf(model, rule="cubature", alpha=0.5)
    with pytest.raises(ValueError, match="order is the Gauss-Hermite rule's"):
        jo.make_ukf(model, rule="cubature", order=3)
    with pytest.raises(ValueError, match="order must be an integer >= 2"):
        jo.make_ukf(model, rule="gauss_hermite", order=1)
    with pytest.raises(ValueError, match="alpha must be positive"):
        jo.make_ukf(model, alpha=0.0)
    with pytest.raises(ValueError, match="kappa must exceed -n = -2"):
        jo.make_ukf(model, kappa=-2.0)
    with pytest.raises(ValueError, match="alpha must have shape"):
        jo.make_ukf(model, alpha=[1.0, 2.0])
    with pytest.raises(ValueError, match="model.P0 must be positive definite"):
        jo.make_ukf(jo.nonlinear_model(problem.f, problem.h, problem.Q, problem.R, x0=problem.x0,
                                       P0=np.diag([1.0, 0.0]), n_inputs=1))  # fmt: skip
    with pytest.raises(ValueError, match="iterations must be an integer >= 1"):
        jo.make_ukf(model, iterations=0)
    with pytest.raises(ValueError, match="joseph must be a bool"):
        jo.make_ukf(model, joseph=0)
    with pytest.raises(ValueError, match="model must be a NonlinearModel"):
        jo.make_ukf(problem)
