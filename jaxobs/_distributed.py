"""What the jobs (``jaxobs.sweep``, ``jaxobs.tuning``) need to run in several processes on JAX's distributed runtime
(``jax.distributed.initialize``).

:func:`join` joins a run in bounded time (a malformed coordinator address is an error before anything starts);
:func:`agree` stops every process with the same error when one cannot run the job; :func:`from_process_0` and
:func:`json_from_process_0` give every process process 0's value. All are no-ops (or the identity) in a single
process.
Details: the "Jobs" page of the design notes (docs/theory/jobs.md).
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Callable

import jax
import numpy as np
from jax.experimental import multihost_utils

__all__ = ["DEFAULT_JOIN_TIMEOUT", "coordinator_address", "join", "agree", "from_process_0", "json_from_process_0"]


DEFAULT_JOIN_TIMEOUT = 60.0
"""Seconds a process waits for every process of the run to reach the coordinator (JAX's own default is 300)."""

# JAX's runtime gets this much longer than the watchdog of :func:`join`: its own timeout aborts the process (a C++
# fatal error and a stack trace), which the watchdog pre-empts with one line
_RUNTIME_GRACE_SECONDS = 30


def coordinator_address(address: str) -> str:
    """``address`` checked to be ``HOST:PORT`` (a host name, an IPv4 address or a bracketed IPv6 one, and a port in
    1..65535); :class:`JobError` naming it otherwise (before: an ``IndexError`` deep in JAX)."""
    from jaxobs._resources import JobError

    host, colon, port = address.rpartition(":")
    if not (colon and host and port.isdigit() and 1 <= int(port) <= 65535):
        raise JobError(f"the coordinator address {address!r} must be HOST:PORT, a port in 1..65535: e.g. 10.0.0.1:1234")
    if ":" in host and not (host.startswith("[") and host.endswith("]")):
        raise JobError(f"the coordinator address {address!r}: write an IPv6 host in brackets, e.g. [::1]:1234")
    return address


def join(address: str | None, num_processes: int | None, process_id: int | None, *, timeout: float,
         on_timeout: Callable[[str], None]) -> None:  # fmt: skip
    """Join a multi-process run (``jax.distributed.initialize``), giving up after ``timeout`` seconds.

    Values left None come from the cluster environment that JAX detects (SLURM, Open MPI, ...). Every process waits
    in ``initialize`` until all ``num_processes`` have reached the coordinator at ``address`` (process 0 runs it);
    if that has not happened within ``timeout`` seconds (a partner that never starts, an unreachable host, a port
    that another program holds), ``on_timeout(message)`` is called from a watchdog thread with a one-line message
    naming the address, and must end the process (JAX's runtime would otherwise abort it with a stack trace when
    its own, longer timeout expires). A malformed address or bad counts raise :class:`JobError` before anything
    starts.
    """
    from jaxobs._resources import JobError

    if address is not None:
        coordinator_address(address)
    if isinstance(timeout, bool) or not isinstance(timeout, int | float) or not 0 < timeout < math.inf:
        raise JobError(f"the coordinator timeout must be a positive number of seconds, got {timeout!r}")
    where = f"the coordinator at {address}" if address else "the coordinator"
    who = "" if process_id is None or num_processes is None else f" (process {process_id} of {num_processes})"
    message = (
        f"cannot join the multi-process run{who}: not every process reached {where} within {timeout:g} s; start "
        "the other processes, or check that the address is reachable"
    )
    watchdog = threading.Timer(timeout, on_timeout, args=(message,))
    watchdog.daemon = True
    watchdog.start()
    try:
        jax.distributed.initialize(address, num_processes, process_id,
                                   initialization_timeout=math.ceil(timeout) + _RUNTIME_GRACE_SECONDS)  # fmt: skip
    except (ValueError, RuntimeError) as exc:
        at = f" at {address}" if address else ""
        raise JobError(f"cannot join the multi-process run{at}: {type(exc).__name__}: {exc}") from exc
    finally:
        watchdog.cancel()


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
