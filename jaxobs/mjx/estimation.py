"""State estimation on MuJoCo MJX models: the state ``(qpos, qvel)``, the transition ``mjx.step``, the
measurement ``sensordata``.

:func:`transition` and :func:`measurement` turn an ``mjx.Model`` into the ``f`` and ``h`` of
:func:`jaxobs.nonlinear.nonlinear_model`, so the EKF and UKF run on it unchanged; both carry the model as a pytree
leaf, so a mismatched or batched model reuses one compiled filter. :func:`check_model` states the requirements
(hinge and slide joints, no activations, position- and velocity-stage sensors). :data:`CARTPOLE` is the shipped
cart-pole with sensors. Details: docs/theory/mjx.md.
"""

from __future__ import annotations

import functools
import importlib.resources

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxobs import _checks
from jaxobs.mjx.common import check_solver_iterations, put_model, step

__all__ = ["CARTPOLE", "load_cartpole", "check_model", "state", "transition", "measurement", "sample_period"]

CARTPOLE = "cartpole_sensors.xml"


def load_cartpole() -> tuple[mujoco.MjModel, mjx.Model]:
    """The shipped cart-pole with sensors (``jaxobs/mjx/assets/cartpole_sensors.xml``): ``(mj_model, mjx_model)``."""
    text = importlib.resources.files("jaxobs.mjx").joinpath("assets", CARTPOLE).read_text()
    m = mujoco.MjModel.from_xml_string(text)
    return m, put_model(m)


def check_model(model, *, sensors: bool = True) -> None:
    """Raise ``ValueError`` unless ``model`` (an ``mjx.Model`` or ``mujoco.MjModel``) has a state ``(qpos, qvel)``
    that an additive Gaussian filter can estimate (``nq == nv``, ``na == 0``) and, when ``sensors``, at least one
    sensor and none of the acceleration stage."""
    if model.nq != model.nv:
        raise ValueError(
            "model: the state (qpos, qvel) needs nq == nv (hinge and slide joints only; a free or ball joint's "
            f"quaternion needs a multiplicative update), got nq={model.nq}, nv={model.nv}"
        )
    if model.na:
        raise ValueError(f"model has {model.na} actuator activations: (qpos, qvel) would not be its whole state")
    if not sensors:
        return
    if model.nsensordata == 0:
        raise ValueError("model has no sensors: the measurement is its sensordata")
    if np.any(np.asarray(model.sensor_needstage) == mujoco.mjtStage.mjSTAGE_ACC):
        raise ValueError("model has acceleration-stage sensors (e.g. accelerometer, force, touch): their values "
                         "depend on the control, and the measurement h(x) only on the state")  # fmt: skip


def state(data: mjx.Data) -> jax.Array:
    """The filter state ``x = (qpos, qvel)`` of ``data``, shape (nq + nv,)."""
    return jnp.concatenate([data.qpos, data.qvel])


def _data(model: mjx.Model, x):
    nq = model.nq
    return mjx.make_data(model).replace(qpos=x[:nq], qvel=x[nq:])


def _transition(model: mjx.Model, x, u, t, *, substeps: int, solver_iterations: int | None):
    data = _data(model, x).replace(ctrl=u, time=t)
    data = jax.lax.fori_loop(0, substeps, lambda _, d: step(model, d, solver_iterations), data)
    return state(data)


def _measurement(model: mjx.Model, x):
    data = _data(model, x)
    data = mjx.sensor_pos(model, mjx.fwd_position(model, data))
    data = mjx.sensor_vel(model, mjx.fwd_velocity(model, data))
    return data.sensordata


@functools.cache
def _transition_of(substeps: int, solver_iterations: int | None):
    """One function object per setting: ``Partial`` s built from it compare equal (the same pytree structure),
    so a jitted filter is not retraced for another model or another call of :func:`transition`."""
    return functools.partial(_transition, substeps=substeps, solver_iterations=solver_iterations)


def transition(model: mjx.Model, *, substeps: int = 1, solver_iterations: int | None = None) -> jax.tree_util.Partial:
    """``f(x, u, t)``: the state after ``substeps`` physics steps from ``x = (qpos, qvel)`` with ``ctrl = u`` (nu,)
    held, starting at time ``t``; a ``Partial`` carrying ``model`` as a leaf. The sample period is
    :func:`sample_period`. ``solver_iterations``: None or 0 for MJX's constraint solver at the model's settings, an
    int for a solver of exactly that many iterations (:func:`jaxobs.mjx.common.step`; both differentiable)."""
    check_model(model, sensors=False)
    substeps = _checks.count("substeps", substeps, minimum=1, hint="physics steps per sample")
    solver_iterations = check_solver_iterations(solver_iterations)
    return jax.tree_util.Partial(_transition_of(substeps, solver_iterations), model)


def measurement(model: mjx.Model) -> jax.tree_util.Partial:
    """``h(x)``: the ``sensordata`` (nsensordata,) of the state ``x = (qpos, qvel)`` (position and velocity
    stages); a ``Partial`` carrying ``model`` as a leaf."""
    check_model(model)
    return jax.tree_util.Partial(_measurement, model)


def sample_period(model: mjx.Model, substeps: int) -> float:
    """``substeps`` times the model's physics time step: the period of :func:`transition`'s samples."""
    return float(model.opt.timestep) * _checks.count("substeps", substeps, minimum=1)
