"""The ``grip2010-scb`` reproduction: the five worked examples of Grip 2010, section 7.5, and the discrepancies
between the printed results and the exact decomposition."""

import json

import numpy as np
import pytest

from tests._published import printed

sp = pytest.importorskip("sympy")

from jaxobs.papers.grip2010 import scb  # noqa: E402


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("grip2010_scb")
    summary = scb.reproduce(out)
    return summary, json.loads((out / f"{scb.NAME}.json").read_text())


def test_every_case_has_the_reported_fields(written):
    _, data = written
    keys = {"dims", "chain_lengths", "invariant_zeros", "left_invertible", "right_invertible", "A", "B", "C"}
    keys |= {"state_transform", "output_transform", "input_transform", "residuals", "printed_check", "seconds"}
    for name in scb.CASES:
        assert keys <= set(data[name]), name
        assert data[name]["residuals"] == {"A": 0, "B": 0, "C": 0, "D": 0}
        assert data[name]["matches_printed"]["dims"] and data[name]["matches_printed"]["chain_lengths"]
        assert data[name]["matches_printed"]["invariant_zeros"]
    assert "A_numeric" in data["dc_motor"] and "misprints" in data


def test_symbolic_matrices_are_srepr_strings_that_round_trip(written):
    _, data = written
    A = sp.Matrix([[sp.sympify(e) for e in row] for row in data["dc_motor"]["A"]])
    s0, s1 = sp.Symbol("sigma_0", positive=True), sp.Symbol("sigma_1", positive=True)
    assert sp.simplify(A[0, 0] + s0 / s1) == 0
    assert data["tenth_order"]["A"][0][:2] == [1, 0]  # rational case: numbers


def test_printed_checks(written):
    _, data = written
    check = {name: data[name]["printed_check"] for name in scb.CASES}
    # printed transformations: single-track cases; one differing entry each
    front = check["single_track"]["differing_entries"]
    assert [(e["matrix"], e["entry"]) for e in front] == [("output_transform", [0, 1])]
    assert sp.simplify(sp.sympify(front[0]["implied_text"]) - sp.sympify("c_r*(l_f + l_r)/(T_r*J)")) == 0
    rear = check["single_track_rear"]["differing_entries"]
    assert [(e["matrix"], e["entry"]) for e in rear] == [("A", [1, 2])]
    assert sp.simplify(sp.sympify(rear[0]["implied_text"]) - sp.sympify("(l_r*c_r - l_f*c_f)/(m*T_r*v_x)")) == 0
    # no printed transformations: the identities are solvable with nonsingular transformations, unique up to a factor
    for name in ("dc_motor", "dc_motor_sigma1_zero", "tenth_order"):
        assert check[name]["identities_hold"] and check[name]["solution_space_dim"] == 1, name


def test_solved_transformations_are_a_proof(written):
    """The transformations found for the printed tenth-order SCB satisfy the identities exactly and are nonsingular."""
    _, data = written
    A, B, C = scb.systems()["tenth_order"]
    p = scb.printed()["tenth_order"]
    G1, G2, G3 = (sp.Matrix(data["tenth_order"]["printed_check"][k]) for k in scb.TRANSFORMS)
    assert G1.det() != 0 and G2.det() != 0 and G3.det() != 0
    assert G1 * p["A"] == A * G1 and G1 * p["B"] == B * G3 and G2 * p["C"] == C * G1


def test_misprints(written):
    _, data = written
    found = {(m["case"], m.get("matrix"), tuple(m.get("entry", ()))) for m in data["misprints"]}
    assert found == {
        ("single_track", "output_transform", (0, 1)),
        ("single_track_rear", "A", (1, 2)),
        ("dc_motor", None, ()),
    }


def test_dc_motor_numeric_scb(written):
    _, data = written
    num, printed = np.array(data["dc_motor"]["A_numeric"]), np.array(scb.DC_MOTOR_A_NUMERIC_PRINTED)
    # the printed numbers are rounded to the digits shown: -433.3, -592.7, -1.1e5, -1.5e5, 95.9
    digits = np.array([[1, 1, 0], [0, 0, 0], [1e4, 1e4, 0.1]]) / 2 + np.array([[0.05, 0.05, 0], [0, 0, 0], [0, 0, 0]])
    assert np.all(np.abs(num - printed) <= np.maximum(digits, 1e-12))


def test_random_20_state_systems(written):
    """Section 7.6: with 4 inputs the typical SCB is x_a 16 + x_d 4, with 3 inputs x_b 17 + x_d 3; exact."""
    _, data = written
    runs = data["random_20_states"]
    assert all(r["residuals_zero"] for k in ("4_inputs", "3_inputs") for r in runs[k])
    assert [r["dims"] for r in runs["4_inputs"]].count([16, 0, 0, 4]) >= 2
    assert [r["dims"] for r in runs["3_inputs"]].count([0, 17, 0, 3]) >= 2


@pytest.mark.published
def test_readme_row(written):
    """The README's row of this reproduction shows the computed dims, in the order of the cases."""
    _, data = written
    row = printed(r"\| `grip2010-scb` \|([^|]*\|[^|]*)\|")
    shown = ", ".join("({}, {}, {}, {})".format(*data[name]["dims"]) for name in scb.CASES)
    assert f"dims {shown}" in row
