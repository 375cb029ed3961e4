"""The `jaxobs` command: listing, the one-line errors with exit status 2 (before anything is built), Ctrl-C."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from jaxobs.cli import main


def test_list(capsys):
    assert main(["reproduce", "--list"]) == 0
    out = capsys.readouterr().out
    assert "cortesao2006-example1" in out and "cortesao-stochastic-ramp" in out


def test_unknown_name_exits_2(capsys, tmp_path):
    assert main(["reproduce", "no-such-paper", "--out", str(tmp_path)]) == 2
    assert "unknown reproduction" in capsys.readouterr().err


@pytest.mark.slow
def test_reproduce_as_a_subprocess(tmp_path):
    """The installed entry point writes the JSON with the required keys."""
    proc = subprocess.run(
        [sys.executable, "-m", "jaxobs.cli", "reproduce", "cortesao-stochastic-ramp", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "cortesao-stochastic-ramp.json").read_text())
    assert abs(data["delta_f_ss_ckf"] - 4.1034) < 5e-4
    assert "delta_f_ss_ckf" in proc.stdout


# --------------------------------------------------------------------------------------------
# User errors: exit 2 and one line, before anything is built


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_out_that_is_a_file_or_under_one_exits_2(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    for command in (["sweep"], ["tune"], ["reproduce", "cortesao-stochastic-ramp"]):
        assert main([*command, "--out", str(tmp_path / "file")]) == 2
        assert _one_line(capsys) == (
            f"jaxobs {command[0]}: {tmp_path / 'file'} exists and is not a directory; choose another output directory"
        )
    assert main(["sweep", "--out", str(tmp_path / "file" / "sub")]) == 2
    assert _one_line(capsys).endswith("sub: Not a directory; choose another output directory")


def test_out_without_write_permission_exits_2(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if os.access(locked, os.W_OK):
            pytest.skip("running as root: chmod does not stop writes (the read-only file system test covers it)")
        assert main(["sweep", "--out", str(locked / "out")]) == 2
        assert _one_line(capsys).endswith("out: Permission denied; choose another output directory")
    finally:
        locked.chmod(0o700)


def test_out_on_a_read_only_file_system_exits_2(tmp_path):
    """A read-only tmpfs mounted in a private mount namespace (unshare; skipped where that is not allowed)."""
    mount = tmp_path / "ro"
    mount.mkdir()
    script = (f"mount -t tmpfs -o ro tmpfs {mount} || exit 99; "
              f"exec {sys.executable} -m jaxobs.cli sweep --out {mount / 'out'}")  # fmt: skip
    try:
        proc = subprocess.run(["unshare", "--mount", "--map-root-user", "sh", "-c", script], capture_output=True,
                              text=True, timeout=120, env={**os.environ, "JAX_PLATFORMS": "cpu"})  # fmt: skip
    except FileNotFoundError:
        pytest.skip("unshare is not installed")
    if proc.returncode == 99 or "unshare:" in proc.stderr:
        pytest.skip(f"cannot mount a read-only file system here: {proc.stderr.strip()}")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        f"jaxobs sweep: cannot write to {mount / 'out'}: Read-only file system; choose another output directory"
    )


@pytest.mark.parametrize(
    "manifest, message",
    [("[]", "a JSON list instead of an object"), ('{"format_version": 2, "config": []}', "config is list")],
)
def test_a_manifest_of_the_wrong_structure_exits_2(tmp_path, capsys, manifest, message):
    (tmp_path / "manifest.json").write_text(manifest)
    assert main(["sweep", "--out", str(tmp_path)]) == 2
    line = _one_line(capsys)
    assert str(tmp_path / "manifest.json") in line and message in line and "--overwrite" in line


def test_a_tuning_record_of_the_wrong_structure_exits_2(tmp_path, capsys):
    (tmp_path / "config.json").write_text("[]")
    assert main(["tune", "--out", str(tmp_path)]) == 2
    assert "config.json: not a jaxobs tune record" in _one_line(capsys)


@pytest.mark.parametrize(
    "command, toml, key",
    [
        ("sweep", "[plant]\nstiffness = [0.3, inf]\n", "plant.stiffness"),
        ("sweep", "[simulation]\nsensor_noise = nan\n", "simulation.sensor_noise"),
        ("sweep", 'scenario = "liu-peng"\n[noise]\nstd = -inf\n', "noise.std"),
        ("tune", "[scenario]\nsensor_noise = nan\n", "scenario.sensor_noise"),
        ("tune", "[optimizer]\nlearning_rate = inf\n", "optimizer.learning_rate"),
    ],
)
def test_non_finite_config_values_exit_2_naming_file_and_key(tmp_path, capsys, command, toml, key):
    path = tmp_path / "bad.toml"
    path.write_text(toml)
    assert main([command, "--config", str(path), "--out", str(tmp_path / "out")]) == 2
    assert _one_line(capsys).startswith(f"jaxobs {command}: {path}: {key}: must be finite, got ")
    assert not (tmp_path / "out").exists()


def test_a_run_that_cannot_fit_in_memory_exits_2_with_the_estimate(tmp_path, capsys):
    path = tmp_path / "big.toml"
    path.write_text("[plants]\nheldout = 1000000000000\n")
    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "out")]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"jaxobs tune: {path}: plants: the sensor noise of 1000000000016 plants over 250 steps "
                           "needs about 2 PB (estimated), more than the ")  # fmt: skip
    assert line.endswith("; lower plants.train, plants.heldout or scenario.duration")
    assert not (tmp_path / "out").exists()


def test_ctrl_c_exits_130_with_the_resume_hint(tmp_path):
    """SIGINT once the command holds its output directory (its pid is in the lock file): no traceback."""
    config = tmp_path / "small.toml"
    config.write_text('scenario = "liu-peng"\nchunk_size = 3\n[vehicle]\ncount = 6\n')
    out = tmp_path / "out"
    run_cli = (  # Python's own SIGINT handler even where the test runner's SIGINT is ignored (a background job)
        "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "sys.argv[0] = 'jaxobs'; runpy.run_module('jaxobs.cli', run_name='__main__')"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", run_cli, "sweep", "--config", str(config), "--out", str(out), "--no-progress"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )  # fmt: skip
    deadline = time.monotonic() + 120
    lock = out / ".jaxobs.lock"
    while not (lock.exists() and lock.read_text().strip() == str(proc.pid)):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the command did not start"
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("jaxobs sweep: interrupted")
    assert err.strip().endswith("rerun the same command to resume")
