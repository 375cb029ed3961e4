"""Tests for jaxobs.mjx.estimation (the (qpos, qvel) state, mjx.step transition and sensordata measurement of an
MJX model) and for examples/mjx_state_estimation.py (EKF and UKF on the cart-pole, true and mismatched model)."""

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
    """f(x, u, t) is `substeps` mj_step's of MuJoCo (C) with ctrl = u held; h(x) is the sensordata."""
    mj_model, model = estimation.load_cartpole()
    x, u = np.array([0.1, 0.7, -0.3, 1.2]), np.array([1.5])
    f, h = estimation.transition(model, substeps=3), estimation.measurement(model)
    x_next, y = jax.jit(lambda x, u: (f(x, u, 0.0), h(x)))(x, u)
    data = mujoco.MjData(mj_model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = x[:2], x[2:], u
    mujoco.mj_forward(mj_model, data)
    np.testing.assert_allclose(y, data.sensordata, rtol=1e-12, atol=1e-12)
    for _ in range(3):
        mujoco.mj_step(mj_model, data)
    np.testing.assert_allclose(x_next, np.concatenate([data.qpos, data.qvel]), rtol=1e-10, atol=1e-12)
    assert estimation.sample_period(model, 3) == pytest.approx(0.03)


def test_models_of_one_structure_give_one_pytree_structure():
    """A mismatched model is the same pytree with other values: a jitted filter compiles once for both."""
    mj_model, model = estimation.load_cartpole()
    heavier = mj_model.__copy__()
    heavier.body_mass[2] *= 1.3
    other = estimation.load_cartpole()[1].replace(body_mass=jnp.asarray(heavier.body_mass))
    for make in (lambda m: estimation.transition(m, substeps=2), estimation.measurement):
        assert jax.tree_util.tree_structure(make(model)) == jax.tree_util.tree_structure(make(other))


def test_bad_models_raise_naming_the_problem():
    free = _model("<freejoint/>", "<framepos objtype='body' objname='world'/>")
    with pytest.raises(ValueError, match="nq == nv"):
        estimation.transition(free)
    hinge = "<joint name='j' type='hinge'/>"
    with pytest.raises(ValueError, match="no sensors"):
        estimation.measurement(_model(hinge))
    with pytest.raises(ValueError, match="acceleration-stage sensors"):
        estimation.measurement(_model(hinge + "<site name='s'/>", "<accelerometer site='s'/>"))
    with pytest.raises(ValueError, match="substeps"):
        estimation.transition(_model(hinge), substeps=0)


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
