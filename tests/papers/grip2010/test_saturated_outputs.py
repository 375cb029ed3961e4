"""The ``grip2010-saturated-outputs`` reproduction (Grip 2010, §8.5): every key, the printed pattern with the spectral
norm in alpha, the other norms' patterns, exact reconstruction and rest at the origin."""

import json

import numpy as np

from jaxobs.papers.grip2010 import saturated_outputs as g
from tests._published import pin


def test_reproduction_writes_every_key_and_matches_the_print(tmp_path):
    g.reproduce(tmp_path)
    data = json.loads((tmp_path / f"{g.NAME}.json").read_text())
    keys = ("T", "rho", "x0", "alpha", "alpha_norm", "Bbar", "intervals", "first_unsaturated_interval",
            "deadbeat_interval", "x0_reconstruction_error", "max_abs_x_after_deadbeat",
            "alternative_norms")  # fmt: skip
    for key in keys:
        assert key in data, key
    assert (data["T"], data["rho"], data["x0"]) == (0.5, 1.1, [2.0, -4.0, 1.0])
    assert data["alpha_norm"] == "2" and data["matches_printed"]
    assert data["first_unsaturated_interval"] == [1, 5] and data["deadbeat_interval"] == 6
    assert data["y1_saturated_when_y2_unsaturates"]
    np.testing.assert_allclose(data["alpha"], 1.1 * np.sqrt(2), rtol=1e-14)  # exp(A T) = I + A T, 2-norm sqrt(2)
    assert data["x0_reconstruction_error"] < 1e-9 and data["max_abs_x_after_deadbeat"] < 1e-9
    assert data["interval_map_max_error"] < 1e-8
    assert len(data["intervals"]) == 10
    for entry in data["intervals"]:
        assert set(entry) >= {"k", "mode", "unsaturated", "x_end", "U_norm"}
    assert [e["mode"] for e in data["intervals"]] == ["desaturate"] * 5 + ["deadbeat"] * 5
    assert set(data["alternative_norms"]) == {"1", "inf", "fro"}
    for other in data["alternative_norms"].values():  # no other norm reproduces the printed pattern
        assert other["deadbeat_interval"] != 6
    assert (tmp_path / data["figures"][0]).stat().st_size > 10_000
    row = r"`grip2010-saturated-outputs` \| Grip 2010 §8\.5 \|.*?"
    assert data["max_abs_x_after_deadbeat"] < 1e-11 and data["x0_reconstruction_error"] < 1e-11
    assert data["interval_map_max_error"] < 1e-13
    norms = [e["U_norm"] for e in data["intervals"][:6]]
    for i, value in enumerate(norms):
        pin(value, row + r"\\\|U_k\\\| = " + r"[\d.]+, " * i + r"([\d.]+)")
    deadbeat = [data["alternative_norms"][n]["deadbeat_interval"] for n in ("1", "inf", "fro")]
    for i, value in enumerate(deadbeat):
        pin(value, row + r"deadbeat intervals " + r"\d, " * i + r"(\d)")
