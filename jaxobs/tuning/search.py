"""Scoring designs outside the tuner: the batched scorer any gradient-free search can use
(:func:`batch_objective`), the random-search baseline (:func:`random_search`) and the held-out scores
(:func:`evaluate`)."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._distributed import from_process_0
from jaxobs.batching import safe_vmap
from jaxobs.tuning._devices import compile_spread, host, spread, stall_watch, watched
from jaxobs.tuning.box import Layout, search_box
from jaxobs.tuning.objectives import cvar, make_objective, penalise_diverged, robust_objective
from jaxobs.tuning.problem import TuningProblem
from jaxobs.tuning.settings import CANDIDATE_CHUNK, TuneSettings

__all__ = ["SearchResult", "batch_objective", "random_search", "evaluate", "evaluator"]

logger = logging.getLogger("jaxobs.tuning")


def _strong(theta: dict) -> dict:
    """``theta`` as NumPy arrays of fixed (not weak) dtypes, the types the compiled scorer is called with."""
    return {k: np.asarray(jnp.asarray(v).astype(jnp.asarray(v).dtype)) for k, v in theta.items()}


def batch_objective(problem: TuningProblem, settings: TuneSettings = TuneSettings()) -> Callable:
    """A compiled scorer of candidate parameters for gradient-free searches: ``candidates -> (objectives,
    diverged)`` for ``candidates``, a dict like ``theta0`` with a leading axis of any length N, scored
    :data:`CANDIDATE_CHUNK` at a time (one ``vmap`` over candidates and training plants per call, spread over the
    devices like :func:`jaxobs.tuning.tune`'s rollouts). ``objectives`` (N,) is the tuner's training objective (inf
    where every plant diverged or it is not finite), ``diverged`` (N,) the count of diverged training plants.
    :func:`random_search` uses it; so can CMA-ES or any ask/tell optimiser.

    Example::

        >>> import jax.numpy as jnp, numpy as np
        >>> from jaxobs.tuning import TuningProblem, batch_objective
        >>> losses = lambda theta, t: ((theta["x"] - t) ** 2, t < -1e9)
        >>> problem = TuningProblem({"x": jnp.array(0.0)}, losses, jnp.array([1.0, 3.0]), jnp.array([2.0]))
        >>> batch_objective(problem)({"x": np.array([0.0, 2.0])})[0].tolist()
        [5.0, 1.0]
    """
    size = problem.batch_size(problem.train)
    chunk = {k: np.repeat(v[None], CANDIDATE_CHUNK, 0) for k, v in _strong(problem.theta0).items()}
    score, train, _, _ = compile_spread(
        lambda mesh: safe_vmap(make_objective(spread(problem.losses, mesh, size), settings, problem.penalty),
                               (0, None)),
        problem.train, chunk, f"the scorer of {CANDIDATE_CHUNK} candidates a call ({size} training rollouts each)",
        hint="use fewer training plants",
    )  # fmt: skip

    def scores(candidates: dict):
        count = len(next(iter(candidates.values())))
        rows = np.minimum(np.arange(-(-count // CANDIDATE_CHUNK) * CANDIDATE_CHUNK), count - 1)  # pad with the last
        values, diverged = [], []
        with stall_watch(f"scoring {count} candidates") as stall:
            for first in range(0, rows.size, CANDIDATE_CHUNK):
                part = {k: np.asarray(v)[rows[first : first + CANDIDATE_CHUNK]] for k, v in candidates.items()}
                label = f"candidates {first} to {first + CANDIDATE_CHUNK - 1}"
                value, failed = watched(stall, label, score, part, train)
                counts = np.sum(np.asarray(failed), axis=1)
                values.append(np.where((counts < size) & np.isfinite(value), value, np.inf))
                diverged.append(counts)
        return np.concatenate(values)[:count], np.concatenate(diverged)[:count]

    return scores


class SearchResult(NamedTuple):
    """Result of :func:`random_search`.

    Attributes:
      candidates: every candidate theta, the first being theta0
      objectives: training objective per candidate (inf where every plant diverged)
      diverged: diverged training plants per candidate
      elapsed: wall time (s) when each candidate's score was known, compilation included
      rollouts_per_candidate: training plants each candidate was rolled out on
    """

    candidates: list
    objectives: np.ndarray
    diverged: np.ndarray
    elapsed: np.ndarray
    rollouts_per_candidate: int

    def best(self, count: int | None = None) -> tuple[dict, float, int]:
        """``(theta, objective, diverged)`` of the best of the first ``count`` candidates (default: all): the
        fewest diverged plants, then the lowest objective."""
        count = len(self.candidates) if count is None else count
        i = min(range(count), key=lambda j: (self.diverged[j], self.objectives[j]))
        return self.candidates[i], float(self.objectives[i]), int(self.diverged[i])

    def within(self, seconds: float) -> int:
        """How many candidates were scored within ``seconds`` (at least 1)."""
        return max(1, int(np.searchsorted(self.elapsed, seconds, side="right")))


def random_search(
    problem: TuningProblem,
    settings: TuneSettings,
    num_candidates: int,
    *,
    seconds: float = 0.0,
    spread: float | None = None,
    seed: int = 0,
    progress: bool = True,
) -> SearchResult:
    """Gradient-free baseline: ``theta0``, then candidates drawn uniformly from ``problem.search_box`` (default:
    ``theta0 +- spread`` per unconstrained coordinate, a factor up to ``e^spread`` on log-parameters), each
    scored by the same penalised training objective as :func:`jaxobs.tuning.tune` (one rollout per training plant),
    :data:`CANDIDATE_CHUNK` candidates per batched call. Draws at least ``num_candidates`` and goes on, a chunk at
    a time, until ``seconds`` of wall time (compilation included) have passed, so that one search gives the
    baseline at equal rollouts (:meth:`SearchResult.best` of the first ones) and at equal wall time
    (:meth:`SearchResult.within`).

    Args:
      problem: the :class:`jaxobs.tuning.TuningProblem`.  settings: the objective's settings (as for the tuner).
      num_candidates: candidates drawn at least.  seconds: keep drawing until this much wall time has passed.
      spread: half-width of the default box in unconstrained coordinates (default ``settings.spread``).
      seed: seed of the draws.  progress: show a progress bar.
    """
    from tqdm.auto import tqdm

    settings.validate()
    if num_candidates < 1:
        raise ValueError(f"num_candidates must be >= 1, got {num_candidates}")
    start = time.perf_counter()
    scores = batch_objective(problem, settings)
    theta0 = _strong(problem.theta0)
    layout = Layout(theta0)
    box = search_box(theta0, problem.search_box, settings.spread if spread is None else spread)
    low, high = (np.asarray(b) for b in layout.bounds(box))
    rng = np.random.default_rng(seed)
    candidates, values, diverged, elapsed = [], [], [], []
    bar = tqdm(total=num_candidates, desc="random search", disable=not (progress and jax.process_index() == 0),
               unit="candidate")  # fmt: skip
    while len(candidates) < num_candidates or from_process_0(np.bool_(elapsed[-1] < seconds)):  # process 0's clock
        rows = low + rng.random((CANDIDATE_CHUNK, layout.size)) * (high - low)
        drawn = {k: np.asarray(v) for k, v in layout.unflat_rows(rows).items()}
        if not candidates:
            drawn = {k: np.concatenate([theta0[k][None], v[:-1]]) for k, v in drawn.items()}
        value, count = scores(drawn)
        now = time.perf_counter() - start
        short = num_candidates - len(candidates)  # a last chunk past the time budget keeps only what is missing
        keep = CANDIDATE_CHUNK if short <= 0 or from_process_0(np.bool_(now < seconds)) else min(short, CANDIDATE_CHUNK)
        candidates += [{k: v[i] for k, v in drawn.items()} for i in range(keep)]
        values += value[:keep].tolist()
        diverged += count[:keep].tolist()
        elapsed += [now] * keep
        bar.update(keep)
    bar.close()
    logger.info("random search: %d candidates scored in %.1f s, best objective %.4g", len(candidates), elapsed[-1],
                min(values))  # fmt: skip
    return SearchResult(candidates, np.asarray(values), np.asarray(diverged), np.asarray(elapsed),
                        problem.batch_size(problem.train))  # fmt: skip


def evaluator(problem: TuningProblem, settings: TuneSettings = TuneSettings(), batch=None) -> Callable:
    """``theta -> scores`` of :func:`evaluate`, its rollouts compiled once for every design it scores."""
    batch = problem.heldout if batch is None else batch
    size = problem.batch_size(batch)
    compiled, placed, _, _ = compile_spread(
        lambda mesh: spread(problem.losses, mesh, size), batch, problem.theta0,
        f"a design's {size} rollouts for its scores", hint="use fewer plants",
    )  # fmt: skip

    dtypes = {k: np.asarray(v).dtype for k, v in problem.theta0.items()}

    def scores(theta: dict) -> dict:
        losses, diverged = host(compiled({k: np.asarray(v, dtypes[k]) for k, v in theta.items()}, placed))
        return _scores(losses, diverged, settings)

    return scores


def _scores(losses, diverged, settings: TuneSettings) -> dict:
    failed = np.asarray(diverged) | ~np.isfinite(losses)
    penalised = penalise_diverged(jnp.asarray(losses), jnp.asarray(failed), settings.divergence_factor)
    finite = losses[~failed]
    stats = dict.fromkeys(("mean", "cvar", "p50", "p90", "max"))
    if finite.size:
        quantiles = np.quantile(finite, [0.5, 0.9, 1.0])
        stats = {"mean": float(np.mean(finite)), "cvar": float(cvar(jnp.asarray(finite), settings.cvar_alpha)),
                 "p50": float(quantiles[0]), "p90": float(quantiles[1]), "max": float(quantiles[2])}  # fmt: skip
    objective = float(robust_objective(penalised, settings.objective, settings.cvar_alpha)) if finite.size else math.inf
    return {
        "objective": objective,
        "finite_fraction": float(finite.size / failed.size),
        "diverged": int(failed.sum()),
        **stats,
        "losses": np.where(failed, np.inf, losses),
    }


def evaluate(problem: TuningProblem, theta: dict, settings: TuneSettings = TuneSettings(), batch=None) -> dict:
    """Scores of ``theta`` on ``batch`` (default: the held-out plants): ``objective`` (the robust objective of
    ``settings`` with diverged plants penalised as in training: finite unless every plant diverges),
    ``finite_fraction`` (of plants that did not diverge), ``diverged`` (their count), the ``mean``, ``cvar`` and
    quantiles ``p50``, ``p90``, ``max`` of the finite losses (None if there are none), and ``losses`` (inf where
    diverged). Several designs: :func:`evaluator` compiles the rollouts once for all."""
    return evaluator(problem, settings, batch)(theta)
