"""Registry entries: the vehicle simulator and its observers (jaxobs.vehicle).

Entries: the elementwise tyre curves, the friction switch's gates, the low-pass, the road-angle lemmas' bounds and
error systems, the model (state, forces, dynamics, friction model). Pending (PENDING below): the rest of the package
(the observers and their factories, the simulator with its driver and ESC, the friction switch), whose examples need
measurements of a drive or a manoeuvre."""

import numpy as np

from tests.api_registry import Design, Example, slow

ELEMENTWISE = "elementwise: any shapes that broadcast"
SLIPS = np.array([-0.05, 0.02, 0.1])
LOADS = np.array([3500.0, 4000.0, 4200.0])


def _vehicle():
    import jax

    from jaxobs.vehicle.model import VehicleParams

    return jax.tree_util.tree_map(np.float64, VehicleParams())  # arrays: the parameters are traced


def _tyre():
    from jaxobs.vehicle.tyres import TyreParams

    return TyreParams()


def _either(fn, a, b):
    return fn(a, b)


ENTRIES = {
    "jaxobs.vehicle.tyres.pure_force": Example(
        lambda: dict(tyre=_tyre(), slip=SLIPS, fz=LOADS),
        diff="slip",
        batched=("slip", "fz"),
        skip={"batch": ELEMENTWISE},
    ),
    "jaxobs.vehicle.tyres.tyre_forces": Example(
        lambda: dict(tyre=_tyre(), kappa=np.array([0.01, -0.03, 0.05]), tan_alpha=SLIPS, fz=LOADS),
        diff="tan_alpha",
        skip={"batch": ELEMENTWISE},
    ),
    "jaxobs.vehicle.switching.gate": Example(
        lambda: dict(smooth=5.0, x=np.array([0.2, 1.4]), threshold=np.float64(1.0), scale=np.float64(0.5)),
        diff="x",
        skip={"batch": ELEMENTWISE},
    ),
    "jaxobs.vehicle.switching.either": Example(
        lambda: dict(a=np.array([0.2, 0.9]), b=np.array([0.5, 0.1])), call=_either, skip={"batch": ELEMENTWISE}
    ),
    "jaxobs.vehicle.sensors.low_pass": Example(
        lambda: dict(x=np.sin(np.arange(8.0)), cutoff=np.float64(2.0), period=np.float64(0.01)),
        skip={"batch": "x (K, ...): any trailing axes are filtered alike"},
    ),
    "jaxobs.vehicle.road_angles.inclination_gain_bound": Example(lambda: dict(a=np.float64(2.0))),
    "jaxobs.vehicle.road_angles.bank_gain_bound": Example(
        lambda: dict(K_vy=np.float64(1.5), delta_min=np.float64(3.0))
    ),
    "jaxobs.vehicle.road_angles.inclination_error_system": Example(
        lambda: dict(a=np.float64(2.0), K_theta_i=np.float64(0.1))
    ),
    "jaxobs.vehicle.road_angles.bank_error_system": Example(
        lambda: dict(K_vy=np.float64(1.5), delta_min=np.float64(3.0), K_theta_b=np.float64(0.2))
    ),
    "jaxobs.vehicle.model.understeer_gradient": Example(
        lambda: dict(vehicle=_vehicle()),
        tangent="scale",
    ),
    "jaxobs.vehicle.model.reference_yaw_rate": Example(
        lambda: dict(vehicle=_vehicle(), vx=np.float64(20.0), steering_wheel=np.float64(0.5)),
        diff="vx",
    ),
    "jaxobs.vehicle.model.normal_loads": Example(
        lambda: dict(p=_vehicle(), ax=np.float64(1.0), ay=np.float64(3.0)),
        diff="ay",
    ),
    "jaxobs.vehicle.model.wheel_kinematics": Example(
        lambda: dict(
            p=_vehicle(), vx=np.float64(20.0), vy=np.float64(0.3), r=np.float64(0.1), steering_wheel=np.float64(0.5)
        ),
        diff="vy",
    ),
    "jaxobs.vehicle.lateral.lyapunov_3_1": Example(
        lambda: dict(
            params=_lateral(),
            vy=np.float64(0.5),
            theta=np.float64(0.6),
            vy_hat=np.float64(0.3),
            theta_hat=np.float64(0.4),
        ),
        diff="vy_hat",
        batched=("vy", "vy_hat"),
        skip={"batch": ELEMENTWISE},
    ),
}


def _state():
    import jax

    from jaxobs.vehicle.model import steady_state

    return jax.tree_util.tree_map(np.asarray, steady_state(_vehicle(), 20.0, vy=0.3, r=0.1, steering_wheel=0.5))


def _inputs():
    from jaxobs.vehicle.model import Inputs

    return Inputs(np.float64(0.5), np.array([80.0, 80.0, 0.0, 0.0]), np.float64(0.01), np.float64(0.02),
                  np.float64(0.9))  # fmt: skip


MEASURED = dict(vx=np.float64(20.0), vy=np.float64(0.3), r=np.float64(0.1), steering_wheel=np.float64(0.5),
                omega=np.array([62.0, 63.0, 62.5, 62.8]), ax=np.float64(0.5), ay=np.float64(2.0))  # fmt: skip

MORE = {
    "jaxobs.vehicle.model.steady_state": Example(
        lambda: dict(
            p=_vehicle(),
            vx=np.float64(20.0),
            vy=np.float64(0.3),
            r=np.float64(0.1),
            steering_wheel=np.float64(0.5),
            ax=np.float64(0.5),
        ),
        diff="vy",
    ),  # fmt: skip
    "jaxobs.vehicle.model.forces": Example(lambda: dict(p=_vehicle(), x=_state(), u=_inputs()), diff="x"),
    "jaxobs.vehicle.model.dynamics": Example(lambda: dict(p=_vehicle(), x=_state(), u=_inputs()), diff="x"),
    "jaxobs.vehicle.model.friction_model": Example(lambda: dict(p=_vehicle(), **MEASURED), diff="vy"),
    "jaxobs.vehicle.model.lateral_acceleration": Example(lambda: dict(p=_vehicle(), **MEASURED), diff="vy"),
    "jaxobs.vehicle.model.broadcast": Example(
        lambda: dict(params=_vehicle(), n=3),
        tangent="scale",
        skip={"batch": "params is any pytree: its leaves get the leading axis"},
    ),  # fmt: skip
    "jaxobs.vehicle.switching.make_switching": Example(
        lambda: dict(vehicle=_vehicle()), tangent="scale", out=lambda params: params.vehicle
    ),  # the thresholds stay the Python numbers given: the vehicle is the traced part
    "jaxobs.vehicle.road_angles.lemma_check": Design(lambda: dict(lemma="4.1", a=np.float64(0.5)), traced="a"),
}


def _measurements():
    from jaxobs.vehicle.sensors import Measurements

    k = np.arange(5.0)
    return Measurements(0.01 * k, 0.1 * np.sin(k), 2.0 + 0.1 * k, 0.1 + 0.01 * k, 0.5 * np.cos(k),
                        62.0 + np.outer(k, [0.1, 0.2, 0.3, 0.4]), 20.0 + 0.1 * k, np.zeros(5))  # fmt: skip


def _command():
    from jaxobs.vehicle.manoeuvres import Command

    return Command(*(np.float64(v) for v in (0.4, 0.01, 0.5, 21.0, 0.2, 0.0, 0.01, 1.0)))


def _esc():
    from jaxobs.vehicle.simulate import ESCParams

    return ESCParams()


MORE_2 = {
    "jaxobs.vehicle.sensors.sensor_inputs": Example(lambda: dict(measurements=_measurements())),
    "jaxobs.vehicle.simulate.esc_intervention": Example(
        lambda: dict(p=_vehicle(), esc=_esc(), x=_state(), steering_wheel=np.float64(2.0), friction=np.float64(0.8)),
        diff="x",
    ),  # fmt: skip
    "jaxobs.vehicle.nvso.make_nvso": Example(
        lambda: dict(vehicle=_vehicle()), tangent="scale", out=lambda params: params.vehicle
    ),  # fmt: skip
    "jaxobs.vehicle.road_angles.make_road_angles": Example(
        lambda: dict(vehicle=_vehicle()), tangent="scale", out=lambda params: params.vehicle
    ),  # fmt: skip
}

VEHICLE_EXEMPT = {
    "jaxobs.vehicle.model.check_vehicle": "validator: refuses a vehicle that is not a valid VehicleParams",
    "jaxobs.vehicle.manoeuvres.manoeuvre": "loader: a test drive by its name",
    "jaxobs.vehicle.lateral.vehicle_model": "transformation: returns the nominal friction model of a vehicle",
    "jaxobs.vehicle.lateral.lemma_3_1_check": "static: a run of Lemma 3.1's plant from Python settings only",
}


def _lateral():
    from jaxobs.vehicle.lateral import make_adaptive_lateral

    return make_adaptive_lateral()


EXEMPT = VEHICLE_EXEMPT


def _slipping_state():
    """A turning, accelerating state whose rear (driven) wheels slip by 2 % and front wheels by -1 %: inside the
    driver's traction limiter, away from its kink at zero slip (a free-rolling wheel under a driving torque, where
    the limiter's one-sided derivatives differ)."""
    from jaxobs.vehicle.model import wheel_kinematics

    x, p = _state(), _vehicle()
    v_l = np.asarray(wheel_kinematics(p, x.vx, x.vy, x.r, np.float64(0.5))[0])
    return x._replace(omega=v_l * np.array([0.99, 0.99, 1.02, 1.02]) / p.wheel_radius)


def _run(estimator, params, inputs):
    from jaxobs.observers.base import run

    return run(estimator, params, inputs)


def _drive_inputs():
    import jax

    from jaxobs.vehicle.sensors import sensor_inputs

    return jax.tree_util.tree_map(np.asarray, sensor_inputs(_measurements()))


def _observer(make, diff="inputs", **options):
    """The entry of a vehicle observer: ``run`` over the five samples of :func:`_measurements`. Central differences
    with a step of 1e-6: at 1e-5 the high-gain observers' curvature costs 2e-6 of the derivative (the NVSO, the
    lateral observers) and the EKF's minus side crosses a switch (one-sided differences 4110 and 6583 at 1e-5, both
    4110.35 at 1e-6, as reverse mode)."""
    build = lambda: dict(params=make(), inputs=_drive_inputs())
    tangent = "scale" if diff == "params" else "random"
    return Example(build, diff=diff, tangent=tangent, call=_run, fd_step=1e-6, **options)


def _ekf():
    from jaxobs.vehicle.ekf import make_vehicle_ekf

    return make_vehicle_ekf(_vehicle())


def _nvso():
    from jaxobs.vehicle.nvso import make_nvso

    return make_nvso(_vehicle())


def _road_angles():
    from jaxobs.vehicle.road_angles import make_road_angles

    return make_road_angles(_vehicle())


def _road_outputs():
    from jaxobs.vehicle.road_angles import RoadAnglesOutputs

    k = np.arange(4.0)
    x = np.stack([20.0 + k, 0.1 * k, 0.01 * k, 0.02 * k, 0.8 + 0 * k], axis=1)
    return RoadAnglesOutputs(x, 0.01 * k, 0.02 * k, 0.005 * k, np.stack([0.1 * k, -0.2 * k], axis=1), 3.0 + k)


def _trajectory():
    """Twenty plant samples (two sensor samples at 100 Hz) of a car turning at a slowly changing yaw rate."""
    import jax

    from jaxobs.vehicle.model import Inputs
    from jaxobs.vehicle.simulate import Trajectory

    k = np.arange(20.0)
    state = jax.tree_util.tree_map(lambda a: np.stack([np.asarray(a)] * 20), _state())
    state = state._replace(r=0.1 + 0.002 * k)
    inputs = Inputs(0.5 + 0.01 * k, np.full((20, 4), 80.0), 0 * k, 0 * k, 1 + 0 * k)
    return Trajectory(1e-3 * k, state, inputs, 0.5 + 0 * k, 2.0 + 0.05 * k, 0.015 + 0 * k, np.full((20, 4), 4e3),
                      0 * k)  # fmt: skip


def _sensors():
    from jaxobs.vehicle.sensors import SensorParams

    return SensorParams(bias_ax=np.float64(0.1), noise_acc=np.float64(0.05), cutoff=np.float64(15.0))


def _switching():
    from jaxobs.vehicle.switching import make_switching

    return make_switching(_vehicle(), smooth=5.0)


_STEP = dict(off_timer=np.float64(0.3), low_pass=np.float64(0.1), vx=np.float64(20.0), r=np.float64(0.12),
             ay=np.float64(3.0), steering_wheel=np.float64(0.6), esc_active=np.float64(0.0))  # fmt: skip

OBSERVERS = {
    "jaxobs.vehicle.simulate.driver": Example(lambda: dict(p=_vehicle(), x=_slipping_state(), c=_command()), diff="x"),
    "jaxobs.vehicle.simulate.simulate": Example(
        lambda: dict(manoeuvre="sine_steer", params=_vehicle(), duration=0.005),
        diff="params",
        tangent="scale",
    ),
    "jaxobs.vehicle.sensors.measure": Example(
        lambda: dict(trajectory=_trajectory(), params=_vehicle(), sensors=_sensors(), key=_key(4)),
        diff="trajectory",
    ),
    "jaxobs.vehicle.switching.switching": Example(lambda: dict(params=_switching(), **_STEP), diff="vx"),
    "jaxobs.vehicle.road_angles.final_angles": Example(
        lambda: dict(outputs=_road_outputs(), inclination=0.01 * np.arange(4.0), bank=0.02 * np.arange(4.0)),
        diff="inclination",
        skip={"batch": "outputs is a record of K samples; inclination and bank (K,) are checked against it"},
    ),
    "jaxobs.vehicle.lateral.make_adaptive_lateral": Example(
        lambda: dict(vehicle=_vehicle()), tangent="scale", out=lambda params: (params.mass, params.K_vy)
    ),
    "jaxobs.vehicle.ekf.make_vehicle_ekf": Example(
        lambda: dict(vehicle=_vehicle(), r_std=np.array([0.3, 0.3, 0.3, 0.1]), P0_diag=np.linspace(1e-3, 0.1, 8)),
        diff="r_std",
        out=lambda params: (params.ekf.model.R, params.ekf.model.P0),
    ),
    "jaxobs.vehicle.ekf.vehicle_ekf": _observer(_ekf),
    "jaxobs.vehicle.lateral.lateral_observer": _observer(_lateral),
    "jaxobs.vehicle.lateral.full_observer": _observer(_lateral),
    "jaxobs.vehicle.nvso.nvso": _observer(_nvso),
    "jaxobs.vehicle.road_angles.road_angles": _observer(_road_angles),
    "jaxobs.vehicle.road_angles.road_angles_adaptive": _observer(_road_angles),
}


def _key(seed: int):
    import jax

    return jax.random.key(seed)


_SLOW_VEHICLE = tuple(
    f"jaxobs.vehicle.{name}"
    for name in ("simulate.simulate", "sensors.measure", "ekf.vehicle_ekf", "ekf.make_vehicle_ekf",
                 "lateral.lateral_observer", "lateral.full_observer", "nvso.nvso", "road_angles.road_angles",
                 "road_angles.road_angles_adaptive", "simulate.driver", "switching.switching")
)  # fmt: skip

ENTRIES = slow(
    {**ENTRIES, **MORE, **MORE_2, **OBSERVERS},
    "a scan over a record or a drive (the observers, the simulator, the sensors) or the whole driver or switch, "
    "compiled for each promise",
    *_SLOW_VEHICLE,
)
