# slow: 4000 closed-loop spectral radii in chunks of 1000 (about 12 s of CPU)
"""Robustness sweep guide: a Monte-Carlo sweep of your own with the engine behind ``jaxobs sweep``."""

# --8<-- [start:design]
import jax
import jax.numpy as jnp
import numpy as np

import jaxobs as jo

jax.config.update("jax_enable_x64", True)

plant = jo.force_plant(3.0, 0.032, 0.008, 0.040)  # the nominal model the AOB-1 is designed on
L_r = jo.critically_damped_gain(plant, tau_c=0.32)
aob = jo.make_aob(plant, 1, 2.1e-2, q_active=1e-3, steady_state=True)
params = jo.FeedbackParams(aob, jo.feedback_gain(aob, L_r))
# --8<-- [end:design]


# --8<-- [start:sweep]
def sampler(key, index):
    """One configuration: a true plant drawn from its own key (log-uniform stiffness, uniform dead time)."""
    k_ks, k_td = jax.random.split(key)
    return {
        "stiffness": jnp.exp(jax.random.uniform(k_ks, minval=jnp.log(0.3), maxval=jnp.log(30.0))),
        "dead_time_samples": jax.random.uniform(k_td, minval=3.0, maxval=8.0),
    }


def evaluate(p):
    """Its metrics: the spectral radius of the loop with model errors (Cortesão 2006 Theorem 2, eq. 59)."""
    true = jo.force_plant(p["stiffness"], 0.032, 0.008, 0.008 * p["dead_time_samples"], n_delay=8)
    rho = jo.spectral_radius(jo.closed_loop_matrix(true, jo.active_observer_controller, params))
    return {"spectral_radius": rho, "stable": rho < 1.0}


jo.run_sweep(sampler, evaluate, 4000, "out/my-sweep", chunk_size=1000, progress=False)  # a rerun resumes
rows = jo.load_results("out/my-sweep")  # {"index", "param.<name>", "metric.<name>"}: one row per configuration
ks, stable = rows["param.stiffness"], rows["metric.stable"]
near = (ks > 2.0) & (ks < 4.5)  # within x1.5 of the nominal 3 N/mm
print(f"stable: {stable.mean():.3f} overall, {stable[near].mean():.3f} within x1.5 of Ks")
# prints: stable: 0.725 overall, 1.000 within x1.5 of Ks
print(f"largest stable stiffness: {np.max(ks[stable]):.1f} N/mm")
# prints: largest stable stiffness: 10.0 N/mm
# --8<-- [end:sweep]
