# slow: compiles two filters and smoothers and one fit (about 20 s)
"""Nonlinear guide: the EKF and UKF on a hidden pendulum, their likelihood and smoothers, and gravity learned."""

# --8<-- [start:model]
import jax
import jax.numpy as jnp

import jaxobs as jo

jax.config.update("jax_enable_x64", True)

dt = 0.01  # sample time (s)


def f(x, u, t, g=9.81):
    """One Euler step of the pendulum angle'' = -g sin(angle); the state is (angle, rate)."""
    return jnp.array([x[0] + dt * x[1], x[1] - dt * g * jnp.sin(x[0])])


def h(x):
    """Only the sine of the angle is measured (the horizontal position of the bob)."""
    return jnp.sin(x[:1])


Q = 0.1 * jnp.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])  # white-noise torque over dt
R = jnp.array([[0.01]])


def simulate(key, steps=500, start=(1.2, 0.0)):
    """True states from ``start`` and noisy measurements of the model."""
    kw, kv = jax.random.split(key)
    w = jax.random.multivariate_normal(kw, jnp.zeros(2), Q, (steps - 1,))
    x = jax.lax.scan(lambda x, w: (f(x, None, 0.0) + w,) * 2, jnp.array(start), w)[1]
    x = jnp.concatenate([jnp.array([start]), x])
    return x, jnp.sin(x[:, :1]) + jnp.sqrt(R[0, 0]) * jax.random.normal(kv, (steps, 1))


x_true, y = simulate(jax.random.PRNGKey(0))
y = y.at[200:260].set(jnp.nan)  # a gap in the record: 0.6 s without measurements
model = jo.nonlinear_model(f, h, Q, R, x0=[1.0, 0.0], P0=0.5 * jnp.eye(2))
inputs = jo.EstimatorInputs(y=y)
# --8<-- [end:model]

# --8<-- [start:smooth]
rms = lambda x: float(jnp.sqrt(jnp.mean((x[:, 0] - x_true[:, 0]) ** 2)))  # angle error (rad)
filters = {"EKF": (jo.extended_kalman_filter, jo.make_ekf(model)),
           "UKF": (jo.unscented_kalman_filter, jo.make_ukf(model))}  # fmt: skip
for name, (estimator, params) in filters.items():
    filtered, smoothed = jo.smooth(estimator, params, inputs)
    log_p = jo.log_likelihood(estimator, params, inputs)
    print(f"{name}: log p(y) = {log_p:.1f}, angle error "
          f"filtered {rms(filtered.x):.3f}, smoothed {rms(smoothed.x):.3f}")  # fmt: skip
# prints: EKF: log p(y) = 366.5, angle error filtered 0.054, smoothed 0.025
# prints: UKF: log p(y) = 362.8, angle error filtered 0.103, smoothed 0.024
# --8<-- [end:smooth]


# --8<-- [start:fit]
def build(theta):
    """The EKF of the model with gravity theta["g"] and measurement variance exp(theta["log_r"])."""
    f_g = jax.tree_util.Partial(f, g=theta["g"])  # a Partial: gradients reach its bound g
    R_theta = jnp.exp(theta["log_r"]) * jnp.eye(1)
    return jo.make_ekf(jo.nonlinear_model(f_g, h, Q, R_theta, x0=[1.0, 0.0], P0=0.5 * jnp.eye(2)))


theta0 = {"g": 5.0, "log_r": 0.0}  # a poor guess: g = 5, R = 1
result = jo.fit(jo.extended_kalman_filter, build, theta0, inputs, progress=False)
print(f"{result.stopped} after {len(result.loss)} steps: g = {result.theta['g']:.2f}, "
      f"R = {jnp.exp(result.theta['log_r']):.3f}")  # fmt: skip
# prints: converged after 22 steps: g = 10.16, R = 0.010
# --8<-- [end:fit]
