"""Your own robot in MJX (jaxobs.mjx.robot): names, mismatch, linearisation against MuJoCo's finite differences,
an LQG closed loop on the shipped payload cart, and gradients of a rollout (reverse and forward mode)."""

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jaxobs import design
from jaxobs.lti import ss
from jaxobs.mjx import robot as rb
from jaxobs.papers.robot_tuning import LQG, lqg_params
from jaxobs.papers.shipped import ROBOTS

XML = ROBOTS / "cartpole_payload.xml"
NOISE = np.array([0.002, 0.005])
STEPS = 250  # 5 s at 20 ms


@pytest.fixture(scope="module")
def cart():
    return rb.make_robot(XML, ["push"], ["cart_position", "pole_angle"], substeps=2, dead_time=1, sensor_noise=NOISE)


def _lqg(cart):
    """LQG on the nominal linearisation: the cart position follows r."""
    lin = rb.linearize(cart)
    L, _, _ = design.dlqr(lin.Phi, lin.Gamma, jnp.diag(jnp.array([10.0, 10.0, 1.0, 1.0, 0.0])), 0.01 * jnp.eye(1))
    N = design.reference_gain(ss(lin.Phi, lin.Gamma, lin.C[:1], dt=lin.dt), L)
    Q = jnp.diag(jnp.array([1e-6, 1e-6, 1e-4, 1e-4, 0.0]))
    return lqg_params(lin, Q, jnp.diag(jnp.asarray(NOISE) ** 2), L, N)


def test_unknown_names_are_errors_that_list_the_valid_ones(cart):
    with pytest.raises(ValueError, match="unknown actuator 'pusher'.*'push'"):
        rb.make_robot(XML, ["pusher"], ["cart_position"])
    with pytest.raises(ValueError, match="unknown sensor 'tip'.*'cart_position', 'pole_angle'"):
        rb.make_robot(XML, ["push"], ["tip"])
    with pytest.raises(ValueError, match="unknown body 'load'.*'payload'"):
        rb.mismatch(cart.model, {"body_mass[load]": 2.0})
    with pytest.raises(ValueError, match="unknown joint 'elbow'.*'slider', 'hinge'"):
        rb.mismatch(cart.model, {"dof_damping[elbow]": 2.0})
    with pytest.raises(ValueError, match="'body_mas' is not a scalable model field.*body_mass"):
        rb.mismatch(cart.model, {"body_mas[payload]": 2.0})
    with pytest.raises(ValueError, match="sensor_noise must be a scalar or have shape \\(2,\\)"):
        rb.make_robot(XML, ["push"], ["cart_position", "pole_angle"], sensor_noise=[0.1, 0.1, 0.1])
    with pytest.raises(ValueError, match="substeps must be an integer >= 1"):
        rb.make_robot(XML, ["push"], ["cart_position"], substeps=0)


def test_free_joints_and_acceleration_sensors_are_refused():
    free = '<mujoco><worldbody><body><freejoint/><geom size="0.1" mass="1"/></body></worldbody></mujoco>'
    with pytest.raises(ValueError, match="nq == nv"):
        rb.make_robot(free, ["a"], ["s"])
    acc = XML.read_text().replace("</sensor>", '<jointactuatorfrc name="f" joint="slider"/></sensor>')
    with pytest.raises(ValueError, match="sensor 'f' is of the acceleration stage"):
        rb.make_robot(acc, ["push"], ["f"])


def test_mismatch_scales_the_named_rows_and_vmaps(cart):
    model = cart.model
    payload = mujoco.mj_name2id(mujoco.MjModel.from_xml_path(str(XML)), mujoco.mjtObj.mjOBJ_BODY, "payload")
    scales = jnp.array([0.5, 1.0, 2.0])
    batch = jax.vmap(lambda s: rb.mismatch(model, {"body_mass[payload]": s, "dof_damping[hinge]": 2 * s,
                                                   "actuator_gear": s}))(scales)  # fmt: skip
    expected = np.repeat(np.asarray(model.body_mass)[None], 3, 0)
    expected[:, payload] *= np.asarray(scales)
    np.testing.assert_allclose(batch.body_mass, expected)
    np.testing.assert_allclose(batch.dof_damping[:, 1], 2 * scales * model.dof_damping[1])
    np.testing.assert_allclose(batch.dof_damping[:, 0], model.dof_damping[0])
    np.testing.assert_allclose(batch.actuator_gear, scales[:, None, None] * model.actuator_gear[None])


@pytest.mark.slow  # ~15 s: MJX derivatives in both libraries
def test_linearize_matches_mujoco_finite_differences(cart):
    """Phi, Gamma, C by jax.jacfwd of mjx.step against MuJoCo's own centred finite differences
    (mjd_transitionFD) chained over the two physics steps, at a point off the equilibrium."""
    qpos, ctrl = np.array([0.1, 0.4]), np.array([1.5])
    with pytest.warns(RuntimeWarning, match="not an equilibrium"):
        lin = rb.linearize(cart, qpos0=qpos, qvel0=np.array([0.2, -0.3]), ctrl0=ctrl)
    m = mujoco.MjModel.from_xml_path(str(XML))
    data = mujoco.MjData(m)
    data.qpos[:], data.qvel[:], data.ctrl[:] = qpos, [0.2, -0.3], ctrl
    A, B, C = np.zeros((4, 4)), np.zeros((4, 1)), np.zeros((m.nsensordata, 4))
    mujoco.mjd_transitionFD(m, data, 1e-7, True, A, B, C, None)
    # the second physics step starts elsewhere: its Jacobians at the state after the first step
    mujoco.mj_step(m, data)
    A2, B2 = np.zeros((4, 4)), np.zeros((4, 1))
    mujoco.mjd_transitionFD(m, data, 1e-7, True, A2, B2, None, None)
    assert lin.Phi.shape == (5, 5) and lin.Gamma.shape == (5, 1) and lin.C.shape == (2, 5)
    np.testing.assert_allclose(lin.Phi[:4, :4], A2 @ A, atol=1e-6)
    np.testing.assert_allclose(lin.Phi[:4, 4:], A2 @ B + B2, atol=1e-6)  # the command in flight acts next period
    np.testing.assert_allclose(lin.C[:, :4], C, atol=1e-6)
    np.testing.assert_array_equal(lin.Gamma[:, 0], [0, 0, 0, 0, 1])
    np.testing.assert_array_equal(lin.Phi[4], 0)


ARM = ROBOTS / "arm_on_table.xml"


def test_holding_ctrl_holds_a_pose_and_linearize_warns_about_one_it_does_not():
    """The arm raised against gravity: the control of holding_ctrl leaves it at rest (qacc = 0 in MuJoCo), the
    linearisation about it is silent, the one without it warns naming the drifting joint; an unactuated joint
    under load (the payload cart's hinge) or a control outside ctrlrange cannot hold."""
    pose = np.array([0.3, 0.5])
    ctrl = rb.holding_ctrl(ARM, pose)
    m = mujoco.MjModel.from_xml_path(str(ARM))
    data = mujoco.MjData(m)
    data.qpos[:], data.ctrl[:] = pose, ctrl
    mujoco.mj_forward(m, data)
    np.testing.assert_allclose(data.qacc, 0.0, atol=1e-9)
    arm = rb.make_robot(ARM, ["shoulder_motor", "elbow_motor"], ["shoulder_angle", "elbow_angle"], qpos0=pose,
                        ctrl0=ctrl, solver_iterations=4)  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lin = rb.linearize(arm)
    assert (lin.Phi.shape, lin.Gamma.shape, lin.C.shape) == ((4, 4), (4, 2), (2, 4))
    assert lin.Phi is lin.A and lin.Gamma is lin.B
    with pytest.warns(RuntimeWarning, match=r"changes qvel\[1\] \(joint 'elbow'\).*holding_ctrl"):
        rb.linearize(arm, ctrl0=np.zeros(2))
    with pytest.raises(ValueError, match="cannot hold this pose.*joint 'hinge'"):
        rb.holding_ctrl(XML, [0.0, 0.3])
    limited = ARM.read_text().replace('gear="1"/>', 'gear="1" ctrlrange="-1 1"/>')
    with pytest.raises(ValueError, match="outside ctrlrange: 'shoulder_motor' needs 1.923"):
        rb.holding_ctrl(limited, pose)


@jax.jit
def _runs(cart, params, payload, keys):
    """The cart moved by 0.5 m under the LQG, one rollout per payload factor and noise key (vmapped)."""
    reference = jnp.full((STEPS, 1), 0.5)
    one = lambda s, k: rb.rollout(cart, LQG, params, {"body_mass[payload]": s}, k, STEPS, reference=reference)
    return jax.vmap(one)(payload, keys)


@pytest.mark.slow  # MJX closed-loop compile
def test_lqg_on_the_linearisation_moves_the_cart_for_any_payload(cart):
    """The LQG designed on the nominal linearisation (0.5 kg payload, one period of dead time) brings the cart to
    the 0.5 m set-point with the pole still for a 4x lighter and a 2x heavier payload; the sensor noise the
    controller read has the robot's standard deviations."""
    payload = jnp.array([0.25, 1.0, 2.0])
    out = _runs(cart, _lqg(cart), payload, jax.random.split(jax.random.PRNGKey(0), 3))
    assert out.x.shape == (3, STEPS, 4) and out.u.shape == (3, STEPS, 1) and out.y.shape == (3, STEPS, 2)
    final = np.asarray(out.x[:, -10:])
    assert np.all(np.abs(final[..., 0] - 0.5) < 0.01), final[..., 0]
    assert np.all(np.abs(final[..., 1]) < 0.01), final[..., 1]
    assert np.max(np.abs(out.x[..., 1])) > 0.02  # the move swings the pole: the loop did something
    assert not np.allclose(out.x[0, :, 1], out.x[2, :, 1], atol=1e-3)  # the payloads differ in the plants
    np.testing.assert_array_equal(out.applied[:, 1:], out.u[:, :-1])  # one period of dead time
    np.testing.assert_array_equal(out.applied[:, 0], 0.0)
    noise = np.asarray(out.y - out.y_true).reshape(-1, 2)
    np.testing.assert_allclose(noise.std(axis=0), NOISE, rtol=0.15)


def _cost(cart, params, gain):
    """Mean squared cart error and pole angle of one rollout (2x payload) as a function of a feedback gain."""
    L = params.L.at[0, 1].multiply(gain)
    reference = jnp.full((60, 1), 0.5)
    out = rb.rollout(cart, LQG, dataclasses.replace(params, L=L), {"body_mass[payload]": 2.0},
                     jax.random.PRNGKey(1), 60, reference=reference)  # fmt: skip
    return jnp.mean((out.x[:, 0] - 0.5) ** 2 + out.x[:, 1] ** 2)


@pytest.mark.slow
def test_rollout_gradient_reverse_equals_forward_and_finite_differences(cart):
    params = _lqg(cart)
    f = jax.jit(lambda g: _cost(cart, params, g))
    reverse = jax.jit(jax.grad(lambda g: _cost(cart, params, g)))(1.0)
    _, forward = jax.jit(lambda g: jax.jvp(lambda a: _cost(cart, params, a), (g,), (1.0,)))(1.0)
    eps = 1e-5
    fd = (f(1.0 + eps) - f(1.0 - eps)) / (2 * eps)
    np.testing.assert_allclose(reverse, forward, rtol=1e-9)
    np.testing.assert_allclose(reverse, fd, rtol=1e-5)
    assert abs(float(reverse)) > 0


@pytest.mark.slow
def test_a_joint_limit_needs_a_fixed_solver_count_for_reverse_mode():
    """The payload cart with a limit on its rail, which the rollout reaches: reverse mode raises in MJX's solver
    loop; with ``solver_iterations=4`` it equals forward mode through that loop, and the rollout equals the one
    with the solver run to its tolerance."""
    xml = XML.read_text().replace('<flag contact="disable" constraint="disable"/>', "")
    xml = xml.replace('damping="0.5"/>', 'damping="0.5" range="-0.3 0.3" limited="true"/>')
    kwargs = dict(substeps=2, dead_time=1, sensor_noise=NOISE)
    cart = rb.make_robot(xml, ["push"], ["cart_position", "pole_angle"], **kwargs)
    fixed = rb.make_robot(xml, ["push"], ["cart_position", "pole_angle"], **kwargs, solver_iterations=4)
    params = _lqg(cart)
    with pytest.raises(ValueError, match="Reverse-mode differentiation does not work for lax.while_loop"):
        jax.eval_shape(jax.grad(lambda g: _cost(cart, params, g)), 1.0)
    reverse = jax.jit(jax.grad(lambda g: _cost(fixed, params, g)))(1.0)
    _, forward = jax.jit(lambda g: jax.jvp(lambda a: _cost(cart, params, a), (g,), (1.0,)))(1.0)
    np.testing.assert_allclose(reverse, forward, rtol=1e-8)
    run = lambda robot: rb.rollout(robot, LQG, params, None, jax.random.PRNGKey(1), 60,
                                   reference=jnp.full((60, 1), 0.5)).x  # fmt: skip
    exact, counted = jax.jit(lambda: run(cart))(), jax.jit(lambda: run(fixed))()
    assert float(jnp.max(exact[:, 0])) > 0.29  # the cart reaches its limit
    np.testing.assert_allclose(counted, exact, atol=1e-10)


@pytest.mark.slow
def test_docstring_examples_run():
    import doctest

    result = doctest.testmod(rb, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted >= 2 and result.failed == 0
