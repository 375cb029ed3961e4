"""Registry entries: the MuJoCo MJX plants (jaxobs.mjx).

The physics entries (rollouts, steps, sensor readings, model edits on an ``mjx.Model``) are still pending: each
needs a loaded model and compiles a physics step, which belongs in the slow suite (PENDING below)."""

import functools

import numpy as np

from tests.api_registry import Example
from tests.api_registry.observers import _kalman

JOINTS = """<mujoco><worldbody><body><freejoint/><geom size=".1"/>
 <body pos="0 0 .3"><joint type="ball"/><geom size=".1"/>
  <body pos="0 0 .3"><joint type="hinge"/><joint type="slide"/><geom size=".1"/></body></body></body>
</worldbody></mujoco>"""
"""A body tree with a free, a ball, a hinge and a slide joint: nq = 7 + 4 + 2 = 13, nv = 6 + 3 + 2 = 11."""


@functools.cache
def _joints():
    import mujoco

    return mujoco.MjModel.from_xml_string(JOINTS)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


QA, QB = _unit([0.9, 0.1, -0.3, 0.2]), _unit([0.8, -0.2, 0.1, 0.4])
QPOS = np.concatenate([[0.1, -0.2, 0.3], QA, QB, [0.4, -0.5]])
QVEL = np.linspace(-0.5, 0.6, 11)
_BROADCASTS = "broadcasts over leading axes (documented): a batch is the documented use"

ENTRIES = {
    "jaxobs.mjx.manifold.quat_multiply": Example(lambda: dict(a=QA, b=QB), skip={"batch": _BROADCASTS}),
    "jaxobs.mjx.manifold.quat_difference": Example(lambda: dict(qa=QA, qb=QB), skip={"batch": _BROADCASTS}),
    "jaxobs.mjx.manifold.quat_integrate": Example(
        lambda: dict(q=QA, v=np.array([0.1, -0.2, 0.3])), diff="v", skip={"batch": _BROADCASTS}
    ),
    "jaxobs.mjx.manifold.integrate_pos": Example(lambda: dict(model=_joints(), qpos=QPOS, qvel=QVEL), diff="qvel"),
    "jaxobs.mjx.manifold.differentiate_pos": Example(
        lambda: dict(model=_joints(), qpos1=QPOS, qpos2=np.concatenate([[0.0, 0.1, 0.2], QB, QA, [0.3, 0.1]])),
        diff="qpos2",
    ),
    "jaxobs.mjx.common.dead_time_step": Example(
        lambda: dict(fifo=np.array([[0.1], [0.2]]), u_k=np.array([0.3]), d=2),
        diff="u_k",
        skip={"batch": "fifo and u_k take any trailing shape (a command vector or a batch of them)"},
    ),
    "jaxobs.mjx.compliant_6dof.stack_controllers": Example(
        lambda: dict(controllers=[_kalman()] * 6),
        tangent="scale",
        skip={"batch": "stacks per-DOF parameters of any shapes: their leading axes are carried"},
    ),
}

EXEMPT = {
    "jaxobs.mjx.robot.warn_outside_joint_ranges": "validator: warns about concrete joint positions outside their "
    "ranges",
    "jaxobs.mjx.estimation.check_rotations": "validator: refuses free or ball joints under RK4 (MJX's derivative)",
    "jaxobs.mjx.estimation.put": "loader: mjx.put_model, naming what MJX cannot simulate",
    "jaxobs.mjx.estimation.sensor_noise": "loader: reads the MJCF's noise attribute of the named sensors",
    "jaxobs.mjx.estimation.state_size": "static: the sizes nq + nv + na and 2 nv + na of a model",
    "jaxobs.mjx.manifold.sensor_ids": "static: the ids of named sensors of a model",
    "jaxobs.mjx.manifold.tangent_rows": "static: the sensordata rows and tangent sizes of named sensors",
    "jaxobs.mjx.manifold.tangent_names": "static: a name per tangent entry of a model's state",
    "jaxobs.mjx.manifold.sensor_units": "static: the SI unit per tangent entry of named sensors",
    "jaxobs.mjx.manifold.state_manifold": "loader: the Manifold of a model's state, from its joint layout",
    "jaxobs.mjx.manifold.sensor_manifold": "loader: the Manifold of named sensors' readings, from the model",
    "jaxobs.mjx.robot.steady_activation": "loader: the resting activations of an MJCF under a constant control "
    "(NumPy on the model's actuator settings)",
    "jaxobs.mjx.common.check_solver_iterations": "validator: refuses a solver iteration count that is not an int >= 1",
    "jaxobs.mjx.common.check_timing": "validator: refuses a dead time or substep count that is not a valid int",
    "jaxobs.mjx.common.is_int_at_least": "validator: whether a static setting is an integer of at least a minimum",
    "jaxobs.mjx.compliant_6dof.check_per_dof": "validator: refuses a per-DOF setting of the wrong shape or value",
    "jaxobs.mjx.common.input_series": "validator: an input series checked against its shape (zeros for None)",
    "jaxobs.mjx.common.put_model": "loader: mjx.put_model on this process's first device",
    "jaxobs.mjx.common.constraint_rows": "static: a count read from the shapes of an mjx.Data",
    "jaxobs.mjx.estimation.sample_period": "static: the model's time step times an integer",
    "jaxobs.mjx.compliant_6dof.load_model": "loader: reads the packaged MJCF",
    "jaxobs.mjx.force_1dof.load_model": "loader: reads the packaged (or a given) MJCF",
    "jaxobs.mjx.estimation.load_cartpole": "loader: reads the shipped cart-pole",
    "jaxobs.mjx.robot.load_mjcf": "loader: reads an MJCF file or text",
    "jaxobs.mjx.robot.make_robot": "loader: builds a Robot from an MJCF and actuator/sensor names",
    "jaxobs.mjx.robot.holding_ctrl": "loader: MuJoCo's inverse dynamics on an MJCF (concrete, eager)",
    "jaxobs.mjx.estimation.measurement": "transformation: returns the measurement function h of a model",
    "jaxobs.mjx.estimation.transition": "transformation: returns the transition function f of a model",
}

_PHYSICS = "pending: needs a loaded MJX model and compiles a physics step (a slow-suite entry, not yet written)"

PENDING = {
    key: _PHYSICS
    for key in (
        "jaxobs.mjx.common.forward",
        "jaxobs.mjx.common.initial_data",
        "jaxobs.mjx.common.solve",
        "jaxobs.mjx.common.step",
        "jaxobs.mjx.compliant_6dof.closed_loop_rollout",
        "jaxobs.mjx.compliant_6dof.contact_point",
        "jaxobs.mjx.compliant_6dof.coupling_force",
        "jaxobs.mjx.compliant_6dof.rollout",
        "jaxobs.mjx.compliant_6dof.sensor_wrench",
        "jaxobs.mjx.compliant_6dof.with_params",
        "jaxobs.mjx.estimation.filter_model",
        "jaxobs.mjx.estimation.state",
        "jaxobs.mjx.force_1dof.closed_loop_rollout",
        "jaxobs.mjx.force_1dof.rollout",
        "jaxobs.mjx.force_1dof.sensor_force",
        "jaxobs.mjx.force_1dof.with_params",
        "jaxobs.mjx.robot.linearize",
        "jaxobs.mjx.robot.mismatch",
        "jaxobs.mjx.robot.rollout",
    )
}
