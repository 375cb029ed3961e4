# slow: the linearisation and one closed-loop rollout compile through mjx.step (about a minute of CPU)
"""Own-robot guide: an MJCF of your robot, its linearisation by jax.jacfwd of mjx.step, an LQG designed on it, and
closed-loop MJX rollouts of the robot with payloads of unknown mass (examples/robots/cartpole_payload.xml)."""

# --8<-- [start:robot]
from pathlib import Path

import jax
import jax.numpy as jnp

import jaxobs as jo
from jaxobs.mjx import robot as rb
from jaxobs.observers import feedback, kalman

jax.config.update("jax_enable_x64", True)

mjcf = Path(__file__).parent / "robots" / "cartpole_payload.xml"  # a cart with a hanging payload (a gantry crane)
cart = rb.make_robot(
    mjcf,
    actuators=["push"],  # the controller's u: the motor force on the cart (N)
    sensors=["cart_position", "pole_angle"],  # its y: these sensordata entries
    substeps=2,  # 2 physics steps of 10 ms: a 20 ms control period
    dead_time=1,  # u_k acts during period k + 1
    sensor_noise=[0.002, 0.005],  # m, rad
)
print(cart.actuators, cart.sensors, cart.period)  # prints: (0,) (0, 1) 0.02
# --8<-- [end:robot]

# --8<-- [start:hold]
arm = Path(__file__).parent / "robots" / "arm_on_table.xml"  # a two-link arm in a vertical plane
pose = [0.3, 0.5]  # shoulder and elbow raised against gravity: not a rest pose without torque
ctrl0 = rb.holding_ctrl(arm, pose)  # the motor torques that hold it (MuJoCo's inverse dynamics)
print(ctrl0.round(3))  # prints: [1.923 0.88 ]
raised = rb.make_robot(arm, ["shoulder_motor", "elbow_motor"], ["shoulder_angle", "elbow_angle"], qpos0=pose,
                       ctrl0=ctrl0, solver_iterations=4)  # fmt: skip
# --8<-- [end:hold]

# --8<-- [start:linearize]
lin = rb.linearize(cart)  # about the operating point (cart at 0, pole hanging, no force)
print(lin.Phi.shape, lin.Gamma.shape, lin.C.shape)  # prints: (5, 5) (5, 1) (2, 5)
L, _, poles = jo.dlqr(lin.Phi, lin.Gamma, jnp.diag(jnp.array([10.0, 10.0, 1.0, 1.0, 0.0])), 0.01 * jnp.eye(1))
N = jo.reference_gain(jo.ss(lin.Phi, lin.Gamma, lin.C[:1], dt=lin.dt), L)  # the cart position follows r
Q = jnp.diag(jnp.array([1e-6, 1e-6, 1e-4, 1e-4, 0.0]))  # no noise on the dead-time slot: it is known
estimator = jo.make_kalman(lin.Phi, lin.C, Q, jnp.diag(cart.sensor_noise**2), Gamma=lin.Gamma, steady_state=True)
params = jo.FeedbackParams(estimator, L, N)
lqg = feedback.observer_controller(kalman.kalman_filter)  # any jaxobs Controller runs in the loop
print(f"closed-loop spectral radius {float(jnp.max(jnp.abs(poles))):.4f}")  # prints: closed-loop spectral radius 0.9703
# --8<-- [end:linearize]

# --8<-- [start:rollout]
steps = 250  # 5 s
reference = jnp.full((steps, 1), 0.5)  # move the cart by 0.5 m


@jax.jit
def move(payload, key):
    """One rollout with the payload's mass scaled by ``payload`` (the controller was designed for 1x)."""
    return rb.rollout(cart, lqg, params, {"body_mass[payload]": payload}, key, steps, reference=reference)


payloads = jnp.array([0.25, 1.0, 2.0])
out = jax.vmap(move)(payloads, jax.random.split(jax.random.PRNGKey(0), 3))  # three plants at once
for scale, x in zip(payloads, out.x, strict=True):
    print(f"payload x{float(scale)}: cart {float(x[-1, 0]):.3f} m after 5 s, largest swing "
          f"{float(jnp.max(jnp.abs(x[:, 1]))):.3f} rad")  # fmt: skip
# prints: payload x0.25: cart 0.499 m after 5 s, largest swing 0.156 rad
# prints: payload x1.0: cart 0.501 m after 5 s, largest swing 0.139 rad
# prints: payload x2.0: cart 0.497 m after 5 s, largest swing 0.128 rad
# --8<-- [end:rollout]
