"""The MJX plants' shared physics step (jaxobs.mjx.common.step): MJX's constraint solver with implicit derivatives,
and the fixed-count solver, on the shipped arm whose hand strikes a wall (frictional contact) and whose elbow has a
joint limit."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from jaxobs.mjx import common
from tests import ROOT

ARM = ROOT / "examples" / "robots" / "arm_on_table.xml"
STEPS = 160  # 0.8 s at 5 ms: the hand reaches the wall after about 0.5 s
TORQUE = jnp.array([-3.5, -0.6])  # the shoulder drives the hand into the wall
AT_LIMIT = (jnp.array([0.0, -0.31]), jnp.array([0.5, -2.0]))  # elbow pressed on its limit, the wall never reached


@pytest.fixture(scope="module")
def arm():
    m = mujoco.MjModel.from_xml_path(str(ARM))
    return m, common.put_model(m)


@pytest.fixture(scope="module")
def tight():
    """The arm with its solver run to a tolerance of 1e-10 in at most 50 iterations: a user's settings, left as
    written."""
    xml = ARM.read_text().replace('iterations="20"', 'iterations="50" tolerance="1e-10"')
    return common.put_model(mujoco.MjModel.from_xml_string(xml))


def _trajectory(model, torque, solver_iterations, qpos=None, steps=STEPS, step=common.step):
    """qpos (steps, 2) and the constraint forces' largest magnitude under a constant torque ``torque`` (2,)."""

    def body(data, _):
        data = step(model, data.replace(ctrl=torque), solver_iterations)
        return data, (data.qpos, jnp.max(jnp.abs(data.qfrc_constraint)))

    data = common.initial_data(model, jnp.float64)
    data = data if qpos is None else data.replace(qpos=qpos)
    _, (qpos, force) = jax.lax.scan(body, data, None, length=steps)
    return qpos, jnp.max(force)


def _with_mass(model, scale):
    """The arm with its hand's mass scaled by ``scale`` (a traced model field)."""
    return model.replace(body_mass=model.body_mass.at[-1].multiply(scale))


def test_the_step_is_mjx_step_and_the_fixed_count_reproduces_it_through_contact(arm):
    """MJX's solver at the model's settings: the trajectory is ``mjx.step``'s bit for bit and CPU MuJoCo's to
    rounding while the wall pushes back (constraint forces of tens of N m); 4 warm-started Newton iterations equal it
    to 1e-12, a single iteration per step is off by about 1e-2 rad."""
    m, model = arm
    assert common.constraint_rows(common.initial_data(model, jnp.float64)) > 0
    run = jax.jit(_trajectory, static_argnames=("solver_iterations", "steps", "step"))
    reference, force = run(model, TORQUE, None)
    assert float(force) > 10
    plain, _ = run(model, TORQUE, None, step=lambda m, d, _: mjx.step(m, d))
    np.testing.assert_array_equal(reference, plain)
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


def test_implicit_gradient_on_a_constrained_segment_matches_central_differences(tight):
    """The elbow held on its joint limit for 0.3 s (an active constraint row throughout): the reverse-mode gradient
    with respect to a torque gain and the hand's mass, through MJX's own solver (50 iterations, tolerance 1e-10),
    equals central differences to 1e-6 relative."""
    qpos0, torque = AT_LIMIT

    def loss(theta):
        qpos, force = _trajectory(_with_mass(tight, theta[1]), theta[0] * torque, None, qpos0, 60)
        return jnp.sum(qpos**2), force

    theta = jnp.array([1.0, 1.0])
    grad, force = jax.jit(jax.grad(loss, has_aux=True))(theta)
    assert float(force) > 0.5  # the limit pushes back
    value = jax.jit(lambda th: loss(th)[0])
    eps = 1e-6
    fd = np.array([(value(theta + eps * e) - value(theta - eps * e)) / (2 * eps) for e in np.eye(2)])
    assert np.all(np.abs(fd) > 1e-3)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


@pytest.mark.slow
def test_implicit_gradients_through_contact_and_limit(tight):
    """0.8 s in which the hand strikes the wall and slides on it (contact rows switching on and off): reverse and
    forward mode through MJX's own solver agree to 1e-10, equal the fixed count's gradient once its iterations
    converge (16 per step), and central differences to 1e-6; a free swing (no active row) likewise."""

    def loss(theta, solver_iterations, qpos0=None):
        qpos, _ = _trajectory(_with_mass(tight, theta[1]), theta[0] * TORQUE, solver_iterations, qpos0)
        return jnp.sum(qpos[:, 0] ** 2)

    theta = jnp.array([1.0, 1.0])
    reverse = jax.jit(jax.grad(lambda th: loss(th, None)))(theta)
    forward = jax.jit(jax.jacfwd(lambda th: loss(th, None)))(theta)
    unrolled = jax.jit(jax.grad(lambda th: loss(th, 16)))(theta)
    value = jax.jit(lambda th: loss(th, None))
    eps = 1e-6
    fd = np.array([(value(theta + eps * e) - value(theta - eps * e)) / (2 * eps) for e in np.eye(2)])
    assert np.all(np.abs(fd) > 1)
    np.testing.assert_allclose(reverse, forward, rtol=1e-10)
    np.testing.assert_allclose(reverse, unrolled, rtol=1e-10)
    np.testing.assert_allclose(reverse, fd, rtol=1e-6)
    swing = jax.jit(jax.grad(lambda th: loss(th, None, jnp.array([0.3, 0.2]))))(-theta)
    swing_value = jax.jit(lambda th: loss(th, None, jnp.array([0.3, 0.2])))
    swing_fd = np.array([(swing_value(-theta + eps * e) - swing_value(-theta - eps * e)) / (2 * eps)
                         for e in np.eye(2)])  # fmt: skip
    np.testing.assert_allclose(swing, swing_fd, rtol=1e-6)


@pytest.mark.slow
def test_elliptic_cone_and_vmap(tight):
    """The contact's elliptic friction cone (its curvature enters the solver's Hessian): reverse mode equals forward
    mode, and a vmapped batch of gains equals the loop over them."""
    model = tight.replace(opt=tight.opt.replace(cone=mujoco.mjtCone.mjCONE_ELLIPTIC))

    def loss(gain):
        return jnp.sum(_trajectory(model, gain * TORQUE, None)[0][:, 0] ** 2)

    gains = jnp.array([0.9, 1.0, 1.1])
    batched = jax.jit(jax.vmap(jax.grad(loss)))(gains)
    forward = jax.jit(jax.vmap(lambda g: jax.jvp(loss, (g,), (1.0,))[1]))(gains)
    looped = np.array([jax.jit(jax.grad(loss))(g) for g in gains])
    np.testing.assert_allclose(batched, forward, rtol=1e-9)
    np.testing.assert_allclose(batched, looped, rtol=1e-12)


def test_solver_iterations_zero_is_none_and_bad_ones_are_refused(arm):
    _, model = arm
    assert common.check_solver_iterations(0) is None and common.check_solver_iterations(None) is None
    assert common.check_solver_iterations(np.int64(3)) == 3
    data = common.initial_data(model, jnp.float64)
    for bad in (-1, 2.0, True, "4"):
        with pytest.raises(ValueError, match="solver_iterations must be None or 0"):
            common.step(model, data, bad)
