"""Tests for jaxobs.observers.ekf: dynamax's extended Kalman filter on a pendulum and a bearings-only model, the
Kalman filter on a linear model (discrete, and continuous-discrete against the exact discretisation), the
Gauss-Newton iterated update (its fixed point is the MAP estimate), missing measurements, jit/vmap/grad and bad
inputs."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxobs as jo
from jaxobs.lti import c2d, ss
from jaxobs.nonlinear import gaussian_step
from tests._nonlinear_models import (
    bearings,
    bearings_h,
    dynamax_params,
    linear_problem,
    pendulum,
    pendulum_f,
    relative_error,
    van_loan,
    without_dynamax_regularisation,
)


@pytest.mark.parametrize("make_problem", [pendulum, bearings], ids=["pendulum", "bearings"])
def test_equals_dynamax_ekf(make_problem, monkeypatch):
    """dynamax's extended_kalman_filter (num_iter=1) on the same data and prior, its 1e-9 I regularisation of the
    innovation covariance removed: means and covariances agree to 1e-9 relative (measured 3e-16 / 6e-16 on the
    pendulum; with dynamax's regularisation left in, 1.5e-9 / 6.9e-9, the size of that regularisation)."""
    nlgssm = pytest.importorskip("dynamax.nonlinear_gaussian_ssm")
    without_dynamax_regularisation(monkeypatch)
    problem = make_problem()
    _, out = jo.run(jo.extended_kalman_filter, jo.make_ekf(problem.model()), problem.inputs())
    inputs = None if problem.u_prev is None else jnp.asarray(problem.u_prev)
    post = nlgssm.extended_kalman_filter(dynamax_params(problem), jnp.asarray(problem.y), inputs=inputs)
    assert relative_error(out.x, post.filtered_means) < 1e-9
    assert relative_error(out.P, post.filtered_covariances) < 1e-9
    # the filter tracks: the estimate is closer to the truth than the prior guess
    assert np.sqrt(np.mean((out.x[-30:] - problem.x[-30:]) ** 2)) < 0.5


@pytest.mark.parametrize("bierman", [False, True], ids=["joseph", "bierman"])
def test_linear_model_equals_the_kalman_filter(bierman):
    """On a linear model the EKF is the Kalman filter, missing components included (to rounding), with the Joseph
    and with Bierman's U-D measurement update: estimates, gains and per-step log-likelihoods."""
    problem, A, B, C = linear_problem()
    params = jo.make_ekf(problem.model(), bierman=bierman)
    state, out = jo.run(jo.extended_kalman_filter, params, problem.inputs())
    kf = jo.make_kalman(A, C, problem.Q, problem.R, Gamma=B, x0=problem.x0, P0=problem.P0)
    kf_state, kf_out = jo.run(jo.kalman_filter, kf, problem.inputs())
    for name in ("x", "x_prior", "innovation", "gain", "log_likelihood"):
        np.testing.assert_allclose(getattr(out, name), getattr(kf_out, name), rtol=1e-12, atol=1e-12, err_msg=name)
    np.testing.assert_allclose(state.P, kf_state.P, rtol=1e-12, atol=1e-14)
    assert int(state.missing) == int(kf_state.missing) == 4


def test_continuous_discrete_linear_model_equals_the_exact_discretisation():
    """Continuous-discrete EKF of ``x' = A x + B u + w`` (spectral density Qc) = the Kalman filter of its exact
    zero-order-hold discretisation (Phi, Gamma by c2d, Q_d by Van Loan), up to the RK4 error of the moment
    equations dm/dt = A m + B u, dP/dt = A P + P A' + Qc: fourth order in the substep (error ratio 16 from 20 to
    40 substeps of a 0.1 s sample; measured relative errors of the means and gains 1.3e-9 and 7.9e-11)."""
    A = jnp.array([[0.0, 1.0], [-4.0, -0.6]])
    B = jnp.array([[0.0], [1.0]])
    C = jnp.array([[1.0, 0.0]])
    Qc, R, h = jnp.diag(jnp.array([0.01, 0.2])), jnp.array([[0.05]]), 0.1
    rng = np.random.default_rng(3)
    T = 40
    inputs = jo.EstimatorInputs(jnp.asarray(rng.normal(size=(T, 1))), jnp.asarray(rng.normal(size=(T, 1))))
    plant = c2d(ss(A, B, C), h)
    kf = jo.make_kalman(plant.A, C, van_loan(A, Qc, h), R, Gamma=plant.B, x0=[1.0, 0.0], P0=jnp.eye(2))
    _, exact = jo.run(jo.kalman_filter, kf, inputs)
    errors = []
    for substeps in (20, 40):
        model = jo.nonlinear_model(lambda x, u, t: A @ x + B @ u, lambda x: C @ x, Qc, R, x0=[1.0, 0.0],
                                   P0=jnp.eye(2), n_inputs=1, dt=h, continuous=True, substeps=substeps)  # fmt: skip
        _, out = jo.run(jo.extended_kalman_filter, jo.make_ekf(model), inputs)
        errors.append(max(relative_error(out.x, exact.x), relative_error(out.gain, exact.gain)))
    assert errors[1] < 1e-9
    assert 12 < errors[0] / errors[1] < 20


def test_iterated_update_converges_to_the_map_estimate():
    """Gauss-Newton iterations (Bell & Cathey 1993) from the prior N(m, P) minimise
    J(x) = (x - m)' P^-1 (x - m) + (y - h(x))' R^-1 (y - h(x)): after 8 iterations the gradient of J vanishes (to
    1e-9 of its size at the plain EKF's estimate). dynamax's num_iter conditions on the same measurement again
    with the posterior as prior, a different update, so it is no oracle here."""
    problem = bearings()
    m, P = jnp.array([0.5, -0.5, 1.0, 0.0]), jnp.diag(jnp.array([1.0, 1.0, 0.5, 0.5]))
    y = jnp.asarray(problem.y[0])
    model = jo.nonlinear_model(problem.f, problem.h, problem.Q, problem.R, x0=m, P0=P)

    def J(x):
        e = y - bearings_h(x)
        return (x - m) @ jnp.linalg.solve(P, x - m) + e @ jnp.linalg.solve(jnp.asarray(problem.R), e)

    # one step: eager dispatch is cheaper than compiling one program per iteration count
    def estimate(params):
        return jo.extended_kalman_filter.step(params, jo.extended_kalman_filter.init(params), jo.EstimatorInputs(y))[1]

    plain, iterated = estimate(jo.make_ekf(model)), estimate(jo.make_ekf(model, iterations=8))
    g_plain, g_iterated = (float(jnp.linalg.norm(jax.grad(J)(o.x))) for o in (plain, iterated))
    assert g_plain > 1.0
    assert g_iterated < 1e-9 * g_plain
    assert J(iterated.x) < J(plain.x)
    np.testing.assert_allclose(iterated.innovation, plain.innovation, rtol=1e-15)  # y - h(prior mean) for both
    # the log-likelihood is the predictive density of y, before the update: the first linearisation's for both
    np.testing.assert_allclose(iterated.log_likelihood, plain.log_likelihood, rtol=1e-15)


def test_iterations_change_nothing_on_a_linear_measurement():
    problem, *_ = linear_problem(missing=True)
    model = problem.model()
    _, one = jo.run(jo.extended_kalman_filter, jo.make_ekf(model), problem.inputs())
    _, three = jo.run(jo.extended_kalman_filter, jo.make_ekf(model, iterations=3), problem.inputs())
    np.testing.assert_allclose(three.x, one.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(three.P, one.P, rtol=1e-10, atol=1e-12)


def test_missing_component_equals_the_model_without_it():
    """A measurement component that is NaN at every sample is skipped exactly: the filter (and its log-likelihood)
    equals the EKF of the model that does not measure it, its innovation is zero and every skip is counted."""
    problem = bearings(T=30)
    y = problem.y.copy()
    y[:, 1] = np.nan
    full = jo.make_ekf(problem.model())
    state, out = jo.run(jo.extended_kalman_filter, full, jo.EstimatorInputs(jnp.asarray(y)))
    reduced = jo.nonlinear_model(problem.f, lambda x: bearings_h(x)[:1], problem.Q, problem.R[:1, :1],
                                 x0=problem.x0, P0=problem.P0)  # fmt: skip
    _, ref = jo.run(jo.extended_kalman_filter, jo.make_ekf(reduced), jo.EstimatorInputs(jnp.asarray(y[:, :1])))
    np.testing.assert_allclose(out.x, ref.x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(out.P, ref.P, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(out.log_likelihood, ref.log_likelihood, rtol=1e-12)  # contributes nothing
    np.testing.assert_array_equal(out.innovation[:, 1], 0.0)
    assert int(state.missing) == 30


def test_innovation_gate_skips_outliers_like_missing_samples():
    """With ``gate=4`` two outliers (30 rad added to a bearing at samples 10 and 20) are skipped: the filter equals
    the ungated one on the data with those components NaN (its log-likelihood too), and ``state.gated`` counts them
    (``state.missing`` too). Without a gate, and with a gate so wide nothing fails it, the outliers enter the
    estimate."""
    problem = bearings(T=30)
    y = problem.y.copy()
    y[[10, 20], 0] += 30.0
    holes = y.copy()
    holes[[10, 20], 0] = np.nan
    model = problem.model()
    filter_ = jax.jit(lambda params, y: jo.run(jo.extended_kalman_filter, params, jo.EstimatorInputs(y)))  # 2 compiles
    gated_state, gated = filter_(jo.make_ekf(model, gate=4.0), y)
    _, skipped = filter_(jo.make_ekf(model), holes)
    np.testing.assert_allclose(gated.x, skipped.x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(gated.P, skipped.P, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(gated.log_likelihood, skipped.log_likelihood, rtol=1e-12)
    assert int(gated_state.gated) == 2 and int(gated_state.missing) == 2
    for params in (jo.make_ekf(model), jo.make_ekf(model, gate=1e6)):
        state, out = filter_(params, y)
        assert int(state.gated) == 0 and np.abs(np.asarray(out.x[10] - skipped.x[10])).max() > 0.1


def test_eager_steps_jit_and_vmap_agree():
    """Step by step in Python (eager) = run (one scan) = the same under jit; vmap over three measurement sequences
    = a loop over them."""
    problem = pendulum(T=25)
    params = jo.make_ekf(problem.model())
    inputs = problem.inputs()
    _, out = jo.run(jo.extended_kalman_filter, params, inputs)
    state = jo.extended_kalman_filter.init(params)
    for k in (0, 1):
        sample = jo.EstimatorInputs(inputs.y[k], inputs.u_prev[k])
        state, step_out = jo.extended_kalman_filter.step(params, state, sample)
        np.testing.assert_allclose(step_out.x, out.x[k], rtol=1e-13)
    estimates = jax.jit(lambda y: jo.run(jo.extended_kalman_filter, params, inputs._replace(y=y))[1].x)
    np.testing.assert_allclose(estimates(inputs.y), out.x, rtol=1e-13)
    ys = jnp.stack([inputs.y, inputs.y + 0.1, inputs.y - 0.1])
    batched = jax.vmap(estimates)(ys)
    for b in range(3):
        np.testing.assert_allclose(batched[b], estimates(ys[b]), rtol=1e-12)


@pytest.mark.parametrize("continuous", [False, pytest.param(True, marks=pytest.mark.slow)],
                         ids=["discrete", "continuous-discrete"])  # fmt: skip
def test_gradients_reach_model_parameters_and_noise(continuous):
    """check_grads (forward and reverse) of the estimation error through the EKF with respect to a model parameter
    bound in a Partial (the pendulum's gravity), the measurement noise and, continuous-discrete, the spectral
    density."""
    problem = pendulum(T=8)
    truth, inputs = jnp.asarray(problem.x), problem.inputs()

    def loss(g, r, continuous):
        if continuous:
            f = jax.tree_util.Partial(lambda g, x, u, t: jnp.array([x[1], -g * jnp.sin(x[0]) + u[0]]), g)
            Q = r * jnp.eye(2)
            extra = dict(continuous=True, dt=0.0125, substeps=2)
        else:
            f = jax.tree_util.Partial(lambda g, x, u, t: pendulum_f(x, u, t, g), g)
            Q, extra = problem.Q, {}
        model = jo.nonlinear_model(f, problem.h, Q, r * jnp.eye(1), x0=problem.x0, P0=problem.P0, n_inputs=1,
                                   **extra)  # fmt: skip
        x = jo.run(jo.extended_kalman_filter, jo.make_ekf(model), inputs)[1].x
        return jnp.sum((x - truth) ** 2)

    check_grads(jax.jit(partial(loss, continuous=continuous)), (9.81, 0.09), order=1, modes=("fwd", "rev"))


def test_gaussian_step_is_the_ekf_step():
    """The estimator is gaussian_step with the Taylor linearisation (one home for the filter step)."""
    problem = pendulum(T=3)
    params = jo.make_ekf(problem.model())
    state = jo.extended_kalman_filter.init(params)
    inputs = jo.EstimatorInputs(jnp.asarray(problem.y[0]), jnp.asarray(problem.u_prev[0]))
    a = jo.extended_kalman_filter.step(params, state, inputs)[1]
    b = gaussian_step(jo.observers.ekf.taylor, 1, params.model, state, inputs)[1]
    np.testing.assert_array_equal(a.x, b.x)


def test_bad_inputs_raise_naming_the_argument():
    problem = pendulum(T=5)
    good = dict(x0=problem.x0, P0=problem.P0, n_inputs=1)
    with pytest.raises(ValueError, match=r"f\(x, u, t\) must return the next state"):
        jo.nonlinear_model(lambda x, u, t: x[:1], problem.h, problem.Q, problem.R, **good)
    with pytest.raises(ValueError, match=r"h\(x\) must return the measurement.*\(1,\)"):
        jo.nonlinear_model(problem.f, lambda x: x, problem.Q, problem.R, **good)
    with pytest.raises(ValueError, match=r"f\(x, u, t\) failed on arguments"):
        jo.nonlinear_model(problem.f, problem.h, problem.Q, problem.R, x0=problem.x0, P0=problem.P0)  # u is empty
    with pytest.raises(ValueError, match="R must be positive definite"):
        jo.nonlinear_model(problem.f, problem.h, problem.Q, [[0.0]], **good)
    with pytest.raises(ValueError, match="Q has shape"):
        jo.nonlinear_model(problem.f, problem.h, np.eye(3), problem.R, **good)
    with pytest.raises(ValueError, match="f must be a function"):
        jo.nonlinear_model("f", problem.h, problem.Q, problem.R, **good)
    with pytest.raises(ValueError, match="method must be one of"):
        jo.nonlinear_model(problem.f, problem.h, problem.Q, problem.R, method="rk5", **good)
    with pytest.raises(ValueError, match="dt must be a finite positive number"):
        jo.nonlinear_model(problem.f, problem.h, problem.Q, problem.R, dt=0.0, **good)
    model = problem.model()
    with pytest.raises(ValueError, match="iterations must be an integer >= 1"):
        jo.make_ekf(model, iterations=0)
    with pytest.raises(ValueError, match="bierman must be a bool"):
        jo.make_ekf(model, bierman="yes")
    with pytest.raises(ValueError, match="joseph must be a bool"):
        jo.make_ekf(model, joseph=1)
    with pytest.raises(ValueError, match="choose one covariance update"):
        jo.make_ekf(model, bierman=True, joseph=False)
    with pytest.raises(ValueError, match="model must be a NonlinearModel"):
        jo.make_ekf(problem)
    with pytest.raises(ValueError, match="gate must be finite and positive"):
        jo.make_ekf(model, gate=0.0)
    params = jo.make_ekf(model)
    step = jax.jit(jo.extended_kalman_filter.step)
    state = jo.extended_kalman_filter.init(params)
    with pytest.raises(ValueError, match=r"inputs.y must have shape \(1,\)"):
        step(params, state, jo.EstimatorInputs(jnp.zeros(2), jnp.zeros(1)))
    with pytest.raises(ValueError, match="inputs.u_prev is required"):
        step(params, state, jo.EstimatorInputs(jnp.zeros(1)))
