"""Multi-process runs on JAX's distributed runtime, on one machine: N local processes (each with its own CPU
devices, collectives through gloo) joined by ``jax.distributed.initialize`` with a coordinator on 127.0.0.1.

``run_sweep`` in 2 and 4 processes gives the one-process rows bit for bit, only process 0 writes, a run killed in
one process resumes when all are rerun (with another process count, too), processes that run different sweeps
are refused in every process, and an evaluation with LAPACK kernels runs on every device. The sweep is the one of
tests/test_sweep.py (tests/sweep_scripts/sweep_case.py).

``tune`` (tests/sweep_scripts/tune_case.py: an analytic problem, and the shipped 1-DOF force problem on MJX at tiny
sizes) in 2 and 4 processes, and in one process with 4 CPU devices, gives one device's parameter history and
objective up to the order of the gradient's sums, only process 0 writes the checkpoint, a killed run resumes in
another process count, and ``jaxobs tune`` runs in 2 processes.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from jaxobs.sweep import load_results, run_sweep
from tests import ROOT

SCRIPT = Path(__file__).parent / "sweep_scripts" / "sweep_case.py"
N, CHUNK = 1000, 128  # 8 chunks, the last one partial


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(devices: int, extra=None) -> dict:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAX_NUM_CPU_DEVICES": str(devices), **(extra or {})}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    return env


def _start(script: Path, processes: int, args, devices=1, env=None):
    """Start ``processes`` copies of ``script`` with ``args(pid)`` joined on a free local port (one process alone
    joins nothing)."""
    port, procs = _free_port(), []
    for pid in range(processes):
        join = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(processes), "--process-id", str(pid)]
        cmd = [sys.executable, str(script), *map(str, args(pid)), *(join if processes > 1 else [])]
        procs.append(subprocess.Popen(cmd, env=_env(devices, env), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True))  # fmt: skip
    return procs


def _launch(processes: int, *args, devices=1, env=None, nums=None):
    """Start ``processes`` copies of the sweep script (``nums``: per-process N)."""
    return _start(SCRIPT, processes, lambda pid: [*args, "--num", N if nums is None else nums[pid], "--chunk", CHUNK],
                  devices, env)  # fmt: skip


def _finish(procs, timeout=240, ok=True):
    """Each process's (return code, JSON lines of stdout, stderr)."""
    results = []
    for proc in procs:
        out, err = proc.communicate(timeout=timeout)
        assert (proc.returncode == 0) == ok, err[-3000:]
        results.append((proc.returncode, [json.loads(x) for x in out.splitlines() if x.startswith("{")], err))
    return results


def _one_process(out, evaluate="evaluate"):
    import importlib.util

    spec = importlib.util.spec_from_file_location("sweep_case", SCRIPT)
    case = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(case)
    run_sweep(case.sampler, getattr(case, evaluate), N, out, chunk_size=CHUNK, config=case.CONFIG, progress=False)
    return load_results(out)


def _assert_same(got, want):
    assert list(got) == list(want)
    for name in want:
        assert got[name].dtype == want[name].dtype and np.array_equal(got[name], want[name]), name


def _manifest(out):
    return json.loads((Path(out) / "manifest.json").read_text())


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    return _one_process(tmp_path_factory.mktemp("mp") / "reference")


def test_importing_jaxobs_starts_no_backend():
    """``jax.distributed.initialize`` must come before any backend starts; importing jaxobs (and its command's
    scenarios) must not start one."""
    code = (
        "import jax._src.xla_bridge as xb\n"
        "xb.backends = lambda *a, **k: (_ for _ in ()).throw(AssertionError('a backend started at import'))\n"
        "import jaxobs, jaxobs.cli, jaxobs.sweep, jaxobs.tuning\n"
        "from jaxobs.papers.registry import sweep_scenarios\nsweep_scenarios()\n"
    )
    subprocess.run([sys.executable, "-c", code], env=_env(1), check=True, timeout=120, capture_output=True)


@pytest.mark.slow  # ~11 s: three processes
def test_two_processes_match_one_process_and_only_process_0_writes(reference, tmp_path):
    out = tmp_path / "sweep"
    results = _finish(_launch(2, out, devices=2))
    for pid, (_, lines, _) in enumerate(results):
        sweep, info = lines
        assert (sweep["chunks_computed"], sweep["chunks_reused"]) == (8, 0)
        assert (info["devices"], info["processes"]) == (4, 2)
        assert (info["files_written"] > 0) == (pid == 0), f"process {pid} wrote {info['files_written']} files"
    _assert_same(load_results(out), reference)
    m = _manifest(out)
    assert (m["device_count"], m["process_count"]) == (4, 2)
    assert {(e["device_count"], e["process_count"]) for e in m["completed"].values()} == {(4, 2)}


@pytest.mark.slow
def test_four_processes_killed_in_one_resume_in_two(reference, tmp_path):
    """SIGKILL one of 4 processes mid-sweep (then the rest, as a scheduler does), rerun in 2 processes: the chunks
    done are reused and the rows equal the one-process sweep."""
    out = tmp_path / "sweep"
    procs = _launch(4, out, env={"SWEEP_SLEEP": "0.5"})  # every chunk sleeps in a host callback
    deadline, done = time.monotonic() + 180, 0
    try:
        while done < 2:
            assert all(p.poll() is None for p in procs), [p.communicate()[1][-2000:] for p in procs if p.poll()]
            assert time.monotonic() < deadline, "the sweep made no progress"
            time.sleep(0.05)
            if (out / "manifest.json").exists():
                done = len(_manifest(out)["completed"])
        procs[2].send_signal(signal.SIGKILL)
        procs[2].communicate()
    finally:
        for proc in procs:
            proc.kill()
            proc.communicate()
    done = len(_manifest(out)["completed"])
    assert 2 <= done < 8, "the processes were not killed mid-sweep"

    results = _finish(_launch(2, out))
    for _, (sweep, info), _ in results:
        assert sweep["chunks_reused"] >= done and sweep["chunks_reused"] + sweep["chunks_computed"] == 8
        assert (info["devices"], info["processes"]) == (2, 2)
    _assert_same(load_results(out), reference)
    counts = {e["process_count"] for e in _manifest(out)["completed"].values()}
    assert counts == {4, 2}


@pytest.mark.slow
def test_processes_running_different_sweeps_all_stop(tmp_path):
    results = _finish(_launch(2, tmp_path / "sweep", nums=[N, N + 1]), ok=False)
    for returncode, _, err in results:
        assert returncode != 0 and "run a different sweep from process 0's" in err, err[-2000:]
    assert not (tmp_path / "sweep" / "manifest.json").exists()


@pytest.mark.slow
def test_lapack_evaluation_runs_on_every_device(tmp_path):
    """2 processes x 2 CPU devices: an evaluation with a batched LAPACK solve runs on all 4 devices (its blocks
    keep jaxlib's kernels sequential, so several devices cannot deadlock them) and gives the one-process rows."""
    want = _one_process(tmp_path / "one", evaluate="evaluate_lapack")
    out = tmp_path / "sweep"
    _finish(_launch(2, out, "--lapack", devices=2))
    _assert_same(load_results(out), want)
    assert (_manifest(out)["device_count"], _manifest(out)["process_count"]) == (4, 2)


@pytest.mark.slow
def test_cli_sweep_in_two_processes_matches_one_process(tmp_path):
    """``jaxobs sweep --coordinator ... --num-processes 2 --process-id I``, one CPU device each: the rows and the
    report of one process with two CPU devices (the same mesh). (This scenario's rows on one device differ from
    those on two in the last bit of two RMS columns, in one process as well.)"""
    config = tmp_path / "hgo.toml"
    config.write_text(
        'scenario = "dc-motor-hgo"\nchunk_size = 2\n[grid]\neps = [1.0, 0.2]\nsigma = [0.0, 1e-2]\n'
        "alpha_0 = [0.28]\nseeds = 1\n[simulation]\nduration = 2.0\nrms_start = 1.0\n"
    )
    one, two = tmp_path / "one", tmp_path / "two"
    cmd = [sys.executable, "-m", "jaxobs.cli", "sweep", "--config", str(config), "--no-progress", "--no-cache"]
    subprocess.run([*cmd, "--out", str(one)], env=_env(2), check=True, capture_output=True, timeout=300)
    cmd += ["--out", str(two), "--coordinator", f"127.0.0.1:{_free_port()}", "--num-processes", "2"]
    procs = [subprocess.Popen([*cmd, "--process-id", str(pid)], env=_env(1), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for pid in range(2)]  # fmt: skip
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs[0][1][-2000:] + outs[1][1][-2000:]
    assert "4 configurations" in outs[0][0] and "4 configurations" not in outs[1][0]
    assert "process 1 of 2: done" in outs[1][0]
    _assert_same(load_results(two), load_results(one))
    summary = [json.loads((out / "summary.json").read_text()) for out in (one, two)]
    for s in summary:  # wall times differ
        for key in ("seconds", "configs_per_second", "compile_seconds", "compute_seconds"):
            s.pop(key, None)
    assert summary[0] == summary[1]
    assert sorted(p.name for p in two.iterdir()) == sorted(p.name for p in one.iterdir())


def test_cli_without_a_coordinator_exits_2():
    """A launch that names no coordinator (and no cluster environment to find one) is a user error."""
    cmd = [sys.executable, "-m", "jaxobs.cli", "sweep", "--num-processes", "2", "--process-id", "0", "--no-cache"]
    done = subprocess.run(cmd, env=_env(1), capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "cannot join the multi-process run: ValueError: coordinator_address" in done.stderr


@pytest.mark.parametrize("address", ["nonsense", "127.0.0.1", "127.0.0.1:0", "127.0.0.1:65536", ":1234", "::1:1234"])
def test_a_malformed_coordinator_address_exits_2_naming_it(tmp_path, capsys, address):
    """``--coordinator nonsense`` (or no port, a port out of range, an IPv6 host without brackets): one line naming
    the address, before anything starts (before: an IndexError traceback in JAX)."""
    from jaxobs.cli import main

    argv = ["sweep", "--coordinator", address, "--num-processes", "2", "--process-id", "0", "--out", str(tmp_path)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"jaxobs sweep: the coordinator address {address!r}")


@pytest.mark.parametrize("timeout", ["0", "-1", "nan", "inf"])
def test_a_coordinator_timeout_that_is_not_a_positive_number_exits_2(tmp_path, capsys, timeout):
    from jaxobs.cli import main

    argv = ["tune", "--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "1",
            "--coordinator-timeout", timeout, "--out", str(tmp_path)]  # fmt: skip
    assert main(argv) == 2
    assert capsys.readouterr().err.strip().startswith("jaxobs tune: the coordinator timeout must be a positive")


@pytest.mark.parametrize("command, process_id", [("sweep", 0), ("tune", 1)])
def test_a_partner_that_never_comes_fails_in_bounded_time_with_one_line(command, process_id):
    """Process 0 (which runs the coordinator) or 1 of a two-process run whose other process never starts: exit 2
    after --coordinator-timeout (2 s here) with one line naming the address (before: silence for JAX's 300 s, then
    an abort with a stack trace)."""
    address = f"127.0.0.1:{_free_port()}"
    cmd = [sys.executable, "-m", "jaxobs.cli", command, "--coordinator", address, "--num-processes", "2",
           "--process-id", str(process_id), "--coordinator-timeout", "2", "--no-cache"]  # fmt: skip
    start = time.monotonic()
    done = subprocess.run(cmd, env=_env(1), capture_output=True, text=True, timeout=120)
    elapsed = time.monotonic() - start
    assert done.returncode == 2, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr[-2000:]
    assert lines[0].startswith(f"jaxobs {command}: cannot join the multi-process run (process {process_id} of 2)")
    assert address in lines[0] and "within 2 s" in lines[0]
    assert elapsed < 60  # the timeout plus the start of Python and JAX, far below JAX's default of 300 s


# --------------------------------------------------------------------------------------------
# tune

TUNE_SCRIPT = Path(__file__).parent / "sweep_scripts" / "tune_case.py"
TINY_TUNE = """
[plants]
train = 3
heldout = 2
[scenario]
duration = 0.4
[optimizer]
steps = 3
checkpoint_every = 1
screening = 15
evolve = 3
[baseline]
random_search = false
"""


def _tune(processes: int, checkpoint, *args, devices=1, env=None):
    """Run tune_case.py in ``processes`` processes with ``checkpoint``; each one's JSON line."""
    procs = _start(TUNE_SCRIPT, processes, lambda pid: [checkpoint, *args], devices, env)
    return [lines[-1] for _, lines, _ in _finish(procs, timeout=900)]


def _tiny_config(tmp_path) -> list:
    """``--config`` of the default (1-DOF force, MJX) tuning problem at tiny sizes."""
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TUNE)
    return ["--config", config]


def _assert_same_tuning(got, want, rtol=1e-12):
    """The same evaluations, objectives and parameters up to ``rtol`` (the order of the gradient's sums)."""
    assert [(h["accepted"], h["diverged"]) for h in got["history"]] == [
        (h["accepted"], h["diverged"]) for h in want["history"]
    ]
    for mine, theirs in zip(got["history"] + [got], want["history"] + [want], strict=True):
        np.testing.assert_allclose(mine["objective"], theirs["objective"], rtol=rtol, atol=0)
        for key, value in theirs["theta"].items():
            np.testing.assert_allclose(mine["theta"][key], value, rtol=rtol, atol=0, err_msg=key)
    if "heldout" in want:
        np.testing.assert_allclose(got["heldout"], want["heldout"], rtol=rtol, atol=0)


@pytest.fixture(scope="module")
def tuned(tmp_path_factory):
    """The analytic problem of tune_case.py tuned in one process on one CPU device."""
    (result,) = _tune(1, tmp_path_factory.mktemp("tune") / "one.npz", "--evaluate")
    assert (result["devices"], result["processes"], len(result["history"])) == (1, 1, 5)
    return result


@pytest.fixture(scope="module")
def tuned_mjx(tmp_path_factory):
    """The tiny MJX problem tuned in one process on one CPU device."""
    tmp = tmp_path_factory.mktemp("tune_mjx")
    (result,) = _tune(1, tmp / "one.npz", *_tiny_config(tmp))
    assert (result["devices"], result["processes"], len(result["history"])) == (1, 1, 3)
    return result


@pytest.mark.slow
def test_tune_in_two_processes_matches_one_process(tuned, tmp_path):
    """2 processes of one CPU device (3 training plants padded to 4 rows): the parameter history, objectives and
    held-out losses of one device; only process 0 writes the checkpoint."""
    results = _tune(2, tmp_path / "two.npz", "--evaluate")
    for pid, result in enumerate(results):
        assert (result["devices"], result["processes"]) == (2, 2)
        assert (result["checkpoints_written"] > 0) == (pid == 0)
        _assert_same_tuning(result, tuned)


@pytest.mark.slow
@pytest.mark.parametrize("processes, devices", [(4, 1), (1, 4)])
def test_tune_on_four_devices_matches_one_device(tuned, tmp_path, processes, devices):
    """4 processes of one CPU device, or one process of 4 (3 plants padded to 4 rows)."""
    for result in _tune(processes, tmp_path / "four.npz", "--evaluate", devices=devices):
        assert (result["devices"], result["processes"]) == (4, processes)
        _assert_same_tuning(result, tuned)


@pytest.mark.slow
def test_tune_with_lapack_runs_on_every_device(tuned, tmp_path):
    """2 processes x 2 CPU devices, an evaluation with a batched LAPACK solve: computed on all 4 devices, with
    the one-device numbers."""
    procs = _start(TUNE_SCRIPT, 2, lambda pid: [tmp_path / "lapack.npz", "--evaluate", "--lapack"], devices=2)
    results = _finish(procs, timeout=900)
    for _, lines, _err in results:
        assert (lines[-1]["devices"], lines[-1]["processes"]) == (4, 2)
        _assert_same_tuning(lines[-1], tuned)


@pytest.mark.slow
def test_tune_of_the_mjx_problem_in_two_processes_matches_one_process(tuned_mjx, tmp_path):
    """The shipped 1-DOF force problem (MJX rollouts) at tiny sizes."""
    results = _tune(2, tmp_path / "two.npz", *_tiny_config(tmp_path))
    for pid, result in enumerate(results):
        assert (result["devices"], result["processes"], result["checkpoints_written"] > 0) == (2, 2, pid == 0)
        _assert_same_tuning(result, tuned_mjx)


def _kill_after_first_checkpoint(procs, checkpoint, timeout: float = 300) -> None:
    """SIGKILL ``procs`` as soon as ``checkpoint`` exists (each write sleeps first, so the kill lands mid-run)."""
    deadline = time.monotonic() + timeout
    try:
        while not checkpoint.exists():
            assert all(p.poll() is None for p in procs), [p.communicate()[1][-2000:] for p in procs if p.poll()]
            assert time.monotonic() < deadline, "no checkpoint was written"
            time.sleep(0.05)
    finally:
        for proc in procs:
            proc.kill()
            proc.communicate()


@pytest.mark.slow
def test_tune_killed_in_two_processes_resumes_in_one(tuned, tmp_path):
    """SIGKILL both processes once process 0 has written a checkpoint (each write sleeps first), then rerun in one
    process: it resumes where process 0 stopped and ends where the uninterrupted run ended."""
    checkpoint = tmp_path / "killed.npz"
    _kill_after_first_checkpoint(_start(TUNE_SCRIPT, 2, lambda pid: [checkpoint], env={"TUNE_SLEEP": "2"}), checkpoint)
    (result,) = _tune(1, checkpoint, "--evaluate")
    assert 0 < result["checkpoints_written"] < 6  # resumed, not restarted (6 writes from the start)
    _assert_same_tuning(result, tuned)


@pytest.mark.slow
def test_cli_tune_in_two_processes(tuned_mjx, tmp_path):
    """``jaxobs tune --coordinator ... --num-processes 2 --process-id I``: process 0 writes tuned.json and prints the
    summary, process 1 writes nothing (not even its own --out)."""
    config = _tiny_config(tmp_path)[1]
    cmd = [sys.executable, "-m", "jaxobs.cli", "tune", "--config", str(config), "--no-progress", "--no-cache",
           "--coordinator", f"127.0.0.1:{_free_port()}", "--num-processes", "2"]  # fmt: skip
    procs = [
        subprocess.Popen([*cmd, "--out", str(tmp_path / f"out{pid}"), "--process-id", str(pid)], env=_env(1),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for pid in range(2)
    ]  # fmt: skip
    outs = [p.communicate(timeout=900) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs[0][1][-2000:] + outs[1][1][-2000:]
    assert "6 gradient evaluations" in outs[0][0] and "process 1 of 2: done" in outs[1][0]
    assert not (tmp_path / "out1").exists()
    summary = json.loads((tmp_path / "out0" / "tuned.json").read_text())
    assert summary["evaluations"] == 6  # 2 starts x 3 steps
    np.testing.assert_allclose(summary["train_objective"]["tuned"], tuned_mjx["objective"], rtol=1e-12)


def test_a_killed_population_run_resumes_to_the_same_result(tmp_path):
    """3 starts seeded by 7 screened candidates (analytic problem): SIGKILL once the first checkpoint is written
    (the screening's), rerun: it resumes without screening again and ends where the uninterrupted run ended,
    start by start."""
    population = ["--starts", "3", "--screening", "7"]
    (straight,) = _tune(1, tmp_path / "straight.npz", *population)
    checkpoint = tmp_path / "killed.npz"
    _kill_after_first_checkpoint(
        _start(TUNE_SCRIPT, 1, lambda pid: [checkpoint, *population], env={"TUNE_SLEEP": "2"}), checkpoint
    )
    (resumed,) = _tune(1, checkpoint, *population)
    assert 0 < resumed["checkpoints_written"] < straight["checkpoints_written"]  # resumed, not restarted
    _assert_same_tuning(resumed, straight)
    assert len(resumed["starts"]) == 3
    for got, want in zip(resumed["starts"], straight["starts"], strict=True):
        assert (got["stopped"], got["evaluations"]) == (want["stopped"], want["evaluations"])
        np.testing.assert_allclose(got["objective"], want["objective"], rtol=1e-12)
        np.testing.assert_allclose(got["theta"]["log_gain"], want["theta"]["log_gain"], rtol=1e-12)
