"""jaxobs.sweep: columns and values, chunk-size and device-count independence, resume after damage, SIGKILL
and KeyboardInterrupt, refusal of a different sweep (config, columns or the program's fingerprint) and of a
damaged manifest, extension to more configurations, the lock against a second process, the memory check,
input validation.

The sweep itself (a 50-step damped oscillator with sampled parameters) lives in sweep_scripts/sweep_case.py so
that subprocesses run exactly the same functions as this process.
"""

import importlib.util
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxobs.sweep as sweep
from jaxobs.errors import Interrupted, JobError
from jaxobs.sweep import SweepError, config_key, load_results, run_history, run_sweep

SCRIPT = Path(__file__).parent / "sweep_scripts" / "sweep_case.py"
_spec = importlib.util.spec_from_file_location("sweep_case", SCRIPT)
case = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(case)

N, CHUNK = 1000, 128  # 8 chunks, the last one partial (104 rows)
COLUMNS = ["index", "param.mode"]
COLUMNS += [f"param.plant.A[{i},{j}]" for i in range(2) for j in range(2)]
COLUMNS += ["param.plant.b[0]", "param.plant.b[1]", "param.x0[0]", "param.x0[1]"]
COLUMNS += ["metric.cost", "metric.peak", "metric.x_final[0]", "metric.x_final[1]", "metric.stable"]


def _run(out_dir, **kw):
    kw = {"chunk_size": CHUNK, "config": case.CONFIG, "progress": False} | kw
    return run_sweep(case.sampler, case.evaluate, kw.pop("num_configs", N), out_dir, **kw)


def _manifest(out_dir):
    return json.loads((Path(out_dir) / "manifest.json").read_text())


def _assert_same(got, want):
    assert list(got) == list(want)
    for name in want:
        assert got[name].dtype == want[name].dtype, name
        assert np.array_equal(got[name], want[name]), name


def _subprocess(*args, env=None, **kw):
    env = {**os.environ, "JAX_ENABLE_X64": "1", "JAX_PLATFORMS": "cpu", **(env or {})}
    cmd = [sys.executable, str(SCRIPT), *map(str, args), "--num", str(N), "--chunk", str(CHUNK)]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _finish(proc, timeout=120):
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err
    return [json.loads(line) for line in out.splitlines()]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted one-device sweep: (out_dir, columns)."""
    out = tmp_path_factory.mktemp("sweep") / "reference"
    result = _run(out)
    assert (result.chunks_computed, result.chunks_reused, result.num_configs) == (8, 0, N)
    return out, load_results(out)


def test_columns_dtypes_and_values_match_a_direct_vmap(reference):
    out, cols = reference
    assert list(cols) == COLUMNS
    assert cols["index"].dtype == np.int64 and np.array_equal(cols["index"], np.arange(N))
    assert cols["param.mode"].dtype == np.int32 and cols["metric.stable"].dtype == np.bool_
    assert cols["metric.cost"].dtype == np.float64

    def row(i):
        params = case.sampler(config_key(0, i), i)
        return params, case.evaluate(params)

    params, metrics = jax.jit(jax.vmap(row))(jnp.arange(N, dtype=jnp.int32))
    assert np.array_equal(cols["param.plant.A[1,0]"], params["plant"]["A"][:, 1, 0])
    assert np.array_equal(cols["param.mode"], params["mode"])
    assert np.array_equal(cols["metric.x_final[1]"], metrics.x_final[:, 1])
    for field in ("cost", "peak", "stable"):
        assert np.array_equal(cols[f"metric.{field}"], getattr(metrics, field)), field
    assert (
        jax.random.key_data(config_key(3, 7)).tolist()
        == jax.random.key_data(jax.random.fold_in(jax.random.key(3), 7)).tolist()
    )

    m = _manifest(out)
    assert m["config"] == case.CONFIG and (m["seed"], m["num_configs"], m["chunk_size"]) == (0, N, CHUNK)
    assert (m["device_count"], m["platform"], m["format_version"]) == (1, "cpu", 2)
    assert len(m["fingerprint"]) == 64
    assert set(m["versions"]) == {"python", "jax", "jaxlib", "numpy", "pyarrow", "jaxobs"}
    assert list(m["columns"]) == COLUMNS and m["columns"]["metric.stable"] == "bool"
    assert sorted(m["completed"], key=int) == [str(c) for c in range(8)]
    assert sum(e["rows"] for e in m["completed"].values()) == N
    assert m["compile_seconds"] > 0 and m["seconds"] >= m["compile_seconds"]
    assert sorted(p.name for p in (out / "chunks").iterdir()) == [f"chunk-{c:05d}.parquet" for c in range(8)]
    assert sorted(p.name for p in out.iterdir()) == [".jaxobs.lock", "chunks", "manifest.json"]  # no temporaries


def test_chunk_size_does_not_change_results(reference, tmp_path, caplog):
    """(Another chunk size compiles another step: the sweep says so at INFO level, and reports its seconds as part
    of the call's.)"""
    with caplog.at_level(logging.INFO, logger="jaxobs.sweep"):
        result = _run(tmp_path, chunk_size=300)
    assert result.chunks_computed == 4
    _assert_same(load_results(tmp_path), reference[1])
    said = [r.getMessage() for r in caplog.records if r.name == "jaxobs.sweep"]
    assert said[:2] == ["compiling the sweep step (300 configurations per device, 1 device(s)) ...",
                        f"compiled the sweep step (300 configurations per device, 1 device(s)) in "
                        f"{result.compile_seconds:.1f} s"]  # fmt: skip
    assert 0 < result.compile_seconds <= result.seconds


def test_resume_recomputes_missing_truncated_and_corrupt_chunks(reference, tmp_path, caplog):
    out = tmp_path / "sweep"
    shutil.copytree(reference[0], out)
    chunk = out / "chunks" / "chunk-{:05d}.parquet"
    Path(str(chunk).format(1)).unlink()
    data = Path(str(chunk).format(2)).read_bytes()
    Path(str(chunk).format(2)).write_bytes(data[: len(data) // 2])
    data = bytearray(Path(str(chunk).format(5)).read_bytes())
    data[len(data) // 2] ^= 0xFF
    Path(str(chunk).format(5)).write_bytes(bytes(data))
    with pytest.raises(ValueError, match="chunk 1 .* missing; rerun"):
        load_results(out)

    result = _run(out)
    assert (result.chunks_computed, result.chunks_reused) == (3, 5)
    warned = " ".join(r.getMessage() for r in caplog.records)
    for name in ("chunk-00001.parquet", "chunk-00002.parquet", "chunk-00005.parquet"):
        assert name in warned
    _assert_same(load_results(out), reference[1])
    assert _run(out).chunks_computed == 0


@pytest.mark.slow  # ~12 s: two CLI processes
def test_sigkill_mid_sweep_then_resume_is_bit_identical(reference, tmp_path):
    out = tmp_path / "sweep"
    proc = _subprocess(out, env={"SWEEP_SLEEP": "0.4"})  # every chunk sleeps in a host callback
    deadline, done = time.monotonic() + 90, 0
    try:
        while done < 2:
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "the sweep subprocess made no progress"
            time.sleep(0.02)
            if (out / "manifest.json").exists():
                done = len(_manifest(out)["completed"])
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
    done = len(_manifest(out)["completed"])
    assert 2 <= done < 8, "the subprocess was not killed mid-sweep"

    (result,) = _finish(_subprocess(out))[:1]
    assert result["chunks_reused"] >= done and result["chunks_reused"] + result["chunks_computed"] == 8
    _assert_same(load_results(out), reference[1])


def test_four_devices_give_bit_identical_results(reference, tmp_path):
    fresh, mixed = tmp_path / "fresh", tmp_path / "mixed"
    shutil.copytree(reference[0], mixed)
    for c in (3, 7):  # recomputed on 4 devices: one step, padded with repeats of chunk 7 (itself partial)
        (mixed / "chunks" / f"chunk-{c:05d}.parquet").unlink()
    env = {"XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()}
    first, second, info = _finish(_subprocess(fresh, mixed, env=env))
    assert (info["devices"], info["processes"], info["x64"]) == (4, 1, True)
    assert (first["chunks_computed"], second["chunks_computed"], second["chunks_reused"]) == (8, 2, 6)

    _assert_same(load_results(fresh), reference[1])
    _assert_same(load_results(mixed), reference[1])
    assert _manifest(fresh)["device_count"] == 4
    assert {e["device_count"] for e in _manifest(fresh)["completed"].values()} == {4}
    per_chunk = {int(c): e["device_count"] for c, e in _manifest(mixed)["completed"].items()}
    assert per_chunk == {c: 4 if c in (3, 7) else 1 for c in range(8)}


def test_keyboard_interrupt_leaves_a_resumable_sweep(reference, tmp_path, monkeypatch, capsys):
    write, calls = sweep._write_chunk, []

    def interrupted_write(path, table):
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return write(path, table)

    monkeypatch.setattr(sweep, "_write_chunk", interrupted_write)
    with pytest.raises(Interrupted, match="interrupted after 2 of 8 chunks; rerun the same command to resume"):
        _run(tmp_path)
    assert sorted(_manifest(tmp_path)["completed"]) == ["0", "1"]
    with pytest.raises(SweepError, match=r"incomplete \(2 of 8 chunks\); rerun"):
        load_results(tmp_path)

    monkeypatch.setattr(sweep, "_write_chunk", write)
    result = _run(tmp_path, progress=True)
    assert (result.chunks_computed, result.chunks_reused) == (6, 2) and result.configs_per_second > 0
    assert "1000/1000" in capsys.readouterr().err  # the progress bar
    _assert_same(load_results(tmp_path), reference[1])


def test_a_ctrl_c_whose_keyboard_interrupt_was_swallowed_still_stops_the_sweep(tmp_path, monkeypatch):
    """Python prints a KeyboardInterrupt raised in a garbage-collection callback (XLA has one) as "Exception
    ignored" and goes on; the sweep still stops before its next chunk."""
    write, calls = sweep._write_chunk, []

    def write_then_lose_a_ctrl_c(path, table):
        calls.append(path)
        if len(calls) == 2:
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(1)  # the handler runs here
            except KeyboardInterrupt:
                pass  # swallowed, as in a gc callback
        return write(path, table)

    monkeypatch.setattr(sweep, "_write_chunk", write_then_lose_a_ctrl_c)
    with pytest.raises(Interrupted, match="interrupted after 2 of 8 chunks; rerun"):
        _run(tmp_path)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_different_sweep_is_refused_unless_overwrite(reference, tmp_path):
    out = tmp_path / "sweep"
    shutil.copytree(reference[0], out)
    for kw, what in [({"seed": 1}, "seed"), ({"config": {"c": 1}}, "config"), ({"chunk_size": 100}, "chunk_size")]:
        with pytest.raises(SweepError, match=f"different sweep \\({what} differ.*overwrite=True"):
            _run(out, **kw)
    with pytest.raises(SweepError, match="columns differ"):
        run_sweep(case.sampler, lambda p: {"cost": p["x0"].sum()}, N, out, chunk_size=CHUNK, config=case.CONFIG)

    def changed(p):  # the same config and columns, other numbers: the fingerprint tells them apart
        return case.evaluate(p)._replace(cost=2.0 * case.evaluate(p).cost)

    with pytest.raises(SweepError, match="computed by other code .*overwrite=True"):
        run_sweep(case.sampler, changed, N, out, chunk_size=CHUNK, config=case.CONFIG, progress=False)
    assert _manifest(out) == _manifest(reference[0])  # nothing touched

    result = run_sweep(case.sampler, changed, N, out, chunk_size=CHUNK, config=case.CONFIG, progress=False,
                       overwrite=True)  # fmt: skip
    assert (result.chunks_computed, result.chunks_reused) == (8, 0)
    np.testing.assert_array_equal(load_results(out)["metric.cost"], 2.0 * reference[1]["metric.cost"])


def test_more_configurations_extend_the_sweep(reference, tmp_path):
    """1000 -> 1300 configurations: the 7 full chunks are reused, the partial chunk 7 and chunks 8-10 computed;
    back to 1000: chunk 7 is recomputed with 104 rows, chunks 8-10 stay for a later extension."""
    out = tmp_path / "sweep"
    shutil.copytree(reference[0], out)
    longer = _run(out, num_configs=1300)
    assert (longer.chunks_computed, longer.chunks_reused, longer.num_configs) == (4, 7, 1300)
    cols = load_results(out)
    assert cols["index"].tolist() == list(range(1300))
    _assert_same({k: v[:N] for k, v in cols.items()}, reference[1])
    shorter = _run(out)
    assert (shorter.chunks_computed, shorter.chunks_reused) == (1, 7)
    _assert_same(load_results(out), reference[1])
    assert sorted(_manifest(out)["completed"], key=int) == [str(c) for c in range(11)]


@pytest.mark.parametrize(
    "text, message",
    [
        ("[]", "a JSON list instead of an object"),
        ("", "unreadable"),
        ('{"format_version": 2}', "config is missing"),
        ("MANIFEST completed=[]", "completed is list"),
        ('MANIFEST completed={"0": []}', r"completed\['0'\] is not a chunk entry"),
        ("MANIFEST format_version=1", "format_version 1"),
    ],
)
def test_a_damaged_manifest_is_refused_with_its_name(reference, tmp_path, text, message):
    out = tmp_path / "sweep"
    shutil.copytree(reference[0], out)
    if text.startswith("MANIFEST"):
        key, value = text.split(" ", 1)[1].split("=", 1)
        text = json.dumps({**_manifest(out), key: json.loads(value)})
    (out / "manifest.json").write_text(text)
    for call in (lambda: _run(out), lambda: load_results(out)):
        with pytest.raises(SweepError, match=message) as info:
            call()
        assert str(out / "manifest.json") in str(info.value)
    assert _run(out, overwrite=True).chunks_computed == 8


def test_a_second_process_on_the_same_out_dir_exits_2_naming_the_holder(tmp_path):
    """A slow sweep holds the lock; `jaxobs sweep` on the same directory exits 2 at once, naming its pid."""
    out = tmp_path / "sweep"
    holder = _subprocess(out, env={"SWEEP_SLEEP": "3"})  # 8 chunks: about 24 s, killed well before
    try:
        deadline = time.monotonic() + 90
        while not (out / "manifest.json").exists():
            assert holder.poll() is None, holder.communicate()[1]
            assert time.monotonic() < deadline, "the sweep subprocess did not start"
            time.sleep(0.05)
        env = {**os.environ, "JAX_PLATFORMS": "cpu"}
        second = subprocess.run([sys.executable, "-m", "jaxobs.cli", "sweep", "--out", str(out), "--no-progress"],
                                env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
        assert second.returncode == 2, second.stderr
        lines = second.stderr.strip().splitlines()
        assert lines == [
            f"jaxobs sweep: {out} is in use by another jaxobs process (pid {holder.pid}); wait for it to finish "
            "or choose another output directory"
        ]
        with pytest.raises(JobError, match=f"pid {holder.pid}"):  # the library refuses as well
            _run(out)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.communicate()
    assert _run(out).chunks_computed > 0  # the kernel released the dead holder's lock


def test_a_step_that_cannot_fit_in_memory_is_refused_before_it_runs(tmp_path):
    def evaluate(p):  # a 10^7-sample intermediate per configuration: 80 MB each, 8 TB per chunk of 10^5
        return {"s": jnp.cumsum(jax.random.normal(jax.random.key(0), (10**7,)) * p["a"])[-1]}

    message = (r"one step of the sweep \(1 device\(s\) x chunk_size 100000\) needs about [\d.]+ TB \(estimated\), "
               r"more than the .* of memory available; lower chunk_size")  # fmt: skip
    with pytest.raises(JobError, match=message):
        run_sweep(_scalar_sampler, evaluate, 10**5, tmp_path / "out", chunk_size=10**5, progress=False)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [".jaxobs.lock"]  # nothing written


def _scalar_sampler(key, index):
    return {"a": jax.random.uniform(key)}


@pytest.mark.parametrize(
    "args, message",
    [
        ({"num_configs": 0}, "num_configs must be >= 1"),
        ({"chunk_size": 0}, "chunk_size must be >= 1"),
        ({"seed": 1.5}, "seed must be an int"),
        ({"seed": True}, "seed must be an int"),
        ({"sampler": None}, "sampler must be a function"),
        ({"evaluate": 3}, "evaluate must be a function"),
        ({"config": {"bad": {1, 2}}}, "config must be a JSON-serialisable dict"),
        ({"evaluate": lambda p: {"z": p["a"] * 1j}}, "metric.z has dtype complex"),
        ({"evaluate": lambda p: {}}, "evaluate returned no arrays"),
        ({"evaluate": lambda p: "text"}, "sampler/evaluate failed"),
        ({"evaluate": lambda p: p["missing"]}, "KeyError"),
        ({"evaluate": lambda p: {"y": p["a"], "key": jax.random.key(0)}}, "metric.key has dtype key"),
        ({"evaluate": lambda p: {"a.b": p["a"], "a": {"b": p["a"]}}}, "column names collide"),
    ],
)
def test_bad_inputs_raise_before_any_file_is_written(tmp_path, args, message):
    kw = {"sampler": _scalar_sampler, "evaluate": lambda p: {"y": p["a"] ** 2}, "num_configs": 10} | args
    with pytest.raises(ValueError, match=message):
        run_sweep(kw.pop("sampler"), kw.pop("evaluate"), kw.pop("num_configs"), tmp_path / "out", **kw)
    assert not (tmp_path / "out").exists()


def test_documented_example_runs(tmp_path, monkeypatch):
    """The example of the sweep engine's design notes (docs/theory/jobs.md); it also checks that a scan may start
    from a constant carry (shard_map with check_vma=False)."""
    notes = (Path(__file__).parents[1] / "docs" / "theory" / "jobs.md").read_text()
    code = notes.split("## `jaxobs.sweep`")[1].split("```python\n")[1].split("```")[0]
    monkeypatch.chdir(tmp_path)
    namespace = {}
    exec(code, namespace)
    cols = namespace["cols"]
    assert sorted(cols) == ["index", "metric.converged", "metric.x50", "param.a"]
    assert len(cols["index"]) == 10_000 and cols["metric.converged"].dtype == np.bool_


def test_load_results_without_a_sweep(tmp_path):
    with pytest.raises(SweepError, match="no manifest.json"):
        load_results(tmp_path)


def test_an_unwritable_out_dir_is_refused_before_compiling(tmp_path):
    (tmp_path / "file").write_text("")
    for out, message in [(tmp_path / "file", "exists and is not a directory"),
                         (tmp_path / "file" / "sub", "cannot write to .*: Not a directory")]:  # fmt: skip
        with pytest.raises(JobError, match=message):
            run_sweep(_scalar_sampler, lambda p: {"y": p["a"]}, 10, out, progress=False)


def test_interrupt_watch_notes_ctrl_c_and_leaves_other_handlers_alone():
    from jaxobs._resources import InterruptWatch

    with InterruptWatch() as watch:
        watch.check()  # nothing yet
        with pytest.raises(KeyboardInterrupt):  # Python's handler still raises at once
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
        with pytest.raises(KeyboardInterrupt):
            watch.check()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with InterruptWatch():  # the command's watch, entered first: a watch entered later shares its record
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
        except KeyboardInterrupt:
            pass  # lost before the engine's watch existed
        with InterruptWatch() as engine, pytest.raises(KeyboardInterrupt):
            engine.check()
    with InterruptWatch() as watch:
        watch.check()  # a new command starts with a clean record
    own = []
    previous = signal.signal(signal.SIGINT, lambda *_: own.append(1))
    try:
        with InterruptWatch() as watch:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.2)
            watch.check()  # a caller's own handler is not replaced
        assert own == [1] and not watch.requested
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_ctrl_c_inside_a_finaliser_is_left_to_the_next_check(monkeypatch):
    """A KeyboardInterrupt raised in a gc callback or __del__ would be printed with its traceback and dropped; the
    watch raises none there, and its next check does."""
    from jaxobs._resources import InterruptWatch

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)

    class Buffer:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.2)  # the handler runs here, inside __del__

    with InterruptWatch() as watch:
        buffer = Buffer()
        del buffer
        assert unraisable == [] and watch.requested
        with pytest.raises(KeyboardInterrupt):
            watch.check()


def test_a_prng_key_parameter_reaches_evaluate_but_is_not_a_column(tmp_path):
    """The noise key a sampler draws for evaluate is not written (it is a function of (seed, index)): no
    param.noise_key[0], param.noise_key[1] columns, and the metrics are those of that key."""

    def sampler(key, index):
        k_a, k_noise = jax.random.split(key)
        return {"a": jax.random.uniform(k_a), "noise_key": k_noise}

    def evaluate(p):
        return {"y": p["a"] + jax.random.normal(p["noise_key"])}

    run_sweep(sampler, evaluate, 6, tmp_path / "out", chunk_size=4, progress=False)
    rows = load_results(tmp_path / "out")
    assert list(rows) == ["index", "param.a", "metric.y"]
    want = [float(evaluate(sampler(config_key(0, i), i))["y"]) for i in range(6)]
    np.testing.assert_allclose(rows["metric.y"], want, rtol=1e-12)


def test_load_results_as_a_pandas_dataframe(reference):
    pandas = pytest.importorskip("pandas")
    out, cols = reference
    frame = load_results(out, as_frame=True)
    assert isinstance(frame, pandas.DataFrame) and frame.index.name == "index"
    assert list(frame.columns) == COLUMNS[1:] and frame.index.tolist() == cols["index"].tolist()
    np.testing.assert_array_equal(frame["metric.cost"].to_numpy(), cols["metric.cost"])


def test_a_rerun_keeps_the_measured_history(tmp_path):
    """Rerunning a finished sweep adds nothing to what its runs measured (the wall time, the compilation and the
    throughput of the chunks computed); extending it adds the run that computes the new chunks."""
    out = tmp_path / "out"
    first = _run(out, num_configs=256)
    history = run_history(out)
    assert (history.runs, history.configs_computed) == (1, 256)
    assert history.compile_seconds == pytest.approx(first.compile_seconds)
    assert history.compile_seconds < history.seconds and 0 < history.compute_seconds < history.seconds
    assert history.configs_per_second == pytest.approx(256 / history.compute_seconds)
    again = _run(out, num_configs=256)
    assert (again.chunks_computed, again.configs_per_second) == (0, 0.0)
    assert run_history(out) == history
    _run(out, num_configs=512)
    extended = run_history(out)
    assert (extended.runs, extended.configs_computed) == (2, 512) and extended.seconds > history.seconds
    assert _manifest(out)["seconds"] == pytest.approx(extended.seconds)
