"""A report of any finished sweep from its rows alone: what breaks the design, and what the runs measured.

:func:`write_report` reads the rows of the sweep in ``out_dir`` (:func:`jaxobs.sweep.load_results`) and writes
``summary.json``, ``report.md`` and two figures: the stable fraction against each swept parameter (one panel each)
and the distributions of the metrics over the stable configurations. It uses the columns a robustness evaluation
writes (:func:`jaxobs.stability.robustness_metrics`: ``metric.valid``, ``metric.stable``, the margins) where they
exist, and reads the rest by their types: a parameter is *swept* when it takes several values (integer columns
with many values, such as seeds and design indices, are listed but not binned). :func:`summarize` is the
summary without the files; :func:`finish_report` writes any sweep report's files with the time the runs took
(:func:`jaxobs.sweep.run_history`), the shipped scenarios' included.

No margin of an invalid or unstable configuration enters a statistic: the metric distributions are over the
configurations that are valid and stable (valid ones where there is no ``stable`` column); a NaN is left out, an
infinite value counted apart (on a stable loop: no crossover of that kind, nothing destabilises it that way).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from jaxobs._output import pyplot, save_figure, to_builtin
from jaxobs.sweep import load_results, read_manifest, run_history

__all__ = ["METRIC_UNITS", "MARGIN_NOTES", "quantiles", "summarize", "timing", "write_report", "finish_report"]

METRIC_UNITS = {
    "gain_margin": "factor",
    "gain_margin_lower": "factor",
    "gain_margin_upper": "factor",
    "phase_margin": "deg",
    "delay_margin": "s",
    "stability_margin": "distance to -1",
    "spectral_radius": "closed loop",
}
"""Units of the metrics :func:`jaxobs.stability.robustness_metrics` writes, shown on the axes and in the tables."""

MARGIN_NOTES = (
    "Margins are those of the loop cut at the plant input (jaxobs.stability.loop_transfer), over the stable "
    "configurations only. A gain margin is the factor on the loop gain that makes the loop unstable: "
    "gain_margin_upper (above 1) the increase, gain_margin_lower (below 1) the reduction; a gain_margin_lower "
    "above 0 marks a conditionally stable loop, which a *smaller* gain destabilises. gain_margin is "
    "python-control's: whichever of the two is closer to 1, so a value below 1 is a lower margin. An infinite "
    "margin on a stable loop means no crossover of its kind (no gain increase, phase lag or delay destabilises it). "
    "The phase margin is that of the gain crossover nearest to -1 in phase; with several crossovers (a resonance) "
    "it can be negative on a stable loop, and the delay margin, which counts every crossover, is the one to read."
)
"""What the margins mean, as the reports say it."""

ZERO_MEANS = {"gain_margin_lower": "not cond. stable"}
"""Metrics whose zero is a category of its own (drawn apart from the histogram)."""

MAX_CATEGORIES = 12  # a parameter with at most this many values is shown value by value
MAX_SEED_VALUES = 20  # an integer parameter with more values than this (a seed, an index) is not binned


def quantiles(values) -> dict:
    """``{"count", "infinite", "p05", "median", "p95"}`` of ``values``: NaN left out, infinite values counted apart
    (``count`` is the number of finite ones, whose quantiles are given; none: ``count`` 0 only)."""
    values = np.asarray(values, float)
    values = values[~np.isnan(values)]
    finite = values[np.isfinite(values)]
    out = {"count": int(finite.size), "infinite": int(values.size - finite.size)}
    if finite.size:
        q = np.quantile(finite, [0.05, 0.5, 0.95])
        out |= {"p05": float(q[0]), "median": float(q[1]), "p95": float(q[2])}
    return out


def _short(column: str) -> str:
    return column.split(".", 1)[1] if "." in column else column


def _masks(rows: dict) -> tuple[np.ndarray, np.ndarray | None]:
    """``(valid, stable)`` row masks: ``metric.valid`` (all valid without it) and ``metric.stable`` (None without
    it), an invalid configuration counted as not stable."""
    n = rows["index"].size
    valid = rows["metric.valid"].astype(bool) if "metric.valid" in rows else np.ones(n, bool)
    stable = rows["metric.stable"].astype(bool) & valid if "metric.stable" in rows else None
    return valid, stable


def _spread_in_log(values: np.ndarray) -> bool:
    """Whether positive ``values`` are spread evenly in log rather than linearly (log-uniform, a log grid): their
    median sits nearer the middle of the range in log."""
    low, median, high = np.quantile(values.astype(float), [0.0, 0.5, 1.0])
    in_log = (np.log(median) - np.log(low)) / (np.log(high) - np.log(low))
    return abs(in_log - 0.5) < abs((median - low) / (high - low) - 0.5)


def _parameter_bins(values: np.ndarray, bins: int) -> dict | None:
    """How a parameter column is binned: ``{"kind", "log", "edges" or "values"}``, or None when it is not swept
    (a single value) or not binned (an integer with more than :data:`MAX_SEED_VALUES` values)."""
    distinct = np.unique(values[np.isfinite(values)] if values.dtype.kind == "f" else values)
    if distinct.size < 2 or (values.dtype.kind in "iu" and distinct.size > MAX_SEED_VALUES):
        return None
    log = bool(distinct[0] > 0 and distinct[-1] / distinct[0] >= 10.0 and _spread_in_log(values))
    if distinct.size <= MAX_CATEGORIES or values.dtype.kind in "biu":
        return {"kind": "values", "log": log, "values": distinct}
    low, high = (np.log(distinct[0]), np.log(distinct[-1])) if log else (distinct[0], distinct[-1])
    edges = np.linspace(low, high, bins + 1)
    return {"kind": "bins", "log": log, "edges": np.exp(edges) if log else edges}


def _binned(values: np.ndarray, binning: dict, valid: np.ndarray, stable: np.ndarray | None) -> list[dict]:
    """Per bin (or value) of ``values``: its range, configurations, stable (None without ``stable``) and invalid
    fractions."""
    if binning["kind"] == "values":
        groups = [(v, v, values == v) for v in binning["values"]]
    else:
        edges = binning["edges"]
        which = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, edges.size - 2)
        groups = [(edges[i], edges[i + 1], (which == i) & np.isfinite(values)) for i in range(edges.size - 1)]
    out = []
    for low, high, sel in groups:
        count = int(sel.sum())
        out.append({
            "low": float(low), "high": float(high), "configs": count,
            "stable_fraction": float(stable[sel].mean()) if count and stable is not None else None,
            "invalid_fraction": float((~valid[sel]).mean()) if count else None,
        })  # fmt: skip
    return out


def _worst(rows: dict, worst_by, valid: np.ndarray, count: int) -> tuple[str, list[dict]]:
    """``(what orders them, the ``count`` worst valid configurations with every parameter and metric)``."""
    if worst_by is None:
        floats = [c for c in rows if c.startswith("metric.") and rows[c].dtype.kind == "f"]
        worst_by = next((c for c in ("metric.spectral_radius",) if c in rows), floats[0] if floats else None)
    if worst_by is None:
        return "", []
    column, largest = (worst_by, True) if isinstance(worst_by, str) else (worst_by[0], worst_by[1] == "max")
    if column not in rows:
        raise ValueError(f"worst_by: no column {column!r} (columns: {', '.join(rows)})")
    values = np.where(valid & ~np.isnan(rows[column].astype(float)), rows[column], np.nan).astype(float)
    order = np.argsort(-values if largest else values, kind="stable")
    picked = [i for i in order if not np.isnan(values[i])][:count]
    cases = [{name: rows[name][i].item() for name in rows} for i in picked]
    return f"{column} ({'largest' if largest else 'smallest'} first)", cases


def summarize(rows: dict, *, worst_by=None, worst_count: int = 10, bins: int = 10) -> dict:
    """The summary :func:`write_report` writes, from the rows ``{column: array}`` of a sweep.

    Args:
      rows: the columns (:func:`jaxobs.sweep.load_results`).
      worst_by: the column that orders the worst configurations, largest first, or ``(column, "min")`` for
        smallest first; default ``metric.spectral_radius`` (the least stable first), else the first float metric.
      worst_count: how many worst configurations to list.  bins: bins per continuous parameter.

    Returns ``{"num_configs", "invalid", "stable", "stable_fraction", "stable_fraction_of_valid", "parameters",
    "not_binned", "metrics", "worst_by", "worst", "invalid_examples"}`` (``stable`` and its fractions None without
    a ``metric.stable`` column); ``parameters[name]`` lists per bin its range, configurations, stable and invalid
    fractions; ``metrics[name]`` the :func:`quantiles` over the valid, stable configurations.
    """
    valid, stable = _masks(rows)
    n = int(valid.size)
    parameters, not_binned = {}, []
    for column in (c for c in rows if c.startswith("param.")):
        binning = _parameter_bins(rows[column], bins)
        if binning is None:
            not_binned += [_short(column)] if np.unique(rows[column]).size > 1 else []
            continue
        parameters[_short(column)] = {"log": binning["log"], "discrete": binning["kind"] == "values",
                                      "bins": _binned(rows[column], binning, valid, stable)}  # fmt: skip
    kept = valid if stable is None else stable
    metrics = {
        _short(c): quantiles(rows[c][valid if c == "metric.spectral_radius" else kept])
        for c in rows if c.startswith("metric.") and rows[c].dtype.kind == "f"
    }  # fmt: skip
    worst_by, worst = _worst(rows, worst_by, valid, worst_count)
    invalid = np.flatnonzero(~valid)[:worst_count]
    return {
        "num_configs": n,
        "invalid": int(n - valid.sum()),
        "stable": None if stable is None else int(stable.sum()),
        "stable_fraction": None if stable is None else float(stable.mean()),
        "stable_fraction_of_valid": None if stable is None or not valid.any() else float(stable[valid].mean()),
        "parameters": parameters,
        "not_binned": not_binned,
        "metrics": metrics,
        "worst_by": worst_by,
        "worst": worst,
        "invalid_examples": [{name: rows[name][i].item() for name in rows if not name.startswith("metric.")}
                             for i in invalid],
    }  # fmt: skip


def _label(name: str, units: dict) -> str:
    return f"{name} ({units[name]})" if units.get(name) else name


def _grid(plt, count: int, width: float = 4.2, height: float = 3.2):
    columns = min(count, 3)
    rows = math.ceil(count / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(width * columns, height * rows + 0.6), squeeze=False,
                             layout="constrained")  # fmt: skip
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    return fig, axes.flat


def _plot_stable_fraction(summary: dict, units: dict, out_dir: Path) -> str | None:
    """One panel per swept parameter: the stable fraction per bin (a step over each bin, a marker per value of a
    discrete parameter), the invalid fraction where any configuration is invalid, the overall stable fraction."""
    if summary["stable"] is None or not summary["parameters"]:
        return None
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator

    fig, axes = _grid(plt, len(summary["parameters"]))
    for ax, (name, parameter) in zip(axes, summary["parameters"].items(), strict=False):
        cells = parameter["bins"]
        series = [("stable", "stable_fraction", "C0", "-")]
        series += [("invalid", "invalid_fraction", "0.45", "--")] if summary["invalid"] else []
        for label, key, colour, style in series:
            values = np.array([np.nan if c[key] is None else c[key] for c in cells])
            if parameter["discrete"]:
                ax.plot([c["low"] for c in cells], values, "o" + style, color=colour, label=label)
            else:
                edges = [cells[0]["low"]] + [c["high"] for c in cells]
                ax.stairs(values, edges, baseline=None, color=colour, linestyle=style, lw=1.8, label=label)
        ax.axhline(summary["stable_fraction"], color="k", lw=0.8, ls=":", label="stable, all configurations")
        if parameter["log"]:
            ax.set_xscale("log")
        elif parameter["discrete"] and all(float(c["low"]).is_integer() for c in cells):
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set(xlabel=_label(name, units), ylim=(-0.03, 1.03), title=name)
        ax.set_ylabel("fraction of the configurations")
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle(f"Stable fraction against each swept parameter ({summary['num_configs']} configurations)")
    return save_figure(fig, out_dir, "stable_fraction")


def _plot_metrics(rows: dict, units: dict, out_dir: Path) -> str | None:
    """Histograms of the float metrics over the valid, stable configurations (the spectral radius over the valid
    ones, with the stability bound 1 marked); log axes for positive values spanning over two decades."""
    valid, stable = _masks(rows)
    kept = valid if stable is None else stable
    columns = [c for c in rows if c.startswith("metric.") and rows[c].dtype.kind == "f"]
    if not columns:
        return None
    plt = pyplot()
    fig, axes = _grid(plt, len(columns))
    for ax, column in zip(axes, columns, strict=False):
        name = _short(column)
        values = rows[column][valid if name == "spectral_radius" else kept].astype(float)
        values = values[~np.isnan(values)]
        zero = f", {int(np.sum(values == 0))} zero ({ZERO_MEANS[name]}, not drawn)" if name in ZERO_MEANS else ""
        values = values[values != 0] if zero else values
        finite = values[np.isfinite(values)]
        log = finite.size > 1 and finite.min() > 0 and finite.max() / finite.min() > 100
        if finite.size:
            bins = np.geomspace(finite.min(), finite.max() * (1 + 1e-9), 41) if log else 40
            ax.hist(finite, bins=bins, color="C0" if name != "spectral_radius" else "C1")
        else:
            ax.text(0.5, 0.5, "no value to draw", ha="center", va="center", transform=ax.transAxes, color="0.4")
            ax.set_xticks([])
            ax.set_yticks([])
        if log:
            ax.set_xscale("log")
        if name == "spectral_radius":
            ax.axvline(1.0, color="k", lw=0.8, ls="--", label="stability bound")
            ax.legend(fontsize=8)
        infinite = f", {values.size - finite.size} infinite (not drawn)" if values.size > finite.size else ""
        ax.set(xlabel=_label(name, units), title=f"{name}\n{finite.size} drawn{zero}{infinite}")
        ax.title.set_fontsize(9)
        ax.set_ylabel("configurations")
    over = "valid" if stable is None else "stable"
    fig.suptitle(f"Metrics over the {int(kept.sum())} {over} configurations (spectral radius: over the "
                 f"{int(valid.sum())} valid ones)")  # fmt: skip
    return save_figure(fig, out_dir, "metrics")


def _number(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool | np.bool_):
        return str(bool(value)).lower()
    if isinstance(value, int | np.integer):
        return str(int(value))
    return f"{value:.4g}"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in rows)]


def _parameter_lines(summary: dict, units: dict) -> list[str]:
    rows = []
    for name, parameter in summary["parameters"].items():
        cells = parameter["bins"]
        fractions = " ".join("-" if c["stable_fraction"] is None else f"{c['stable_fraction']:.2f}" for c in cells)
        scale = "values" if parameter["discrete"] else f"{len(cells)} {'log' if parameter['log'] else 'equal'} bins"
        span = f"{_number(cells[0]['low'])} to {_number(cells[-1]['high'])}"
        counts = [c["configs"] for c in cells]
        rows.append([_label(name, units), span, scale, f"{min(counts)} to {max(counts)}", fractions])
    lines = ["## Stable fraction against each swept parameter", ""]
    header = ["parameter", "range", "binned in", "configurations per bin", "stable fraction per bin, low to high"]
    lines += _table(header, rows)
    if summary["not_binned"]:
        lines += ["", f"Not binned (integers with many values, e.g. seeds): {', '.join(summary['not_binned'])}."]
    return lines


def _metric_lines(summary: dict, units: dict) -> list[str]:
    over = "valid" if summary["stable"] is None else "valid and stable"
    rows = [[name, units.get(name, ""), str(q["count"]), *(_number(q.get(k)) for k in ("p05", "median", "p95")),
             str(q["infinite"])] for name, q in summary["metrics"].items()]  # fmt: skip
    lines = [f"## Metrics over the {over} configurations (spectral radius: over the valid ones)", ""]
    lines += _table(["metric", "unit", "finite", "p05", "median", "p95", "infinite"], rows)
    if any(name.endswith("_margin") or "gain_margin" in name for name in summary["metrics"]):
        lines += ["", MARGIN_NOTES]
    return lines


def _case_lines(title: str, cases: list[dict], columns: list[str]) -> list[str]:
    if not cases:
        return []
    rows = [[_number(case[c]) for c in columns] for case in cases]
    return [title, "", *_table([_short(c) for c in columns], rows)]


def _markdown(summary: dict, units: dict, title: str) -> str:
    n, invalid, stable = summary["num_configs"], summary["invalid"], summary["stable"]
    head = f"{n} configurations: {invalid} invalid"
    if stable is not None:
        of_valid = "-" if summary["stable_fraction_of_valid"] is None else f"{summary['stable_fraction_of_valid']:.3f}"
        head += f", {stable} stable ({summary['stable_fraction']:.3f} of all, {of_valid} of the valid ones)"
    lines = [f"# {title}", "", head + ".", ""]
    if invalid:
        lines += ["Invalid: the evaluation's `valid` column is false (a non-finite plant, a dead time beyond the "
                  "model's slots, a solver that did not converge); such a configuration has NaN margins and "
                  "enters no statistic.", ""]  # fmt: skip
    if summary["parameters"]:
        lines += [*_parameter_lines(summary, units), ""]
    if summary["metrics"]:
        lines += [*_metric_lines(summary, units), ""]
    worst = summary["worst"]
    if worst:
        params = [c for c in worst[0] if c.startswith("param.")]
        order = summary["worst_by"].split(" ")[0]
        metrics = [c for c in ("metric.valid", "metric.stable", "metric.spectral_radius", order) if c in worst[0]]
        columns = ["index", *params, *dict.fromkeys(metrics)]
        lines += [*_case_lines(f"## Worst configurations: by {summary['worst_by']}", worst, columns), ""]
    examples = summary["invalid_examples"]
    if examples:
        lines += [*_case_lines(f"## Invalid configurations (the first {len(examples)})", examples, list(examples[0])),
                  ""]  # fmt: skip
    return "\n".join(lines)


def timing(out_dir, result=None) -> dict:
    """What the runs of the sweep in ``out_dir`` measured (:func:`jaxobs.sweep.run_history`: wall time, compilation,
    computation, configurations computed and their rate, summed over the runs that computed chunks) and, given
    this call's :class:`jaxobs.sweep.SweepResult` ``result``, the chunks it computed and reused."""
    history = run_history(out_dir)
    out = {"seconds": history.seconds, "compile_seconds": history.compile_seconds,
           "compute_seconds": history.compute_seconds, "configs_computed": history.configs_computed,
           "configs_per_second": history.configs_per_second, "runs": history.runs}  # fmt: skip
    if result is not None:
        out |= {"chunks_computed": result.chunks_computed, "chunks_reused": result.chunks_reused}
    return out


def _footer(summary: dict) -> str:
    """The end of every sweep report: the time its runs took and the figures."""
    runs = summary["runs"]
    lines = [f"Run time {summary['seconds']:.1f} s in {runs} run{'s' if runs != 1 else ''}, "
             f"{summary['compile_seconds']:.1f} s of it compiling the sweep step"]  # fmt: skip
    if summary["configs_computed"]:
        lines[0] += (f"; {summary['configs_per_second']:.3g} configurations/s over the "
                     f"{summary['configs_computed']} configurations computed (compilation excluded)")  # fmt: skip
    lines[0] += "."  # what this call computed or reused is not said: a rerun of a finished sweep leaves the report
    if summary.get("invalid") is not None:
        lines += ["", f"Invalid configurations: {summary['invalid']} of {summary['num_configs']}."]
    return "\n".join([*lines, "", *(f"![{f}]({f})" for f in summary["figures"])]) + "\n"


def finish_report(out_dir, summary: dict, markdown, figures: list[str], result=None) -> dict:
    """Write a sweep report's files into ``out_dir``: ``summary.json`` (``summary`` with :func:`timing` and the
    ``figures``' names) and ``report.md`` (``markdown(summary)``, then the run time, the invalid count where the
    summary has one, and the figures). Returns the summary written."""
    out_dir = Path(out_dir)
    summary = {**summary, **timing(out_dir, result), "figures": list(figures)}
    (out_dir / "summary.json").write_text(json.dumps(to_builtin(summary), indent=2, allow_nan=True) + "\n")
    (out_dir / "report.md").write_text(markdown(summary).rstrip("\n") + "\n\n" + _footer(summary))
    return summary


def write_report(out_dir, *, title: str | None = None, units: dict | None = None, worst_by=None,
                 worst_count: int = 10, bins: int = 10, result=None) -> dict:  # fmt: skip
    """Write ``summary.json``, ``report.md``, ``stable_fraction.png`` and ``metrics.png`` for the finished sweep
    in ``out_dir`` from its rows alone (any sweep: a ``stable`` or ``valid`` column is used where there is one).

    Args:
      out_dir: the sweep's directory (:func:`jaxobs.sweep.run_sweep`).
      title: the report's heading (default: "Sweep in OUT_DIR").
      units: ``{parameter or metric name: unit}`` for the axes and tables (the margins' are known).
      worst_by, worst_count, bins: as :func:`summarize`.
      result: this call's :class:`jaxobs.sweep.SweepResult`, if the sweep ran in it (the report says what it
        computed).

    Returns the summary written (:func:`summarize`, the config stored in the manifest, :func:`timing` and the
    figures' names). Raises :class:`jaxobs.sweep.SweepError` for an incomplete sweep.

    Example:
      >>> summary = write_report("out/my-sweep")                      # doctest: +SKIP
      >>> summary["stable_fraction"], summary["invalid"]              # doctest: +SKIP
    """
    out_dir = Path(out_dir)
    rows = load_results(out_dir)
    summary = summarize(rows, worst_by=worst_by, worst_count=worst_count, bins=bins)
    summary["config"] = read_manifest(out_dir)["config"]
    units = {**METRIC_UNITS, **(units or {})}
    figures = [f for f in (_plot_stable_fraction(summary, units, out_dir), _plot_metrics(rows, units, out_dir)) if f]
    title = title or f"Sweep in {out_dir}"
    return finish_report(out_dir, summary, lambda s: _markdown(s, units, title), figures, result)
