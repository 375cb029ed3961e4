"""MuJoCo MJX plants shipped with jaxobs (MJCF under ``jaxobs/mjx/assets``).

``force_1dof``: the 1-DOF robot force-control plant of Cortesão 2006 §7, 001 §4 and 003 §7 (velocity-servo
robot, compliant force sensor of stiffness ``Ks``, command dead time as a FIFO in the rollout state).
``rollout`` runs it open loop; ``closed_loop_rollout`` runs it under an AOB / CKF (the observer protocol of
:mod:`jaxobs.observers`) as :func:`jaxobs.closed_loop.simulate` runs the analytic plant.

``compliant_6dof`` (a submodule, since its names mirror the 1-DOF ones): the 6-DOF compliant-motion
plant of the MRAC chapter §7 (Table 1 stiffnesses, per-DOF AOB-1 HBA / CKF SBA of eq. 62-68, the peg-on-hole
alignment scenario with its contact moment coupled to the alignment rotation).

``estimation`` (a submodule): state estimation on MJX models for the EKF and UKF of :mod:`jaxobs.observers`:
the state ``(qpos, qvel)``, the transition ``mjx.step``, the measurement ``sensordata``; the shipped cart-pole
with sensors (``examples/mjx_state_estimation.py``).

``robot`` (a submodule): your own robot from any MJCF: the actuators a controller drives, the sensors it
measures, the control period and dead time (``make_robot``), its linearisation by ``jax.jacfwd`` of ``mjx.step``
(``linearize``), named model mismatch such as ``body_mass[payload]`` (``mismatch``) and the closed loop of any
controller (``rollout``); ``jaxobs tune``'s ``own-robot`` problem tunes an observer on it.

``common`` (a submodule): the parts the plants share (device placement of a model, initial data, the dead-time
FIFO, per-step input series, timing checks).

Importing this package imports ``mujoco.mjx``; ``import jaxobs`` does not import it.
"""

from jaxobs.mjx import common, compliant_6dof, estimation, robot
from jaxobs.mjx.force_1dof import (
    CONTROL_PERIOD,
    SUBSTEPS,
    ClosedLoopRollout,
    ForcePlantParams,
    ForceRollout,
    closed_loop_rollout,
    load_model,
    rollout,
    sensor_force,
    with_params,
)

__all__ = [
    "common",
    "compliant_6dof",
    "estimation",
    "robot",
    "CONTROL_PERIOD",
    "SUBSTEPS",
    "ForcePlantParams",
    "ForceRollout",
    "ClosedLoopRollout",
    "closed_loop_rollout",
    "load_model",
    "rollout",
    "sensor_force",
    "with_params",
]
