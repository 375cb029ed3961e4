"""Grip 2010, ch. 9: semiglobal stabilisation of a sandwich system by dynamic output feedback (Grip, Saberi,
Stoorvogel, Wang & Roy), on an instance of this project's choice (the chapter prints no example).

Reported: the detectors of §9.3.1 on four windows (Theorem 9.1, :func:`jaxobs.saturation.sandwich_detectors`),
the low-gain ARE (9.12) over :data:`EPS_FAMILY`, and the three-stage controller from a grid of initial states
(:func:`closed_loop`). The instance and the design: docs/theory/papers.md.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import ct
from jaxobs.papers._output import pyplot, save_figure, write_reproduction
from jaxobs.papers.scenarios import Reproduction
from jaxobs.saturation import CLASSES, low_gain_are, sandwich_design, sandwich_detectors, simulate_sandwich

NAME = "grip2010-sandwich"
SYSTEM = dict(A=[[0.0, 1.0], [0.0, 0.0]], B=[[0.0], [1.0]], C=[[1.0, 0.0]], M=[[-1.0]], N=[[1.0]], G=[[1.0]])
F = [[-1.0, -2.0]]
WINDOW_T, WINDOW_STEPS = 0.5, 1000
WINDOWS = {  # case: (initial chi = (x1, x2, w), expected class)
    "z >= 1": ([3.0, 1.0, 0.2], "positive"),
    "z <= -1": ([-3.0, 1.0, 0.5], "negative"),
    "|z| < 1": ([0.5, -1.0, 0.2], "linear"),
    "z crossing 1": ([1.5, -2.0, 0.2], "mixed"),
}
EPS_FAMILY = (1e-1, 1e-2, 1e-3, 1e-4)
DESIGN = dict(T=0.05, Tbar_intervals=4, rho=1.1, eps=1e-3)
SUBSTEPS, INTERVALS, GRID = 50, 800, 5
STABLE_NORM = 1e-6


def _plant(chi, u, t):
    return jnp.stack([chi[1], u, -chi[2] + jnp.clip(chi[0], -1.0, 1.0)])


@jax.jit
def _window(design, chi0):
    """One window of ``u = 0`` (RK4 at ``WINDOW_T / WINDOW_STEPS``) and its detectors."""
    h = WINDOW_T / WINDOW_STEPS
    chi = ct.trajectory(_plant, chi0, jnp.zeros(WINDOW_STEPS), h=h, substeps=1)
    return chi, sandwich_detectors(design, chi[:, 2:3], jnp.zeros(WINDOW_STEPS + 1), h)


def windows(design) -> list[dict]:
    """The four detector windows: simulated (``u = 0``), classified, compared with the true range of ``z``."""
    out = []
    for case, (chi0, expected) in WINDOWS.items():
        chi, res = _window(design, jnp.asarray(chi0))
        z = np.asarray(chi[:, 0])
        out.append({
            "case": case, "z_min": float(z.min()), "z_max": float(z.max()), "e_plus": float(res.e_plus),
            "e_minus": float(res.e_minus), "e_zero": float(res.e_zero), "classified": CLASSES[int(res.cls)],
            "expected": expected, "correct": CLASSES[int(res.cls)] == expected,
            "e_at_2h": np.asarray(res.coarse),
            "chi_end_error": float(np.max(np.abs(np.asarray(res.chi_end) - np.asarray(chi[-1]))))
            if expected == "linear" else None,
        })  # fmt: skip
    return out


def are_family() -> dict:
    """Norm and smallest eigenvalue of the low-gain ARE solution ``P(eps)`` over :data:`EPS_FAMILY`."""
    P = [np.asarray(low_gain_are(**{k: SYSTEM[k] for k in "ABCMN"}, F=F, eps=e).X) for e in EPS_FAMILY]
    norms = [float(np.linalg.norm(p, 2)) for p in P]
    return {
        "eps": list(EPS_FAMILY),
        "P_norm": norms,
        "P_min_eig": [float(np.linalg.eigvalsh(p)[0]) for p in P],
        "P_norm_over_eps": [n / e for n, e in zip(norms, EPS_FAMILY, strict=True)],
    }


def grid() -> np.ndarray:
    """(GRID**3, 3) initial states ``chi_0``: a regular grid over ``[-5, 5]^2 x [-1, 1]``."""
    g, gw = np.linspace(-5, 5, GRID), np.linspace(-1, 1, GRID)
    return np.array(np.meshgrid(g, g, gw, indexing="ij")).reshape(3, -1).T


def closed_loop(design):
    """The initial states of :func:`grid` and the sandwich closed loop simulated from each (one ``vmap``)."""
    chi0 = grid()
    run = jax.jit(jax.vmap(lambda c: simulate_sandwich(design, c, INTERVALS, substeps=SUBSTEPS)))
    return chi0, run(jnp.asarray(chi0))


def reproduce(out_dir: Path) -> dict:
    """Run the windows, the ARE family and the closed loop; write ``grip2010-sandwich.json`` and the figure."""
    out_dir = Path(out_dir)
    design = sandwich_design(**SYSTEM, F=F, **DESIGN)
    chi0, trace = closed_loop(design)
    stage = np.asarray(trace.stage)
    T = DESIGN["T"]
    final = np.linalg.norm(np.asarray(trace.chi_end)[:, -1], axis=1)
    first = lambda s: np.where((stage == s).any(axis=1), np.argmax(stage == s, axis=1) * T, np.nan)
    t2, t3 = first(2), first(3)
    in3 = stage == 3
    est = np.linalg.norm(np.asarray(trace.chi_end) - np.asarray(trace.chi_hat_end), axis=2)
    summary = {
        "system": SYSTEM,
        "F": F,
        "design": {
            **DESIGN,
            "Tbar": DESIGN["T"] * DESIGN["Tbar_intervals"],
            "alpha": float(design.alpha),
            "h": np.asarray(design.h),
            "substeps": SUBSTEPS,
            "horizon_s": INTERVALS * T,
            "K": np.asarray(design.K),
        },  # fmt: skip
        "detectors": windows(design),
        "low_gain_are": are_family(),
        "closed_loop": {
            "n_initial_conditions": int(chi0.shape[0]),
            "box": "|x1| <= 5, |x2| <= 5, |w| <= 1 (5 x 5 x 5 grid)",
            "stabilised_fraction": float(np.mean(final < STABLE_NORM)),
            "stabilised_means": f"||chi|| < {STABLE_NORM} at t = {INTERVALS * T} s",
            "max_final_norm": float(final.max()),
            "stage_switch_times": {
                "stage2_start_s": {
                    "min": float(np.nanmin(t2)),
                    "median": float(np.nanmedian(t2)),
                    "max": float(np.nanmax(t2)),
                    "never": int(np.isnan(t2).sum()),
                },
                "stage3_start_s": {
                    "min": float(np.nanmin(t3)),
                    "median": float(np.nanmedian(t3)),
                    "max": float(np.nanmax(t3)),
                    "never": int(np.isnan(t3).sum()),
                },
                "per_initial_condition": [[a, b] for a, b in zip(t2.tolist(), t3.tolist(), strict=True)],
            },  # fmt: skip
            "max_estimate_error_stage3": float(est[in3].max()) if in3.any() else None,
            "max_abs_u": float(np.asarray(trace.u_max).max()),
        },
    }
    worst = int(np.nanargmax(t3))
    return write_reproduction(out_dir, NAME, summary, [_figure(out_dir, chi0[worst], trace, worst)])


def _figure(out_dir: Path, chi0, trace, i: int) -> str:
    plt = pyplot()
    T = DESIGN["T"]
    t = T * (np.arange(INTERVALS) + 1)
    chi = np.asarray(trace.chi_end)[i]
    fig, ax = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    ax[0].fill_between(t - T, np.asarray(trace.z_min)[i], np.asarray(trace.z_max)[i], step="post", alpha=0.8,
                       label="z over the window")  # fmt: skip
    ax[0].plot(t, chi[:, 2], label="y = w")
    ax[0].axhline(1, color="k", lw=0.5, ls="--")
    ax[0].axhline(-1, color="k", lw=0.5, ls="--")
    ax[0].set_ylim(-8, 8)
    ax[0].set_ylabel("z, y")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"chi(0) = {np.round(chi0, 2).tolist()}: detector class per window and stage switches",
                    fontsize=10)  # fmt: skip
    ax[1].step(t - T, np.asarray(trace.cls)[i], where="post", color="C1")
    ax[1].set_yticks(range(4), ["z >= 1", "z <= -1", "linear", "mixed"])
    ax[1].set_ylim(-0.5, 3.5)
    ax[1].set_ylabel("detector class")
    ax[2].semilogy(t, np.maximum(np.linalg.norm(chi, axis=1), 1e-16), label="||chi||")
    ax[2].set_xlabel("t [s]")
    ax[2].set_ylabel("||chi||")
    stage = np.asarray(trace.stage)[i]
    for j, k in enumerate(np.flatnonzero(np.diff(stage)) + 1):  # the window after which the stage changed
        for a in ax:
            a.axvline(t[k] - T, color="0.4", lw=0.8, ls=":")
        ax[1].annotate(f"stage {int(stage[k])}", (t[k] - T, 3.5), xytext=(3, -10 - 11 * j), textcoords="offset points",
                       fontsize=8)  # fmt: skip
    for a in ax[:2]:
        a.set_xlim(0, min(t[-1], 15))
    return save_figure(fig, out_dir, "grip2010_sandwich")


__all__ = [
    "NAME",
    "REPRODUCTION",
    "SYSTEM",
    "F",
    "WINDOWS",
    "EPS_FAMILY",
    "DESIGN",
    "windows",
    "are_family",
    "grid",
    "closed_loop",
    "reproduce",
]

REPRODUCTION = Reproduction(name=NAME, summary=__doc__, reproduce=reproduce)
