"""jaxobs' tuner against the searches a user would pick instead, at a box that holds every method's best design,
at equal wall time, with the held-out objective against wall time (anytime curves).

Problems: the shipped tuning problems (their configs: ``jaxobs tune --config ...``) and three problems with an exact
optimum, the finite-horizon gain schedule of a linear filter with 104, 1000 and 10 000 gains
(``jaxobs.tuning.problems``: ``(J - J*) / J*`` is reported). Every method gets the same wall-time budget per seed,
compilation included, searches the same box (:data:`FAIR_SPREAD`: ``theta0 +- spread`` per unconstrained coordinate,
Cholesky couplings +- 1; the gain schedules: +-1.5 times the largest optimal gain) and scores candidates with the
same batched training objective (``jaxobs.tuning.batch_objective``):

* jaxobs: ``jaxobs.tuning.tune`` with the shipped strategy (Sobol screening, CMA-ES in JAX, L-BFGS polish of two
  starts in one vmap) kept in the box (``bounded``), its screening sized to the parameters (``screening = "auto"``)
  and restarting (``rounds``) until the budget is spent;
* random search: uniform draws in the box, as ``jaxobs.tuning.random_search`` makes them;
* CMA-ES in JAX (evosax ``CMA_ES``), separable CMA-ES (evosax ``Sep_CMA_ES``), OpenAI-ES (evosax ``Open_ES``), all
  on the unit cube of the box from ``theta0``, and the reference CMA-ES (``cma``; not above
  :data:`CMA_MAX_DIMENSION` coordinates, where its covariance does not fit);
* Optuna's default sampler (TPE), a population of trials asked per batch.

Each method's best design so far (fewest diverged training plants, then lowest training objective) is scored on
the held-out plants at :data:`GRID` log-spaced times up to the budget: the anytime curves (median and range over
the seeds). The table gives the median [min, max] over the seeds at the budget, the training rollouts each method
computed, and where a method's best lies on the boundary of the box (then the box is too small: ``--widen``).

    python benchmarks/tuning.py --out DIR [--problems NAME ...] [--seeds 5] [--budget S] [--spread S] [--widen N]
                                [--methods M ...] [--readme README.md docs/tuning-results.md]
    python benchmarks/tuning.py --out DIR --merge A/tuning.json B/tuning.json [--readme ...]

Writes ``DIR/tuning.json``, ``DIR/tuning.png`` (anytime curves) and ``DIR/tuning.md`` (the tables); ``--readme``
replaces the tables between the ``<!-- tuning-table -->`` and ``<!-- tuning-anytime -->`` markers of those files;
``--merge`` runs nothing and tabulates and plots runs saved by earlier calls.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)  # each method compiles within its own budget

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _timing import optional_import  # noqa: E402
from _tuning_problems import ORACLES, PROBLEMS, load_oracle, load_problem  # noqa: E402

from jaxobs.tuning import batch_objective, tune  # noqa: E402
from jaxobs.tuning.box import Layout, search_box  # noqa: E402

METHODS = ("jaxobs", "random search", "CMA-ES (evosax)", "CMA-ES (cma)", "sep-CMA-ES (evosax)", "OpenAI-ES (evosax)",
           "Optuna (TPE)")  # fmt: skip
FAIR_SPREAD = {"force-1dof": 20.0, "force-1dof-cvar": 20.0, "peg-on-hole": 45.0, "grip-example56": 3.0,
               "cartpole-payload": 12.0, "arm-on-table": 8.0, "sideslip": 4.0, "peg-on-hole-cholesky": 45.0,
               "cartpole-payload-aob": 12.0, "arm-on-table-cholesky": 8.0, "arm7-aob-cholesky": 4.0}  # fmt: skip
"""The fair box per shipped problem: ``theta0 +- spread``, wide enough to hold every method's best design (the
designs the tuner finds when it may leave the shipped box, docs/tuning-results.md)."""
BUDGET = {"gain-schedule-100": 45.0, "gain-schedule-1000": 60.0, "gain-schedule-10000": 90.0,
          "speed-schedule-256": 90.0, "arm7-aob-cholesky": 600.0}  # fmt: skip
"""Wall time per method and seed (s), compilation included; 120 s for the problems not named."""
STRATEGY = {"bounded": True, "rounds": 10_000, "screening": "auto"}
"""jaxobs' settings over each problem's (the shipped strategy): the box kept, restarts until the budget is spent, a
screening sized to the parameters (``jaxobs.tuning.screening_size``: 31 candidates up to 8 parameters, 63 up to
16, 127 above); ``tune``'s ``seconds`` ends the first round's screening and CMA-ES at their share of the budget
(``jaxobs.tuning.job.EXPLORE_SHARE``)."""
CMA_MAX_DIMENSION = 2000
GRID = 16
TIE = 0.01  # relative difference under which two medians tie


class Box:
    """The box as flat vectors (``jaxobs.tuning.box.Layout`` order): ``unit(rows)`` and ``rows(unit)`` map between
    the box and the unit cube; ``free`` marks the coordinates that move."""

    def __init__(self, problem, spread: float):
        self.layout = Layout(problem.theta0)
        low, high = self.layout.bounds(search_box(problem.theta0, problem.search_box, spread))
        self.low, self.high = np.asarray(low), np.asarray(high)
        self.free = self.high > self.low
        self.width = np.where(self.free, self.high - self.low, 1.0)
        self.theta0 = np.asarray(self.layout.flat(problem.theta0))

    def rows(self, unit) -> np.ndarray:
        return np.where(self.free, self.low + np.clip(unit, 0.0, 1.0) * (self.high - self.low), self.low)

    def unit(self, rows) -> np.ndarray:
        return np.clip((np.asarray(rows) - self.low) / self.width, 0.0, 1.0) * self.free

    def theta(self, rows) -> dict:
        return {k: np.asarray(v) for k, v in self.layout.unflat_rows(np.atleast_2d(rows)).items()}

    def on_boundary(self, row) -> bool:
        """Whether ``row`` lies within 1e-3 of the box's width of a bound (or beyond) in a free coordinate."""
        unit = (np.asarray(row) - self.low) / self.width
        return bool(np.any(self.free & ((unit < 1e-3) | (unit > 1 - 1e-3))))


class Trace:
    """A method's best design so far: one entry per improvement, ``(seconds, rollouts, objective, diverged,
    row)``; :meth:`add` records scored candidates."""

    def __init__(self, batch: int):
        self.start, self.batch, self.scored, self.points = time.perf_counter(), batch, 0, []

    def add(self, rows, values, diverged) -> np.ndarray:
        now = time.perf_counter() - self.start
        self.scored += len(values)
        order = np.lexsort((values, diverged))
        best = (int(diverged[order[0]]), float(values[order[0]]))
        if not self.points or best < (self.points[-1][3], self.points[-1][2]):
            self.points.append((now, self.scored * self.batch, best[1], best[0], np.asarray(rows[order[0]])))
        finite = np.isfinite(values)  # an all-diverged candidate ranks below every other for the optimisers
        return np.where(finite, values, (np.max(values[finite]) if finite.any() else 1.0) * 1e6) + 1e6 * diverged

    def seconds(self) -> float:
        return time.perf_counter() - self.start


def population(box: Box) -> int:
    """The evolution strategies' population: ``4 + 3 ln d`` (Hansen 2016) rounded up to a multiple of 16."""
    return 16 * math.ceil((4 + 3 * math.log(max(int(box.free.sum()), 1))) / 16)


def _evosax(method, box, evaluate, seconds, seed, trace):
    import jax.numpy as jnp
    import optax
    from evosax.algorithms import CMA_ES, Open_ES, Sep_CMA_ES

    size, x0 = population(box), jnp.asarray(box.unit(box.theta0))
    if method == "OpenAI-ES (evosax)":
        es = Open_ES(population_size=size, solution=x0, optimizer=optax.adam(0.02),
                     std_schedule=optax.constant_schedule(0.05))  # fmt: skip
        params = es.default_params
    else:
        es = (CMA_ES if method == "CMA-ES (evosax)" else Sep_CMA_ES)(population_size=size, solution=x0)
        params = es.default_params.replace(std_init=0.25)
    key = jax.random.PRNGKey(seed)
    state = es.init(key, x0, params)
    ask, tell = jax.jit(es.ask), jax.jit(es.tell)
    while trace.seconds() < seconds:
        key, k1, k2 = jax.random.split(key, 3)
        unit, state = ask(k1, state, params)
        fitness = evaluate(box.rows(np.asarray(unit)))
        state, _ = tell(k2, unit, jnp.asarray(fitness), state, params)


def _cma(box, evaluate, seconds, seed, trace):
    cma, why = optional_import("cma")
    if cma is None:
        raise RuntimeError(why)
    options = {"popsize": population(box), "seed": seed + 1, "verbose": -9, "bounds": [0.0, 1.0]}
    es = cma.CMAEvolutionStrategy(box.unit(box.theta0), 0.25, options)
    while trace.seconds() < seconds:
        unit = np.asarray(es.ask())
        es.tell(list(unit), list(evaluate(box.rows(unit))))


def _optuna(box, evaluate, seconds, seed, trace):
    optuna, why = optional_import("optuna")
    if optuna is None:
        raise RuntimeError(why)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(sampler=optuna.samplers.TPESampler(seed=seed))
    free, size, first = np.flatnonzero(box.free), population(box), True
    while trace.seconds() < seconds:
        trials = [study.ask() for _ in range(size)]
        rows = np.tile(box.low, (size, 1))
        for r, trial in enumerate(trials):
            for i in free:
                rows[r, i] = trial.suggest_float(f"x{i}", box.low[i], box.high[i])
        if first:  # theta0 among the first batch, as for the other methods
            rows[0], first = box.theta0, False
        for trial, value in zip(trials, evaluate(rows), strict=True):
            study.tell(trial, float(value))


def run_method(method: str, problem, settings, box: Box, seconds: float, seed: int) -> Trace:
    """Run ``method`` for ``seconds`` (compilation included); its :class:`Trace`."""
    trace = Trace(problem.batch_size(problem.train))
    if method == "jaxobs":
        tuned = dataclasses.replace(settings, seed=seed, **STRATEGY)
        result = tune(problem, tuned, progress=False, seconds=seconds)
        trace.scored = result.rollouts // trace.batch
        trace.points = [(p["seconds"], p["rollouts"], p["objective"], p["diverged"],
                         np.asarray(box.layout.flat(p["theta"]))) for p in result.curve]  # fmt: skip
        return trace
    score = batch_objective(problem, settings)

    def evaluate(rows):
        values, diverged = score(box.theta(rows))
        return trace.add(rows, values, diverged)

    evaluate(box.theta0[None])  # the hand-set design first, as the random search and the tuner score it
    if method == "random search":  # jaxobs.tuning.random_search's draws, kept as a Trace
        rng = np.random.default_rng(seed)
        while trace.seconds() < seconds:
            evaluate(box.rows(rng.random((16, box.low.size))))
    elif method == "CMA-ES (cma)":
        _cma(box, evaluate, seconds, seed, trace)
    elif method == "Optuna (TPE)":
        _optuna(box, evaluate, seconds, seed, trace)
    else:
        _evosax(method, box, evaluate, seconds, seed, trace)
    return trace


def anytime(trace: Trace, grid: np.ndarray, heldout) -> dict:
    """The held-out objective of the best design so far at each ``grid`` time (None before the first) and at the
    end of the run (the last entry: the method's result, after the step that passed the budget), the training
    objective and rollouts then, and the final design's row."""
    times = np.array([p[0] for p in trace.points])
    at = np.append(np.searchsorted(times, grid, side="right") - 1, len(trace.points) - 1)
    unique = sorted({int(i) for i in at if i >= 0})
    scores = dict(zip(unique, heldout(np.stack([trace.points[i][4] for i in unique])), strict=True)) if unique else {}
    return {
        "heldout": [float(scores[i]) if i >= 0 else None for i in at],
        "train": [trace.points[i][2] if i >= 0 else None for i in at],
        "rollouts": [trace.points[i][1] if i >= 0 else None for i in at],
        "final_rollouts": trace.scored * trace.batch,
        "row": trace.points[-1][4].tolist() if trace.points else None,
        "first": trace.points[0][0] if trace.points else None,
    }


def _load(label: str, spread: float | None):
    """``(problem, settings, box, optimum)``: a problem of :data:`ORACLES` (its own box) or a shipped one in its
    fair box (:data:`FAIR_SPREAD` unless ``spread``)."""
    if label in ORACLES:
        problem, settings, optimum = load_oracle(label)
        return problem, settings, Box(problem, settings.spread), optimum
    problem, settings, _ = load_problem(label, spread or FAIR_SPREAD[label])
    return problem, settings, Box(problem, settings.spread), None


def run_problem(label: str, seeds: list[int], methods: list[str], budget: float | None, spread: float | None) -> dict:
    problem, settings, box, optimum = _load(label, spread)
    seconds = budget or BUDGET.get(label, 120.0)
    grid = np.geomspace(seconds / 100, seconds, GRID)
    score = batch_objective(dataclasses.replace(problem, train=problem.heldout),
                            dataclasses.replace(settings, penalty_weight=0.0))  # fmt: skip

    def heldout(rows):
        return score(box.theta(rows))[0]

    runs = {m: [] for m in methods}
    for seed in seeds:
        for method in methods:
            if method == "CMA-ES (cma)" and box.free.sum() > CMA_MAX_DIMENSION:
                continue
            trace = run_method(method, problem, settings, box, seconds, seed)
            record = anytime(trace, grid, heldout)
            record["on_boundary"] = record["row"] is not None and box.on_boundary(record["row"])
            record["load"] = os.getloadavg()[0]  # the machine's 1-minute load average as the run ended
            runs[method].append(record)
            logging.info("%s seed %d %-20s held-out %.6g after %d rollouts%s (load %.1f)", label, seed, method,
                         record["heldout"][-1], record["final_rollouts"], " ON THE BOUNDARY" * record["on_boundary"],
                         os.getloadavg()[0])  # fmt: skip
    return {"parameters": int(box.free.sum()), "spread": settings.spread, "budget": seconds, "grid": grid.tolist(),
            "optimum": optimum, "training_plants": problem.batch_size(problem.train), "runs": runs,
            "load": os.getloadavg()}  # fmt: skip


def _first(run: dict, grid: list) -> float:
    """When the run scored its first design (s); for a run saved without it, the first grid time with one."""
    if "first" in run:
        return math.inf if run["first"] is None else run["first"]
    return next((t for t, v in zip(grid, run["heldout"], strict=False) if v is not None), math.inf)


def _final(run: dict) -> float:
    value = run["heldout"][-1]
    return math.inf if value is None else value


def summarise(r: dict) -> dict:
    """Per method: the median, min and max over the seeds of the held-out objective at the budget (for a problem with
    an optimum, ``(J - J*) / J*``), the median rollouts, the seeds whose best lies on the box's boundary; for jaxobs
    also the median time at which it reached the best baseline's median final value."""
    scale = (lambda v: (v - r["optimum"]) / r["optimum"]) if r["optimum"] else (lambda v: v)
    out = {}
    for method, runs in r["runs"].items():
        if runs:
            finals = [scale(_final(x)) for x in runs]
            out[method] = {"median": statistics.median(finals), "min": min(finals), "max": max(finals),
                           "rollouts": statistics.median(x["final_rollouts"] for x in runs),
                           "first": statistics.median(_first(x, r["grid"]) for x in runs),
                           "on_boundary": sum(bool(x["on_boundary"]) for x in runs)}  # fmt: skip
    baselines = [m for m in out if m != "jaxobs"]
    if "jaxobs" in out and baselines:
        target = min(out[m]["median"] for m in baselines)
        reached = []
        for run in r["runs"]["jaxobs"]:
            hits = [t for t, v in zip(r["grid"], run["heldout"], strict=False) if v is not None and scale(v) <= target]
            reached.append(hits[0] if hits else math.inf)
        out["jaxobs"]["time_to_best_baseline"] = statistics.median(reached)
    return out


def _load_range(r: dict) -> str:
    """The range of the machine's load average over a problem's runs (at each run's end)."""
    loads = [x["load"] for runs in r["runs"].values() for x in runs if "load" in x] or [r["load"][0]]
    return f"{min(loads):.3g} to {max(loads):.3g}"


def _cell(s: dict, oracle: bool) -> str:
    fmt = (lambda v: f"{v:.2g}") if oracle else (lambda v: f"{v:.4g}")
    text = f"{fmt(s['median'])} [{fmt(s['min'])}, {fmt(s['max'])}]"
    return text + (" ‡" if s["on_boundary"] else "")


def markdown_table(results: dict) -> str:
    head = ["problem (parameters; box)", "budget", *METHODS, "jaxobs reaches the best baseline"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for label, r in results.items():
        s, oracle = summarise(r), bool(r["optimum"])
        lowest = min(v["median"] for v in s.values()) + (1 if oracle else 0)  # with an optimum: J / J*
        box = "+-1.5 max gain" if oracle else f"+-{r['spread']:g}"
        cells = [f"{label} ({r['parameters']}; {box})", f"{r['budget']:g} s"]
        for m in METHODS:
            if m not in s:
                cells.append("not run")
                continue
            text = _cell(s[m], oracle)
            win = s[m]["median"] + (1 if oracle else 0) <= lowest * (1 + TIE)
            cells.append(f"**{text}**" if win else text)
        t = s.get("jaxobs", {}).get("time_to_best_baseline", math.inf)
        cells.append(f"{t:.3g} s ({t / r['budget']:.0%})" if math.isfinite(t) else "not reached")
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("\nMedian [min, max] over the seeds of the held-out objective of each method's best design at the "
                 "budget (gain schedules: (J - J*) / J*); bold: lowest median, or within 1 % of it; ‡: on the box's "
                 "boundary for some seed. The runs' load, rollouts and first designs: with the anytime curves of "
                 "docs/tuning-results.md.")  # fmt: skip
    return "\n".join(lines)


def run_notes(results: dict) -> str:
    """The runs' machine load, each method's rollouts and the time of its first scored design, per problem."""
    return ("Load average during the runs: " + "; ".join(
                f"{label}: {_load_range(r)}" for label, r in results.items()) + ". Rollouts: " + "; ".join(
                f"{label}: " + ", ".join(f"{m} {v['rollouts']:.3g}" for m, v in summarise(r).items())
                for label, r in results.items()) + ". First design scored (median s; for runs saved without "
            "the time, the anytime grid's first time with one): " + "; ".join(
                f"{label}: " + ", ".join(f"{m} {v['first']:.3g}" for m, v in summarise(r).items())
                for label, r in results.items()) + ".")  # fmt: skip


def anytime_table(results: dict, shares=(0.1, 0.25, 0.5, 1.0)) -> str:
    """The anytime curves as numbers: per problem and method, the median over the seeds of the held-out objective
    (gain schedules: ``(J - J*) / J*``) of the best design so far at ``shares`` of the budget."""
    head = ["problem", "method", *(f"{share:.0%} of the budget" for share in shares)]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for label, r in results.items():
        grid = np.asarray(r["grid"])
        columns = [int(np.argmin(np.abs(grid - share * r["budget"]))) for share in shares]
        for method in METHODS:
            runs = r["runs"].get(method) or []
            if not runs:
                continue
            cells = []
            for j in columns:
                values = [x["heldout"][j] for x in runs]
                if any(v is None for v in values):
                    cells.append("-")
                    continue
                value = statistics.median(values)
                cells.append(f"{(value - r['optimum']) / r['optimum']:.2g}" if r["optimum"] else f"{value:.4g}")
            lines.append(f"| {label} | {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def replace_tables(path: Path, tables: dict) -> None:
    """Replace the text between each pair of ``<!-- name -->`` markers of ``path`` by ``tables[name]``."""
    text = path.read_text()
    for name, table in tables.items():
        marker = f"<!-- {name} -->"
        text = re.sub(f"{marker}.*?{marker}", lambda _, m=marker, t=table: f"{m}\n{t}\n{m}", text, flags=re.S)
    path.write_text(text)


def plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot, save_figure

    count = len(results)
    cols = min(3, count)
    rows = math.ceil(count / cols)
    fig, axes = pyplot().subplots(rows, cols, figsize=(5 * cols, 3.6 * rows), squeeze=False, layout="constrained")
    for ax, (label, r) in zip(axes.flat, results.items(), strict=False):
        oracle = bool(r["optimum"])
        for i, method in enumerate(METHODS):
            runs = r["runs"].get(method) or []
            if not runs:
                continue
            values = np.array([[np.nan if v is None else v for v in x["heldout"][:-1]] for x in runs], float)
            if oracle:
                values = (values - r["optimum"]) / r["optimum"]
            grid = np.asarray(r["grid"])
            ax.plot(grid, np.nanmedian(values, 0), color=f"C{i}", label=method)
            ax.fill_between(grid, np.nanmin(values, 0), np.nanmax(values, 0), color=f"C{i}", alpha=0.15, lw=0)
        ax.set(xscale="log", yscale="log", xlabel="wall time (s, compilation included)",
               ylabel="(J - J*) / J*" if oracle else "held-out objective",
               title=f"{label} ({r['parameters']} parameters; load {_load_range(r)})")  # fmt: skip
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8)
    fig.suptitle("Best design so far against wall time: median over the seeds that have one by then, band min to max "
                 "(lower is better)")  # fmt: skip
    save_figure(fig, path.parent, path.stem, dpi=110)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    names = [*ORACLES, *PROBLEMS]
    parser.add_argument("--problems", nargs="+", default=names, choices=names)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--budget", type=float, help="wall time per method and seed (s); default: BUDGET")
    parser.add_argument("--spread", type=float, help="replace the fair box's spread of the shipped problems")
    parser.add_argument("--widen", type=int, default=0, help="rerun a problem with a doubled spread while a best "
                        "design lies on the box's boundary, at most this many times")  # fmt: skip
    parser.add_argument(
        "--readme",
        nargs="+",
        default=[],
        help="replace the tables between <!-- tuning-table --> "
        "and <!-- tuning-anytime --> markers of these files (README.md, docs/tuning-results.md)",
    )
    parser.add_argument("--merge", nargs="+", metavar="JSON", help="run nothing: the table and figure of these "
                        "tuning.json files' problems (a later file's run of a problem replaces an earlier "
                        "one's)")  # fmt: skip
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("jaxobs.tuning").setLevel(logging.WARNING)  # not every backtracking step
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for path in args.merge or []:
        results.update(json.loads(Path(path).read_text())["results"])
    for label in [] if args.merge else args.problems:
        spread = args.spread
        for _ in range(args.widen + 1):
            results[label] = run_problem(label, list(range(args.seeds)), args.methods, args.budget, spread)
            (out / "tuning.json").write_text(json.dumps({"device": jax.devices()[0].device_kind, "results": results},
                                                        indent=2, default=float) + "\n")  # fmt: skip
            widened = any(x["on_boundary"] for runs in results[label]["runs"].values() for x in runs)
            if label in ORACLES or not widened:
                break
            spread = 2 * results[label]["spread"]
    tables = {"tuning-table": markdown_table(results),
              "tuning-anytime": anytime_table(results) + "\n\n" + run_notes(results)}  # fmt: skip
    print(tables["tuning-table"])
    (out / "tuning.md").write_text("\n\n".join(tables.values()) + "\n")
    plot(results, out / "tuning.png")
    for path in args.readme:
        replace_tables(Path(path), tables)
    return results


if __name__ == "__main__":
    main()
