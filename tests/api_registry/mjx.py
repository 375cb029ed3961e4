"""Registry entries: the MuJoCo MJX plants (jaxobs.mjx).

The physics entries (rollouts, steps, sensor readings, model edits) run in the slow suite: each compiles physics
steps of a loaded model. One model per module, loaded once: a one-joint pendulum pushed past its joint limit (so the
constraint solver has a row) for jaxobs.mjx.common, .estimation and .robot, the packaged plants for force_1dof and
compliant_6dof. The model is a constant of the call (``call=``), not a traced argument: an ``mjx.Model`` is MJX's
pytree, batched and cast as MJX allows; the traced arguments are the arrays the functions take beside it (a state
``qpos``, ``qvel`` written into the model's ``mjx.Data``, commands, parameters)."""

import functools

import numpy as np

from tests.api_registry import Example, slow
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


PENDULUM = """<mujoco><option timestep="0.01"/><worldbody><body>
 <joint name="swing" type="hinge" axis="0 1 0" limited="true" range="-0.5 0.5" damping="0.1"/>
 <geom type="capsule" size=".05" fromto="0 0 0 0 0 -.3" mass="1"/></body></worldbody>
<actuator><motor name="push" joint="swing"/></actuator><sensor><jointpos name="angle" joint="swing" noise="0.01"/>
</sensor></mujoco>"""
"""A pendulum of one hinge with a joint limit at 0.5 rad, a motor and an angle sensor (nq = nv = nu = 1)."""

OVER_LIMIT = dict(qpos=np.array([0.52]), qvel=np.array([0.3]))
"""Past the limit: the solver has one constraint row (a soft limit: smooth in the state)."""


@functools.cache
def _pendulum():
    import mujoco

    from jaxobs.mjx.common import put_model

    m = mujoco.MjModel.from_xml_string(PENDULUM)
    return m, put_model(m)


@functools.cache
def _force_plant():
    from jaxobs.mjx.force_1dof import load_model

    return load_model()[1]


@functools.cache
def _compliant():
    from jaxobs.mjx.compliant_6dof import load_model

    return load_model()[1]


@functools.cache
def _robot():
    from jaxobs.mjx.robot import make_robot

    return make_robot(PENDULUM, ["push"], ["angle"])  # hanging at rest: an equilibrium


def _data(model, qpos, qvel):
    import mujoco.mjx as mjx

    return mjx.make_data(model).replace(qpos=qpos, qvel=qvel)


def _on_state(model, prepare=None):
    """``call``: ``fn(model, data)`` with the traced ``qpos``, ``qvel`` written into the model's data (``prepare``:
    the stages run on it before, e.g. the constraint rows for :func:`jaxobs.mjx.common.solve`)."""

    def call(fn, qpos, qvel, **static):
        data = _data(model(), qpos, qvel)
        return fn(model(), prepare(model(), data) if prepare else data, **static)

    return call


def _on_model(model):
    """``call``: ``fn(model, **args)`` with the model a constant."""
    return lambda fn, **args: fn(model(), **args)


def _staged(model, data):
    """``data`` through the stages before the constraint solve (a batched state as it is: MJX's stages cannot take
    it, and the batch check is the solve's)."""
    from jaxobs.mjx.common import STAGES

    if np.ndim(data.qpos) > 1 or np.ndim(data.qvel) > 1:
        return data
    for _, stage in STAGES:
        data = stage(model, data)
    return data


def _controller():
    from jaxobs.observers.active import active_observer_controller

    return active_observer_controller


_MODEL_DTYPE = "the output has the model's precision (MJX computes in the mjx.Model's dtype: put it in float32)"
_IN_DATA = "its arrays live in an mjx.Data (qpos, qvel), not in lists"
_STATE = dict(skip={"float32": _MODEL_DTYPE, "lists": _IN_DATA})
_PEND = lambda: _pendulum()[1]  # noqa: E731


def _state_entry(model, out, prepare=None, **options):
    return Example(lambda: dict(OVER_LIMIT), diff="qvel", call=_on_state(model, prepare), out=out, **_STATE, **options)


PHYSICS = {
    "jaxobs.mjx.common.initial_data": Example(
        lambda: dict(model=_PEND(), dtype=np.float64),
        tangent="scale",
        out=lambda data: (data.qpos, data.qvel, data.ctrl),
        skip={"float32": "the dtype argument sets the state's dtype"},
    ),
    "jaxobs.mjx.common.forward": _state_entry(_PEND, lambda d: (d.qacc, d.qfrc_constraint, d.sensordata)),
    "jaxobs.mjx.common.step": _state_entry(_PEND, lambda d: (d.qpos, d.qvel)),
    "jaxobs.mjx.common.solve": _state_entry(_PEND, lambda d: (d.qacc, d._impl.efc_force), prepare=_staged),
    "jaxobs.mjx.estimation.state": Example(
        lambda: dict(OVER_LIMIT), call=lambda fn, qpos, qvel: fn(_data(_PEND(), qpos, qvel)), **_STATE
    ),
    "jaxobs.mjx.estimation.filter_model": Example(
        lambda: dict(Q=1e-4 * np.eye(2), x0=np.array([0.1, 0.0]), P0=1e-2 * np.eye(2), R=np.array([[1e-4]])),
        diff="Q",
        call=_on_model(_PEND),
        out=lambda model: (model.Q, model.R, model.x0, model.P0),
        skip={"float32": "its transition and measurement carry the mjx.Model, in the model's precision"},
    ),
    "jaxobs.mjx.force_1dof.sensor_force": _state_entry(_force_plant, None),
    "jaxobs.mjx.force_1dof.with_params": Example(
        lambda: dict(params=_force_params()),
        tangent="scale",
        call=_on_model(_force_plant),
        skip={"float32": _MODEL_DTYPE},
        out=lambda m: (m.jnt_stiffness, m.dof_damping, m.actuator_gainprm, m.dof_armature),
    ),
    "jaxobs.mjx.force_1dof.rollout": Example(
        lambda: dict(commands=np.array([1.0, -0.5, 0.2]), dead_time_samples=1, substeps=2),
        call=_on_model(_force_plant),
        skip={"float32": _MODEL_DTYPE},
    ),
    "jaxobs.mjx.force_1dof.closed_loop_rollout": Example(
        lambda: dict(
            controller=_controller(),
            params=_aob_controller(),
            reference=np.array([1.0, 1.0, 1.0]),
            dead_time_samples=1,
            substeps=2,
        ),
        diff="reference",
        call=_on_model(_force_plant),
        skip={"float32": _MODEL_DTYPE},
    ),  # fmt: skip
    "jaxobs.mjx.compliant_6dof.contact_point": Example(
        lambda: dict(qpos=np.array([0.1, 0.0, -0.2, 0.0, 0.01, 0.0])),
        call=_on_model(_compliant),
        skip={"float32": _MODEL_DTYPE},
    ),  # fmt: skip
    "jaxobs.mjx.compliant_6dof.coupling_force": Example(
        lambda: dict(qpos=np.array([0.1, 0.0, -0.2, 0.0, 0.01, 0.0])),
        call=_on_model(_compliant),
        skip={"float32": _MODEL_DTYPE},
    ),  # fmt: skip
    "jaxobs.mjx.compliant_6dof.sensor_wrench": Example(
        lambda: dict(qpos=np.array([0.1, 0.0, -0.2, 0.0, 0.01, 0.0]), qvel=np.linspace(-0.1, 0.1, 6)),
        diff="qvel",
        call=_on_state(_compliant),
        **_STATE,
    ),
    "jaxobs.mjx.compliant_6dof.with_params": Example(
        lambda: dict(params=_compliant_params()),
        tangent="scale",
        call=_on_model(_compliant),
        skip={"float32": _MODEL_DTYPE},
        out=lambda m: (m.jnt_stiffness, m.dof_damping, m.actuator_gainprm, m.dof_armature, m.site_pos),
    ),
    "jaxobs.mjx.compliant_6dof.rollout": Example(
        lambda: dict(commands=np.linspace(-1.0, 1.0, 18).reshape(3, 6), dead_time_samples=1, substeps=2),
        call=_on_model(_compliant),
        skip={"float32": _MODEL_DTYPE},
    ),
    "jaxobs.mjx.compliant_6dof.closed_loop_rollout": Example(
        lambda: dict(
            controller=_controller(), params=_stacked_aob(), reference=np.ones((3, 6)), dead_time_samples=1, substeps=2
        ),
        diff="reference",
        call=_on_model(_compliant),
        skip={"float32": _MODEL_DTYPE},
    ),  # fmt: skip
    "jaxobs.mjx.robot.linearize": Example(
        lambda: dict(qpos0=np.array([0.0]), qvel0=np.array([0.0])),  # the rest pose: an equilibrium
        diff="qpos0",
        call=lambda fn, **args: fn(_robot(), **args),
        skip={"float32": _MODEL_DTYPE},
    ),
    "jaxobs.mjx.robot.mismatch": Example(
        lambda: dict(scales={"dof_damping": np.float64(1.2), "body_mass": np.float64(0.9)}),
        call=_on_model(_PEND),
        out=lambda m: (m.dof_damping, m.body_mass),
        skip={
            "float32": _MODEL_DTYPE,
            "batch": "the factors may be arrays that broadcast against the scaled field (documented)",
        },
    ),
    "jaxobs.mjx.robot.rollout": Example(
        lambda: dict(controller=_controller(), params=_aob_controller(), scales=None, key=_key(5), steps=3),
        tangent="scale",
        diff="params",
        call=lambda fn, **args: fn(_robot(), **args),
        skip={"float32": _MODEL_DTYPE},
    ),
}


def _force_params():
    import jax

    from jaxobs.mjx.force_1dof import ForcePlantParams

    return jax.tree_util.tree_map(np.float64, ForcePlantParams())


def _compliant_params():
    import jax

    from jaxobs.mjx.compliant_6dof import Compliant6Params

    return jax.tree_util.tree_map(np.asarray, Compliant6Params())


def _aob_controller():
    from tests.api_registry.observers import _aob_controller as aob

    return aob()


def _stacked_aob():
    from jaxobs.mjx.compliant_6dof import stack_controllers

    return stack_controllers([_aob_controller()] * 6)


def _key(seed: int):
    import jax

    return jax.random.key(seed)


ENTRIES = slow(
    {**ENTRIES, **PHYSICS},
    "compiles physics steps of a loaded MJX model (a rollout: a scan of them) for each promise",
    *PHYSICS,
)
