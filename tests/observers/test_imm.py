"""Tests for jaxobs.observers.imm: filterpy's IMMEstimator on a two-mode Kalman example (a constant-velocity and a
manoeuvring mode; the model and the filterpy reference are those of benchmarks/estimation_breadth.py), the mixing
algebra, modes of different families, jit/vmap over plants/grad and bad inputs.

Prior conventions: filterpy predicts before every update, so it gets the prior of ``x_{-1}``; jaxobs' modes get
their own predictions of it (the prior of ``x_0``) and the IMM the predicted mode probabilities ``mu M``, as its
first step has no transition (tests/observers/test_kalman.py does the same for the Kalman filter)."""

import importlib.util
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxobs as jo
from jaxobs.observers import EstimatorInputs, run
from jaxobs.observers.imm import IMMState, make_imm, mix
from jaxobs.observers.imm import imm as make_imm_estimator
from tests import ROOT
from tests._nonlinear_models import relative_error


def _workload():
    """benchmarks/estimation_breadth.py, the one home of the two-mode example and of its filterpy reference."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("estimation_breadth", ROOT / "benchmarks" / "estimation_breadth.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


BENCH = _workload()
F_CA, H, Q_CA, R, TRANSITION = BENCH.F_CA, BENCH.H, BENCH.Q_CA, BENCH.R_IMM, BENCH.TRANSITION


def manoeuvring_record(T=80, seed=0):
    """Positions of a target that cruises, accelerates between samples 30 and 45, then cruises again."""
    return BENCH.manoeuvre(T, 30, 15, np.random.default_rng(seed))


jaxobs_imm_params = BENCH.imm_params


def test_equals_filterpy_imm_estimator():
    """filterpy's IMMEstimator with two KalmanFilters: the combined mean and covariance and the mode probabilities
    agree to 1e-8 relative at every step (measured about 1e-14); the manoeuvre moves the probability to the
    constant-acceleration mode and back."""
    y = manoeuvring_record()
    xs, Ps, mus = BENCH.filterpy_imm_estimates(y)
    _, out = run(jo.imm(jo.kalman_filter, jo.kalman_filter), jaxobs_imm_params(), EstimatorInputs(jnp.asarray(y)))
    assert relative_error(out.x, xs) < 1e-8
    assert relative_error(out.P, Ps) < 1e-8
    assert relative_error(out.probabilities, mus) < 1e-8
    assert float(jnp.mean(out.probabilities[35:45, 1])) > 0.8 > float(jnp.mean(out.probabilities[70:, 1]))


def test_mix_is_the_moment_matched_mixture_and_the_log_likelihood_the_mixture_density():
    """``mix`` equals the moments of a Gaussian mixture sampled densely; the IMM's per-step log-likelihood is
    ``log sum_j c_j exp(l_j)`` of its modes' outputs (and with one mode's transition probability 1 and prior 1, the
    IMM is that mode's filter)."""
    rng = np.random.default_rng(1)
    weights = np.array([0.2, 0.5, 0.3])
    x = rng.normal(size=(3, 2))
    G = rng.normal(size=(3, 2, 2))
    P = G @ np.swapaxes(G, 1, 2) + 0.1 * np.eye(2)
    mean, cov = mix(jnp.asarray(weights)[:, None], jnp.asarray(x), jnp.asarray(P))
    second = sum(w * (Pi + np.outer(xi, xi)) for w, xi, Pi in zip(weights, x, P, strict=True))
    np.testing.assert_allclose(mean[0], weights @ x, rtol=1e-14)
    np.testing.assert_allclose(cov[0], second - np.outer(weights @ x, weights @ x), rtol=1e-13)
    y = jnp.asarray(manoeuvring_record(T=20))
    params = make_imm(jaxobs_imm_params().modes, np.eye(2), [1.0, 0.0])
    _, out = run(jo.imm(jo.kalman_filter, jo.kalman_filter), params, EstimatorInputs(y))
    _, alone = run(jo.kalman_filter, params.modes[0], EstimatorInputs(y))
    np.testing.assert_allclose(out.x, alone.x, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(out.log_likelihood, alone.log_likelihood, rtol=1e-13)
    np.testing.assert_allclose(out.probabilities[:, 0], 1.0)


def test_modes_of_different_families():
    """A Kalman filter and an EKF of the same linear model as two modes equal the IMM of two Kalman filters."""
    y = jnp.asarray(manoeuvring_record(T=30))
    params = jaxobs_imm_params()
    fast = params.modes[1]
    model = jo.nonlinear_model(lambda x, u, t: jnp.asarray(F_CA) @ x, lambda x: jnp.asarray(H) @ x, Q_CA, R,
                               x0=fast.x0, P0=fast.P0)  # fmt: skip
    mixed = make_imm([params.modes[0], jo.make_ekf(model)], TRANSITION, params.mode_prior)
    _, reference = run(jo.imm(jo.kalman_filter, jo.kalman_filter), params, EstimatorInputs(y))
    _, out = run(jo.imm(jo.kalman_filter, jo.extended_kalman_filter), mixed, EstimatorInputs(y))
    np.testing.assert_allclose(out.x, reference.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out.probabilities, reference.probabilities, rtol=1e-10, atol=1e-12)


def _log_likelihood(switch, q_scale):
    """The IMM's log-likelihood of the record as a function of the switching probability and the manoeuvre
    mode's process noise scale."""
    transition = jnp.array([[1.0 - switch, switch], [switch, 1.0 - switch]])
    params = jaxobs_imm_params(transition)
    modes = (params.modes[0], jo.make_kalman(F_CA, H, q_scale * Q_CA, R, x0=params.modes[1].x0, P0=params.modes[1].P0))
    params = make_imm(modes, transition, params.mode_prior)
    y = jnp.asarray(manoeuvring_record(T=40))
    _, out = run(jo.imm(jo.kalman_filter, jo.kalman_filter), params, EstimatorInputs(y))
    return jnp.sum(out.log_likelihood)


def test_jit_vmap_over_plants_and_grad():
    """eager = jit; a vmap over three switching probabilities (three plants' params) equals a loop; check_grads
    of the log-likelihood with respect to the switching probability and the mode's noise scale."""
    np.testing.assert_allclose(jax.jit(_log_likelihood)(0.04, 1.0), _log_likelihood(0.04, 1.0), rtol=1e-13)
    switches = jnp.array([0.01, 0.04, 0.2])
    batched = jax.jit(jax.vmap(_log_likelihood, (0, None)))(switches, 1.0)
    np.testing.assert_allclose(batched, [_log_likelihood(s, 1.0) for s in switches], rtol=1e-12)
    check_grads(jax.jit(_log_likelihood), (0.04, 1.2), order=1, modes=("rev",))


def test_bad_inputs_raise_naming_the_argument():
    params = jaxobs_imm_params()
    y = EstimatorInputs(jnp.ones((3, 1)))
    with pytest.raises(ValueError, match="modes must hold at least two"):
        make_imm(params.modes[:1], [[1.0]])
    with pytest.raises(ValueError, match="transition: each row must sum to 1"):
        make_imm(params.modes, [[0.5, 0.4], [0.1, 0.9]])
    with pytest.raises(ValueError, match="transition must be finite and non-negative"):
        make_imm(params.modes, [[1.1, -0.1], [0.1, 0.9]])
    with pytest.raises(ValueError, match="mode_prior must have shape"):
        make_imm(params.modes, TRANSITION, [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="imm needs at least two Estimators"):
        make_imm_estimator(jo.kalman_filter)
    with pytest.raises(ValueError, match="params.modes holds 2 params for the 3 estimators"):
        run(jo.imm(jo.kalman_filter, jo.kalman_filter, jo.kalman_filter), params, y)
    with pytest.raises(ValueError, match=r"state.modes\[1\] \(LinearObserverState\) has no fields x and P"):
        run(
            jo.imm(jo.kalman_filter, jo.linear_observer),
            make_imm(
                [
                    params.modes[0],
                    jo.observers.LinearObserver(
                        params.modes[0].Phi, params.modes[0].Gamma, params.modes[0].C, jnp.zeros((3, 1))
                    ),
                ],
                TRANSITION,
            ),
            y,
        )
    small = jo.make_kalman(np.eye(2), np.ones((1, 2)), np.eye(2), R)
    with pytest.raises(ValueError, match="means and covariances of one size n"):
        run(jo.imm(jo.kalman_filter, jo.kalman_filter), make_imm([params.modes[0], small], TRANSITION), y)
    assert isinstance(jo.imm(jo.kalman_filter, jo.kalman_filter).init(params), IMMState)
