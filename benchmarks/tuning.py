"""jaxobs' gradient tuning against the searches a user would pick instead, on the shipped tuning problems.

For every problem (its shipped config: ``jaxobs tune --config ...``) and seed, ``jaxobs.tuning.tune`` runs with the
problem's settings (its screening seeded by the seed) and its wall time ``T`` (compilation and screening included)
is the budget of every baseline, each compiling its own scorer within its budget:

* random search: ``jaxobs.tuning.random_search`` in the problem's search box;
* CMA-ES in JAX (evosax ``CMA_ES``, population 16), batched on the same rollouts (``jaxobs.tuning.batch_objective``);
* CMA-ES of the reference ``cma`` package (population 16, the same scorer);
* Optuna's default sampler (TPE), 16 trials asked per batch (the same scorer).

The CMA-ES start at ``theta0`` with a step size of half the box's half-width and keep to the box; every method
scores candidates by the training objective of ``tune`` (``jaxobs.tuning.batch_objective``). The result of each is
its best candidate on the training objective (fewest diverged plants, then lowest objective), scored once on the
held-out plants (the objective of ``jaxobs.tuning.evaluate``). A baseline is also reported at equal rollouts (its
best among its first candidates whose rollouts match the tuner's). The gradient's price per problem: the median
time of one gradient evaluation (the tuner's mode) over one forward evaluation of the training batch, with their
compile times (``benchmarks/_tuning_problems.py``; both modes: ``benchmarks/mjx_rollouts.py --problems``).

    python benchmarks/tuning.py --out DIR [--problems NAME ...] [--seeds 3] [--spread S] [--readme README.md]
    python benchmarks/tuning.py --out DIR --merge A/tuning.json B/tuning.json [--readme README.md]

Writes ``DIR/tuning.json`` and ``DIR/tuning.png``; ``--readme`` replaces the table between the
``<!-- tuning-table -->`` markers of that file by the results; ``--merge`` runs nothing and tabulates and plots
runs saved by earlier calls (one table from runs made one problem at a time).
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)  # each method compiles within its own budget

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _timing import optional_import  # noqa: E402
from _tuning_problems import PROBLEMS, gradient_costs, load_problem  # noqa: E402

from jaxobs.tuning import batch_objective, gradient_mode, random_search, tune  # noqa: E402

POPULATION = 16  # candidates per generation of the CMA-ES, trials per batch of Optuna
METHODS = ("jaxobs", "random search", "CMA-ES (evosax)", "CMA-ES (cma)", "Optuna (TPE)")


class Box:
    """The problem's search box as a flat vector: ``flat(theta)``, ``unflat(rows)`` (N, d) -> stacked theta."""

    def __init__(self, problem, spread: float):
        from jaxobs.tuning.box import search_box

        self.theta0 = {k: np.asarray(v) for k, v in problem.theta0.items()}
        box = search_box(problem.theta0, problem.search_box, spread)
        self.low = self.flat({k: np.broadcast_to(box[k][0], v.shape) for k, v in self.theta0.items()})
        self.high = self.flat({k: np.broadcast_to(box[k][1], v.shape) for k, v in self.theta0.items()})
        self.free = self.high > self.low

    def outside(self, theta: dict) -> float:
        """How far ``theta`` lies outside the box: its largest excursion beyond a bound, in box half-widths (0
        inside)."""
        x, half = self.flat(theta)[self.free], (self.high - self.low)[self.free] / 2
        return float(np.max(np.maximum(np.maximum(self.low[self.free] - x, x - self.high[self.free]), 0) / half))

    def flat(self, theta: dict) -> np.ndarray:
        return np.concatenate([np.ravel(np.asarray(theta[k], float)) for k in self.theta0])

    def unflat(self, rows: np.ndarray) -> dict:
        rows = np.where(self.free, np.clip(rows, self.low, self.high), self.low)
        out, offset = {}, 0
        for k, v in self.theta0.items():
            out[k] = rows[:, offset : offset + v.size].reshape((len(rows), *v.shape)).astype(v.dtype)
            offset += v.size
        return out


class Tracker:
    """Every scored candidate's objective, diverged count and finishing time; the best (fewest diverged, then
    lowest objective) overall and among the first ``n``."""

    def __init__(self, start: float):
        self.start, self.rows, self.values, self.diverged, self.elapsed = start, [], [], [], []

    def add(self, rows: np.ndarray, values: np.ndarray, diverged: np.ndarray) -> np.ndarray:
        now = time.perf_counter() - self.start
        self.rows += list(rows)
        self.values += list(values)
        self.diverged += list(diverged)
        self.elapsed += [now] * len(rows)
        finite = np.isfinite(values)  # an all-diverged candidate ranks below every other for the optimisers
        return np.where(finite, values, (np.max(values[finite]) if finite.any() else 1.0) * 1e6)

    def best(self, count: int | None = None) -> tuple[np.ndarray, float]:
        count = len(self.rows) if count is None else min(count, len(self.rows))
        i = min(range(count), key=lambda j: (self.diverged[j], self.values[j]))
        return self.rows[i], float(self.values[i])


def _search(problem, settings, seconds, seed, method):
    """Run a baseline for ``seconds`` (compilation included); its :class:`Tracker` and flat box."""
    start = time.perf_counter()
    box = Box(problem, settings.spread)
    tracker = Tracker(start)
    if method == "random search":
        search = random_search(problem, settings, 1, seconds=seconds, seed=seed, progress=False)
        tracker.add(np.array([box.flat(c) for c in search.candidates]), search.objectives, search.diverged)
        tracker.elapsed = list(search.elapsed)
        return tracker, box
    score = batch_objective(problem, settings)
    x0, sigma = box.flat(box.theta0), 0.5 * float(np.max((box.high - box.low)[box.free]) / 2)

    def evaluate(rows):
        values, diverged = score(box.unflat(np.asarray(rows)))
        return tracker.add(np.asarray(rows), values, diverged)

    if method == "CMA-ES (evosax)":
        import jax.numpy as jnp
        from evosax.algorithms import CMA_ES

        es = CMA_ES(population_size=POPULATION, solution=jnp.asarray(x0))
        params = es.default_params.replace(std_init=sigma)
        key = jax.random.PRNGKey(seed)
        state = es.init(key, jnp.asarray(x0), params)
        ask, tell = jax.jit(es.ask), jax.jit(es.tell)
        while time.perf_counter() - start < seconds:
            key, k1, k2 = jax.random.split(key, 3)
            rows, state = ask(k1, state, params)
            fitness = evaluate(np.clip(np.asarray(rows), box.low, box.high))
            state, _ = tell(k2, rows, jnp.asarray(fitness), state, params)
    elif method == "CMA-ES (cma)":
        cma, why = optional_import("cma")
        if cma is None:
            raise RuntimeError(why)
        options = {"popsize": POPULATION, "seed": seed + 1, "verbose": -9,
                   "bounds": [list(box.low - ~box.free), list(box.high + ~box.free)]}  # fmt: skip
        es = cma.CMAEvolutionStrategy(x0, sigma, options)
        while time.perf_counter() - start < seconds:
            rows = np.asarray(es.ask())
            es.tell(list(rows), list(evaluate(rows)))
    elif method == "Optuna (TPE)":
        optuna, why = optional_import("optuna")
        if optuna is None:
            raise RuntimeError(why)
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        study = optuna.create_study(sampler=optuna.samplers.TPESampler(seed=seed))
        free = np.flatnonzero(box.free)
        first = True
        while time.perf_counter() - start < seconds:
            trials = [study.ask() for _ in range(POPULATION)]
            rows = np.tile(box.low, (POPULATION, 1))
            for r, trial in enumerate(trials):
                for i in free:
                    rows[r, i] = trial.suggest_float(f"x{i}", box.low[i], box.high[i])
            if first:  # theta0 among the first batch, as for the other methods
                rows[0], first = x0, False
            for trial, value in zip(trials, evaluate(rows), strict=True):
                study.tell(trial, float(value))
    else:
        raise ValueError(method)
    return tracker, box


def run_problem(label: str, seeds: list[int], progress: bool, spread: float | None = None) -> dict:
    problem, settings, config = load_problem(label, spread)
    batch = problem.batch_size(problem.train)
    heldout = batch_objective(dataclasses.replace(problem, train=problem.heldout),
                              dataclasses.replace(settings, penalty_weight=0.0))  # fmt: skip
    runs = {m: [] for m in METHODS}
    for seed in seeds:
        start = time.perf_counter()
        result = tune(problem, dataclasses.replace(settings, seed=seed), progress=progress)
        seconds = time.perf_counter() - start
        candidates = result.rollouts // batch
        theta = {k: np.asarray(v)[None] for k, v in result.theta.items()}
        runs["jaxobs"].append({
            "seconds": seconds, "rollouts": result.rollouts, "train": result.objective,
            "heldout": float(heldout(theta)[0][0]), "converged": result.converged,
            "evaluations": result.evaluations, "starts": len(result.starts),
            "outside_box": Box(problem, settings.spread).outside(result.theta),
            "theta": {k: np.asarray(v).tolist() for k, v in result.theta.items()},
        })  # fmt: skip
        for method in METHODS[1:]:
            tracker, box = _search(problem, settings, seconds, seed, method)
            row, train = tracker.best(tracker_count := int(np.searchsorted(tracker.elapsed, seconds, "right")) or 1)
            same_row, same_train = tracker.best(candidates)
            scores = heldout(box.unflat(np.stack([row, same_row])))[0]
            runs[method].append({
                "seconds": float(tracker.elapsed[tracker_count - 1]), "rollouts": tracker_count * batch,
                "train": train, "heldout": float(scores[0]),
                "equal_rollouts": {"rollouts": min(candidates, len(tracker.rows)) * batch, "train": same_train,
                                   "heldout": float(scores[1])},
            })  # fmt: skip
            logging.info("%s seed %d %s: held-out %.4g (jaxobs %.4g)", label, seed, method, scores[0],
                         runs["jaxobs"][-1]["heldout"])  # fmt: skip
    costs = gradient_costs(problem, settings, modes=[gradient_mode(settings, problem.theta0)])
    summary = {m: _summary([r["heldout"] for r in rs]) for m, rs in runs.items()}
    return {"config": PROBLEMS[label], "spread": settings.spread, "parameters": free_parameters(problem, settings),
            "training_plants": batch, "runs": runs, "heldout": summary, "gradient_cost": costs}  # fmt: skip


def free_parameters(problem, settings) -> int:
    """The coordinates the search box leaves free: every parameter but the unused upper triangles of Cholesky
    factors."""
    return int(np.sum(Box(problem, settings.spread).free))


def _summary(values):
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def markdown_table(results: dict) -> str:
    head = ["problem (parameters)", *METHODS, "gradient / forward (compile)", "jaxobs wall time"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for label, r in results.items():
        best = min(r["heldout"][m]["median"] for m in METHODS[1:])
        cells = [f"{label} ({r['parameters']})"]
        for m in METHODS:
            s = r["heldout"][m]
            text = f"{s['median']:.4g} [{s['min']:.3g}, {s['max']:.3g}]"
            if m == "jaxobs" and statistics.median(x.get("outside_box", 0.0) for x in r["runs"][m]) > 0:
                text += " †"
            cells.append(f"**{text}**" if m == "jaxobs" and s["median"] <= best else text)
        c = r["gradient_cost"]
        cells.append(f"{c['ratio']:.1f}x ({c['compile_ratio']:.1f}x), {c['mode']}")
        cells.append(f"{statistics.median(x['seconds'] for x in r['runs']['jaxobs']):.0f} s")
        lines.append("| " + " | ".join(cells) + " |")
    if any("†" in line for line in lines):
        lines.append("\n† the tuned design lies outside the search box the baselines keep to (median over seeds).")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot, save_figure

    fig, ax = pyplot().subplots(figsize=(10, 4.5), layout="constrained")
    width = 0.8 / len(METHODS)
    for i, m in enumerate(METHODS):
        for j, r in enumerate(results.values()):
            values = np.array([x["heldout"] for x in r["runs"][m]]) / r["heldout"]["random search"]["median"]
            ax.plot(np.full(values.size, j + (i - 2) * width), values, "o", ms=4, color=f"C{i}",
                    label=m if j == 0 else None)  # fmt: skip
    ax.axhline(1.0, color="k", lw=0.6, ls=":")
    ax.set_xticks(range(len(results)), list(results), rotation=15)
    ax.set(ylabel="held-out objective / random search's median", yscale="log",
           title="Tuning at equal wall time (one marker per seed; lower is better)")  # fmt: skip
    fig.legend(fontsize=8, loc="outside right upper")  # beside the axes: no marker hidden
    save_figure(fig, path.parent, path.stem, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=list(PROBLEMS))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--readme", help="replace the table between <!-- tuning-table --> markers of this file")
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--spread", type=float, help="replace each problem's baseline.spread (its search box)")
    parser.add_argument(
        "--merge",
        nargs="+",
        metavar="JSON",
        help="run nothing: the table and figure of these "
        "tuning.json files' problems (a later file's run of a problem replaces an earlier one's)",
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    if args.merge:
        for path in args.merge:
            results.update(json.loads(Path(path).read_text())["results"])
        results = {label: results[label] for label in PROBLEMS if label in results}
        for label, r in results.items():  # runs saved before the count left out unused entries
            problem, settings, _ = load_problem(label)
            r["parameters"] = free_parameters(problem, settings)
    for label in [] if args.merge else args.problems:
        results[label] = run_problem(label, list(range(args.seeds)), args.progress, args.spread)
        (out / "tuning.json").write_text(json.dumps({"device": jax.devices()[0].device_kind, "results": results},
                                                    indent=2, default=float) + "\n")  # fmt: skip
    table = markdown_table(results)
    print(table)
    plot(results, out / "tuning.png")
    if args.readme:
        path = Path(args.readme)
        text = path.read_text()
        marker = "<!-- tuning-table -->"
        new = re.sub(f"{marker}.*?{marker}", lambda _: f"{marker}\n{table}\n{marker}", text, flags=re.S)
        path.write_text(new)


if __name__ == "__main__":
    main()
