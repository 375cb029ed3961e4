"""The `jaxobs` command: listing, --print-config, --version, the compilation cache, the one-line errors with exit
status 2 (before anything is built), Ctrl-C."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import jax
import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from jaxobs import __version__, cli
from jaxobs._config import leaf_keys
from jaxobs.cli import main
from jaxobs.papers.registry import reproductions, sweep_scenarios, tuning_problems
from jaxobs.papers.shipped import shipped_configs
from tests import FAST_COMPILE_FLAGS

COMMANDS = {"sweep": ("scenario", sweep_scenarios), "tune": ("problem", tuning_problems)}
NAME_STYLE = re.compile(r"[a-z][a-z0-9]*(-[a-z0-9]+(\.[0-9]+)*)*")  # lower-case words, hyphens (numbers as 5.6)


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxobs {__version__}"


def test_every_name_has_one_style():
    names = [*reproductions(), *sweep_scenarios(), *tuning_problems()]
    assert [n for n in names if not NAME_STYLE.fullmatch(n)] == []


@pytest.mark.parametrize("command", ["sweep", "tune", "reproduce"])
def test_list_prints_every_name_with_its_description(capsys, command):
    registry = {"sweep": sweep_scenarios, "tune": tuning_problems, "reproduce": reproductions}[command]()
    assert main([command, "--list"]) == 0
    out = capsys.readouterr().out
    registered, _, shipped = out.partition("\n\n")
    lines = registered.splitlines()
    assert [line.split()[0] for line in lines] == list(registry)
    for line, entry in zip(lines, registry.values(), strict=True):
        description = line.split(maxsplit=1)[1]
        assert description == entry.summary and len(description) > 20 and "``" not in description
    kind = {"sweep": "sweep", "tune": "tune"}.get(command)
    names = [line.split()[0] for line in shipped.splitlines()[1:]]
    assert names == [config.name for config in shipped_configs() if config.kind == kind]


def _scenarios():
    return [(command, name) for command, (_, registry) in COMMANDS.items() for name in registry()]


def _tables(config: dict, prefix: str = "") -> set:
    """The dotted names of the tables (nested ones too) of ``config``."""
    names = set()
    for key, value in config.items():
        if isinstance(value, dict):
            names |= {prefix + key} | _tables(value, f"{prefix}{key}.")
    return names


@pytest.mark.parametrize("command, name", _scenarios())
def test_print_config_is_the_full_default_every_key_commented(tmp_path, capsys, command, name):
    """The TOML parses back to the scenario's complete default config, every value has a comment line above it,
    and it runs as a config file (a round trip through --config)."""
    key, registry = COMMANDS[command]
    scenario = registry()[name]
    assert main([command, "--print-config", name]) == 0
    text = capsys.readouterr().out
    assert tomllib.loads(text) == scenario.validate({key: name})
    notes = scenario.config_notes()
    assert set(leaf_keys(scenario.defaults)) <= set(notes)  # every key documented ...
    assert set(notes) <= set(leaf_keys(scenario.defaults)) | _tables(scenario.defaults)  # ... and no stale note
    lines = text.splitlines()
    values = [i for i, line in enumerate(lines) if re.match(r'(\w+|"[^"]+") = ', line)]  # bare or quoted keys
    assert len(values) == len(leaf_keys(scenario.defaults))
    assert all(lines[i - 1].startswith("# ") for i in values)
    path = tmp_path / "printed.toml"
    path.write_text(text)
    assert main([command, "--config", str(path), "--print-config"]) == 0
    assert tomllib.loads(capsys.readouterr().out) == tomllib.loads(text)


def test_print_config_of_a_file_merges_it_over_its_scenario(tmp_path, capsys):
    path = tmp_path / "small.toml"
    path.write_text('scenario = "liu-peng"\n[vehicle]\ncount = 7\n')
    assert main(["sweep", "--config", str(path), "--print-config"]) == 0
    printed = tomllib.loads(capsys.readouterr().out)
    assert printed["scenario"] == "liu-peng" and printed["vehicle"]["count"] == 7
    assert printed["noise"] == sweep_scenarios()["liu-peng"].defaults["noise"]
    assert main(["sweep", "--print-config"]) == 0  # no name, no file: the default scenario
    assert tomllib.loads(capsys.readouterr().out)["scenario"] == next(iter(sweep_scenarios()))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["sweep", "--print-config", "liu_peng"], "--print-config: scenario: must be one of 'force-control', "),
        (["tune", "--print-config", "nope"], "--print-config: problem: must be one of 'force-1dof', 'peg-on-hole'"),
    ],
)
def test_print_config_of_an_unknown_name_exits_2(capsys, argv, message):
    assert main(argv) == 2
    assert _one_line(capsys).startswith(f"jaxobs {argv[0]}: {message}")


def test_print_config_that_contradicts_the_file_exits_2(tmp_path, capsys):
    path = tmp_path / "lp.toml"
    path.write_text('scenario = "liu-peng"\n')
    assert main(["sweep", "--config", str(path), "--print-config", "steer-by-wire"]) == 2
    assert _one_line(capsys) == (f"jaxobs sweep: {path}: scenario: is 'liu-peng', not the 'steer-by-wire' of "
                                 "--print-config")  # fmt: skip


def test_cache_directory(monkeypatch, tmp_path):
    monkeypatch.delenv("JAXOBS_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cli.cache_dir() == tmp_path / "xdg" / "jaxobs" / "jax-cache"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cli.cache_dir() == tmp_path / "home" / ".cache" / "jaxobs" / "jax-cache"
    monkeypatch.setenv("JAXOBS_CACHE_DIR", str(tmp_path / "mine"))
    assert cli.cache_dir() == tmp_path / "mine"


def test_cache_is_enabled_where_it_can_be_created(monkeypatch, tmp_path, capsys):
    """(The test's JAX configuration, the suite's own cache included, is restored by conftest; nothing is compiled
    while the cache is changed.)"""
    jax.config.update("jax_compilation_cache_dir", None)
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("JAXOBS_CACHE_DIR", str(tmp_path / "file" / "cache"))
    cli._enable_compilation_cache()
    assert jax.config.jax_compilation_cache_dir is None
    assert _one_line(capsys).startswith(f"jaxobs: no compilation cache ({tmp_path / 'file' / 'cache'}: ")
    monkeypatch.setenv("JAXOBS_CACHE_DIR", str(tmp_path / "cache"))
    cli._enable_compilation_cache()
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "cache") and (tmp_path / "cache").is_dir()
    assert jax.config.jax_persistent_cache_min_compile_time_secs == cli.CACHE_MIN_COMPILE_SECONDS


def test_a_call_of_main_leaves_the_cache_off(capsys):
    jax.config.update("jax_compilation_cache_dir", None)  # the suite's own cache off (conftest restores it)
    assert main(["reproduce", "--list"]) == 0
    assert jax.config.jax_compilation_cache_dir is None


def test_unknown_name_exits_2(capsys, tmp_path):
    assert main(["reproduce", "no-such-paper", "--out", str(tmp_path)]) == 2
    assert "unknown reproduction" in capsys.readouterr().err


@pytest.mark.slow
def test_reproduce_as_a_subprocess_fills_and_reuses_the_compilation_cache(tmp_path):
    """The command writes the JSON with the required keys; its first run fills the persistent compilation cache,
    a second run reads it and prints the same numbers; ``--no-cache`` writes nothing."""

    def run(out, cache, *flags):
        env = {**os.environ, "JAXOBS_CACHE_DIR": str(cache), "JAX_PLATFORMS": "cpu", "JAX_LOG_COMPILES": "1",
               "XLA_FLAGS": os.environ.get("XLA_FLAGS", "").replace(FAST_COMPILE_FLAGS, "").strip()}  # fmt: skip
        # (JAX_LOG_COMPILES logs each persistent-cache hit; XLA's default compilation, a user's, whose programs are
        # slow enough to compile to pass the command's caching threshold, unlike the suite's cheapest compilation)
        env.pop("JAX_COMPILATION_CACHE_DIR", None)
        command = [sys.executable, "-m", "jaxobs.cli", "reproduce", "cortesao-stochastic-ramp", "--out", str(out)]
        proc = subprocess.run([*command, *flags], capture_output=True, text=True, timeout=300, env=env)
        assert proc.returncode == 0, proc.stderr
        hits = set(re.findall(r"Persistent compilation cache hit for '[^']*' with key '([^']*)'", proc.stderr))
        return proc.stdout, hits

    first, _ = run(tmp_path / "first", tmp_path / "cache")
    data = json.loads((tmp_path / "first" / "cortesao-stochastic-ramp.json").read_text())
    assert abs(data["delta_f_ss_ckf"] - 4.1034) < 5e-4
    assert "delta_f_ss_ckf" in first
    cached = {p.name.removesuffix("-cache") for p in (tmp_path / "cache").glob("*-cache")}
    assert cached, "the first run cached no program"
    second, hits = run(tmp_path / "second", tmp_path / "cache")
    assert cached <= hits  # every program the first run cached was read back instead of compiled

    def numbers(out):
        return [line for line in out.splitlines() if line.startswith("  ")]

    assert numbers(second) == numbers(first)
    run(tmp_path / "third", tmp_path / "no-cache", "--no-cache")
    assert not (tmp_path / "no-cache").exists()


# --------------------------------------------------------------------------------------------
# User errors: exit 2 and one line, before anything is built


def _one_line(capsys) -> str:
    """The error's one line on stderr, beside the progress the library logs (what compiled, in how long)."""
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("jaxobs.")]
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
    path.write_text("[plants]\nheldout = 2000000000\n")
    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "out")]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"jaxobs tune: {path}: plants: the sensor noise of 2000000016 plants over 250 steps "
                           "needs about 4 TB (estimated), more than the ")  # fmt: skip
    assert line.endswith("; lower plants.train, plants.heldout or scenario.duration")
    assert not (tmp_path / "out").exists()


SATURATED = 'scenario = "saturated-outputs"\n'
TINY_FORCE = "chunk_size = 4\n[controllers]\norders = [1]\ngrid_points = 1\n[simulation]\nconfigs_per_design = 8\n"


@pytest.mark.parametrize(
    "toml, key, message",
    [
        pytest.param(SATURATED + "seed = 100000000000000000000\n", "seed",
                     "must be an integer of magnitude at most 2**31 - 1", id="integer-beyond-int32"),
        pytest.param(SATURATED + "[grid]\ninitial_states = 1000000000\n", "grid.initial_states",
                     "num_configs must be below 2**31 (indices are int32), got 27000000000", id="count-beyond-int32"),
        pytest.param(SATURATED + "[run]\nintervals = 100000000\n", "run.intervals",
                     "one step of the sweep (1 device(s) x chunk_size 64) needs about ", id="step-memory"),
        pytest.param(TINY_FORCE + "duration = 1e9\n", "simulation.duration",
                     "one step of the sweep (1 device(s) x chunk_size 4) needs about ", id="simulated-time-memory",
                     marks=pytest.mark.slow),  # ~40 s: the AOB design compiles first
    ],
)  # fmt: skip
def test_job_limits_exit_2_naming_file_and_key(tmp_path, capsys, toml, key, message):
    """The issue's examples: an integer JAX cannot hold, a count of configurations beyond int32 and a step whose
    memory estimate exceeds the machine's (set by the intervals, by the simulated time) exit 2 with one line
    naming the file and the key, before any configuration is computed (before: OverflowError and ValueError
    tracebacks, RESOURCE_EXHAUSTED allocating 1 TB, a memory message naming neither file nor key)."""
    path, out = tmp_path / "big.toml", tmp_path / "out"
    path.write_text(toml)
    assert main(["sweep", "--config", str(path), "--out", str(out), "--no-progress"]) == 2
    assert _one_line(capsys).startswith(f"jaxobs sweep: {path}: {key}: {message}")
    assert not out.exists() or [p.name for p in out.iterdir()] in ([], [".jaxobs.lock"])  # nothing computed


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


def test_shipped_configs_are_listed_and_run_by_name(capsys):
    """``--list`` names every shipped config after the scenarios, ``--example NAME`` reads it from the package."""
    assert main(["tune", "--list"]) == 0
    listed = capsys.readouterr().out
    assert "\ncartpole_payload " in listed and "[own-robot]" in listed and "\ntune-small " in listed
    assert main(["tune", "--example", "cartpole_payload", "--print-config"]) == 0
    printed = capsys.readouterr().out
    mjcf = re.search(r'^mjcf = "(.+)"', printed, re.M).group(1)
    assert os.path.isabs(mjcf) and mjcf.endswith("jaxobs/mjx/assets/cartpole_payload.xml")  # not the cwd's


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--example", "no-such"], "--example: no-such: no shipped tune config 'no-such'; one of"),
        (["--example", "tune-small", "--config", "x.toml"], "give one of --config and --example"),
        (["--set", "optimizer.stepz=3"], "--set: optimizer.stepz: unknown key"),
        (["--set", "seed"], "--set: 'seed' must be KEY=VALUE"),
        (["--steps", "-1"], "--set: optimizer: steps must be > 0, got -1"),
        (["--seconds", "-5"], "--set: optimizer.seconds: must be >= 0, got -5.0"),
    ],
)
def test_command_line_keys_are_checked_like_the_file(capsys, argv, message):
    assert main(["tune", "--problem", "own-robot", *argv, "--print-config"]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err


def test_command_line_keys_override_the_file(tmp_path, capsys):
    path = tmp_path / "mine.toml"
    path.write_text('problem = "own-robot"\nseed = 4\n[plants]\ntrain = 3\n')
    argv = ["--set", "plants.train=5", "--steps", "7", "--seconds", "90", "--print-config"]
    assert main(["tune", "--config", str(path), *argv]) == 0
    printed = capsys.readouterr().out
    assert re.search(r"^seed = 4$", printed, re.M) and re.search(r"^train = 5", printed, re.M)
    assert re.search(r"^steps = 7", printed, re.M) and re.search(r"^seconds = 90", printed, re.M)
