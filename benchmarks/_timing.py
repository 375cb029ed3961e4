"""Interleaved timing shared by the benchmarks.

Every entry is prepared first (JAX functions compiled ahead of time, the compile time kept apart); then
``rounds`` rounds each run every entry once, in the same order. A slow phase of a shared machine then hits all
entries of a round alike, so the ratio of two entries is taken round by round (paired) and summarised, like
the times, by the median and the [min, max] range over the rounds.
"""

from __future__ import annotations

import dataclasses
import importlib
import statistics
import time
from collections.abc import Callable

import jax


def optional_import(name: str):
    """``(module, None)``, or ``(None, reason)`` when ``name`` cannot be imported. JAX's matmul precision is
    restored afterwards: dynamax sets ``jax_default_matmul_precision`` when imported, which would change the
    programs of every library timed after it."""
    precision = jax.config.jax_default_matmul_precision
    try:
        return importlib.import_module(name), None
    except Exception as exc:  # any import-time failure means "skip this peer"
        return None, f"{type(exc).__name__}: {exc}"
    finally:
        jax.config.update("jax_default_matmul_precision", precision)


class Skipped(Exception):
    """An entry is unavailable (a peer not installed); the message says why."""


@dataclasses.dataclass
class Timed:
    """Per-round wall times of one entry, already multiplied by its ``scale`` (extrapolation to the full
    workload), the first call's compile time (JAX entries) and the result of the last round."""

    seconds: list[float]
    compile_s: float | None
    result: object

    def record(self, work_items: float, unit: str) -> dict:
        """JSON record: median and range of the time and of the throughput ``work_items / seconds``."""
        rates = [work_items / s for s in self.seconds]
        return {
            "status": "ok",
            "seconds": summary(self.seconds),
            "throughput": summary(rates),
            "unit": unit,
            "compile_s": self.compile_s,
        }


def summary(values: list[float]) -> dict:
    """``{"median", "min", "max", "rounds", "values"}`` of per-round values."""
    return {
        "median": statistics.median(values),
        "min": min(values),
        "max": max(values),
        "rounds": len(values),
        "values": list(values),
    }


def compile_jax(fn: Callable, *args):
    """``(compiled fn, seconds)``: ``jax.jit(fn)`` lowered and compiled for ``args``."""
    start = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    return compiled, time.perf_counter() - start


def time_interleaved(entries: dict, rounds: int, *, required: tuple = ()) -> tuple[dict, dict]:
    """Time every entry of ``{name: (prepare, jit, scale)}`` in ``rounds`` interleaved rounds.

    ``prepare()`` returns ``(fn, args)`` (or raises :class:`Skipped`); ``jit`` compiles ``fn`` first;
    ``scale`` multiplies each measured time (an entry timed on part of the workload and extrapolated).
    Returns ``(timings {name: Timed}, problems {name: {"status", "reason"}})``; an entry in ``required`` that
    fails raises, any other is recorded and left out.
    """
    ready, problems = {}, {}
    for name, (prepare, jit, scale) in entries.items():
        try:
            fn, args = prepare()
            compile_s = None
            if jit:
                fn, compile_s = compile_jax(fn, *args)
            ready[name] = (fn, args, scale, compile_s)
        except Skipped as exc:
            problems[name] = {"status": "skipped", "reason": str(exc)}
        except Exception as exc:  # a broken peer must not abort the other measurements
            if name in required:
                raise
            problems[name] = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}"}
    seconds = {name: [] for name in ready}
    results = {}
    for _ in range(rounds):
        for name, (fn, args, scale, _) in ready.items():
            start = time.perf_counter()
            results[name] = jax.block_until_ready(fn(*args))
            seconds[name].append((time.perf_counter() - start) * scale)
    timings = {name: Timed(seconds[name], ready[name][3], results[name]) for name in ready}
    return timings, problems


def paired_ratio(numerator: Timed, denominator: Timed) -> dict:
    """Summary of the round-by-round ratio ``denominator time / numerator time`` (how many times faster the
    numerator entry ran than the denominator entry in the same round)."""
    return summary([d / n for n, d in zip(numerator.seconds, denominator.seconds, strict=True)])


def format_range(s: dict, fmt: str = ".3g", suffix: str = "") -> str:
    """``median [min, max]`` of a :func:`summary`."""
    return f"{s['median']:{fmt}}{suffix} [{s['min']:{fmt}}, {s['max']:{fmt}}]"
