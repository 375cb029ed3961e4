"""Getting started: a Kalman filter over recorded data with missing samples, batched and differentiated."""

# --8<-- [start:filter]
import jax
import jax.numpy as jnp

import jaxobs as jo

jax.config.update("jax_enable_x64", True)  # the library is dtype-polymorphic: enable float64 in your program

Phi, C = jnp.array([[1.0, 0.1], [0.0, 1.0]]), jnp.array([[1.0, 0.0]])  # constant velocity, position measured
kf = jo.make_kalman(Phi, C, Q=1e-3 * jnp.eye(2), R=[[0.25]])  # no inputs: no Gamma, no u_prev
y = jnp.sin(0.1 * jnp.arange(200.0))[:, None] + 0.5 * jax.random.normal(jax.random.PRNGKey(1), (200, 1))
y = y.at[50:60].set(jnp.nan)  # missing samples: skipped, counted
state, out = jo.run(jo.kalman_filter, kf, jo.EstimatorInputs(y=y))
print(out.x.shape, int(state.missing))  # prints: (200, 2) 10
# --8<-- [end:filter]

# --8<-- [start:batch]
ys = jnp.stack([y, 2 * y, -y])  # three recordings of the same model: vmap over the leading axis
_, outs = jax.vmap(lambda y: jo.run(jo.kalman_filter, kf, jo.EstimatorInputs(y=y)))(ys)
print(outs.x.shape)  # prints: (3, 200, 2)
# --8<-- [end:batch]
