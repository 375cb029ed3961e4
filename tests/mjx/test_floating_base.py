"""The EKF and the UKF on a floating base with an IMU (the shipped free flyer, examples/floating_base_estimation.py):
consistent over Monte-Carlo runs, better than dead reckoning, and pure (jit, vmap over mismatched models, grad)."""

import dataclasses
import importlib.util

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxobs as jo
from jaxobs.mjx import estimation
from jaxobs.mjx.robot import mismatch
from tests import ROOT


def _example():
    spec = importlib.util.spec_from_file_location("floating_base_estimation",
                                                  ROOT / "examples" / "floating_base_estimation.py")  # fmt: skip
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    return example


@pytest.mark.slow  # MJX compiles of both filters over the 16-direction tangent space: minutes
def test_filters_are_consistent_and_beat_dead_reckoning():
    """20 runs of 2 s (100 samples): each filter's NEES averaged over runs and samples lies in the band of the
    per-sample average (the chi-square band of 20 x 16 degrees of freedom, averaged over the samples), at least 80 %
    of the samples' averages lie in their band (95 % expected; correlated samples scatter), and the IMU's position
    and orientation errors are under a fifth of dead reckoning's (the IMU integrated alone from the prior mean)."""
    results = _example().monte_carlo(runs=20, seconds=2.0)
    dead = results["dead reckoning"]["rms"]
    for name in ("EKF", "UKF"):
        r = results[name]
        assert r["band"][0] <= r["nees"] <= r["band"][1], (name, r)
        assert r["fraction_inside"] >= 0.8, (name, r)
        assert r["rms"][0] < 0.2 * dead[0] and r["rms"][1] < 0.2 * dead[1], (name, r, dead)


@pytest.mark.slow
def test_jit_vmap_over_mismatched_models_and_grad():
    """A batch of free flyers with other forearm masses runs through one jitted EKF (vmap = loop), and the record's
    log-likelihood is differentiable in that mass (reverse mode = central differences)."""
    example = _example()
    mj_model, model, x0, P0, Q = example.setup()
    nominal = estimation.filter_model(mj_model, Q, x0=x0, P0=P0, sensors=example.SENSORS, substeps=example.SUBSTEPS)
    x_true, y, u_prev = example.simulate(model, x0, P0, Q, nominal.R, 15, jax.random.key(3))
    inputs = jo.EstimatorInputs(y=y, u_prev=u_prev)

    def heavier(factor):
        plant = mismatch(model, {"body_mass[forearm]": factor})
        return dataclasses.replace(nominal, f=jax.tree_util.Partial(nominal.f.func, plant),
                                   h=jax.tree_util.Partial(nominal.h.func, plant))  # fmt: skip

    def ll(factor):
        return jo.log_likelihood(jo.extended_kalman_filter, jo.make_ekf(heavier(factor)), inputs)

    factors = jnp.array([1.0 - 1e-5, 1.0 + 1e-5, 2.0])
    batched = jax.jit(jax.vmap(ll))(factors)
    one = jax.jit(ll)  # one program for the loop (an eager call retraces the filter's scan for each factor)
    np.testing.assert_allclose(batched, [one(f) for f in factors], rtol=1e-10)
    grad = jax.jit(jax.grad(ll))(1.0)
    np.testing.assert_allclose(grad, (batched[1] - batched[0]) / 2e-5, rtol=1e-4)
    assert float(batched[2]) < float(one(1.0))  # the true forearm explains the record better than a doubled one
