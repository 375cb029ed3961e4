"""The MuJoCo state ``(qpos, qvel, act)`` and measured ``sensordata`` as manifolds: errors in the tangent space.

A free joint's ``qpos`` holds a position and a unit quaternion (7 entries for 6 degrees of freedom), a ball
joint's a quaternion (4 for 3): they are not added and subtracted as vectors. MuJoCo moves along them with
``mj_integratePos`` and measures between them with ``mj_differentiatePos`` (rotations as 3-vectors in the joint's
local frame, ``q1 * exp(v) = q2``); :func:`integrate_pos` and :func:`differentiate_pos` are the same maps in JAX, and
:func:`state_manifold` makes them the :class:`~jaxobs.nonlinear.Manifold` of the state ``x = (qpos, qvel, act)``
(``nq + nv + na`` entries, ``2 nv + na`` tangent dimensions), the covariance space of every MJX estimator and
linearisation (as in MuJoCo MPC's estimators). :func:`sensor_manifold` does the same for measured sensors: a
``framequat`` or ``ballquat`` reading (4 entries) has a 3-dimensional rotation residual.

Smooth everywhere (series near the zero rotation), so ``jax.jacfwd`` and ``jax.grad`` go through them; the joint
layout is static (taken from the model when the manifold is made). Details: docs/theory/mjx.md.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxobs.nonlinear import Manifold

__all__ = [
    "QUATERNION_SENSORS",
    "quat_multiply",
    "quat_difference",
    "quat_integrate",
    "differentiate_pos",
    "integrate_pos",
    "tangent_names",
    "sensor_units",
    "state_manifold",
    "sensor_manifold",
    "tangent_rows",
    "sensor_ids",
]

QUATERNION_SENSORS = (mujoco.mjtSensor.mjSENS_FRAMEQUAT, mujoco.mjtSensor.mjSENS_BALLQUAT)
"""The sensor types whose reading is a unit quaternion (4 entries, a 3-dimensional tangent space)."""

_SERIES = 1e-8  # squared angle (or tangent of half of it) below which the series replace the closed forms


def quat_multiply(a, b):
    """The quaternion product ``a * b`` (w, x, y, z first-axis-last), MuJoCo's ``mju_mulQuat``; broadcasts."""
    aw, ax, ay, az = jnp.moveaxis(jnp.asarray(a), -1, 0)
    bw, bx, by, bz = jnp.moveaxis(jnp.asarray(b), -1, 0)
    return jnp.stack([aw * bw - ax * bx - ay * by - az * bz,
                      aw * bx + ax * bw + ay * bz - az * by,
                      aw * by - ax * bz + ay * bw + az * bx,
                      aw * bz + ax * by - ay * bx + az * bw], axis=-1)  # fmt: skip


def quat_difference(qa, qb):
    """The rotation vector ``v`` (..., 3) with ``qb * exp(v) = qa``: MuJoCo's ``mju_subQuat(qa, qb)``, the shorter
    of the two rotations, in ``qb``'s local frame. ``qa``, ``qb`` (..., 4), unit (scale does not matter)."""
    qb = jnp.asarray(qb)
    conj = qb * jnp.array([1.0, -1.0, -1.0, -1.0], qb.dtype)
    q = quat_multiply(conj, qa)
    sign = jnp.where(q[..., :1] < 0, -1.0, 1.0)  # -q is the same rotation: take the one with w >= 0
    w, v = sign[..., 0] * q[..., 0], sign * q[..., 1:]
    s2 = jnp.sum(v * v, axis=-1)
    small = s2 <= _SERIES * w * w
    w_small = jnp.where(small, w, 1.0)
    series = 2.0 / w_small * (1.0 - jnp.where(small, s2, 0.0) / (3.0 * w_small * w_small))  # 2 atan(s/w) / s
    s = jnp.sqrt(jnp.where(small, 1.0, s2))
    closed = 2.0 * jnp.arctan2(s, w) / s
    return jnp.where(small, series, closed)[..., None] * v


def quat_integrate(q, v):
    """``q * exp(v)``: ``q`` (..., 4) turned by the rotation vector ``v`` (..., 3) in its local frame, MuJoCo's
    ``mju_quatIntegrate(q, v, 1)`` (``q`` normalised first)."""
    q, v = jnp.asarray(q), jnp.asarray(v)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    t2 = jnp.sum(v * v, axis=-1)
    small = t2 <= _SERIES
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    t2_small = jnp.where(small, t2, 0.0)
    cos = jnp.where(small, 1.0 - t2_small / 8.0 + t2_small * t2_small / 384.0, jnp.cos(0.5 * t))
    sinc = jnp.where(small, 0.5 - t2_small / 48.0, jnp.sin(0.5 * t) / t)  # sin(t / 2) / t
    return quat_multiply(q, jnp.concatenate([cos[..., None], sinc[..., None] * v], axis=-1))


@dataclasses.dataclass(frozen=True)
class _Layout:
    """Where the vector entries and the quaternions of a point sit, and their coordinates in the tangent space
    (static index tuples: hashable, so one function object per layout)."""

    size: int  # entries of a point
    dim: int  # tangent dimension
    linear: tuple  # point index of each vector entry
    linear_tangent: tuple  # its tangent index
    quats: tuple  # (k, 4) point indices of each quaternion
    quats_tangent: tuple  # (k, 3) its tangent indices

    def assemble(self, linear, quats):
        """The tangent vector (dim,) from the vector entries (len(linear),) and rotations (k, 3)."""
        order = np.argsort(np.concatenate([self.linear_tangent, np.ravel(self.quats_tangent)]).astype(int))
        return jnp.concatenate([linear, jnp.reshape(quats, (-1,))])[order]


def _linear(layout: _Layout):
    return np.asarray(layout.linear, int), np.asarray(layout.linear_tangent, int)


def _quats(layout: _Layout):
    points, tangent = np.asarray(layout.quats, int), np.asarray(layout.quats_tangent, int)
    return np.reshape(points, (-1, 4)), np.reshape(tangent, (-1, 3))


@functools.cache
def _difference_of(layout: _Layout):
    def difference(a, b):
        (lp, _), (qp, _) = _linear(layout), _quats(layout)
        a, b = jnp.asarray(a), jnp.asarray(b)
        _check_point("a", a, layout)
        _check_point("b", b, layout)
        return layout.assemble(a[lp] - b[lp], quat_difference(a[qp], b[qp]))

    return difference


@functools.cache
def _retract_of(layout: _Layout):
    def retract(b, delta):
        (lp, lt), (qp, qt) = _linear(layout), _quats(layout)
        delta = jnp.asarray(delta)
        b = jnp.asarray(b, jnp.result_type(b, delta))
        _check_point("b", b, layout)
        if jnp.shape(delta) != (layout.dim,):
            raise ValueError(f"delta must be a tangent vector of shape ({layout.dim},), got {jnp.shape(delta)}")
        point = b.at[lp].add(delta[lt])
        return point.at[qp].set(quat_integrate(b[qp], delta[qt])) if qp.size else point

    return retract


def _check_point(name: str, value, layout: _Layout) -> None:
    if jnp.shape(value) != (layout.size,):
        raise ValueError(f"{name} must be a point of shape ({layout.size},), got {jnp.shape(value)}")


def _manifold(layout: _Layout) -> Manifold:
    return Manifold(jax.tree_util.Partial(_difference_of(layout)), jax.tree_util.Partial(_retract_of(layout)),
                    layout.dim, layout.size)  # fmt: skip


def _qpos_layout(model) -> tuple[list, list, list, list]:
    """``(linear, linear_tangent, quats, quats_tangent)`` of ``qpos`` (tangent: ``qvel``'s layout)."""
    linear, linear_tangent, quats, quats_tangent = [], [], [], []
    for kind, q, v in zip(np.asarray(model.jnt_type), np.asarray(model.jnt_qposadr), np.asarray(model.jnt_dofadr),
                          strict=True):  # fmt: skip
        kind, q, v = int(kind), int(q), int(v)
        if kind == mujoco.mjtJoint.mjJNT_FREE:
            linear += [q, q + 1, q + 2]
            linear_tangent += [v, v + 1, v + 2]
            q, v = q + 3, v + 3
        if kind in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL):
            quats.append(tuple(range(q, q + 4)))
            quats_tangent.append(tuple(range(v, v + 3)))
        else:
            linear.append(q)
            linear_tangent.append(v)
    return linear, linear_tangent, quats, quats_tangent


def _freeze(size: int, dim: int, linear, linear_tangent, quats, quats_tangent) -> _Layout:
    return _Layout(size, dim, tuple(linear), tuple(linear_tangent), tuple(quats), tuple(quats_tangent))


def differentiate_pos(model, qpos1, qpos2, dt=1.0):
    """The velocity (nv,) that moves ``qpos1`` to ``qpos2`` (nq,) in time ``dt``: MuJoCo's
    ``mj_differentiatePos(m, qvel, dt, qpos1, qpos2)`` (rotations of free and ball joints in their local frames).
    ``model``: an ``mjx.Model`` or ``mujoco.MjModel``."""
    layout = _freeze(model.nq, model.nv, *_qpos_layout(model))
    qpos1, qpos2 = jnp.asarray(qpos1), jnp.asarray(qpos2)
    _check_point("qpos1", qpos1, layout)
    _check_point("qpos2", qpos2, layout)
    return _difference_of(layout)(qpos2, qpos1) / dt


def integrate_pos(model, qpos, qvel, dt=1.0):
    """``qpos`` (nq,) moved by the velocity ``qvel`` (nv,) for time ``dt``: MuJoCo's ``mj_integratePos(m, qpos,
    qvel, dt)``."""
    layout = _freeze(model.nq, model.nv, *_qpos_layout(model))
    qvel = jnp.asarray(qvel)
    qpos = jnp.asarray(qpos, qvel.dtype)
    _check_point("qpos", qpos, layout)
    if qvel.shape != (layout.dim,):
        raise ValueError(f"qvel must have shape ({layout.dim},) (nv), got {qvel.shape}")
    return _retract_of(layout)(qpos, qvel * dt)


def state_manifold(model) -> Manifold:
    """The :class:`~jaxobs.nonlinear.Manifold` of the state ``x = (qpos, qvel, act)`` of ``model`` (an
    ``mjx.Model`` or ``mujoco.MjModel``): ``difference(x, x_ref)`` is ``(differentiate_pos(x_ref.qpos, x.qpos),
    qvel - qvel_ref, act - act_ref)`` (``2 nv + na`` entries) and ``retract`` its inverse, ``integrate_pos`` on
    ``qpos``. The functions hold the joint layout, not the model: every model of one structure (a mismatched one,
    a batch) shares them.

    Example:
      >>> import mujoco, numpy as np
      >>> from jaxobs.mjx import manifold
      >>> m = mujoco.MjModel.from_xml_string(
      ...     "<mujoco><worldbody><body><freejoint/><geom size='.1'/></body></worldbody></mujoco>")
      >>> space = manifold.state_manifold(m)
      >>> m.nq + m.nv + m.na, space.dim  # a point has 13 entries, an error 12
      (13, 12)
    """
    nq, nv, na = model.nq, model.nv, model.na
    linear, linear_tangent, quats, quats_tangent = _qpos_layout(model)
    linear += list(range(nq, nq + nv + na))
    linear_tangent += list(range(nv, 2 * nv + na))
    return _manifold(_freeze(nq + nv + na, 2 * nv + na, linear, linear_tangent, quats, quats_tangent))


def sensor_ids(model, sensors=None) -> list[int]:
    """The ids of the sensors named ``sensors`` (None: every sensor, in the model's order); ``ValueError`` for an
    unknown name, listing the valid ones."""
    if sensors is None:
        return list(range(model.nsensor))
    ids = [mjx.name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name) for name in sensors]
    for name, i in zip(sensors, ids, strict=True):
        if i < 0:
            valid = [mjx.id2name(model, mujoco.mjtObj.mjOBJ_SENSOR, j) or f"#{j}" for j in range(model.nsensor)]
            raise ValueError(f"unknown sensor {name!r}; the model's sensors are: "
                             f"{', '.join(map(repr, valid)) or 'none'}")  # fmt: skip
    return [int(i) for i in ids]


def tangent_rows(model, sensors=None) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """``(rows, tangent)``: the ``sensordata`` rows of the named sensors (None: all), in order, and the number of
    tangent entries of each sensor (its dimension, 3 for a quaternion sensor)."""
    rows, tangent = [], []
    adr, dim, kind = (np.asarray(getattr(model, f)) for f in ("sensor_adr", "sensor_dim", "sensor_type"))
    for i in sensor_ids(model, sensors):
        rows += range(int(adr[i]), int(adr[i]) + int(dim[i]))
        tangent.append(3 if int(kind[i]) in QUATERNION_SENSORS else int(dim[i]))
    return tuple(rows), tuple(tangent)


def sensor_manifold(model, sensors=None) -> Manifold:
    """The :class:`~jaxobs.nonlinear.Manifold` of the readings of the named sensors (None: every sensor), their
    ``sensordata`` entries in order: a ``framequat`` or ``ballquat`` reading is a unit quaternion whose residual is
    the rotation vector ``quat_difference(y, y_ref)`` (3 entries); every other entry subtracts."""
    rows, tangent = tangent_rows(model, sensors)
    kind = np.asarray(model.sensor_type)
    linear, linear_tangent, quats, quats_tangent = [], [], [], []
    point = coordinate = 0
    for i, size in zip(sensor_ids(model, sensors), tangent, strict=True):
        if int(kind[i]) in QUATERNION_SENSORS:
            quats.append(tuple(range(point, point + 4)))
            quats_tangent.append(tuple(range(coordinate, coordinate + 3)))
            point += 4
        else:
            linear += range(point, point + size)
            linear_tangent += range(coordinate, coordinate + size)
            point += size
        coordinate += size
    return _manifold(_freeze(len(rows), coordinate, linear, linear_tangent, quats, quats_tangent))


def _dof_names(model) -> list[str]:
    """A name per degree of freedom (``qvel`` entry): the joint's, with ``.x .y .z .rx .ry .rz`` for a free joint's
    and ``.rx .ry .rz`` for a ball joint's."""
    names = []
    for j, kind in enumerate(np.asarray(model.jnt_type)):
        name = mjx.id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"
        axes = {mujoco.mjtJoint.mjJNT_FREE: ("x", "y", "z", "rx", "ry", "rz"), mujoco.mjtJoint.mjJNT_BALL:
                ("rx", "ry", "rz")}.get(int(kind))  # fmt: skip
        names += [name] if axes is None else [f"{name}.{a}" for a in axes]
    return names


def tangent_names(model) -> list[str]:
    """A name per entry of :func:`state_manifold`'s tangent (``2 nv + na``): each degree of freedom's position
    (its joint's name), then its velocity (``"... vel"``), then each activation (``"... act"``, its actuator's).

    Example:
      >>> import mujoco
      >>> from jaxobs.mjx import manifold
      >>> m = mujoco.MjModel.from_xml_string("<mujoco><worldbody><body><joint name='hinge'/><geom size='.1'/>"
      ...                                    "</body></worldbody></mujoco>")
      >>> manifold.tangent_names(m)
      ['hinge', 'hinge vel']
    """
    dofs = _dof_names(model)
    dynamic = np.flatnonzero(np.asarray(model.actuator_dyntype) != mujoco.mjtDyn.mjDYN_NONE)
    acts = [mjx.id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, int(i)) or f"actuator{i}" for i in dynamic]
    return [*dofs, *(f"{d} vel" for d in dofs), *(f"{a} act" for a in acts)]


_SENSOR_UNITS = {"TOUCH": "N", "ACCELEROMETER": "m/s²", "VELOCIMETER": "m/s", "GYRO": "rad/s", "FORCE": "N",
                 "TORQUE": "N m", "MAGNETOMETER": "T", "RANGEFINDER": "m", "TENDONPOS": "m", "TENDONVEL": "m/s",
                 "BALLQUAT": "rad", "BALLANGVEL": "rad/s", "FRAMEPOS": "m", "FRAMEQUAT": "rad", "FRAMELINVEL": "m/s",
                 "FRAMEANGVEL": "rad/s", "FRAMELINACC": "m/s²", "FRAMEANGACC": "rad/s²", "SUBTREECOM": "m",
                 "SUBTREELINVEL": "m/s", "SUBTREEANGMOM": "kg m²/s", "CLOCK": "s"}  # fmt: skip
_JOINT_UNITS = {"JOINTPOS": ("rad", "m"), "JOINTVEL": ("rad/s", "m/s"), "JOINTACTFRC": ("N m", "N")}


def sensor_units(model, sensors=None) -> list[str]:
    """The SI unit of each tangent entry of the named sensors' readings (None: every sensor; see
    :func:`tangent_rows`): radians for a hinge joint's position (whatever the MJCF's angle unit), a quaternion
    sensor's rotation vector in rad; ``""`` where the unit depends on a transmission or is not known (actuator
    sensors, user sensors)."""
    units = []
    for i, size in zip(sensor_ids(model, sensors), tangent_rows(model, sensors)[1], strict=True):
        kind = mujoco.mjtSensor(int(np.asarray(model.sensor_type)[i])).name.removeprefix("mjSENS_")
        unit = _SENSOR_UNITS.get(kind, "")
        if kind in _JOINT_UNITS:
            joint = int(np.asarray(model.jnt_type)[int(np.asarray(model.sensor_objid)[i])])
            unit = _JOINT_UNITS[kind][joint == mujoco.mjtJoint.mjJNT_SLIDE]
        units += [unit] * size
    return units
