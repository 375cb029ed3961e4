"""The ``grip2010-dc-motor`` reproduction (Grip 2010, section 6.8): the SCB structures, the printed gains and the
1/eps scaling by default; the full simulation (20 s, two noise levels, the pure ESO) is slow."""

import json

import numpy as np
import pytest

from tests._published import pin

pytest.importorskip("sympy")

from jaxobs.papers.grip2010 import dc_motor


def test_design_matches_the_printed_structure_and_gains():
    summary, _, _ = dc_motor.design()
    assert summary["design_system"]["scb_dims"] == (0, 0, 0, 4)
    assert summary["true_error_system"]["scb_dims"] == (1, 0, 0, 3)
    np.testing.assert_allclose(summary["true_error_system"]["A_aa"], [[-260.0 / 0.6]], rtol=1e-12)
    for name in ("observer1", "observer2"):
        K, printed = np.asarray(summary[name]["K"]), np.asarray(summary[name]["printed_K"])
        assert np.max(np.abs(K - printed)) < 0.1, (name, K)  # printed to the nearest integer ("K ~ [6, 13, 0, 13]")
    poles = np.asarray(summary["observer1"]["poles_true_system"])
    assert np.all(poles[:, 0] < 0)
    scaling = summary["eps_scaling"]
    slow = np.asarray([np.asarray(p)[:, 0] for p in scaling["slow_poles"]])  # real parts of the slow pair
    np.testing.assert_allclose(slow[:, 0] * np.asarray(scaling["eps"]), slow[0, 0], rtol=0.01)  # ~ 1 / eps
    np.testing.assert_allclose(scaling["K"][2][0] * 0.2, scaling["K"][0][0], rtol=1e-12)  # K_1 = Kbar_1 / eps
    row = r"`grip2010-dc-motor` \| Grip 2010 §6\.8 \|[^|]*"
    pin(summary["true_error_system"]["A_aa"][0, 0], row + r"the zero (-[\d.]+)")
    K1, K2 = summary["observer1"]["K"], summary["observer2"]["K"]
    for i, value in enumerate(K1[1:]):
        pin(value, row + r"observer 1 K = \[6" + ", [-\\d.]+" * i + r", ([-\d.]+)")
    for i, value in enumerate(K2[1:]):
        pin(value, row + r"observer 2 K = \[4" + ", [-\\d.]+" * i + r", ([-\d.]+)")
    pin(poles[0, 0], row + r"true system (-[\d.]+) ± ([\d.]+)j")
    pin(poles[0, 1], row + r"true system (-[\d.]+) ± ([\d.]+)j", 2)
    pin(poles[2, 0], row + r"true system [^,]*, (-[\d.]+) ± ([\d.]+)j")
    pin(poles[2, 1], row + r"true system [^,]*, (-[\d.]+) ± ([\d.]+)j", 2)


@pytest.mark.slow
def test_reproduction_writes_every_key(tmp_path):
    summary = dc_motor.reproduce(tmp_path)
    data = json.loads((tmp_path / f"{dc_motor.NAME}.json").read_text())
    sim = data["simulation"]
    assert set(sim["rms_omega_error"]["pure_eso"]) == {"1.0", "0.5", "0.2", "0.1"}
    assert sim["finite"] and data["simulation_noise_free"]["finite"]
    assert 0.05 <= sim["theta_hat_mean_t_gt_10"] <= 1.0
    for key in ("design_system", "true_error_system", "observer1", "observer2", "eps_scaling", "misprints"):
        assert key in data
    assert all((tmp_path / f).exists() for f in summary["figures"])
    row = r"`grip2010-dc-motor` \| Grip 2010 §6\.8 \|[^|]*"
    pin(sim["theta_hat_mean_t_gt_10"], row + r"theta_hat averages ([\d.]+)")
    rms = sim["rms_omega_error"]
    pin(rms["observer1"], row + r"observer 1 ([\d.]+),")
    pin(rms["observer2"], row + r"observer 2 ([\d.]+),")
    for i, eps in enumerate(("1.0", "0.5", "0.2", "0.1")):
        pin(rms["pure_eso"][eps], row + r"same gains\) " + "[\\d.]+, " * i + r"([\d.]+)")
