"""MuJoCo MJX plants shipped with jaxobs (MJCF under ``jaxobs/mjx/assets``).

``force_1dof``: the 1-DOF robot force-control plant of seeds 000 §7, 001 §4 and 003 §7 (velocity-servo
robot, compliant force sensor of stiffness ``Ks``, command dead time as a FIFO in the rollout state).
``rollout`` runs it open loop; ``closed_loop_rollout`` runs it under an AOB / CKF (the observer protocol of
:mod:`jaxobs.observers`) as :func:`jaxobs.closed_loop.simulate` runs the analytic plant.

Importing this package imports ``mujoco.mjx``; ``import jaxobs`` does not import it.
"""

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
