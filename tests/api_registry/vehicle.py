"""Registry entries: the vehicle simulator and its observers (jaxobs.vehicle).

Entries: the elementwise tyre curves, the friction switch's gates, the low-pass, the road-angle lemmas' bounds and
error systems, the model's static relations. Pending (PENDING below): the rest of the package (the observers, the
simulator, the model's dynamics), whose examples need a vehicle state and measurements of a simulated drive."""

import numpy as np

from tests.api_registry import Example

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
        skip={"batch": "a batch of vehicles is a vmap (parameters are pytrees of scalars)"},
    ),
    "jaxobs.vehicle.model.reference_yaw_rate": Example(
        lambda: dict(vehicle=_vehicle(), vx=np.float64(20.0), steering_wheel=np.float64(0.5)),
        diff="vx",
        skip={"batch": "a batch of vehicles is a vmap"},
    ),
    "jaxobs.vehicle.model.normal_loads": Example(
        lambda: dict(p=_vehicle(), ax=np.float64(1.0), ay=np.float64(3.0)),
        diff="ay",
        skip={"batch": "a batch of vehicles is a vmap"},
    ),
    "jaxobs.vehicle.model.wheel_kinematics": Example(
        lambda: dict(
            p=_vehicle(), vx=np.float64(20.0), vy=np.float64(0.3), r=np.float64(0.1), steering_wheel=np.float64(0.5)
        ),
        diff="vy",
        skip={"batch": "a batch of vehicles is a vmap"},
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


def _lateral():
    from jaxobs.vehicle.lateral import make_adaptive_lateral

    return make_adaptive_lateral()


EXEMPT = {}

_VEHICLE = "pending: not audited yet (needs a vehicle, its state and measurements of a simulated drive)"

PENDING = {
    key: _VEHICLE
    for key in (
        "jaxobs.vehicle.ekf.make_vehicle_ekf",
        "jaxobs.vehicle.ekf.vehicle_ekf",
        "jaxobs.vehicle.lateral.full_observer",
        "jaxobs.vehicle.lateral.lateral_observer",
        "jaxobs.vehicle.lateral.lemma_3_1_check",
        "jaxobs.vehicle.lateral.make_adaptive_lateral",
        "jaxobs.vehicle.lateral.vehicle_model",
        "jaxobs.vehicle.manoeuvres.manoeuvre",
        "jaxobs.vehicle.model.broadcast",
        "jaxobs.vehicle.model.check_vehicle",
        "jaxobs.vehicle.model.dynamics",
        "jaxobs.vehicle.model.forces",
        "jaxobs.vehicle.model.friction_model",
        "jaxobs.vehicle.model.lateral_acceleration",
        "jaxobs.vehicle.model.steady_state",
        "jaxobs.vehicle.nvso.make_nvso",
        "jaxobs.vehicle.nvso.nvso",
        "jaxobs.vehicle.road_angles.final_angles",
        "jaxobs.vehicle.road_angles.lemma_check",
        "jaxobs.vehicle.road_angles.make_road_angles",
        "jaxobs.vehicle.road_angles.road_angles",
        "jaxobs.vehicle.road_angles.road_angles_adaptive",
        "jaxobs.vehicle.sensors.measure",
        "jaxobs.vehicle.sensors.sensor_inputs",
        "jaxobs.vehicle.simulate.driver",
        "jaxobs.vehicle.simulate.esc_intervention",
        "jaxobs.vehicle.simulate.simulate",
        "jaxobs.vehicle.switching.make_switching",
        "jaxobs.vehicle.switching.switching",
    )
}
