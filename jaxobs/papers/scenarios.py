"""What the paper layer registers: reproductions, sweep scenarios and tuning problems, as description objects.

Each is defined beside its code (``REPRODUCTION = Reproduction(...)``, ``SCENARIO = SweepScenario(...)``,
``PROBLEM = TuningScenario(...)``) and listed once in :mod:`jaxobs.papers.registry`; the ``jaxobs`` command lists,
validates and runs them through these objects only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import jax

from jaxobs._config import check_choice, fail, get, merge
from jaxobs._resources import LimitError
from jaxobs.papers import tune_job, tuning_config
from jaxobs.papers.shipped import resolve_path
from jaxobs.sweep import run_configured_sweep

__all__ = ["first_paragraph", "Reproduction", "Sweep", "SweepScenario", "TuningScenario"]


def first_paragraph(text: str | None) -> str:
    """The first paragraph of ``text`` on one line, without reST literals (the description ``--list`` prints)."""
    first = (text or "").strip().split("\n\n")[0]
    return " ".join(first.replace("``", "").split())


@dataclasses.dataclass(frozen=True, kw_only=True)
class Reproduction:
    """A source's numbers and figures, written by ``jaxobs reproduce NAME``.

    Attributes:
      name: the command-line name (lower case with hyphens).
      summary: what it reproduces (a docstring: its first paragraph is kept).
      reproduce: ``reproduce(out_dir) -> dict`` writes ``out_dir/NAME.json`` and the figures and returns the summary
        (with its ``"figures"``).
      headline: keys of the summary the command prints after the run (scalars, or dicts of scalars).
    """

    name: str
    summary: str
    reproduce: Callable[[Path], dict]
    headline: tuple[str, ...] = ()

    def __post_init__(self):
        """Keep the summary's first paragraph only."""
        object.__setattr__(self, "summary", first_paragraph(self.summary))


@dataclasses.dataclass(frozen=True, kw_only=True)
class _Configured:
    """A job driven by a TOML config: its defaults, the notes ``--print-config`` writes, its checks, and the keys
    that set its sizes.

    The limits are checked in one place for every registered job: integers beyond int32 when the config is merged
    (:func:`jaxobs._config.merge`), and, as :meth:`run` builds and compiles the job (before it computes any
    configuration or step), the memory estimates and counts of the engines (:class:`jaxobs._resources.LimitError`),
    or an allocation or size that fails outright, as a :class:`jaxobs._config.ConfigError` naming the file and the
    size key (:meth:`blame`).
    """

    key: ClassVar[str]  # the config key that names the job
    common_size_keys: ClassVar[tuple[str, ...]] = ()  # size keys every job of the kind has

    name: str
    summary: str
    defaults: dict
    notes: dict
    check: Callable[[dict, str], None]
    open_tables: tuple[str, ...] = ()
    size_keys: tuple[str, ...] = ()
    path_keys: tuple[str, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "summary", first_paragraph(self.summary))
        if self.defaults.get(self.key) != self.name:
            raise ValueError(f"{self.name}: defaults[{self.key!r}] must be {self.name!r}")
        undocumented = [k for k in self.defaults if k not in self.config_notes()]
        if undocumented:
            raise ValueError(f"{self.name}: config keys without a note: {undocumented}")
        for key in self.all_size_keys():
            try:
                value = get(self.defaults, key)
            except (KeyError, TypeError):
                value = None
            if isinstance(value, bool) or not isinstance(value, int | float | list):
                raise ValueError(f"{self.name}: size key {key!r} is not a number or a list of the defaults")

    def config_notes(self) -> dict:
        """``{dotted key: note}`` of every key, for ``--print-config``."""
        return {self.key: f"the {self.key} (list them with --list)", **self.notes}

    def all_size_keys(self) -> tuple[str, ...]:
        """The dotted keys that set the job's sizes (simulated time, counts, grids, batches): its own
        ``size_keys``, then those every job of its kind has."""
        return self.size_keys + tuple(k for k in self.common_size_keys if k not in self.size_keys)

    def blame(self, config: dict) -> str:
        """The size key that ``config`` raises most over the defaults (relative to the default's value, or its length
        for a list): the one to name when the job exceeds a limit; the first size key when none is raised."""

        def size(value) -> float:
            return float(len(value)) if isinstance(value, list) else abs(float(value))

        def growth(key: str) -> float:
            return size(get(config, key)) / max(size(get(self.defaults, key)), 1e-300)

        keys = self.all_size_keys()
        return max(keys, key=growth) if keys else self.key  # max keeps the first of equal growths

    def validate(self, given: dict | None = None, source: str = "<default>") -> dict:
        """The complete configuration (``given`` over the defaults), or a :class:`jaxobs._config.ConfigError`
        naming ``source`` and the key."""
        config = merge(self.defaults, given or {}, source, open_tables=self.open_tables)
        check_choice(config, source, self.key, (self.name,))
        for key in self.path_keys:  # a file path: from the config file's directory, or a shipped file
            *tables, last = key.split(".")
            table = get(config, ".".join(tables)) if tables else config
            table[last] = resolve_path(table[last], source)
        self.check(config, source)
        return config

    def run(self, config: dict, out_dir, *, source: str = "<default>", progress: bool = True,
            overwrite: bool = False) -> dict | None:  # fmt: skip
        """Run the job on its validated ``config`` (read from ``source``) into ``out_dir`` (:meth:`_run`). A limit it
        exceeds while it is built and compiled (a :class:`jaxobs._resources.LimitError`, or an allocation or a size
        that fails: XLA's ``RESOURCE_EXHAUSTED``, ``MemoryError``, ``OverflowError``) is a
        :class:`jaxobs._config.ConfigError` naming ``source`` and the size key :meth:`blame` finds."""
        try:
            return self._run(config, out_dir, progress=progress, overwrite=overwrite)
        except LimitError as exc:
            reason = exc.reason
        except (MemoryError, OverflowError, jax.errors.JaxRuntimeError) as exc:
            if isinstance(exc, jax.errors.JaxRuntimeError) and "RESOURCE_EXHAUSTED" not in str(exc):
                raise
            first = (str(exc).strip().splitlines() or [""])[0]
            reason = f"the job's sizes exceed this machine ({type(exc).__name__}: {first})"
        key = self.blame(config)
        others = [k for k in self.all_size_keys() if k != key]
        also = f" (sizes are also set by {', '.join(others)})" if others else ""
        fail(source, key, f"{reason}; lower {key}{also}")

    def _run(self, config: dict, out_dir, *, progress: bool, overwrite: bool) -> dict | None:
        raise NotImplementedError


class Sweep(NamedTuple):
    """What a sweep scenario builds from its config, for :func:`jaxobs.sweep.run_configured_sweep`.

    Attributes:
      sampler: ``sampler(key, index) -> dict`` of one configuration's parameters.
      evaluate: ``evaluate(params) -> dict`` of its metrics.
      num_configs: how many configurations.
      context: whatever the report needs besides the rows (e.g. the designs), or None.
    """

    sampler: Callable
    evaluate: Callable
    num_configs: int
    context: Any = None


@dataclasses.dataclass(frozen=True, kw_only=True)
class SweepScenario(_Configured):
    """A Monte-Carlo sweep run by ``jaxobs sweep`` (the config's ``scenario`` key names it).

    Attributes:
      name, summary, defaults, notes, check, open_tables: the config (``check(config, source)`` raises a
        :class:`jaxobs._config.ConfigError` for a bad value).
      build: ``build(config) -> Sweep``.
      report: ``report(config, out_dir, result, context) -> dict`` writes ``summary.json``, ``report.md`` and the
        figures from the finished sweep in ``out_dir`` (``result``: this call's
        :class:`jaxobs.sweep.SweepResult`, or None) and returns the summary (with ``num_configs`` and
        ``figures``).
      size_key: the dotted key that sets the number of configurations: raising it extends a finished sweep in the
        same directory (None: any change starts over).
      size_keys: the dotted keys that set the sweep's sizes (``chunk_size`` is added), named when it exceeds a
        limit (:meth:`run`).
      path_keys: the dotted keys that hold file paths, resolved by :func:`jaxobs.papers.shipped.resolve_path`.
    """

    key: ClassVar[str] = "scenario"
    common_size_keys: ClassVar[tuple[str, ...]] = ("chunk_size",)

    build: Callable[[dict], Sweep]
    report: Callable[..., dict]
    size_key: str | None = None

    def _run(self, config: dict, out_dir, *, progress: bool, overwrite: bool) -> dict | None:
        """Run the sweep (resuming a partial run in ``out_dir``) and write its report; returns the report's summary
        in process 0, None in the other processes of a multi-process run (process 0 writes)."""
        sweep = self.build(config)
        return run_configured_sweep(
            config, sweep.sampler, sweep.evaluate, sweep.num_configs, out_dir, size_key=self.size_key,
            progress=progress, overwrite=overwrite,
            report=lambda result: self.report(config, Path(out_dir), result, sweep.context),
        )  # fmt: skip


@dataclasses.dataclass(frozen=True, kw_only=True)
class TuningScenario(_Configured):
    """A tuning problem run by ``jaxobs tune`` (the config's ``problem`` key names it); the config's
    ``[optimizer]`` and ``[baseline]`` tables and ``seed`` are common to every problem
    (:mod:`jaxobs.papers.tuning_config`) and checked here.

    Attributes:
      name, summary, defaults, notes, check, open_tables: the config.
      build: ``build(config) -> jaxobs.tuning.TuningProblem``; a ``ValueError`` (e.g. an invalid MJCF) is reported
        as a config error.
      size_keys: the dotted keys that set the problem's sizes (``optimizer.screening`` and ``optimizer.starts`` are
        added), named when it exceeds a limit (:meth:`run`).
      path_keys: the dotted keys that hold file paths, resolved by :func:`jaxobs.papers.shipped.resolve_path`.
    """

    key: ClassVar[str] = "problem"
    common_size_keys: ClassVar[tuple[str, ...]] = ("optimizer.screening", "optimizer.starts")

    build: Callable[[dict], Any]

    def config_notes(self) -> dict:
        """Comments on the configuration keys, the tuning keys' included."""
        return {**super().config_notes(), **tuning_config.COMMON_NOTES}

    def validate(self, given: dict | None = None, source: str = "<default>") -> dict:
        """The defaults merged with ``given``, checked, the tuning keys included (a :class:`ConfigError` names the
        first invalid key)."""
        config = super().validate(given, source)
        tuning_config.check_common(config, source)
        return config

    def _run(self, config: dict, out_dir, *, progress: bool, overwrite: bool) -> dict | None:
        """Tune, run the baselines and score on the held-out plants (:func:`jaxobs.papers.tune_job.run`)."""
        return tune_job.run(self, config, out_dir, progress=progress, overwrite=overwrite)
