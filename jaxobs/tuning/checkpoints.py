"""The tuner's checkpoint: a :class:`jaxobs.tuning.tuner.TunerState` as ``.npz`` arrays and a JSON ``meta`` record
(the starts' bookkeeping and histories), its fingerprint, and the checks of a file read back."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._resources import temporary_path
from jaxobs.tuning.problem import CheckpointError
from jaxobs.tuning.tuner import PHASES, STOPS, Lanes, TunerState

_META = {"iterations": int, "screened": int, "polished": int, "round": int, "phase": str, "seconds": float,
         "lanes": list, "fingerprint": str, "arrays": int}  # fmt: skip
_LANE = {"evaluations": int, "scale": float, "best_objective": float, "best_diverged": int, "diverged": int,
         "since_best": int, "rejections": int, "stopped": str, "history": list}  # fmt: skip
_TREES = ("start", "theta", "anchor", "update", "best", "opt", "search")


def fingerprint(theta0: dict, settings, tag: str, program: str, train) -> str:
    """What a checkpoint was written for: the settings (but ``steps``: more may continue a run), the optimiser's
    state structure, ``tag``, ``theta``'s shapes, the ``program`` of one step on one device (lowered text) and
    the training batch's values (an argument of it). An optimiser's hyperparameters are not visible in its state:
    ``tag`` names them (the TOML layer's tag does)."""
    shapes = {k: list(np.shape(v)) for k, v in theta0.items()}
    fixed = {
        f.name: getattr(settings, f.name) for f in dataclasses.fields(settings) if f.name not in ("steps", "optimizer")
    }
    strong = {k: jnp.asarray(v).astype(jnp.asarray(v).dtype) for k, v in theta0.items()}
    state = jax.eval_shape(settings.optimizer.init, strong)
    fixed["optimizer"] = f"{jax.tree.structure(state)} {[(x.shape, str(x.dtype)) for x in jax.tree.leaves(state)]}"
    text = json.dumps({"tag": tag, "settings": fixed, "theta": shapes, "jax": jax.__version__}, sort_keys=True)
    digest = hashlib.sha256((text + program).encode())
    for leaf in jax.tree.leaves(train):
        leaf = np.asarray(leaf)
        digest.update(f"{leaf.dtype}{leaf.shape}".encode() + np.ascontiguousarray(leaf).tobytes())
    return digest.hexdigest()[:16]


def split(state: TunerState, histories: list, seconds: float) -> tuple[dict, dict]:
    """``(trees, meta)`` of ``state`` (on the host): the arrays, and the scalars, the starts' bookkeeping (one record
    per start, with its ``histories`` entry) and the wall time so far."""
    trees = {name: getattr(state, name) for name in _TREES}
    lanes = [
        {**{f: (STOPS[int(v[k])] if f == "stopped" else float(v[k]) if f in ("scale", "best_objective") else
                int(v[k])) for f, v in state.lanes._asdict().items()}, "history": histories[k]}
        for k in range(len(histories))
    ]  # fmt: skip
    meta = {"iterations": int(state.iteration), "screened": int(state.scored), "polished": int(state.polished),
            "round": int(state.round), "phase": PHASES[int(state.phase)], "seconds": seconds,
            "lanes": lanes}  # fmt: skip
    return trees, meta


def join(trees: dict, meta: dict, steps: int) -> tuple[TunerState, list]:
    """The :class:`TunerState` (its cap ``steps``) and the starts' histories of a checkpoint's ``(trees, meta)``."""
    lanes = meta["lanes"]
    dtype = np.asarray(jax.tree.leaves(trees["theta"])[0]).dtype

    def column(field):
        values = [STOPS.index(lane[field]) if field == "stopped" else lane[field] for lane in lanes]
        return np.asarray(values, dtype if field in ("scale", "best_objective") else np.int32)

    names = {"phase": PHASES.index(meta["phase"]), "round": meta["round"], "iteration": meta["iterations"],
             "polished": meta["polished"], "scored": meta["screened"], "cap": steps}  # fmt: skip
    scalars = {k: np.asarray(v, np.int32) for k, v in names.items()}
    state = TunerState(**scalars, lanes=Lanes(*(column(f) for f in Lanes._fields)), **trees)
    return state, [lane["history"] for lane in lanes]


def save(path: Path, trees: dict, meta: dict) -> None:
    """Write ``trees``'s arrays and ``meta`` to ``path`` atomically."""
    arrays = {f"leaf{i}": np.asarray(leaf) for i, leaf in enumerate(jax.tree.leaves(trees))}
    tmp = temporary_path(path, ".tmp.npz")
    try:
        np.savez(tmp, meta=np.array(json.dumps({**meta, "arrays": len(arrays)})), **arrays)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def _fields_problem(record: dict, fields: dict, where: str) -> str | None:
    """What makes ``record`` (a JSON object) miss or mistype one of ``fields``, or None."""
    for key, kind in fields.items():
        value = record.get(key)
        ok = isinstance(value, int | float) if kind is float else isinstance(value, kind)
        if not ok or isinstance(value, bool):
            return f"{where}{key} is {'missing' if key not in record else repr(value)}, expected {kind.__name__}"
    numbers = [record[k] for k, kind in fields.items() if kind in (int, float)]
    if not all(math.isfinite(v) and v >= 0 for v in numbers if v != math.inf):
        return f"{where[:-1]} holds a negative or non-finite count, scale or objective"
    return None


def _meta_problem(meta) -> str | None:
    """What makes a checkpoint's ``meta`` unusable, or None."""
    if not isinstance(meta, dict):
        return f"meta is a JSON {type(meta).__name__}, not an object"
    problem = _fields_problem(meta, _META, "meta.")
    if problem is not None:
        return problem
    if not meta["lanes"] or meta["phase"] not in PHASES:
        return "meta.lanes is empty" if not meta["lanes"] else f"meta.phase {meta['phase']!r} is not a phase"
    for k, lane in enumerate(meta["lanes"]):
        where = f"meta.lanes[{k}]."
        problem = _fields_problem(lane, _LANE, where) if isinstance(lane, dict) else f"{where[:-1]} is not an object"
        if problem is not None:
            return problem
        if lane["scale"] <= 0 or lane["stopped"] not in STOPS:
            return f"{where[:-1]} holds a scale or stop reason out of range"
        ended = meta["phase"] == "done" and not lane["history"]  # the last of several rounds: its starts are finished
        if (len(lane["history"]) != lane["evaluations"] and not ended) or not all(
            isinstance(h, dict) for h in lane["history"]
        ):
            return f"{where}history has {len(lane['history'])} entries for {lane['evaluations']} evaluations"
    return None


def load(path: Path, template: dict) -> tuple[dict, dict]:
    """``(trees, meta)`` from ``path`` (``template``: trees of the expected shapes); :class:`CheckpointError` naming
    the file for anything unusable but the fingerprint (checked by the caller)."""
    leaves, treedef = jax.tree.flatten(template)
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            count = len(data.files) - 1
            loaded = [data[f"leaf{i}"] for i in range(min(count, len(leaves)))]
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise CheckpointError(f"{path}: corrupt or unreadable checkpoint ({exc}); delete it to start over") from exc
    problem = _meta_problem(meta)
    if problem is None and count != meta["arrays"]:
        problem = f"{count} arrays, written with {meta['arrays']}"
    if problem is not None:
        raise CheckpointError(f"{path}: damaged checkpoint ({problem}); delete it to start over")
    other = f"{count} arrays, expected {len(leaves)}" if count != len(leaves) else None
    for i, (new, old) in enumerate(zip(loaded, leaves, strict=False)):
        if other is None and new.shape != np.shape(old):
            other = f"array {i} has shape {new.shape}, expected {np.shape(old)}"
    if other is None and len(meta["lanes"]) != np.shape(template["start"][next(iter(template["start"]))])[0]:
        other = f"{len(meta['lanes'])} starts, expected {np.shape(template['start'][next(iter(template['start']))])[0]}"
    if other is not None:  # another optimiser, parameter layout or number of starts
        raise CheckpointError(
            f"{path}: written for a different problem, program or settings ({other}); delete it (or use another "
            "--out) to start over"
        )
    for i, new in enumerate(loaded):
        if new.dtype.kind in "fc" and not np.all(np.isfinite(new)):
            raise CheckpointError(f"{path}: array {i} holds NaN or infinite values; delete it to start over")
    meta.pop("arrays")
    return jax.tree.unflatten(treedef, list(loaded)), meta
