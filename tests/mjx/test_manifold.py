"""jaxobs.mjx.manifold: MuJoCo's integratePos / differentiatePos in JAX (against MuJoCo C on free, ball, hinge and
slide joints), the state and sensor manifolds, and their derivatives at the zero rotation."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxobs.mjx import manifold

XML = """<mujoco><worldbody>
<body name="base"><freejoint/><geom size=".1"/>
 <body name="arm" pos="0 0 .3"><joint name="ball" type="ball"/><geom size=".1"/>
  <body name="fore" pos="0 0 .3"><joint name="hinge" type="hinge" axis="0 1 0"/><geom size=".1"/>
   <body name="tip" pos="0 0 .3"><joint name="slide" type="slide" axis="1 0 0"/><geom size=".1"/>
    <site name="s"/></body></body></body></body>
</worldbody>
<actuator><general joint="hinge" dyntype="filter" dynprm="0.1"/></actuator>
<sensor><framequat name="att" objtype="site" objname="s"/><jointpos name="angle" joint="hinge"/>
 <ballquat name="shoulder" joint="ball"/><gyro name="gyro" site="s"/></sensor></mujoco>"""


@pytest.fixture(scope="module")
def model():
    return mujoco.MjModel.from_xml_string(XML)


def _up_to_sign(x, expected, quats):
    """``x`` with each quaternion ``x[i:i+4]`` (``i`` in ``quats``) of the sign of ``expected``'s: the same rotation."""
    x = np.array(x)
    for i in quats:
        x[i : i + 4] *= np.sign(x[i : i + 4] @ expected[i : i + 4])
    return x


def _qpos(rng):
    quat = lambda: (q := rng.normal(size=4)) / np.linalg.norm(q)  # noqa: E731
    return np.concatenate([rng.normal(size=3), quat(), quat(), rng.normal(size=2)])


def test_integrate_and_differentiate_pos_equal_mujoco(model):
    """Free, ball, hinge and slide joints; rotations from 1e-9 rad (the series) to several turns, both signs of
    the quaternions' scalar part, two time steps: MuJoCo C's mj_integratePos and mj_differentiatePos to 1e-12."""
    rng = np.random.default_rng(0)
    q1, q3 = (np.stack([_qpos(rng) for _ in range(40)]) for _ in range(2))
    v = rng.normal(size=(40, model.nv)) * np.repeat([1e-9, 1e-5, 0.3, 3.0], 10)[:, None]
    for dt in (1.0, 0.01):
        q2 = q1.copy()
        for q, w in zip(q2, v, strict=True):
            mujoco.mj_integratePos(model, q, w, dt)
        ours = jax.jit(jax.vmap(lambda q, w, dt=dt: manifold.integrate_pos(model, q, w, dt)))(q1, v)
        np.testing.assert_allclose(ours, q2, atol=1e-12, rtol=0)
        for target in (q2, q3):
            expected = np.zeros((40, model.nv))
            for e, a, b in zip(expected, q1, target, strict=True):
                mujoco.mj_differentiatePos(model, e, dt, a, b)
            ours = jax.jit(jax.vmap(lambda a, b, dt=dt: manifold.differentiate_pos(model, a, b, dt)))(q1, target)
            np.testing.assert_allclose(ours, expected, atol=1e-12 / dt, rtol=0)


def test_state_manifold_is_a_retraction_with_unit_derivative(model):
    """retract(b, difference(a, b)) = a, difference(b, b) = 0, and d difference(retract(b, d), b) / dd = I at d = 0
    (the series branch): the tangent coordinates of the filters. Gradients of both maps match central
    differences at and away from the zero rotation."""
    space = manifold.state_manifold(model)
    assert (space.size, space.dim) == (model.nq + model.nv + model.na, 2 * model.nv + model.na) == (25, 23)
    rng = np.random.default_rng(1)
    a, b = (np.concatenate([_qpos(rng), rng.normal(size=model.nv + model.na)]) for _ in range(2))
    np.testing.assert_allclose(_up_to_sign(space.retract(b, space.difference(a, b)), a, (3, 7)), a, atol=1e-12)
    np.testing.assert_allclose(space.difference(b, b), 0.0, atol=1e-15)
    J = jax.jacfwd(lambda d: space.difference(space.retract(b, d), b))(jnp.zeros(space.dim))
    np.testing.assert_allclose(J, np.eye(space.dim), atol=1e-12)
    retract, difference = jax.jit(lambda d: space.retract(b, d)), jax.jit(lambda x: space.difference(x, b))
    for delta in (np.zeros(space.dim), 0.3 * rng.normal(size=space.dim)):
        check_grads(retract, (delta,), order=1, modes=("fwd", "rev"))
        check_grads(difference, (space.retract(b, delta),), order=1, modes=("fwd", "rev"))


def test_sensor_manifold_residual_of_a_quaternion_is_its_rotation(model):
    """A framequat or ballquat reading has a 3-entry residual, the rotation vector of MuJoCo's mju_subQuat; -q is the
    same rotation; vector entries subtract."""
    readings = manifold.sensor_manifold(model)
    assert (readings.size, readings.dim) == (model.nsensordata, 3 + 1 + 3 + 3)
    assert manifold.tangent_rows(model, ["angle", "att"]) == ((4, 0, 1, 2, 3), (1, 3))
    rng = np.random.default_rng(2)
    y, y_ref = rng.normal(size=12), rng.normal(size=12)
    for q in (y[0:4], y[5:9], y_ref[0:4], y_ref[5:9]):
        q /= np.linalg.norm(q)
    e = readings.difference(y, y_ref)
    expected = np.zeros(3)
    mujoco.mju_subQuat(expected, y[0:4], y_ref[0:4])
    np.testing.assert_allclose(e[:3], expected, atol=1e-13)
    np.testing.assert_allclose(e[3], y[4] - y_ref[4])
    np.testing.assert_allclose(e[7:], y[9:] - y_ref[9:])
    flipped = y.copy()
    flipped[5:9] *= -1
    np.testing.assert_allclose(readings.difference(flipped, y_ref), e, atol=1e-13)
    np.testing.assert_allclose(_up_to_sign(readings.retract(y_ref, e), y, (0, 5)), y, atol=1e-12)
    with pytest.raises(ValueError, match="unknown sensor 'tip'; the model's sensors are: 'att', 'angle'"):
        manifold.sensor_manifold(model, ["tip"])


def test_jit_and_vmap(model):
    space = manifold.state_manifold(model)
    rng = np.random.default_rng(3)
    a, b = (np.stack([np.concatenate([_qpos(rng), rng.normal(size=12)]) for _ in range(3)]) for _ in range(2))
    looped = np.stack([space.difference(x, y) for x, y in zip(a, b, strict=True)])
    np.testing.assert_allclose(jax.jit(jax.vmap(space.difference))(a, b), looped, atol=1e-13)
    with pytest.raises(ValueError, match=r"delta must be a tangent vector of shape \(23,\)"):
        space.retract(a[0], np.zeros(22))


def test_names_and_units_of_the_tangent_entries(model):
    """A name per tangent entry of the state (a free joint's six, a ball joint's three, a filtered actuator's
    activation) and the SI unit per tangent entry of the sensors (a quaternion reading's rotation in rad)."""
    names = manifold.tangent_names(model)
    dofs = ["joint0.x", "joint0.y", "joint0.z", "joint0.rx", "joint0.ry", "joint0.rz", "ball.rx", "ball.ry", "ball.rz",
            "hinge", "slide"]  # fmt: skip
    assert names == [*dofs, *(f"{d} vel" for d in dofs), "actuator0 act"]
    assert len(names) == manifold.state_manifold(model).dim
    assert manifold.sensor_units(model) == ["rad"] * 3 + ["rad"] + ["rad"] * 3 + ["rad/s"] * 3
    slide = mujoco.MjModel.from_xml_string(XML.replace('type="hinge"', 'type="slide"'))
    assert manifold.sensor_units(slide, ["angle"]) == ["m"]
