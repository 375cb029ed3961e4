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


def test_the_speed_schedule_is_bounded_by_each_profiles_riccati_gains():
    """The lateral model's accelerometer row against its dynamics (``a_y = dv_y / dt + v r``); interpolation
    weights that sum to one (one knot: a fixed gain); every plant's loss of the fixed-gain design above 1 (its
    Riccati bound), and that bound reached by the Riccati gains themselves."""
    from jaxobs.tuning import problems

    Phi, C = problems.lateral_model(np.array([10.0, 30.0]), h=1e-6)  # a_y = dv_y / dt + v r: C's row is A's
    assert Phi.shape == (2, 4, 4) and C.shape == (2, 2, 4)
    np.testing.assert_allclose(Phi[:, 2:, 2:], np.broadcast_to(np.eye(2), (2, 2, 2)))  # the biases are random walks
    speeds, h = np.array([10.0, 30.0]), 1e-6
    A_first_row = (Phi[:, 0, :2] - np.array([1.0, 0.0])) / h  # Phi = I + A h + O(h^2)
    np.testing.assert_allclose(A_first_row, np.stack([C[:, 1, 0], C[:, 1, 1] - speeds], -1), rtol=1e-4)  # a_y
    weights = problems._hat_weights(np.array([5.0, 7.5, 40.0, 22.0]), np.linspace(5.0, 40.0, 8))
    np.testing.assert_allclose(weights.sum(-1), 1.0)
    assert problems._hat_weights(np.array([12.0]), np.array([20.0])).tolist() == [[1.0]]
    problem, bounds = problems.speed_schedule_problem(knots=4, train=2, heldout=3, steps=60)
    assert problem.theta0["gains"].shape == (4, 4, 2) and bounds["heldout"].shape == (3,)
    losses = jax.jit(problem.losses)(problem.theta0, problem.heldout)[0]
    assert bool(jnp.all(losses > 1.0)) and problem.describe(problem.theta0)["excess"] > 0
    plant = jax.tree.map(lambda x: x[0], problem.train)
    model = {k: plant[k] for k in ("Phi", "C", "Q", "R", "P_init")}
    np.testing.assert_allclose(schedule_cost(optimal_schedule(**model).gains, **model) / plant["optimum"], 1.0,
                               rtol=1e-12)  # fmt: skip


def test_values_below_the_optimum_count_as_diverged():
    """A cost below the Riccati optimum is the roundoff of a covariance that blew up (an unstable schedule's
    recursion can end negative): the losses flag it like a non-finite one, and the optimum itself is valid."""
    from jaxobs.tuning import problems

    problem, best = gain_schedule_problem(13)
    J = float(best.cost)
    flagged = problems._invalid(jnp.array([J, 2 * J, J * (1 - 1e-3), -1e80, jnp.inf, jnp.nan]), J)
    assert flagged.tolist() == [False, False, True, True, True, True]
    assert not bool(problem.losses({"gains": best.gains}, problem.train)[1][0])
    assert not bool(problem.losses(problem.theta0, problem.train)[1][0])
