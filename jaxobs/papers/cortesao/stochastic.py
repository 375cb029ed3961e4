"""Cortesão, Koeppe, Nunes, Hirzinger, "Stochastic Active Observers: active state analysis"
(the stochastic AOB paper), §4: AOB vs CKF force tracking while the contact surface moves.

From 8 s the surface recedes at ``xdot_e = 2 mm/s`` (eq. 48): a constant velocity disturbance at
the plant input. The sensor-based CKF keeps a steady-state force error, printed as
``Delta F_ss ~= 0.6839 Ks xdot_e`` (eq. 50; 4.1034 N for Ks = 3); the AOB-1 removes it. The printed
number is reproduced by the CKF with the sensor-based gain ``K = [1, 0, ..., 0]'`` and the
Example 1 ``L_r``, for which the closed form is ``(1 + Ks L_2 + sum_{i>=3} L_i) / (Ks L_1) Ks xdot_e``.
The tiny-Q CKF of the printed recipe (gamma = 1e-12) has almost zero gain and does not.
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxobs.closed_loop import ideal_response, simulate
from jaxobs.observers import active
from jaxobs.papers._output import pyplot, save_figure, write_reproduction
from jaxobs.papers.cortesao.example1 import sensor_based_ckf
from jaxobs.papers.cortesao.force_control import EXAMPLE1, nominal_design, reference_gain, with_feedback
from jaxobs.papers.scenarios import Reproduction

NAME = "cortesao-stochastic-ramp"

PRINTED_COEFFICIENT = 0.6839  # eq. 50
SURFACE_SPEED = 2.0  # mm/s (xdot_e)
SURFACE_START = 8.0  # s
Q_ACTIVE = 1e-5  # The stochastic AOB paper §4: "Q_k = 1e-5"
GAMMA_OTHER = 1e-12  # The stochastic AOB paper §4: gamma for the other states, beta from eq. 47
FORCE_SETPOINT = 10.0  # N (not printed)
ADAPTIVE_ALPHA = 0.5  # strategy P(|w_k| > |w_{k-1}|) = alpha (eq. 20)
ADAPTIVE_SIGMA_FLOOR = float(np.sqrt(Q_ACTIVE))  # sigma* (§3.1): never less active than Q = 1e-5


def ramp(setup=EXAMPLE1) -> dict:
    """Every number of the §4 experiment (arrays as JAX/NumPy values)."""
    plant, L_r = nominal_design(setup)
    T = setup.num_steps
    t = jnp.arange(T) * setup.h
    disturbance = jnp.where(t >= SURFACE_START, SURFACE_SPEED, 0.0)
    reference = jnp.full((T,), reference_gain(L_r) * FORCE_SETPOINT)
    desired = ideal_response(plant, L_r, reference)[:, 0]

    q_plant = float(active.deviation_variance(GAMMA_OTHER))
    controllers = {
        "CKF-SBA": sensor_based_ckf(plant, L_r, setup.R),
        "CKF-tiny-Q": with_feedback(active.make_ckf(plant, setup.R, q_plant=q_plant), L_r),
        "AOB-1": with_feedback(active.make_aob(plant, 1, setup.R, q_plant=q_plant, q_active=Q_ACTIVE), L_r),
        "AOB-1-adaptive": with_feedback(active.make_aob(
            plant, 1, setup.R, q_plant=q_plant, q_active=Q_ACTIVE,
            alpha=ADAPTIVE_ALPHA, sigma_floor=ADAPTIVE_SIGMA_FLOOR,
        ), L_r),
    }  # fmt: skip
    controller = active.active_observer_controller
    traces = {name: simulate(plant, controller, params, reference, disturbance=disturbance)
              for name, params in controllers.items()}  # fmt: skip
    force_error = {name: tr.y_true[:, 0] - desired for name, tr in traces.items()}
    settled = t >= setup.duration - 1.0  # last second: steady state
    delta_f_ss = {name: float(jnp.mean(e[settled])) for name, e in force_error.items()}
    after = t >= SURFACE_START
    peak = {name: float(jnp.max(jnp.abs(e[after]))) for name, e in force_error.items()}

    L = np.asarray(L_r).ravel()
    coefficient = (1.0 + setup.Ks * L[1] + L[2:].sum()) / (setup.Ks * L[0])
    adaptive = traces["AOB-1-adaptive"].controller.estimator
    fixed = traces["AOB-1"].controller.estimator
    return {
        "t": t,
        "force_error": force_error,
        "active_state": {k: traces[k].controller.estimator.d[:, 0] for k in ("AOB-1", "AOB-1-adaptive")},
        "surface_speed": SURFACE_SPEED,
        "delta_f_ss_ckf": delta_f_ss["CKF-SBA"],
        "delta_f_ss_ckf_printed": PRINTED_COEFFICIENT * setup.Ks * SURFACE_SPEED,
        "delta_f_ss_coefficient": delta_f_ss["CKF-SBA"] / (setup.Ks * SURFACE_SPEED),
        "delta_f_ss_coefficient_closed_form": float(coefficient),
        "delta_f_ss_coefficient_printed": PRINTED_COEFFICIENT,
        "delta_f_ss_aob": delta_f_ss["AOB-1"],
        "delta_f_ss_aob_adaptive": delta_f_ss["AOB-1-adaptive"],
        "delta_f_ss_ckf_tiny_q": delta_f_ss["CKF-tiny-Q"],
        "delta_f_ss": delta_f_ss,
        "peak_force_error_after_surface_change": peak,
        "adaptive_strategy": {
            "alpha": ADAPTIVE_ALPHA,
            "sigma_floor": ADAPTIVE_SIGMA_FLOOR,
            "q_trace": adaptive.q_active[:, 0],
            "q_min": float(jnp.min(adaptive.q_active)),
            "q_max": float(jnp.max(adaptive.q_active)),
            "alpha_trace": adaptive.alpha[:, 0],
        },
        "fixed_q_strategy": {"q": Q_ACTIVE, "alpha_trace": fixed.alpha[:, 0]},  # eq. 34
    }


def plot(results: dict, out_dir: Path) -> str:
    """Fig. 5 / Fig. 2 analogues: force error of CKF vs AOB (all controllers, then the bounded ones at their own
    scale), active state vs surface speed, and the adaptive strategy's Q_k and implied alpha_k traces; one colour
    per controller in every panel."""
    plt = pyplot()
    t = np.asarray(results["t"])
    errors = {name: np.asarray(err) for name, err in results["force_error"].items()}
    colour = {name: f"C{i}" for i, name in enumerate(errors)}
    printed = results["delta_f_ss_ckf_printed"]
    fig, axes = plt.subplots(5, 1, figsize=(9, 12), sharex=True, layout="constrained")
    bounded = [name for name, err in errors.items() if np.max(np.abs(err)) < 4 * printed]
    for ax, names in ((axes[0], list(errors)), (axes[1], bounded)):
        for name in names:
            ax.plot(t, errors[name], lw=0.9, color=colour[name], label=name)
        ax.axhline(printed, color="k", ls=":", lw=0.8, label="printed CKF ΔF_ss")
        ax.set_ylabel("force error [N]")
        ax.legend(fontsize=8, loc="upper left")
    axes[0].set_title("all controllers (the tiny-Q CKF barely corrects: its error grows with the ramp)", fontsize=9)
    axes[1].set_title("the controllers that settle, at their own scale", fontsize=9)
    surface = np.where(t >= SURFACE_START, results["surface_speed"], 0.0)
    axes[2].plot(t, surface, "k--", lw=0.9, label="surface speed")
    for name, p in results["active_state"].items():
        axes[2].plot(t, np.asarray(p), lw=0.9, color=colour[name], label=f"active state, {name}")
    axes[2].set_ylabel("[mm/s]")
    axes[2].legend(fontsize=8)
    fixed, adaptive = results["fixed_q_strategy"], results["adaptive_strategy"]
    axes[3].semilogy(t, np.asarray(adaptive["q_trace"]), lw=0.9, color=colour["AOB-1-adaptive"],
                     label="Q_k, AOB-1-adaptive")  # fmt: skip
    axes[3].axhline(fixed["q"], color=colour["AOB-1"], ls=":", lw=1.2, label=f"Q, AOB-1 (fixed {fixed['q']:.0e})")
    axes[3].set_ylabel("Q_k (active state)")
    axes[3].legend(fontsize=8)
    axes[4].plot(t, np.asarray(fixed["alpha_trace"]), lw=0.9, color=colour["AOB-1"],
                 label="alpha_k, AOB-1 (fixed Q, eq. 34)")  # fmt: skip
    axes[4].plot(t, np.asarray(adaptive["alpha_trace"]), lw=0.9, color=colour["AOB-1-adaptive"],
                 label="alpha_k, AOB-1-adaptive")  # fmt: skip
    axes[4].set_ylabel("alpha_k")
    axes[4].set_xlabel("time [s]")
    axes[4].legend(fontsize=8)
    fig.suptitle("the stochastic AOB paper §4: AOB vs CKF under a moving surface")
    return save_figure(fig, out_dir, NAME)


def reproduce(out_dir: Path) -> dict:
    """Compute the §4 experiment, write ``cortesao-stochastic-ramp.json`` and the figure."""
    results = ramp()
    figure = plot(results, out_dir)
    summary = {k: v for k, v in results.items() if k not in ("t", "force_error", "active_state")}
    summary["adaptive_strategy"] = {k: v for k, v in results["adaptive_strategy"].items() if not k.endswith("trace")}
    summary["fixed_q_strategy"] = {"q": Q_ACTIVE}
    return write_reproduction(out_dir, NAME, summary, [figure])


REPRODUCTION = Reproduction(
    name=NAME,
    summary=__doc__,
    reproduce=reproduce,
    headline=(
        "delta_f_ss_ckf",
        "delta_f_ss_ckf_printed",
        "delta_f_ss_coefficient",
        "delta_f_ss_aob",
        "delta_f_ss_aob_adaptive",
    ),
)
