"""Reproductions of the printed numbers (Cortesão 2006 §7, the stochastic AOB paper §4) through `reproduce`, and the
README's reproduction figures pinned to them (tests/_published.py)."""

import json

import numpy as np
import pytest

from jaxobs.papers.cortesao import example1 as example1_module
from jaxobs.papers.cortesao import stochastic
from jaxobs.papers.cortesao.force_control import nominal_design
from jaxobs.papers.registry import reproductions
from tests._published import pin


@pytest.fixture(scope="module")
def example1(tmp_path_factory):
    out = tmp_path_factory.mktemp("example1")
    return out, example1_module.reproduce(out)


@pytest.fixture(scope="module")
def ramp(tmp_path_factory):
    out = tmp_path_factory.mktemp("ramp")
    return out, stochastic.reproduce(out)


def test_registry_names():
    assert set(reproductions()) == {
        "cortesao2006-example1",
        "cortesao-stochastic-ramp",
        "cortesao2006-example2",
        "liu-peng2002-vehicle",
        "grip2010-scb",
        "grip2010-example1.1",
        "grip2010-example5.6",
        "grip2010-drilling",
        "grip2010-dc-motor",
        "grip2010-saturated-outputs",
        "grip2010-sandwich",
        "grip2010-sideslip",
    }


@pytest.mark.slow  # the reproduction's shared run (~30 s)
def test_example1_outputs_written(example1):
    out, summary = example1
    data = json.loads((out / "cortesao2006-example1.json").read_text())
    for key in ("L_r", "kalman_gains", "kalman_gains_max_abs_error", "rms_force_error"):
        assert key in data
    assert set(data["kalman_gains"]) == {"AOB-1", "AOB-2", "AOB-3"}
    assert set(data["rms_force_error"]) == {"AOB-1", "AOB-2", "AOB-3", "CKF"}
    assert (out / "cortesao2006-example1.png").stat().st_size > 10_000


@pytest.mark.slow  # the reproduction's shared run (~30 s)
def test_eq83_state_feedback_gain_all_seven_to_4_decimals(example1):
    """Cortesão 2006 eq. 83: L_r = [0.1148 -0.0717 -0.0615 -0.0797 -0.1031 -0.1332 -0.1718]."""
    _, summary = example1
    np.testing.assert_array_equal(np.round(summary["L_r"], 4), example1_module.PRINTED_L_R)


@pytest.mark.slow  # the reproduction's shared run (~30 s)
def test_table1_kalman_gains_nominal_within_1e_3(example1):
    """Cortesão 2006 Table I with R = 2.1e-2 as printed: max abs error 9.9e-4 (about 0.1 %), the README's figure."""
    _, summary = example1
    assert summary["kalman_gains_max_abs_error"] < 1.0e-3
    for name, printed in example1_module.PRINTED_TABLE_I.items():
        np.testing.assert_allclose(summary["kalman_gains"][name], printed, rtol=1.2e-3)
    pin(summary["kalman_gains_max_abs_error"], r"Table I steady-state gains within ([0-9.e-]+) \(max abs\)")


@pytest.mark.slow  # the reproduction's shared run (~30 s)
def test_table1_kalman_gains_with_the_fitted_sigma2_over_r(example1):
    """A fit, not a reproduction: sigma^2/R scaled by SIGMA2_OVER_R_FIT = 0.99795 (R = 0.021043 unrounded), the
    factor that minimises the max abs error against the printed Table I (moving it by 1e-4 either way raises the
    error), leaves every gain within 5.0e-5 of the printed value, i.e. equal to 4 decimals up to rounding.
    AOB-2 entry 6 is 0.464250 and rounds half-to-even to 0.4642, printed 0.4643 (a rounding boundary); that value
    is a regression snapshot (this implementation's, to its 6 printed decimals)."""
    _, summary = example1
    fit = summary["kalman_gains_fit"]
    error = summary["kalman_gains_fit_max_abs_error"]
    assert fit["sigma2_over_r_fit"] == example1_module.SIGMA2_OVER_R_FIT
    plant, _ = nominal_design()
    for moved in (example1_module.SIGMA2_OVER_R_FIT - 1e-4, example1_module.SIGMA2_OVER_R_FIT + 1e-4):
        gains = {f"AOB-{n}": example1_module.aob_params(plant, n, r_scale=1.0 / moved).gain.ravel() for n in (1, 2, 3)}
        worse = max(np.abs(np.asarray(g) - example1_module.PRINTED_TABLE_I[k]).max() for k, g in gains.items())
        assert worse > error
    rounded = {k: np.round(v, 4) for k, v in fit["gains"].items()}
    mismatches = [
        (k, i) for k, v in rounded.items() for i, g in enumerate(v) if g != example1_module.PRINTED_TABLE_I[k][i]
    ]
    assert mismatches == [("AOB-2", 5)]
    pin(error, r"within ([0-9.e-]+) with sigma²/R scaled by")
    pin(example1_module.SIGMA2_OVER_R_FIT, r"with sigma²/R scaled by ([0-9.]+)")
    pin(fit["gains"]["AOB-2"][5], r"rounding boundary, ([0-9.]+) vs printed 0\.4643")


@pytest.mark.slow  # the reproduction's shared run (~30 s)
def test_force_tracking_improves_with_aob_order(example1):
    """Cortesão 2006 §7.2: "the improvement of the force response as the AOB order increases" under D(t)
    of eq. 81-82, and every AOB beats the sensor-based CKF. The RMS errors the README prints are regression
    snapshots (this implementation's, one noise seed), pinned to their printed digits."""
    _, summary = example1
    e = summary["rms_force_error"]
    assert e["AOB-1"] > e["AOB-2"] > e["AOB-3"]
    assert e["CKF"] > 3 * e["AOB-1"]
    pattern = r"RMS force error AOB-1 ([0-9.]+) N > AOB-2 ([0-9.]+) N > AOB-3 ([0-9.]+) N, sensor-based CKF ([0-9.]+) N"
    for group, name in enumerate(("AOB-1", "AOB-2", "AOB-3", "CKF"), start=1):
        pin(e[name], pattern, group)


@pytest.mark.slow  # the reproduction's shared run (~30 s)
def test_noise_sensitivity_grows_with_order(example1):
    """Cortesão 2006 §7.2: the gains increase with the order, 'being more sensitive to noise'."""
    _, summary = example1
    jitter = summary["closed_loop"]["force_jitter"]
    assert jitter["AOB-1"] < jitter["AOB-2"] < jitter["AOB-3"]


def test_stochastic_aob_ckf_steady_state_force_error(ramp):
    """The stochastic AOB paper eq. 50: Delta F_ss ~= 0.6839 Ks xdot_e = 4.1034 N (Ks = 3, xdot_e = 2) for the
    sensor-based CKF; the simulated value equals the closed form to 1e-9 and the printed
    coefficient to its 4 decimals (the README's 4.1032 N and 0.683867 pinned)."""
    _, s = ramp
    assert s["delta_f_ss_coefficient"] == pytest.approx(s["delta_f_ss_coefficient_closed_form"], rel=1e-9)
    assert round(s["delta_f_ss_coefficient"], 4) == 0.6839
    assert s["delta_f_ss_ckf"] == pytest.approx(4.1034, abs=5e-4)
    pin(s["delta_f_ss_ckf"], r"sensor-based CKF ΔF_ss = ([0-9.]+) N")
    pin(s["delta_f_ss_coefficient"], r"coefficient ([0-9.]+)\)")


def test_stochastic_aob_aob_removes_the_steady_state_error(ramp):
    """The stochastic AOB paper §4: 'When the AOB is used, the steady state error disappears' (fixed and adaptive Q)."""
    out, s = ramp
    pin(abs(s["delta_f_ss_aob"]), r"AOB-1 ΔF_ss ≈ ([0-9.e-]+) N")  # the README's figure (1.2e-9 N)
    assert abs(s["delta_f_ss_aob_adaptive"]) < 1e-11  # 3e-12 N
    peaks = s["peak_force_error_after_surface_change"]
    assert peaks["AOB-1"] < peaks["CKF-SBA"]  # "the transient Delta F is reduced"
    assert s["adaptive_strategy"]["q_max"] > 100 * s["adaptive_strategy"]["q_min"]  # Q_k adapts
    data = json.loads((out / "cortesao-stochastic-ramp.json").read_text())
    assert {"delta_f_ss_ckf", "delta_f_ss_aob"} <= set(data)
    assert (out / "cortesao-stochastic-ramp.png").exists()
