"""Tests for jaxobs.ct: fourth-order convergence of RK4 (first order of Euler) against the exact zero-order-hold map
of jaxobs.lti.c2d on a linear system and against diffrax on a nonlinear one, pytree states and time-dependent
models, checkpointed gradients, jit/vmap/grad and bad inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxobs import ct
from jaxobs.lti import c2d, ss

A = jnp.array([[0.0, 1.0], [-4.0, -0.4]])
B = jnp.array([[0.0], [1.0]])


def linear(x, u, t):
    return A @ x + B @ u


def van_der_pol(x, u, t, mu=1.5):
    """A forced Van der Pol oscillator: nonlinear, with input and explicit time dependence."""
    return jnp.array([x[1], mu * (1 - x[0] ** 2) * x[1] - x[0] + u[0] + 0.3 * jnp.sin(2 * t)])


def test_rk4_is_fourth_order_and_euler_first_order_against_the_exact_zoh_map():
    """One 0.1 s sample of x' = A x + B u (u held) against c2d's exact ZOH map: halving the substep divides the
    RK4 error by 16 (measured 17.0, 16.6, 16.3 from 1 to 8 substeps; 9e-10 at 8) and the Euler error by 2."""
    h, x0, u = 0.1, jnp.array([1.0, 0.0]), jnp.array([0.3])
    plant = c2d(ss(A, B, jnp.eye(2)), h)
    exact = plant.A @ x0 + plant.B @ u
    for method, order, smallest in (("rk4", 4, 1e-9), ("euler", 1, 3e-3)):
        err = [float(jnp.max(jnp.abs(ct.integrate(linear, x0, u, 0.0, h, substeps=s, method=method) - exact)))
               for s in (1, 2, 4, 8)]  # fmt: skip
        ratios = np.array(err[:-1]) / np.array(err[1:])
        np.testing.assert_allclose(ratios, 2.0**order, rtol=0.1, err_msg=method)
        assert err[-1] < smallest, method


def test_rk4_against_diffrax_on_a_nonlinear_system():
    """A 2 s trajectory of the forced Van der Pol oscillator with held random inputs, sample by sample, against
    diffrax's Dopri8 at rtol = atol = 1e-13 over each sample: fourth order (error ratio 16.2 from 8 to 16
    substeps, measured) and 6e-10 at 16 substeps of 6.25 ms."""
    diffrax = pytest.importorskip("diffrax")
    T, h = 20, 0.1
    u = jnp.asarray(np.random.default_rng(0).normal(size=(T, 1)))
    x0 = jnp.array([1.0, 0.5])
    term = diffrax.ODETerm(lambda t, x, u: van_der_pol(x, u, t))
    controller = diffrax.PIDController(rtol=1e-13, atol=1e-13)

    def sample(x, inputs):
        u_k, t_k = inputs
        sol = diffrax.diffeqsolve(term, diffrax.Dopri8(), t_k, t_k + h, h / 4, x, args=u_k,
                                  stepsize_controller=controller, max_steps=4096)  # fmt: skip
        return sol.ys[-1], sol.ys[-1]

    _, xs = jax.lax.scan(sample, x0, (u, h * jnp.arange(T, dtype=float)))
    reference = jnp.concatenate([x0[None], xs])
    err = [float(jnp.max(jnp.abs(ct.trajectory(van_der_pol, x0, u, h=h, substeps=s) - reference))) for s in (8, 16)]
    assert err[1] < 1e-9
    assert 14 < err[0] / err[1] < 18.5


def test_pytree_states_and_time_dependence():
    """A state given as a tuple integrates like the concatenated array; a time-dependent model sees t."""
    x0, u = jnp.array([1.0, 0.0]), jnp.array([0.3])
    split = lambda x, u, t: (linear(jnp.concatenate(x), u, t)[:1], linear(jnp.concatenate(x), u, t)[1:])
    as_tuple = ct.integrate(split, (x0[:1], x0[1:]), u, 0.0, 0.1, substeps=3)
    np.testing.assert_allclose(jnp.concatenate(as_tuple), ct.integrate(linear, x0, u, 0.0, 0.1, substeps=3), rtol=1e-14)
    # x' = cos t from t = 1: x(1.5) - x(1) = sin 1.5 - sin 1 (RK4 is Simpson's rule here: error 2e-10 at 10 steps)
    x = ct.integrate(lambda x, u, t: jnp.cos(t)[None], jnp.zeros(1), None, 1.0, 0.5, substeps=10)
    np.testing.assert_allclose(x[0], np.sin(1.5) - np.sin(1.0), atol=1e-9)


def test_trajectory_starts_at_x0_and_follows_the_samples():
    u = jnp.asarray(np.random.default_rng(1).normal(size=(5, 1)))
    x0 = jnp.array([1.0, 0.0])
    tr = ct.trajectory(linear, x0, u, h=0.1, substeps=2, t0=0.3)
    assert tr.shape == (6, 2)
    np.testing.assert_array_equal(tr[0], x0)
    np.testing.assert_allclose(tr[3], ct.integrate(linear, tr[2], u[2], 0.5, 0.1, substeps=2), rtol=1e-14)


def test_checkpoint_gives_the_same_values_and_gradients():
    """checkpoint=True recomputes the substeps in reverse mode: same trajectory, same gradient; check_grads
    (forward and reverse) of a trajectory loss with respect to x0, a model parameter and the sample period."""
    u = jnp.asarray(np.random.default_rng(2).normal(size=(10, 1)))

    def loss(x0, mu, h, checkpoint):
        f = lambda x, u, t: van_der_pol(x, u, t, mu)
        return jnp.sum(ct.trajectory(f, x0, u, h=h, substeps=3, checkpoint=checkpoint) ** 2)

    args = (jnp.array([1.0, 0.5]), 1.5, 0.1)
    plain = jax.jit(lambda *a: loss(*a, checkpoint=False))
    saved = jax.jit(lambda *a: loss(*a, checkpoint=True))
    np.testing.assert_allclose(saved(*args), plain(*args), rtol=1e-14)
    g_plain, g_saved = (jax.grad(fn, argnums=(0, 1, 2))(*args) for fn in (plain, saved))
    for a, b in zip(g_plain, g_saved, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12)
    # the loss is strongly curved in h (d/dh = -15.14): check_grads' default step 1e-4 has a central-difference
    # error of 4e-5 relative; a step of 1e-6 brings it to rounding level
    check_grads(saved, args, order=1, modes=("fwd", "rev"), eps=1e-6)


def test_jit_and_vmap_agree_with_eager():
    x0s = jnp.asarray(np.random.default_rng(3).normal(size=(4, 2)))
    u = jnp.array([0.2])
    step = ct.discretize(van_der_pol, 0.1, substeps=4)
    batched = jax.vmap(lambda x: step(x, u, 0.0))(x0s)
    jitted = jax.jit(step)
    for b in range(4):
        eager = step(x0s[b], u, 0.0)
        np.testing.assert_allclose(batched[b], eager, rtol=1e-13)
        np.testing.assert_allclose(jitted(x0s[b], u, 0.0), eager, rtol=1e-13)


def test_bad_inputs_raise_naming_the_argument():
    x0, u = jnp.array([1.0, 0.0]), jnp.array([0.3])
    with pytest.raises(ValueError, match="substeps must be an integer >= 1"):
        ct.integrate(linear, x0, u, 0.0, 0.1, substeps=0)
    with pytest.raises(ValueError, match="substeps must be an integer"):
        ct.discretize(linear, 0.1, substeps=2.0)
    with pytest.raises(ValueError, match="method must be one of"):
        ct.integrate(linear, x0, u, 0.0, 0.1, method="rk45")
    with pytest.raises(ValueError, match=r"f\(x, u, t\) must return dx/dt with the structure, shapes and dtypes"):
        ct.integrate(lambda x, u, t: x[:1], x0, u, 0.0, 0.1)
    with pytest.raises(ValueError, match=r"t must have shape \(\)"):
        ct.integrate(linear, x0, u, jnp.zeros(2), 0.1)
    with pytest.raises(ValueError, match="u must have one leading time axis"):
        ct.trajectory(linear, x0, jnp.array(0.3), h=0.1)
    with pytest.raises(ValueError, match="substeps must be a concrete integer"):
        jax.jit(lambda s: ct.integrate(linear, x0, u, 0.0, 0.1, substeps=s))(2)
