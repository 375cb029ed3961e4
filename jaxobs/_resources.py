"""What the jobs (``jaxobs.sweep``, ``jaxobs.tuning`` and the ``jaxobs`` command) need from the machine: a writable
output directory held by one process at a time, atomic writes, and enough memory.

:func:`locked_out_dir` (a re-entrant ``flock`` on ``.jaxobs.lock``), :func:`atomic_write`, :func:`check_memory`,
:func:`program_nbytes` and :func:`compile_checked` (XLA's memory estimate checked before a program runs),
:class:`InterruptWatch` (Ctrl-C noted even when its ``KeyboardInterrupt`` was lost) and :class:`StallWatch` (a
computation that makes no progress reported, never waited on forever). POSIX only (``fcntl``).
Details: docs/theory/jobs.md.
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import fcntl
import logging
import os
import secrets
import signal
import sys
import threading
import time
from pathlib import Path

from jaxobs._checks import MAX_INDEX

__all__ = [
    "JobError",
    "LimitError",
    "MAX_INDEX",
    "Interrupted",
    "InterruptWatch",
    "Stalled",
    "StallWatch",
    "LOCK_NAME",
    "locked_out_dir",
    "atomic_write",
    "temporary_path",
    "available_memory",
    "program_nbytes",
    "check_memory",
    "compile_checked",
    "format_bytes",
]

LOCK_NAME = ".jaxobs.lock"
_held: dict[Path, list] = {}  # resolved directory -> [file descriptor, depth]


class JobError(ValueError):
    """A job cannot run as asked: its output directory is unusable or in use, or it cannot fit in memory."""


class LimitError(JobError):
    """A job beyond a limit of the machine or of JAX: more memory than is available (its estimate), or a count
    beyond :data:`MAX_INDEX`. ``reason`` says what, ``hint`` what to lower; the paper layer names the config key
    instead (:class:`jaxobs.papers.scenarios.SweepScenario`)."""

    def __init__(self, reason: str, hint: str = ""):
        super().__init__(reason + (f"; {hint}" if hint else ""))
        self.reason, self.hint = reason, hint


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during a resumable job; the message says where it stopped and how to resume."""


class Stalled(JobError):
    """A job's computation made no progress within the :class:`StallWatch` bound: the message says which, how long,
    and what to do. The process's JAX runtime stays blocked: the interpreter is ended with ``os._exit`` at exit."""


_FINALISERS = frozenset({"_xla_gc_callback", "__del__"})


def _in_finaliser(frame) -> bool:
    """True when ``frame`` runs inside a garbage-collection callback or a ``__del__`` (XLA frees buffers from one):
    an exception raised there is printed with its traceback and dropped."""
    while frame is not None:
        if frame.f_code.co_name in _FINALISERS:
            return True
        frame = frame.f_back
    return False


class InterruptWatch:
    """A context manager that notes Ctrl-C (SIGINT) while it is entered; :meth:`check` raises
    ``KeyboardInterrupt`` once one arrived, even if the ``KeyboardInterrupt`` the signal raised at the time was
    swallowed. Python's own handler still runs, so Ctrl-C interrupts at once wherever it can, except inside a
    garbage-collection callback or ``__del__``, where it is left to the next :meth:`check`. Installed only in
    the main thread over Python's default handler (a caller's own handler is left alone); a watch entered inside
    another shares its record, so the command's watch sees a Ctrl-C from its first line on.
    """

    def __init__(self):
        self._record = {"requested": False}
        self._installed = False

    @property
    def requested(self) -> bool:
        return self._record["requested"]

    def __enter__(self) -> InterruptWatch:
        if threading.current_thread() is threading.main_thread():
            current = signal.getsignal(signal.SIGINT)
            if current is signal.default_int_handler:
                signal.signal(signal.SIGINT, self._note)
                self._installed = True
            elif isinstance(getattr(current, "__self__", None), InterruptWatch):
                self._record = current.__self__._record
        return self

    def __exit__(self, *exc_info) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, signal.default_int_handler)
            self._installed = False

    def _note(self, signum, frame) -> None:
        self._record["requested"] = True
        if not _in_finaliser(frame):  # there Python would print the KeyboardInterrupt as "Exception ignored"
            signal.default_int_handler(signum, frame)

    def check(self) -> None:
        """Raise ``KeyboardInterrupt`` if Ctrl-C arrived since the (outermost) watch was entered."""
        if self.requested:
            raise KeyboardInterrupt


def _check_writable(path: Path) -> None:
    if path.exists() and not path.is_dir():
        raise JobError(f"{path} exists and is not a directory; choose another output directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = temporary_path(path / ".jaxobs-write-test")
        with open(probe, "wb") as f:
            f.write(b"0")
            f.flush()
            os.fsync(f.fileno())
        probe.unlink()
    except OSError as exc:
        raise JobError(f"cannot write to {path}: {exc.strerror or exc}; choose another output directory") from exc


def _holder(fd: int) -> str:
    os.lseek(fd, 0, os.SEEK_SET)
    text = os.read(fd, 64).decode(errors="replace").strip()
    return f"pid {text}" if text.isdigit() else "pid unknown"


@contextlib.contextmanager
def locked_out_dir(path):
    """Check that ``path`` can be written (creating it) and hold its lock for the ``with`` block; yields ``path``.

    Raises :class:`JobError` naming the directory (and the holder's pid when another process has it).
    """
    path = Path(path)
    _check_writable(path)
    key = path.resolve()
    if key in _held:
        _held[key][1] += 1
        try:
            yield path
        finally:
            _held[key][1] -= 1
        return
    try:
        fd = os.open(key / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise JobError(f"cannot create the lock file in {path}: {exc.strerror or exc}") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _holder(fd)
        os.close(fd)
        raise JobError(
            f"{path} is in use by another jaxobs process ({holder}); wait for it to finish or choose another "
            "output directory"
        ) from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _held[key] = [fd, 1]
    try:
        yield path
    finally:
        _held[key][1] -= 1
        if _held[key][1] == 0:
            del _held[key]
            os.close(fd)  # releases the flock


def temporary_path(path: Path, suffix: str = ".tmp") -> Path:
    """``path`` + ``.<pid>.<random>`` + ``suffix``: a temporary name no other writer uses."""
    return path.with_name(f"{path.name}.{os.getpid()}.{secrets.token_hex(4)}{suffix}")


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file next to ``path``, fsync, then ``os.replace`` it onto ``path``."""
    tmp = temporary_path(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _read_int(path: str) -> int | None:
    try:
        text = Path(path).read_text().split()[0]
    except (OSError, IndexError):
        return None
    return int(text) if text.isdigit() else None


def _host_memory() -> int | None:
    """Bytes of host memory available: ``MemAvailable`` capped by the cgroup's limit minus its usage."""
    available = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                available = int(line.split()[1]) * 1024
    except OSError:
        pass
    if available is None and hasattr(os, "sysconf"):
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError):
            pass
    for limit_file, usage_file in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),  # cgroup v2
        ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"),  # v1
    ):
        limit, usage = _read_int(limit_file), _read_int(usage_file)
        if limit is not None and limit < 2**60:  # "max" or a huge number: no limit
            room = max(limit - (usage or 0), 0)
            available = room if available is None else min(available, room)
            break
    return available


def available_memory(device=None) -> int | None:
    """Bytes free for a new allocation on ``device`` (default: the host); None where unknown."""
    if device is None or device.platform == "cpu":
        return _host_memory()
    try:
        stats = device.memory_stats() or {}
    except Exception:  # noqa: BLE001 - some backends do not implement memory_stats
        return None
    if "bytes_limit" not in stats:
        return None
    return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))


def program_nbytes(compiled) -> int | None:
    """XLA's estimate of the memory one run of ``compiled`` needs per device (arguments, outputs, temporaries
    and code); None where the backend gives no memory analysis."""
    try:
        stats = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not implemented on every backend
        return None
    if stats is None:
        return None
    return int(
        stats.argument_size_in_bytes + stats.output_size_in_bytes + stats.temp_size_in_bytes
        + stats.generated_code_size_in_bytes - stats.alias_size_in_bytes
    )  # fmt: skip


def format_bytes(n: float) -> str:
    """``1.6e12`` -> ``"1.6 TB"`` (decimal units)."""
    units, i = ("bytes", "KB", "MB", "GB", "TB", "PB"), 0
    while abs(n) >= 1000 and i < len(units) - 1:
        n, i = n / 1000, i + 1
    return f"{n:.0f} bytes" if i == 0 else f"{n:.3g} {units[i]}"


def check_memory(nbytes: int | None, what: str, device=None, hint: str = "") -> None:
    """Raise :class:`LimitError` if ``nbytes`` (an estimate of what ``what`` allocates) exceeds the memory
    available on ``device`` (default: the host). Unknown sizes or unknown free memory pass."""
    free = available_memory(device)
    if nbytes is None or free is None or nbytes <= free:
        return
    where = "memory" if device is None or device.platform == "cpu" else f"memory on {device.device_kind}"
    raise LimitError(
        f"{what} needs about {format_bytes(nbytes)} (estimated), more than the {format_bytes(free)} of {where} "
        "available",
        hint,
    )


def compile_checked(lowered, what: str, hint: str = ""):
    """Compile ``lowered`` (a ``jax.jit(f).lower(...)``) after checking that one run fits in the memory of this
    process's first device (:class:`LimitError` otherwise)."""
    import jax

    compiled = lowered.compile()
    check_memory(program_nbytes(compiled), what, device=jax.local_devices()[0], hint=hint)
    return compiled


_log = logging.getLogger(__name__)


class StallWatch:
    """Reports a job's computation that makes no progress instead of waiting on it forever.

    ``with StallWatch(what, hint, cpu=...) as watch:`` starts a monitor thread; each blocking wait of the job runs
    in ``with watch.waiting(label, program):``. A wait is stalled when

    * on CPU devices (``cpu=True``), the process used less than 2 % of one core over the last
      :attr:`IDLE_SECONDS` (a deadlocked runtime, e.g. jaxlib's batched LAPACK kernels of
      :mod:`jaxobs.batching`, leaves every thread waiting), or
    * it has lasted more than :attr:`FACTOR` times the slowest completed wait of the same ``program`` (and at
      least :attr:`MIN_SECONDS`). A program's first wait has no time bound: it may include its compilation.

    Then the monitor logs an error naming ``label`` and interrupts the main thread: the wait raises
    :class:`Stalled` (message: the stall, its bound and ``hint``). A deadlocked runtime cannot be stopped, and
    would keep the interpreter from exiting: if ``pending`` (the arrays the wait is for) are not ready at exit, the
    process ends with ``os._exit(1)`` once the exit handlers before this one have run.
    """

    POLL_SECONDS = 0.5
    IDLE_SHARE = 0.02
    IDLE_SECONDS = 60.0
    FACTOR = 20.0
    MIN_SECONDS = 60.0

    def __init__(self, what: str, hint: str, *, cpu: bool):
        self.what, self.hint, self.cpu = what, hint, cpu
        self.idle_seconds, self.factor, self.min_seconds = self.IDLE_SECONDS, self.FACTOR, self.MIN_SECONDS
        self.slowest: dict = {}  # program -> seconds of its slowest completed wait
        self._lock, self._stop = threading.Lock(), threading.Event()
        self._wait: dict | None = None
        self._thread: threading.Thread | None = None
        self.message = ""

    def __enter__(self) -> StallWatch:
        self._thread = threading.Thread(target=self._monitor, name="jaxobs-stall-watch", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()

    def bound(self, program="") -> float | None:
        """Seconds after which a wait of ``program`` is stalled whatever the CPU does (None: no bound yet)."""
        slowest = self.slowest.get(program)
        return None if slowest is None else max(self.min_seconds, self.factor * slowest)

    @contextlib.contextmanager
    def waiting(self, label: str, program=""):
        """Watch the ``with`` block (one blocking computation of ``program``, any hashable key; ``label`` names the
        wait); yields a dict where the block puts its ``"pending"`` arrays (checked at exit after a stall)."""
        wait = {"label": label, "program": program, "start": time.perf_counter(), "cpu": collections.deque(),
                "pending": None, "fired": False}  # fmt: skip
        with self._lock:
            self._wait = wait
        try:
            yield wait
        except BaseException:  # the interrupt, or what it became inside JAX (an error of a host callback)
            if wait["fired"]:
                raise Stalled(self.message) from None
            raise
        finally:
            with self._lock:
                self._wait = None
        if wait["fired"]:  # fired as the computation ended: its interrupt may still be pending
            raise Stalled(self.message)
        self.slowest[program] = max(self.slowest.get(program, 0.0), time.perf_counter() - wait["start"])

    def _stalled(self, wait: dict, now: float) -> str | None:
        """Why ``wait`` counts as stalled at ``now``, or None."""
        elapsed = now - wait["start"]
        samples = wait["cpu"]
        samples.append((now, time.process_time()))
        while len(samples) > 1 and samples[1][0] <= now - self.idle_seconds:
            samples.popleft()
        if self.cpu and elapsed >= self.idle_seconds and samples[0][0] <= now - self.idle_seconds:
            used = samples[-1][1] - samples[0][1]
            if used < self.IDLE_SHARE * (now - samples[0][0]):
                return f"the CPU stayed idle ({used:.2f} s of CPU in the last {now - samples[0][0]:.0f} s)"
        bound = self.bound(wait["program"])
        if bound is not None and elapsed > bound:
            return f"it has run {elapsed:.3g} s, over {self.factor:g}x the slowest step so far ({bound:.3g} s)"
        return None

    def _monitor(self) -> None:
        while not self._stop.wait(self.POLL_SECONDS):
            with self._lock:
                wait = self._wait
                why = None if wait is None or wait["fired"] else self._stalled(wait, time.perf_counter())
                if why is None:
                    continue
                wait["fired"] = True
                self.message = (
                    f"{self.what}: {wait['label']} made no progress ({why}); it is left running, and this "
                    f"process is ended at exit if it has not finished by then; {self.hint}"
                )
                _log.error("%s", self.message)
                atexit.register(_exit_if_pending, wait)
                signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)  # wakes a blocking call too


def _exit_if_pending(wait: dict) -> None:
    """At exit after a stall: end the process at once if the stalled computation never finished (the runtime's
    own clean-up would wait on it forever)."""
    import jax

    pending = [leaf for leaf in jax.tree.leaves(wait["pending"]) if hasattr(leaf, "is_ready")]
    if wait["pending"] is None or not all(leaf.is_ready() for leaf in pending):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(1)
