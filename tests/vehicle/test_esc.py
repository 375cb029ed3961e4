"""The simulated ESC of jaxobs.vehicle.simulate and the switching condition (iii) of Grip 2010 §2.5 it feeds: which
wheel it brakes, that it keeps a car on low friction from spinning, its status in the sensor vector, the NVSO and the
EKF switching on from it, and its input checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.observers.base import EstimatorInputs, run
from jaxobs.vehicle import (
    N_SENSORS,
    ESCParams,
    Manoeuvre,
    VehicleParams,
    esc_intervention,
    make_nvso,
    make_switching,
    make_vehicle_ekf,
    manoeuvre,
    measure,
    nvso,
    reference_yaw_rate,
    sensor_inputs,
    simulate,
    steady_state,
    vehicle_ekf,
)
from jaxobs.vehicle.sensors import ESC_ACTIVE, VX_REF, WHEEL_SPEED, SensorParams
from jaxobs.vehicle.switching import switching

P = VehicleParams()
ESC = ESCParams()
DEG = np.pi / 180


@pytest.mark.parametrize(
    ("sign", "offset", "wheel"),
    [(1, 0.2, 1), (1, -0.2, 2), (-1, 0.2, 0), (-1, -0.2, 3)],
    ids=["left-oversteer-FR", "left-understeer-RL", "right-oversteer-FL", "right-understeer-RR"],
)
def test_esc_brakes_the_outer_front_wheel_in_oversteer_and_the_inner_rear_in_understeer(sign, offset, wheel):
    """At 20 m/s on a dry road with a steering wheel whose reference yaw rate is 0.3 rad/s (turning left, sign 1, or
    right), a yaw rate 0.2 rad/s beyond it (oversteer) or short of it (understeer) brakes exactly one wheel: the outer
    front or the inner rear; the torque is ``gain (|e| - threshold) R / (track / 2)`` below the cap."""
    vx = 20.0
    steering = sign * 0.3 / float(reference_yaw_rate(P, vx, 1.0))
    r = sign * (0.3 + offset)
    brake, active = esc_intervention(P, ESC, steady_state(P, vx, r=r), steering, 1.0)
    assert float(active) == 1.0
    expected = np.zeros(4)
    track = P.track_front if offset > 0 else P.track_rear
    torque = ESC.gain * (0.2 - ESC.yaw_rate_threshold) * P.wheel_radius / (track / 2)
    expected[wheel] = -min(torque, ESC.max_brake_torque)
    np.testing.assert_allclose(brake, expected, rtol=1e-12)


def test_esc_stays_off_inside_its_dead_band_and_below_the_friction_limit():
    """No intervention within the dead band of the reference, nor for a yaw rate at the friction limit
    ``mu g / v_x`` while the linear reference asks for more (the ESC's reference is held at the limit)."""
    vx = 20.0
    per_rad = float(reference_yaw_rate(P, vx, 1.0))
    # linear references 0.3 rad/s (under the dry road's limit of 0.49) and 0.5 rad/s (over friction 0.3's 0.147)
    for r, reference, friction in ((0.3 + 0.9 * ESC.yaw_rate_threshold, 0.3, 1.0), (0.3 * 9.81 / vx, 0.5, 0.3)):
        brake, active = esc_intervention(P, ESC, steady_state(P, vx, r=r), reference / per_rad, friction)
        assert float(active) == 0.0
        np.testing.assert_array_equal(brake, np.zeros(4))


def _beyond_the_limit(duration=10.0):
    """The check sine on friction 0.3 at 1.5 times its amplitude: more steering than the road can give."""
    base = manoeuvre("sine_steer")

    def command(t):
        return base.command(t)._replace(steering_wheel=37.5 * DEG * jnp.sin(jnp.pi * t), friction=0.3)

    return Manoeuvre("sine_beyond_limit", command, duration, base.initial_speed)


def test_esc_keeps_the_car_from_spinning_on_low_friction_and_reports_its_status():
    """Beyond the limit on friction 0.3 the car without ESC spins (|beta| > 30 deg) and its status is 0 throughout;
    with the ESC the sideslip stays under 5 deg, the ESC intervenes part of the time and its status reaches the
    observers' sensor vector in column ESC_ACTIVE."""
    drive = _beyond_the_limit()
    free = simulate(drive, P)
    held = simulate(drive, P, esc=ESC)
    assert float(jnp.max(jnp.abs(free.beta))) > 30 * DEG
    np.testing.assert_array_equal(free.esc_active, 0.0)
    assert float(jnp.max(jnp.abs(held.beta))) < 5 * DEG
    assert 0.05 < float(jnp.mean(held.esc_active)) < 1.0
    y = sensor_inputs(measure(held, P, SensorParams(), jax.random.key(0))).y
    assert y.shape[1] == N_SENSORS
    np.testing.assert_array_equal(y[:, ESC_ACTIVE], held.esc_active[::10])


def test_esc_settings_batch_under_vmap_and_jit():
    """A vmap over two ESC gains under jit gives each gain's own drive."""
    drive = _beyond_the_limit(2.0)
    gains = jnp.array([1e4, 4e4])
    batched = jax.jit(jax.vmap(lambda g: simulate(drive, P, esc=ESC._replace(gain=g)).state.r))(gains)
    for i, gain in enumerate((1e4, 4e4)):
        np.testing.assert_allclose(batched[i], simulate(drive, P, esc=ESC._replace(gain=gain)).state.r, atol=1e-9)
    assert float(jnp.max(jnp.abs(batched[0] - batched[1]))) > 1e-3


@pytest.mark.parametrize(
    ("esc", "match"),
    [
        (ESCParams(gain=-1.0), "esc.gain"),
        (ESCParams(yaw_rate_threshold=0.0), "esc.yaw_rate_threshold"),
        (ESCParams(drive_cut=1.5), r"esc.drive_cut must be in \[0, 1\]"),
        ("on", "esc must be an ESCParams or None"),
    ],
)
def test_bad_esc_settings_raise(esc, match):
    with pytest.raises(ValueError, match=match):
        simulate("straight", P, duration=0.01, esc=esc)


@pytest.mark.parametrize("smooth", [None, 1e4])
def test_condition_iii_is_the_esc_but_not_for_steady_state_understeer(smooth):
    """Grip 2010 §2.5 (iii) alone (|r_ref| = 0.09 rad/s under the 0.1 of (i), no oversteer): at 30 m/s with
    ``r = 0.04``, understeer of 1.5 m/s^2; the switch is on with the ESC and lateral motion (a_y - r v_x = 2 m/s^2
    through the high-pass), off with the ESC in steady understeer (no lateral motion) and off without the ESC. A
    neutral car (r = r_ref) with the ESC: on. Exact and smooth gates agree."""
    params = make_switching(P, smooth=smooth)
    vx = 30.0
    steering = 0.09 / float(reference_yaw_rate(P, vx, 1.0))
    cases = [  # (r, lateral a_y beyond r v_x, ESC status, expected mode)
        (0.04, 2.0, 1.0, 1.0),
        (0.04, 0.0, 1.0, 0.0),
        (0.04, 2.0, 0.0, 0.0),
        (0.09, 0.0, 1.0, 1.0),
    ]
    for r, lateral, esc, expected in cases:
        result = switching(params, 1.0, 0.0, vx, r, r * vx + lateral, steering, esc)
        assert float(result.mode) == pytest.approx(expected, abs=1e-6), (r, lateral, esc)


def test_the_nvso_and_the_ekf_estimate_friction_while_the_esc_intervenes():
    """Straight ahead at 20 m/s (nothing excites (i) or (ii)): with the ESC status 1 both observers' friction
    estimation is on from the second sample, with 0 it stays off."""
    y = jnp.zeros((50, N_SENSORS)).at[:, WHEEL_SPEED].set(20.0 / P.wheel_radius).at[:, VX_REF].set(20.0)
    for status, expected in ((1.0, 1.0), (0.0, 0.0)):
        inputs = EstimatorInputs(y=y.at[:, ESC_ACTIVE].set(status))
        for estimator, params in ((nvso, make_nvso(P, vx0=20.0)), (vehicle_ekf, make_vehicle_ekf(P, vx0=20.0))):
            _, out = run(estimator, params, inputs)
            np.testing.assert_array_equal(np.asarray(out.mode)[2:], expected)


def test_esc_gain_gradient_matches_central_differences():
    """The gradient of a drive's summed squared sideslip with respect to the ESC's gain (2 s beyond the limit on
    friction 0.3) agrees with central differences to 1e-6 relative (measured 4e-8)."""
    drive = _beyond_the_limit(2.0)

    def cost(gain):
        return jnp.sum(simulate(drive, P, esc=ESC._replace(gain=gain)).beta ** 2)

    h = 1.0
    central = (cost(2e4 + h) - cost(2e4 - h)) / (2 * h)
    np.testing.assert_allclose(jax.grad(cost)(2e4), central, rtol=1e-6)
