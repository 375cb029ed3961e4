"""Tests for jaxobs.mjx.estimation (the (qpos, qvel, act) state, mjx.step transition and sensordata measurement of
every stage of an MJX model, against MuJoCo C) and for examples/mjx_state_estimation.py (EKF and UKF on the
cart-pole, true and mismatched model)."""

import importlib.util
import pathlib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jaxobs.mjx import estimation
from tests import ROOT

EXAMPLE = ROOT / "examples" / "mjx_state_estimation.py"


def _model(body: str, sensors: str = "") -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(
        f"<mujoco><worldbody><body>{body}<geom size='0.1' mass='1'/></body></worldbody>"
        f"<sensor>{sensors}</sensor></mujoco>"
    )


def test_transition_and_measurement_equal_mujoco():
    """f(x, u, t) is `substeps` mj_step's of MuJoCo (C) with ctrl = u held; h(x, u) is the sensordata."""
    mj_model, model = estimation.load_cartpole()
    x, u = np.array([0.1, 0.7, -0.3, 1.2]), np.array([1.5])
    f, h = estimation.transition(model, substeps=3), estimation.measurement(model)
    x_next, y = jax.jit(lambda x, u: (f(x, u, 0.0), h(x, u)))(x, u)
    data = mujoco.MjData(mj_model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = x[:2], x[2:], u
    mujoco.mj_forward(mj_model, data)
    np.testing.assert_allclose(y, data.sensordata, rtol=1e-12, atol=1e-12)
    for _ in range(3):
        mujoco.mj_step(mj_model, data)
    np.testing.assert_allclose(x_next, np.concatenate([data.qpos, data.qvel]), rtol=1e-10, atol=1e-12)
    assert estimation.sample_period(model, 3) == pytest.approx(0.03)


JOINTS = """<body name="base" pos="0 0 0.3"><freejoint/><geom name="torso" size=".08" mass="2"/>
 <site name="imu" pos=".02 0 .01"/>
 <body pos=".1 0 0"><joint name="shoulder" type="ball" damping=".1"/>
  <geom type="capsule" fromto="0 0 0 .2 0 0" size=".02" mass=".3"/>
  <body pos=".2 0 0"><joint name="elbow" axis="0 1 0" damping=".05"/>
   <geom type="capsule" fromto="0 0 0 .15 0 0" size=".02" mass=".2"/>
   <body pos=".15 0 0"><joint name="slide" type="slide" axis="1 0 0" damping=".5"/>
    <geom name="tip" size=".03" mass=".05"/><site name="touch" size=".035"/></body></body></body></body>"""
ACTUATORS = """<tendon><fixed name="t"><joint joint="elbow" coef="0.05"/></fixed></tendon>
<actuator><motor name="elbow_motor" joint="elbow"/><muscle name="flexor" tendon="t" force="50" lengthrange="-.2 .2"/>
 <position name="slide_servo" joint="slide" kp="20" timeconst="0.05"/></actuator>"""
SENSORS = """<accelerometer name="acc" site="imu"/><gyro name="gyro" site="imu"/><force name="f" site="imu"/>
 <torque name="tq" site="imu"/><framequat name="att" objtype="site" objname="imu"/>
 <ballquat name="bq" joint="shoulder"/><framepos name="pos" objtype="site" objname="imu"/>
 <velocimeter name="vel" site="imu"/><jointpos name="jp" joint="elbow"/><jointvel name="jv" joint="slide"/>
 <actuatorfrc name="af" actuator="flexor"/><magnetometer name="mag" site="imu"/>"""


def _every_joint(contacts: bool) -> mujoco.MjModel:
    """Free, ball, hinge and slide joints, a motor, a muscle and a filtered servo (two activations), sensors of every
    stage; with ``contacts`` a floor the body and the tip touch, and a touch sensor."""
    floor = '<geom name="floor" type="plane" size="5 5 .1"/>' if contacts else ""
    flag = "" if contacts else '<option><flag contact="disable"/></option>'
    touch = '<touch name="touch" site="touch"/>' if contacts else ""
    xml = f'<mujoco>{flag}<option timestep="0.005"/><worldbody>{floor}{JOINTS}</worldbody>{ACTUATORS}'
    return mujoco.MjModel.from_xml_string(f"{xml}<sensor>{SENSORS}{touch}</sensor></mujoco>")


def _state(m, rng, height):
    quat = lambda: (q := rng.normal(size=4)) / np.linalg.norm(q)  # noqa: E731
    qpos = np.concatenate([[0.0, 0.0, height], quat(), quat(), [0.3, 0.02]])
    return qpos, rng.normal(size=m.nv), rng.uniform(0.1, 0.9, size=m.na), np.array([0.3, 0.5, 0.1])


def _agrees_with_mujoco(m, height, substeps):
    """h(x, u) against mj_forward's sensordata and f(x, u) against mj_step, at two random states."""
    model = estimation.put(m)
    f, h = estimation.transition(model, substeps=substeps), estimation.measurement(model)
    both = jax.jit(lambda x, u: (h(x, u), f(x, u, 0.0)))
    rng = np.random.default_rng(0)
    for _ in range(2):
        qpos, qvel, act, ctrl = _state(m, rng, height)
        y, x_next = both(np.concatenate([qpos, qvel, act]), ctrl)
        data = mujoco.MjData(m)
        data.qpos[:], data.qvel[:], data.act[:], data.ctrl[:] = qpos, qvel, act, ctrl
        mujoco.mj_forward(m, data)
        np.testing.assert_allclose(y, data.sensordata, rtol=0, atol=1e-10)
        for _ in range(substeps):
            mujoco.mj_step(m, data)
        np.testing.assert_allclose(x_next, np.concatenate([data.qpos, data.qvel, data.act]), rtol=0, atol=1e-10)
    return data


def test_sensors_of_every_stage_equal_mujoco():
    """Free, ball, hinge and slide joints with two actuator activations (a muscle, a filtered servo): every stage's
    sensors (accelerometer, force and torque with the control; the framequat and ballquat quaternions) equal
    mj_forward's sensordata, and the transition mj_step's (qpos, qvel, act), to 1e-10."""
    m = _every_joint(contacts=False)
    assert (m.nq, m.nv, m.na) == (13, 11, 2)
    assert set(np.asarray(m.sensor_needstage)) == {1, 2, 3}  # the position, velocity and acceleration stages
    _agrees_with_mujoco(m, 0.3, substeps=1)


@pytest.mark.slow  # MJX compiles the collision detection
def test_touch_sensor_and_contacts_equal_mujoco():
    """The same robot on a floor that it touches (spheres and capsules against a plane): the touch sensor and the
    acceleration-stage sensors after MJX's constraint solve equal MuJoCo C's to 1e-10, and so do three steps."""
    m = _every_joint(contacts=True)
    data = _agrees_with_mujoco(m, 0.07, substeps=3)
    assert data.ncon > 0


def test_models_of_one_structure_give_one_pytree_structure():
    """A mismatched model is the same pytree with other values: a jitted filter compiles once for both."""
    mj_model, model = estimation.load_cartpole()
    heavier = mj_model.__copy__()
    heavier.body_mass[2] *= 1.3
    other = estimation.load_cartpole()[1].replace(body_mass=jnp.asarray(heavier.body_mass))
    for make in (lambda m: estimation.transition(m, substeps=2), estimation.measurement):
        assert jax.tree_util.tree_structure(make(model)) == jax.tree_util.tree_structure(make(other))


def test_bad_models_raise_naming_the_problem():
    hinge = "<joint name='j' type='hinge'/>"
    with pytest.raises(ValueError, match="no sensors"):
        estimation.measurement(_model(hinge))
    with pytest.raises(ValueError, match="unknown sensor 'tip'; the model's sensors are: 'acc'"):
        estimation.measurement(_model(hinge + "<site name='s'/>", "<accelerometer name='acc' site='s'/>"), ["tip"])
    with pytest.raises(ValueError, match="substeps"):
        estimation.transition(_model(hinge), substeps=0)
    implicit = mujoco.MjModel.from_xml_string("<mujoco><option integrator='implicit'/><worldbody><body><joint/>"
                                              "<geom size='.1'/></body></worldbody></mujoco>")  # fmt: skip
    with pytest.raises(ValueError, match=r"^MJX \(mujoco [\d.]+\) cannot simulate this model: .*IMPLICIT"):
        estimation.put(implicit)
    silent = _model(hinge + "<site name='s'/>", "<gyro name='gyro' site='s' noise='0.1'/><accelerometer name='acc' "
                    "site='s'/>")  # fmt: skip
    with pytest.raises(ValueError, match="R: sensor 'acc' has no noise in the MJCF"):
        estimation.filter_model(silent, np.eye(2), x0=np.zeros(2), P0=np.eye(2))
    model = estimation.filter_model(silent, np.eye(2), x0=np.zeros(2), P0=np.eye(2), sensors=["gyro"])
    np.testing.assert_allclose(model.R, 0.01 * np.eye(3))
    assert (model.manifold.dim, model.measurement_manifold.dim, model.feedthrough) == (2, 3, True)


@pytest.mark.slow
def test_example_tracks_the_cartpole_and_a_mismatched_model_costs_accuracy(tmp_path):
    """The worked example, measured: with the true model both filters estimate every state to better than the
    sensors measure it (cart 2.6 mm RMS from a 5 mm sensor; pole angle 7.5 mrad from 10 mm tip readings at 0.5 m,
    20 mrad); a 30 % heavier pole in the filter's model costs accuracy in the velocities (+43 % and +30 % RMS)
    and the cart position (+20 %) but still tracks. The lost tip samples are skipped and counted."""
    spec = importlib.util.spec_from_file_location("mjx_state_estimation", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    results = example.main(["--out", str(tmp_path)])
    assert pathlib.Path(results["figure"]).stat().st_size > 10_000
    assert results["missing_samples"] > 0
    for name in ("EKF", "UKF"):
        true, mismatched = (np.array(results[f"{name}, {m}"]["rms"]) for m in ("true model", "pole mass +30 %"))
        assert results[f"{name}, true model"]["missing"] == 3 * results["missing_samples"]
        assert true[0] < 0.6 * example.SENSOR_STD[0]  # m, cart position
        assert true[1] < 0.5 * example.SENSOR_STD[1] / 0.5  # rad, pole angle vs the tip readings' angle noise
        assert np.all(true[2:] < [0.04, 0.1])  # m/s, rad/s (the velocities are not measured)
        assert np.all(mismatched[[0, 2, 3]] > 1.15 * true[[0, 2, 3]])
        assert np.all(mismatched < 2 * true)
    ekf, ukf = (np.array(results[f"{name}, true model"]["rms"]) for name in ("EKF", "UKF"))
    np.testing.assert_allclose(ekf, ukf, rtol=0.05)
