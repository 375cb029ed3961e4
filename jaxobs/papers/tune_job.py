"""``jaxobs tune``: run a tuning problem end to end and report it.

:func:`run` tunes a :class:`~jaxobs.papers.scenarios.TuningScenario`'s problem from its hand-set design with
:func:`jaxobs.tuning.tune` (checkpointed, resumable), runs the random-search baseline in the problem's search box
(:func:`jaxobs.papers.tuning_config.search_box`) for at least as many rollouts and as much wall time as the tuning
took, scores the hand-set, tuned and random-search designs (best at equal rollouts, best at equal wall time) on the
held-out plants, and writes ``tuned.json``, ``report.md`` (the same results for a reader) and three figures:
``loss_curves.png``, ``responses.png`` (before/after on held-out plants) and ``parameters.png`` (trajectories of
the unconstrained parameters). The output directory is
locked for the run (:func:`jaxobs._resources.locked_out_dir`). Several processes may run it together.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path

import jax
import numpy as np

from jaxobs._config import ConfigError
from jaxobs._distributed import agree, from_process_0
from jaxobs._resources import LOCK_NAME, JobError, LimitError, atomic_write, locked_out_dir
from jaxobs.papers._output import pyplot, save_figure, to_builtin
from jaxobs.papers.tuning_config import config_tag
from jaxobs.papers.tuning_config import settings as tuning_settings
from jaxobs.tuning import batch_objective, evaluator, random_search, tune

__all__ = ["run"]


def _refuse_another_run(out: Path, tag: str, overwrite: bool) -> None:
    """Refuse to mix runs: ``out`` may hold only a run of the same configuration (resumed) unless ``overwrite``."""
    marker = out / "config.json"
    if not overwrite and marker.exists():
        try:
            previous = json.loads(marker.read_text())
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{marker}: unreadable ({exc}); use --overwrite to start over") from exc
        if not isinstance(previous, dict) or not isinstance(previous.get("tag"), str):
            raise ConfigError(f"{marker}: not a jaxobs tune record (no tag); use --overwrite to start over")
        if previous["tag"] != tag:
            raise ConfigError(f"{out} holds a tuning run of another configuration; use --overwrite or another --out")


def _prepare(out: Path, tag: str, config: dict, overwrite: bool) -> None:
    """Mark ``out`` as the run of ``config``, emptied first (all but the lock the caller holds) when ``overwrite``."""
    if overwrite:
        for entry in out.iterdir():
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            elif entry.name != LOCK_NAME:
                entry.unlink()
    atomic_write(out / "config.json", (json.dumps({"tag": tag, "config": config}, indent=2) + "\n").encode())


def _box_position(theta: dict, box: dict) -> dict:
    """Where ``theta`` lies in ``box``: per free coordinate, 0 at the low and 1 at the high bound."""
    position = {}
    for name, (low, high) in box.items():
        low, high, value = (np.ravel(np.asarray(a)) for a in (low, high, theta[name]))
        free = high > low
        position[name] = ((value[free] - low[free]) / (high[free] - low[free])).tolist()
    return position


def run(scenario, config: dict, out_dir, *, progress: bool = True, overwrite: bool = False) -> dict | None:
    """Tune ``scenario`` (a :class:`~jaxobs.papers.scenarios.TuningScenario`) with its validated ``config``, run the
    baseline, evaluate on the held-out plants, write ``tuned.json`` and the figures.

    In a multi-process run (``jax.distributed.initialize``) every process makes the same call and computes its
    devices' share of every batch of rollouts; process 0 alone locks and writes ``out_dir`` and returns the
    summary, the others return None (and need not see ``out_dir``). The problem is built (its last checks: the
    model's names and counts) before anything is written to ``out_dir``, so a config it refuses leaves no record
    that would refuse the corrected one."""
    writer = jax.process_index() == 0
    tag = config_tag(config)
    with contextlib.ExitStack() as held:
        out, error = Path(out_dir), None
        try:
            if writer:
                out = held.enter_context(locked_out_dir(out_dir))
                _refuse_another_run(out, tag, overwrite)
        except JobError as exc:  # ConfigError included
            error = exc
        agree(error, bytes.fromhex(tag), job=f"the tuning run in {out_dir}", kind="tuning run",
              differs="their config files differ", error_type=ConfigError)  # fmt: skip
        try:
            problem = scenario.build(config)
        except LimitError:  # named by the config key that sets the size (jaxobs.papers.scenarios)
            raise
        except ValueError as exc:  # e.g. an invalid MJCF
            raise ConfigError(f"{config['problem']}: {exc}") from exc
        if writer:
            _prepare(out, tag, config, overwrite)
        return _run(problem, config, out, tag, progress, writer)


def _run(problem, config: dict, out: Path, tag: str, progress: bool, writer: bool) -> dict | None:
    settings = tuning_settings(config)
    result = tune(problem, settings, checkpoint=out / "checkpoint.npz", progress=progress, tag=tag,
                  seconds=config["optimizer"]["seconds"] or None)  # fmt: skip
    recorded = _recorded(out, config, result) if writer else None
    if from_process_0(np.bool_(recorded is not None)):  # a rerun of a finished run: its record, not a new one
        if writer:
            atomic_write(out / "report.md", markdown_report(recorded).encode())
        return recorded
    summary = _tuned(problem, config, result)
    search, designs = _baselines(problem, settings, config, result, summary, progress)
    scorer = evaluator(problem, settings)
    scores = {name: scorer(theta) for name, theta in designs.items()}
    if not writer:
        return None
    hand = scores["hand-set"]["objective"]
    summary["heldout"] = {
        name: {
            **{k: v for k, v in s.items() if k != "losses"},
            "reduction_vs_hand_set": 1.0 - s["objective"] / hand if np.isfinite(hand) else None,
        }
        for name, s in scores.items()
    }
    summary["parameters"] = {name: problem.describe(theta) for name, theta in designs.items()}
    summary["theta"] = {name: {k: np.asarray(v) for k, v in theta.items()} for name, theta in designs.items()}
    summary["parameter_labels"] = problem.component_labels()
    summary["loss_unit"] = problem.loss_unit
    summary["figures"] = [_plot_loss_curves(result, search, scores, settings.objective, problem.loss_unit, out)]
    if result.history:  # a time budget may end the run before its first gradient step
        summary["figures"].append(_plot_parameters(problem, result.history, result.theta, out))
    if problem.responses is not None:
        summary["figures"].append(_plot_responses(problem, designs, scores["hand-set"]["losses"], out))
    atomic_write(out / "tuned.json", (json.dumps(to_builtin(summary), indent=2) + "\n").encode())
    atomic_write(out / "report.md", markdown_report(summary).encode())
    return summary


def _recorded(out: Path, config: dict, result) -> dict | None:
    """``tuned.json`` of ``out`` when it records ``result`` (a rerun of a finished run: same configuration, same
    measured time and counts) and its figures are there; else None."""
    try:
        summary = json.loads((out / "tuned.json").read_text())
    except (OSError, ValueError):
        return None
    same = isinstance(summary, dict) and summary.get("config") == json.loads(json.dumps(to_builtin(config))) and all(
        summary.get(key) == value for key, value in
        (("seconds_tune", result.seconds), ("evaluations", result.evaluations), ("rollouts", result.rollouts))
    )  # fmt: skip
    return summary if same and all((out / name).exists() for name in summary.get("figures", [])) else None


def _tuned(problem, config: dict, result) -> dict:
    """The tuning's part of the summary."""
    return {
        "problem": config["problem"],
        "config": config,
        "stopped": result.stopped,
        "converged": result.converged,
        "evaluations": result.evaluations,
        "rollouts": result.rollouts,
        "seconds_tune": result.seconds,
        "compile_seconds_tune": result.compile_seconds,
        "train_objective": {"tuned": result.objective},
        "train_diverged": {"tuned": result.diverged},
        "starts": [
            {"objective": r.objective, "diverged": r.diverged, "stopped": r.stopped, "evaluations": r.evaluations}
            for r in result.starts
        ],  # fmt: skip
    }


def _baselines(problem, settings, config: dict, result, summary: dict, progress: bool):
    """``(search, designs)``: the random search (None without it) and the designs to score (hand-set, tuned, the
    search's best at equal rollouts and, with ``baseline.equal_time``, at equal time); the training objectives go
    into ``summary``."""
    designs = {"hand-set": problem.theta0, "tuned": result.theta}
    search, equal_rollouts = None, max(1, result.rollouts // problem.batch_size(problem.train))
    if config["baseline"]["random_search"]:
        equal_time = config["baseline"]["equal_time"]
        search = random_search(problem, settings, equal_rollouts, seconds=result.seconds if equal_time else 0.0,
                               seed=config["seed"], progress=progress)  # fmt: skip
        summary["random_search"] = {
            "spread": config["baseline"]["spread"],
            "tuned_position_in_box": _box_position(result.theta, problem.search_box),
            "candidates": len(search.candidates),
            "failed_candidates": int(np.sum(~np.isfinite(search.objectives))),
        }
        budgets = {"equal rollouts": equal_rollouts}
        if equal_time:
            budgets["equal time"] = search.within(result.seconds)
        for name, count in budgets.items():
            theta, objective, diverged = search.best(count)
            designs[f"random search, {name}"] = theta
            summary["random_search"][name] = {
                "candidates": count,
                "rollouts": count * search.rollouts_per_candidate,
                "seconds": float(search.elapsed[count - 1]),
                "train_objective": objective,
                "train_diverged": diverged,
            }
    if search is None:
        hand = batch_objective(problem, settings)({k: np.asarray(v)[None] for k, v in problem.theta0.items()})
    else:
        hand = search.objectives, search.diverged  # theta0 is the search's first candidate
    summary["train_objective"]["hand-set"], summary["train_diverged"]["hand-set"] = float(hand[0][0]), int(hand[1][0])
    return search, designs


# --------------------------------------------------------------------------------------------
# The report


def _cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool | np.bool_ | str):
        return str(value).lower() if not isinstance(value, str) else value
    if isinstance(value, int | np.integer):
        return f"{int(value):,}".replace(",", " ")
    return f"{value:.4g}"


def _table(header: list[str], rows: list[list]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header),
            *("| " + " | ".join(map(_cell, row)) + " |" for row in rows), ""]  # fmt: skip


def markdown_report(summary: dict) -> str:
    """``report.md`` of a finished tune from its ``summary`` (``tuned.json``'s content): the held-out results of
    every design, the run (its stopping, starts and time split into compiling and computing), the random-search
    baseline at equal rollouts and (``baseline.equal_time``) at equal time, the settings and the figures."""
    config, held = summary["config"], summary["heldout"]
    plants = config.get("plants", {})  # a problem without plant counts (noise seeds, vehicles) names them itself
    counts = ""
    if {"heldout", "train"} <= set(plants):
        counts = f" Held-out: {plants['heldout']}, training: {plants['train']}."
    lines = [f"# Tuning report: {summary['problem']}", "",
             f"Objective: the {config['optimizer']['objective']} of the per-plant losses on held-out plants, never "
             f"used in training.{counts}", "", "## Held-out plants", ""]  # fmt: skip
    rows = []
    for name, s in held.items():
        change = s["reduction_vs_hand_set"]
        change = None if change is None or name == "hand-set" else f"{-100 * change:+.1f} %"
        rows.append([name, s["objective"], change, f"{100 * s['finite_fraction']:.0f} %", s["p50"], s["p90"], s["max"]])
    lines += _table(["design", "objective", "vs hand-set", "finite plants", "median loss", "90 % loss", "worst loss"],
                    rows)  # fmt: skip
    compile_s = summary["compile_seconds_tune"]
    lines += ["## The run", "",
              f"Stopped: {summary['stopped']}{'' if summary['converged'] else ' (not converged)'} after "
              f"{summary['evaluations']} gradient evaluations and {_cell(summary['rollouts'])} rollouts; "
              f"{summary['seconds_tune']:.1f} s of tuning ({compile_s:.1f} s compiling, "
              f"{summary['seconds_tune'] - compile_s:.1f} s computing, screening included). Training objective: "
              f"hand-set {_cell(summary['train_objective']['hand-set'])}, tuned "
              f"{_cell(summary['train_objective']['tuned'])}.", ""]  # fmt: skip
    lines += _table(["start", "training objective", "diverged plants", "evaluations", "stopped"],
                    [[i, r["objective"], r["diverged"], r["evaluations"], r["stopped"]]
                     for i, r in enumerate(summary["starts"])])  # fmt: skip
    search = summary.get("random_search")
    if search:
        lines += ["## Baseline: random search in the same box", "",
                  f"{search['candidates']} candidates drawn in the search box (spread {search['spread']}); the best "
                  f"at {' and at '.join(b for b in ('equal rollouts', 'equal time') if b in search)}, scored on the "
                  "held-out plants above.", ""]  # fmt: skip
        lines += _table(["budget", "candidates", "rollouts", "seconds", "training objective"],
                        [[name, b["candidates"], b["rollouts"], b["seconds"], b["train_objective"]]
                         for name, b in search.items() if isinstance(b, dict) and "rollouts" in b])  # fmt: skip
    lines += _parameter_table(summary)
    settings = (f"- `{key} = {json.dumps(value)}`" for key, value in config["optimizer"].items())
    figures = (f"![{name}]({name})" for name in summary["figures"])
    lines += ["## Settings (`[optimizer]`)", "", *settings, "", "## Figures", "", *figures, ""]
    return "\n".join(lines)


def _parameter_table(summary: dict) -> list[str]:
    """The tuned parameters by name: hand-set and tuned unconstrained values, and the factor of a log entry."""
    labels, theta = summary.get("parameter_labels"), summary.get("theta", {})
    if not labels or not {"hand-set", "tuned"} <= set(theta):
        return []
    rows = []
    for name, entry in labels.items():
        hand, tuned = (np.ravel(np.asarray(theta[k][name], float)) for k in ("hand-set", "tuned"))
        for label, a, b in zip(entry, hand, tuned, strict=True):
            if label != "unused":
                rows.append([label, a, b, f"x {np.exp(b - a):.3g}" if label.startswith("log") else f"{b - a:+.3g}"])
    return ["## Parameters", "", "Unconstrained values (log entries: natural logs; the change of a log entry is its "
            "factor).", "", *_table(["parameter", "hand-set", "tuned", "change"], rows)]  # fmt: skip


# --------------------------------------------------------------------------------------------
# Figures


def _unit(unit: str) -> str:
    return f", {unit}" if unit else ""


def _plot_loss_curves(result, search, scores, objective: str, unit: str, out: Path) -> str:
    """The training objective against the rollouts per training plant spent (the screening's candidates, then each
    step of every start), beside the random search's; the held-out plants' sorted losses of each design."""
    from matplotlib.ticker import MaxNLocator

    plt = pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    history = result.history
    ev = result.screened + len(result.starts) * np.array([h["evaluation"] for h in history], int)
    val = np.array([np.nan if h["objective"] is None else h["objective"] for h in history], float)
    ok = np.array([h["accepted"] for h in history], bool)  # empty when a time budget ended the run before a step
    ax.plot(ev[ok], val[ok], "o-", ms=3, label="gradient: objective (best start)")
    if np.any(~ok):
        ax.plot(ev[~ok], np.where(np.isfinite(val[~ok]), val[~ok], np.nanmax(val)), "rx", label="rejected step")
    ax.plot(ev[ok], np.minimum.accumulate(val[ok]), "C0-", lw=5, alpha=0.25, drawstyle="steps-post", zorder=1,
            label="gradient: best so far")  # fmt: skip
    if search is not None:
        best = np.minimum.accumulate(search.objectives)
        ax.plot(np.arange(1, best.size + 1), best, "C1-", label="random search: best so far")
        spent = ev[-1] if ev.size else result.screened
        ax.axvline(spent, color="k", lw=0.6, ls=":", label="the gradient run's rollouts (equal-rollouts budget)")
        ax.set_xscale("log")  # the search runs for as long as the tuning took: often many more rollouts
    else:
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set(xlabel="rollouts per training plant (screening, CMA-ES, then gradient steps)",
           ylabel=f"training objective\n({objective} of the per-plant losses{_unit(unit)})", yscale="log",
           title="Training objective")  # fmt: skip
    ax.legend(fontsize=8)
    for name, s in scores.items():
        losses = np.sort(s["losses"])
        bx.plot(np.linspace(0, 1, losses.size), losses, label=f"{name} (objective {s['objective']:.3g})")
    bx.set(xlabel="fraction of held-out plants", ylabel=f"per-plant loss ({unit})" if unit else "per-plant loss",
           yscale="log",
           title="Held-out plants, sorted losses")  # fmt: skip
    bx.legend(fontsize=8)
    return save_figure(fig, out, "loss_curves")


def _free_components(problem) -> tuple[list[str], np.ndarray]:
    """``(labels, mask)`` over ``theta``'s flattened components: their labels, and which the tuning may move (not
    fixed by the search box, not an unused entry)."""
    labels = [label for entry in problem.component_labels().values() for label in entry]
    free = np.array([label != "unused" for label in labels])
    if problem.search_box is not None:
        low, high = (np.concatenate([np.ravel(problem.search_box[k][i]) for k in problem.theta0]) for i in (0, 1))
        free &= high > low
    return labels, free


def _flat(theta: dict, names) -> np.ndarray:
    return np.concatenate([np.ravel(np.asarray(theta[k], float)) for k in names])


def _plot_parameters(problem, history, tuned: dict, out: Path, shown: int = 6) -> str:
    """Each free parameter's change from the hand-set design: the tuned design's (bars, one per parameter, named
    by :meth:`~jaxobs.tuning.TuningProblem.component_labels`), and the best start's path over its evaluations for
    the ``shown`` that changed most."""
    from matplotlib.ticker import MaxNLocator

    names, (labels, free) = list(problem.theta0), _free_components(problem)
    hand = _flat(problem.theta0, names)
    change = (_flat(tuned, names) - hand)[free]
    paths = np.array([_flat(h["theta"], names) - hand for h in history])[:, free]
    labels = [label for label, f in zip(labels, free, strict=True) if f]
    plt = pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, max(3.8, 0.22 * len(labels) + 1.5)), layout="constrained",
                                 width_ratios=(1, 1.3))  # fmt: skip
    rows = np.arange(len(labels))[::-1]
    ax.barh(rows, change, color=np.where(change >= 0, "C3", "C0"))
    ax.set_yticks(rows, labels, fontsize=7 if len(labels) > 20 else 9)
    ax.axvline(0.0, color="k", lw=0.6)
    ax.set(xlabel="tuned minus hand-set, unconstrained (log entries: ln of the factor)",
           title=f"Change of the {len(labels)} tuned parameters")  # fmt: skip
    ev = [h["evaluation"] for h in history]
    for i in np.argsort(-np.abs(change))[:shown]:
        bx.plot(ev, paths[:, i], "o-", ms=2.5, lw=1, label=labels[i])
    bx.axhline(0.0, color="k", lw=0.6, ls=":", label="hand-set")
    bx.set(xlabel="gradient evaluation of the best start", ylabel="change from hand-set (unconstrained)",
           title=f"Path of the {min(shown, len(labels))} that changed most")  # fmt: skip
    bx.xaxis.set_major_locator(MaxNLocator(integer=True))
    bx.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return save_figure(fig, out, "parameters")


def _plot_responses(problem, designs: dict, hand_losses, out: Path) -> str:
    """The held-out plants with the lowest, median and highest hand-set loss (columns), each tracked output (rows):
    each design's response, the desired one and, where the problem gives it, the set-point."""
    import textwrap

    order = np.argsort(np.where(np.isfinite(hand_losses), hand_losses, np.inf))
    picks = np.asarray([order[0], order[order.size // 2], order[-1]])
    plants = jax.tree.map(lambda x: x[picks], problem.heldout)
    runs = {name: problem.responses(theta, plants) for name, theta in designs.items()}
    r = next(iter(runs.values()))
    desired = np.asarray(r["desired"]).reshape(len(r["t"]), -1)
    k = desired.shape[1]
    ylabels = [r["ylabel"]] * k if isinstance(r["ylabel"], str) else list(r["ylabel"])
    setpoint = None if r.get("setpoint") is None else np.broadcast_to(r["setpoint"], (k,))
    plt = pyplot()
    fig, axes = plt.subplots(k, picks.size, figsize=(4.6 * picks.size, 2.9 * k + 0.8), sharex=True, sharey="row",
                             squeeze=False, layout="constrained")  # fmt: skip
    for name, run in runs.items():
        output = np.asarray(run["output"]).reshape(picks.size, len(r["t"]), k)
        for (j, i), ax in np.ndenumerate(axes):
            ax.plot(r["t"], output[i, :, j], lw=1, label=name)
    for (j, i), ax in np.ndenumerate(axes):
        ax.plot(r["t"], desired[:, j], "k--", lw=1, label="desired")
        if setpoint is not None and np.isfinite(setpoint[j]):
            ax.axhline(setpoint[j], color="0.5", lw=0.8, ls=":", label="set-point")
        if j == 0:
            ax.set_title("\n".join(textwrap.wrap(f"held-out: {r['labels'][i]}", 48)), fontsize=9)
    for j, label in enumerate(ylabels):
        axes[j, 0].set_ylabel(label)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    handles, labels = max((ax.get_legend_handles_labels() for ax in axes.flat), key=lambda hl: len(hl[1]))
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8)
    return save_figure(fig, out, "responses")
