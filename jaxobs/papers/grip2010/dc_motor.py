"""Grip 2010, section 6.8: a DC motor with LuGre friction (Canudas de Wit & Lischinsky 1997), the modified
high-gain observer estimating the static Coulomb friction theta = alpha_0, the cascaded state observer of
section 6.6, and the pure high-gain design (the extended-state observer without the model, g = 0) it is compared
with.

The plant of Table 6.1, gains designed on the unperturbed matrices (section 6.7.1), the parameter law of
Proposition 6.2 with projection; the thesis prints no simulation inputs, so they are chosen here. The plant,
gains and inputs: docs/theory/papers.md.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import ct
from jaxobs.adaptive import Box, InversionLaw
from jaxobs.observers import EstimatorInputs, run
from jaxobs.observers.hgo import hgo_gains, hgo_observer, make_hgo, smooth_abs
from jaxobs.papers._output import pyplot, save_figure, write_reproduction
from jaxobs.papers.scenarios import Reproduction
from jaxobs.scb import scb, scb_arrays

NAME = "grip2010-dc-motor"
TABLE_6_1 = {"J": 0.0023, "sigma_0": 260.0, "sigma_1": 0.6, "alpha_0": 0.28, "alpha_1": 0.05, "alpha_2": 0.176,
             "omega_0": 0.01}  # fmt: skip
POLES_1 = (-1 + 0.2j, -1 - 0.2j, -2 + 0.2j, -2 - 0.2j)
POLES_2 = (-1 + 0.2j, -1 - 0.2j, -2.0)
KAPPA, THRESHOLD, THETA_SET = 0.1, 1.0, (0.05, 1.0)
PRINTED_K = {"observer1": [6, 13, 0, 13], "observer2": [4, 5, 0]}
ESO_EPS = (1.0, 0.5, 0.2, 0.1)
SCALING_EPS = (1.0, 0.5, 0.2)
SIGMAS = (0.0, 1e-3)
DT, SUBSTEPS, DURATION = 1e-3, 10, 20.0


def matrices(sigma_1: float):
    """``(A, B, E, C)`` of the plant with the given sigma_1 (section 6.8; 0 for the design system)."""
    p = TABLE_6_1
    J = p["J"]
    A = np.array([[0, 1, 0], [0, -(p["alpha_2"] + sigma_1) / J, -p["sigma_0"] / J], [0, 1, 0]])
    return A, np.array([[0], [1 / J], [0]]), np.array([[0], [sigma_1 / J], [-1]]), np.array([[1.0, 0, 0]])


def _zeta(omega, alpha_0):
    return alpha_0 + TABLE_6_1["alpha_1"] * jnp.exp(-((omega / TABLE_6_1["omega_0"]) ** 2))


def g_model(v, x, theta):
    """The observer's perturbation model: ``sigma_0 eta a(omega) / zeta(omega, theta)``, ``a`` the smooth |.|."""
    return jnp.atleast_1d(TABLE_6_1["sigma_0"] * x[2] * smooth_abs(x[1], KAPPA) / _zeta(x[1], theta[0]))


def g_exact(v, x, theta):
    """Observer 2's perturbation model: g with the exact ``|omega|``."""
    return jnp.atleast_1d(TABLE_6_1["sigma_0"] * x[2] * jnp.abs(x[1]) / _zeta(x[1], theta[0]))


def theta_star(v, x, phi):
    """The parameter ``theta`` solved from ``phi = g``:
    ``sigma_0 eta a(omega) / phi - alpha_1 exp(-(omega / omega_0)^2)``."""
    return jnp.atleast_1d(TABLE_6_1["sigma_0"] * x[2] * smooth_abs(x[1], KAPPA) / phi[0] - _zeta(x[1], 0.0))


def _plant(x, u, t, alpha_0):
    A, B, E, _ = (jnp.asarray(M) for M in matrices(TABLE_6_1["sigma_1"]))
    phi = TABLE_6_1["sigma_0"] * x[2] * jnp.abs(x[1]) / _zeta(x[1], alpha_0)
    return A @ x + B[:, 0] * jnp.sin(jnp.pi * t) + E[:, 0] * phi


def design():
    """The SCB structures, the gains of both observers and the eps scaling (no simulation)."""
    true, nominal = matrices(TABLE_6_1["sigma_1"]), matrices(0.0)
    ext = lambda A, E, C: (np.block([[A, E], [np.zeros((1, 4))]]), np.vstack([np.zeros((3, 1)), [[1.0]]]),  # noqa: E731
                           np.hstack([C, [[0.0]]]))  # fmt: skip
    s_true = scb_arrays(scb(*ext(true[0], true[2], true[3])))
    s_design = scb(*ext(nominal[0], nominal[2], nominal[3]))
    A, _, E, C = true
    d = (nominal[0], nominal[2], nominal[3])
    obs1 = hgo_gains(A, E, C, POLES_1, 1.0, design=d)
    obs2 = hgo_gains(A, E, C, POLES_2, 1.0, design=d, extended=False)
    scaled = [hgo_gains(A, E, C, POLES_1, eps, design=d) for eps in SCALING_EPS]
    return (
        {
            "design_system": {"scb_dims": s_design.dims, "chain_lengths": s_design.chain_lengths},
            "true_error_system": {
                "scb_dims": s_true.dims,
                "A_aa": s_true.block("aa"),
                "A_aa_formula": "-sigma_0 / sigma_1",
            },  # fmt: skip
            "observer1": {
                "K": obs1.K[:, 0],
                "printed_K": PRINTED_K["observer1"],
                "poles_true_system": _pairs(obs1.poles),
            },
            "observer2": {
                "K": obs2.K[:, 0],
                "printed_K": PRINTED_K["observer2"],
                "poles_true_system": _pairs(obs2.poles),
            },
            "eps_scaling": {
                "eps": list(SCALING_EPS),
                "K": [g.K[:, 0] for g in scaled],
                "slow_poles": [_pairs(sorted(g.poles, key=abs)[:2]) for g in scaled],  # the two of least modulus
            },
        },
        obs1,
        obs2,
    )


def _pairs(values):
    return [[float(np.real(z)), float(np.imag(z))] for z in values]


def truth(alpha_0, sigma, key, duration: float = DURATION):
    """Plant from rest under u = sin(pi t) and its sampled, noisy measurement (traceable in ``alpha_0``, ``sigma``
    and ``key``): ``(t, x, phi, inputs)`` at the ``duration / DT`` samples."""
    steps = int(round(duration / DT))
    t = DT * jnp.arange(steps)
    plant = lambda x, u, time: _plant(x, u, time, alpha_0)  # noqa: E731
    xs = ct.trajectory(plant, jnp.zeros(3), jnp.zeros((steps, 0)), h=DT, substeps=SUBSTEPS)[:-1]
    y = xs[:, :1] + sigma * jax.random.normal(key, (steps, 1), xs.dtype)
    inputs = EstimatorInputs(y=y, u_prev=jnp.sin(jnp.pi * (t - DT))[:, None])  # u_{k-1} = u(t_{k-1})
    phi = TABLE_6_1["sigma_0"] * xs[:, 2] * jnp.abs(xs[:, 1]) / _zeta(xs[:, 1], alpha_0)
    return t, xs, phi, inputs


def observers(K1, K2, inputs):
    """Observer 1 (6.3) with the Proposition 6.2 law and the cascaded observer 2 (section 6.6) on ``inputs``."""
    A, B, E, C = matrices(TABLE_6_1["sigma_1"])
    region = Box(jnp.array([THETA_SET[0]]), jnp.array([THETA_SET[1]]))
    law = InversionLaw(theta_star, adaptation_gain=1.0, threshold=THRESHOLD, region=region, epsilon=0.05)
    params = make_hgo(A, B, E, C, K1, g_model, law=law, theta0=[1.0], K2=K2, g2=g_exact, dt=DT, substeps=SUBSTEPS)
    return run(hgo_observer, params, inputs)[1]


def pure_eso(K, inputs):
    """The extended-state observer without the model (g = 0) with the gain ``K``: its state estimates."""
    A, B, E, C = matrices(TABLE_6_1["sigma_1"])
    params = make_hgo(A, B, E, C, K, lambda v, x, th: jnp.zeros(1), dt=DT, substeps=SUBSTEPS)
    return run(hgo_observer, params, inputs)[1].x


def simulate(obs1_K, obs2_K, eso_Ks, sigma: float, seed: int = 0, duration: float = DURATION):
    """Plant, measurement, observers 1 and 2 and the pure ESOs (stacked ``eso_Ks``) over ``duration``."""
    t, xs, phi, inputs = truth(TABLE_6_1["alpha_0"], sigma, jax.random.PRNGKey(seed), duration)
    out = observers(obs1_K, obs2_K, inputs)
    eso_x = jax.lax.map(lambda K: pure_eso(K, inputs), jnp.asarray(eso_Ks))
    return {"t": t, "x": xs, "y": inputs.y, "phi": phi, "obs": out, "eso_x": eso_x}


def _rms(err, t):
    late = np.asarray(t) > 10.0
    return float(np.sqrt(np.mean(np.asarray(err)[late] ** 2)))


def reproduce(out_dir: Path) -> dict:
    """Design, simulate for both noise levels, write ``grip2010-dc-motor.json`` and the figures."""
    out_dir = Path(out_dir)
    summary, obs1, obs2 = design()
    A, _, E, C = matrices(TABLE_6_1["sigma_1"])
    nominal = matrices(0.0)
    d = (nominal[0], nominal[2], nominal[3])
    eso_Ks = np.stack([hgo_gains(A, E, C, POLES_1, eps, design=d).K for eps in ESO_EPS])
    runs = {}
    for sigma in SIGMAS:
        sim = simulate(obs1.K, obs2.K, eso_Ks, sigma)
        t, omega = sim["t"], sim["x"][:, 1]
        runs[sigma] = sim
        runs[sigma]["summary"] = {
            "sigma": sigma,
            "theta_hat_mean_t_gt_10": float(np.mean(np.asarray(sim["obs"].theta[:, 0])[np.asarray(t) > 10])),
            "theta_true": TABLE_6_1["alpha_0"],
            "rms_omega_error": {
                "observer1": _rms(omega - sim["obs"].x[:, 1], t),
                "observer2": _rms(omega - sim["obs"].x2[:, 1], t),
                "pure_eso": {str(eps): _rms(omega - sim["eso_x"][i, :, 1], t) for i, eps in enumerate(ESO_EPS)},
            },
            "rms_phi_error_observer1": _rms(sim["phi"] - sim["obs"].phi[:, 0], t),
            "finite": bool(np.all(np.isfinite(np.asarray(sim["obs"].x)))),
        }
    summary["simulation"] = runs[1e-3]["summary"]
    summary["simulation_noise_free"] = runs[0.0]["summary"]
    summary["misprints"] = MISPRINTS
    figures = _figures(out_dir, runs[1e-3])
    return write_reproduction(out_dir, NAME, summary, figures)


MISPRINTS = [
    {"where": "section 6.3.2, K_qjq", "printed": "col(Kbar_qj1 / eps^(nbar_q - n_qj + 1), ..., Kbar_qjn / eps^nbar_q)",
     "corrected": "col(Kbar_qj1 / eps, ..., Kbar_qjn / eps^n_qj) (the author's corrigendum)",
     "evidence": "tests/observers/test_hgo_gains.py: only the corrected gains put eps x the fast poles on eig(H_j) for "
                 "chains of different lengths"},
    {"where": "section 6.8.1, SCB with sigma_1 != 0", "printed": "chi_q2' = chi_q2 - K_q2 gamma",
     "corrected": "chi_q2' = chi_q3 - K_q2 gamma (an integrator chain)",
     "evidence": "true_error_system.scb_dims: one zero state and a 3-chain"},
    {"where": "section 6.8.1, parameter law", "printed": "theta_hat = Proj(l Gamma (theta*(v, x_hat, theta_hat) - "
     "theta_hat))", "corrected": "theta_hat' = Proj(l Gamma (theta*(v, x_hat, phi_hat) - theta_hat))",
     "evidence": "theta* is solved from phi = g, so it depends on phi_hat (Proposition 6.2)"},
]  # fmt: skip


def _figures(out_dir: Path, sim) -> list[str]:
    plt = pyplot()
    beside = dict(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)  # legends off the traces
    t = np.asarray(sim["t"])
    names = []
    fig, ax = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    ax[0].plot(t, np.asarray(sim["y"])[:, 0], lw=0.5, label="y (noisy)")
    ax[0].plot(t, np.asarray(sim["x"])[:, 0], lw=1.0, label="Omega")
    ax[0].set_ylabel("rad")
    ax[0].legend(**beside)
    ax[1].plot(t, np.asarray(sim["phi"]), lw=0.8, label="phi")
    ax[1].plot(t, np.asarray(sim["obs"].phi)[:, 0], lw=0.5, label="phi_hat (observer 1)")
    ax[1].set_xlabel("t [s]")
    ax[1].legend(**beside)
    names.append(save_figure(fig, out_dir, "grip2010_dc_motor_measurement"))
    fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    ax[0].plot(t, np.asarray(sim["x"])[:, 1], label="omega")
    ax[0].plot(t, np.asarray(sim["obs"].x)[:, 1], lw=0.6, label="observer 1")
    ax[0].plot(t, np.asarray(sim["obs"].x2)[:, 1], lw=0.6, label="observer 2")
    ax[0].plot(t, np.asarray(sim["eso_x"])[-1, :, 1], lw=0.4, label=f"pure ESO, eps = {ESO_EPS[-1]}")
    ax[0].legend(**beside)
    ax[1].plot(t, np.asarray(sim["x"])[:, 2], label="eta")
    ax[1].plot(t, np.asarray(sim["obs"].x2)[:, 2], lw=0.6, label="observer 2")
    ax[1].legend(**beside)
    ax[2].plot(t, np.asarray(sim["obs"].theta)[:, 0], label="theta_hat")
    ax[2].axhline(TABLE_6_1["alpha_0"], color="k", ls="--", lw=0.8, label="alpha_0")
    ax[2].set_xlabel("t [s]")
    ax[2].legend(**beside)
    names.append(save_figure(fig, out_dir, "grip2010_dc_motor_estimates"))
    return names


__all__ = [
    "NAME",
    "REPRODUCTION",
    "TABLE_6_1",
    "matrices",
    "g_model",
    "theta_star",
    "design",
    "truth",
    "observers",
    "pure_eso",
    "simulate",
    "reproduce",
]

REPRODUCTION = Reproduction(name=NAME, summary=__doc__, reproduce=reproduce)
