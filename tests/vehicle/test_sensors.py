"""ESC sensors of jaxobs.vehicle: exact without errors, bias, random-walk drift statistics, the 15 Hz low-pass,
the reference velocity, the rate check, batching over keys."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.vehicle import GRAVITY, Inputs, SensorParams, Trajectory, VehicleParams, VehicleState, measure

P = VehicleParams()
EXACT = SensorParams(noise_acc=0.0, noise_yaw_rate=0.0, noise_steering=0.0, noise_wheel=0.0, cutoff=jnp.inf)


def _drive(T=2001, dt=1e-3):
    """A synthetic straight-ahead drive with varying signals and free-rolling wheels (vx_ref exact)."""
    t = dt * jnp.arange(T)
    vx = 20.0 + jnp.sin(t)
    zeros = jnp.zeros(T)
    state = VehicleState(
        vx, zeros, 0.1 * jnp.sin(3 * t), jnp.tile((vx / P.wheel_radius)[:, None], 4), jnp.zeros((T, 4)), zeros, zeros
    )
    inputs = Inputs(zeros, jnp.zeros((T, 4)), zeros, zeros, jnp.ones(T))
    return Trajectory(t, state, inputs, jnp.cos(t), 2.0 * jnp.sin(2 * t), zeros, jnp.zeros((T, 4)), zeros)


def test_error_free_sensors_sample_the_truth():
    tr = _drive()
    m = measure(tr, P, EXACT, jax.random.key(0))
    assert m.time.shape == (201,)
    np.testing.assert_allclose(m.time, tr.time[::10])
    np.testing.assert_allclose(m.ax, tr.ax[::10], atol=1e-12)
    np.testing.assert_allclose(m.ay, (1 + P.roll_gradient * GRAVITY) * tr.ay[::10], atol=1e-12)
    np.testing.assert_allclose(m.yaw_rate, tr.state.r[::10], atol=1e-12)
    np.testing.assert_allclose(m.wheel_speed, tr.state.omega[::10], atol=1e-12)
    # the front wheels see vx -+ r t_f / 2; straight wheels rolling at vx: vx_ref = vx + r * 0 on average
    np.testing.assert_allclose(m.vx_ref, tr.state.vx[::10], atol=1e-12)


def test_bias_and_drift_statistics():
    """A bias shifts the samples; the drift's spread after t seconds is drift sqrt(t) (64 keys, chi-square 99.9 %)."""
    tr = _drive()
    s = SensorParams(bias_ay=0.4, drift_yaw_rate=0.01, noise_acc=0.0, noise_yaw_rate=0.0, cutoff=jnp.inf)
    keys = jax.random.split(jax.random.key(1), 64)
    m = jax.jit(jax.vmap(lambda k: measure(tr, P, s, k)))(keys)
    np.testing.assert_allclose(m.ay - (1 + P.roll_gradient * GRAVITY) * tr.ay[::10], 0.4, atol=1e-12)
    drift = m.yaw_rate[:, -1] - tr.state.r[-1]
    var = float(jnp.mean(drift**2))
    expected = 0.01**2 * float(tr.time[-1])
    assert 0.58 < var / expected < 1.57  # chi-square(64)/64 at 0.1 % and 99.9 %


def test_low_pass_step_response_is_first_order_at_15_hz():
    T = 501
    tr = _drive(T)
    tr = tr._replace(ax=jnp.where(jnp.arange(T) >= 100, 1.0, 0.0))
    m = measure(tr, P, SensorParams(noise_acc=0.0), jax.random.key(2))
    k = jnp.arange(m.time.shape[0]) - 10
    expected = jnp.where(k >= 0, 1.0 - jnp.exp(-2 * jnp.pi * 15.0 * 0.01 * (k + 1)), 0.0)
    np.testing.assert_allclose(m.ax, expected, atol=1e-12)


@pytest.mark.parametrize("rate", [30.0, 2000.0, 0.0])
def test_sensor_rate_must_divide_into_plant_steps(rate):
    with pytest.raises(ValueError, match="rate"):
        measure(_drive(101), P, SensorParams(), jax.random.key(0), rate=rate)


def test_bad_sensor_parameters_raise():
    with pytest.raises(ValueError, match="noise_acc"):
        measure(_drive(101), P, SensorParams(noise_acc=-1.0), jax.random.key(0))
    with pytest.raises(ValueError, match="cutoff"):
        measure(_drive(101), P, SensorParams(cutoff=0.0), jax.random.key(0))
