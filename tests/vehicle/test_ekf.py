"""The EKF baseline of jaxobs.vehicle.ekf (Grip 2010 §2.9) against the simulator: the sideslip error on the double
lane change with known friction and exact sensors, Bierman's update equal to Joseph's, the start of the 40 m circle
(the start-up transient that made the filter diverge), the attraction of the friction estimate to its default
without excitation, missing sensor samples, bad settings."""

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
_run_from = jax.jit(lambda params, inputs, state: run(vehicle_ekf, params, inputs, state))


@pytest.fixture(scope="module")
def lane_change():
    """The 120 km/h double lane change on a 0.5 deg bank, friction 1, sensors without errors (15 Hz low-pass kept):
    ``(measurements, true sideslip at the samples)``."""
    tr = jax.jit(lambda: simulate("double_lane_change_120kmh", P))()
    return measure(tr, P, EXACT_SENSORS, jax.random.PRNGKey(0)), tr.beta[::10]


def test_sideslip_error_on_the_double_lane_change_and_bierman_equals_joseph(lane_change):
    """Peak sideslip 3.9 deg at 0.92 g: the EKF's sideslip error stays below 0.45 deg (measured 0.34 deg max, 0.15
    rms), the friction estimate within [0.9, 1.05] of the true 1 (measured 0.98 at its lowest), the bank within
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


def test_start_of_the_40m_circle_holds_sideslip_and_friction():
    """The first 3 s of ``circle_40m_ramp`` (default sensor noise): the driver turns 18 deg of road-wheel angle at
    8 m/s from a straight run, a transient the EKF's friction model (no tyre relaxation) cannot explain. The
    friction estimate never falls below the friction the drive demonstrably uses (its peak |(a_x, a_y)| / g,
    0.52 at 0.05 s; measured lowest estimate 0.68), and from 0.5 s on the sideslip error stays within the 1 deg
    Grip 2010 §2.8 asks of an estimate for feedback control (measured 0.12 deg; the true sideslip peaks at
    2.2 deg). The former defaults (no innovation gate, prior variances 1, 1, ..., 0.05 on v_x, v_y, mu) fail both:
    friction 0.15 and a 3.1 deg error (the full drive then stayed at -20 to -31 deg of sideslip)."""
    tr = jax.jit(lambda: simulate("circle_40m_ramp", P, duration=3.0))()
    meas = measure(tr, P, SensorParams(), jax.random.PRNGKey(0))
    used = float(np.max(np.hypot(np.asarray(tr.ax), np.asarray(tr.ay)))) / 9.81
    state, out = _run(make_vehicle_ekf(P), sensor_inputs(meas))
    error = np.rad2deg(np.abs(np.asarray(out.beta) - np.asarray(tr.beta[::10])))
    assert used > 0.5
    assert float(out.x[:, 4].min()) >= used
    assert error[50:].max() < 1.0
    assert int(state.filter.gated) > 0  # the start-up samples the model cannot explain were rejected


def test_friction_is_drawn_to_its_default_without_excitation():
    """Straight ahead at 20 m/s (constant sensors, no lateral excitation: slow friction estimation throughout) from
    ``mu = 0.5``: the tyres are at zero slip, where the friction model's forces carry almost no information on
    ``mu``, so it follows the attraction, ``mu_k - 1 = (0.5 - 1) (1 - k_mu dt)^k`` (to 1e-5, measured 7e-7); with
    ``mu_attraction=0`` it stays at 0.5."""
    y = jnp.tile(jnp.array([0.0, 0.0, 0.0, 0.0, *[20.0 / P.wheel_radius] * 4, 20.0, 0.0]), (300, 1))
    for k_mu in (0.5, 0.0):
        params = make_vehicle_ekf(P, mu_attraction=k_mu)
        state = vehicle_ekf.init(params)
        state = state._replace(filter=state.filter._replace(x=state.filter.x.at[4].set(0.5)))
        _, out = _run_from(params, EstimatorInputs(y=y), state)
        assert float(jnp.max(out.mode)) == 0.0
        expected = 1.0 - 0.5 * (1.0 - k_mu * 0.01) ** np.arange(300)
        np.testing.assert_allclose(out.x[:, 4], expected, rtol=0, atol=1e-5)


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
    with pytest.raises(ValueError, match="switching must be SwitchingParams"):
        make_vehicle_ekf(switching={"off_delay": 0.5})
    with pytest.raises(ValueError, match="bierman must be a bool"):
        make_vehicle_ekf(bierman=1)
    with pytest.raises(ValueError, match="gate must be finite and positive"):
        make_vehicle_ekf(gate=-1.0)
    with pytest.raises(ValueError, match="mu_attraction must be finite and non-negative"):
        make_vehicle_ekf(mu_attraction=-0.5)
