"""Batched Monte-Carlo sweeps: chunked, sharded over devices, resumable, written to Parquet.

A sweep evaluates ``num_configs`` configurations. Configuration ``i`` is sampled from its own key,
``config_key(seed, i)``, so every number in the output depends only on ``(seed, i)``: never on the chunk size,
the device count or whether the sweep was interrupted and resumed::

    import jax, jax.numpy as jnp
    from jaxobs.sweep import load_results, run_sweep

    def sampler(key, index):                    # one configuration's parameters (a pytree of arrays)
        return {"a": jax.random.uniform(key, minval=0.5, maxval=1.0)}

    def evaluate(params):                       # one configuration's metrics (a pytree of arrays)
        x = jax.lax.fori_loop(0, 50, lambda k, x: params["a"] * x + 1.0, 0.0)
        return {"x50": x, "converged": jnp.abs(x - 1 / (1 - params["a"])) < 1e-3}

    run_sweep(sampler, evaluate, 10_000, "out/sweep-demo", config={"steps": 50}, progress=False)
    cols = load_results("out/sweep-demo")       # {"index", "param.a", "metric.converged", "metric.x50"}

How it runs. ``row(i) = evaluate(sampler(config_key(seed, i), i))`` is ``vmap``ped over one chunk of
``chunk_size`` indices per device inside ``jax.shard_map`` on a 1-D mesh over ``jax.devices()`` (axis
"configs"; the index array is placed with ``NamedSharding(mesh, PartitionSpec("configs"))``), and the ``jax.jit``
of that is compiled once, ahead of time (``compile_seconds`` in the manifest). Each step computes
``device_count`` chunks, one per device; the last, partial chunk is padded with copies of the last index, a step
short of chunks repeats its last chunk, and the padding is dropped before writing. Every device thus always runs
the same program on ``chunk_size`` rows, which makes the results bit-for-bit identical on 1 and 4 devices (XLA
may emit different code for a different per-device batch: on CPU a 50-term sum rounds differently for batches
of 32 and 128). Different ``chunk_size`` values give the same numbers up to such rounding, usually bit for bit.
``shard_map`` (with ``check_vma=False``, so that a ``scan`` may start from a constant carry) rather than ``jit``
with ``in_shardings``: the per-device program is exactly ``vmap(row)``, and host callbacks run on each device
instead of being funnelled through device 0. A chunk file holds ``chunk_size``
rows (the last one fewer) whatever the device count, so a sweep may be resumed on another machine.
On CPU, an evaluation that calls jaxlib's batched LAPACK kernels (``jnp.linalg.solve``, ``eigvals``,
``cholesky``, ...) runs on one device per process (logged, and recorded as ``device_count``): with jaxlib
0.10 several CPU devices running those kernels at once can deadlock its thread pool.

Output (``out_dir``): ``chunks/chunk-00000.parquet``, ... and ``manifest.json``. Columns: ``index`` (int64),
then ``param.<name>`` and ``metric.<name>``, where ``<name>`` is the leaf's pytree key path joined with "."
(dict keys, dataclass / NamedTuple fields, list positions; a bare array has no suffix). A leaf with trailing
dimensions becomes one column per entry, ``name[i]`` / ``name[i,j]`` (C order). Bool, integer and float dtypes
are kept. Every file is written to ``*.tmp``, fsynced and moved into place with ``os.replace``; the manifest
records each completed chunk's row count and SHA-256. Rerunning the same call reuses the chunks whose checksum
matches and recomputes the rest; a different sweep in the same directory is refused unless ``overwrite=True``.

Multi-host (not tested here: it needs several machines). Call ``jax.distributed.initialize()`` first and run
the same command in every process, with ``out_dir`` on a filesystem all processes see. The mesh then spans the
devices of all processes; the list of chunks to compute is taken from process 0 (``broadcast_one_to_all``),
each chunk's rows are gathered with ``jax.experimental.multihost_utils.process_allgather``, and only
``jax.process_index() == 0`` writes files and shows progress.

Precision: the engine never touches ``jax_enable_x64``; enable it in your entry point for float64 columns.
"""

from __future__ import annotations

import datetime
import hashlib
import importlib.metadata
import io
import json
import logging
import math
import os
import platform
import re
import shutil
import sys
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

__all__ = ["SweepResult", "config_key", "load_results", "run_sweep", "run_configured_sweep"]

FORMAT_VERSION = 1
_MANIFEST = "manifest.json"
_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SweepResult:
    """Summary of one ``run_sweep`` call (the data itself is read with ``load_results``).

    ``seconds`` is this call's wall time (compilation included); ``configs_per_second`` counts the configurations
    computed in this call over the time spent computing and writing them (compilation excluded; 0 if none).
    """

    out_dir: Path
    num_configs: int
    chunks_computed: int
    chunks_reused: int
    seconds: float
    configs_per_second: float


def config_key(seed: int, index) -> jax.Array:
    """The PRNG key of configuration ``index``: ``fold_in(key(seed), index)``."""
    return jax.random.fold_in(jax.random.key(seed), index)


def _chunk_path(out_dir: Path, chunk: int) -> Path:
    return out_dir / "chunks" / f"chunk-{chunk:05d}.parquet"


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path.tmp``, fsync, then ``os.replace`` it onto ``path``."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _write_chunk(path: Path, table: pa.Table) -> str:
    """Write one chunk atomically; return the SHA-256 of the file's bytes."""
    sink = io.BytesIO()
    pq.write_table(table, sink)
    data = sink.getvalue()
    _atomic_write(path, data)
    return hashlib.sha256(data).hexdigest()


def _write_manifest(out_dir: Path, manifest: dict) -> None:
    manifest["updated"] = _now()
    _atomic_write(out_dir / _MANIFEST, json.dumps(manifest, indent=1).encode())


def _read_manifest(out_dir: Path) -> dict | None:
    try:
        return json.loads((out_dir / _MANIFEST).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        raise ValueError(f"{out_dir / _MANIFEST} is unreadable ({e}); use overwrite=True or a new out_dir") from e


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
    if num_configs >= 2**31:
        raise ValueError(f"num_configs must be below 2**31 (indices are int32), got {num_configs}")
    try:
        json.dumps(config, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"config must be a JSON-serialisable dict (it is stored in the manifest): {e}") from e


# jaxlib's batched LAPACK kernels on CPU (LU, eigenvalues, Cholesky, ...; triangular solves are plain loops)
# split their batch over XLA's intra-op thread pool and block a pool thread until the parts are done.
# Several CPU devices running such kernels at once can take every pool thread and then wait forever
# (seen with jaxlib 0.10.2: 2 cores, 2 forced host devices, a batched jnp.linalg.solve or eigvals).
_BLOCKING_LAPACK = re.compile(r'custom_call_target="lapack_(?!\w*trsm)\w+"')


def _compile(row, devices, chunk_size: int):
    """``(compiled step, input sharding, devices used)`` for ``vmap(row)`` over one chunk per device.

    On CPU, a program with blocking LAPACK kernels (see ``_BLOCKING_LAPACK``) is run on one device per
    process instead: the forced host devices share the same cores, and jaxlib already spreads each
    LAPACK batch over all of them.
    """
    while True:
        mesh = Mesh(np.array(devices), ("configs",))
        sharding = NamedSharding(mesh, PartitionSpec("configs"))
        spec = PartitionSpec("configs")  # check_vma=False: scans may start from constant carries
        step = jax.shard_map(jax.vmap(row), mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)
        batch = jax.ShapeDtypeStruct((len(devices) * chunk_size,), jnp.int32, sharding=sharding)
        compiled = jax.jit(step).lower(batch).compile()
        one_per_process = [next(d for d in devices if d.process_index == p) for p in range(jax.process_count())]
        if len(devices) == len(one_per_process) or devices[0].platform != "cpu":
            return compiled, sharding, devices
        kernels = sorted(set(_BLOCKING_LAPACK.findall(compiled.as_text())))
        if not kernels:
            return compiled, sharding, devices
        _log.warning(
            "the evaluation calls jaxlib's batched CPU LAPACK kernels (%s), which can deadlock when several CPU "
            "devices run them at once; computing on %d device(s), one per process, instead of %d",
            ", ".join(k.split('"')[1] for k in kernels),
            len(one_per_process),
            len(devices),
        )
        devices = one_per_process


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

    ``sampler(key, index)`` returns one configuration's parameters, ``evaluate(params)`` its metrics (pytrees of
    bool/int/float arrays; the engine ``vmap``s both). ``config`` is a JSON-able description of the sweep stored
    verbatim in the manifest. Rerunning the same call resumes; ``overwrite=True`` discards an existing sweep.
    Raises ``ValueError`` for bad arguments, a bad evaluation (checked with ``jax.eval_shape`` before any file
    is written) or a different sweep already in ``out_dir``.
    """
    _check_args(sampler, evaluate, num_configs, chunk_size, seed, config)
    num_configs, chunk_size, seed = int(num_configs), int(chunk_size), int(seed)
    config = {} if config is None else json.loads(json.dumps(config))

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
    columns = {"index": "int64"} | {name: str(dtype) for name, _, _, dtype in layout}

    out_dir = Path(out_dir)
    writer = jax.process_index() == 0
    num_chunks = math.ceil(num_configs / chunk_size)
    sweep_id = {"config": config, "seed": seed, "num_configs": num_configs, "chunk_size": chunk_size}
    old = None if overwrite else _read_manifest(out_dir)
    if old is not None:
        diff = [k for k in sweep_id if old.get(k) != sweep_id[k]]
        diff += ["columns"] if not diff and old.get("columns") != columns else []
        if diff or old.get("format_version") != FORMAT_VERSION:
            raise ValueError(
                f"{out_dir} holds a different sweep ({', '.join(diff) or 'format_version'} differ); "
                "pass overwrite=True (CLI: --overwrite) to replace it, or use a new out_dir"
            )
    completed = {}
    for chunk in range(0 if overwrite else num_chunks):
        entry = ((old or {}).get("completed") or {}).get(str(chunk))
        if entry is None and not _chunk_path(out_dir, chunk).exists():
            continue
        data, why = _read_chunk(out_dir, chunk, entry)
        if data is None:
            _log.warning("recomputing chunk %d (%s): %s", chunk, _chunk_path(out_dir, chunk), why)
        else:
            completed[str(chunk)] = entry
    todo = np.array([str(c) not in completed for c in range(num_chunks)])
    if jax.process_count() > 1:  # every process must compute the same chunks: process 0 decides
        todo = np.asarray(multihost_utils.broadcast_one_to_all(todo))
    completed = {c: e for c, e in completed.items() if not todo[int(c)]}
    reused_rows = sum(e["rows"] for e in completed.values())

    devices, compiled, sharding, compile_seconds = jax.devices(), None, None, (old or {}).get("compile_seconds")
    start = time.perf_counter()
    if todo.any():  # compile before touching out_dir, so that a failure leaves it as it was
        compiled, sharding, devices = _compile(row, devices, chunk_size)
        compile_seconds = time.perf_counter() - start
    manifest = {
        "format_version": FORMAT_VERSION,
        **sweep_id,
        "num_chunks": num_chunks,
        "device_count": len(devices),
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
    try:
        if writer:
            if overwrite:
                (out_dir / _MANIFEST).unlink(missing_ok=True)
                shutil.rmtree(out_dir / "chunks", ignore_errors=True)
            (out_dir / "chunks").mkdir(parents=True, exist_ok=True)
            for tmp in (out_dir / "chunks").glob("*.tmp"):
                tmp.unlink()
            _write_manifest(out_dir, manifest)
        bar = tqdm(total=num_configs, initial=reused_rows, unit="config", disable=not (progress and writer))
        todo_chunks = [int(c) for c in np.flatnonzero(todo)]
        for first in range(0, len(todo_chunks), ndev):
            t0 = time.perf_counter()
            group = todo_chunks[first : first + ndev]
            padded = group + group[-1:] * (ndev - len(group))  # one chunk per device
            starts = np.repeat(np.array(padded) * chunk_size, chunk_size) + np.tile(np.arange(chunk_size), ndev)
            outputs = compiled(jax.device_put(np.minimum(starts, num_configs - 1).astype(np.int32), sharding))
            if jax.process_count() > 1:
                outputs = multihost_utils.process_allgather(outputs, tiled=True)
            leaves = [np.asarray(x).reshape(ndev, chunk_size, -1) for x in jax.tree_util.tree_leaves(outputs)]
            for j, chunk in enumerate(group):
                rows = min(chunk_size, num_configs - chunk * chunk_size)
                if writer:
                    indices = np.arange(chunk * chunk_size, chunk * chunk_size + rows)
                    table = _table(indices, [leaf[j, :rows] for leaf in leaves], layout)
                    sha = _write_chunk(_chunk_path(out_dir, chunk), table)
                    manifest["completed"][str(chunk)] = {"rows": rows, "sha256": sha, "device_count": ndev}
                    manifest["seconds"] = previous_seconds + time.perf_counter() - start
                    _write_manifest(out_dir, manifest)
                done_chunks += 1
                computed_rows += rows
                bar.update(rows)
            compute_seconds += time.perf_counter() - t0
            bar.set_postfix({"configs/s": f"{computed_rows / compute_seconds:.0f}"})
    except KeyboardInterrupt:
        if bar is not None:
            bar.close()
        print(
            f"interrupted after {done_chunks} of {num_chunks} chunks; rerun the same command to resume",
            file=sys.stderr,
        )
        raise
    bar.close()
    seconds = time.perf_counter() - start
    return SweepResult(
        out_dir=out_dir,
        num_configs=num_configs,
        chunks_computed=int(todo.sum()),
        chunks_reused=num_chunks - int(todo.sum()),
        seconds=seconds,
        configs_per_second=computed_rows / compute_seconds if computed_rows else 0.0,
    )


def run_configured_sweep(
    config: dict, sampler, evaluate, num_configs: int, out_dir, *, progress: bool = True, overwrite: bool = False
) -> SweepResult:
    """:func:`run_sweep` with ``seed`` and ``chunk_size`` read from ``config`` (a scenario's validated
    configuration), which is also stored in the manifest."""
    return run_sweep(
        sampler, evaluate, num_configs, out_dir, seed=config["seed"], chunk_size=config["chunk_size"],
        config=config, progress=progress, overwrite=overwrite,
    )  # fmt: skip


def load_results(out_dir) -> dict[str, np.ndarray]:
    """All rows of a finished sweep, ``{column: array}`` in index order; checksums are verified.

    Raises ``ValueError`` if the sweep is incomplete or a chunk is missing or corrupt (rerun the same
    ``run_sweep`` call to resume or repair it).
    """
    out_dir = Path(out_dir)
    manifest = _read_manifest(out_dir)
    if manifest is None:
        raise ValueError(f"no {_MANIFEST} in {out_dir}; run run_sweep there first")
    completed, num_chunks = manifest["completed"], manifest["num_chunks"]
    if len(completed) < num_chunks or any(str(c) not in completed for c in range(num_chunks)):
        raise ValueError(
            f"sweep in {out_dir} is incomplete ({len(completed)} of {num_chunks} chunks); "
            "rerun the same run_sweep call to resume it"
        )
    tables = []
    for chunk in range(num_chunks):
        data, why = _read_chunk(out_dir, chunk, completed[str(chunk)])
        if data is None:
            raise ValueError(
                f"chunk {chunk} of the sweep in {out_dir} is {why}; rerun the same run_sweep call to repair it"
            )
        tables.append(pq.read_table(pa.BufferReader(data)))
    table = pa.concat_tables(tables)
    return {name: table.column(name).to_numpy() for name in manifest["columns"]}
