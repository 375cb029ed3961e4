"""The tuner as a pure state machine in optax's shape: ``tuner = make_tuner(settings)``, ``state =
tuner.init(theta0)``, ``state, info = tuner.step(state, losses, batch)``, each step one batched computation and
jittable, so that a JAX program can run the tuner inside its own loop.

Phases (:data:`PHASES`): the screening (Sobol candidates of the search box, ``population`` per step), the
evolution (a CMA-ES, :mod:`jaxobs.tuning.cmaes`, one generation per step, until it stalls), the polish (the starts'
gradient steps in one ``vmap``: accepted or rejected, each start stopped by the plateau rule, rejections or the
cap), then the next round (the CMA-ES restarted at a random point of the box) or done. :func:`jaxobs.tuning.tune`
is a thin loop over :meth:`Tuner.step` that adds checkpoints, devices, progress and reports; docs/theory/jobs.md
has the design.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxobs import _checks
from jaxobs.batching import safe_vmap
from jaxobs.tuning import cmaes
from jaxobs.tuning.box import Layout, search_box
from jaxobs.tuning.objectives import make_objective, value_and_grad
from jaxobs.tuning.settings import TuneSettings, gradient_mode, screening_size

__all__ = ["PHASES", "PROGRAMS", "PROGRAM_OF", "STOPS", "REASONS", "NONE_YET", "Lanes", "Best", "Archive", "Search",
           "TunerState", "StepInfo", "Tuner", "make_tuner", "best_start", "explore_until"]  # fmt: skip

PHASES = ("screen", "evolve", "polish", "next", "done")
"""``TunerState.phase`` indexes this: exploring (screen, evolve), polishing, between rounds (next), done."""
SCREEN, EVOLVE, POLISH, NEXT, DONE = range(len(PHASES))

PROGRAMS = ("explore", "polish", "advance", "done")
"""The step's programs: :meth:`Tuner.step` branches between them, :meth:`Tuner.step_in` runs one alone (a job
compiles each when it is first needed: the exploration's first results do not wait for the polish's compilation)."""
PROGRAM_OF = (0, 0, 1, 2, 3)
"""The program (index into :data:`PROGRAMS`) of each phase (index into :data:`PHASES`): screen and evolve share one."""

STOPS = ("", "converged", "steps", "rejected", "failed")
"""``Lanes.stopped`` indexes this: still running (""), the plateau rule, the cap, rejections, a failed start."""
RUNNING, CONVERGED, CAPPED, REJECTED, FAILED = range(len(STOPS))

REASONS = (None, "every plant diverged", "more plants diverged", "objective not finite", "gradient not finite",
           "objective rose")  # fmt: skip
"""``StepInfo.reason`` indexes this: why a start's evaluation was rejected (None: accepted)."""
ACCEPTED, ALL_DIVERGED, MORE_DIVERGED, BAD_OBJECTIVE, BAD_GRADIENT, ROSE = range(len(REASONS))

NONE_YET = 2**30
"""The diverged count of a best that does not exist yet (ranks below every real one)."""


class Lanes(NamedTuple):
    """The starts' bookkeeping, one entry per start (K,).

    Attributes:
      evaluations: gradient evaluations so far.  scale: the step scale (halved on a rejection, doubled back to 1).
      best_objective, best_diverged: the best accepted evaluation (inf and :data:`NONE_YET` before one).
      diverged: diverged training plants at the last accepted point.  since_best: evaluations since the best
      improved by ``min_improvement``.  rejections: rejected evaluations in a row.  stopped: index into
        :data:`STOPS`.
    """

    evaluations: jax.Array
    scale: jax.Array
    best_objective: jax.Array
    best_diverged: jax.Array
    diverged: jax.Array
    since_best: jax.Array
    rejections: jax.Array
    stopped: jax.Array


class Best(NamedTuple):
    """A best design: ``row`` (d,) its flat ``theta``, its ``objective`` and ``diverged`` count (``+max`` float and
    :data:`NONE_YET` for none)."""

    row: jax.Array
    objective: jax.Array
    diverged: jax.Array


class Archive(NamedTuple):
    """The best screened candidates (M), best first: ``rows`` (M, d), ``objective``, ``diverged``, ``order``
    (when each was scored: ties keep it) and ``used`` (already a start)."""

    rows: jax.Array
    objective: jax.Array
    diverged: jax.Array
    order: jax.Array
    used: jax.Array


class Search(NamedTuple):
    """What the exploration keeps (flat coordinates, :class:`jaxobs.tuning.box.Layout`).

    Attributes:
      low, high: (d,) the search box.  points: (P, d) ``theta0`` and the screening's candidates.  next: () the next
      point to score.  archive: :class:`Archive`.  cma: the CMA-ES's state.  since: () generations without an
      improvement of ``incumbent``.  key: PRNG key of the CMA-ES.  incumbent: the round's best of the CMA-ES.
      best: the best design scored in any phase.  until: () the phase (screening, the round's CMA-ES) moves on
      once ``TunerState.scored`` reaches it (:func:`explore_until`; :data:`NONE_YET`: by its own rules alone).
    """

    low: jax.Array
    high: jax.Array
    points: jax.Array
    next: jax.Array
    archive: Archive
    cma: cmaes.CMAState
    since: jax.Array
    key: jax.Array
    incumbent: Best
    best: Best
    until: jax.Array


class TunerState(NamedTuple):
    """State of the tuner (:func:`make_tuner`).

    Attributes:
      phase: () index into :data:`PHASES`.  round: () the explore-and-polish round.  iteration: () polish steps of
      this round.  polished: () polish steps of every round.  scored: () candidates scored (screening, CMA-ES).
      cap: () gradient evaluations per start at most (``TuneSettings.steps``; a value, so that a larger cap can
        continue a run with the same compiled step).
      lanes: :class:`Lanes` of the starts.
      start, theta, anchor, update, best: ``theta``-shaped dicts with a leading axis of starts (K, ...): each
        start's starting point, the point evaluated next, its last accepted point, the optimiser's update from
        it, and its best accepted point.
      opt: the optimiser's states (K, ...).
      search: :class:`Search`, or None for a tuner that neither explores nor keeps to a box.
    """

    phase: jax.Array
    round: jax.Array
    iteration: jax.Array
    polished: jax.Array
    scored: jax.Array
    cap: jax.Array
    lanes: Lanes
    start: dict
    theta: dict
    anchor: dict
    update: dict
    best: dict
    opt: Any
    search: Search | None


class StepInfo(NamedTuple):
    """What a step computed.

    Attributes:
      phase: () the phase it ran (index into :data:`PHASES`).
      objective, diverged, reason, grad_norm: (K,) each start's training objective, diverged plants, index into
        :data:`REASONS` and gradient norm (a polish step; zeros otherwise).
      candidates, candidates_diverged: (C,) the candidates' training objectives (inf where every plant diverged)
        and diverged plants (an exploration step; C = ``population``).  scored: () how many of them count.
    """

    phase: jax.Array
    objective: jax.Array
    diverged: jax.Array
    reason: jax.Array
    grad_norm: jax.Array
    candidates: jax.Array
    candidates_diverged: jax.Array
    scored: jax.Array


class Tuner(NamedTuple):
    """A tuner (:func:`make_tuner`): ``init(theta0, key=None, *, box=None, starts=None) -> TunerState`` and
    ``step(state, losses, batch) -> (TunerState, StepInfo)``, pure; ``settings`` its :class:`TuneSettings`;
    ``step_in(program, state, losses, batch)``: the step of a state whose phase belongs to ``program`` (index into
    :data:`PROGRAMS`, ``PROGRAM_OF[state.phase]``), that program alone: the same result as ``step``, in a smaller
    program to compile."""

    init: Callable
    step: Callable
    settings: TuneSettings
    step_in: Callable


def make_tuner(settings: TuneSettings = TuneSettings(), *, penalty: Callable | None = None) -> Tuner:
    """The tuner of ``settings`` (a :class:`TuneSettings`) as a pure ``init`` / ``step`` pair (see the module
    docstring for its phases); ``penalty``: an optional ``theta -> scalar`` added to the objective with
    ``settings.penalty_weight`` (a :class:`jaxobs.tuning.TuningProblem`'s).

    ``init(theta0, key=None, *, box=None, starts=None)``: the state before the first step; ``theta0`` a dict of
    arrays, ``key`` the CMA-ES's PRNG key (default: from ``settings.seed``), ``box`` ``{name: (low, high)}`` (default
    ``theta0 +- settings.spread``), ``starts`` a list of ``theta`` to polish at once without exploring.

    ``step(state, losses, batch)``: one batched computation of ``losses(theta, batch) -> (losses (B,), diverged
    (B,))`` (a :class:`jaxobs.tuning.TuningProblem`'s), whose training objective (:func:`make_objective`, with the
    penalty) the tuner minimises; returns the new state and a
    :class:`StepInfo`. A step after the last does nothing (``PHASES[state.phase] == "done"``). Jittable: the
    shapes of ``state`` are fixed by ``init``.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> from jaxobs.tuning import TuneSettings, make_tuner, lbfgs
        >>> losses = lambda theta, t: ((theta["x"] - t) ** 2, t < -1e9)
        >>> tuner = make_tuner(TuneSettings(lbfgs(), backtrack=True, screening=15, evolve=5, patience=3))
        >>> state = tuner.init({"x": jnp.array(0.0)})
        >>> step = jax.jit(lambda s: tuner.step(s, losses, jnp.array([1.0, 3.0]))[0])
        >>> for _ in range(30):
        ...     state = step(state)
        >>> round(float(state.search.best.row[0]), 4)
        2.0
    """
    settings.validate()
    optimizer = optax.with_extra_args_support(settings.optimizer)
    init = jax.jit(functools.partial(_init, settings, optimizer))  # one program, not an eager operation at a time
    step, step_in = (functools.partial(f, settings, optimizer, penalty) for f in (_step, _step_in))
    return Tuner(init, step, settings, step_in)


# --------------------------------------------------------------------------------------------
# init


def _sobol(count: int, dim: int, seed: int) -> np.ndarray:
    """``count`` points (count, dim) of a scrambled Sobol sequence in the unit cube (computed when traced)."""
    from scipy.stats import qmc

    if count == 0:
        return np.zeros((0, dim))
    return qmc.Sobol(dim, scramble=True, seed=seed).random_base2(max(0, math.ceil(math.log2(count))))[:count]


def _no_best(d: int, dtype) -> Best:
    return Best(jnp.zeros(d, dtype), jnp.asarray(jnp.finfo(dtype).max, dtype), jnp.asarray(NONE_YET, jnp.int32))


def _archive_size(settings: TuneSettings) -> int:  # settings.screening: a count
    """Screened candidates kept: enough for every round's starts and a choice of distinct ones."""
    return min(settings.screening + 1, max(16, 4 * settings.starts * settings.rounds))


def _search_init(settings: TuneSettings, layout: Layout, theta0: dict, box: dict, key) -> Search:
    low, high = layout.bounds(box)
    d, dtype = layout.size, layout.dtype
    unit = jnp.asarray(_sobol(settings.screening, d, settings.seed), dtype)
    points = jnp.concatenate([layout.flat(theta0)[None], low + unit * (high - low)])
    m = _archive_size(settings)
    none = jnp.full(m, NONE_YET, jnp.int32)
    archive = Archive(jnp.zeros((m, d), dtype), jnp.full(m, jnp.finfo(dtype).max, dtype), none, none,
                      jnp.zeros(m, bool))  # fmt: skip
    cma = cmaes.init(_unit(layout.flat(theta0), low, high), settings.evolve_sigma, high > low)
    zero, until = jnp.zeros((), jnp.int32), jnp.asarray(NONE_YET, jnp.int32)
    return Search(low, high, points, zero, archive, cma, zero, key, _no_best(d, dtype), _no_best(d, dtype), until)


def _unit(row, low, high):
    """``row``'s position in the box, clipped to the unit cube (0 on fixed coordinates)."""
    width = high - low
    return jnp.clip(jnp.where(width > 0, (row - low) / jnp.where(width > 0, width, 1.0), 0.0), 0.0, 1.0)


def _fresh_lanes(count: int, dtype) -> Lanes:
    zeros = jnp.zeros(count, jnp.int32)
    return Lanes(zeros, jnp.ones(count, dtype), jnp.full(count, jnp.inf, dtype), jnp.full(count, NONE_YET, jnp.int32),
                 jnp.full(count, NONE_YET, jnp.int32), zeros, zeros, zeros)  # fmt: skip


def _begin_polish(optimizer, state: TunerState, starts: dict) -> TunerState:
    """``state`` polishing ``starts`` (stacked ``theta``s) from their first evaluation."""
    count = jax.tree.leaves(starts)[0].shape[0]
    dtype = jnp.result_type(*jax.tree.leaves(starts))
    return state._replace(
        phase=jnp.asarray(POLISH, jnp.int32), iteration=jnp.zeros((), jnp.int32), lanes=_fresh_lanes(count, dtype),
        start=starts, theta=starts, anchor=starts, update=jax.tree.map(jnp.zeros_like, starts), best=starts,
        opt=jax.vmap(optimizer.init)(starts),
    )  # fmt: skip


def _init(settings: TuneSettings, optimizer, theta0: dict, key=None, *, box=None, starts=None) -> TunerState:
    theta0 = {k: jnp.asarray(v).astype(jnp.asarray(v).dtype) for k, v in theta0.items()}  # fixed, not weak, dtypes
    layout = Layout(theta0)
    settings = dataclasses.replace(settings, screening=screening_size(settings, layout.size))  # "auto": a count
    exploring = starts is None and (settings.screening > 0 or settings.evolve > 0)
    if starts is None:
        if settings.starts > 1 and settings.screening < settings.starts - 1 and not settings.evolve:
            raise ValueError(f"starts = {settings.starts} needs screening >= {settings.starts - 1} candidates to start "
                             "from (or pass initial=)")  # fmt: skip
        starts = [theta0] * settings.starts
    stacked = {k: jnp.stack([jnp.asarray(s[k], v.dtype) for s in starts]) for k, v in theta0.items()}
    key = jax.random.PRNGKey(settings.seed) if key is None else key
    search = None
    if exploring or settings.bounded:
        search = _search_init(settings, layout, theta0, search_box(theta0, box, settings.spread), key)
    zero = jnp.zeros((), jnp.int32)
    cap = jnp.asarray(settings.steps, jnp.int32)
    state = TunerState(zero, zero, zero, zero, zero, cap, None, None, None, None, None, None, None, search)
    state = _begin_polish(optimizer, state, stacked)
    phase = (SCREEN if settings.screening else EVOLVE) if exploring else POLISH
    return state._replace(phase=jnp.asarray(phase, jnp.int32))


# --------------------------------------------------------------------------------------------
# step


def _programs(settings: TuneSettings, optimizer, penalty, state: TunerState, losses: Callable) -> list:
    """The step's programs in :data:`PROGRAMS` order, each ``(state, batch) -> (state, info)`` returning the state
    with the dtypes it was given."""
    objective = make_objective(losses, settings, penalty)
    layout = Layout({k: v[0] for k, v in state.theta.items()})
    count = jax.tree.leaves(state.theta)[0].shape[0]
    explore = functools.partial(_explore, settings, optimizer, layout, objective)
    polish = functools.partial(_polish, settings, optimizer, layout, objective)
    advance = functools.partial(_advance, settings, layout)
    done = functools.partial(_done, settings.population, count)
    if state.search is None:  # polish only, one round
        explore = advance = done

    def typed(branch):
        def run(state, batch):
            new, info = branch(state, batch)
            return jax.tree.map(lambda a, b: jnp.asarray(a).astype(b.dtype), new, state), info

        return run

    return [typed(b) for b in (explore, polish, advance, done)]


def _step(settings: TuneSettings, optimizer, penalty, state: TunerState, losses: Callable, batch):
    programs = _programs(settings, optimizer, penalty, state, losses)
    return jax.lax.switch(jnp.asarray(PROGRAM_OF, jnp.int32)[state.phase], programs, state, batch)


def _step_in(settings: TuneSettings, optimizer, penalty, program: int, state: TunerState, losses: Callable, batch):
    return _programs(settings, optimizer, penalty, state, losses)[program](state, batch)


def _info(phase, population: int, count: int, dtype, **given) -> StepInfo:
    zeros = {"objective": jnp.zeros(count, dtype), "diverged": jnp.zeros(count, jnp.int32),
             "reason": jnp.zeros(count, jnp.int32), "grad_norm": jnp.zeros(count, dtype),
             "candidates": jnp.zeros(population, dtype), "candidates_diverged": jnp.zeros(population, jnp.int32),
             "scored": jnp.zeros((), jnp.int32)}  # fmt: skip
    return StepInfo(jnp.asarray(phase, jnp.int32), **{k: jnp.asarray(given.get(k, v)).astype(v.dtype)
                                                      for k, v in zeros.items()})  # fmt: skip


def _done(population: int, count: int, state: TunerState, batch):
    return state, _info(state.phase, population, count, state.lanes.scale.dtype)


def _less(d1, v1, d2, v2):
    """``(d1, v1) < (d2, v2)`` lexicographically: fewer diverged plants, then a lower objective."""
    return (d1 < d2) | ((d1 == d2) & (v1 < v2))


def _improve(best: Best, rows, objective, diverged, valid) -> Best:
    """``best`` or the best valid one of ``rows`` (N, d), whichever ranks first."""
    big = jnp.finfo(objective.dtype).max
    objective = jnp.where(valid, jnp.minimum(objective, big), big)
    diverged = jnp.where(valid, diverged, NONE_YET)
    i = jnp.lexsort((objective, diverged))[0]
    better = _less(diverged[i], objective[i], best.diverged, best.objective)
    return jax.tree.map(lambda new, old: jnp.where(better, new, old), Best(rows[i], objective[i], diverged[i]), best)


def explore_until(state: TunerState, scored) -> TunerState:
    """``state`` whose current exploration phase (the screening, or the round's CMA-ES) moves on once ``scored``
    candidates have been scored in all (``TunerState.scored``; the step that reaches it is its last), its own
    rules notwithstanding: a job's time share (:func:`jaxobs.tuning.tune`'s ``seconds``) or a user's loop. The
    next phase keeps its own rules. Traceable; a state without a search is returned as it is.

    Example::

        >>> import jax.numpy as jnp
        >>> from jaxobs.tuning import TuneSettings, make_tuner, explore_until
        >>> from jaxobs.tuning.tuner import PHASES
        >>> losses = lambda theta, t: ((theta["x"] - t) ** 2, t < -1e9)
        >>> tuner = make_tuner(TuneSettings(screening=63, evolve=5))
        >>> state = explore_until(tuner.init({"x": jnp.array(0.0)}), 16)  # one batch of the screening
        >>> PHASES[int(tuner.step(state, losses, jnp.array([1.0]))[0].phase)]
        'evolve'
    """
    if state.search is None:
        return state
    if jnp.ndim(state.search.until) or jnp.ndim(scored):
        raise ValueError(f"state, scored: one tuner state and one count (vmap for a batch), got counts of shapes "
                         f"{jnp.shape(state.search.until)} and {jnp.shape(scored)}")  # fmt: skip
    return state._replace(search=state.search._replace(until=jnp.asarray(scored, jnp.int32)))


def best_start(state: TunerState) -> jax.Array:
    """Index (a 0-d int32 array; ``int(...)`` for a Python index) of the start with the best accepted evaluation:
    fewest diverged plants, then lowest objective. Traceable: ``jit`` and ``vmap`` over states."""
    lanes = state.lanes
    _checks.fields("state.lanes", lanes, "best_objective (s,), best_diverged (s,)")
    return jnp.lexsort((lanes.best_objective, lanes.best_diverged))[0].astype(jnp.int32)


# --------------------------------------------------------------------------------------------
# exploration: the screening and the CMA-ES


def _score(objective: Callable, layout: Layout, rows, batch):
    """Training objectives (inf where every plant diverged or not finite) and diverged counts of ``rows``."""
    values, failed = safe_vmap(objective, (0, None))(layout.unflat_rows(rows), batch)
    counts = jnp.sum(failed, axis=1).astype(jnp.int32)
    return jnp.where((counts < failed.shape[1]) & jnp.isfinite(values), values, jnp.inf), counts


def _merge(archive: Archive, rows, objective, diverged, order, valid) -> Archive:
    """The best of ``archive`` and the valid ``rows``, ``len(archive)`` of them, best first (ties: scored first)."""
    big = jnp.finfo(objective.dtype).max
    new = Archive(rows, jnp.where(valid, jnp.minimum(objective, big), big), jnp.where(valid, diverged, NONE_YET),
                  jnp.where(valid, order, NONE_YET), jnp.zeros(valid.shape, bool))  # fmt: skip
    both = jax.tree.map(lambda a, b: jnp.concatenate([a, b.astype(a.dtype)]), archive, new)
    keep = jnp.lexsort((both.order, both.objective, both.diverged))[: archive.objective.shape[0]]
    return jax.tree.map(lambda x: x[keep], both)


def _explore(settings, optimizer, layout, objective, state: TunerState, batch):
    """One batch of ``population`` candidates: the screening's next points or a CMA-ES generation."""
    s, c = state.search, settings.population
    screening = state.phase == SCREEN
    key, draw = jax.random.split(s.key)
    index = s.next + jnp.arange(c)
    rows = s.points[jnp.minimum(index, s.points.shape[0] - 1)]
    if settings.evolve:
        unit = cmaes.ask(s.cma, draw, c)
        rows = jnp.where(screening, rows, s.low + unit * (s.high - s.low))
    valid = ~screening | (index < s.points.shape[0])
    values, counts = _score(objective, layout, rows, batch)
    values = values.astype(layout.dtype)
    forced = (state.round == 0) & (state.lanes.scale.shape[0] > 1)  # theta0 (index 0) is a start of its own
    archive = jax.lax.cond(screening, lambda: _merge(s.archive, rows, values, counts, state.scored + index - s.next,
                                                     valid & ~(forced & (index == 0))), lambda: s.archive)  # fmt: skip
    incumbent = _improve(s.incumbent, rows, values, counts, valid & ~screening)
    stalled = ~_less(
        incumbent.diverged,
        incumbent.objective,
        s.incumbent.diverged,
        s.incumbent.objective * (1 - settings.min_improvement),
    )
    search = s._replace(next=s.next + jnp.where(screening, c, 0), archive=archive, key=key, incumbent=incumbent,
                        best=_improve(s.best, rows, values, counts, valid),
                        since=jnp.where(screening, 0, jnp.where(stalled, s.since + 1, 0)))  # fmt: skip
    if settings.evolve:
        ranked = ((rows - s.low) / jnp.where(s.high > s.low, s.high - s.low, 1.0))[jnp.lexsort((values, counts))]
        search = search._replace(cma=jax.tree.map(lambda a, b: jnp.where(screening, a, b), s.cma,
                                                  cmaes.tell(s.cma, ranked)))  # fmt: skip
    state = state._replace(scored=state.scored + jnp.sum(valid), search=search)
    info = _info(state.phase, c, state.lanes.scale.shape[0], state.lanes.scale.dtype, candidates=values,
                 candidates_diverged=counts, scored=jnp.sum(valid))  # fmt: skip
    return _after_exploring(settings, optimizer, layout, state), info


def _after_exploring(settings, optimizer, layout, state: TunerState) -> TunerState:
    """The next phase: the CMA-ES once the screening is scored (from the best point so far), the polish once the
    CMA-ES has stalled, shrunk below 1e-3 of the box or reached ``evolve`` generations; either as soon as
    ``state.scored`` reaches ``search.until``."""
    s = state.search
    ended = state.scored >= s.until
    screened = (state.phase == SCREEN) & ((s.next >= s.points.shape[0]) | ended)
    width = s.cma.sigma * jnp.sqrt(jnp.max(jnp.diagonal(s.cma.cov) if s.cma.cov.ndim == 2 else s.cma.cov))
    evolved = (state.phase == EVOLVE) & ((s.cma.generation >= settings.evolve) | (s.since >= settings.patience) |
                                         (width < 1e-3) | ended)  # fmt: skip
    if settings.evolve:
        centre = cmaes.init(_unit(s.best.row, s.low, s.high), settings.evolve_sigma, s.high > s.low)
        state = state._replace(
            phase=jnp.where(screened, EVOLVE, state.phase),
            search=s._replace(cma=jax.tree.map(lambda a, b: jnp.where(screened, a, b), centre, s.cma),
                              until=jnp.where(screened, NONE_YET, s.until)),
        )  # fmt: skip
        return jax.lax.cond(evolved, lambda: _polish_starts(settings, optimizer, layout, state), lambda: state)
    return jax.lax.cond(screened, lambda: _polish_starts(settings, optimizer, layout, state), lambda: state)


def _polish_starts(settings, optimizer, layout, state: TunerState) -> TunerState:
    """Begin polishing: ``theta0`` first (round 0, several starts), then the CMA-ES's best, then the best unused
    screened candidates at least ``distinct`` box widths from those chosen (the next best where none is)."""
    s, count = state.search, state.lanes.scale.shape[0]
    chosen = jnp.zeros((count, layout.size), layout.dtype)
    taken = jnp.zeros((), jnp.int32)
    if count > 1:
        chosen, taken = chosen.at[0].set(s.points[0]), jnp.where(state.round == 0, 1, 0).astype(jnp.int32)
    archive = s.archive
    if settings.evolve:  # the CMA-ES's best joins the screened candidates (it ranks first, usually)
        i = s.incumbent
        archive = _merge(archive, i.row[None], i.objective[None], i.diverged[None], state.scored[None],
                         (i.diverged < NONE_YET)[None])  # fmt: skip
    chosen, used = _pick(archive, chosen, taken, settings.distinct, s.low, s.high)
    state = state._replace(search=s._replace(archive=archive._replace(used=used)))
    return _begin_polish(optimizer, state, layout.unflat_rows(chosen))


def _pick(archive: Archive, chosen, taken, distinct: float, low, high):
    """Fill ``chosen`` (K, d) from row ``taken`` on with unused archive rows, best first: first those at least
    ``distinct`` (in box widths, largest coordinate) from every chosen row, then any; the last chosen row repeats
    where the archive runs out. Returns the rows and the archive's new ``used`` flags."""
    width = jnp.where(high > low, high - low, 1.0)
    usable = (archive.diverged < NONE_YET) & ~archive.used
    size = archive.rows.shape[0]

    def take(carry, j):  # j < size: a distinct candidate; j >= size: any (the second pass)
        chosen, taken, used = carry
        i, need_distinct = j % size, j < size
        far = jnp.min(jnp.where(jnp.arange(chosen.shape[0]) < taken,
                                jnp.max(jnp.abs(chosen - archive.rows[i]) / width, axis=1), jnp.inf))  # fmt: skip
        ok = usable[i] & ~used[i] & (taken < chosen.shape[0]) & (~need_distinct | (far >= distinct))
        chosen = jnp.where(ok, chosen.at[jnp.minimum(taken, chosen.shape[0] - 1)].set(archive.rows[i]), chosen)
        return (chosen, taken + ok, used.at[i].set(used[i] | ok)), None

    chosen, taken, used = jax.lax.scan(take, (chosen, taken, archive.used), jnp.arange(2 * size))[0]
    last = chosen[jnp.maximum(taken - 1, 0)]
    return jnp.where((jnp.arange(chosen.shape[0]) < taken)[:, None], chosen, last), used


def _advance(settings, layout, state: TunerState, batch):
    """Between rounds: restart the CMA-ES at a uniformly drawn point of the box, or finish."""
    s = state.search
    key, draw = jax.random.split(s.key)
    restart = state.round + 1 < settings.rounds
    cma = cmaes.init(jax.random.uniform(draw, s.low.shape, s.low.dtype), settings.evolve_sigma, s.high > s.low)
    search = s._replace(key=key, cma=cma, since=jnp.zeros((), jnp.int32), incumbent=_no_best(layout.size, layout.dtype),
                        until=jnp.asarray(NONE_YET, jnp.int32))  # fmt: skip
    restarted = state._replace(phase=jnp.asarray(EVOLVE, jnp.int32), round=state.round + 1, search=search)
    state = jax.tree.map(lambda a, b: jnp.where(restart, a, b), restarted,
                         state._replace(phase=jnp.asarray(DONE, jnp.int32)))  # fmt: skip
    return state, _info(NEXT, settings.population, state.lanes.scale.shape[0], state.lanes.scale.dtype)


# --------------------------------------------------------------------------------------------
# polish: the starts' gradient steps


def _gradients(settings, objective, state: TunerState, batch, running):
    """Each start's ``((objective, failed), grad)``. In reverse mode a gradient that a diverged plant made non-finite
    is computed again with the failed plants' inputs replaced by a sound plant's (no terms of their own); both passes
    run the one compiled gradient in a loop of at most two iterations (the objective is the first pass's)."""
    mode = gradient_mode(settings, {k: v[0] for k, v in state.theta.items()})
    count = running.shape[0]
    size, rows = _plant_count(objective, state, batch), jax.tree.leaves(batch)[0].shape[0]  # rows > size: padding

    def evaluate(theta, replaced, batch):
        keep = jnp.where(replaced, jnp.argmin(replaced), jnp.arange(size))[np.minimum(np.arange(rows), size - 1)]
        plants = jax.tree.map(lambda x: x[keep], batch)
        return value_and_grad(lambda t: objective(t, plants, replaced), mode)(theta)

    evaluate = safe_vmap(evaluate, (0, 0, None))
    none = jnp.zeros((count, size), bool)
    if mode == "forward":  # a failed plant's tangents stay in its own lane
        (values, failed), grads = evaluate(state.theta, none, batch)
        return values, failed, grads

    def body(carry):
        passes, _, values, failed, grads, poisoned = carry
        (new_values, new_failed), new_grads = evaluate(state.theta, jnp.where(passes > 0, failed, none), batch)
        first = passes == 0
        values, failed = jnp.where(first, new_values, values), jnp.where(first, new_failed, failed)
        counts = jnp.sum(failed, axis=1)
        found = running & (counts > 0) & (counts < size) & ~_finite_rows(new_grads)
        poisoned = jnp.where(first, found, poisoned)
        grads = jax.tree.map(lambda n, o: jnp.where(first, n, o), new_grads, _where(poisoned, new_grads, grads))
        return passes + 1, first & jnp.any(poisoned), values, failed, grads, poisoned

    (values, failed), grads = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype),
                                           jax.eval_shape(evaluate, state.theta, none, batch))  # fmt: skip
    start = (jnp.zeros((), jnp.int32), jnp.asarray(True), values, failed, grads, jnp.zeros(count, bool))
    _, _, values, failed, grads, _ = jax.lax.while_loop(lambda c: c[1], body, start)
    return values, failed, grads


def _plant_count(objective, state: TunerState, batch) -> int:
    """The training plants (B) the objective scores (the batch may hold padding rows beyond them)."""
    theta = {k: v[0] for k, v in state.theta.items()}
    return jax.eval_shape(lambda t: objective(t, batch)[1], theta).shape[0]


def _finite_rows(tree):
    """Per start: whether every entry of ``tree`` (K, ...) is finite."""
    return functools.reduce(jnp.logical_and, [jnp.all(jnp.isfinite(x), axis=tuple(range(1, x.ndim)))
                                              for x in jax.tree.leaves(tree)])  # fmt: skip


def _where(mask, new, old):
    """Per start (the leading axis): ``new`` where ``mask``, else ``old``, leaf by leaf."""
    return jax.tree.map(lambda a, b: jnp.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), new, old)


def _judge(settings, lanes: Lanes, running, values, counts, size: int, finite_grads, cap):
    """Accept or reject each running start's evaluation (vectorised over starts): ``(lanes, accepted, rejected,
    reason)``; see :func:`jaxobs.tuning.tune` for the rules."""
    first = lanes.evaluations == 0
    allowed = jnp.where(first, size - 1, lanes.diverged)
    reason = jnp.select([counts == size, counts > allowed, ~jnp.isfinite(values), ~finite_grads],
                        [ALL_DIVERGED, MORE_DIVERGED, BAD_OBJECTIVE, BAD_GRADIENT], ACCEPTED)  # fmt: skip
    rose = (reason == ACCEPTED) & settings.backtrack & ~first & ~_less(counts, values, lanes.best_diverged,
                                                                        lanes.best_objective)  # fmt: skip
    reason = jnp.where(running, jnp.where(rose, ROSE, reason), ACCEPTED)
    accepted = running & (reason == ACCEPTED)
    failed_start, rejected = running & ~accepted & first, running & ~accepted & ~first
    rejections = jnp.where(rejected, lanes.rejections + 1, jnp.where(accepted, 0, lanes.rejections))
    improved = (counts < lanes.best_diverged) | (values < lanes.best_objective * (1 - settings.min_improvement))
    since_best = jnp.where(accepted, jnp.where(improved, 0, lanes.since_best + 1), lanes.since_best)
    better = accepted & _less(counts, values, lanes.best_diverged, lanes.best_objective)
    evaluations = lanes.evaluations + running
    stopped = jnp.select(
        [~running, failed_start, rejected & (rejections > settings.max_rejections),
         accepted & (since_best >= settings.patience), evaluations >= cap],
        [lanes.stopped, FAILED, jnp.where(reason == ROSE, CONVERGED, REJECTED), CONVERGED, CAPPED], RUNNING,
    )  # fmt: skip
    new = Lanes(
        evaluations, jnp.where(rejected, lanes.scale / 2, jnp.where(accepted, jnp.minimum(1.0, 2 * lanes.scale),
                                                                    lanes.scale)),
        jnp.where(better, values, lanes.best_objective), jnp.where(better, counts, lanes.best_diverged),
        jnp.where(accepted, counts, lanes.diverged), since_best, rejections, stopped,
    )  # fmt: skip
    return jax.tree.map(lambda a, b: a.astype(b.dtype), new, lanes), accepted, rejected, reason, better


def _polish(settings, optimizer, layout, objective, state: TunerState, batch):
    """One gradient evaluation of every start, its acceptance, and the optimiser's step from the accepted ones."""
    running = state.lanes.stopped == RUNNING
    values, failed, grads = _gradients(settings, objective, state, batch, running)
    values = values.astype(state.lanes.scale.dtype)
    counts = jnp.sum(failed, axis=1).astype(jnp.int32)
    lanes, accepted, rejected, reason, better = _judge(settings, state.lanes, running, values, counts,
                                                       failed.shape[1], _finite_rows(grads), state.cap)  # fmt: skip

    def updates():
        def one(grad, opt, theta, value, plants):  # value_fn: the objective, for an optimiser's line search (L-BFGS)
            return optimizer.update(grad, opt, theta, value=value, grad=grad,
                                    value_fn=lambda th: objective(th, plants)[0])  # fmt: skip

        return safe_vmap(one, (0, 0, 0, 0, None))(grads, state.opt, state.theta, values, batch)

    update, opt = jax.lax.cond(jnp.any(accepted), updates, lambda: (state.update, state.opt))
    anchor = _where(accepted, state.theta, state.anchor)
    update = _where(accepted, update, state.update)
    moved = jax.tree.map(lambda a, u: a + lanes.scale.reshape((-1,) + (1,) * (a.ndim - 1)) * u, anchor, update)
    search = state.search
    if search is not None:
        if settings.bounded:
            low, high = layout.unflat(search.low), layout.unflat(search.high)
            moved = {k: jnp.clip(v, low[k], high[k]) for k, v in moved.items()}
        search = search._replace(best=_improve(search.best, layout.flat_rows(state.theta), values, counts, better))
    stopped = jnp.all(lanes.stopped != RUNNING)
    again = settings.rounds > 1 and search is not None  # without a search (given starts, no box): one round
    state = state._replace(
        phase=jnp.where(stopped, NEXT if again else DONE, POLISH).astype(jnp.int32),
        iteration=state.iteration + 1, polished=state.polished + 1, lanes=lanes,
        theta=_where(accepted | rejected, moved, state.theta), anchor=anchor, update=update,
        best=_where(better, state.theta, state.best), opt=_where(accepted, opt, state.opt), search=search,
    )  # fmt: skip
    norms = jax.vmap(optax.tree.norm)(grads)
    info = _info(POLISH, settings.population, running.shape[0], lanes.scale.dtype, objective=values,
                 diverged=counts, reason=reason, grad_norm=norms)  # fmt: skip
    return state, info
