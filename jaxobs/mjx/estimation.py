"""State estimation on MuJoCo MJX models: the state ``(qpos, qvel, act)``, the transition ``mjx.step``, the
measurement ``sensordata`` of every stage.

:func:`transition` and :func:`measurement` turn an ``mjx.Model`` into the ``f`` and ``h`` of
:func:`jaxobs.nonlinear.nonlinear_model`, and :func:`filter_model` builds the whole model: the state's errors in
the tangent space (``2 nv + na``; :func:`jaxobs.mjx.manifold.state_manifold`, so free and ball joints work), a
quaternion sensor's residual a rotation vector, acceleration-stage sensors (accelerometer, force, torque, touch)
evaluated with the control, the sensor noise of the MJCF's ``noise`` attributes. The EKF and the UKF run on it
unchanged; the functions carry the model as a pytree leaf, so a mismatched or batched model reuses one compiled
filter. :data:`CARTPOLE` is the shipped cart-pole with sensors. Details: docs/theory/mjx.md.
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxobs import _checks
from jaxobs.mjx import manifold
from jaxobs.mjx.common import check_solver_iterations, constraint_rows, put_model, step
from jaxobs.nonlinear import NonlinearModel, nonlinear_model

__all__ = [
    "ASSETS",
    "CARTPOLE",
    "load_cartpole",
    "put",
    "state",
    "state_size",
    "transition",
    "measurement",
    "sensor_noise",
    "filter_model",
    "sample_period",
    "check_rotations",
]

ASSETS = Path(__file__).parent / "assets"
"""The folder of the MJCF models shipped with jaxobs (package data; ``jaxobs.papers.shipped.ROBOTS``)."""

CARTPOLE = "cartpole_sensors.xml"


def load_cartpole() -> tuple[mujoco.MjModel, mjx.Model]:
    """The shipped cart-pole with sensors (``jaxobs/mjx/assets/cartpole_sensors.xml``): ``(mj_model, mjx_model)``."""
    m = mujoco.MjModel.from_xml_path(str(ASSETS / CARTPOLE))
    return m, put_model(m)


def put(m: mujoco.MjModel) -> mjx.Model:
    """``m`` on this process's device as an ``mjx.Model``; what MJX itself cannot simulate (a flex, an integrator,
    a collision pair or sensor type it lacks) is a ``ValueError`` of one line that names it."""
    try:
        return put_model(m)
    except NotImplementedError as exc:
        raise ValueError(f"MJX (mujoco {mujoco.__version__}) cannot simulate this model: {exc}") from exc


def state(data: mjx.Data) -> jax.Array:
    """The filter state ``x = (qpos, qvel, act)`` of ``data``, shape (nq + nv + na,)."""
    _checks.fields("data", data, "qpos (q,), qvel (v,), act (a,)")  # one state: vmap for a batch
    return jnp.concatenate([data.qpos, data.qvel, data.act])


def state_size(model) -> tuple[int, int]:
    """``(n, d)``: the entries of the state ``(qpos, qvel, act)``, ``nq + nv + na``, and of its tangent space,
    ``2 nv + na`` (the size of its covariance)."""
    return model.nq + model.nv + model.na, 2 * model.nv + model.na


def _data(model: mjx.Model, x, u=None):
    nq, nv = model.nq, model.nv
    data = mjx.make_data(model).replace(qpos=x[:nq], qvel=x[nq : nq + nv], act=x[nq + nv :])
    return data if u is None else data.replace(ctrl=u)


def _rotations(model) -> bool:
    """The model has free or ball joints (quaternions in ``qpos``)."""
    kinds = np.asarray(model.jnt_type)
    return bool(np.any((kinds == mujoco.mjtJoint.mjJNT_FREE) | (kinds == mujoco.mjtJoint.mjJNT_BALL)))


def _step(model: mjx.Model, data, solver_iterations: int | None):
    """One physics step (:func:`jaxobs.mjx.common.step`) whose rotations differentiate correctly.

    MJX turns a free or ball joint's quaternion by the angle ``dt |w|`` about ``w / |w|`` with a norm whose
    derivative it sets to 0 at ``w = 0``, so at zero angular velocity (a robot at rest, where it is linearised)
    the derivative of the new orientation with respect to ``w`` is 0 instead of ``dt``. The Euler and implicit-fast
    integrators set ``qpos' = integrate_pos(qpos, qvel', dt)`` with the new velocity: recomputed here with
    :func:`jaxobs.mjx.manifold.integrate_pos` (smooth at ``w = 0``), equal values and the right derivatives. (RK4
    mixes its stages' velocities, which the step does not return: :func:`check_rotations` refuses it.)
    """
    stepped = step(model, data, solver_iterations)
    if _rotations(model) and int(model.opt.integrator) != int(mujoco.mjtIntegrator.mjINT_RK4):
        stepped = stepped.replace(qpos=manifold.integrate_pos(model, data.qpos, stepped.qvel, model.opt.timestep))
    # MJX's step returns some integer fields (a tendon's wrapping) in another width than make_data under x64: cast
    # back, so a loop's carry keeps its types
    return jax.tree.map(lambda new, old: new.astype(old.dtype), stepped, data)


def check_rotations(model, what: str) -> None:
    """``ValueError`` for a model whose step MJX differentiates wrongly: free or ball joints under RK4 (see
    :func:`_step`); ``what`` names the derivative that needs it."""
    if _rotations(model) and int(model.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_RK4):
        kinds = np.asarray(model.jnt_type)
        j = int(np.flatnonzero((kinds == mujoco.mjtJoint.mjJNT_FREE) | (kinds == mujoco.mjtJoint.mjJNT_BALL))[0])
        kind = "free" if kinds[j] == mujoco.mjtJoint.mjJNT_FREE else "ball"
        name = mjx.id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) if isinstance(model, mjx.Model) else model.joint(j).name
        raise ValueError(f"{what}: MJX's RK4 integrator differentiates the rotation of the {kind} joint "
                         f"{name or f'#{j}'!r} wrongly at zero angular velocity (its quaternion update has a zero "
                         "derivative there); use the Euler or implicitfast integrator (<option integrator=...> in "
                         "the MJCF)")  # fmt: skip


def _transition(model: mjx.Model, x, u, t, *, substeps: int, solver_iterations: int | None):
    def substep(_, data):
        return _step(model, data, solver_iterations)

    data = jax.lax.fori_loop(0, substeps, substep, _data(model, x, u).replace(time=t))
    return state(data)


def _measurement(model: mjx.Model, x, u, *, rows: tuple, acceleration: bool):
    data = _data(model, x, u)
    if acceleration:  # mj_forward: every stage, the constraint solve included
        data = mjx.forward(model, data)
        if not constraint_rows(data):  # MJX's forward returns before the acceleration sensors without constraints
            data = mjx.sensor_acc(model, data)
    else:
        data = mjx.sensor_pos(model, mjx.fwd_position(model, data))
        data = mjx.sensor_vel(model, mjx.fwd_velocity(model, data))
    return data.sensordata[np.asarray(rows, int)]


@functools.cache
def _transition_of(substeps: int, solver_iterations: int | None):
    """One function object per setting: ``Partial`` s built from it compare equal (the same pytree structure),
    so a jitted filter is not retraced for another model or another call of :func:`transition`."""
    return functools.partial(_transition, substeps=substeps, solver_iterations=solver_iterations)


@functools.cache
def _measurement_of(rows: tuple, acceleration: bool):
    return functools.partial(_measurement, rows=rows, acceleration=acceleration)


def transition(model: mjx.Model, *, substeps: int = 1, solver_iterations: int | None = None) -> jax.tree_util.Partial:
    """``f(x, u, t)``: the state ``(qpos, qvel, act)`` after ``substeps`` physics steps from ``x`` with ``ctrl = u``
    (nu,) held, starting at time ``t``; a ``Partial`` carrying ``model`` as a leaf. The sample period is
    :func:`sample_period`. ``solver_iterations``: None or 0 for MJX's constraint solver at the model's settings, an
    int for a solver of exactly that many iterations (:func:`jaxobs.mjx.common.step`; both differentiable)."""
    substeps = _checks.count("substeps", substeps, minimum=1, hint="physics steps per sample")
    solver_iterations = check_solver_iterations(solver_iterations)
    return jax.tree_util.Partial(_transition_of(substeps, solver_iterations), model)


def _measured(model, sensors) -> tuple[tuple, bool]:
    """``(rows, acceleration)``: the ``sensordata`` rows of ``sensors`` and whether one needs the acceleration
    stage; ``ValueError`` for a model without sensors or an unknown name."""
    if model.nsensordata == 0:
        raise ValueError("model has no sensors: the measurement is its sensordata")
    if sensors is not None and (isinstance(sensors, str) or not len(sensors)):
        raise ValueError(f"sensors must be a list of sensor names (None: every sensor), got {sensors!r}")
    rows, _ = manifold.tangent_rows(model, sensors)
    stage = np.asarray(model.sensor_needstage)[manifold.sensor_ids(model, sensors)]
    return rows, bool(np.any(stage == mujoco.mjtStage.mjSTAGE_ACC))


def measurement(model: mjx.Model, sensors=None) -> jax.tree_util.Partial:
    """``h(x, u)``: the ``sensordata`` entries of the named sensors (None: all, in the model's order) that
    ``mj_forward`` computes at the state ``x = (qpos, qvel, act)`` with ``ctrl = u``; a ``Partial`` carrying
    ``model`` as a leaf. In a filter (:func:`filter_model`) ``u`` is the control held over the sample that ends at
    the measurement, ``y_k = h(x_k, u_{k-1})``: the acceleration stage (accelerometer, force, torque, touch) sees it,
    the position and velocity stages do not (and skip the forward dynamics). Contact-dependent acceleration sensors
    differentiate in forward mode (``jacfwd``, the EKF): MJX's constraint solver is a ``while`` loop."""
    rows, acceleration = _measured(model, sensors)
    return jax.tree_util.Partial(_measurement_of(rows, acceleration), model)


def sensor_noise(model, sensors=None) -> np.ndarray:
    """The standard deviation of each tangent entry of the named sensors' readings (None: all): the MJCF's
    ``noise`` attribute of each sensor (``sensor_noise``, 0 where unset), repeated over its entries (3 for a
    quaternion sensor, whose noise is then an angle in radians). ``model``: a ``mujoco.MjModel`` (an ``mjx.Model``
    does not keep the noise)."""
    _, tangent = manifold.tangent_rows(model, sensors)
    return np.repeat(np.asarray(model.sensor_noise)[manifold.sensor_ids(model, sensors)], tangent)


def filter_model(
    model: mjx.Model, Q, *, x0, P0, R=None, sensors=None, substeps: int = 1, solver_iterations: int | None = None,
    t0=0.0,
) -> NonlinearModel:  # fmt: skip
    """The :class:`~jaxobs.nonlinear.NonlinearModel` of an MJX model for the EKF, the UKF and their smoothers.

    State ``x = (qpos, qvel, act)`` (``n = nq + nv + na``) on :func:`jaxobs.mjx.manifold.state_manifold` (errors,
    ``Q``, ``P0`` on its ``d = 2 nv + na`` tangent space), ``x_k = f(x_{k-1}, u_{k-1}) + w_k`` by :func:`transition`,
    ``y_k = h(x_k, u_{k-1}) + v_k`` by :func:`measurement` on :func:`jaxobs.mjx.manifold.sensor_manifold` (a
    quaternion sensor's residual is a rotation vector), ``u`` the model's ``ctrl`` (nu,).

    Args:
      model: the ``mjx.Model`` (or a ``mujoco.MjModel``, put on the device by :func:`put`).
      Q: (d, d) process noise on the tangent space.  x0: (n,) prior mean.  P0: (d, d) its covariance.
      R: (r, r) measurement noise on the readings' tangent space; None: ``diag(sensor_noise(model, sensors)^2)``,
        the MJCF's ``noise`` attributes (each measured sensor needs one; ``model`` a ``mujoco.MjModel``).
      sensors: names of the measured sensors (None: every sensor).  substeps: physics steps per sample.
      solver_iterations: see :func:`transition`.  t0: the time of the first measurement.

    The EKF's Jacobians of a model with free or ball joints are right for the Euler and implicit-fast integrators;
    under RK4, MJX's own derivative of a rotation is wrong at zero angular velocity (:func:`check_rotations`).
    """
    if R is None:
        if not isinstance(model, mujoco.MjModel):
            raise ValueError("R: an mjx.Model does not keep the MJCF's sensor noise; give R, or the mujoco.MjModel")
        silent = [i for i in manifold.sensor_ids(model, sensors) if not model.sensor_noise[i] > 0]
        if silent:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SENSOR, silent[0]) or f"#{silent[0]}"
            raise ValueError(f"R: sensor {name!r} has no noise in the MJCF (its noise attribute); give R or set "
                             "noise on every measured sensor")  # fmt: skip
        R = np.diag(sensor_noise(model, sensors) ** 2)
    if isinstance(model, mujoco.MjModel):
        model = put(model)
    n, d = state_size(model)
    return nonlinear_model(
        transition(model, substeps=substeps, solver_iterations=solver_iterations), measurement(model, sensors), Q, R,
        x0=_checks.vector("x0", x0, n, jnp.asarray(Q).dtype, what="one entry per qpos, qvel and act"), P0=P0,
        n_inputs=model.nu, dt=sample_period(model, substeps), t0=t0, manifold=manifold.state_manifold(model),
        measurement_manifold=manifold.sensor_manifold(model, sensors), feedthrough=True,
    )  # fmt: skip


def sample_period(model: mjx.Model, substeps: int) -> float:
    """``substeps`` times the model's physics time step: the period of :func:`transition`'s samples."""
    return float(model.opt.timestep) * _checks.count("substeps", substeps, minimum=1)
