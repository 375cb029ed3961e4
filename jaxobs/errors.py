"""The errors of jaxobs' jobs (:func:`jaxobs.sweep.run_sweep`, :func:`jaxobs.tuning.tune` and the ``jaxobs``
command), to catch in your own programs.

:class:`JobError` (a ``ValueError``): a job cannot run as asked; :class:`LimitError` and :class:`Stalled` are
JobErrors, as are :class:`jaxobs.sweep.SweepError` and the ``jaxobs`` command's configuration errors.
:class:`Interrupted` (a ``KeyboardInterrupt``): Ctrl-C stopped a resumable job. What each job raises, and when:
docs/theory/jobs.md.

Example:
  >>> from jaxobs.errors import Interrupted, JobError, Stalled
  >>> issubclass(Stalled, JobError), issubclass(Interrupted, KeyboardInterrupt)
  (True, True)
"""

from __future__ import annotations

__all__ = ["JobError", "LimitError", "Interrupted", "Stalled"]


class JobError(ValueError):
    """A job cannot run as asked: its output directory is unusable or in use, or it cannot fit in memory."""


class LimitError(JobError):
    """A job beyond a limit of the machine or of JAX: more memory than is available (its estimate), or a count
    beyond ``2**31 - 1``. ``reason`` says what, ``hint`` what to lower; the ``jaxobs`` command names the config
    key instead."""

    def __init__(self, reason: str, hint: str = ""):
        """The error of ``reason``, with ``hint`` (what to lower) after it in the message."""
        super().__init__(reason + (f"; {hint}" if hint else ""))
        self.reason, self.hint = reason, hint


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during a resumable job; the message says where it stopped and how to resume (the same call)."""


class Stalled(JobError):
    """A job's computation made no progress within the stall watch's bound (its CPU idle for a minute, or many
    times slower than the slowest step before it): the message says which, how long, and what to do (e.g. a
    smaller ``chunk_size``). The process's JAX runtime stays blocked: the interpreter is ended with ``os._exit``
    at exit."""
