"""The named test drives of jaxobs.vehicle: names, the lane change's 0.9 g, sensors on a drive, and (slow) every
full manoeuvre against the peaks its docstring states."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.vehicle import MANOEUVRES, SensorParams, VehicleParams, manoeuvre, measure, simulate

P = VehicleParams()
DEG = 180 / np.pi


def test_names_are_those_of_the_issue_and_unknown_names_list_them():
    assert set(MANOEUVRES) == {
        "step_steer_200kmh",
        "double_lane_change_120kmh",
        "circle_40m_ramp",
        "ice_lake_circles",
        "mountain_road",
        "straight",
        "sine_steer",
    }
    for bad in (lambda: manoeuvre("slalom"), lambda: simulate("slalom", P)):
        with pytest.raises(ValueError, match="double_lane_change_120kmh"):
            bad()


def test_lane_change_reaches_about_0_9_g_and_its_sensors_sample_at_100_hz():
    """First 3.5 s of the lane change (the peak, measured 0.915 g at 2.9 s), then ESC measurements of it."""
    tr = jax.jit(lambda p: simulate("double_lane_change_120kmh", p, duration=3.5))(P)
    peak = float(jnp.max(jnp.abs(tr.ay))) / 9.81
    assert 0.88 < peak < 0.95
    m = measure(tr, P, SensorParams(), jax.random.key(0))
    assert m.time.shape == (351,) and m.wheel_speed.shape == (351, 4)
    np.testing.assert_allclose(m.vx_ref, tr.state.vx[::10], atol=0.3)  # front-wheel reference, noisy wheels


# name: (peak |a_y| / g, peak |beta| in deg), measured with the default vehicle (the numbers of docs/theory/vehicle.md)
PEAKS = {
    "straight": (0.0, 0.0),
    "sine_steer": (0.582, 0.85),
    "step_steer_200kmh": (0.433, 1.17),
    "double_lane_change_120kmh": (0.915, 3.86),
    "circle_40m_ramp": (0.861, 2.17),
    "ice_lake_circles": (0.246, 49.5),
    "mountain_road": (0.376, 1.69),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(MANOEUVRES))
def test_full_manoeuvre_peaks(name):
    tr = jax.jit(lambda p: simulate(name, p))(P)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree_util.tree_leaves(tr))
    ay, beta = PEAKS[name]
    np.testing.assert_allclose(float(jnp.max(jnp.abs(tr.ay))) / 9.81, ay, atol=0.005)
    np.testing.assert_allclose(float(jnp.max(jnp.abs(tr.beta))) * DEG, beta, atol=0.05)
    if name == "circle_40m_ramp":  # understeer limit: the tracked radius grows beyond 40 m
        assert float(tr.state.vx[-1] / tr.state.r[-1]) > 43.0
    if name == "mountain_road":
        assert float(jnp.max(jnp.abs(tr.inputs.bank))) * DEG > 3.9
        assert float(jnp.max(jnp.abs(tr.inputs.inclination))) * DEG > 5.9
