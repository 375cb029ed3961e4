"""Your own robot in MJX (jaxobs.mjx.robot): names, mismatch, linearisation against MuJoCo's finite differences (a
floating base with an IMU and a star tracker too), an LQG closed loop on the shipped payload cart, and gradients of a
rollout (reverse and forward mode)."""

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jaxobs import design
from jaxobs.lti import ss
from jaxobs.mjx import estimation
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


FLYER_ACTUATORS = ["thrust_x", "thrust_y", "thrust_z", "torque_x", "torque_y", "torque_z", "shoulder_motor",
                   "elbow_motor"]  # fmt: skip
FLYER_SENSORS = ["accelerometer", "gyro", "position_fix", "star_tracker", "shoulder_angle", "elbow_angle"]


def test_any_mjcf_mjx_simulates_is_a_robot_and_the_rest_is_refused_in_one_line():
    """A floating base with a quaternion sensor and an accelerometer, and a muscle arm: the noise comes from the MJCF,
    the activations at rest follow the control; what MJX cannot simulate is one ValueError naming it."""
    flyer = rb.make_robot("free_flyer.xml", FLYER_ACTUATORS, FLYER_SENSORS)
    assert (flyer.x0.shape, flyer.state_manifold.dim, flyer.sensor_manifold.dim) == ((17,), 16, 14)
    assert flyer.feedthrough and flyer.sensors == tuple(range(15))
    np.testing.assert_allclose(flyer.sensor_noise, [0.02] * 3 + [0.002] * 3 + [0.01] * 3 + [0.005] * 3 + [0.001] * 2)
    ctrl0 = [0.36, 0.23, 0.37, 0.22]
    arm = rb.make_robot("muscle_arm.xml", ["shoulder_flexor", "elbow_flexor"], ["shoulder_angle"],
                        ctrl0=ctrl0)  # fmt: skip
    np.testing.assert_allclose(arm.act0, ctrl0)
    assert not arm.feedthrough and arm.state_manifold.dim == 8
    implicit = XML.read_text().replace('integrator="Euler"', 'integrator="implicit"')
    with pytest.raises(ValueError, match=r"^MJX \(mujoco [\d.]+\) cannot simulate this model: .*IMPLICIT"):
        rb.make_robot(implicit, ["push"], ["cart_position"])
    rk4 = XML.read_text().replace('integrator="Euler"', 'integrator="RK4"')
    rb.make_robot(rk4, ["push"], ["cart_position"])  # no rotations: RK4 differentiates
    flying_rk4 = rb.load_mjcf("free_flyer.xml")
    flying_rk4.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    with pytest.raises(
        ValueError, match="linearize: MJX's RK4 integrator differentiates the rotation of the free joint 'root'"
    ):
        rb.linearize(rb.make_robot(flying_rk4, ["thrust_x"], ["gyro"]))
    with pytest.raises(ValueError, match="MJCF no_such.xml: cannot load it, nor a shipped robot of that name"):
        rb.load_mjcf("no_such.xml")
    assert ROBOTS == estimation.ASSETS  # one folder: the configs' paths and load_mjcf find the same robots


def test_holding_a_muscle_arm_near_a_co_contraction():
    """Muscles pull only: the smallest holding control would push (negative); the one nearest a co-contraction of 0.3
    holds the raised arm at rest (MuJoCo C: qacc = 0, act_dot = 0) within [0, 1]."""
    mjcf, pose = "muscle_arm.xml", np.array([0.3, 0.8])
    with pytest.raises(ValueError, match="outside ctrlrange: 'shoulder_extensor' needs -0.059"):
        rb.holding_ctrl(mjcf, pose)
    ctrl = rb.holding_ctrl(mjcf, pose, near=np.full(4, 0.3))
    assert np.all((ctrl > 0) & (ctrl < 1))
    m = rb.load_mjcf(mjcf)
    data = mujoco.MjData(m)
    data.qpos[:], data.ctrl[:], data.act[:] = pose, ctrl, rb.steady_activation(m, ctrl)
    mujoco.mj_forward(m, data)
    np.testing.assert_allclose(data.qacc, 0.0, atol=1e-9)
    np.testing.assert_allclose(data.act_dot, 0.0, atol=1e-12)
    np.testing.assert_allclose(rb.steady_activation(m, [1.5, -0.2, 0.5, 0.5]), [1.0, 0.0, 0.5, 0.5])


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


def test_mismatch_of_a_free_joint_and_of_the_physics_options():
    """``dof_*[joint]`` scales every degree of freedom of a free joint (six); ``opt.<name>`` scales a physics option;
    a field without objects takes no name."""
    model = rb.make_robot("free_flyer.xml", ["thrust_x"], ["gyro"]).model
    scaled = rb.mismatch(model, {"dof_damping[root]": 3.0, "dof_damping[elbow]": 2.0, "opt.wind": 2.0,
                                 "opt.viscosity": 1.5, "qpos_spring": 1.0})  # fmt: skip
    nominal = np.asarray(model.dof_damping)
    np.testing.assert_allclose(scaled.dof_damping, nominal * np.r_[[3.0] * 6, 1.0, 2.0])
    np.testing.assert_allclose(scaled.opt.viscosity, 1.5 * model.opt.viscosity)
    with pytest.raises(ValueError, match="'opt.timestep' is not a scalable model field"):
        rb.mismatch(model, {"opt.timestep": 2.0})
    with pytest.raises(ValueError, match="'qpos_spring' has no named rows"):
        rb.mismatch(model, {"qpos_spring[root]": 2.0})


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


@pytest.mark.slow  # ~2 min: jax.jacfwd of 4 physics steps and every sensor of the free flyer
def test_floating_base_linearisation_matches_mujoco_finite_differences():
    """The free flyer turned by 0.4 rad, its arm bent: Phi and Gamma in the tangent space (16 directions: a free
    joint's rotation as a 3-vector) against MuJoCo's mjd_transitionFD chained over the four physics steps (which
    differences qpos with mj_differentiatePos: the same coordinates); C against its sensor derivatives; the
    accelerometer's dependence on the command it reads (D, the extra command state) and the star tracker's rotation
    rows against central differences of mj_forward (MuJoCo C)."""
    m = rb.load_mjcf("free_flyer.xml")
    qpos0 = m.qpos0.copy()
    qpos0[3:7], qpos0[7:] = [np.cos(0.2), 0.0, 0.0, np.sin(0.2)], [0.4, -0.6]
    flyer = rb.make_robot(m, FLYER_ACTUATORS, FLYER_SENSORS, substeps=4, qpos0=qpos0)
    lin = rb.linearize(flyer)
    assert (lin.Phi.shape, lin.Gamma.shape, lin.C.shape) == ((24, 24), (24, 8), (14, 24))
    data = mujoco.MjData(m)
    data.qpos[:] = qpos0
    A, B, C = np.zeros((16, 16)), np.zeros((16, 8)), np.zeros((m.nsensordata, 16))
    mujoco.mjd_transitionFD(m, data, 1e-7, True, A, B, C, None)
    np.testing.assert_allclose(lin.Phi[:16, :16], np.linalg.matrix_power(A, 4), atol=1e-7)
    np.testing.assert_allclose(lin.Gamma[:16], sum(np.linalg.matrix_power(A, i) @ B for i in range(4)), atol=1e-7)
    vector_rows, readings = [0, 1, 2, 3, 4, 5, 6, 7, 8, 13, 14], [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 13]
    np.testing.assert_allclose(lin.C[readings, :16], C[vector_rows], atol=1e-7)

    def reading(dq=None, ctrl=None):
        data = mujoco.MjData(m)
        data.qpos[:] = qpos0
        mujoco.mj_integratePos(m, data.qpos, np.zeros(8) if dq is None else dq, 1.0)
        data.ctrl[:] = 0.0 if ctrl is None else ctrl
        mujoco.mj_forward(m, data)
        return data.sensordata.copy()

    eps, y0 = 1e-6, reading()
    D = np.stack([(reading(ctrl=eps * e) - reading(ctrl=-eps * e))[:3] / (2 * eps) for e in np.eye(8)], axis=1)
    np.testing.assert_allclose(lin.C[:3, 16:], D, atol=1e-7)
    np.testing.assert_array_equal(lin.C[3:, 16:], 0.0)  # only the accelerometer reads the command

    def rotation(dq):
        e = np.zeros(3)
        mujoco.mju_subQuat(e, reading(dq)[9:13], y0[9:13])
        return e

    C_rot = np.stack([(rotation(eps * e) - rotation(-eps * e)) / (2 * eps) for e in np.eye(8)], axis=1)
    np.testing.assert_allclose(lin.C[9:12, :8], C_rot, atol=1e-7)


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
def test_reverse_mode_goes_through_a_joint_limit_at_the_models_solver_settings():
    """The payload cart with a limit on its rail, which the rollout reaches: reverse mode through MJX's own solver
    (implicit derivative) equals forward mode, and so does reverse mode through ``solver_iterations=4``, whose
    rollout equals the one with the solver run to its tolerance."""
    xml = XML.read_text().replace('<flag contact="disable" constraint="disable"/>', "")
    xml = xml.replace('damping="0.5"/>', 'damping="0.5" range="-0.3 0.3" limited="true"/>')
    kwargs = dict(substeps=2, dead_time=1, sensor_noise=NOISE)
    cart = rb.make_robot(xml, ["push"], ["cart_position", "pole_angle"], **kwargs)
    fixed = rb.make_robot(xml, ["push"], ["cart_position", "pole_angle"], **kwargs, solver_iterations=4)
    params = _lqg(cart)
    _, forward = jax.jit(lambda g: jax.jvp(lambda a: _cost(cart, params, a), (g,), (1.0,)))(1.0)
    reverse = jax.jit(jax.grad(lambda g: _cost(cart, params, g)))(1.0)
    counted = jax.jit(jax.grad(lambda g: _cost(fixed, params, g)))(1.0)
    np.testing.assert_allclose(reverse, forward, rtol=1e-8)
    np.testing.assert_allclose(counted, forward, rtol=1e-8)
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


def test_qpos_outside_a_joint_range_warns_naming_the_joint_its_type_and_unit():
    m = rb.load_mjcf("arm_on_table.xml")
    with pytest.warns(UserWarning, match=r"^robot.qpos0: hinge joint 'elbow' at -0.5 rad lies outside its range "
                      r"\[-0.3, 1.2\] rad \(MJCF ranges are in degrees unless"):  # fmt: skip
        assert len(rb.warn_outside_joint_ranges(m, [0.2, -0.5], "robot.qpos0")) == 1
    assert (
        rb.warn_outside_joint_ranges(rb.make_robot(m, ["shoulder_motor"], ["elbow_angle"]).model, [0.2, 1.0], "x") == []
    )
