"""The `jaxobs` command."""

import json
import subprocess
import sys

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
