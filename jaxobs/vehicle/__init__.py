"""A planar vehicle simulator for the sideslip observers of Grip 2010 (ch. 2-4).

``tyres`` (Magic Formula and Burckhardt curves, combined slip), ``model`` (the two-track model, the friction
model), ``sensors`` (ESC-type measurements and the observers' sensor vector), ``manoeuvres`` (test drives modelled
on Grip 2010 §2.10), ``simulate`` (a driver and RK4 in one ``lax.scan``), ``switching`` (the friction-estimation
switch of §2.5); the observers ``nvso`` (Grip 2010 ch. 2), ``ekf`` (its EKF baseline, §2.9), ``lateral`` (the
friction-adaptive observers of ch. 3) and ``road_angles`` (inclination and bank, ch. 4).

Parameters are registered dataclass pytrees (a batch of vehicles is a ``vmap``); everything is pure under ``jit``,
``vmap`` and ``grad``. ``import jaxobs`` does not import this package. Design notes: docs/theory/vehicle.md.
"""

from jaxobs.vehicle.ekf import VehicleEKFOutputs, VehicleEKFParams, VehicleEKFState, make_vehicle_ekf, vehicle_ekf
from jaxobs.vehicle.lateral import (
    AdaptiveLateralOutputs,
    AdaptiveLateralParams,
    AdaptiveLateralState,
    Lemma31Check,
    full_observer,
    lateral_observer,
    lemma_3_1_check,
    lyapunov_3_1,
    make_adaptive_lateral,
    vehicle_model,
)
from jaxobs.vehicle.manoeuvres import MANOEUVRES, Command, Manoeuvre, manoeuvre
from jaxobs.vehicle.model import (
    GRAVITY,
    MIN_SPEED,
    Forces,
    Inputs,
    VehicleParams,
    VehicleState,
    broadcast,
    dynamics,
    forces,
    friction_model,
    lateral_acceleration,
    normal_loads,
    steady_state,
    wheel_kinematics,
)
from jaxobs.vehicle.nvso import NVSOOutputs, NVSOParams, NVSOState, make_nvso, nvso
from jaxobs.vehicle.road_angles import (
    FinalAngles,
    LemmaCheck,
    RoadAnglesOutputs,
    RoadAnglesParams,
    RoadAnglesState,
    bank_error_system,
    bank_gain_bound,
    final_angles,
    inclination_error_system,
    inclination_gain_bound,
    lemma_check,
    make_road_angles,
    road_angles,
    road_angles_adaptive,
)
from jaxobs.vehicle.sensors import N_SENSORS, SENSOR_RATE, Measurements, SensorParams, low_pass, measure, sensor_inputs
from jaxobs.vehicle.simulate import PLANT_STEP, Trajectory, driver, simulate
from jaxobs.vehicle.switching import SwitchingParams, make_switching
from jaxobs.vehicle.tyres import BURCKHARDT_SURFACES, BurckhardtTyre, TyreParams, pure_force, tyre_forces

__all__ = [
    "BURCKHARDT_SURFACES",
    "BurckhardtTyre",
    "TyreParams",
    "pure_force",
    "tyre_forces",
    "GRAVITY",
    "MIN_SPEED",
    "Forces",
    "Inputs",
    "VehicleParams",
    "VehicleState",
    "broadcast",
    "dynamics",
    "forces",
    "friction_model",
    "lateral_acceleration",
    "normal_loads",
    "steady_state",
    "wheel_kinematics",
    "PLANT_STEP",
    "Command",
    "Manoeuvre",
    "Trajectory",
    "driver",
    "simulate",
    "MANOEUVRES",
    "manoeuvre",
    "SENSOR_RATE",
    "Measurements",
    "SensorParams",
    "low_pass",
    "measure",
    "N_SENSORS",
    "NVSOOutputs",
    "NVSOParams",
    "NVSOState",
    "make_nvso",
    "nvso",
    "sensor_inputs",
    "SwitchingParams",
    "make_switching",
    "VehicleEKFOutputs",
    "VehicleEKFParams",
    "VehicleEKFState",
    "make_vehicle_ekf",
    "vehicle_ekf",
    "AdaptiveLateralParams",
    "AdaptiveLateralState",
    "AdaptiveLateralOutputs",
    "vehicle_model",
    "make_adaptive_lateral",
    "lateral_observer",
    "full_observer",
    "lyapunov_3_1",
    "Lemma31Check",
    "lemma_3_1_check",
    "RoadAnglesParams",
    "RoadAnglesState",
    "RoadAnglesOutputs",
    "make_road_angles",
    "road_angles",
    "road_angles_adaptive",
    "inclination_error_system",
    "bank_error_system",
    "inclination_gain_bound",
    "bank_gain_bound",
    "LemmaCheck",
    "lemma_check",
    "FinalAngles",
    "final_angles",
]
