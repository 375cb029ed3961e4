"""The ``grip2010-sandwich`` reproduction (Grip 2010, ch. 9, on this project's instance): the four detector windows
and the low-gain ARE family by default; the full run (125 initial states, 40 s) is slow."""

import json

import numpy as np
import pytest

from jaxobs.papers.grip2010 import sandwich as g
from jaxobs.saturation import sandwich_design
from tests._published import pin, printed

ROW = r"`grip2010-sandwich` \| Grip 2010 ch\. 9 \|.*?"


@pytest.mark.slow  # Theorem 9.1 on the instance: tests/test_saturation.py in the default set
def test_detector_windows_are_classified_by_theorem_9_1():
    design = sandwich_design(**g.SYSTEM, F=g.F, **g.DESIGN)
    windows = g.windows(design)
    assert [w["case"] for w in windows] == list(g.WINDOWS)
    for w in windows:
        assert set(w) >= {"case", "z_min", "z_max", "e_plus", "e_minus", "e_zero", "classified"}
        assert w["correct"], w
    crossing = windows[-1]
    assert crossing["z_min"] < 1 < crossing["z_max"]
    assert windows[2]["chi_end_error"] < 1e-9  # the deadbeat reconstruction (9.11b) on the linear window
    pin(crossing["e_zero"], ROW + r"e_k0 = ([\d.e-]+)")


def test_low_gain_are_family():
    are = g.are_family()
    assert are["eps"] == [1e-1, 1e-2, 1e-3, 1e-4]
    assert all(e > 0 for e in are["P_min_eig"])
    np.testing.assert_allclose(are["P_norm_over_eps"][1:], are["P_norm_over_eps"][-1], rtol=0.03)
    for i, value in enumerate(are["P_norm_over_eps"]):
        pin(value, ROW + r"P_eps / eps = " + r"[\d.]+, " * i + r"([\d.]+)")


@pytest.mark.slow
def test_reproduction_writes_every_key(tmp_path):
    g.reproduce(tmp_path)
    data = json.loads((tmp_path / f"{g.NAME}.json").read_text())
    assert set(data["low_gain_are"]) >= {"eps", "P_norm", "P_min_eig"}
    loop = data["closed_loop"]
    assert set(loop) >= {"n_initial_conditions", "stabilised_fraction", "max_final_norm", "stage_switch_times"}
    assert loop["n_initial_conditions"] >= 100
    assert loop["stabilised_fraction"] == 1.0 and loop["max_final_norm"] < 1e-6
    assert loop["stage_switch_times"]["stage3_start_s"]["never"] == 0
    assert all(w["correct"] for w in data["detectors"])
    assert (tmp_path / data["figures"][0]).stat().st_size > 10_000
    # the final norm is at the rounding floor: its digits change with XLA's compile options, so the page bounds it
    assert loop["max_final_norm"] < float(printed(ROW + r"final \\\|chi\\\| below ([\d.e-]+) at 40 s"))
    pin(loop["stage_switch_times"]["stage3_start_s"]["max"], ROW + r"stage 3 reached by ([\d.]+) s")
    pin(loop["n_initial_conditions"], ROW + r"stabilises all (\d+) grid states")
