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


def write_json(out_dir: Path, name: str, data: dict) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.json"
    path.write_text(json.dumps(to_builtin(data), indent=2, sort_keys=False) + "\n")
    return path


def figure_path(out_dir: Path, name: str) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    return out_dir / f"{name}.png"
