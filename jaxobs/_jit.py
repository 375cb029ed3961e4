"""Compilation made visible: what a first call or a job spends compiling, said at INFO level.

A design call's first use compiles its program (seconds for a Riccati solver or a linearised MJX step); later calls
with the same shapes, dtypes and static arguments reuse it. :func:`jit` logs the first compilation of each core,
:class:`Compiling` the programs of the sweep and tuning jobs (and keeps their seconds for the jobs' reports). The
logger is the module's (``logging.getLogger("jaxobs.matrix_equations")``, ...): silent unless the caller configures
logging, e.g. ``logging.basicConfig(level=logging.INFO)``; the ``jaxobs`` command shows it.
"""

from __future__ import annotations

import functools
import logging
import time

import jax

__all__ = ["jit", "Compiling"]


def jit(fun=None, *, what: str, **options):
    """``jax.jit(fun, **options)`` (as a decorator: ``functools.partial(jit, what="dare", static_argnames=...)``)
    whose first compiling call logs, once, the seconds it spent tracing and compiling; ``what`` names the public
    call the core serves."""
    if fun is None:
        return functools.partial(jit, what=what, **options)
    return _Logged(jax.jit(fun, **options), logging.getLogger(fun.__module__), what)


class _Logged:
    """A jitted function that logs its first compilation (its cache growing during a call)."""

    def __init__(self, jitted, logger: logging.Logger, name: str):
        self._jitted, self._logger, self._name, self._logged = jitted, logger, name, False
        functools.update_wrapper(self, jitted)

    def __call__(self, *args, **kwargs):
        cache_size = getattr(self._jitted, "_cache_size", None)  # jax.jit's, not a public API: no log without it
        if self._logged or cache_size is None:
            return self._jitted(*args, **kwargs)
        before, start = cache_size(), time.perf_counter()
        out = self._jitted(*args, **kwargs)
        if cache_size() > before:
            self._logged = True
            self._logger.info(
                "%s: the first call compiled its program in %.1f s (once per shapes, dtypes and static arguments; "
                "later calls reuse it)", self._name, time.perf_counter() - start,
            )  # fmt: skip
        return out

    def __getattr__(self, name):  # lower, eval_shape, trace, clear_cache: the jitted function's
        return getattr(self._jitted, name)


class Compiling:
    """``with Compiling(logger, what) as timer:`` logs at INFO that ``what`` is being traced and compiled, and when
    the block ends without an error, after how many seconds; ``timer.seconds`` holds them."""

    def __init__(self, logger: logging.Logger, what: str):
        self.logger, self.what, self.seconds = logger, what, 0.0

    def __enter__(self) -> Compiling:
        self.logger.info("compiling %s ...", self.what)
        self._start = time.perf_counter()
        return self

    def __exit__(self, kind, *_) -> None:
        self.seconds = time.perf_counter() - self._start
        if kind is None:
            self.logger.info("compiled %s in %.1f s", self.what, self.seconds)
