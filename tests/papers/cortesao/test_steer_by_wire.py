"""Cortesão 2006 §8 (Example 2, steer-by-wire): realisation, L_r / L_c design, eq. 113-114 and the AOB-1 loop."""

import json

import numpy as np
import pytest

from jaxobs.design import dc_compensation, place
from jaxobs.lti import c2d, dcgain, tf2ss
from jaxobs.papers.cortesao import steer_by_wire as sbw
from jaxobs.papers.registry import reproductions
from tests._published import pin

OMEGA = np.array([0.1, 1.0, 10.0, 86.7, 300.0, 1000.0])  # rad/s, around the 87 rad/s target resonance


@pytest.fixture(scope="module")
def design():
    return sbw.design()


@pytest.fixture(scope="module")
def results():
    return sbw.example2()


def test_registry_entry():
    assert reproductions()[sbw.NAME] is sbw.REPRODUCTION


# ------------------------------------------------------------------------------------------------
# Realisation


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_target_realisation_equals_eq91_94(sign):
    """Eq. 90-94: C (sI - A)^{-1} B of the target model equals the printed transfer functions (2 x 4, the
    tau_m and f_s columns zero) at six frequencies, to 4e-15 relative (measured 4e-16: rounding)."""
    printed, _ = sbw.printed_transfer_matrices(1j * OMEGA, sign)
    got = sbw.frequency_response(sbw.target_model(sign), 1j * OMEGA)
    np.testing.assert_allclose(got, printed, rtol=4e-15, atol=1e-15 * np.max(np.abs(printed)))


def test_sbw_realisation_equals_eq95_99():
    """Eq. 95-99: the 7-state SBW model has [y_h, -alpha_h y_h, 0, 0; 0, 0, y_r, -alpha_r y_r]."""
    model = sbw.sbw_model()
    assert (model.n_states, model.n_inputs, model.n_outputs) == (7, 4, 2)
    _, printed = sbw.printed_transfer_matrices(1j * OMEGA)
    got = sbw.frequency_response(model, 1j * OMEGA)
    np.testing.assert_allclose(got, printed, rtol=4e-15, atol=1e-15 * np.max(np.abs(printed)))


@pytest.mark.slow
@pytest.mark.published
def test_readme_realisation_figure(results):
    """The README's "transfer functions equal to 4e-16": the reproduction's max relative error of both models."""
    realisation = results["realisation"]
    pin(
        max(realisation["target_max_rel_error"], realisation["sbw_max_rel_error"]),
        r"transfer functions equal to ([0-9.e-]+)\)",
    )


def test_discrete_plant_dimensions_and_dc(design):
    """§8.4: Phi_r is 7 x 7, Gamma_r 7 x 4 at T_s = 1 ms; ZOH keeps the DC gains."""
    plant = design["plant"]
    assert plant.A.shape == (7, 7) and plant.B.shape == (7, 4) and plant.dt == 1e-3
    np.testing.assert_allclose(dcgain(plant), dcgain(sbw.sbw_model()), rtol=1e-9)


def test_eq100_poles_are_the_discrete_target_poles():
    """Eq. 100: lambda_{1,2} = 0.9890 +- 0.0859i, lambda_3 = 0.9940 are exp(T_s s_i) of eq. 91-94 (4 decimals)."""
    poles = sbw.target_poles()
    np.testing.assert_allclose(np.round(poles.real, 4), [0.9890, 0.9890, 0.9940])
    np.testing.assert_allclose(np.round(np.sort(poles.imag), 4), [-0.0859, 0.0, 0.0859])


# ------------------------------------------------------------------------------------------------
# State feedback and DC compensation


@pytest.mark.parametrize("method", ["decoupled", "coupled"])
def test_state_feedback_places_eq100_101_without_feedback_to_T_h_F_r(design, method):
    """Eq. 100-101 with the T_h and F_r columns of Gamma_r zeroed for the design: rows 1 and 3 of L_r are 0."""
    plant = design["plant"]
    L = sbw.state_feedback(plant, method)
    np.testing.assert_array_equal(L[list(sbw.NON_ACTUATED)], 0.0)
    got = np.sort_complex(np.linalg.eigvals(np.asarray(plant.A) - np.asarray(plant.B) @ L))
    np.testing.assert_allclose(got, np.sort_complex(sbw.design_poles()), atol=1e-9)


def test_decoupled_gain_is_block_diagonal(design):
    """Decoupled design: tau_m feeds back only steering states, f_s only rack states."""
    L = design["L_r"]
    np.testing.assert_array_equal(L[1, sbw.RACK_STATES], 0.0)
    np.testing.assert_array_equal(L[3, sbw.STEERING_STATES], 0.0)


def test_closed_loop_dc_gain_equals_target_dc(design):
    """Eq. 102-104: with r = L_c [T_h; F_r] the SBW closed loop has the target's DC gain (to 1e-12)."""
    cols = list(sbw.NON_ACTUATED)
    sbw_dc = np.asarray(dcgain(sbw.closed_loop(design["plant"], design["L_r"])))[:, cols] @ design["L_c"]
    target_dc = np.asarray(dcgain(design["target"]))[:, cols]
    np.testing.assert_allclose(sbw_dc, target_dc, rtol=1e-10)


def test_eq105_L_c_row1_and_sign_convention(results):
    """Eq. 105 printed L_c = [[0.4785, -0.0046], [67.0076, -0.6399]]. With eq. 91-94 as printed the F_r
    column comes out positive (every row has the target's DC ratio T13(0)/T11(0) = +0.00955, T(0) is
    rank one); with the F_r column flipped (road_force_sign=-1) the signs match the print. Row 1 then
    equals the print to 1.1e-4 (0.47839 vs 0.4785; decoupled design with the printed eq. 100 poles)."""
    np.testing.assert_allclose(results["L_c_row_ratio"], results["target_dc_ratio_T13_T11"], rtol=2e-4)
    Lc, printed = np.asarray(results["L_c_paper_sign"]), np.asarray(sbw.PRINTED_L_C)
    np.testing.assert_array_equal(np.sign(Lc), np.sign(printed))
    np.testing.assert_allclose(Lc[0], printed[0], atol=1.1e-4)
    np.testing.assert_allclose(np.asarray(results["L_c"])[:, 0], Lc[:, 0])  # only column 2 changes sign
    pin(np.abs(Lc[0] - printed[0]).max(), r"`L_c` row 1 = printed eq\. 105 to ([0-9.e-]+) with")


def test_eq105_L_c_row2_gap_documented(results):
    """Documented gap: row 2 of the printed L_c (67.0076, -0.6399) is 1.07 % below the decoupled design's
    (67.7228, -0.6467: a regression snapshot, this implementation's, to its 4 printed decimals). It depends on
    which poles the rack loop gets (MATLAB's coupled place); no pole assignment among eq. 100-101 gives the
    printed row ({0.89, 0.994}: 67.72, {-0.89, 0.994}: 65.77)."""
    Lc = np.asarray(results["L_c_paper_sign"])
    np.testing.assert_allclose(Lc[1], [67.7228, -0.6467], atol=5e-5)
    rel = np.abs(Lc[1] - np.asarray(sbw.PRINTED_L_C[1])) / np.abs(sbw.PRINTED_L_C[1])
    assert np.all((rel > 0.010) & (rel < 0.011))
    for r in rel:
        pin(100 * r, r"row 2 ([0-9.]+) % off")


def test_unrounded_eq100_poles_move_row1_away_from_print(results):
    """With the unrounded target poles row 1 is 0.4811 (not 0.4785): the paper used the rounded eq. 100. (0.48108 is
    a regression snapshot, this implementation's, to its 5 printed decimals.)"""
    assert results["L_c_unrounded_eq100_poles"][0][0] == pytest.approx(0.48108, abs=1e-5)


# ------------------------------------------------------------------------------------------------
# Eq. 113-114 and the closed loop


def test_eq113_formula_equals_simulated_steady_state(results):
    """Eq. 113 two ways: -diag(alpha_h, alpha_r)(0)^{-1} L_c [0; 1000] vs the AOB-1's p_2, p_4 3 s after the
    road disturbance (agree to 7e-14, the README's figure; asserted 1e-12); p_1 and p_3 stay locked at 0
    (eq. 109). [2.7685, -0.6176] is a regression snapshot (this implementation's, to 4 decimals); in the print's
    sign convention it is the README's [-2.77, 0.62]."""
    difference = np.abs(np.asarray(results["eq113_simulated"]) - results["eq113_formula"]).max()
    assert difference < 1e-12
    pin(difference, r"simulated AOB-1 steady state to ([0-9.e-]+),")
    np.testing.assert_allclose(results["eq113_formula"], [2.7685, -0.6176], atol=5e-5)
    assert results["locked_active_states_max_abs"] == 0.0
    for group in (1, 2):
        pin(results["eq113_formula_paper_sign"][group - 1], r"\[p2, p4\] = \[([0-9.-]+), ([0-9.-]+)\]", group)


def test_eq114_printed_p2_is_a_slip(results):
    """Eq. 114 prints [p_2, p_4] -> [-0.27, 0.61]. Eq. 113 with the printed L_c gives [-2.79, 0.61]: p_4
    reproduces (0.611 vs 0.61), p_2 is off by a factor 10 (documented gap, a misprint of -2.7). -2.788 is eq. 113
    evaluated on printed numbers (the printed L_c and the alpha(0) of eq. 95-98)."""
    p = results["eq113_formula_printed_L_c"]
    assert p[1] == pytest.approx(0.61, abs=5e-3)
    assert p[0] == pytest.approx(-2.788, abs=1e-3)
    assert abs(p[0] - sbw.PRINTED_EQ114[0]) > 2.0
    np.testing.assert_allclose(results["eq113_formula_paper_sign"], -np.asarray(results["eq113_formula"]))


def test_fig8_model_matching(results):
    """Fig. 8: SBW + AOB-1 follows the conventional car: delta_h within 6.1 % and x_r within 0.5 % of the
    target's peak (2 Nm, 0.5 Hz torque with the assumed vehicle impedance)."""
    e = results["model_matching_error"]
    assert e["delta_h"]["max_abs"] < 0.061 * e["delta_h"]["target_peak"]
    assert e["x_r"]["max_abs"] < 0.005 * e["x_r"]["target_peak"]
    pattern = r"Fig\. 8 steering-angle error ([0-9.]+) mrad on a ([0-9.]+) mrad peak"
    pin(1e3 * e["delta_h"]["max_abs"], pattern, 1)
    pin(1e3 * e["delta_h"]["target_peak"], pattern, 2)


def test_fig9_rack_has_no_steady_state_error(results):
    """Fig. 9: after tau_D = 1000 N the SBW rack returns to 0 (conventional car: -tau_D / stiffness = -5 mm);
    the steering angle keeps a smaller deviation than the conventional car's."""
    r = results["road_disturbance"]
    pin(r["final_x_r_sbw"], r"Fig\. 9 rack back to ([0-9.e-]+) m")  # the README's 1e-11 m (1.2e-11 m)
    assert r["final_x_r_target"] == pytest.approx(-ROAD_OVER_STIFFNESS, rel=1e-6)
    pin(1e3 * r["final_x_r_target"], r"\(conventional car: ([0-9.-]+) mm\)")
    assert 0 < r["final_delta_h_sbw"] < r["final_delta_h_target"]


ROAD_OVER_STIFFNESS = sbw.ROAD_DISTURBANCE / sbw.IMPEDANCE_STIFFNESS


def test_eq107_actuation_points(results):
    """Eq. 107 as printed (open-loop alpha^{-1} with low-pass filters) diverges in the loop; the closed-loop
    DC-consistent feed-forward is stable and keeps the rack free of steady-state error, with p_4 ->
    -tau_D / alpha_r(0) (the disturbance now enters F_r unamplified)."""
    assert results["eq107_as_printed_diverges"]
    r = results["road_disturbance"]
    alpha_r0 = sbw.ALPHA_R[0][0] / sbw.ALPHA_R[1][-1]
    assert r["actuators_p_final"][3] == pytest.approx(-sbw.ROAD_DISTURBANCE / alpha_r0, rel=1e-9)
    assert abs(r["actuators_final_x_r"]) < 1e-8


def test_actuation_filter_dc_is_eq107(design):
    """At DC the printed eq. 107 filter is -diag(alpha_h, alpha_r)(0)^{-1} (L_c - I)."""
    ff = sbw.actuation_point_filter(design["L_c"])
    a0 = np.array([sbw.ALPHA_H[0][0] / sbw.ALPHA_H[1][-1], sbw.ALPHA_R[0][0] / sbw.ALPHA_R[1][-1]])
    np.testing.assert_allclose(dcgain(ff), -np.diag(1 / a0) @ (design["L_c"] - np.eye(2)), rtol=1e-9)


def test_reproduce_writes_json_and_figures(tmp_path, monkeypatch, results):
    monkeypatch.setattr(sbw, "example2", lambda: results)
    summary = sbw.reproduce(tmp_path)
    data = json.loads((tmp_path / f"{sbw.NAME}.json").read_text())
    for key in ("L_c", "L_c_printed", "eq113_formula", "eq113_simulated", "model_matching_error", "sign_convention"):
        assert key in data
    assert summary["figures"] == [f"{sbw.NAME}-fig8.png", f"{sbw.NAME}-fig9.png"]
    assert all((tmp_path / f).stat().st_size > 10_000 for f in summary["figures"])


# ------------------------------------------------------------------------------------------------
# Bad input


def test_tf_matrix_with_inconsistent_shapes():
    with pytest.raises(ValueError, match="row 1"):
        tf2ss([[sbw.T11, sbw.T13], [sbw.T21]], [[sbw.TARGET_DEN] * 2, [sbw.TARGET_DEN]])
    with pytest.raises(ValueError, match="rows"):
        tf2ss([[sbw.T11]], [[sbw.TARGET_DEN], [sbw.TARGET_DEN]])


def test_tf_matrix_with_improper_entry():
    with pytest.raises(ValueError, match="improper"):
        tf2ss([[(1.0, 0.0, 0.0, 0.0, 0.0)]], [[sbw.TARGET_DEN]])


def test_unreachable_pole_set(design):
    """Zeroing f_s as well leaves the rack unreachable; the decoupled design needs the rack poles."""
    plant = design["plant"]
    with pytest.raises(ValueError, match="not controllable"):
        place(plant.A, plant.B, sbw.design_poles(), zero_input_columns=(0, 2, 3))
    with pytest.raises(ValueError, match="rack poles"):
        sbw.state_feedback(plant, "decoupled", [0.5] * 7)
    with pytest.raises(ValueError, match="method"):
        sbw.state_feedback(plant, "lqr")


def test_non_square_dc_gain():
    with pytest.raises(ValueError, match="square"):
        dc_compensation(np.ones((2, 2)), np.ones((2, 4)))


def test_other_bad_arguments(design):
    with pytest.raises(ValueError, match="road_force_sign"):
        sbw.target_model(2.0)
    with pytest.raises(ValueError, match="2 x 2"):
        sbw.actuation_point_filter(np.eye(3))
    with pytest.raises(ValueError, match="cutoff"):
        sbw.actuation_point_filter(np.eye(2), cutoff=0.0)
    with pytest.raises(ValueError, match="reference"):
        sbw.simulate_sbw(design, np.zeros(3), np.zeros(3), reference="feedforward")


def test_discretisation_keeps_target_dc():
    np.testing.assert_allclose(dcgain(c2d(sbw.target_model(), sbw.H)), dcgain(sbw.target_model()), rtol=1e-9)


# ------------------------------------------------------------------------------------------------
# Robustness sweep over actuator-model errors (jaxobs.papers.cortesao.steer_by_wire_sweep)


def test_scaled_transfer_function_scales_gain_and_poles():
    num, den = sbw.scaled_transfer_function(sbw.Y_H, gain=1.2, pole=0.8)
    np.testing.assert_allclose(num, 1.2 * np.asarray(sbw.Y_H[0]))
    np.testing.assert_allclose(np.sort_complex(np.roots(den)), np.sort_complex(0.8 * np.roots(sbw.Y_H[1])), rtol=1e-9)
    with pytest.raises(ValueError, match="pole"):
        sbw.scaled_transfer_function(sbw.Y_H, pole=0.0)
    with pytest.raises(ValueError, match="mismatch keys"):
        sbw.sbw_model({"y_x": (1.0, 1.0)})


@pytest.mark.slow
def test_robustness_sweep_small(tmp_path, capsys):
    """``jaxobs sweep`` with ``scenario = "steer-by-wire"``: the nominal plant (all factors 1) reproduces the
    Example 2 numbers (steering-angle RMS 4.07 % of the target's peak, a regression snapshot, the README's
    "4.1 % nominal"; rack left at ~1e-11 m after the road disturbance, stable); a +-30 % batch runs end to end
    with its report."""
    from jaxobs.cli import main

    nominal = tmp_path / "nominal.toml"
    nominal.write_text('scenario = "steer-by-wire"\nchunk_size = 2\n[plants]\ncount = 2\n'
                       "gain_scale = [1.0, 1.0]\npole_scale = [1.0, 1.0]\n")  # fmt: skip
    assert main(["sweep", "--config", str(nominal), "--out", str(tmp_path / "nominal"), "--no-progress"]) == 0
    summary = json.loads((tmp_path / "nominal" / "summary.json").read_text())
    assert summary["stable_fraction"] == 1.0
    assert summary["steering_rms_rel"]["median"] == pytest.approx(0.0407, abs=5e-5)
    pin(100 * summary["steering_rms_rel"]["median"], r"\(16 % at the 90th percentile, ([0-9.]+) % nominal\)")
    assert summary["rack_final_error_m"]["max"] < 1e-9
    mixed = tmp_path / "mixed.toml"
    mixed.write_text('scenario = "steer-by-wire"\nchunk_size = 3\n[plants]\ncount = 6\n')
    assert main(["sweep", "--config", str(mixed), "--out", str(tmp_path / "mixed"), "--no-progress"]) == 0
    out = tmp_path / "mixed"
    assert json.loads((out / "summary.json").read_text())["num_configs"] == 6
    assert (out / "robustness.png").stat().st_size > 0 and "stable fraction" in (out / "report.md").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text('scenario = "steer-by-wire"\n[plants]\ngain_scale = [1.3, 0.7]\n')
    assert main(["sweep", "--config", str(bad), "--out", str(tmp_path / "bad")]) == 2
    assert "plants.gain_scale" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.published
def test_readme_sweep_figures(tmp_path):
    """The README's figures of ``jaxobs sweep --config tuning/steer_by_wire_sweep.toml`` (1000 plants), from a fresh
    run of that command: stable fraction, the stable fraction when no factor is off by more than 20 %, the
    steering-angle RMS error (median, 90th percentile) and the largest final rack error. Regression snapshots of
    this implementation (a seeded Monte-Carlo run), pinned to their printed digits."""
    from jaxobs.cli import main

    out = tmp_path / "sbw"
    assert main(["sweep", "--config", "tuning/steer_by_wire_sweep.toml", "--out", str(out), "--no-progress"]) == 0
    s = json.loads((out / "summary.json").read_text())
    pin(s["stable_fraction"], r"up to \+-30 %\. Stable fraction ([0-9.]+) \(")
    assert s["stable_fraction_by_largest_error"]["0-10 %"] in (None, 1.0)
    pin(s["stable_fraction_by_largest_error"]["10-20 %"], r"\(([0-9.]+) when no factor is off by more than 20 %")
    pin(100 * s["steering_rms_rel"]["median"], r"RMS error is ([0-9.]+) % of the target's peak in the median")
    pin(100 * s["steering_rms_rel"]["p90"], r"in the median \(([0-9.]+) % at the 90th percentile")
    pin(s["rack_final_error_m"]["max"], r"returns to within ([0-9.e-]+) m after the 1000 N road disturbance")
