"""jaxobs.tuning.problems: the gain schedule's exact cost, its Riccati optimum (first-order conditions, lower than
every perturbation), transformations and shape checks, and the tuner reaching the optimum."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxobs.tuning import TuneSettings, lbfgs, tune
from jaxobs.tuning.problems import gain_schedule_problem, optimal_schedule, schedule_cost, schedule_plant


@pytest.fixture(scope="module")
def plant():
    return {k: jnp.asarray(v) for k, v in schedule_plant(12, states=4, outputs=2, seed=1).items()}


def test_the_riccati_gains_are_the_optimum(plant):
    best = optimal_schedule(**plant)
    cost = jax.jit(schedule_cost)
    np.testing.assert_allclose(cost(best.gains, **plant), best.cost, rtol=1e-13)
    gradient = jax.grad(schedule_cost)(best.gains, **plant)
    assert float(jnp.max(jnp.abs(gradient))) < 1e-12  # a stationary point of J
    rng = np.random.default_rng(0)
    for scale in (1e-3, 1e-1):
        assert float(cost(best.gains + scale * rng.normal(size=best.gains.shape), **plant)) > float(best.cost)
    batch = jnp.stack([best.gains, 0.5 * best.gains])
    np.testing.assert_allclose(jax.vmap(lambda g: schedule_cost(g, **plant))(batch),
                               [cost(g, **plant) for g in batch], rtol=1e-13)  # fmt: skip
    check_grads(lambda g: schedule_cost(g, **plant), (0.7 * best.gains,), order=1, modes=["rev"])


def test_shapes_are_checked(plant):
    with pytest.raises(ValueError, match=r"gains must have shape \(12, 4, 2\)"):
        schedule_cost(jnp.zeros((11, 4, 2)), **plant)
    with pytest.raises(ValueError, match=r"R must have shape \(T, 2, 2\)"):
        optimal_schedule(**{**plant, "R": plant["R"][0]})
    with pytest.raises(ValueError, match="states must be even"):
        schedule_plant(10, states=3)


def test_the_tuner_reaches_the_optimal_schedule():
    """d = 13 x 4 x 2 = 104 gains from the steady-state design (46 % above J*): L-BFGS ends within 1e-6 of J*; the
    box holds the optimum."""
    problem, best = gain_schedule_problem(13)
    assert problem.describe(problem.theta0)["suboptimality"] > 0.4
    low, high = problem.search_box["gains"]
    assert bool(jnp.all((low < best.gains) & (best.gains < high)))
    result = tune(problem, TuneSettings(lbfgs(), backtrack=True, steps=100, patience=10, min_improvement=1e-7),
                  progress=False)  # fmt: skip
    assert result.converged and problem.describe(result.theta)["suboptimality"] < 1e-6
