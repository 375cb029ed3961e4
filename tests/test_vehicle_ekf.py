"""The EKF baseline of jaxobs.vehicle.ekf (Grip 2010 §2.9) against the simulator: the sideslip error on the double
lane change with known friction and exact sensors, Bierman's update equal to Joseph's, missing sensor samples, bad
settings."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.observers.base import EstimatorInputs, run
from jaxobs.vehicle import SensorParams, VehicleParams, measure, sensor_inputs, simulate
from jaxobs.vehicle.ekf import make_vehicle_ekf, vehicle_ekf

P = VehicleParams()
EXACT_SENSORS = SensorParams(noise_acc=0.0, noise_yaw_rate=0.0, noise_steering=0.0, noise_wheel=0.0)
_run = jax.jit(lambda params, inputs: run(vehicle_ekf, params, inputs))


@pytest.fixture(scope="module")
def lane_change():
    """The 120 km/h double lane change on a 0.5 deg bank, friction 1, sensors without errors (15 Hz low-pass kept):
    ``(measurements, true sideslip at the samples)``."""
    tr = jax.jit(lambda: simulate("double_lane_change_120kmh", P))()
    return measure(tr, P, EXACT_SENSORS, jax.random.PRNGKey(0)), tr.beta[::10]


def test_sideslip_error_on_the_double_lane_change_and_bierman_equals_joseph(lane_change):
    """Peak sideslip 3.9 deg at 0.92 g: the EKF's sideslip error stays below 0.45 deg (measured 0.34 deg max, 0.15
    rms), the friction estimate within [0.9, 1.05] of the true 1 (measured 0.93 at its lowest), the bank within
    0.15 deg of 0.5 deg at the end (measured 0.46); fast friction estimation (the NVSO's switching rule) is on for
    part of the drive; Bierman's U-D update gives the same estimates to 1e-9."""
    meas, beta = lane_change
    inputs = sensor_inputs(meas)
    vx0 = float(meas.vx_ref[0])
    _, joseph = _run(make_vehicle_ekf(P, vx0=vx0), inputs)
    _, bierman = _run(make_vehicle_ekf(P, vx0=vx0, bierman=True), inputs)
    error = np.rad2deg(np.asarray(joseph.beta - beta))
    assert np.abs(error).max() < 0.45
    assert 0.9 <= float(joseph.x[:, 4].min()) and float(joseph.x[:, 4].max()) <= 1.05
    assert abs(np.rad2deg(float(joseph.x[-1, 3])) - 0.5) < 0.15
    assert 0.1 < float(joseph.mode.mean()) < 0.95
    np.testing.assert_allclose(bierman.x, joseph.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(bierman.P, joseph.P, rtol=0, atol=1e-9)


def test_missing_sensor_samples_are_held_skipped_and_counted(lane_change):
    """NaN in 20 sensor entries (a_y, yaw rate, v_x,ref): the count is 20, the estimates stay finite and the
    sideslip error below 0.5 deg."""
    meas, beta = lane_change
    y = np.array(sensor_inputs(meas).y)
    rng = np.random.default_rng(1)
    y[rng.choice(np.arange(5, y.shape[0]), size=20, replace=False), rng.choice([1, 2, 8], size=20)] = np.nan
    state, out = _run(make_vehicle_ekf(P, vx0=float(meas.vx_ref[0])), EstimatorInputs(y=jnp.asarray(y)))
    assert int(state.missing) == 20
    assert bool(jnp.all(jnp.isfinite(out.x)))
    assert np.rad2deg(float(jnp.max(jnp.abs(out.beta - beta)))) < 0.5


def test_bad_settings_raise():
    """Friction bounds with lo >= hi, wrong sizes, non-positive noise and a wrong vehicle raise ValueError naming
    the argument."""
    with pytest.raises(ValueError, match="mu_bounds must have lo < hi"):
        make_vehicle_ekf(mu_bounds=(1.0, 1.0))
    with pytest.raises(ValueError, match="r_std"):
        make_vehicle_ekf(r_std=(0.3, 0.3, 0.3))
    with pytest.raises(ValueError, match="q_v"):
        make_vehicle_ekf(q_v=0.0)
    with pytest.raises(ValueError, match="vehicle must be a VehicleParams"):
        make_vehicle_ekf("car")
    with pytest.raises(ValueError, match="switching must be NVSOParams"):
        make_vehicle_ekf(switching={"off_delay": 0.5})
    with pytest.raises(ValueError, match="bierman must be a bool"):
        make_vehicle_ekf(bierman=1)
