"""The config tables every ``jaxobs tune`` problem shares: ``[optimizer]`` (:class:`jaxobs.tuning.TuneSettings`,
its optax optimiser named by a string), ``[baseline]`` (the random search and its box) and the seed, with their
checks; plus the run's tag.

The search box is ``theta0 +- baseline.spread`` per unconstrained coordinate, fixed by each problem before any
tuning result is known: the random search draws from it and the tuner's screening seeds its starts from it (the
gradient steps may leave it)."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import jax.numpy as jnp
import optax

from jaxobs._config import check_at_least, check_memory, fail
from jaxobs.tuning import TuneSettings, lbfgs

__all__ = [
    "OPTIMIZERS",
    "optimizer_defaults",
    "optimizer",
    "BASELINE_DEFAULTS",
    "SHIPPED_STRATEGY",
    "COMMON_NOTES",
    "check_common",
    "check_plant_memory",
    "settings",
    "config_tag",
    "search_box",
]

BASELINE_DEFAULTS = {"random_search": True, "equal_time": True, "spread": 2.0}

SHIPPED_STRATEGY = {"optimizer": "lbfgs", "learning_rate": 1.0, "screening": 127, "evolve": 50, "distinct": 0.1,
                    "starts": 2, "steps": 100, "patience": 4, "max_rejections": 16}  # fmt: skip
"""The ``[optimizer]`` defaults of the shipped problems: 127 scrambled-Sobol candidates screened in the search box,
a CMA-ES from the best of them until it stalls (at most 50 generations of 16), then L-BFGS with backtracking (16
halvings at most) from two starts at once, ``theta0`` and the best point found, until the plateau rule stops each
(measured against random search, CMA-ES, OpenAI-ES and Optuna at equal wall time: docs/tuning-results.md)."""

OPTIMIZERS = {"adam": optax.adam, "sgd": optax.sgd, "adabelief": optax.adabelief, "lamb": optax.lamb,
              "lbfgs": lbfgs}  # fmt: skip
"""The optax optimisers ``[optimizer] optimizer`` may name, by their step size. L-BFGS is
:func:`jaxobs.tuning.lbfgs`, without a line search of its own: the tuner backtracks on its compiled evaluation
instead (``TuneSettings.backtrack``, set for it)."""

_OPTIMIZER_KEYS = {"optimizer": "adam", "learning_rate": 0.1, "clip_norm": 1.0}  # the optimiser, by name
_ELSEWHERE = ("optimizer", "spread", "seed")  # TuneSettings fields set from other keys: baseline.spread, seed
_JOB_KEYS = {"seconds": 0.0}  # the run's, not the tuner's: jaxobs.tuning.tune's wall-time budget

COMMON_NOTES = {
    "seed": "seed of the sampled plants (training and held-out sets), the screening and the random search",
    "optimizer": "the gradient tuner (jaxobs.tuning.TuneSettings)",
    "optimizer.optimizer": "optax optimizer: 'adam', 'sgd', 'adabelief', 'lamb' or 'lbfgs' (backtracking on)",
    "optimizer.gradient": "'auto' (forward up to jaxobs.tuning.FORWARD_MAX_PARAMETERS parameters), 'reverse' "
    "(value_and_grad) or 'forward' (jacfwd: exact, cheaper for few parameters)",
    "optimizer.starts": "starting points tuned together (one vmap); the result is the best on the training objective",
    "optimizer.screening": "candidates scored in the search box before tuning; the best seed the starts (with theta0)",
    "optimizer.evolve": "CMA-ES generations per round at most after the screening (0: none); its best is a start",
    "optimizer.population": "candidates per batched call of the exploration (a screening chunk, a CMA-ES generation)",
    "optimizer.evolve_sigma": "the CMA-ES's initial step, as a fraction of the search box's width",
    "optimizer.rounds": "explore-and-polish rounds: each later one restarts the CMA-ES at a random point of the box",
    "optimizer.distinct": "starts at least this far apart (largest coordinate difference, in box widths); 0: any",
    "optimizer.bounded": "keep every design in the search box, as the baseline's search does",
    "optimizer.learning_rate": "the optimizer's step size (in the unconstrained parameters)",
    "optimizer.steps": "the cap: gradient evaluations per start at most, rejected ones included",
    "optimizer.seconds": "wall-time budget of the tuning (compilation and a resumed checkpoint's earlier runs "
    "included), ending it after the step that passes it; 0: none",
    "optimizer.objective": "'mean' or 'cvar' (mean of the cvar_alpha worst) of the per-plant training losses",
    "optimizer.cvar_alpha": "fraction of worst training plants the CVaR objective averages",
    "optimizer.penalty_weight": "weight of the problem's penalty term; 0 switches it off",
    "optimizer.divergence_factor": "a diverged plant's loss is this times the largest finite loss (at least 1)",
    "optimizer.clip_norm": "global-norm gradient clipping; 0 switches it off (and for lbfgs)",
    "optimizer.patience": "converged after this many evaluations without a relative improvement of min_improvement",
    "optimizer.min_improvement": "relative improvement of the objective that resets patience",
    "optimizer.max_rejections": "consecutive rejected (more plants diverging) steps before giving up",
    "optimizer.backtrack": "reject and halve a step that does not improve the objective (always on for lbfgs)",
    "optimizer.checkpoint_every": "evaluations between checkpoints (checkpoint.npz; rerun to resume)",
    "baseline": "the search box and the random-search baseline, scored like the tuner",
    "baseline.random_search": "run the random-search baseline (the tuning's rollouts, and its time: equal_time)",
    "baseline.equal_time": "go on to the tuning's wall time (a machine-dependent result); false: equal rollouts only",
    "baseline.spread": "the search box theta0 +- spread per unconstrained coordinate (random search and screening)",
}
"""Notes of the keys every problem shares, for ``jaxobs tune --print-config``."""


def optimizer_defaults(**overrides) -> dict:
    """The ``[optimizer]`` table: the optimiser by name (``optimizer``, ``learning_rate``, ``clip_norm``) and the
    other fields of :class:`jaxobs.tuning.TuneSettings`, with a problem's ``overrides``."""
    settings = TuneSettings()
    fields = {f.name: getattr(settings, f.name) for f in dataclasses.fields(settings) if f.name not in _ELSEWHERE}
    table = {**_OPTIMIZER_KEYS, **fields, **_JOB_KEYS}
    unknown = set(overrides) - set(table)
    if unknown:
        raise KeyError(f"not TuneSettings fields: {sorted(unknown)}")
    return {**table, **overrides}


def check_common(config: dict, source: str) -> None:
    """Check ``seed``, ``[optimizer]`` and ``[baseline]``; a :class:`jaxobs._config.ConfigError` names the key."""
    check_at_least(config, source, "seed", 0)
    check_at_least(config, source, "baseline.spread", 0, strict=True)
    check_at_least(config, source, "optimizer.seconds", 0)
    try:
        settings(config).validate()
    except ValueError as exc:
        fail(source, "optimizer", str(exc))


def optimizer(table: dict) -> optax.GradientTransformation:
    """The optax optimiser an ``[optimizer]`` table names: ``OPTIMIZERS[optimizer](learning_rate)``, after
    global-norm gradient clipping when ``clip_norm > 0`` (never for L-BFGS, whose line search needs the gradient)."""
    name, rate, clip = (table[k] for k in _OPTIMIZER_KEYS)
    if name not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {', '.join(OPTIMIZERS)}, got {name!r}")
    if not rate > 0:
        raise ValueError(f"learning_rate must be > 0, got {rate!r}")
    if not clip >= 0:
        raise ValueError(f"clip_norm must be >= 0, got {clip!r}")
    base = OPTIMIZERS[name](rate)
    return optax.chain(optax.clip_by_global_norm(clip), base) if clip > 0 and name != "lbfgs" else base


def settings(config: dict) -> TuneSettings:
    """The tuner's settings of a tuning configuration (its ``[optimizer]`` table, ``baseline.spread``, ``seed``)."""
    table = config["optimizer"]
    rest = {k: v for k, v in table.items() if k not in _OPTIMIZER_KEYS and k not in _JOB_KEYS}
    rest["backtrack"] = rest["backtrack"] or table["optimizer"] == "lbfgs"
    return TuneSettings(optimizer=optimizer(table), spread=config["baseline"]["spread"], seed=config["seed"], **rest)


def config_tag(config: dict) -> str:
    """A short hash of everything but the optimiser's step budget (a resumed run must match it; the optimiser's
    name and step size are here, since a checkpoint cannot see them)."""
    kept = {k: v for k, v in config.items() if k != "optimizer"}
    kept["optimizer"] = {k: v for k, v in config.get("optimizer", {}).items() if k in _OPTIMIZER_KEYS}
    text = json.dumps(kept, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def check_plant_memory(config: dict, source: str, steps: int, channels: int) -> None:
    """The sampled plants' noise, ``(train + heldout) x steps x channels`` float64 values, must fit in memory."""
    count = config["plants"]["train"] + config["plants"]["heldout"]
    check_memory(source, "plants", 8 * count * steps * channels, f"the sensor noise of {count} plants over {steps} "
                 "steps", hint="lower plants.train, plants.heldout or scenario.duration")  # fmt: skip


COUPLING_HALF_WIDTH = 1.0
"""Half-width of the search box of a Cholesky factor's couplings (:func:`jaxobs.tuning.cholesky_covariance`'s
strict lower triangle, dimensionless): correlations up to about 0.7 between neighbouring states."""


def search_box(config: dict, theta0: dict, cholesky: tuple = ()) -> dict:
    """``{name: (low, high)}``: ``theta0 +- baseline.spread``, except for the Cholesky factors named in
    ``cholesky``: their log scales (diagonal) ``+- spread``, their couplings (strict lower triangle)
    ``+- COUPLING_HALF_WIDTH``, their unused strict upper triangle fixed."""
    spread, box = config["baseline"]["spread"], {}
    for name, value in theta0.items():
        value = jnp.asarray(value)
        width = spread * jnp.ones_like(value)
        if name in cholesky:
            n = value.shape[-1]
            width = spread * jnp.eye(n) + COUPLING_HALF_WIDTH * jnp.tril(jnp.ones((n, n)), -1)
            width = jnp.broadcast_to(width, value.shape)
        box[name] = (value - width, value + width)
    return box
