"""jaxobs.tuning.tuner: the pure tuner inside a user's jitted loop (a scan equals the Python loop of jitted steps and
the loop of each phase's program alone, an eager step equals a jitted one, vmap over keys equals separate runs), its
exploration finding the global basin of a multimodal objective, restarts with distinct starts, the box kept, and the
job's wall-time budget, anytime curve and resumption mid-exploration."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.tuning import TuneSettings, TuningProblem, explore_until, job, lbfgs, make_tuner, screening_size, tune
from jaxobs.tuning.tuner import NONE_YET, PHASES, PROGRAM_OF, PROGRAMS


def losses(theta, targets):
    """A shifted Rastrigin function per plant (many local minima, period 1): the mean over the plants (targets 1.0 and
    1.2 in both coordinates) has its global minimum at (1.1, 1.1), 0.78."""
    z = theta["x"] - targets[:, None]
    value = jnp.sum(z**2 - 2.0 * jnp.cos(2 * jnp.pi * z) + 2.0, axis=1)
    return value, jnp.zeros(targets.shape, bool)


TARGETS = jnp.array([1.0, 1.2])
SETTINGS = TuneSettings(lbfgs(), backtrack=True, screening=31, evolve=20, patience=4, starts=3, rounds=2,
                        distinct=0.1, spread=5.0, bounded=True)  # fmt: skip


def test_the_tuner_runs_inside_a_users_jitted_loop():
    tuner = make_tuner(SETTINGS)
    start = tuner.init({"x": jnp.array([-3.0, 2.5])})  # in the basin of a local minimum

    def run(state, steps):
        return jax.lax.scan(lambda s, _: tuner.step(s, losses, TARGETS), state, None, length=steps)

    final, infos = jax.jit(run, static_argnums=1)(start, 100)
    assert PHASES[int(final.phase)] == "done" and int(final.round) == 1  # two rounds, then done
    np.testing.assert_allclose(final.search.best.row, [1.1, 1.1], atol=1e-6)
    step = jax.jit(lambda s: tuner.step(s, losses, TARGETS))
    state = start
    for _ in range(100):
        state = step(state)[0]
    jax.tree.map(np.testing.assert_array_equal, state, final)  # the scan is the loop of jitted steps
    programs = [jax.jit(lambda s, i=i: tuner.step_in(i, s, losses, TARGETS)) for i in range(len(PROGRAMS))]
    state = start
    for _ in range(100):  # and the loop of the phases' programs alone (a job's, tune's)
        state = programs[PROGRAM_OF[int(state.phase)]](state)[0]
    jax.tree.map(np.testing.assert_array_equal, state, final)
    low, high = final.search.low, final.search.high  # bounded: every start stayed in the box
    assert bool(jnp.all((final.best["x"] >= low) & (final.best["x"] <= high)))
    scored = np.asarray(infos.scored)[np.asarray(infos.phase) < 2]
    assert int(final.scored) == scored.sum() == 32 + 16 * np.sum(np.asarray(infos.phase) == 1)
    cut = step(explore_until(start, 16))[0]  # the screening ends with its first batch, the CMA-ES keeps its rules
    assert (PHASES[int(cut.phase)], int(cut.scored), int(cut.search.until)) == ("evolve", 16, NONE_YET)
    cut = step(explore_until(cut, 17))[0]  # and the CMA-ES with its first generation
    assert (PHASES[int(cut.phase)], int(cut.scored)) == ("polish", 32)


def test_the_auto_screening_is_sized_to_the_parameters():
    """A power of two with ``theta0``: about four points per parameter, two batches at least, 128 at most."""
    auto = TuneSettings(screening="auto")
    assert [screening_size(auto, d) for d in (1, 8, 9, 16, 17, 10_000)] == [31, 31, 63, 63, 127, 127]
    assert screening_size(dataclasses.replace(auto, population=32), 2) == 63
    assert screening_size(TuneSettings(screening=7), 100) == 7
    with pytest.raises(ValueError, match="screening must be an integer >= 0 or 'auto'"):
        TuneSettings(screening="all").validate()
    state = make_tuner(dataclasses.replace(SETTINGS, screening="auto")).init({"x": jnp.array([-3.0, 2.5])})
    assert state.search.points.shape == (32, 2)


@pytest.mark.slow
def test_the_tuners_step_eagerly_and_under_vmap():
    """An eager step is the jitted step; runs vmapped over the CMA-ES's keys are the runs one at a time."""
    tuner = make_tuner(SETTINGS)
    start = tuner.init({"x": jnp.array([-3.0, 2.5])})
    step = jax.jit(lambda s: tuner.step(s, losses, TARGETS))
    for _ in range(3):  # a screening step, then CMA-ES generations
        eager, jitted = tuner.step(start, losses, TARGETS), step(start)
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-12), eager, jitted)
        start = jitted[0]

    def run(key):
        state = tuner.init({"x": jnp.array([-3.0, 2.5])}, key)
        return jax.lax.scan(lambda s, _: tuner.step(s, losses, TARGETS), state, None, length=100)[0]

    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    runs = jax.jit(jax.vmap(run))(keys)
    np.testing.assert_allclose(runs.search.best.row[1], jax.jit(run)(keys[1]).search.best.row, rtol=1e-12)


def test_tune_explores_restarts_and_keeps_a_curve(tmp_path):
    """The job over the same tuner: the global minimum from a start in a local basin, the starts of both rounds
    (theta0 and distinct others), an anytime curve that only falls; a wall-time budget stops it early, and a rerun
    past the budget computes nothing."""
    problem = TuningProblem({"x": jnp.array([-3.0, 2.5])}, losses, TARGETS, TARGETS)
    result = tune(problem, SETTINGS, progress=False)
    np.testing.assert_allclose(result.theta["x"], [1.1, 1.1], atol=1e-6)
    assert len(result.starts) == 6 and result.screened > 32
    np.testing.assert_array_equal(result.starts[0].start["x"], [-3.0, 2.5])  # theta0 is a start of round 0
    firsts = np.array([s.start["x"] for s in result.starts[:3]])
    assert np.min(np.abs(firsts[:, None] - firsts[None]).max(-1)[np.triu_indices(3, 1)]) >= 0.1 * 10
    objectives = [p["objective"] for p in result.curve]
    assert objectives == sorted(objectives, reverse=True) and objectives[-1] == result.objective
    short = tune(problem, SETTINGS, progress=False, seconds=1e-9, checkpoint=tmp_path / "short.npz")
    assert short.stopped == "time" and short.evaluations == 0 and len(short.curve) == 1
    again = tune(problem, SETTINGS, progress=False, seconds=1e-9, checkpoint=tmp_path / "short.npz")  # past its budget
    assert (again.stopped, again.seconds, again.screened, again.curve) == ("time", short.seconds, short.screened, ())


def test_a_time_budget_ends_the_first_rounds_exploration_at_its_share(monkeypatch):
    """With ``seconds``, the first round's screening and CMA-ES move on once their share is used (here none: one
    batch each), the later rounds' CMA-ES keeps its own rules."""
    problem = TuningProblem({"x": jnp.array([-3.0, 2.5])}, losses, TARGETS, TARGETS)
    monkeypatch.setattr(job, "EXPLORE_SHARE", 0.0)
    observe, steps = job._Job.observe, []

    def record(self, before, after, info, seconds):
        steps.append((int(before.round), PHASES[int(info.phase)]))
        return observe(self, before, after, info, seconds)

    monkeypatch.setattr(job._Job, "observe", record)
    result = tune(problem, SETTINGS, progress=False, seconds=1e6)
    assert [p for r, p in steps if r == 0 and p in ("screen", "evolve")] == ["screen", "evolve"]
    assert steps.count((1, "evolve")) > 1 and result.stopped == "converged"


def test_given_starts_without_a_box_polish_one_round():
    """``initial`` starts and no box (nothing to restart the CMA-ES in): one round, then done, whatever ``rounds``."""
    problem = TuningProblem({"x": jnp.array([-3.0, 2.5])}, losses, TARGETS, TARGETS)
    settings = dataclasses.replace(SETTINGS, bounded=False, starts=1)
    result = tune(problem, settings, initial=[{"x": jnp.array([1.0, 1.0])}], progress=False)
    assert len(result.starts) == 1 and result.screened == 0
    np.testing.assert_allclose(result.theta["x"], [1.1, 1.1], atol=1e-6)


def test_a_run_interrupted_while_exploring_resumes_to_the_same_result(tmp_path, monkeypatch, caplog):
    """Ctrl-C mid-exploration, then a rerun: the same result as a run without a break; a rerun of the finished
    checkpoint compiles nothing and reports the same times (tuning and compiling, over both runs)."""
    problem = TuningProblem({"x": jnp.array([-3.0, 2.5])}, losses, TARGETS, TARGETS)
    settings = dataclasses.replace(SETTINGS, checkpoint_every=1)
    straight = tune(problem, settings, progress=False)
    observe, calls = job._Job.observe, []

    def interrupted(self, *args):
        calls.append(1)
        if len(calls) == 4:  # the third CMA-ES generation
            raise KeyboardInterrupt
        return observe(self, *args)

    monkeypatch.setattr(job._Job, "observe", interrupted)
    path = tmp_path / "ckpt.npz"
    with pytest.raises(KeyboardInterrupt, match="after 0 of 50 evaluations; checkpoint saved"):
        tune(problem, settings, checkpoint=path, progress=False)
    monkeypatch.setattr(job._Job, "observe", observe)
    resumed = tune(problem, settings, checkpoint=path, progress=False)
    assert resumed.screened == straight.screened and resumed.objective == straight.objective
    for got, want in zip(resumed.starts, straight.starts, strict=True):
        assert (got.stopped, got.evaluations) == (want.stopped, want.evaluations)
        np.testing.assert_array_equal(got.theta["x"], want.theta["x"])
    caplog.clear()
    with caplog.at_level("INFO", logger="jaxobs.tuning"):
        rerun = tune(problem, settings, checkpoint=path, progress=False)  # finished: nothing to compile or compute
    assert "holds a finished run" in caplog.text and "compiling" not in caplog.text
    assert (rerun.seconds, rerun.compile_seconds, rerun.objective) == (resumed.seconds, resumed.compile_seconds,
                                                                       resumed.objective)  # fmt: skip
    assert rerun.compile_seconds > 0 and rerun.curve == () and len(rerun.starts) == len(resumed.starts)
