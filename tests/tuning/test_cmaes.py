"""jaxobs.tuning.cmaes: the CMA-ES minimises an ill-conditioned rotated ellipsoid (full covariance) and a sphere of
150 coordinates (separable), keeps to the unit cube and leaves fixed coordinates alone; pure under jit and vmap."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs.tuning import cmaes


def _minimise(f, mean, sigma, free, generations, population, key):
    def generation(state, key):
        candidates = cmaes.ask(state, key, population)
        ranked = candidates[jnp.argsort(jax.vmap(f)(candidates))]
        return cmaes.tell(state, ranked), jnp.min(jax.vmap(f)(candidates))

    state = cmaes.init(mean, sigma, free)
    return jax.lax.scan(generation, state, jax.random.split(key, generations))


def test_full_covariance_learns_a_rotated_ellipsoid():
    d = 6
    rotation = np.linalg.qr(np.random.default_rng(0).normal(size=(d, d)))[0]
    scales = jnp.asarray(np.logspace(0, 3, d))  # condition number 1e6 of the Hessian
    target = jnp.full(d, 0.6)

    def f(x):
        return jnp.sum((scales * (rotation @ (x - target))) ** 2)

    run = jax.jit(lambda key: _minimise(f, jnp.full(d, 0.2), 0.2, jnp.ones(d, bool), 400, 12, key))
    state, best = run(jax.random.PRNGKey(0))
    assert float(best[-1]) < 1e-10 and state.cov.shape == (d, d)
    np.testing.assert_allclose(state.mean, target, atol=1e-6)
    many = jax.vmap(run)(jax.random.split(jax.random.PRNGKey(0), 2))[0].mean  # vmap over keys = one run each
    np.testing.assert_allclose(many[1], run(jax.random.split(jax.random.PRNGKey(0), 2)[1])[0].mean, rtol=1e-10)


def test_separable_variant_keeps_to_the_cube_and_the_fixed_coordinates():
    d = cmaes.FULL_MAX + 50
    free = jnp.arange(d) % 10 != 0  # every tenth coordinate fixed
    target = jnp.where(free, 0.97, 0.5)  # near the upper face

    def f(x):
        return jnp.sum((x - target) ** 2)

    state, best = jax.jit(lambda key: _minimise(f, jnp.full(d, 0.5), 0.3, free, 600, 16, key))(jax.random.PRNGKey(1))
    assert state.cov.shape == (d,)
    assert float(best[-1]) < 1e-6 * float(best[0])
    np.testing.assert_array_equal(state.mean[~free], 0.5)
    candidates = cmaes.ask(state._replace(sigma=jnp.asarray(5.0)), jax.random.PRNGKey(2), 32)
    assert float(candidates.min()) >= 0.0 and float(candidates.max()) <= 1.0
