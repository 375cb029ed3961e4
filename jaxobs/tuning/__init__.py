"""Gradient-based tuning of observer designs with optax: parameterisations, robust objectives, the tuner and its job.

A :class:`TuningProblem` is unconstrained parameters ``theta``, a function giving one loss per plant of a batch of
mismatched plants, and a training and a held-out batch. The tuner (:func:`make_tuner`, :mod:`jaxobs.tuning.tuner`)
is a pure ``init`` / ``step`` pair that explores the search box (Sobol screening, a CMA-ES in JAX) and polishes the
best points with any optax optimiser from several starts in one ``vmap``, minimising a robust objective (mean or
CVaR) with diverged plants penalised (:func:`penalise_diverged`); a JAX program can run it in its own jitted loop.
:func:`tune` is the job around it (checkpoints, processes and devices, progress, a wall-time budget);
:func:`random_search` the gradient-free baseline; :func:`evaluate` scores a ``theta`` on the held-out batch
(:func:`evaluator`: several designs, compiled once). Parameterisations: :func:`cholesky_covariance`,
:func:`unit_interval`. Design: docs/theory/jobs.md.
"""

from jaxobs.tuning.job import StartResult, TuneResult, tune
from jaxobs.tuning.objectives import (
    GRADIENT_MODES,
    OBJECTIVES,
    cvar,
    make_objective,
    penalise_diverged,
    robust_objective,
    value_and_grad,
)
from jaxobs.tuning.parameters import (
    cholesky_covariance,
    cholesky_labels,
    cholesky_parameters,
    log_labels,
    unit_interval,
    unit_interval_parameters,
)
from jaxobs.tuning.problem import CheckpointError, TuningError, TuningProblem
from jaxobs.tuning.search import SearchResult, batch_objective, evaluate, evaluator, random_search
from jaxobs.tuning.settings import (
    CANDIDATE_CHUNK,
    DEFAULT_OPTIMIZER,
    FORWARD_MAX_PARAMETERS,
    TuneSettings,
    gradient_mode,
    lbfgs,
    screening_size,
)
from jaxobs.tuning.tuner import Tuner, TunerState, explore_until, make_tuner

__all__ = [
    "cholesky_covariance",
    "cholesky_labels",
    "log_labels",
    "cholesky_parameters",
    "unit_interval",
    "unit_interval_parameters",
    "cvar",
    "robust_objective",
    "penalise_diverged",
    "make_objective",
    "value_and_grad",
    "DEFAULT_OPTIMIZER",
    "lbfgs",
    "TuningProblem",
    "TuneSettings",
    "TuneResult",
    "StartResult",
    "gradient_mode",
    "FORWARD_MAX_PARAMETERS",
    "CANDIDATE_CHUNK",
    "GRADIENT_MODES",
    "OBJECTIVES",
    "SearchResult",
    "TuningError",
    "CheckpointError",
    "Tuner",
    "TunerState",
    "make_tuner",
    "explore_until",
    "screening_size",
    "tune",
    "random_search",
    "batch_objective",
    "evaluate",
    "evaluator",
]
