"""Writing reproduction results: JSON with every reported number, PNG figures (the helpers of
:mod:`jaxobs._output`, which the paper modules import from here)."""

from __future__ import annotations

import json
from pathlib import Path

from jaxobs._output import plain_ticks, pyplot, save_figure, to_builtin
from jaxobs.sweep_report import finish_report

__all__ = ["plain_ticks", "pyplot", "save_figure", "to_builtin", "write_reproduction", "write_sweep_report"]


def write_reproduction(out_dir: Path, name: str, summary: dict, figures: list[str]) -> dict:
    """Write ``out_dir/name.json`` (the summary plus the figure names) and return the summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = {**summary, "figures": figures}
    (out_dir / f"{name}.json").write_text(json.dumps(to_builtin(summary), indent=2) + "\n")
    return summary


def write_sweep_report(out_dir: Path, summary: dict, config: dict, result, figures: list[str], markdown) -> dict:
    """Finish the ``summary`` of a sweep scenario with its ``config`` and write it with
    :func:`jaxobs.sweep_report.finish_report`: ``out_dir/summary.json`` (with the time the sweep's runs took and,
    given this call's :class:`jaxobs.sweep.SweepResult` ``result``, the chunks it computed) and ``out_dir/report.md``
    (``markdown(summary)``, then the run time and the ``figures``); returns it."""
    return finish_report(out_dir, {**summary, "config": config}, markdown, figures, result)
