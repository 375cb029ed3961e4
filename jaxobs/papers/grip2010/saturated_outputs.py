"""Grip 2010, section 8.5: global stabilisation of a MIMO system with saturated outputs (Grip, Saberi & Wang).

The example exactly as printed: ``x1' = x2 + x3``, ``x2' = u1``, ``x3' = u2``, ``y1 = sat(x1)``, ``y2 = sat(x1 +
x2)``, T = 0.5, rho = 1.1, ``h_i = C_i'``, ``x(0) = (2, -4, 1)``, under the controller (8.2)-(8.5)
(:func:`jaxobs.saturation.simulate_saturated_outputs`, 500 RK4 steps per interval, 10 intervals). The thesis prints
the outcome in words (Fig. 8.1): ``y1`` out of saturation in the first interval, ``y2`` in the fifth (``y1``
saturated again there), deadbeat control in the sixth, the state at rest at the origin for ``t >= 6T = 3 s``.

``alpha = rho ||exp(A T)||`` (8.3) does not name the matrix norm. All four common ones are run; the spectral norm
(``alpha_norm = "2"``) is the one that reproduces the printed pattern (the 1-norm puts the deadbeat interval at 5,
the infinity and Frobenius norms at 4), reported under ``alternative_norms``. The figure draws the outputs and
states inside the intervals from the exact interval solution ``x(kT + tau) = exp(A tau) x(kT) - Bbar(tau) U_k``.
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np
import scipy.linalg

from jaxobs.papers._output import pyplot, save_figure, write_reproduction
from jaxobs.papers.scenarios import Reproduction
from jaxobs.saturation import ALPHA_NORMS, saturated_output_design, simulate_saturated_outputs

NAME = "grip2010-saturated-outputs"
A = np.array([[0.0, 1, 1], [0, 0, 0], [0, 0, 0]])
B = np.array([[0.0, 0], [1, 0], [0, 1]])
C = np.array([[1.0, 0, 0], [1, 1, 0]])
T, RHO, X0 = 0.5, 1.1, np.array([2.0, -4.0, 1.0])
PRINTED = {"first_unsaturated_interval": [1, 5], "deadbeat_interval": 6}
NORM, INTERVALS, SUBSTEPS = "2", 10, 500
_SIMULATE = jax.jit(simulate_saturated_outputs, static_argnums=2, static_argnames="substeps")


def run(alpha_norm: str = NORM):
    """The design and the trace of the §8.5 example with ``alpha`` in the given matrix norm."""
    design = saturated_output_design(A, B, C, T=T, rho=RHO, alpha_norm=alpha_norm)
    return design, _SIMULATE(design, X0, INTERVALS, substeps=SUBSTEPS)


def pattern(trace) -> dict:
    """1-based interval numbers: each output's first unsaturated interval, and the deadbeat interval."""
    unsat, mode = np.asarray(trace.unsaturated), np.asarray(trace.mode)
    first = [int(np.argmax(unsat[:, i])) + 1 if unsat[:, i].any() else None for i in range(unsat.shape[1])]
    return {"first_unsaturated_interval": first, "deadbeat_interval": int(np.argmax(mode)) + 1 if mode.any() else None}


def inside(design, trace, points: int = 50):
    """Times and states inside every interval from the exact interval solution (SciPy, independent of the run)."""
    BBt = B @ B.T
    taus = np.linspace(0, T, points + 1)[1:]
    maps = []
    for tau in taus:
        M = np.block([[A, BBt], [np.zeros_like(A), -A.T]]) * tau
        maps.append((scipy.linalg.expm(A * tau), scipy.linalg.expm(M)[:3, 3:]))
    times, states = [0.0], [X0]
    for k, (x, U) in enumerate(zip(np.asarray(trace.x_start), np.asarray(trace.U), strict=True)):
        for tau, (E, Bbar_tau) in zip(taus, maps, strict=True):
            times.append(k * T + tau)
            states.append(E @ x - Bbar_tau @ U)
    return np.array(times), np.array(states)


def reproduce(out_dir: Path) -> dict:
    """Run the example, write ``grip2010-saturated-outputs.json`` and its figure, return the summary."""
    out_dir = Path(out_dir)
    design, trace = run(NORM)
    x_start, x_end = np.asarray(trace.x_start), np.asarray(trace.x_end)
    unsat = np.asarray(trace.unsaturated)
    intervals = [
        {"k": k, "interval": k + 1, "mode": ["desaturate", "deadbeat"][int(trace.mode[k])],
         "output_pushed": int(trace.j[k]) + 1 if int(trace.j[k]) >= 0 else None,
         "unsaturated": [bool(v) for v in unsat[k]], "x_end": x_end[k], "U_norm": float(np.linalg.norm(trace.U[k])),
         "gramian_condition": float(trace.condition[k]) if np.isfinite(trace.condition[k]) else None}
        for k in range(INTERVALS)
    ]  # fmt: skip
    found = pattern(trace)
    k_hat = found["deadbeat_interval"] - 1
    alternatives = {}
    for norm in ALPHA_NORMS:
        if norm != NORM:
            d, tr = run(norm)
            alternatives[norm] = {**pattern(tr), "alpha": float(d.alpha)}
    summary = {
        "T": T,
        "rho": RHO,
        "x0": X0,
        "A": A,
        "B": B,
        "C": C,
        "alpha": float(design.alpha),
        "alpha_norm": NORM,
        "alpha_norm_note": "the spectral norm ||exp(AT)||_2 reproduces the printed pattern (y1 out in interval 1, "
        "y2 in interval 5, deadbeat in interval 6); see alternative_norms",
        "Bbar": design.Bbar,
        "intervals": intervals,
        **found,
        "printed": PRINTED,
        "matches_printed": found == PRINTED,
        "y1_saturated_when_y2_unsaturates": not bool(unsat[found["first_unsaturated_interval"][1] - 1, 0]),
        "x0_reconstruction_error": float(np.max(np.abs(np.asarray(trace.x0_hat[k_hat]) - X0))),
        "x_reconstruction_error_at_deadbeat": float(np.max(np.abs(np.asarray(trace.x_hat[k_hat]) - x_start[k_hat]))),
        "max_abs_x_after_deadbeat": float(np.max(np.abs(x_end[k_hat:]))),
        "interval_map_max_error": float(
            np.max(
                np.abs(x_end - x_start @ np.asarray(design.expAT).T + np.asarray(trace.U) @ np.asarray(design.Bbar).T)
            )
        ),
        "alternative_norms": alternatives,
        "method": f"RK4, {SUBSTEPS} steps per interval, {INTERVALS} intervals; Bbar exact (Van Loan)",
    }
    return write_reproduction(out_dir, NAME, summary, [_figure(out_dir, design, trace)])


def _figure(out_dir: Path, design, trace) -> str:
    plt = pyplot()
    t, x = inside(design, trace)
    y = np.clip(x @ C.T, -1, 1)
    fig, ax = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    for i in range(2):
        ax[0].plot(t, y[:, i], label=f"y{i + 1}")
    ax[0].set_ylabel("outputs")
    for i in range(3):
        ax[1].plot(t, x[:, i], label=f"x{i + 1}")
    ax[1].set_ylabel("states")
    ax[2].semilogy(t, np.maximum(np.linalg.norm(x, axis=1), 1e-16), label="||x||")
    ax[2].set_ylabel("||x||")
    ax[2].set_xlabel("t [s]")
    for a in ax:
        for k in range(INTERVALS + 1):
            a.axvline(k * T, color="k", ls="--", lw=0.5)
        a.legend(loc="upper right", fontsize=8)
    ax[0].set_title("Grip 2010 §8.5: y1 out in interval 1, y2 in 5, deadbeat in 6", fontsize=10)
    return save_figure(fig, out_dir, "grip2010_saturated_outputs")


REPRODUCTION = Reproduction(name=NAME, summary=__doc__, reproduce=reproduce)

__all__ = ["NAME", "REPRODUCTION", "A", "B", "C", "T", "RHO", "X0", "PRINTED", "run", "pattern", "inside", "reproduce"]
