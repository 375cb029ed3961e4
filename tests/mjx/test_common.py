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
from jaxobs.papers.shipped import ROBOTS

ARM = ROBOTS / "arm_on_table.xml"
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


def _gradient_and_central_differences(loss, theta, eps=1e-6):
    """The reverse-mode gradient of ``loss`` (``theta -> (value, aux)``) at ``theta``, its central differences of
    step ``eps`` and ``aux``, from one compiled ``value_and_grad`` (called at ``theta`` and its ``2 n`` neighbours)."""
    evaluate = jax.jit(jax.value_and_grad(loss, has_aux=True))
    (_, aux), grad = evaluate(theta)
    steps = eps * np.eye(theta.size)
    fd = np.array([(evaluate(theta + e)[0][0] - evaluate(theta - e)[0][0]) / (2 * eps) for e in steps])
    return grad, fd, aux


def test_implicit_gradient_on_a_constrained_segment_matches_central_differences(tight):
    """The elbow held on its joint limit for 0.3 s (an active constraint row throughout): the reverse-mode gradient
    with respect to a torque gain and the hand's mass, through MJX's own solver (50 iterations, tolerance 1e-10),
    equals central differences to 1e-6 relative."""
    qpos0, torque = AT_LIMIT

    def loss(theta):
        qpos, force = _trajectory(_with_mass(tight, theta[1]), theta[0] * torque, None, qpos0, 60)
        return jnp.sum(qpos**2), force

    grad, fd, force = _gradient_and_central_differences(loss, jnp.array([1.0, 1.0]))
    assert float(force) > 0.5  # the limit pushes back
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


@pytest.mark.slow
def test_a_step_reads_only_its_state_fields_and_passes_some_through(arm):
    """The premise of the Jacobian rule: a step's output depends on ``STATE_FIELDS`` only (JAX's own vjp gives every
    other field of the input a zero cotangent, but for those MJX does not write here, which the output copies) and
    leaves the ``PASSED`` ones as they are (time advanced by dt)."""
    _, model = arm
    data = common.initial_data(model, jnp.float64).replace(qpos=jnp.array([-0.77, 0.0]), ctrl=TORQUE)
    data = common.step(model, data)  # every computed field filled in
    saved, common.JACOBIAN_MAX = common.JACOBIAN_MAX, 0
    try:
        out, pullback = jax.vjp(lambda d: common.step(model, d), data)
        ones = jax.tree.map(lambda x: jnp.ones_like(x) if jnp.issubdtype(x.dtype, jnp.floating) else None, out)
        cotangent = pullback(jax.tree.map(lambda x, o: o if o is not None else np.zeros(x.shape, jax.dtypes.float0),
                                          out, ones))[0]  # fmt: skip
    finally:
        common.JACOBIAN_MAX = saved
    unwritten = []
    for (path, leaf), before, after in zip(jax.tree_util.tree_flatten_with_path(cotangent)[0],
                                           jax.tree.leaves(data), jax.tree.leaves(out), strict=True):  # fmt: skip
        if path[0].name not in common.STATE_FIELDS and leaf.dtype != jax.dtypes.float0 and np.any(np.asarray(leaf)):
            np.testing.assert_array_equal(after, before)  # a field MJX never writes (qfrc_fluid): identity, no physics
            np.testing.assert_array_equal(leaf, 1.0)
            unwritten.append(path[0].name)
    assert set(unwritten) == {"qfrc_fluid", "qfrc_inverse", "_impl"}  # _impl: cacc, cfrc_int, ... (no sensor uses them)
    assert np.any(np.asarray(cotangent.qpos)) and np.any(np.asarray(cotangent.ctrl))
    for name in common.PASSED:
        if name != "time":
            np.testing.assert_array_equal(getattr(out, name), getattr(data, name))
    assert float(out.time - data.time) == pytest.approx(float(model.opt.timestep))


def _one_dof_loss():
    """``(theta, scale) -> loss``: 30 steps of the 1-DOF plant from ``(qpos, qvel) = theta[:2]`` under the control
    ``theta[2]``, its damping scaled by ``scale`` (3 differentiated entries per step: the Jacobian rule)."""
    from jaxobs.mjx import force_1dof

    model = force_1dof.load_model()[1]

    def loss(theta, scale):
        plant = model.replace(dof_damping=model.dof_damping * scale)
        data = common.initial_data(plant, jnp.float64).replace(qpos=theta[:1], qvel=theta[1:2])

        def body(d, _):
            d = common.step(plant, d.replace(ctrl=theta[2:]))
            return d, d.qpos[0]

        return jnp.sum(jax.lax.scan(body, data, None, length=30)[1] ** 2)

    return loss


THETA = jnp.array([[0.3, -1.0, 2.0], [0.1, 0.5, -1.0]])


def test_jacobian_rule_matches_central_differences():
    """Reverse mode by the Jacobian rule equals central differences (forward mode, JAX's transpose and ``vmap``: the
    slow test below)."""
    loss = _one_dof_loss()
    grad, fd, _ = _gradient_and_central_differences(lambda th: (loss(th, 1.0), None), THETA[0])
    assert np.all(np.abs(fd) > 1e-3)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


@pytest.mark.slow
def test_jacobian_rule_equals_forward_mode_and_jax_transpose_and_steps_aside_for_a_model_field():
    """The Jacobian rule equals forward mode and JAX's transpose of the step, ``vmap`` equals the loop, and with a
    model field differentiated the rule steps aside (JAX's transpose; equal to forward mode)."""
    loss = _one_dof_loss()
    rule = jax.jit(jax.vmap(jax.grad(loss), in_axes=(0, None)))(THETA, 1.0)
    forward = jax.jit(jax.vmap(jax.jacfwd(loss), in_axes=(0, None)))(THETA, 1.0)
    np.testing.assert_allclose(rule, forward, rtol=1e-12, atol=1e-15)
    saved, common.JACOBIAN_MAX = common.JACOBIAN_MAX, 0
    try:
        transposed = jax.jit(jax.vmap(jax.grad(loss), in_axes=(0, None)))(THETA, 1.0)
    finally:
        common.JACOBIAN_MAX = saved
    np.testing.assert_allclose(rule, transposed, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(rule[1], jax.jit(jax.grad(loss))(THETA[1], 1.0), rtol=1e-13)
    both = jax.jit(jax.grad(loss, argnums=(0, 1)))(THETA[0], 1.0)
    np.testing.assert_allclose(both[0], rule[0], rtol=1e-12)
    np.testing.assert_allclose(both[1], jax.jit(jax.jacfwd(loss, argnums=1))(THETA[0], 1.0), rtol=1e-10)


def test_solver_iterations_zero_is_none_and_bad_ones_are_refused(arm):
    _, model = arm
    assert common.check_solver_iterations(0) is None and common.check_solver_iterations(None) is None
    assert common.check_solver_iterations(np.int64(3)) == 3
    data = common.initial_data(model, jnp.float64)
    for bad in (-1, 2.0, True, "4"):
        with pytest.raises(ValueError, match="solver_iterations must be None or 0"):
            common.step(model, data, bad)
