"""The two-track model of jaxobs.vehicle: the steady-state circle against the linear single-track model, the
monotonicity of a_y in v_y (and where it fails), the standstill guard, batching, bad parameters."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.vehicle import (
    GRAVITY,
    MIN_SPEED,
    BurckhardtTyre,
    Command,
    Inputs,
    Manoeuvre,
    TyreParams,
    VehicleParams,
    broadcast,
    dynamics,
    lateral_acceleration,
    pure_force,
    simulate,
    steady_state,
    wheel_kinematics,
)

P = VehicleParams()


def test_steady_state_circle_equals_the_linear_single_track_gain_at_small_lateral_acceleration():
    """Constant steering at constant speed for 5 s. The yaw rate equals the single-track gain
    ``r / delta = v / (L + K v^2)``, ``K = (1/c_f - 1/c_r) / g`` (tyre stiffnesses proportional to the load), to
    5e-4 at a_y = 0.38 m/s^2 (measured 4.8e-4: drive slip and the finite track), and falls below it as the
    tyres leave their linear range (measured -2.8 % at 5.5 m/s^2)."""
    deltas = jnp.deg2rad(jnp.array([0.2, 3.0]))  # road-wheel angles

    def run(delta):
        command = lambda t: Command(steering_wheel=delta * P.steering_ratio, speed=20.0)
        tr = simulate(Manoeuvre("circle", command, 5.0, 20.0), P)
        return tr.state.r[-1], tr.state.vx[-1], tr.ay[-1], tr.state.r[-1] - tr.state.r[-500]

    r, vx, ay, settle = jax.jit(jax.vmap(run))(deltas)
    assert float(jnp.max(jnp.abs(settle / r))) < 2e-4  # settled: measured 2e-7 and 6e-5 change over the last 0.5 s
    K = (1 / P.tyre_front.cornering_stiffness - 1 / P.tyre_rear.cornering_stiffness) / GRAVITY
    linear = vx / (P.wheelbase + K * vx**2) * deltas
    error = r / linear - 1
    assert float(ay[0]) < 0.5 and abs(float(error[0])) < 5e-4
    assert float(ay[1]) > 5.0 and float(error[1]) < -0.02


def test_lateral_acceleration_decreases_in_vy_unless_all_four_tyres_are_past_their_peak():
    """Grip 2010 §2.2: a_y strictly decreasing in v_y, which fails when all tyres saturate. Over a grid of v_y
    at 20 m/s, yaw rate 0.2 rad/s, 2 deg road-wheel angle: d a_y / d v_y (autodiff) is below -0.2 s^-1
    wherever every tyre is below the slip of its peak force, and positive wherever every tyre is past it
    (|v_y| above about 4 m/s here: the observer's a_y then has no information on v_y)."""
    vx, r, sw = 20.0, 0.2, jnp.deg2rad(2.0) * P.steering_ratio
    v_l, _, _ = wheel_kinematics(P, vx, 0.0, r, sw)
    omega = v_l / P.wheel_radius
    vys = jnp.linspace(-15.0, 15.0, 301)
    slope = jax.jit(jax.vmap(jax.grad(lambda vy: lateral_acceleration(P, vx, vy, r, sw, omega, 0.0, 3.0))))(vys)

    def tan_alpha(vy):
        v_l, v_s, _ = wheel_kinematics(P, vx, vy, r, sw)
        return jnp.abs(v_s / jnp.maximum(jnp.abs(v_l), MIN_SPEED))

    s = jnp.linspace(0.0, 1.0, 100001)
    peak = jnp.array([s[jnp.argmax(pure_force(t, s, 4000.0))] for t in (P.tyre_front, P.tyre_rear)])
    slips = jax.vmap(tan_alpha)(vys)
    below = (slips <= jnp.repeat(peak, 2)).all(axis=1)
    above = (slips > jnp.repeat(peak, 2)).all(axis=1)
    assert below.sum() > 20 and above.sum() > 100
    assert float(slope[below].max()) < -0.2
    assert float(slope[above].min()) > 0.0


def test_burckhardt_tyres_on_the_vehicle_scale_exactly_with_road_friction():
    """Road friction scales c1 and c3, so every Burckhardt force, hence a_y, scales by it; a_y falls in v_y."""
    p = dataclasses.replace(P, tyre_front=BurckhardtTyre.surface("snow"), tyre_rear=BurckhardtTyre.surface("snow"))
    args = (15.0, 0.3, 0.1, 0.5, jnp.full(4, 15.0 / P.wheel_radius), 0.0, 1.0)
    full = lateral_acceleration(p, *args)
    np.testing.assert_allclose(lateral_acceleration(p, *args, friction=0.4), 0.4 * full, rtol=1e-12)
    slope = jax.grad(lambda vy: lateral_acceleration(p, 15.0, vy, *args[2:]))(0.0)
    assert np.isfinite(slope) and slope < 0


def test_standstill_is_guarded_under_jit_and_grad():
    """At rest (below MIN_SPEED) the derivatives and their gradients are finite."""
    x = steady_state(P, 0.0)
    u = Inputs(jnp.asarray(0.3), jnp.array([0.0, 0.0, 50.0, 50.0]))
    dx = jax.jit(lambda p: dynamics(p, x, u))(P)
    assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(dx))
    g = jax.grad(lambda m: dynamics(dataclasses.replace(P, mass=m), x, u).vx)(1600.0)
    assert np.isfinite(g)


def test_vehicle_parameters_batch_under_vmap():
    """A mass and friction sweep in one vmapped simulation equals the single runs."""
    masses, mus = jnp.array([1400.0, 1900.0]), jnp.array([1.0, 0.3])
    batch = broadcast(dataclasses.replace(P, mass=masses, tyre_front=dataclasses.replace(P.tyre_front, mu=mus)), 2)
    m = Manoeuvre("s", lambda t: Command(steering_wheel=0.5 * jnp.sin(4.0 * t), speed=15.0), 0.3, 15.0)
    run = jax.jit(lambda p: simulate(m, p).state.vy[-1])
    batched = jax.vmap(run)(batch)
    for i in range(2):
        single = dataclasses.replace(
            P, mass=float(masses[i]), tyre_front=TyreParams(mu=float(mus[i]), cornering_stiffness=15.0)
        )
        np.testing.assert_allclose(batched[i], run(single), rtol=1e-10)


@pytest.mark.slow  # ~12 s per mode: the vehicle observers' gradient tests run in the default set
@pytest.mark.parametrize("mode", [jax.jacfwd, jax.grad], ids=["fwd", "rev"])
def test_gradient_through_a_simulation_matches_central_differences(mode):
    """d v_y(0.2 s) / d mass and / d front cornering stiffness through the RK4 scan, forward and reverse mode,
    against central differences."""
    m = Manoeuvre("s", lambda t: Command(steering_wheel=0.5 * jnp.sin(4.0 * t), speed=15.0), 0.2, 15.0)

    def vy(z):
        tyre = dataclasses.replace(P.tyre_front, cornering_stiffness=z[1])
        return simulate(m, dataclasses.replace(P, mass=z[0], tyre_front=tyre)).state.vy[-1]

    z = jnp.array([1600.0, 15.0])
    grad = jax.jit(mode(vy))(z)
    f = jax.jit(vy)
    for i, h in enumerate((1.0, 0.01)):
        e = jnp.zeros(2).at[i].set(h)
        np.testing.assert_allclose(grad[i], (f(z + e) - f(z - e)) / (2 * h), rtol=1e-5)


@pytest.mark.parametrize(
    "field, value",
    [
        ("mass", 0.0),
        ("mass", -1.0),
        ("yaw_inertia", 0.0),
        ("lf", 0.0),
        ("lr", -1.0),
        ("wheel_radius", 0.0),
        ("steering_ratio", 0.0),
        ("roll_share_front", 1.5),
        ("mass", jnp.array([1500.0, -1.0])),
    ],
)
def test_bad_vehicle_parameters_raise(field, value):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(P, **{field: value}).validate()


@pytest.mark.parametrize("field, value", [("mu", 0.0), ("cornering_stiffness", -5.0)])
def test_bad_tyre_of_the_vehicle_raises_in_simulate(field, value):
    bad = dataclasses.replace(P, tyre_rear=dataclasses.replace(P.tyre_rear, **{field: value}))
    with pytest.raises(ValueError, match=field):
        simulate(Manoeuvre("s", lambda t: Command(), 0.01, 10.0), bad)
