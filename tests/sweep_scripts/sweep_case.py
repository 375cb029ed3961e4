"""The sweep used by tests/test_sweep.py, importable and runnable as a subprocess.

``python sweep_case.py OUT_DIR [OUT_DIR ...] --num N --chunk C`` runs the sweep into each OUT_DIR and prints one
JSON line per run (the SweepResult). ``--coordinator HOST:PORT --num-processes N --process-id I`` first joins a
multi-process run (``jax.distributed.initialize``); ``--lapack`` adds a metric computed with ``jnp.linalg.solve``
(jaxlib's batched LAPACK kernel, which the engine keeps on its sequential path: jaxobs.batching). The last line
counts the files this process wrote through the engine (``files_written``). ``SWEEP_SLEEP`` (seconds, read at
run time) slows every chunk down so that a test can kill the process mid-sweep; the sleep is an identity
callback, so the numbers do not depend on it.
"""

import argparse
import dataclasses
import json
import os
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import jaxobs.sweep
from jaxobs.sweep import run_sweep

WRITES = []


def _counted_write(path, data, *, _write=jaxobs.sweep.atomic_write):
    WRITES.append(str(path))
    _write(path, data)


jaxobs.sweep.atomic_write = _counted_write  # every chunk and manifest goes through it

CONFIG = {"case": "damped oscillator", "steps": 50}


class Metrics(NamedTuple):
    cost: jax.Array
    peak: jax.Array
    x_final: jax.Array  # shape (2,): two columns
    stable: jax.Array  # bool


def _sleep(index):
    time.sleep(float(os.environ.get("SWEEP_SLEEP", "0")))
    return index


def sampler(key, index):
    """A 2-state discrete oscillator with sampled frequency, damping, input gain and initial state."""
    k1, k2, k3, k4 = jax.random.split(key, 4)
    index = jax.pure_callback(_sleep, jax.ShapeDtypeStruct((), jnp.int32), index, vmap_method="broadcast_all")
    w = jax.random.uniform(k1, minval=0.5, maxval=2.0)
    zeta = jax.random.uniform(k2, minval=-0.05, maxval=0.5)
    dt = 0.1
    a = jnp.array([[1.0, dt], [-(w**2) * dt, 1.0 - 2 * zeta * w * dt]])
    return {
        "plant": {"A": a, "b": jax.random.normal(k3, (2,))},
        "x0": jax.random.normal(k4, (2,)),
        "mode": index % 3,
    }


def evaluate(p):
    def step(x, k):
        u = jnp.where(p["mode"] == 0, 0.0, jnp.sin(0.3 * k))
        x = p["plant"]["A"] @ x + p["plant"]["b"] * u
        return x, x @ x

    x, energy = jax.lax.scan(step, p["x0"], jnp.arange(50.0))
    return Metrics(cost=energy.sum(), peak=energy.max(), x_final=x, stable=energy[-1] < energy[0] + 1.0)


def evaluate_lapack(p):
    """:func:`evaluate` plus the solution of ``A x = b`` (a batched LAPACK LU solve once vmapped)."""
    return evaluate(p)._asdict() | {"solve": jnp.linalg.solve(p["plant"]["A"], p["plant"]["b"])}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("out_dirs", nargs="+")
    parser.add_argument("--num", type=int, default=1000)
    parser.add_argument("--chunk", type=int, default=128)
    parser.add_argument("--coordinator")
    parser.add_argument("--num-processes", type=int)
    parser.add_argument("--process-id", type=int)
    parser.add_argument("--lapack", action="store_true")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    if args.coordinator:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    fn = evaluate_lapack if args.lapack else evaluate
    for out in args.out_dirs:
        res = run_sweep(sampler, fn, args.num, out, chunk_size=args.chunk, config=CONFIG, progress=False)
        print(json.dumps({k: str(v) if k == "out_dir" else v for k, v in dataclasses.asdict(res).items()}))
    print(
        json.dumps(
            {
                "devices": len(jax.devices()),
                "processes": jax.process_count(),
                "files_written": len(WRITES),
                "x64": bool(np.asarray(jnp.zeros(())).dtype == np.float64),
            }
        )
    )


if __name__ == "__main__":
    main()
