# slow: compiles several filters and a gradient through one (about 14 s)
"""Filtering guide: time-varying and steady-state Kalman gains, missing data, gradients through the filter."""

# --8<-- [start:model]
import jax
import jax.numpy as jnp

import jaxobs as jo

jax.config.update("jax_enable_x64", True)

h = 0.1  # sample time (s): constant-velocity target, position measured
Phi, C = jnp.array([[1.0, h], [0.0, 1.0]]), jnp.array([[1.0, 0.0]])
q, r = 1e-2, 0.25  # acceleration noise intensity, measurement variance
Q = q * jnp.array([[h**3 / 3, h**2 / 2], [h**2 / 2, h]])  # white-noise acceleration, integrated over h


def simulate(key, steps=500):
    """True states and measurements of the model (process and measurement noise from ``key``)."""
    kw, kv = jax.random.split(key)
    w = jax.random.multivariate_normal(kw, jnp.zeros(2), Q, (steps,))
    x = jax.lax.scan(lambda x, w: (Phi @ x + w, Phi @ x + w), jnp.array([0.0, 1.0]), w)[1]
    return x, x @ C.T + jnp.sqrt(r) * jax.random.normal(kv, (steps, 1))


x_true, y = simulate(jax.random.PRNGKey(0))
# --8<-- [end:model]

# --8<-- [start:filter]
kf = jo.make_kalman(Phi, C, Q, [[r]], x0=jnp.zeros(2), P0=jnp.eye(2))  # time-varying gain (Riccati recursion)
kf_ss = jo.make_kalman(Phi, C, Q, [[r]], x0=jnp.zeros(2), P0=jnp.eye(2), steady_state=True)  # DARE gain
for name, params in (("time-varying", kf), ("steady-state", kf_ss)):
    _, out = jo.run(jo.kalman_filter, params, jo.EstimatorInputs(y=y))
    print(f"{name}: RMS position error {jo.rms(out.x[100:, 0] - x_true[100:, 0]):.3f}")
# prints: time-varying: RMS position error 0.177
# prints: steady-state: RMS position error 0.177
print(f"measurement noise alone: {jo.rms(y[100:, 0] - x_true[100:, 0]):.3f}")
# prints: measurement noise alone: 0.525
# --8<-- [end:filter]

# --8<-- [start:missing]
gappy = y.at[200:260].set(jnp.nan)  # a 6 s dropout: predicted through, counted
state, out = jo.run(jo.kalman_filter, kf, jo.EstimatorInputs(y=gappy))
print(int(state.missing), f"{jo.rms(out.x[200:260, 0] - x_true[200:260, 0]):.2f}")  # prints: 60 0.15
# --8<-- [end:missing]


# --8<-- [start:grad]
def innovation_score(log_q):
    """Mean squared one-step prediction error (innovation) for the process-noise intensity exp(log_q)."""
    params = jo.make_kalman(Phi, C, jnp.exp(log_q) / q * Q, [[r]], x0=jnp.zeros(2), P0=jnp.eye(2))
    _, out = jo.run(jo.kalman_filter, params, jo.EstimatorInputs(y=y))
    return jnp.mean(out.innovation[50:] ** 2)


step = jax.jit(jax.value_and_grad(innovation_score))  # the gradient runs back through the Riccati recursion
log_q = jnp.log(1e-4)  # start 100 times too small
for _ in range(40):
    score, slope = step(log_q)
    log_q = log_q - 50.0 * slope
print(f"q = {jnp.exp(log_q):.1e} (the data's: {q:.0e}), score {score:.4f}")
# prints: q = 4.2e-03 (the data's: 1e-02), score 0.2910
# --8<-- [end:grad]
