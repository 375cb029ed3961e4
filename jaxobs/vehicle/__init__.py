"""A planar vehicle simulator for the sideslip observers of Grip 2010 (ch. 2-4): tyres, a two-track model,
ESC-type sensors and manoeuvres modelled on the thesis's test drives.

``tyres``: Magic Formula and Burckhardt tyre curves with combined slip in the friction ellipse.
``model``: the planar two-track model (:class:`VehicleParams`, :func:`dynamics`, the friction model's
:func:`lateral_acceleration`).
``sensors``: ESC-type measurements at 100 Hz with bias, drift, noise and the 15 Hz low-pass (:func:`measure`), and
the sensor vector the observers take (:data:`N_SENSORS`, :func:`sensor_inputs`).
``manoeuvres``: the named test drives modelled on Grip 2010 §2.10 (:data:`MANOEUVRES`, :func:`manoeuvre`).
``simulate``: a driver that follows a :class:`Command` and :func:`simulate` (RK4 at 1 ms in one ``lax.scan``).
``switching``: the friction-estimation switch of Grip 2010 §2.5 that the NVSO and its EKF baseline share
(:func:`make_switching`).
``nvso``: the nonlinear vehicle sideslip observer of Grip 2010 ch. 2 (:func:`make_nvso`, :data:`nvso`).
``ekf``: its EKF baseline of Grip 2010 §2.9 (:func:`make_vehicle_ekf`, :data:`vehicle_ekf`).
``lateral``: the friction-adaptive observers (3.4) and (3.14) of Grip 2010 ch. 3 (:func:`make_adaptive_lateral`,
:data:`lateral_observer`, :data:`full_observer`, :func:`lyapunov_3_1`, :func:`lemma_3_1_check`).
``road_angles``: the inclination and bank estimators of Grip 2010 ch. 4 (:func:`make_road_angles`,
:data:`road_angles`, :data:`road_angles_adaptive`) and the gain bounds of its Lemmas 4.1-4.2 (:func:`lemma_check`).

Every parameter set is a registered dataclass pytree, so a batch of vehicles is a dataclass of arrays under
``vmap``; everything is pure and works under ``jit``, ``vmap`` and ``grad``. ``import jaxobs`` does not import
this package.
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
