"""What the jobs (``jaxobs.sweep``, ``jaxobs.tuning``) need to run in several processes on JAX's distributed runtime
(``jax.distributed.initialize``), and on several CPU devices of one process.

:func:`agree` stops every process with the same error when one cannot run the job; :func:`from_process_0` and
:func:`json_from_process_0` give every process process 0's value; :func:`lapack_guard` runs programs with jaxlib's
blocking LAPACK kernels on one CPU device per process. All are no-ops (or the identity) in a single process.
Details: the "Jobs" page of the design notes (docs/theory/jobs.md).
"""

from __future__ import annotations

import json
import logging
import re

import jax
import numpy as np
from jax.experimental import multihost_utils

__all__ = ["agree", "from_process_0", "json_from_process_0", "lapack_guard"]

_BLOCKING_LAPACK = re.compile(r'custom_call_target="lapack_(?!\w*trsm)\w+"')


def agree(error: Exception | None, digest: bytes = b"", *, job: str, kind: str, differs: str, error_type) -> None:
    """Raise in every process if one process failed (``error``) or, given the ``digest`` of its job (its first
    16 bytes are compared), runs a different job from process 0's; a no-op in a single process apart from
    raising ``error``.

    Args:
      error: this process's error, or None.  digest: what identifies this process's job.
      job: the job in the message for a failed process ("the sweep in out/x").  kind: the job's kind ("sweep").
      differs: what may differ, for the message.  error_type: the exception raised in the other processes.
    """
    if jax.process_count() > 1:
        mine = np.append(np.frombuffer(digest.ljust(16, b"\0")[:16], np.int32), int(error is not None))
        table = np.asarray(multihost_utils.process_allgather(mine.astype(np.int32)))  # (processes, 5)
        failed = np.flatnonzero(table[:, -1]).tolist()
        other = np.flatnonzero((table[:, :-1] != table[0, :-1]).any(axis=1)).tolist()
        if error is None and failed:
            raise error_type(f"process(es) {failed} could not run {job} (see their error)")
        if error is None and other:
            raise error_type(
                f"process(es) {other} run a different {kind} from process 0's ({differs}); run the same call in "
                "every process"
            )
    if error is not None:
        raise error


def from_process_0(tree):
    """Process 0's ``tree`` (a pytree of arrays of the same shapes and dtypes in every process) in every process, as
    NumPy arrays; the identity in a single process."""
    if jax.process_count() == 1:
        return tree
    return jax.tree.map(np.asarray, multihost_utils.broadcast_one_to_all(tree))


def json_from_process_0(value):
    """Process 0's ``value`` (anything JSON can hold; the other processes' values may differ in anything) in every
    process; the identity in a single process."""
    if jax.process_count() == 1:
        return value
    data = np.frombuffer(json.dumps(value).encode(), np.uint8) if jax.process_index() == 0 else np.zeros(0, np.uint8)
    size = int(from_process_0(np.int64(data.size)))
    return json.loads(from_process_0(np.resize(data, size)).tobytes().decode())


def lapack_guard(compiled, devices: list, log: logging.Logger) -> list | None:
    """One device per process instead of ``devices`` when ``compiled`` (a program over all of ``devices``) runs
    on several CPU devices of a process and calls jaxlib's blocking LAPACK kernels (logged on ``log``); None
    when ``devices`` are fine."""
    one_per_process = [next(d for d in devices if d.process_index == p) for p in range(jax.process_count())]
    if len(devices) == len(one_per_process) or devices[0].platform != "cpu":
        return None
    kernels = sorted(set(_BLOCKING_LAPACK.findall(compiled.as_text())))
    if not kernels:
        return None
    log.warning(
        "the computation calls jaxlib's batched CPU LAPACK kernels (%s), which can deadlock when several CPU "
        "devices run them at once; computing on %d device(s), one per process, instead of %d",
        ", ".join(k.split('"')[1] for k in kernels), len(one_per_process), len(devices),
    )  # fmt: skip
    return one_per_process
