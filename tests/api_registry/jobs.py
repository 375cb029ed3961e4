"""Registry entries: jobs and their pure pieces (jaxobs.sweep, jaxobs.sweep_report, jaxobs.tuning), the function
transformations of jaxobs.batching and jaxobs.checked."""

import numpy as np

from tests.api_registry import Design, Example, slow

LOSSES = np.array([0.3, 1.2, 0.7, 2.5])

ENTRIES = {
    "jaxobs.sweep.config_key": Example(
        lambda: dict(seed=3, index=np.int32(5)),
        skip={"grad": "a PRNG key of an integer index", "batch": "index is any integer array (fold_in broadcasts)"},
    ),
    "jaxobs.tuning.parameters.cholesky_covariance": Example(
        lambda: dict(raw=np.array([[0.1, 0.0], [0.5, -0.3]])), batched=("raw",)
    ),
    "jaxobs.tuning.parameters.unit_interval": Example(lambda: dict(raw=np.array([-1.0, 0.5])), batched=("raw",)),
    "jaxobs.tuning.objectives.cvar": Example(
        lambda: dict(losses=LOSSES, alpha=0.5), skip={"batch": "losses is any array of losses (raveled)"}
    ),
    "jaxobs.tuning.objectives.robust_objective": Example(
        lambda: dict(losses=LOSSES, kind="cvar", alpha=0.5), skip={"batch": "losses is any array of losses (raveled)"}
    ),
    "jaxobs.tuning.objectives.penalise_diverged": Example(
        lambda: dict(losses=LOSSES, failed=np.array([False, True, False, False]), factor=2.0),
        diff="losses",
        skip={
            "batch": "losses (B,) is a batch of plants by definition; more axes broadcast",
            "grad": "documented: the penalty scale (the largest sound loss) is held constant in derivatives",
        },
    ),
    "jaxobs.tuning.problems.schedule_cost": Example(
        lambda: dict(
            gains=np.full((3, 2, 1), 0.3),
            Phi=np.array([[1.0, 0.1], [0.0, 0.9]]),
            C=np.array([[1.0, 0.0]]),
            Q=0.01 * np.eye(2),
            R=np.full((3, 1, 1), 0.1),
            P_init=np.eye(2),
        ),  # fmt: skip
        skip={"batch": "gains (T, n, p) is a schedule over its leading time axis"},
    ),
}

EXEMPT = {
    "jaxobs.tuning.objectives.make_objective": "transformation: the tuner's objective function of a loss function",
    "jaxobs.tuning.tuner.make_tuner": "transformation: the tuner's pure init and step functions",
    "jaxobs.tuning.problems.gain_schedule_problem": "loader: a TuningProblem (functions and plants) from sizes and a "
    "seed",
    "jaxobs.tuning.problems.speed_schedule_problem": "loader: a TuningProblem (functions and plants) from sizes and a "
    "seed",
    "jaxobs.tuning.problems.schedule_plant": "static: a seeded random plant of the given sizes (NumPy)",
    "jaxobs.batching.safe_vmap": "transformation: jax.vmap with LAPACK calls split (tested in tests/test_batching.py)",
    "jaxobs.batching.safe_lapack": "transformation: rewrites a function's LAPACK calls (tests/test_batching.py)",
    "jaxobs.batching.lapack_calls": "transformation: inspects the program of a function (tests/test_batching.py)",
    "jaxobs.checked": "transformation: the function with its value checks compiled in (tests/test_checks.py)",
    "jaxobs.sweep.run_sweep": "job: evaluates configurations in chunks into Parquet files with a manifest",
    "jaxobs.sweep.run_configured_sweep": "job: run_sweep with the settings of a configuration",
    "jaxobs.sweep.load_results": "loader: reads a finished sweep's Parquet chunks",
    "jaxobs.sweep.read_manifest": "loader: reads a sweep's manifest file",
    "jaxobs.sweep.run_history": "loader: reads a sweep's run records",
    "jaxobs.sweep_report.write_report": "job: writes a sweep's summary, report and figures",
    "jaxobs.sweep_report.finish_report": "job: writes a report's files",
    "jaxobs.sweep_report.summarize": "job: NumPy statistics of a finished sweep's rows (concrete results)",
    "jaxobs.sweep_report.quantiles": "job: NumPy quantiles of a finished sweep's column (concrete results)",
    "jaxobs.sweep_report.timing": "loader: reads what a sweep's runs measured",
    "jaxobs.tuning.job.tune": "job: an optimisation run (optax steps in a Python loop with restarts and a "
    "stopping rule)",
    "jaxobs.tuning.search.random_search": "job: a gradient-free search over candidates within a time budget",
    "jaxobs.tuning.search.evaluate": "job: compiles and scores parameters on a tuning problem's held-out plants",
    "jaxobs.tuning.search.evaluator": "job: compiles a tuning problem's held-out rollouts once for many designs",
    "jaxobs.tuning.parameters.log_labels": "static: strings naming log-variance parameters",
    "jaxobs.tuning.parameters.cholesky_labels": "static: strings naming a Cholesky parameterisation's entries",
    "jaxobs.tuning.search.batch_objective": "transformation: returns a compiled scorer of candidates",
    "jaxobs.tuning.objectives.value_and_grad": "transformation: the value and gradient function of an objective",
    "jaxobs.tuning.settings.lbfgs": "transformation: returns an optax gradient transformation",
    "jaxobs.tuning.settings.gradient_mode": "static: resolves a setting string from the size of the parameters",
    "jaxobs.tuning.settings.screening_size": "static: a count (Python int) from a setting and the parameters' count",
    "jaxobs.tuning.parameters.cholesky_parameters": "validator: the inverse of cholesky_covariance for a starting "
    "point, which refuses a concrete covariance that is not positive definite",
    "jaxobs.tuning.parameters.unit_interval_parameters": "validator: the inverse of unit_interval for a starting "
    "point, which refuses a concrete value outside (0, 1)",
}


def _cma():
    """A CMA-ES on 3 coordinates (the last fixed) near the middle of the cube, as cmaes.init builds it."""
    import jax

    from jaxobs.tuning import cmaes

    return jax.tree_util.tree_map(np.asarray, cmaes.init(np.array([0.5, 0.4, 0.6]), 0.1, np.array([True, True, False])))


RANKED = np.array([[0.52, 0.43, 0.6], [0.47, 0.41, 0.6], [0.55, 0.35, 0.6], [0.44, 0.46, 0.6]])
"""Four candidates of :func:`_cma`'s generation, best first (the fixed coordinate where it is)."""


def _tuner_state():
    """The state of a tuner of two starts polishing a 2-vector, its lanes' best evaluations set apart."""
    import jax

    from jaxobs.tuning import TuneSettings
    from jaxobs.tuning.tuner import make_tuner

    starts = [{"a": np.zeros(2)}, {"a": np.ones(2)}]
    state = make_tuner(TuneSettings(steps=2, starts=2)).init({"a": np.zeros(2)}, starts=starts)
    lanes = state.lanes._replace(best_objective=np.array([0.7, 0.4]), best_diverged=np.array([0, 0], np.int32))
    return jax.tree_util.tree_map(np.asarray, state._replace(lanes=lanes))


_INDEX = "an index: an integer output"


def _exploring_state():
    """The state of a tuner about to screen 15 candidates around a 2-vector."""
    from jaxobs.tuning import TuneSettings
    from jaxobs.tuning.tuner import make_tuner

    return make_tuner(TuneSettings(screening=15)).init({"a": np.zeros(2)})


TUNER = {
    "jaxobs.kalman_steps.joseph_covariance": Example(
        lambda: dict(
            P1=np.array([[1.0, 0.2], [0.2, 0.5]]),
            C=np.array([[1.0, 0.0]]),
            R=np.array([[0.1]]),
            K=np.array([[0.6], [0.1]]),
        ),
        diff="K",
    ),  # fmt: skip
    "jaxobs.tuning.box.search_box": Example(
        lambda: dict(theta0={"q": np.array([0.1, 0.2]), "r": np.float64(0.3)}, box=None, spread=0.5),
        skip={"batch": "theta0's entries are parameter arrays of any shapes"},
    ),
    "jaxobs.tuning.cmaes.init": Example(
        lambda: dict(mean=np.array([0.5, 0.4, 0.6]), sigma=np.float64(0.1), free=np.array([True, True, False]))
    ),
    "jaxobs.tuning.cmaes.ask": Example(lambda: dict(state=_cma(), key=jax_key(3), population=4)),
    "jaxobs.tuning.cmaes.tell": Example(lambda: dict(state=_cma(), ranked=RANKED), diff="ranked"),
    "jaxobs.tuning.problems.optimal_schedule": Example(
        lambda: dict(
            Phi=np.array([[1.0, 0.1], [0.0, 0.9]]),
            C=np.array([[1.0, 0.0]]),
            Q=0.01 * np.eye(2),
            R=np.full((3, 1, 1), 0.1),
            P_init=np.eye(2),
        ),
        diff="R",
    ),  # fmt: skip
    "jaxobs.tuning.problems.lateral_model": Design(lambda: dict(speed=np.array([10.0, 25.0]), h=0.05)),
    "jaxobs.tuning.tuner.best_start": Example(lambda: dict(state=_tuner_state()), skip={"grad": _INDEX}),
    "jaxobs.tuning.tuner.explore_until": Example(
        lambda: dict(state=_exploring_state(), scored=np.int32(16)),
        diff="scored",
        skip={"grad": "sets an integer count of the state; its other leaves pass through unchanged"},
    ),  # fmt: skip
}


def jax_key(seed: int):
    import jax

    return jax.random.key(seed)


ENTRIES = slow(
    {**ENTRIES, **TUNER},
    "an eigendecomposition or a Riccati scan differentiated (the CMA-ES update, the optimal schedule)",
    "jaxobs.tuning.cmaes.ask",
    "jaxobs.tuning.cmaes.tell",
    "jaxobs.tuning.problems.optimal_schedule",
)
