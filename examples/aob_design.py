# slow: three steady-state designs, their margins and three 2500-step closed loops (about 35 s of CPU)
"""AOB design guide: Cortesão 2006 Example 1 (robot force control), from the plant to margins and a closed loop."""

# --8<-- [start:plant]
import jax
import jax.numpy as jnp

import jaxobs as jo
from jaxobs.observers import active

jax.config.update("jax_enable_x64", True)  # the AOB designs (Q entries of 1e-12 next to 1e-3) need float64

# Ks / (s (1 + Tp s)) e^{-s Td}: Ks = 3 N/mm, Tp = 32 ms, sampled at h = 8 ms with Td = 5 h of dead time
plant = jo.force_plant(3.0, 0.032, 0.008, 0.040)  # states [F, dF/dt, u_{k-5}, ..., u_{k-1}]
L_r = jo.critically_damped_gain(plant, tau_c=0.32)  # double pole at exp(-h / tau_c), the rest at 0 (eq. 83)
print(plant.A.shape, [round(float(v), 4) for v in L_r[0, :3]])  # prints: (7, 7) [0.1148, -0.0717, -0.0615]
# --8<-- [end:plant]

# --8<-- [start:design]
R = 2.1e-2  # N^2, the force sensor's noise variance
designs = {}
for order in (1, 2, 3):
    q_active = active.evolution_variance(1e-3, order, c=1 / 500)  # Theorem 1 / eq. 55 (Table I's values)
    aob = jo.make_aob(plant, order, R, q_plant=1e-12, q_active=q_active, steady_state=True)  # DARE gains
    designs[f"AOB-{order}"] = jo.FeedbackParams(aob, jo.feedback_gain(aob, L_r))  # u = r - L_r x_r - p (eq. 49-50)
    print(f"AOB-{order}: q_active {float(q_active):.1e}, gain {[round(float(k), 4) for k in aob.gain[:2, 0]]}")
# prints: AOB-1: q_active 1.0e-03, gain [0.096, 0.6049]
# prints: AOB-2: q_active 4.0e-06, gain [0.1285, 1.104]
# prints: AOB-3: q_active 2.4e-08, gain [0.1691, 1.9543]
# --8<-- [end:design]

# --8<-- [start:margins]
for name, params in designs.items():  # the loop broken at the plant input (Cortesão 2006 Theorem 3, eq. 65-66)
    m = jo.stability_margins(jo.loop_transfer(plant, jo.active_observer_controller, params))
    print(f"{name}: gain margin {float(m.gain_margin):.2f}, phase margin {float(m.phase_margin):.1f} deg, "
          f"delay margin {1e3 * float(m.delay_margin):.1f} ms")  # fmt: skip
# prints: AOB-1: gain margin 2.98, phase margin 43.5 deg, delay margin 210.2 ms
# prints: AOB-2: gain margin 1.83, phase margin 24.3 deg, delay margin 68.9 ms
# prints: AOB-3: gain margin 1.49, phase margin 13.3 deg, delay margin 28.7 ms
# --8<-- [end:margins]

# --8<-- [start:simulate]
steps = 2500  # 20 s
t = 0.008 * jnp.arange(steps)
reference = jnp.full(steps, L_r[0, 0] * 10.0)  # r = L_1 F_d: a 10 N force set-point
u = 2 * jnp.sin(jnp.pi * (0.01 + 0.0045 * t) * t) - 0.5 * (t >= 8)  # the disturbance of eq. 81-82 ...
disturbance = u**3 + u**2 - u  # ... at the plant input
noise = jo.measurement_noise(jax.random.PRNGKey(0), steps, R)
for name, params in designs.items():
    trace = jo.simulate(plant, jo.active_observer_controller, params, reference, disturbance=disturbance, noise=noise)
    print(f"{name}: RMS force error {float(jo.rms(trace.y_true[250:, 0] - 10.0)):.2f} N")
# prints: AOB-1: RMS force error 1.43 N
# prints: AOB-2: RMS force error 0.48 N
# prints: AOB-3: RMS force error 0.35 N
# --8<-- [end:simulate]
