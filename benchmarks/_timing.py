"""Interleaved timing shared by the benchmarks.

Every entry is prepared first (JAX functions compiled ahead of time, the compile time kept apart); then
``rounds`` rounds each run every entry once, in the same order. A slow phase of a shared machine then hits all
entries of a round alike, so the ratio of two entries is taken round by round (paired) and summarised, like
the times, by the median and the [min, max] range over the rounds.
"""

from __future__ import annotations

import dataclasses
import importlib
import multiprocessing
import os
import queue
import statistics
import time
import traceback
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


def time_interleaved(entries: dict, rounds: int, *, required: tuple = (), progress=None) -> tuple[dict, dict]:
    """Time every entry of ``{name: (prepare, jit, scale)}`` in ``rounds`` interleaved rounds.

    ``prepare()`` returns ``(fn, args)`` (or raises :class:`Skipped`); ``jit`` compiles ``fn`` first, twice: once
    for every entry, then, after ``jax.clear_caches()``, again, timed (the compile time each entry reports), so
    that the entry compiled first does not pay the process's one-time costs for all;
    ``scale`` multiplies each measured time (an entry timed on part of the workload and extrapolated).
    Returns ``(timings {name: Timed}, problems {name: {"status", "reason"}})``; an entry in ``required`` that
    fails raises, any other is recorded and left out. ``progress(name)``, if given, is called before each
    preparation and each call of an entry, and ``progress(None)`` after it (a watchdog's heartbeat).
    """
    progress = progress or (lambda name: None)
    prepared, problems = {}, {}
    for name, (prepare, jit, scale) in entries.items():
        progress(name)
        try:
            fn, args = prepare()
            if jit:
                compile_jax(fn, *args)  # untimed: a process's first compilations pay one-time costs
            prepared[name] = (fn, args, jit, scale)
        except Skipped as exc:
            problems[name] = {"status": "skipped", "reason": str(exc)}
        except Exception as exc:  # a broken peer must not abort the other measurements
            if name in required:
                raise
            problems[name] = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}"}
        progress(None)
    jax.clear_caches()  # every entry compiles again from scratch, in a process warmed alike for all
    ready = {}
    for name, (fn, args, jit, scale) in prepared.items():
        progress(name)
        compiled, compile_s = compile_jax(fn, *args) if jit else (fn, None)
        ready[name] = (compiled, args, scale, compile_s)
        progress(None)
    seconds = {name: [] for name in ready}
    results = {}
    for _ in range(rounds):
        for name, (fn, args, scale, _) in ready.items():
            progress(name)
            start = time.perf_counter()
            results[name] = jax.block_until_ready(fn(*args))
            seconds[name].append((time.perf_counter() - start) * scale)
            progress(None)
    timings = {name: Timed(seconds[name], ready[name][3], results[name]) for name in ready}
    return timings, problems


def paired_ratio(numerator: Timed, denominator: Timed) -> dict:
    """Summary of the round-by-round ratio ``denominator time / numerator time`` (how many times faster the
    numerator entry ran than the denominator entry in the same round)."""
    return summary([d / n for n, d in zip(numerator.seconds, denominator.seconds, strict=True)])


def format_range(s: dict, fmt: str = ".3g", suffix: str = "") -> str:
    """``median [min, max]`` of a :func:`summary`."""
    return f"{s['median']:{fmt}}{suffix} [{s['min']:{fmt}}, {s['max']:{fmt}}]"


class Hung(Exception):
    """A watched child stopped making progress; ``entry`` names the entry it was running (``None`` between
    entries), ``what`` says how."""

    def __init__(self, entry, what: str):
        super().__init__(f"{entry or 'the benchmark'} {what}")
        self.entry = entry


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of process ``pid`` (all its threads), from ``/proc``; ``None`` where unavailable."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


IDLE_CPU_SHARE = 0.02
"""A child that used less CPU time than this share of the wall time is idle (a wedged XLA runtime still wakes
now and then: its slow-operation alarm and thread pool use a few milliseconds a minute)."""


def _watched_child(messages, target, args):
    try:
        result = target(*args, progress=lambda name: messages.put(("progress", name)))
        messages.put(("result", result))
    except BaseException:  # the parent re-raises it with the child's traceback
        messages.put(("error", traceback.format_exc()))


def run_watched(target: Callable, args: tuple, *, idle_timeout: float):
    """``target(*args, progress=...)`` in a spawned child process; returns its (picklable) result.

    XLA's CPU runtime can wedge, every thread parked on a condition variable, and never return (measured here:
    cuthbert's log-likelihood gradient over 1024 sequences of 10 states). The child reports which entry it runs
    through ``progress``; when it neither reports nor uses CPU time (under ``IDLE_CPU_SHARE`` of the wall time)
    for ``idle_timeout`` seconds, it is killed and :class:`Hung` names that entry. An entry that computes is killed
    only after ``10 idle_timeout`` seconds in one call. Needs ``/proc`` (Linux) to tell idle from slow; elsewhere
    the child is killed after ``idle_timeout`` seconds without progress.
    """
    context = multiprocessing.get_context("spawn")
    messages = context.Queue()
    child = context.Process(target=_watched_child, args=(messages, target, args), daemon=True)
    child.start()
    current, reported = None, time.monotonic()
    window = (reported, _cpu_seconds(child.pid))  # start of the current idle window: (time, CPU seconds)
    try:
        while True:
            try:
                kind, payload = messages.get(timeout=1.0)
            except queue.Empty:
                if not child.is_alive():
                    raise RuntimeError(f"the benchmark's child process died (exit code {child.exitcode})") from None
                now, cpu = time.monotonic(), _cpu_seconds(child.pid)
                if now - window[0] > idle_timeout:
                    if cpu is None or window[1] is None or cpu - window[1] < IDLE_CPU_SHARE * (now - window[0]):
                        raise Hung(current, f"made no progress and used no CPU for {idle_timeout:g} s") from None
                    window = (now, cpu)  # computing: a new window
                if now - reported > 10 * idle_timeout:
                    raise Hung(current, f"computed {10 * idle_timeout:g} s without finishing a call") from None
                continue
            reported = time.monotonic()
            window = (reported, _cpu_seconds(child.pid))
            if kind == "progress":
                current = payload
            elif kind == "result":
                return payload
            else:
                raise RuntimeError("the benchmark's child process failed:\n" + payload)
    finally:
        if child.is_alive():
            child.kill()
        child.join()
