"""The reproduction ``grip2010-sideslip`` (Grip 2010 ch. 2): the NVSO and its EKF baseline on the simulated drives
and the chapter's claims as checks, with expected values from physics (``b / g``, the true road angles). The
default set runs one reduced reproduction (the double lane change and the checks' drives) shared by every test;
the full run over all seven manoeuvres is slow."""

import json

import numpy as np
import pytest

from jaxobs.papers.grip2010 import sideslip
from jaxobs.papers.registry import reproductions
from jaxobs.vehicle import MANOEUVRES, VehicleParams
from tests._published import pin

ESTIMATE_KEYS = {
    "max_abs_beta_error_deg",
    "rms_beta_error_deg",
    "theta_hat_final",
    "bank_estimate_deg",
    "inclination_estimate_deg",
}


@pytest.fixture(scope="module")
def reduced(tmp_path_factory):
    out = tmp_path_factory.mktemp("sideslip")
    summary = sideslip.reproduce(out, manoeuvres=["double_lane_change_120kmh"], cost_repeats=1)
    return out, summary


def _check_manoeuvre_keys(entry):
    assert {"peak_ay_g", "peak_beta_deg", "nvso", "ekf"} <= set(entry)
    for observer in ("nvso", "ekf"):
        assert ESTIMATE_KEYS <= set(entry[observer])
        assert all(np.isfinite(entry[observer][k]) for k in ESTIMATE_KEYS)


@pytest.mark.slow  # shares a 25 s reproduction run
def test_registered_and_written_with_every_key(reduced):
    out, summary = reduced
    assert reproductions()["grip2010-sideslip"] is sideslip.REPRODUCTION
    data = json.loads((out / "grip2010-sideslip.json").read_text())
    assert set(data["manoeuvres"]) == {"double_lane_change_120kmh"}
    _check_manoeuvre_keys(data["manoeuvres"]["double_lane_change_120kmh"])
    assert set(data["checks"]) == {"known_friction_flat", "ay_bias", "bank", "inclination", "friction_adaptation",
                                   "straight_no_excitation", "lemma_4_1", "lemma_4_2", "lemma_3_1"}  # fmt: skip
    assert data["checks"]["lemma_4_1"] == {"a": 4.0, "bound": pytest.approx(4.0 / 9.81), "spr_below": True,
                                           "spr_above": False}  # fmt: skip
    lemma_4_2 = data["checks"]["lemma_4_2"]
    assert lemma_4_2["bound"] == pytest.approx(10.0**2 * 0.8995 / 9.81)
    assert (lemma_4_2["K_vy"], lemma_4_2["delta_min"], lemma_4_2["spr_below"], lemma_4_2["spr_above"]) == (
        10.0, 0.8995, True, False)  # fmt: skip
    assert data["checks"]["lemma_3_1"]["max_relative_V_increase"] < 0  # V decreases at every step
    assert {"max_abs_beta_error_deg", "rms_beta_error_deg"} <= set(data["checks"]["known_friction_flat"])
    assert {"bias", "theta_b_final", "expected"} <= set(data["checks"]["ay_bias"])
    assert {"bank_deg", "theta_b_final", "expected"} <= set(data["checks"]["bank"])
    assert {"incl_deg", "theta_i_final", "expected"} <= set(data["checks"]["inclination"])
    friction = data["checks"]["friction_adaptation"]
    assert {"theta_true", "theta_hat_final", "max_abs_beta_error_deg"} <= set(friction)
    assert set(friction["max_abs_beta_error_deg"]) == {"mode1", "mode2"}
    assert {"theta_hat_change", "vy_error_final"} <= set(data["checks"]["straight_no_excitation"])
    assert {"nvso_step_us", "ekf_step_us", "ratio"} <= set(data["cost"])
    assert data["cost"]["nvso_step_us"] > 0 and data["cost"]["ekf_step_us"] > 0
    assert {"vehicle", "nvso", "ekf", "sensors", "checks"} <= set(data["assumed"])
    assert {"(2.13)", "(2.20) vs ch. 4"} <= set(data["misprints"])
    assert data["figures"] == ["grip2010_sideslip.png"]
    assert (out / "grip2010_sideslip.png").stat().st_size > 20_000


@pytest.mark.slow  # shares a 25 s reproduction run
def test_known_friction_on_a_flat_road(reduced):
    """Grip 2010 §2.3: with known friction on a horizontal road the basic observer (2.3), (2.5) is GES. On the double
    lane change with a flat road (peak 0.92 g) and exact sensors the sideslip error is 0.18 deg at most, 0.080 deg
    rms, not 0: the observer's friction model omits the simulator's tyre relaxation (as the thesis's model omits
    the real tyres' dynamics, §2.8); within the < 1 deg of §2.8's requirement for feedback control."""
    _, s = reduced
    known = s["checks"]["known_friction_flat"]
    assert known["max_abs_beta_error_deg"] < 0.2
    assert known["rms_beta_error_deg"] < 0.09
    pin(known["max_abs_beta_error_deg"], r"known friction on a flat road ([0-9.]+) deg max")
    pin(known["rms_beta_error_deg"], r"known friction on a flat road [0-9.]+ deg max, ([0-9.]+) deg rms")


@pytest.mark.slow  # shares a 25 s reproduction run
def test_accelerometer_bias_goes_into_the_bank_estimate(reduced):
    """Grip 2010 §2.6: an a_y bias b only biases the bank estimate: theta_b -> b / g on a flat straight road, with
    the roll correction of §2.2 ``b / (g (1 + p_phi g))`` (0.04705; b / g = 0.05097); measured equal to 5e-9."""
    _, s = reduced
    c = s["checks"]["ay_bias"]
    assert c["expected"] == pytest.approx(c["bias"] / (9.81 * c["roll_factor"]), rel=1e-3)
    assert abs(c["theta_b_final"] - c["expected"]) < 1e-7


@pytest.mark.slow  # shares a 25 s reproduction run
def test_bank_and_inclination_are_estimated(reduced):
    """Grip 2010 §2.6: theta_b -> cos(Theta) sin(Phi) and theta_i -> sin(Theta) on straight drives of 30 s on a
    3 deg bank (measured 1.6e-8 off) and a 5 deg slope (4.5e-5 off, still converging at the slow pole of
    ``s^2 + K_vx s + g K_theta_i K_vx``, -0.27 1/s)."""
    _, s = reduced
    bank, incl = s["checks"]["bank"], s["checks"]["inclination"]
    assert bank["expected"] == pytest.approx(np.sin(np.deg2rad(3.0)))
    assert abs(bank["theta_b_final"] - bank["expected"]) < 1e-7
    assert incl["expected"] == pytest.approx(np.sin(np.deg2rad(5.0)))
    assert abs(incl["theta_i_final"] - incl["expected"]) < 1e-4


@pytest.mark.slow  # shares a 25 s reproduction run
def test_friction_adaptation_on_low_friction(reduced):
    """Grip 2010 §2.4-2.5 on friction 0.3 (a 25 deg sine steer at 80 km/h, peak 0.27 g, sideslip 0.87 deg): with
    friction estimation (on 90 % of the time) the estimate of mu_H moves from 1 to within 15 % of 0.3 in the 10 s,
    and after 5 s the largest sideslip error is below that of mode 1 only (theta held at theta* = 1; measured 0.25
    against 0.45 deg; halved once the estimate has settled, tests/vehicle/test_nvso.py). Over the whole drive the
    largest errors are alike: both come at the first steer, before anything is learned."""
    _, s = reduced
    c = s["checks"]["friction_adaptation"]
    assert c["theta_hat_final_mode1"] == 1.0
    assert c["theta_hat_final"] == pytest.approx(0.3, rel=0.15)
    adapted = c["max_abs_beta_error_after_first_cycles_deg"]
    assert adapted["mode2"] < adapted["mode1"]
    assert c["max_abs_beta_error_deg"]["mode2"] < c["max_abs_beta_error_deg"]["mode1"] < 0.5
    pin(c["theta_hat_final"], r"on friction 0.3 the friction estimate goes from 1 to ([0-9.]+) ")


@pytest.mark.slow  # shares a 25 s reproduction run
def test_no_friction_convergence_without_excitation(reduced):
    """Grip 2010 §2.4: on a straight drive (no lateral excitation) in mode 2 the velocity error converges (0.5 m/s
    to 3e-10 m/s in 30 s) but theta does not: from 0.5 (true 1) it moves only during the v_y transient, to 0.37
    (change -0.13), away from the truth."""
    _, s = reduced
    c = s["checks"]["straight_no_excitation"]
    assert c["vy_error_initial"] == 0.5
    assert abs(c["vy_error_final"]) < 1e-8
    assert abs(c["theta_hat_initial"] + c["theta_hat_change"] - c["theta_true"]) > 0.4


@pytest.mark.slow  # shares a 25 s reproduction run
def test_lane_change_nvso_and_ekf(reduced):
    """The double lane change (0.92 g, 3.9 deg, default sensor noise and 15 Hz low-pass): NVSO error 0.24 deg max,
    0.11 rms; EKF 0.34 deg max, 0.15 rms; both bank estimates within 0.1 deg of the road's 0.5 deg."""
    _, s = reduced
    m = s["manoeuvres"]["double_lane_change_120kmh"]
    assert m["peak_ay_g"] == pytest.approx(0.91, abs=0.02)
    assert m["nvso"]["max_abs_beta_error_deg"] < 0.3
    assert m["ekf"]["max_abs_beta_error_deg"] < 0.4
    for observer in ("nvso", "ekf"):
        assert abs(m[observer]["bank_estimate_deg"] - 0.5) < 0.1
    pin(m["peak_ay_g"], r"double lane change at ([0-9.]+) g")
    pin(m["nvso"]["max_abs_beta_error_deg"], r"sideslip error NVSO ([0-9.]+) deg, EKF")
    pin(m["ekf"]["max_abs_beta_error_deg"], r"sideslip error NVSO [0-9.]+ deg, EKF ([0-9.]+) deg \(max\)")


def test_unknown_manoeuvre_raises():
    with pytest.raises(ValueError, match="manoeuvres must be a non-empty subset"):
        sideslip.estimate(VehicleParams(), ["moon_landing"])
    with pytest.raises(ValueError, match="manoeuvres must be a non-empty subset"):
        sideslip.estimate(VehicleParams(), [])


@pytest.mark.slow
def test_full_reproduction(tmp_path):
    """All seven manoeuvres (measured, default run): every key; both observers hold the 40 m circle within 0.1 deg
    rms (NVSO 0.039, EKF 0.054; the EKF lost it from its start, 23.8 deg, before its start-up fix) and the ice lake
    within 10 deg rms (NVSO 5.5, EKF 9.1; they were at 10.5 and 53 deg before the counter-steer oversteer condition
    and the EKF's start-up fix, the NVSO at 7.6 with the thesis's friction scale). The gaps to the thesis's figures:
    on the ice lake (Fig. 2.7: error < 3 deg most of the time) both underestimate the 50 deg drifts (max errors
    11.7 and 21.5 deg); on the circle the NVSO's max error is 1.16 deg (Fig. 2.6 upper: more accurate)."""
    s = sideslip.reproduce(tmp_path)
    assert set(s["manoeuvres"]) == set(MANOEUVRES)
    for entry in s["manoeuvres"].values():
        _check_manoeuvre_keys(entry)
    m = s["manoeuvres"]
    for name in ("sine_steer", "step_steer_200kmh", "double_lane_change_120kmh", "straight"):
        assert m[name]["nvso"]["max_abs_beta_error_deg"] < 0.3
    assert m["step_steer_200kmh"]["nvso"]["bank_estimate_deg"] == pytest.approx(1.5, abs=0.1)
    for observer in ("nvso", "ekf"):
        assert m["circle_40m_ramp"][observer]["rms_beta_error_deg"] < 0.1
        assert m["ice_lake_circles"][observer]["rms_beta_error_deg"] < 10.0
    pin(m["circle_40m_ramp"]["nvso"]["rms_beta_error_deg"], r"40 m circle NVSO ([0-9.]+), EKF")
    pin(m["circle_40m_ramp"]["ekf"]["rms_beta_error_deg"], r"40 m circle NVSO [0-9.]+, EKF ([0-9.]+) deg rms")
    pin(m["ice_lake_circles"]["nvso"]["rms_beta_error_deg"], r"ice lake ([0-9.]+) deg rms NVSO error")  # the gap
    pin(m["ice_lake_circles"]["ekf"]["rms_beta_error_deg"], r"ice lake [0-9.]+ deg rms NVSO error, EKF ([0-9.]+)")
