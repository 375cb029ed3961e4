"""Writing a job's results: JSON-able summaries and PNG figures (matplotlib on its headless Agg backend, imported
only when a figure is drawn). Shared by the sweep report (:mod:`jaxobs.sweep_report`) and the paper layer."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["to_builtin", "pyplot", "plain_ticks", "save_figure"]


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
    """matplotlib.pyplot on the non-interactive Agg backend (jobs and reproductions run headless)."""
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
