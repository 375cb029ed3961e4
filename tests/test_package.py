"""The installed package stands on its own: a wheel built from the repository, installed in a fresh virtual
environment and run from a scratch directory (no repository on the path), runs the README's tour, lists and prints
every shipped config, runs the guides' small sweep and tune and the own-robot problem by name.

The fresh environment gets jaxobs from the wheel alone; its dependencies are read from the test run's environment
(a ``.pth`` line), so nothing is downloaded but the build backend. The runs share the suite's compilation cache.
"""

import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests import ROOT
from tests.test_docs import assert_prints_its_output

pytestmark = [pytest.mark.slow, pytest.mark.published]


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """The ``bin`` folder of a fresh virtual environment holding the wheel of the repository."""
    root = tmp_path_factory.mktemp("package")
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q", "-w", str(root / "dist")],
                   check=True, capture_output=True, timeout=600)  # fmt: skip
    subprocess.run([sys.executable, "-m", "venv", str(root / "venv")], check=True, timeout=300)
    bin_dir = root / "venv" / "bin"
    wheel = next((root / "dist").glob("jaxobs-*.whl"))
    clean = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # else pip finds a checkout's egg-info
    subprocess.run([bin_dir / "python", "-m", "pip", "install", "--no-deps", "-q", str(wheel)], check=True,
                   capture_output=True, timeout=600, env=clean)  # fmt: skip
    purelib = subprocess.run([bin_dir / "python", "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()  # fmt: skip
    (Path(purelib) / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return bin_dir


def _jaxobs(installed: Path, cwd: Path, *args: str) -> str:
    """``jaxobs *args`` of the installed package, run in ``cwd``; its standard output (a failure fails the test)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([str(installed / "jaxobs"), *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=1800)  # fmt: skip
    assert done.returncode == 0, f"jaxobs {' '.join(args)}: {done.stderr[-3000:]}"
    return done.stdout


def test_the_package_is_the_wheels(installed, tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    where = subprocess.run([installed / "python", "-c", "import jaxobs; print(jaxobs.__file__)"], cwd=tmp_path,
                           env=env, capture_output=True, text=True, check=True).stdout  # fmt: skip
    assert str(installed.parent) in where and str(ROOT) not in where


def test_readme_tour_runs_from_the_wheel(installed, tmp_path):
    assert_prints_its_output(ROOT / "README.md", tmp_path, python=str(installed / "python"))


def test_every_shipped_config_is_listed_and_prints(installed, tmp_path):
    """``jaxobs COMMAND --list`` names every shipped config and ``--example NAME --print-config`` prints each (the
    print-outs in one process of the installed interpreter: one import of jaxobs, not one per config)."""
    calls = []
    for command in ("sweep", "tune"):
        listed = _jaxobs(installed, tmp_path, command, "--list")
        names = [path.stem for path in (ROOT / "tuning").glob("*.toml")
                 if ("scenario = " if command == "sweep" else "problem = ") in path.read_text()]  # fmt: skip
        assert names and all(f"\n{name} " in listed for name in names), listed
        calls += [[command, "--example", name, "--print-config"] for name in names]
    script = (f"from jaxobs.cli import main\nfor args in {calls!r}:\n    print('=== ' + ' '.join(args), flush=True)\n"
              "    assert main(args) == 0, args\n")  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([installed / "python", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    printed = done.stdout.split("=== ")[1:]
    assert len(printed) == len(calls) and all(p.split("\n", 1)[1].strip() for p in printed), done.stdout[-3000:]


@pytest.mark.parametrize("command, guide", [("sweep", "sweeps"), ("tune", "tuning")])
def test_guide_configs_run_from_the_wheel(installed, tmp_path, command, guide):
    """The guide's small config (``jaxobs COMMAND --example COMMAND-small``) prints the results (the indented lines
    of the command's summary) that the guide's transcript shows."""
    printed = _jaxobs(installed, tmp_path, command, "--example", f"{command}-small", "--out", "out", "--no-progress")
    results = [line.rstrip() for line in printed.splitlines() if line.startswith("  ")]
    page = (ROOT / "docs" / "guides" / f"{guide}.md").read_text()
    assert results and [line for line in results if line not in page] == []


def test_own_robot_runs_by_name_from_the_wheel(installed, tmp_path):
    """The own-robot problem with its shipped MJCF, named only (no config file, no repository): a minimal run."""
    _jaxobs(installed, tmp_path, "tune", "--problem", "own-robot", "--steps", "1", "--set", "optimizer.screening=0",
            "--set", "optimizer.starts=1", "--set", "baseline.random_search=false", "--set", "plants.train=2",
            "--set", "plants.heldout=2", "--set", "scenario.duration=1.0", "--out", "out", "--no-progress")  # fmt: skip
    assert (tmp_path / "out" / "tuned.json").is_file()
