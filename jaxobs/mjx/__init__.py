"""MuJoCo MJX plants shipped with jaxobs (MJCF under ``jaxobs/mjx/assets``).

``force_1dof``: the 1-DOF robot force-control plant of seeds 000 §7, 001 §4 and 003 §7 (velocity-servo
robot, compliant force sensor of stiffness ``Ks``, command dead time as a FIFO in the rollout state).

Importing this package imports ``mujoco.mjx``; ``import jaxobs`` does not import it.
"""

from jaxobs.mjx.force_1dof import (
    CONTROL_PERIOD,
    SUBSTEPS,
    ForcePlantParams,
    ForceRollout,
    load_model,
    rollout,
    with_params,
)

__all__ = [
    "CONTROL_PERIOD",
    "SUBSTEPS",
    "ForcePlantParams",
    "ForceRollout",
    "load_model",
    "rollout",
    "with_params",
]
