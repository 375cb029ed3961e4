"""Tests for jaxobs.observers.continuous: a continuous-time Luenberger observer run as a sampled estimator equals
the exact zero-order-hold discretisation of the observer (input and measurement held), a missing channel
switches off its output injection, jit/vmap/grad and bad inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxobs.lti import c2d, ss
from jaxobs.observers import EstimatorInputs, run
from jaxobs.observers.continuous import continuous_observer, make_continuous_observer

A = jnp.array([[0.0, 1.0], [-2.0, -0.3]])
B = jnp.array([[0.0], [1.0]])
C = jnp.array([[1.0, 0.0], [0.0, 1.0]])
L = jnp.array([[3.0, 0.5], [1.0, 2.0]])
H = 0.05


def luenberger(L, x, u, y, t):
    return A @ x + B @ u + L @ (y - C @ x)


def observer(L=L, substeps=20):
    return make_continuous_observer(jax.tree_util.Partial(luenberger, L), lambda x, u: C @ x, x0=jnp.array([0.5, -0.2]),
                                    dt=H, n_inputs=1, substeps=substeps)  # fmt: skip


def data(T=40, seed=0):
    rng = np.random.default_rng(seed)
    return EstimatorInputs(jnp.asarray(rng.normal(size=(T, 2))), jnp.asarray(rng.normal(size=(T, 1))))


def test_equals_the_exact_discretisation_of_the_observer():
    """x_hat' = (A - L C) x_hat + B u + L y with u_{k-1}, y_{k-1} held over [t_{k-1}, t_k] is, sampled, the
    c2d model of (A - L C, [B L]); the first step outputs x0. RK4 with 20 substeps agrees to 1e-10 absolute on
    states of size ~0.6 (its truncation error here is 4e-11, and 6e-10 with 10 substeps: the 4th order)."""
    inputs = data()
    _, out = run(continuous_observer, observer(), inputs)
    sampled = c2d(ss(A - L @ C, jnp.hstack([B, L]), jnp.eye(2)), H)
    x, expected = jnp.array([0.5, -0.2]), []
    for k in range(inputs.y.shape[0]):
        if k:
            x = sampled.A @ x + sampled.B @ jnp.concatenate([inputs.u_prev[k], inputs.y[k - 1]])
        expected.append(x)
    np.testing.assert_allclose(out.x, jnp.stack(expected), rtol=0, atol=1e-10)
    np.testing.assert_allclose(out.innovation, inputs.y - out.x @ C.T, rtol=1e-12, atol=1e-12)


def test_a_missing_channel_switches_off_its_output_injection():
    """A measurement channel that is NaN is replaced by the observer's prediction: the observer equals the one
    whose gain has that channel's column zeroed, its innovation is zero and the samples are counted."""
    inputs = data(T=20)
    y = inputs.y.at[:, 1].set(jnp.nan)
    state, out = run(continuous_observer, observer(), inputs._replace(y=y))
    _, ref = run(continuous_observer, observer(L=L.at[:, 1].set(0.0)), inputs._replace(y=y.at[:, 1].set(0.0)))
    np.testing.assert_allclose(out.x, ref.x, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(out.innovation[:, 1], 0.0)
    assert int(state.missing) == 20


def test_jit_vmap_and_gradients_with_respect_to_the_gain():
    inputs = data(T=15)
    estimates = jax.jit(lambda L, y: run(continuous_observer, observer(L, substeps=4), inputs._replace(y=y))[1].x)
    ys = jnp.stack([inputs.y, 2 * inputs.y])
    batched = jax.vmap(estimates, in_axes=(None, 0))(L, ys)
    for b in range(2):
        np.testing.assert_allclose(batched[b], estimates(L, ys[b]), rtol=1e-13)
    check_grads(lambda L: jnp.sum(estimates(L, inputs.y) ** 2), (L,), order=1, modes=("fwd", "rev"))


def test_bad_inputs_raise_naming_the_argument():
    with pytest.raises(ValueError, match=r"F\(x_hat, u, y, t\) must return dx_hat/dt"):
        make_continuous_observer(lambda x, u, y, t: x[:1], lambda x, u: x, x0=jnp.zeros(2), dt=0.1)
    with pytest.raises(ValueError, match=r"h\(x_hat, u\) must return the output estimate"):
        make_continuous_observer(lambda x, u, y, t: x, lambda x, u: jnp.sum(x), x0=jnp.zeros(2), dt=0.1)
    with pytest.raises(ValueError, match="dt must be a finite positive number"):
        make_continuous_observer(lambda x, u, y, t: x, lambda x, u: x, x0=jnp.zeros(2), dt=-1.0)
    params = observer()
    state = continuous_observer.init(params)
    with pytest.raises(ValueError, match=r"inputs.y must have shape \(2,\)"):
        continuous_observer.step(params, state, EstimatorInputs(jnp.zeros(3), jnp.zeros(1)))
    with pytest.raises(ValueError, match="inputs.u_prev is required"):
        continuous_observer.step(params, state, EstimatorInputs(jnp.zeros(2)))
