"""Batched Monte-Carlo sweeps: chunked, sharded over devices, resumable, written to Parquet.

:func:`run_sweep` evaluates ``num_configs`` configurations, configuration ``i`` sampled from its own key
:func:`config_key` ``(seed, i)``, so every number depends only on ``(seed, i)``: never on the chunk size, the device
count or an interruption (up to the rounding of sums, which XLA may order differently for another batch or device
count). ``vmap`` over a chunk per device inside ``jax.shard_map``; chunks written atomically to
``out_dir/chunks/*.parquet`` with a checksummed manifest; a rerun resumes, a different sweep is refused
(:class:`SweepError`); several processes run one sweep after ``jax.distributed.initialize``. :func:`load_results`
reads the columns. How it runs, the output format and resuming: docs/theory/jobs.md and docs/guides/sweeps.md.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import importlib.metadata
import io
import json
import logging
import math
import platform
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from jaxobs._distributed import agree, from_process_0
from jaxobs._jit import Compiling
from jaxobs._resources import (
    MAX_INDEX,
    Interrupted,
    InterruptWatch,
    JobError,
    LimitError,
    StallWatch,
    atomic_write,
    check_memory,
    locked_out_dir,
    program_nbytes,
)
from jaxobs.batching import lapack_calls, safe_vmap

__all__ = [
    "SweepError",
    "SweepResult",
    "config_key",
    "load_results",
    "read_manifest",
    "run_sweep",
    "run_configured_sweep",
]

FORMAT_VERSION = 2
_MANIFEST = "manifest.json"
_REPLACE = "pass overwrite=True (CLI: --overwrite) to replace it, or use a new out_dir"
_log = logging.getLogger(__name__)


class SweepError(JobError):
    """``out_dir`` holds something this sweep cannot use: another sweep, a damaged manifest, missing chunks."""


@dataclass(frozen=True)
class SweepResult:
    """Summary of one ``run_sweep`` call (the data itself is read with ``load_results``).

    Attributes:
      out_dir: the directory holding the results.  num_configs: configurations in the sweep.
      chunks_computed, chunks_reused: chunks computed in this call and found already written.
      seconds: this call's wall time from the compilation to the last chunk written (compilation included; the
        caller's building of the sampler and evaluation, and any report, not).
      configs_per_second: configurations computed in this call over the time spent computing and writing them
        (compilation excluded; 0 if none).
      compile_seconds: this call's tracing and compiling of the sweep step (part of ``seconds``; 0 when every
        chunk was already written).
    """

    out_dir: Path
    num_configs: int
    chunks_computed: int
    chunks_reused: int
    seconds: float
    configs_per_second: float
    compile_seconds: float = 0.0


def config_key(seed: int, index) -> jax.Array:
    """The PRNG key of configuration ``index``: ``fold_in(key(seed), index)``."""
    return jax.random.fold_in(jax.random.key(seed), index)


def _chunk_path(out_dir: Path, chunk: int) -> Path:
    return out_dir / "chunks" / f"chunk-{chunk:05d}.parquet"


def _write_chunk(path: Path, table: pa.Table) -> str:
    """Write one chunk atomically; return the SHA-256 of the file's bytes."""
    sink = io.BytesIO()
    pq.write_table(table, sink)
    data = sink.getvalue()
    atomic_write(path, data)
    return hashlib.sha256(data).hexdigest()


def _write_manifest(out_dir: Path, manifest: dict) -> None:
    manifest["updated"] = _now()
    atomic_write(out_dir / _MANIFEST, json.dumps(manifest, indent=1).encode())


_MANIFEST_FIELDS = {
    "config": dict, "seed": int, "num_configs": int, "chunk_size": int, "num_chunks": int, "columns": dict,
    "completed": dict, "fingerprint": str,
}  # fmt: skip


def _manifest_problem(manifest) -> str | None:
    """What makes ``manifest`` (parsed JSON) unusable, or None."""
    if not isinstance(manifest, dict):
        return f"a JSON {type(manifest).__name__} instead of an object"
    if manifest.get("format_version") != FORMAT_VERSION:
        return f"format_version {manifest.get('format_version')!r}, this version writes {FORMAT_VERSION}"
    for key, kind in _MANIFEST_FIELDS.items():
        value = manifest.get(key)
        if not isinstance(value, kind) or isinstance(value, bool):
            return f"{key} is {'missing' if key not in manifest else type(value).__name__}, expected {kind.__name__}"
    if not all(isinstance(v, str) for v in manifest["columns"].values()) or "index" not in manifest["columns"]:
        return "columns is not a table of column dtypes"
    for chunk, entry in manifest["completed"].items():
        if not (
            chunk.isdigit() and isinstance(entry, dict) and isinstance(entry.get("rows"), int)
            and entry["rows"] > 0 and isinstance(entry.get("sha256"), str)
        ):  # fmt: skip
            return f"completed[{chunk!r}] is not a chunk entry (rows, sha256)"
    return None


def read_manifest(out_dir) -> dict | None:
    """The manifest of the sweep in ``out_dir`` (None if there is none); :class:`SweepError` if it is unreadable
    or not a manifest of this version (a cheap check to run before building a sweep)."""
    path = Path(out_dir) / _MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        raise SweepError(f"{path} is unreadable ({e}); {_REPLACE}") from e
    problem = _manifest_problem(manifest)
    if problem is not None:
        raise SweepError(f"{path} is not a sweep manifest this version can use ({problem}); {_REPLACE}")
    return manifest


def _read_chunk(out_dir: Path, chunk: int, entry: dict | None) -> tuple[bytes | None, str]:
    """(file bytes, "") if chunk file matches its manifest entry, else (None, the reason it does not)."""
    if entry is None:
        return None, "not in the manifest"
    try:
        data = _chunk_path(out_dir, chunk).read_bytes()
    except OSError:
        return None, "missing"
    if hashlib.sha256(data).hexdigest() != entry.get("sha256"):
        return None, "corrupt (checksum mismatch)"
    return data, ""


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _versions() -> dict:
    out = {"python": platform.python_version()}
    for name in ("jax", "jaxlib", "numpy", "pyarrow", "jaxobs"):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def _columns(shapes) -> list[tuple[str, int, int, np.dtype]]:
    """(column name, leaf number, flat position in the leaf, dtype) for the (params, metrics) of one config."""
    cols = []
    leaves = jax.tree_util.tree_flatten_with_path(shapes)[0]
    for leaf_no, (path, leaf) in enumerate(leaves):
        prefix = ("param", "metric")[path[0].idx]
        name = ".".join(filter(None, [prefix, jax.tree_util.keystr(path[1:], simple=True, separator=".")]))
        dtype = leaf.dtype
        if not isinstance(dtype, np.dtype) or dtype.kind not in "biuf":
            raise ValueError(
                f"{name} has dtype {leaf.dtype}; sampler and evaluate must return bool, integer or float arrays "
                "(split complex values into real and imaginary parts, turn PRNG keys into key_data)"
            )
        for pos, ix in enumerate(np.ndindex(*leaf.shape)):
            suffix = f"[{','.join(map(str, ix))}]" if ix else ""
            cols.append((name + suffix, leaf_no, pos, dtype))
    return cols


def _table(indices: np.ndarray, leaves: list[np.ndarray], layout) -> pa.Table:
    """Arrow table of the rows ``indices``; ``leaves`` are the output leaves reshaped to (rows, -1)."""
    data = {"index": pa.array(indices.astype(np.int64))}
    for name, leaf_no, pos, _ in layout:
        data[name] = pa.array(np.ascontiguousarray(leaves[leaf_no][:, pos]))
    return pa.table(data)


def _check_args(sampler, evaluate, num_configs, chunk_size, seed, config) -> None:
    for name, fn in (("sampler", sampler), ("evaluate", evaluate)):
        if not callable(fn):
            raise ValueError(f"{name} must be a function, got {type(fn).__name__}")
    for name, value, lo in (("num_configs", num_configs, 1), ("chunk_size", chunk_size, 1), ("seed", seed, None)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(f"{name} must be an int, got {value!r}")
        if lo is not None and value < lo:
            raise ValueError(f"{name} must be >= {lo}, got {value}")
    if num_configs > MAX_INDEX:
        raise LimitError(f"num_configs must be below 2**31 (indices are int32), got {num_configs}")
    try:
        json.dumps(config, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"config must be a JSON-serialisable dict (it is stored in the manifest): {e}") from e


def _log_blocks(row, chunk_size: int) -> None:
    """Say (INFO) which LAPACK calls of a chunk run in blocks (:func:`jaxobs.batching.safe_vmap`)."""
    if jax.default_backend() != "cpu":
        return
    calls = lapack_calls(jax.vmap(row), jax.ShapeDtypeStruct((chunk_size,), jnp.int32))
    over = sorted({f"{name} of {shape[-2]}x{shape[-1]} in blocks of {bound}" for name, shape, bound in calls
                   if math.prod(shape[:-2]) > bound})  # fmt: skip
    if over:
        _log.info("LAPACK calls of a chunk done in blocks, on one thread each (jaxobs.batching): %s", "; ".join(over))


def _compile(row, devices, chunk_size: int):
    """``(compiled step, input sharding)`` for ``vmap(row)`` over one chunk per device, in blocks that keep CPU
    LAPACK kernels on their sequential path (:func:`jaxobs.batching.safe_vmap`)."""
    mesh = Mesh(np.array(devices), ("configs",))
    sharding = NamedSharding(mesh, PartitionSpec("configs"))
    spec = PartitionSpec("configs")  # check_vma=False: scans may start from constant carries
    _log_blocks(row, chunk_size)
    step = jax.shard_map(safe_vmap(row), mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)
    batch = jax.ShapeDtypeStruct((len(devices) * chunk_size,), jnp.int32, sharding=sharding)
    return jax.jit(step).lower(batch).compile(), sharding


def _row(sampler, evaluate, seed: int):
    """``(row, layout)``: ``row(index) = (params, metrics)`` of one configuration and its columns
    (:func:`_columns`), checked with ``jax.eval_shape``."""

    def row(index):
        params = sampler(config_key(seed, index), index)
        return params, evaluate(params)

    try:
        shapes = jax.eval_shape(row, jax.ShapeDtypeStruct((), jnp.int32))
    except Exception as e:
        raise ValueError(
            f"sampler/evaluate failed on one configuration (jax.eval_shape): {type(e).__name__}: {e}"
        ) from e
    layout = _columns(shapes)
    if not any(name.startswith("metric") for name, *_ in layout):
        raise ValueError("evaluate returned no arrays; it must return a pytree of metric arrays")
    names = ["index"] + [name for name, *_ in layout]
    if len(set(names)) != len(names):
        raise ValueError(f"column names collide (rename pytree keys): {names}")
    return row, layout


def _compute(compiled, sharding, group: list[int], ndev: int, chunk_size: int, num_configs: int, stall) -> list:
    """The output leaves, shaped (devices, chunk_size, -1), of the chunks ``group`` (one per device; the last
    repeated to fill them), computed under the :class:`jaxobs._resources.StallWatch` ``stall``."""
    padded = group + group[-1:] * (ndev - len(group))
    starts = np.repeat(np.array(padded) * chunk_size, chunk_size) + np.tile(np.arange(chunk_size), ndev)
    indices = np.minimum(starts, num_configs - 1).astype(np.int32)  # each process places its devices' part
    with stall.waiting(f"chunk(s) {', '.join(map(str, group))}") as wait:
        outputs = wait["pending"] = compiled(jax.make_array_from_callback(indices.shape, sharding, indices.__getitem__))
        if jax.process_count() > 1:
            outputs = multihost_utils.process_allgather(outputs, tiled=True)
        return [np.asarray(x).reshape(ndev, chunk_size, -1) for x in jax.tree_util.tree_leaves(outputs)]


def _row_nbytes(layout) -> int:
    return 8 + sum(dtype.itemsize for *_, dtype in layout)


def _fingerprint(row, chunk_size: int) -> str:
    """What computes the chunks: the SHA-256 of the lowered program of ``vmap(row)`` over one chunk (without
    shardings, so the device count does not enter) and of the jax and jaxlib versions."""
    lowered = jax.jit(jax.vmap(row)).lower(jax.ShapeDtypeStruct((chunk_size,), jnp.int32))
    digest = hashlib.sha256(lowered.as_text().encode())
    versions = _versions()
    digest.update(f"jax {versions['jax']} jaxlib {versions['jaxlib']}".encode())
    return digest.hexdigest()


def _check_step_memory(compiled, devices, chunk_size: int, row_nbytes: int) -> None:
    """Refuse a step that cannot fit: XLA's per-device estimate of the compiled step (CPU devices share the host
    memory) and the host copy of its outputs (NumPy arrays, then an Arrow table)."""
    per_device = program_nbytes(compiled)
    host = 2 * len(devices) * chunk_size * row_nbytes
    what = f"one step of the sweep ({len(devices)} device(s) x chunk_size {chunk_size})"
    if devices[0].platform == "cpu":
        check_memory(host + len(devices) * (per_device or 0), what, hint="lower chunk_size")
    else:
        check_memory(per_device, what, device=devices[0], hint="lower chunk_size")
        check_memory(host, f"the host copy of {what}", hint="lower chunk_size")


def _check_same_sweep(out_dir: Path, old: dict | None, identity: dict, columns: dict, fingerprint: str) -> None:
    """Refuse (:class:`SweepError`) a manifest ``old`` of another sweep than ``identity``, ``columns``,
    ``fingerprint``."""
    if old is None:
        return
    diff = [k for k in identity if old[k] != identity[k]] or (["columns"] if old["columns"] != columns else [])
    if diff:
        raise SweepError(f"{out_dir} holds a different sweep ({', '.join(diff)} differ); {_REPLACE}")
    if old["fingerprint"] != fingerprint:
        raise SweepError(
            f"{out_dir} holds chunks computed by other code (the lowered sampler/evaluate program or the "
            f"jax/jaxlib versions differ from this call's); {_REPLACE}"
        )


def _reusable(out_dir: Path, old: dict | None, num_configs: int, chunk_size: int) -> dict:
    """The manifest entries of ``old`` to keep: the chunks of this sweep whose file matches its checksum and
    holds the rows it must hold now, and any chunks past its end (kept for a later extension)."""
    num_chunks = math.ceil(num_configs / chunk_size)
    entries = (old or {}).get("completed", {})
    kept = {c: e for c, e in entries.items() if int(c) >= num_chunks}
    for chunk in range(num_chunks):
        entry = entries.get(str(chunk))
        if entry is None and not _chunk_path(out_dir, chunk).exists():
            continue
        rows = min(chunk_size, num_configs - chunk * chunk_size)
        data, why = _read_chunk(out_dir, chunk, entry)
        if data is not None and entry["rows"] != rows:
            data, why = None, f"it holds {entry['rows']} rows, the sweep now needs {rows}"
        if data is None:
            _log.warning("recomputing chunk %d (%s): %s", chunk, _chunk_path(out_dir, chunk), why)
        else:
            kept[str(chunk)] = entry
    return kept


def run_sweep(
    sampler,
    evaluate,
    num_configs: int,
    out_dir,
    *,
    seed: int = 0,
    chunk_size: int = 4096,
    config: dict | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> SweepResult:
    """Evaluate ``evaluate(sampler(config_key(seed, i), i))`` for ``i < num_configs`` into ``out_dir``.

    Args:
      sampler: ``sampler(key, index)`` returns one configuration's parameters (a pytree of arrays).
      evaluate: ``evaluate(params)`` returns its metrics (a pytree of bool/int/float arrays); the engine ``vmap``s
        both and writes one row per configuration (Parquet chunks).
      num_configs: how many configurations.  out_dir: where the chunks and the manifest go.
      seed: the PRNG seed of the configuration keys.  chunk_size: configurations per compiled step and chunk.
      config: a JSON-able description of the sweep stored verbatim in the manifest.
      progress: show a progress bar.  overwrite: discard an existing, different sweep in ``out_dir``.

    Rerunning the same call resumes; with a larger ``num_configs`` it extends the sweep. Returns a
    :class:`SweepResult`; read the rows with :func:`load_results`.

    Raises ``ValueError`` for bad arguments or a bad evaluation (checked with ``jax.eval_shape`` before any file
    is written), :class:`SweepError` (a ``ValueError``) for a different sweep in ``out_dir``,
    :class:`jaxobs._resources.JobError` (a ``ValueError``) for an unwritable or locked ``out_dir`` or a step
    that cannot fit in memory, :class:`jaxobs._resources.Interrupted` on Ctrl-C, and
    :class:`jaxobs._resources.Stalled` (a ``JobError``) for a chunk that makes no progress (its CPU idle for a
    minute, or 20 times slower than the slowest chunk before it): the chunks written so far are kept.

    Each chunk runs in blocks that keep jaxlib's CPU LAPACK kernels on their sequential path
    (:func:`jaxobs.batching.safe_vmap`): the same numbers, without the deadlock those kernels can cause.
    """
    _check_args(sampler, evaluate, num_configs, chunk_size, seed, config)
    num_configs, chunk_size, seed = int(num_configs), int(chunk_size), int(seed)
    config = {} if config is None else json.loads(json.dumps(config))

    row, layout = _row(sampler, evaluate, seed)
    out_dir = Path(out_dir)
    writer = jax.process_index() == 0
    with contextlib.ExitStack() as held:
        return _run_locked(row, layout, num_configs, out_dir, seed, chunk_size, config, progress, overwrite, writer,
                           held)  # fmt: skip


def _agree(out_dir: Path, error: Exception | None, digest: bytes = b"") -> None:
    """:func:`jaxobs._distributed.agree` for the sweep into ``out_dir``."""
    agree(error, digest, job=f"the sweep in {out_dir}", kind="sweep", error_type=SweepError,
          differs="sampler, evaluate, num_configs, chunk_size, seed or config differ")  # fmt: skip


def _run_locked(row, layout, num_configs, out_dir, seed, chunk_size, config, progress, overwrite, writer, held):
    """:func:`run_sweep` once its arguments are checked: process 0 (the ``writer``) takes the lock of ``out_dir``
    into ``held`` and decides which chunks to compute, the others follow."""
    watch = held.enter_context(InterruptWatch())
    columns = {"index": "int64"} | {name: str(dtype) for name, _, _, dtype in layout}
    num_chunks = math.ceil(num_configs / chunk_size)
    identity = {"config": config, "seed": seed, "chunk_size": chunk_size}
    fingerprint = _fingerprint(row, chunk_size)
    old, completed, todo, error = None, {}, np.zeros(num_chunks, bool), None
    try:
        if writer:
            held.enter_context(locked_out_dir(out_dir))
            old = None if overwrite else read_manifest(out_dir)
            _check_same_sweep(out_dir, old, identity, columns, fingerprint)
            completed = _reusable(out_dir, old, num_configs, chunk_size)
            todo = np.array([str(c) not in completed for c in range(num_chunks)])
    except JobError as exc:  # SweepError included
        error = exc
    digest = hashlib.sha256(json.dumps([identity, columns, fingerprint, num_configs]).encode()).digest()
    _agree(out_dir, error, digest)
    todo = from_process_0(todo)  # every process must compute the same chunks: process 0 decides
    completed = {c: e for c, e in completed.items() if int(c) >= num_chunks or not todo[int(c)]}
    reused_rows = sum(e["rows"] for c, e in completed.items() if int(c) < num_chunks)

    devices, compiled, sharding, compile_seconds = jax.devices(), None, None, (old or {}).get("compile_seconds")
    start, compiled_now = time.perf_counter(), 0.0
    if todo.any():  # compile and size the step before writing anything
        what = f"the sweep step ({chunk_size} configurations per device, {len(devices)} device(s))"
        with Compiling(_log, what) as timer:
            compiled, sharding = _compile(row, devices, chunk_size)
        compile_seconds = compiled_now = timer.seconds
        try:
            _check_step_memory(compiled, devices, chunk_size, _row_nbytes(layout))
        except JobError as exc:
            error = exc
        _agree(out_dir, error)
    manifest = {
        "format_version": FORMAT_VERSION,
        **identity,
        "num_configs": num_configs,
        "num_chunks": num_chunks,
        "fingerprint": fingerprint,
        "device_count": len(devices),
        "process_count": jax.process_count(),
        "platform": devices[0].platform,
        "device_kind": devices[0].device_kind,
        "versions": _versions(),
        "columns": columns,
        "completed": completed,
        "created": (old or {}).get("created", _now()),
        "seconds": (old or {}).get("seconds", 0.0),  # wall time of all runs, compilation included
        "compile_seconds": compile_seconds,
    }
    previous_seconds = manifest["seconds"]
    done_chunks, computed_rows, compute_seconds = num_chunks - int(todo.sum()), 0, 0.0
    bar, ndev = None, len(devices)
    stall = held.enter_context(StallWatch(
        f"the sweep in {out_dir}", "rerun with a smaller chunk_size, or with NPROC=1 in the environment (one XLA "
        "intra-op thread); finished chunks are kept", cpu=devices[0].platform == "cpu",
    ))  # fmt: skip
    try:
        if writer:
            if overwrite:
                (out_dir / _MANIFEST).unlink(missing_ok=True)
                shutil.rmtree(out_dir / "chunks", ignore_errors=True)
            (out_dir / "chunks").mkdir(parents=True, exist_ok=True)
            for tmp in [*(out_dir / "chunks").glob("*.tmp"), *out_dir.glob(f"{_MANIFEST}.*.tmp")]:
                tmp.unlink()  # left by a killed run: this process holds the lock, so no other writer owns them
            _write_manifest(out_dir, manifest)
        bar = tqdm(total=num_configs, initial=reused_rows, unit="config", disable=not (progress and writer),
                   desc=f"sweep (compiled in {compiled_now:.1f} s)")  # fmt: skip
        todo_chunks = [int(c) for c in np.flatnonzero(todo)]
        for first in range(0, len(todo_chunks), ndev):
            watch.check()
            t0 = time.perf_counter()
            group = todo_chunks[first : first + ndev]
            leaves = _compute(compiled, sharding, group, ndev, chunk_size, num_configs, stall)
            for j, chunk in enumerate(group):
                rows = min(chunk_size, num_configs - chunk * chunk_size)
                if writer:
                    indices = np.arange(chunk * chunk_size, chunk * chunk_size + rows)
                    table = _table(indices, [leaf[j, :rows] for leaf in leaves], layout)
                    sha = _write_chunk(_chunk_path(out_dir, chunk), table)
                    manifest["completed"][str(chunk)] = {
                        "rows": rows, "sha256": sha, "device_count": ndev, "process_count": jax.process_count(),
                    }  # fmt: skip
                    manifest["seconds"] = previous_seconds + time.perf_counter() - start
                    _write_manifest(out_dir, manifest)
                done_chunks += 1
                computed_rows += rows
                bar.update(rows)
            compute_seconds += time.perf_counter() - t0
            bar.set_postfix({"configs/s": f"{computed_rows / compute_seconds:.0f}"})
        watch.check()
    except KeyboardInterrupt as exc:
        raise Interrupted(
            f"interrupted after {done_chunks} of {num_chunks} chunks; rerun the same command to resume"
        ) from exc
    finally:
        if bar is not None:
            bar.close()
    seconds = time.perf_counter() - start
    return SweepResult(
        out_dir=out_dir,
        num_configs=num_configs,
        chunks_computed=int(todo.sum()),
        chunks_reused=num_chunks - int(todo.sum()),
        seconds=seconds,
        configs_per_second=computed_rows / compute_seconds if computed_rows else 0.0,
        compile_seconds=compiled_now,
    )


def run_configured_sweep(
    config: dict, sampler, evaluate, num_configs: int, out_dir, *, size_key: str | None = None,
    progress: bool = True, overwrite: bool = False, report=None,
):  # fmt: skip
    """:func:`run_sweep` with ``seed`` and ``chunk_size`` read from ``config`` (a scenario's validated
    configuration), which is also stored in the manifest, less the dotted ``size_key`` that sets ``num_configs``
    if given: then the same configuration with more configurations extends the sweep in ``out_dir``. A
    scenario's report loads every row, so the rows must fit in memory (:class:`jaxobs._resources.JobError`
    before anything is computed otherwise).

    Returns the :class:`SweepResult`, or with ``report`` (a function of it that writes the scenario's report into
    ``out_dir``) what ``report`` returns: in process 0 only, as only process 0 writes; ``None`` in the others of a
    multi-process run."""
    _check_args(sampler, evaluate, num_configs, config["chunk_size"], config["seed"], config)
    layout = _row(sampler, evaluate, config["seed"])[1]
    check_memory(2 * num_configs * _row_nbytes(layout), f"the report of {num_configs} configurations",
                 hint=f"lower {size_key}" if size_key else "")  # fmt: skip
    identity = json.loads(json.dumps(config))
    if size_key is not None:
        *parents, last = size_key.split(".")
        table = identity
        for part in parents:
            table = table[part]
        del table[last]
    result = run_sweep(
        sampler, evaluate, num_configs, out_dir, seed=config["seed"], chunk_size=config["chunk_size"],
        config=identity, progress=progress, overwrite=overwrite,
    )  # fmt: skip
    if report is None:
        return result
    return report(result) if jax.process_index() == 0 else None


def load_results(out_dir) -> dict[str, np.ndarray]:
    """All rows of the finished sweep in ``out_dir``, ``{column: array}`` in index order; checksums are verified.

    Raises :class:`SweepError` (a ``ValueError``) if the sweep is incomplete or a chunk is missing or corrupt
    (rerun the same ``run_sweep`` call to resume or repair it), and :class:`jaxobs._resources.JobError` if the
    columns cannot fit in memory (checked before reading).
    """
    out_dir = Path(out_dir)
    manifest = read_manifest(out_dir)
    if manifest is None:
        raise SweepError(f"no {_MANIFEST} in {out_dir}; run run_sweep there first")
    completed, num_chunks = manifest["completed"], manifest["num_chunks"]
    missing = [c for c in range(num_chunks) if str(c) not in completed]
    if missing:
        raise SweepError(
            f"sweep in {out_dir} is incomplete ({num_chunks - len(missing)} of {num_chunks} chunks); "
            "rerun the same run_sweep call to resume it"
        )
    row_nbytes = sum(np.dtype(dtype).itemsize for dtype in manifest["columns"].values())
    check_memory(2 * manifest["num_configs"] * row_nbytes, f"loading the {manifest['num_configs']} rows of {out_dir}")
    tables = []
    for chunk in range(num_chunks):
        data, why = _read_chunk(out_dir, chunk, completed[str(chunk)])
        if data is None:
            raise SweepError(
                f"chunk {chunk} of the sweep in {out_dir} is {why}; rerun the same run_sweep call to repair it"
            )
        tables.append(pq.read_table(pa.BufferReader(data), use_threads=False))
    table = pa.concat_tables(tables)
    # columns copied out of Arrow's buffers, read without Arrow's threads: with zero-copy views a script that had
    # read the results aborted at exit now and then ("terminate called without an active exception")
    return {name: np.array(table.column(name).to_numpy(), copy=True) for name in manifest["columns"]}
