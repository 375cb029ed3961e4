"""Writing reproduction results: JSON with every reported number, PNG figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def to_builtin(value):
    """Convert arrays/NumPy scalars in a nested structure to JSON-serialisable Python objects."""
    if isinstance(value, dict):
        return {str(k): to_builtin(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_builtin(v) for v in value]
    if hasattr(value, "shape") or isinstance(value, np.generic):
        array = np.asarray(value)
        return array.item() if array.ndim == 0 else array.tolist()
    return value


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (reproductions run headless)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plain_ticks(fig) -> None:
    """Tick labels read as numbers: no offset (``1e-9 - 1.5`` above an axis) on linear axes; on log axes ``40``
    rather than ``4x10^1`` between 1e-3 and 1e4, ``9e-5`` rather than ``9x10^-5`` outside."""
    from matplotlib.ticker import LogFormatterSciNotation, ScalarFormatter

    class PlainLog(LogFormatterSciNotation):
        def __call__(self, x, pos=None):
            if not super().__call__(x, pos):
                return ""
            return f"{x:.4g}" if 1e-3 <= abs(x) < 1e4 else f"{x:.2g}".replace("e-0", "e-").replace("e+0", "e")

    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() == "log":
                axis.set_major_formatter(PlainLog())
                axis.set_minor_formatter(PlainLog(labelOnlyBase=False))
            elif isinstance(axis.get_major_formatter(), ScalarFormatter):
                axis.get_major_formatter().set_useOffset(False)


def save_figure(fig, out_dir: Path, name: str, dpi: int = 110) -> str:
    """Lay out, write ``out_dir/name.png`` (tick labels made plain by :func:`plain_ticks`) and close ``fig``;
    returns the file name."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.png"
    plain_ticks(fig)
    if fig.get_layout_engine() is None:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path.name


def write_reproduction(out_dir: Path, name: str, summary: dict, figures: list[str]) -> dict:
    """Write ``out_dir/name.json`` (the summary plus the figure names) and return the summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = {**summary, "figures": figures}
    (out_dir / f"{name}.json").write_text(json.dumps(to_builtin(summary), indent=2) + "\n")
    return summary


def write_sweep_report(out_dir: Path, summary: dict, config: dict, result, figures: list[str], markdown) -> dict:
    """Finish the ``summary`` of a sweep scenario and write it: the run's timing when the sweep ran in this call
    (``result``, a :class:`jaxobs.sweep.SweepResult`, else ``None``), the ``config`` and the ``figures``' names go
    in; ``out_dir/summary.json`` and ``out_dir/report.md`` (``markdown(summary)``, then the run time and the
    figures) are written; returns it."""
    if result is not None:
        summary["seconds"] = result.seconds
        summary["compile_seconds"] = result.compile_seconds
        summary["configs_per_second"] = result.configs_per_second
        summary["chunks_computed"] = result.chunks_computed
        summary["chunks_reused"] = result.chunks_reused
    summary["config"] = config
    summary["figures"] = figures
    (out_dir / "summary.json").write_text(json.dumps(to_builtin(summary), indent=2, allow_nan=True) + "\n")
    (out_dir / "report.md").write_text(markdown(summary).rstrip("\n") + "\n\n" + _report_footer(summary))
    return summary


def _report_footer(summary: dict) -> str:
    """The end every sweep report shares: this call's run time (when the sweep ran in it) and the figures."""
    lines = []
    if "seconds" in summary:
        lines += [
            f"Run time {summary['seconds']:.1f} s, {summary['compile_seconds']:.1f} s of it compiling the sweep step "
            f"({summary['configs_per_second']:.3g} configurations/s after it; {summary['chunks_computed']} chunks "
            f"computed, {summary['chunks_reused']} reused).",
            "",
        ]
    lines += [f"![{f}]({f})" for f in summary["figures"]]
    return "\n".join(lines) + "\n"
