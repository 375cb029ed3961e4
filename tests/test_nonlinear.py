"""jaxobs.nonlinear on manifolds: a model's ``difference`` and ``retract`` carry the EKF, the UKF, their smoother, the
likelihood and NEES to a state or a measurement that is not a vector (here a unit quaternion); vector models keep
their results."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxobs as jo
from jaxobs.mjx.manifold import quat_difference, quat_integrate
from jaxobs.nonlinear import Manifold

DT = 0.05
ROTATION = Manifold(jax.tree_util.Partial(quat_difference), jax.tree_util.Partial(quat_integrate), 3, 4)
VECTORS = jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # gravity and north, world frame


def turn(q, u, t):
    """The attitude after one sample of the body rate ``u`` (rad/s), held."""
    del t
    return quat_integrate(q, DT * u)


def body_vectors(q):
    """The two world vectors seen in the body frame (an accelerometer at rest and a magnetometer): (6,)."""
    w, v = q[0], q[1:]
    rotate_back = lambda r: r + 2 * jnp.cross(v, jnp.cross(v, r) - w * r)  # noqa: E731  (R(q)' r)
    return jnp.concatenate([rotate_back(VECTORS[0]), rotate_back(VECTORS[1])])


def _attitude_model(measure_quaternion: bool):
    Q = (0.02**2) * jnp.eye(3)
    if measure_quaternion:
        return jo.nonlinear_model(turn, lambda q: q, Q, (0.05**2) * jnp.eye(3), x0=[1.0, 0, 0, 0], P0=0.05 * jnp.eye(3),
                                  n_inputs=3, dt=DT, manifold=ROTATION, measurement_manifold=ROTATION)  # fmt: skip
    return jo.nonlinear_model(turn, body_vectors, Q, (0.05**2) * jnp.eye(6), x0=[1.0, 0, 0, 0], P0=0.05 * jnp.eye(3),
                              n_inputs=3, dt=DT, manifold=ROTATION)  # fmt: skip


@jax.jit
def _simulate(model, key):
    """A true attitude drawn from the prior, turned by known rates plus the process noise; readings with noise."""
    T = 60
    k0, kw, kv = jax.random.split(key, 3)
    rates = jnp.stack([jnp.sin(0.3 * jnp.arange(T)), jnp.cos(0.2 * jnp.arange(T)), 0.5 * jnp.ones(T)], axis=1)
    start = quat_integrate(model.x0, jnp.linalg.cholesky(model.P0) @ jax.random.normal(k0, (3,)))
    w = jax.random.normal(kw, (T, 3)) @ jnp.linalg.cholesky(model.Q).T

    def advance(q, inputs):
        u, w_next = inputs
        return quat_integrate(turn(q, u, 0.0), w_next), q

    _, truth = jax.lax.scan(advance, start, (rates, w))
    r = model.R.shape[0]
    v = jax.random.normal(kv, (T, r)) @ jnp.linalg.cholesky(model.R).T
    if model.measurement_manifold is None:
        y = jax.vmap(model.h)(truth) + v
    else:
        y = jax.vmap(lambda q, e: quat_integrate(model.h(q), e))(truth, v)
    u_prev = jnp.concatenate([jnp.zeros((1, 3)), rates[:-1]])
    return truth, y, u_prev


@pytest.mark.parametrize("measure_quaternion", [False, True], ids=["vector readings", "quaternion readings"])
def test_attitude_filters_are_consistent(measure_quaternion):
    """A quaternion attitude (4 entries, 3 tangent directions) under known rates, measured by two body-frame vectors
    or by a quaternion (a star tracker, residual a rotation vector): over 30 Monte-Carlo runs the EKF's and the UKF's
    average NEES over the runs lies in its 95 % band at 80 % of the 60 samples or more (a consistent filter: 95 % in
    expectation; the samples' errors are correlated, so the fraction of one record scatters: 87 % to 97 % measured)
    and its average over runs and samples within 10 % of the 3 degrees of freedom; the smoother lowers the error."""
    model = _attitude_model(measure_quaternion)
    truth, y, u_prev = jax.vmap(lambda key: _simulate(model, key))(jax.random.split(jax.random.key(0), 30))
    for estimator, params in ((jo.extended_kalman_filter, jo.make_ekf(model)),
                              (jo.unscented_kalman_filter, jo.make_ukf(model))):  # fmt: skip
        run = jax.jit(jax.vmap(lambda y, u, params=params, e=estimator: jo.smooth(e, params, jo.EstimatorInputs(y, u))))
        filtered, smoothed = run(y, u_prev)
        np.testing.assert_allclose(jnp.linalg.norm(filtered.x, axis=-1), 1.0, atol=1e-12)
        test = jo.nees(filtered, truth, manifold=ROTATION)
        assert float(test.fraction_inside) >= 0.8, (float(test.fraction_inside), float(test.time_average))
        assert abs(float(test.time_average) - 3.0) < 0.3, float(test.time_average)
        error = lambda x: jnp.mean(jax.vmap(jax.vmap(quat_difference))(x, truth) ** 2)  # noqa: E731
        assert float(error(smoothed.x)) < 0.8 * float(error(filtered.x))
        assert smoothed.P.shape == filtered.P.shape == (30, 60, 3, 3)


def _linear_model(manifold):
    f = lambda x, u, t: jnp.array([x[0] + 0.1 * x[1], x[1] - 0.1 * jnp.sin(x[0]) + 0.1 * u[0]])  # noqa: E731
    h = lambda x: jnp.array([jnp.sin(x[0]), x[0] * x[1]])  # noqa: E731
    return jo.nonlinear_model(f, h, 1e-3 * jnp.eye(2), 0.01 * jnp.eye(2), x0=[0.3, 0.0], P0=0.5 * jnp.eye(2),
                              n_inputs=1, manifold=manifold, measurement_manifold=manifold)  # fmt: skip


def test_the_vector_space_as_a_manifold_gives_the_vector_results():
    """The tangent-space code path with ``a - b`` and ``b + d`` as the manifold's maps equals the vector filters
    (iterated and gated EKF, UKF and cubature, smoother, likelihood, with a missing and an outlying reading)."""
    plus = Manifold(jax.tree_util.Partial(jnp.subtract), jax.tree_util.Partial(jnp.add), 2, 2)
    T = 30
    y = jnp.stack([jnp.sin(0.1 * jnp.arange(T)), jnp.cos(0.2 * jnp.arange(T))], 1).at[5, 0].set(jnp.nan)
    inputs = jo.EstimatorInputs(y=y.at[17, 1].set(50.0), u_prev=jnp.sin(0.3 * jnp.arange(T))[:, None])
    for vector, on_manifold in ((_linear_model(None), _linear_model(plus)),):
        for estimator, make in ((jo.extended_kalman_filter, lambda m: jo.make_ekf(m, iterations=3, gate=3.0)),
                                (jo.unscented_kalman_filter, jo.make_ukf),
                                (jo.unscented_kalman_filter, lambda m: jo.make_ukf(m, rule="cubature"))):  # fmt: skip
            expected, smoothed = jo.smooth(estimator, make(vector), inputs)
            got, got_smoothed = jo.smooth(estimator, make(on_manifold), inputs)
            for field in ("x", "P", "innovation", "log_likelihood", "transition"):
                np.testing.assert_allclose(getattr(got, field), getattr(expected, field), rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(got_smoothed.x, smoothed.x, rtol=1e-10, atol=1e-12)


def test_gradient_of_the_likelihood_on_a_manifold():
    """The log-likelihood of a quaternion record is differentiable in the noise level (reverse = central
    differences) and batches over models (vmap = loop)."""
    model = _attitude_model(True)
    truth, y, u_prev = _simulate(model, jax.random.key(1))

    def ll(scale):
        scaled = dataclasses.replace(model, R=scale * model.R)
        return jo.log_likelihood(jo.unscented_kalman_filter, jo.make_ukf(scaled), jo.EstimatorInputs(y, u_prev))

    scales = jnp.array([1.3 - 1e-5, 1.3 + 1e-5, 0.8])
    batched = jax.jit(jax.vmap(ll))(scales)
    np.testing.assert_allclose(batched[2], ll(0.8), rtol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.grad(ll))(1.3), (batched[1] - batched[0]) / 2e-5, rtol=1e-5)


def test_bad_manifold_models_raise_naming_the_argument():
    with pytest.raises(ValueError, match=r"Q has shape \(4, 4\), but dimension 0 must be 3"):
        jo.nonlinear_model(turn, body_vectors, jnp.eye(4), jnp.eye(6), x0=[1.0, 0, 0, 0], n_inputs=3,
                           manifold=ROTATION)  # fmt: skip
    with pytest.raises(ValueError, match="continuous=True"):
        jo.nonlinear_model(turn, body_vectors, jnp.eye(3), jnp.eye(6), x0=[1.0, 0, 0, 0], n_inputs=3,
                           manifold=ROTATION, continuous=True)  # fmt: skip
    with pytest.raises(ValueError, match=r"R must be \(3, 3\)"):
        jo.nonlinear_model(turn, lambda q: q, jnp.eye(3), jnp.eye(4), x0=[1.0, 0, 0, 0], n_inputs=3,
                           manifold=ROTATION, measurement_manifold=ROTATION)  # fmt: skip
    with pytest.raises(ValueError, match="manifold holds points of 4 entries"):
        jo.nonlinear_model(turn, body_vectors, jnp.eye(3), jnp.eye(6), x0=[1.0, 0, 0], n_inputs=3, manifold=ROTATION)
    model = _attitude_model(False)
    filtered = jo.run(jo.extended_kalman_filter, dataclasses.replace(jo.make_ekf(model), output_covariance=True),
                      jo.EstimatorInputs(jnp.zeros((5, 6)), jnp.zeros((5, 3))))[1]  # fmt: skip
    with pytest.raises(ValueError, match="parallel=True"):
        jo.rts_smoother(filtered.transition, filtered, parallel=True, manifold=ROTATION)
