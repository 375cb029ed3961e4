"""MuJoCo MJX plants shipped with jaxobs (MJCF under ``jaxobs/mjx/assets``).

``force_1dof``: the 1-DOF robot force-control plant of Cortesão 2006 §7 (``rollout``, ``closed_loop_rollout``).
``compliant_6dof``: the 6-DOF compliant-motion plant and peg-on-hole scenario of the MRAC chapter §7.
``estimation``: MJX models as the nonlinear models of the EKF and UKF; the shipped cart-pole with sensors.
``manifold``: the state ``(qpos, qvel, act)`` and the sensors' readings with errors in the tangent space.
``robot``: your own robot from any MJCF (``make_robot``, ``linearize``, ``mismatch``, ``rollout``).
``common``: the parts the plants share (device placement, initial data, the dead-time FIFO, input series).

Importing this package imports ``mujoco.mjx``; ``import jaxobs`` does not. The models and their
simplifications: docs/theory/mjx.md.
"""

import contextlib
import io
import re
import sys

# mujoco.mjx prints "Failed to import warp: No module named 'warp'" (and the same for mujoco_warp) on import when
# the optional package for its warp backend is absent; that reads as an error on every run that does not use the
# backend. Only those two lines are dropped: anything else it prints (a warp install that fails) still shows.
_WARP_ABSENT = re.compile(r"Failed to import (mujoco_)?warp: No module named '(mujoco_)?warp(\.[\w.]*)?'$")
with contextlib.redirect_stdout(io.StringIO()) as _printed:
    import mujoco.mjx  # noqa: F401
sys.stdout.write("".join(line + "\n" for line in _printed.getvalue().splitlines() if not _WARP_ABSENT.match(line)))

from jaxobs.mjx import common, compliant_6dof, estimation, manifold, robot  # noqa: E402 (after the quiet import)
from jaxobs.mjx.force_1dof import (  # noqa: E402
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
    "manifold",
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
