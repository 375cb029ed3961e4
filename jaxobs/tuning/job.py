"""``tune``: the job shell around the pure tuner (:mod:`jaxobs.tuning.tuner`): one compiled step over every device
of every process, checkpoints and resumption, Ctrl-C and stalls, progress, the starts' histories and the result."""

from __future__ import annotations

import functools
import json
import logging
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from jaxobs._distributed import agree, from_process_0, json_from_process_0
from jaxobs._jit import Compiling
from jaxobs._resources import Interrupted, InterruptWatch, Stalled
from jaxobs.tuning import checkpoints
from jaxobs.tuning._devices import compile_over, host, spread, stall_watch, watched
from jaxobs.tuning.box import Layout
from jaxobs.tuning.problem import CheckpointError, TuningError, TuningProblem
from jaxobs.tuning.settings import TuneSettings, gradient_mode
from jaxobs.tuning.tuner import (
    ACCEPTED,
    ALL_DIVERGED,
    BAD_OBJECTIVE,
    CAPPED,
    DONE,
    EVOLVE,
    FAILED,
    MORE_DIVERGED,
    NEXT,
    NONE_YET,
    POLISH,
    PROGRAM_OF,
    PROGRAMS,
    REJECTED,
    ROSE,
    RUNNING,
    SCREEN,
    STOPS,
    Tuner,
    TunerState,
    explore_until,
    make_tuner,
)

__all__ = ["EXPLORE_SHARE", "StartResult", "TuneResult", "tune"]

logger = logging.getLogger("jaxobs.tuning")

EXPLORE_SHARE = 0.5
"""With a ``seconds`` budget, the first round's exploration moves on once it has used this share of the time left
after the first compilation: the screening at half of it (then the CMA-ES), the CMA-ES at all of it (then the
polish), each with the batch that would pass it (timed at run time), so that a slow machine does not spend its
budget screening (docs/tuning-results.md has the measurements)."""


class StartResult(NamedTuple):
    """One starting point of :func:`tune`.

    Attributes:
      start: the starting ``theta``
      theta: its best accepted parameters (fewest diverged training plants, then lowest objective)
      objective: their training objective (inf when no evaluation was accepted)
      diverged: diverged training plants of ``theta``
      stopped: "converged" (the plateau rule of ``TuneSettings.patience``), "steps" (the cap), "rejected"
        (``max_rejections`` rejected steps in a row) or "failed" (the start fails on the training batch)
      evaluations: its gradient evaluations
      history: one dict per evaluation: evaluation, objective, diverged, accepted, reason, grad_norm, theta, ...
    """

    start: dict
    theta: dict
    objective: float
    diverged: int
    stopped: str
    evaluations: int
    history: list


class TuneResult(NamedTuple):
    """Result of :func:`tune`: the best design it evaluated.

    Attributes:
      theta: the best accepted parameters of every start (fewest diverged training plants, then lowest objective),
        or a scored candidate that is better (a run stopped by its time budget before polishing it)
      objective: their training objective
      history: the best start's evaluations, one dict each: evaluation, objective, diverged, accepted, reason,
        grad_norm, theta, ...
      stopped: why the best start ended: "converged" (the plateau rule) or "steps" (the cap), see
        :class:`StartResult`; "time" when the ``seconds`` budget ended the run
      evaluations: gradient evaluations of every start together
      rollouts: rollouts computed, one per training plant for each scored candidate and for each start at each
        step of the loop (a start that has stopped is computed along with the others until all have)
      diverged: diverged training plants of the best theta
      seconds: wall time of the tuning over all runs that built this checkpoint, screening and compilation
        included
      starts: one :class:`StartResult` per starting point (of every round)
      screened: candidates scored by the exploration (screening and CMA-ES, ``theta0`` included), 0 without one
      compile_seconds: the tracing and compiling of the tuner's step over all runs that built this checkpoint (part
        of ``seconds``; a rerun of a finished checkpoint compiles nothing and adds no time to either)
      curve: the best design so far, one dict each time it improved: seconds, rollouts, objective, diverged, theta
        (the anytime performance of this call; empty when the checkpoint had nothing left to do)
    """

    theta: dict
    objective: float
    history: list
    stopped: str
    evaluations: int
    rollouts: int
    diverged: int
    seconds: float
    starts: tuple = ()
    screened: int = 0
    compile_seconds: float = 0.0
    curve: tuple = ()

    @property
    def converged(self) -> bool:
        """Whether the best start stopped on the plateau rule (not on the cap ``TuneSettings.steps``)."""
        return self.stopped == "converged"


def _initial(problem: TuningProblem, initial) -> list | None:
    """``initial`` checked against ``theta0``'s entries and shapes (None: the tuner's own starts)."""
    if initial is None:
        return None
    initial = list(initial)
    if not initial:
        raise ValueError("initial must hold at least one theta")
    want = {k: np.shape(v) for k, v in problem.theta0.items()}
    for i, theta in enumerate(initial):
        shapes = {k: np.shape(v) for k, v in theta.items()} if isinstance(theta, dict) else None
        if shapes != want:
            raise ValueError(f"initial[{i}] must have theta0's entries and shapes {want}, got {shapes}")
    return initial


def _lower(step, state, batch, mode: str):
    """``jax.jit(step)`` lowered on one device: traced, not run, so that a rollout reverse mode cannot
    differentiate is reported (:class:`TuningError`, one line) before anything is compiled or run."""
    try:
        return jax.jit(step).lower(host(state), batch)
    except ValueError as exc:
        if mode == "reverse" and "Reverse-mode differentiation does not work for lax.while_loop" in str(exc):
            raise TuningError(
                "reverse mode cannot differentiate a while loop in the rollouts: give the loop a fixed count or a "
                "custom derivative (as jaxobs.mjx.common.solve does for MJX's constraint solver), or tune with "
                "gradient = 'forward'"
            ) from None
        raise


def _agree(error: Exception | None, digest: bytes = b"") -> None:
    """:func:`jaxobs._distributed.agree` for a tuning run."""
    agree(error, digest, job="the tuning", kind="tuning", error_type=CheckpointError,
          differs="problem, training plants, settings or tag differ")  # fmt: skip


def _reason(code: int, value: float, count: int, allowed: int, best: float) -> str | None:
    """The words of a rejection (:data:`jaxobs.tuning.tuner.REASONS`)."""
    return {
        ACCEPTED: None,
        ALL_DIVERGED: f"every one of the {count} plants diverged",
        MORE_DIVERGED: f"{count} plant(s) diverged, {allowed} at the last accepted point",
        BAD_OBJECTIVE: f"the objective is {value}",
        ROSE: f"the objective rose to {value:.6g} from {best:.6g}",
    }.get(code, "the gradient is not finite")


def _row(stacked: dict, k: int) -> dict:
    return {name: np.asarray(v[k]) for name, v in stacked.items()}


def _as_numpy(theta: dict) -> dict:
    return {k: np.asarray(v).tolist() for k, v in theta.items()}


def _record(
    before: TunerState, after: TunerState, info, k: int, batch: int, seconds: float, named: str, factor: float
) -> dict:
    """The history record of start ``k``'s evaluation in the step from ``before`` to ``after``, logged as
    :func:`tune` says (a diverging start, a rejected step; ``factor``: the divergence factor)."""
    lane, value, count = before.lanes, float(info.objective[k]), int(info.diverged[k])
    first = int(lane.evaluations[k]) == 0
    allowed = batch - 1 if first else int(lane.diverged[k])
    code = int(info.reason[k])
    reason = _reason(code, value, count, allowed, float(lane.best_objective[k]))
    evaluation, scale = int(lane.evaluations[k]) + 1, float(after.lanes.scale[k])
    if reason is not None and first:
        logger.warning("%sthe starting point fails on the training batch: %s", named, reason)
    elif code == ROSE:  # backtracking: a shorter step along the same update; none improves: a minimum
        logger.info("%sevaluation %d: %s; step scale %g", named, evaluation, reason, scale)
    elif reason is not None:
        logger.warning("%sevaluation %d: step rejected: %s; retrying from the last accepted point with step scale %g",
                       named, evaluation, reason, scale)  # fmt: skip
    elif first and count:
        logger.warning("%s%d of %d training plants diverge under the initial design; each counts as at least %g "
                       "times the largest loss of the others", named, count, batch, factor)  # fmt: skip
    return {"evaluation": evaluation, "objective": value if math.isfinite(value) else None, "diverged": count,
            "accepted": reason is None, "reason": reason, "scale": float(lane.scale[k]),
            "grad_norm": float(info.grad_norm[k]) if reason is None else None,
            "theta": _as_numpy(_row(before.theta, k)), "seconds": seconds}  # fmt: skip


def _start_result(state: TunerState, k: int, history: list, batch: int) -> StartResult:
    lanes = state.lanes
    diverged = int(lanes.best_diverged[k])
    return StartResult(_row(state.start, k), _row(state.best, k), float(lanes.best_objective[k]),
                       batch if diverged >= NONE_YET else diverged, STOPS[int(lanes.stopped[k])] or "steps",
                       int(lanes.evaluations[k]), history)  # fmt: skip


def _stored(result: StartResult) -> dict:
    return {**result._asdict(), "start": _as_numpy(result.start), "theta": _as_numpy(result.theta)}


def _loaded(record: dict, theta0: dict) -> StartResult:
    record = {**record, **{k: {n: np.asarray(v, np.asarray(theta0[n]).dtype) for n, v in record[k].items()}
                           for k in ("start", "theta")}}  # fmt: skip
    return StartResult(**record)


class _Fingerprint(NamedTuple):
    """What a checkpoint was written for: ``setup`` (all but the step's program), ``recorded`` (with the program:
    the checkpoint's, or this run's once :meth:`_Job.adopt` has it) and ``program`` (``text -> fingerprint``)."""

    setup: str
    recorded: str | None
    program: Callable


class _Job:
    """One call of :func:`tune`: its checkpoint, the starts' histories, the starts of finished rounds, the anytime
    curve and the clock."""

    def __init__(self, problem, settings, path, fingerprint, meta: dict, histories: list, clock: float):
        self.problem, self.settings, self.path, self.fingerprint = problem, settings, path, fingerprint
        self.batch, self.count = problem.batch_size(problem.train), len(histories)
        self.writer = jax.process_index() == 0  # process 0 alone writes the checkpoint; the others follow it
        self.histories, self.resumed = histories, False
        self.finished = [_loaded(r, problem.theta0) for r in meta.get("finished", [])]
        self.previous, self.clock, self.curve = meta["seconds"], clock, []
        self.compiled = meta.get("compile_seconds", 0.0)  # by the runs that built the checkpoint
        self.named = (lambda k: f"start {k}: ") if self.count > 1 else (lambda k: "")
        self.explored_from = None  # when this call's first exploration step began (s, as seconds() counts)

    def adopt(self, text: str) -> None:
        """Take ``text`` (the step's programs for one device, lowered) as the run's program: :class:`CheckpointError`
        when the checkpoint was written by another one."""
        program, recorded = self.fingerprint.program(text), self.fingerprint.recorded
        _agree(None if recorded in (None, program) else _other_run(self.path), bytes.fromhex(program))
        self.fingerprint = self.fingerprint._replace(recorded=program)

    def seconds(self) -> float:
        """Wall time of every run of the checkpoint (this one's until it stops)."""
        return self.previous + (0.0 if self.clock is None else time.perf_counter() - self.clock)

    def save(self, state: TunerState) -> None:
        if self.path is not None and self.writer:
            trees, meta = checkpoints.split(host(state), self.histories, self.seconds())
            meta.update(finished=[_stored(r) for r in self.finished], fingerprint=self.fingerprint.recorded,
                        setup=self.fingerprint.setup, compile_seconds=self.compiled)  # fmt: skip
            checkpoints.save(self.path, trees, meta)

    def share(self, state: TunerState, seconds: float | None, last: float) -> TunerState:
        """``state`` whose first round's exploration phase ends with the next step where that step (about ``last``
        seconds, the previous step's) would pass the phase's share of ``seconds`` (:data:`EXPLORE_SHARE`)."""
        phase = int(state.phase)
        if seconds is None or state.search is None or int(state.round) or phase not in (SCREEN, EVOLVE):
            return state
        if self.explored_from is None:
            self.explored_from = self.seconds()
        share = EXPLORE_SHARE * (0.5 if phase == SCREEN else 1.0) * max(seconds - self.explored_from, 0.0)
        if self.seconds() + last < self.explored_from + share:
            return state
        return explore_until(state, int(state.scored) + self.settings.population)

    def rollouts(self, state: TunerState) -> int:
        return (int(state.scored) + int(state.polished) * self.count) * self.batch

    def observe(self, before: TunerState, after: TunerState, info, seconds: float) -> None:
        """Record a step: each evaluated start's history entry, the screening's summary, the best so far."""
        phase = int(info.phase)
        if phase == POLISH:
            for k in np.flatnonzero(np.asarray(before.lanes.stopped) == RUNNING):
                self.histories[k].append(_record(before, after, info, k, self.batch, seconds, self.named(k),
                                                 self.settings.divergence_factor))  # fmt: skip
        if phase == SCREEN and int(after.phase) != SCREEN:
            logger.info("screened %d candidates: best objective %.4g", int(after.scored),
                        float(after.search.best.objective))  # fmt: skip
        best, last = self.best(after), self.curve[-1] if self.curve else None
        if best is not None and (last is None or best[1:] < (last["diverged"], last["objective"])):
            self.curve.append({"seconds": self.seconds(), "rollouts": self.rollouts(after), "objective": best[2],
                               "diverged": best[1], "theta": best[0]})  # fmt: skip

    def best(self, state: TunerState):
        """``(theta, diverged, objective)`` of the best design evaluated so far, or None."""
        if state.search is not None:
            best = state.search.best
            if int(best.diverged) >= NONE_YET:
                return None
            theta = Layout(self.problem.theta0).unflat(np.asarray(best.row))
            return {k: np.asarray(v) for k, v in theta.items()}, int(best.diverged), float(best.objective)
        k = int(np.lexsort((state.lanes.best_objective, state.lanes.best_diverged))[0])
        if int(state.lanes.best_diverged[k]) >= NONE_YET:
            return None
        return _row(state.best, k), int(state.lanes.best_diverged[k]), float(state.lanes.best_objective[k])

    def finish_round(self, state: TunerState) -> None:
        """Keep the starts of the round that ``state`` ends; the next round's starts begin new histories."""
        self.finished += [_start_result(state, k, self.histories[k], self.batch) for k in range(self.count)]
        self.histories = [[] for _ in range(self.count)]

    def starts(self, state: TunerState) -> tuple:
        """The starts of every round: the finished rounds', then the current round's once it polishes."""
        current = int(state.phase) >= POLISH and int(state.round) > len(self.finished) // self.count - 1
        mine = [_start_result(state, k, self.histories[k], self.batch) for k in range(self.count)] if current else []
        return tuple(self.finished + mine)

    def check(self, state: TunerState) -> None:
        """:class:`TuningError` when every start failed, or every one ended in rejections."""
        stops = np.asarray(state.lanes.stopped)
        if np.all(stops == FAILED):
            reasons = "; ".join(h[-1]["reason"] for h in self.histories if h)
            raise TuningError(
                f"the initial parameters fail on the training batch: {reasons}" if self.count == 1 else
                f"every one of the {self.count} starting points fails on the training batch: {reasons}"
            )  # fmt: skip
        if np.all((stops == REJECTED) | (stops == FAILED)):
            self.save(state)
            last = next(h[-1]["reason"] for h in self.histories if h and h[-1]["reason"])
            rejections = int(np.max(state.lanes.rejections))
            raise TuningError(f"{rejections} consecutive steps rejected (last: {last}); lower the learning rate")

    def result(self, state: TunerState, timed_out: bool) -> TuneResult:
        starts = self.starts(state)
        best = self.best(state)
        history, stopped = [], "steps"
        if starts:
            top = min(starts, key=lambda s: (s.diverged, s.objective))
            history, stopped = top.history, top.stopped
            if best is None or not (best[1], best[2]) < (top.diverged, top.objective * (1 - 1e-9)):
                best = (top.theta, top.diverged, top.objective)
        if best is None:
            raise TuningError("the time budget ended the run before any design was evaluated")
        return TuneResult(best[0], best[2], history, "time" if timed_out else stopped,
                          sum(s.evaluations for s in starts), self.rollouts(state), best[1], self.seconds(), starts,
                          int(state.scored), self.compiled, tuple(self.curve))  # fmt: skip


def _label(state: TunerState, population: int) -> str:
    phase = int(state.phase)
    if phase == POLISH:
        return f"evaluation {int(state.iteration) + 1}"
    return f"candidates {int(state.scored)} to {int(state.scored) + population - 1}" if phase < POLISH else "restart"


def _loop(job: _Job, programs: _Programs, state: TunerState, seconds: float | None, bar):
    """Step until the tuner is done or a step ends after ``seconds``; ``(state, timed_out)``. Ctrl-C or a stall
    save the checkpoint of the last completed step and raise."""
    settings, last = job.settings, 0.0
    saved = (state, [list(h) for h in job.histories], list(job.finished))
    with InterruptWatch() as watch, stall_watch("the tuning") as stall:
        try:
            while int(state.phase) != DONE:
                watch.check()
                saved = (state, [list(h) for h in job.histories], list(job.finished))  # consistent, for Ctrl-C
                start, label = time.perf_counter(), _label(state, settings.population)
                if int(state.phase) == NEXT:
                    job.finish_round(state)
                state = job.share(state, seconds, last)
                step = programs.get(state)
                new, info = watched(stall, label, step, state, programs.train)
                last = time.perf_counter() - start
                job.observe(state, new, info, last)
                state, polished = new, int(info.phase) == POLISH
                if polished:
                    job.check(state)
                    bar.update(1)
                bar.set_postfix(best=f"{job.curve[-1]['objective']:.4g}" if job.curve else "-",
                                running=int(np.sum(np.asarray(state.lanes.stopped) == RUNNING)))  # fmt: skip
                turned = int(new.phase) != int(saved[0].phase)
                if (turned and not polished) or (polished and int(state.iteration) % settings.checkpoint_every == 0):
                    job.save(state)
                if seconds is not None and job.seconds() >= seconds and int(state.phase) != DONE:
                    return state, True
            return state, False
        except (KeyboardInterrupt, Stalled) as exc:
            state, job.histories, job.finished = saved
            where = ""
            if (int(state.polished) or int(state.scored)) and job.path is not None and job.writer:
                job.save(state)
                where = f"; checkpoint saved to {job.path}"
            if isinstance(exc, Stalled):
                raise Stalled(f"{exc}{where}") from None
            raise Interrupted(
                f"interrupted after {int(state.iteration)} of {settings.steps} evaluations{where}; "
                "rerun the same command to resume"
            ) from exc
        finally:
            bar.close()


def _resumed(settings: TuneSettings, state: TunerState) -> TunerState:
    """A larger cap continues the starts the former one stopped."""
    lanes = state.lanes
    capped = (np.asarray(lanes.stopped) == CAPPED) & (np.asarray(lanes.evaluations) < settings.steps)
    if not capped.any():
        return state
    state = state._replace(lanes=lanes._replace(stopped=np.where(capped, RUNNING, lanes.stopped).astype(np.int32)))
    return state._replace(phase=np.asarray(POLISH if int(state.phase) == DONE else state.phase, np.int32))


def tune(
    problem: TuningProblem,
    settings: TuneSettings = TuneSettings(),
    *,
    initial: list[dict] | None = None,
    checkpoint: str | Path | None = None,
    progress: bool = True,
    tag: str = "",
    seconds: float | None = None,
) -> TuneResult:
    """Minimise the robust objective of ``problem``'s training losses: explore the search box, then polish the
    best points with the gradient (the tuner of :func:`jaxobs.tuning.make_tuner`, stepped until it is done).

    The starting points are ``initial`` if given, else ``theta0``, or with ``settings.screening`` candidates (and
    ``settings.evolve`` CMA-ES generations): the best of them and ``theta0`` for one start, ``theta0`` and the
    ``settings.starts - 1`` best for more. They run together: each step evaluates the objective and its gradient at
    every start in one call (one rollout per training plant and start). An accepted evaluation takes an optax step
    ``theta <- theta + s * update`` with step scale ``s`` (1 normally); a rejected one (more training plants diverge
    than at the last accepted point, a non-finite objective or gradient; with ``backtrack``, also a step that does
    not improve) returns to the start's last accepted ``theta`` and retries with ``s / 2`` (``s`` doubles back
    towards 1 on each acceptance). A start stops when it has converged (no relative improvement of
    ``min_improvement`` in ``patience`` evaluations, or ``max_rejections`` backtracking halvings in a row), at the
    cap ``steps``, or after ``max_rejections`` diverging steps in a row; each start's run is the run :func:`tune`
    makes from it alone. Training plants that diverge at a start are penalised and logged; a start that fails on
    every plant is dropped, and when every start fails (or every one ends in rejections) a :class:`TuningError`
    says why.

    Args:
      problem: the :class:`TuningProblem`.
      settings: :class:`TuneSettings`.
      initial: starting points (a list of dicts shaped like ``theta0``), replacing ``theta0`` and the exploration.
      checkpoint: a ``.npz`` path: written after the exploration, every ``settings.checkpoint_every`` steps, at the
        end and on Ctrl-C, and resumed from when it exists (it must come from the same problem, program, settings
        and ``tag``).
      progress: show a progress bar with the objective.
      tag: a string identifying the problem's configuration, checked when resuming.
      seconds: a wall-time budget (compilation included): the run stops after the step that passes it, and the
        result is the best design evaluated by then (``stopped == "time"``); the first round's screening and
        CMA-ES end early where they would pass their share of it (:data:`EXPLORE_SHARE`).

    Returns:
      :class:`TuneResult` with the best accepted ``theta``. Ctrl-C raises :class:`jaxobs._resources.Interrupted`
      after saving the checkpoint.

    Example::

        >>> import jax.numpy as jnp, optax
        >>> from jaxobs.tuning import TuneSettings, TuningProblem, tune
        >>> losses = lambda theta, t: ((theta["x"] - t) ** 2, t < -1e9)
        >>> problem = TuningProblem({"x": jnp.array(0.0)}, losses, jnp.array([1.0, 3.0]), jnp.array([2.0]))
        >>> result = tune(problem, TuneSettings(optax.adam(0.3), starts=4, screening=15), progress=False)
        >>> round(float(result.theta["x"]), 2), len(result.starts)
        (2.0, 4)
    """
    from tqdm.auto import tqdm

    settings.validate()
    clock = time.perf_counter()
    initial = _initial(problem, initial)
    tuner = make_tuner(settings, penalty=problem.penalty)
    state = tuner.init(problem.theta0, box=problem.search_box, starts=initial)
    job, state = _open(problem, settings, state, checkpoint, tag, initial, clock)
    state = _resumed(settings, state)
    if job.resumed and (int(state.phase) == DONE or (seconds is not None and job.previous >= seconds)):
        logger.info("%s holds a finished run: nothing to compute", job.path)  # its times and result, unchanged
        job.clock = None
        return job.result(state, int(state.phase) != DONE)
    if job.fingerprint.recorded is not None:  # a checkpoint read
        logger.info("resuming from %s at step %d", job.path, int(state.iteration))
    programs = _Programs(problem, tuner, job, state)
    programs.get(state)  # the first phase's program (the exploration's, usually)
    programs.ahead(state)  # the others in the background, or when first needed
    bar = tqdm(total=settings.steps, initial=int(state.iteration), desc=f"tune (compiled in {job.compiled:.1f} s)",
               disable=not (progress and job.writer), unit="step")  # fmt: skip
    state, timed_out = _loop(job, programs, state, seconds, bar)
    job.previous, job.clock = job.seconds(), None  # the checkpoint and the result hold the same time
    job.save(state)
    return job.result(state, timed_out)


class _Programs:
    """The tuner's step as its programs (:data:`jaxobs.tuning.tuner.PROGRAMS`), traced for one device at once (their
    text checked against the checkpoint's, :meth:`_Job.adopt`) and compiled over every device of every process
    when a state first needs one (:meth:`get`) or ahead of it in a background thread (:meth:`ahead`); each
    tracing and compiling said in one line pair and added to ``job.compiled``; ``train``: the training batch as
    placed for them."""

    HINT = "use fewer training plants or starts, shorter rollouts or a gradient_horizon"

    def __init__(self, problem: TuningProblem, tuner: Tuner, job: _Job, state: TunerState):
        self.problem, self.tuner, self.job, self.train = problem, tuner, job, problem.train
        batch, count = problem.batch_size(problem.train), int(state.lanes.scale.shape[0])
        mode = gradient_mode(tuner.settings, problem.theta0)
        self.what = f"the tuner's step ({batch} training rollouts at {count} start(s), {mode}-mode gradient)"
        with Compiling(logger, f"{self.what}: tracing its {len(PROGRAMS)} programs") as tracing:
            self.lowered = [_lower(lambda s, plants, i=i: tuner.step_in(i, s, problem.losses, plants), state,
                                   problem.train, mode) for i in range(len(PROGRAMS))]  # fmt: skip
            job.adopt("".join(program.as_text() for program in self.lowered))
        job.compiled += tracing.seconds
        self.compiled, self.pending = {}, {}

    def get(self, state: TunerState):
        """The compiled step of ``state``'s phase."""
        program = PROGRAM_OF[int(state.phase)]
        if program not in self.compiled:
            pending = self.pending.pop(program, None)
            self.compiled[program], seconds = pending.result() if pending else self._compile(program, state)
            self.job.compiled += seconds
        return self.compiled[program]

    def ahead(self, state: TunerState) -> None:
        """Compile the programs after ``state``'s phase (the polish's, between rounds) in a background thread while
        the first one runs: on one device, where the programs are already lowered (a mesh's are lowered when
        compiled, in the thread of the call, with its JAX configuration)."""
        first, rounds = PROGRAM_OF[int(state.phase)], self.tuner.settings.rounds
        later = [p for p in (PROGRAMS.index("polish"), PROGRAMS.index("advance")) if p > first]
        later = [p for p in later if p != PROGRAMS.index("advance") or rounds > 1]
        if len(jax.devices()) > 1 or not later:
            return
        pool = ThreadPoolExecutor(1, thread_name_prefix="jaxobs-compile")
        self.pending.update({p: pool.submit(self._compile, p, state) for p in later if p not in self.compiled})
        pool.shutdown(wait=False)  # the thread ends once the programs are compiled

    def _compile(self, program: int, state: TunerState):
        """``(compiled program, seconds)``."""
        losses, size, what = self.problem.losses, self.problem.batch_size(self.problem.train), self.what
        with Compiling(logger, f"{what}: the {PROGRAMS[program]} program") as compiling:
            compiled, self.train, _ = compile_over(
                lambda mesh: lambda s, plants: self.tuner.step_in(program, s, spread(losses, mesh, size), plants),
                self.problem.train, state, what, hint=self.HINT, alone=self.lowered[program],
            )  # fmt: skip
        return compiled, compiling.seconds


def _open(problem: TuningProblem, settings: TuneSettings, state: TunerState, checkpoint, tag: str, initial,
          clock: float):  # fmt: skip
    """``(job, state)``: the run's checkpoint read (process 0) and agreed on by every process, checked against the
    fingerprint of everything but the step's program (:meth:`_Job.adopt` checks that)."""
    count = int(state.lanes.scale.shape[0])
    path = Path(checkpoint) if checkpoint is not None else None
    trees, meta = checkpoints.split(host(state), [[] for _ in range(count)], 0.0)
    resume, error = jax.process_index() == 0 and path is not None and path.exists(), None
    if resume:  # a damaged checkpoint is reported before the step is traced
        try:
            trees, meta = checkpoints.load(path, trees)
        except CheckpointError as exc:
            error = exc
    _agree(error)
    given = "" if initial is None else json.dumps([_as_numpy(t) for t in initial])  # the starting points, if given
    setup = checkpoints.fingerprint(problem.theta0, settings, tag + given, "", problem.train)
    if resume and meta.get("setup", setup) != setup:
        error = _other_run(path)
    _agree(error, bytes.fromhex(setup))
    meta = json_from_process_0(meta)
    state, histories = checkpoints.join(host(from_process_0(trees)), meta, settings.steps)
    resumed = bool(from_process_0(np.bool_(resume)))
    program = functools.partial(checkpoints.fingerprint, problem.theta0, settings, tag + given, train=problem.train)
    recorded = meta.get("fingerprint") if resumed else None
    job = _Job(problem, settings, path, _Fingerprint(setup, recorded, program), meta, histories, clock)
    job.resumed = resumed and "setup" in meta  # a checkpoint of an older jaxobs is checked against the program too
    return job, state


def _other_run(path: Path) -> CheckpointError:
    return CheckpointError(f"{path}: written for a different problem, program or settings; delete it (or use another "
                           "--out) to start over")  # fmt: skip
