"""Registry entries: the vehicle simulator and its observers (jaxobs.vehicle).

Pending (PENDING below): the vehicle package was not audited yet; its functions need a vehicle, a state and
measurements of a simulated drive as inputs."""

ENTRIES = {}

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
        "jaxobs.vehicle.lateral.lyapunov_3_1",
        "jaxobs.vehicle.lateral.make_adaptive_lateral",
        "jaxobs.vehicle.lateral.vehicle_model",
        "jaxobs.vehicle.manoeuvres.manoeuvre",
        "jaxobs.vehicle.model.broadcast",
        "jaxobs.vehicle.model.check_vehicle",
        "jaxobs.vehicle.model.dynamics",
        "jaxobs.vehicle.model.forces",
        "jaxobs.vehicle.model.friction_model",
        "jaxobs.vehicle.model.lateral_acceleration",
        "jaxobs.vehicle.model.normal_loads",
        "jaxobs.vehicle.model.reference_yaw_rate",
        "jaxobs.vehicle.model.steady_state",
        "jaxobs.vehicle.model.understeer_gradient",
        "jaxobs.vehicle.model.wheel_kinematics",
        "jaxobs.vehicle.nvso.make_nvso",
        "jaxobs.vehicle.nvso.nvso",
        "jaxobs.vehicle.road_angles.bank_error_system",
        "jaxobs.vehicle.road_angles.bank_gain_bound",
        "jaxobs.vehicle.road_angles.final_angles",
        "jaxobs.vehicle.road_angles.inclination_error_system",
        "jaxobs.vehicle.road_angles.inclination_gain_bound",
        "jaxobs.vehicle.road_angles.lemma_check",
        "jaxobs.vehicle.road_angles.make_road_angles",
        "jaxobs.vehicle.road_angles.road_angles",
        "jaxobs.vehicle.road_angles.road_angles_adaptive",
        "jaxobs.vehicle.sensors.low_pass",
        "jaxobs.vehicle.sensors.measure",
        "jaxobs.vehicle.sensors.sensor_inputs",
        "jaxobs.vehicle.simulate.driver",
        "jaxobs.vehicle.simulate.esc_intervention",
        "jaxobs.vehicle.simulate.simulate",
        "jaxobs.vehicle.switching.either",
        "jaxobs.vehicle.switching.gate",
        "jaxobs.vehicle.switching.make_switching",
        "jaxobs.vehicle.switching.switching",
        "jaxobs.vehicle.tyres.pure_force",
        "jaxobs.vehicle.tyres.tyre_forces",
    )
}
