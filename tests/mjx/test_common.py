"""The MJX plants' shared physics step (jaxobs.mjx.common.step): a constraint solver of a fixed iteration count
that reverse mode differentiates, on the shipped arm whose hand strikes a wall (frictional contact) and whose elbow
has a joint limit."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jaxobs.mjx import common
from jaxobs.papers.shipped import ROBOTS

ARM = ROBOTS / "arm_on_table.xml"
STEPS = 160  # 0.8 s at 5 ms: the hand reaches the wall after about 0.5 s


@pytest.fixture(scope="module")
def arm():
    m = mujoco.MjModel.from_xml_path(str(ARM))
    return m, common.put_model(m)


def _trajectory(model, torque, solver_iterations):
    """qpos (STEPS, 2) and the constraint forces' largest magnitude under a constant torque ``torque`` (2,)."""

    def body(data, _):
        data = common.step(model, data.replace(ctrl=torque), solver_iterations)
        return data, (data.qpos, jnp.max(jnp.abs(data.qfrc_constraint)))

    _, (qpos, force) = jax.lax.scan(body, common.initial_data(model, jnp.float64), None, length=STEPS)
    return qpos, jnp.max(force)


TORQUE = jnp.array([-3.5, -0.6])  # the shoulder drives the hand into the wall


def test_the_fixed_count_solver_reproduces_mujoco_through_contact(arm):
    """With 4 warm-started Newton iterations the trajectory equals mjx.step's (solver run to its tolerance) and CPU
    MuJoCo's to rounding, while the wall pushes back (constraint forces of tens of N m); a single iteration per
    step is off by about 1e-2 rad."""
    m, model = arm
    assert common.constraint_rows(common.initial_data(model, jnp.float64)) > 0
    run = jax.jit(_trajectory, static_argnums=2)
    reference, force = run(model, TORQUE, None)
    assert float(force) > 10
    data = mujoco.MjData(m)
    cpu = []
    for _ in range(STEPS):
        data.ctrl[:] = np.asarray(TORQUE)
        mujoco.mj_step(m, data)
        cpu.append(data.qpos.copy())
    np.testing.assert_allclose(reference, np.array(cpu), atol=1e-12)
    fixed, _ = run(model, TORQUE, 4)
    np.testing.assert_allclose(fixed, reference, atol=1e-12)
    one, _ = run(model, TORQUE, 1)
    assert 1e-4 < float(jnp.max(jnp.abs(one - reference))) < 0.1


@pytest.mark.slow
def test_reverse_mode_through_contact_and_limit_matches_central_differences(arm):
    """d(sum of squared shoulder angles)/d(torque gain): reverse mode with 4 solver iterations, forward mode through
    MJX's own solver loop, and central differences agree; reverse mode through MJX's while loop raises."""
    _, model = arm

    def loss(gain, solver_iterations):
        qpos, _ = _trajectory(model, gain * TORQUE, solver_iterations)
        return jnp.sum(qpos[:, 0] ** 2)

    reverse = jax.jit(jax.grad(lambda g: loss(g, 4)))(1.0)
    _, forward = jax.jit(lambda g: jax.jvp(lambda a: loss(a, None), (g,), (1.0,)))(1.0)
    value = jax.jit(lambda g: loss(g, 4))
    eps = 1e-6
    fd = (value(1.0 + eps) - value(1.0 - eps)) / (2 * eps)
    assert abs(float(reverse)) > 1
    np.testing.assert_allclose(reverse, fd, rtol=1e-7)
    np.testing.assert_allclose(reverse, forward, rtol=1e-9)
    with pytest.raises(ValueError, match="Reverse-mode differentiation does not work for lax.while_loop"):
        jax.eval_shape(jax.grad(lambda g: loss(g, None)), 1.0)


def test_bad_solver_iterations_are_refused(arm):
    _, model = arm
    data = common.initial_data(model, jnp.float64)
    for bad in (0, 2.0, True, "4"):
        with pytest.raises(ValueError, match="solver_iterations must be None or a Python int >= 1"):
            common.step(model, data, bad)
