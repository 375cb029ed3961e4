"""Grip 2010, ch. 7 (section 7.5): the special coordinate basis of the five worked examples, exactly.

For the single-track vehicle (front, and front and rear steering), the DC motor with LuGre friction (7.8) (and with
sigma_1 = 0) and the tenth-order system of Sannuti & Saberi 1987, :func:`jaxobs.scb.scb` runs in exact arithmetic
and is compared with the thesis: ``residuals`` of the identities (7.6), ``printed_check`` of the printed matrices
and the ``misprints`` these checks prove. The checks and the output format: docs/theory/papers.md.
"""

from __future__ import annotations

import time
from pathlib import Path

from jaxobs.papers._output import write_reproduction
from jaxobs.papers.scenarios import Reproduction
from jaxobs.scb import (
    SCB,
    invariant_zeros,
    is_left_invertible,
    is_right_invertible,
    scb,
    scb_arrays,
    scb_residuals,
)

NAME = "grip2010-scb"
CASES = ("single_track", "single_track_rear", "dc_motor", "dc_motor_sigma1_zero", "tenth_order")
TRANSFORMS = ("state_transform", "output_transform", "input_transform")  # the thesis's Gamma1, Gamma2, Gamma3
# Maple 12 CPU times printed in section 7.6
MAPLE_SECONDS = {
    "single_track": 0.30,
    "single_track_rear": 0.21,
    "dc_motor": 0.19,
    "dc_motor_sigma1_zero": 0.25,
    "tenth_order": 0.48,
}
# Table 6.1 / section 7.5.2 values of the DC motor
DC_MOTOR_VALUES = {"J": 0.0023, "sigma_0": 260.0, "sigma_1": 0.6, "alpha_2": 0.176}
# the numeric SCB printed in section 7.5.2 (Linear Systems Toolkit), to the printed digits
DC_MOTOR_A_NUMERIC_PRINTED = [[-433.3, -592.7, 0.0], [0.0, 0.0, 1.0], [-1.1e5, -1.5e5, 95.9]]


def _symbols():
    import sympy as sp

    names = "v_x m J l_f l_r c_f c_r T_r alpha_2 sigma_0 sigma_1"
    return dict(zip(names.split(), sp.symbols(names, positive=True), strict=True))


def systems() -> dict:
    """The original matrices ``(A, B, C)`` (D = 0) of the five cases (section 7.5), as sympy matrices."""
    import sympy as sp

    s = _symbols()
    vx, m, J, lf, lr, cf, cr, Tr = (s[k] for k in "v_x m J l_f l_r c_f c_r T_r".split())
    a2, s0, s1 = s["alpha_2"], s["sigma_0"], s["sigma_1"]
    st_A = sp.Matrix(
        [
            [0, -vx, 1 / m, 1 / m],
            [0, 0, lf / J, -lr / J],
            [-cf / (Tr * vx), -lf * cf / (Tr * vx), -1 / Tr, 0],
            [-cr / (Tr * vx), lr * cr / (Tr * vx), 0, -1 / Tr],
        ]
    )
    st_B = sp.Matrix([0, 0, cf / Tr, 0])
    st_C = sp.Matrix([[0, 1, 0, 0], [0, 0, 1 / m, 1 / m]])
    dc_A = sp.Matrix([[0, 1, 0], [0, -(a2 + s1) / J, -s0 / J], [0, 1, 0]])  # (7.8)
    dc_B = sp.Matrix([0, s1 / J, -1])
    dc_C = sp.Matrix([[1, 0, 0]])
    tenth_A = sp.Matrix(
        [
            [0, 0, 0, 0, 1, 1, 0, 0, 0, 0],
            [-1, 0, 0, 0, 1, 0, 1, 0, 0, 0],
            [1, 1, -1, -1, 0, 0, -1, 0, 0, 0],
            [0, 1, 1, 1, 0, 0, 0, 0, 0, 0],
            [-1, 2, 0, -1, 2, 0, 1, 0, 0, 0],
            [0, 0, 0, 0, 1, 0, 0, 0, 0, 0],
            [0, 0, 0, 0, 0, 1, 0, 0, 0, 0],
            [-1, -1, 0, 0, 1, 0, 1, 0, 0, 1],
            [0, 0, 0, 0, 0, 0, 0, 0, 0, 0],
            [0, 0, 0, 0, 0, 0, 0, 0, 1, 0],
        ]
    )
    tenth_B = sp.Matrix(
        [
            [0, 1, 0, 1],
            [0, 0, 0, 0],
            [0, 0, 0, 0],
            [0, 1, 0, 1],
            [0, 2, 0, 1],
            [0, 0, 1, 0],
            [0, 0, 0, 0],
            [0, 0, 0, 0],
            [1, 0, 1, 0],
            [0, 0, 0, 0],
        ]
    )
    tenth_CT = sp.Matrix(
        [
            [-1, 0, 0, 0],
            [-1, 0, 0, 0],
            [0, 0, 1, 0],
            [0, 0, 0, 0],
            [1, 0, 0, 0],
            [0, 0, 0, 0],
            [2, 1, 0, 0],
            [0, 1, 0, 1],
            [0, 0, 0, 0],
            [0, 0, 0, 0],
        ]
    )
    return {
        "single_track": (st_A, st_B, st_C),
        "single_track_rear": (st_A, st_B.row_join(sp.Matrix([0, 0, 0, cr / Tr])), st_C),
        "dc_motor": (dc_A, dc_B, dc_C),
        "dc_motor_sigma1_zero": tuple(M.subs(s1, 0) for M in (dc_A, dc_B, dc_C)),
        "tenth_order": (tenth_A, tenth_B, tenth_CT.T),
    }


def printed() -> dict:
    """What section 7.5 prints per case: dims, chain lengths, invariant zeros, the SCB A, B, C and, for the
    single-track cases, state_transform, output_transform, input_transform (the thesis's Gamma1, Gamma2, Gamma3,
    transcribed as printed, misprints included)."""
    import sympy as sp

    s = _symbols()
    vx, m, J, lf, lr, cf, cr, Tr = (s[k] for k in "v_x m J l_f l_r c_f c_r T_r".split())
    a2, s0, s1 = s["alpha_2"], s["sigma_0"], s["sigma_1"]
    L = lf + lr
    half = sp.Rational(1, 2)
    tenth_B, tenth_CT = sp.zeros(10, 4), sp.zeros(10, 4)
    for (i, j), M in zip(((3, 3), (4, 0), (6, 1), (9, 2)), (tenth_B,) * 4, strict=True):
        M[i, j] = 1
    for i, j in ((1, 3), (4, 0), (5, 1), (7, 2)):
        tenth_CT[i, j] = 1
    return {
        "single_track": {
            "dims": (0, 3, 0, 1),
            "chain_lengths": (1,),
            "invariant_zeros": [],
            "A": sp.Matrix(
                [
                    [-1 / Tr, 1, 0, Tr * lf * m / (cr * L)],
                    [-lr * cr * L / (vx * Tr * J), 0, 1, lf * m / (cr * L)],
                    [-cr * L / (Tr * J), 0, 0, 1 / vx],
                    [cr * (lr * cr - lf * cf) * L / (m * Tr**2 * vx * J), 0, -(cf + cr) / (m * Tr), -1 / Tr],
                ]
            ),
            "B": sp.Matrix([0, 0, 0, 1]),
            "C": sp.Matrix([[0, 0, 0, 1], [1, 0, 0, 0]]),
            "state_transform": sp.Matrix(
                [
                    [0, 0, vx, 0],
                    [cr * L / (Tr * J), 0, 0, 0],
                    [-cr / Tr**2, cr / Tr, 0, m],
                    [cr / Tr**2, -cr / Tr, 0, 0],
                ]
            ),
            "output_transform": sp.Matrix([[0, cr * (lf + cr) / (Tr * J)], [1, 0]]),
            "input_transform": sp.Matrix([[m * Tr / cf]]),
        },
        "single_track_rear": {
            "dims": (1, 0, 0, 3),
            "chain_lengths": (1, 2),
            "invariant_zeros": [0],
            "A": sp.Matrix(
                [
                    [0, 1, -vx, 0],
                    [-(cf + cr) / (m * Tr * vx), -1 / Tr, (lf * cr - lr * cf) / (m * Tr * vx), 0],
                    [0, 0, 0, 1],
                    [(lr * cr - lf * cf) / (J * Tr * vx), 0, -(lf**2 * cf + lr**2 * cr) / (J * Tr * vx), -1 / Tr],
                ]
            ),
            "B": sp.Matrix([[0, 0], [1, 0], [0, 0], [0, 1]]),
            "C": sp.Matrix([[0, 1, 0, 0], [0, 0, 1, 0]]),
            "state_transform": sp.Matrix(
                [[1, 0, 0, 0], [0, 0, 1, 0], [0, lr * m / L, 0, J / L], [0, lf * m / L, 0, -J / L]]
            ),
            "output_transform": sp.Matrix([[0, 1], [1, 0]]),
            "input_transform": sp.Matrix(
                [[lr * Tr * m / (cf * L), Tr * J / (cf * L)], [lf * Tr * m / (cr * L), -Tr * J / (cr * L)]]
            ),
        },
        "dc_motor": {
            "dims": (1, 0, 0, 2),
            "chain_lengths": (2,),
            "invariant_zeros": [-s0 / s1],
            "A": sp.Matrix(
                [
                    [-s0 / s1, -s0 * (s0 * J - s1 * a2) / s1**3, 0],
                    [0, 0, 1],
                    [-s0 / J, -s0 * (s0 * J - s1 * a2) / (J * s1**2), (s0 * J - s1 * a2 - s1**2) / (J * s1)],
                ]
            ),
            "B": sp.Matrix([0, 0, 1]),
            "C": sp.Matrix([[0, 1, 0]]),
        },
        "dc_motor_sigma1_zero": {
            "dims": (0, 0, 0, 3),
            "chain_lengths": (3,),
            "invariant_zeros": [],
            "A": sp.Matrix([[0, 1, 0], [0, 0, 1], [0, -s0 / J, -a2 / J]]),
            "B": sp.Matrix([0, 0, 1]),
            "C": sp.Matrix([[1, 0, 0]]),
        },
        "tenth_order": {
            "dims": (1, 2, 1, 6),
            "chain_lengths": (1, 2, 3),
            "invariant_zeros": [1],
            "A": sp.Matrix(
                [
                    [1, 0, 0, 0, 1, -1, 0, -1, 0, 0],
                    [0, 0, 1, 0, 0, 0, 0, 0, 0, 0],
                    [0, 0, 0, 0, -1, 1, 0, 1, 0, 0],
                    [2, -12, 0, 2, -8, 8, 0, 8, 0, 0],
                    [2, -4, -2, half, -2, 1, 1, 1, 1, 0],
                    [0, 0, 0, 0, 0, 0, 1, 0, 0, 0],
                    [2, -2, -2, 0, 0, -1, 1, -1, 1, -1],
                    [0, 0, 0, 0, -1, 0, 0, 0, 1, 0],
                    [0, 0, 0, 0, 0, 0, 0, 0, 0, 1],
                    [0, 2, 0, -half, 2, -2, 0, -2, 0, 0],
                ]
            ),
            "B": tenth_B,
            "C": tenth_CT.T,
        },
    }


# ----------------------------------------------------------------------------------------------- checks


def _nonzero_entries(M) -> list:
    import sympy as sp

    return [[i, j, sp.srepr(sp.factor(M[i, j]))] for i in range(M.rows) for j in range(M.cols) if M[i, j] != 0]


def _residual_report(residuals: dict) -> dict:
    return {k: (0 if all(e == 0 for e in M) else _nonzero_entries(M)) for k, M in residuals.items()}


def _implied_entries(system, case: dict) -> dict:
    """With the printed state_transform and input_transform: the entries of the printed A, B that differ from the ones
    the identities imply (``state_transform^-1 A_hat state_transform``, ``state_transform^-1 B_hat input_transform``),
    and the entries of the printed output_transform that differ from the one ``output_transform C = C_hat
    state_transform`` implies with the printed C and state_transform."""
    import sympy as sp

    A, B, C = system
    G1, G3 = case["state_transform"], case["input_transform"]
    implied = {
        "A": G1.inv() * A * G1,
        "B": G1.inv() * B * G3,
        # the printed C has full row rank, so output_transform C = C_hat state_transform fixes output_transform
        # given the printed C and state_transform
        "output_transform": C * G1 * case["C"].T * (case["C"] * case["C"].T).inv(),
    }
    differing = []
    for name, M in implied.items():
        for i in range(M.rows):
            for j in range(M.cols):
                if sp.cancel(M[i, j] - case[name][i, j]) != 0:
                    differing.append(
                        {
                            "matrix": name,
                            "entry": [i, j],
                            "printed": sp.srepr(case[name][i, j]),
                            "implied": sp.srepr(sp.factor(M[i, j])),
                            "printed_text": str(case[name][i, j]),
                            "implied_text": str(sp.factor(M[i, j])),
                        }
                    )
    return differing


def _solve_transformations(system, case: dict) -> dict:
    """Solve state_transform A_p = A state_transform, state_transform B_p = B input_transform, output_transform C_p
    = C state_transform (linear in the transformations) with the printed A_p, B_p, C_p; a nonsingular element of the
    solution space (tried on the basis and on two fixed combinations of it) proves that the printed matrices are an
    SCB of the system."""
    import sympy as sp
    from sympy.polys.matrices import DomainMatrix

    A, B, C = system
    n, m, p = A.rows, B.cols, C.rows
    G1 = sp.Matrix(n, n, sp.symbols(f"g0:{n * n}"))
    G2 = sp.Matrix(p, p, sp.symbols(f"h0:{p * p}"))
    G3 = sp.Matrix(m, m, sp.symbols(f"k0:{m * m}"))
    eqs = list(G1 * case["A"] - A * G1) + list(G1 * case["B"] - B * G3) + list(G2 * case["C"] - C * G1)
    M, _ = sp.linear_eq_to_matrix(eqs, list(G1) + list(G2) + list(G3))
    # fraction-free elimination over the polynomial ring (much faster than over the field of fractions)
    _, P = DomainMatrix.from_Matrix(M).clear_denoms_rowwise(convert=True)
    R, den, pivots = P.rref_den()
    R = R.to_Matrix()
    free = [j for j in range(M.cols) if j not in pivots]
    basis = sp.zeros(len(free), M.cols)
    for k, f in enumerate(free):
        basis[k, f] = P.domain.to_sympy(den)
        for i, j in enumerate(pivots):
            basis[k, j] = -R[i, f]
    dim = basis.rows
    candidates = [basis[k, :] for k in range(dim)]
    if dim > 1:
        candidates += [sum((basis[k, :] * (k + 1) for k in range(dim)), sp.zeros(1, basis.cols))]
        candidates += [sum((basis[k, :] * (-1) ** k * (2 * k + 3) for k in range(dim)), sp.zeros(1, basis.cols))]
    for v in candidates:
        g1 = sp.Matrix(n, n, list(v[: n * n]))
        g2 = sp.Matrix(p, p, list(v[n * n : n * n + p * p]))
        g3 = sp.Matrix(m, m, list(v[n * n + p * p :]))
        if all(sp.cancel(g.det()) != 0 for g in (g1, g2, g3)):
            return {
                "solution_space_dim": dim,
                "nonsingular_solution": True,
                "state_transform": _export(g1),
                "output_transform": _export(g2),
                "input_transform": _export(g3),
            }
    # dim 0, or dim 1 with a singular solution, proves that no nonsingular solution exists
    return {"solution_space_dim": dim, "nonsingular_solution": False, "proof": dim <= 1}


def printed_check(name: str, system=None) -> dict:
    """Do the printed SCB matrices of case ``name`` satisfy the SCB identities with the original system? With
    printed transformations, the differing entries are listed (:func:`_implied_entries`); otherwise the identities are
    solved for the transformations (:func:`_solve_transformations`)."""
    system = system or systems()[name]
    case = printed()[name]
    if "state_transform" in case:
        differing = _implied_entries(system, case)
        return {"transformations": "printed", "identities_hold": not differing, "differing_entries": differing}
    solved = _solve_transformations(system, case)
    return {"transformations": "solved", "identities_hold": solved["nonsingular_solution"], **solved}


def _export(M):
    """The entries of ``M`` for JSON: sympy srepr strings for symbolic matrices, numbers (int, else float) for
    rational ones."""
    import sympy as sp

    if any(e.free_symbols for e in M):
        return [[sp.srepr(sp.factor(M[i, j])) for j in range(M.cols)] for i in range(M.rows)]
    return [[int(e) if e.is_integer else float(e) for e in M.row(i)] for i in range(M.rows)]


def _exact_strings(M):
    return [[str(e) for e in M.row(i)] for i in range(M.rows)]


def case(name: str) -> dict:
    """Decompose case ``name`` exactly (timed) and compare it with the thesis."""
    import sympy as sp

    system = systems()[name]
    start = time.perf_counter()
    s = scb(*system)
    seconds = time.perf_counter() - start
    zeros = invariant_zeros(s)
    symbolic = bool(s.symbols)
    out = {
        "dims": list(s.dims),
        "chain_lengths": list(s.chain_lengths),
        "invariant_zeros": [sp.srepr(z) if symbolic else _number(z) for z in zeros],
        "left_invertible": is_left_invertible(s),
        "right_invertible": is_right_invertible(s),
        **{k: _export(getattr(s, k)) for k in ("A", "B", "C", *TRANSFORMS)},
        "residuals": _residual_report(scb_residuals(s, *system)),
        "printed_check": printed_check(name, system),
        "matches_printed": _matches_printed(s, printed()[name]),
        "seconds": seconds,
        "maple_seconds_printed": MAPLE_SECONDS[name],
    }
    if not symbolic:
        out.update({f"{k}_exact": _exact_strings(getattr(s, k)) for k in ("A", *TRANSFORMS)})
    if name == "dc_motor":
        num = scb_arrays(s, DC_MOTOR_VALUES)
        out["A_numeric"] = num.A
        out["A_numeric_printed"] = DC_MOTOR_A_NUMERIC_PRINTED
        out["A_numeric_values"] = DC_MOTOR_VALUES
    return out


def _number(z):
    z = complex(z)
    return z.real if z.imag == 0 else [z.real, z.imag]


def _matches_printed(s: SCB, case: dict) -> dict:
    """Per printed item: equal to the computed one (the SCB is not unique, so a difference alone is no error)."""
    import sympy as sp

    out = {"dims": tuple(s.dims) == case["dims"], "chain_lengths": tuple(s.chain_lengths) == case["chain_lengths"]}
    out["invariant_zeros"] = [sp.simplify(z) for z in invariant_zeros(s)] == case["invariant_zeros"]
    for k in ("A", "B", "C", *TRANSFORMS):
        if k in case:
            M = getattr(s, k)
            out[k] = M.shape == case[k].shape and all(sp.cancel(e) == 0 for e in M - case[k])
    return out


def misprints(cases: dict) -> list[dict]:
    """The discrepancies between the printed results and the exact computation that the checks prove."""
    found = []
    for name, c in cases.items():
        for entry in c["printed_check"].get("differing_entries", []):
            found.append(
                {
                    "case": name,
                    "where": "section 7.5",
                    **entry,
                    "proof": f"with the printed state_transform (and input_transform), the SCB identities hold for "
                    f"every other entry and require {entry['matrix']}{entry['entry']} = the implied value",
                }
            )
    dc = cases["dc_motor"]
    found.append(
        {
            "case": "dc_motor",
            "where": "section 7.5.2, text after the numeric SCB",
            "printed": "the first state belongs to the zero dynamics subsystem x_d",
            "implied": "x_a",
            "proof": f"dims (x_a, x_b, x_c, x_d) = {tuple(dc['dims'])}: the first state is the one x_a state",
        }
    )
    return found


def random_systems(inputs: int, seeds=(0, 1, 2)) -> list[dict]:
    """Section 7.6's timing experiment: strictly proper systems with 20 states, ``inputs`` inputs and 4 outputs,
    integer entries in [-10, 10] with 25 % density (seeded NumPy draws), decomposed exactly and timed."""
    import numpy as np

    results = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        A, B, C = (
            rng.integers(-10, 11, shape) * (rng.random(shape) < 0.25) for shape in ((20, 20), (20, inputs), (4, 20))
        )
        start = time.perf_counter()
        s = scb(A, B, C)
        seconds = time.perf_counter() - start
        residuals = _residual_report(scb_residuals(s, A, B, C))
        results.append(
            {
                "seed": seed,
                "dims": list(s.dims),
                "chain_lengths": list(s.chain_lengths),
                "seconds": seconds,
                "residuals_zero": all(r == 0 for r in residuals.values()),
            }
        )
    return results


def reproduce(out_dir: Path) -> dict:
    """Decompose the five cases, check the printed results, write ``grip2010-scb.json`` and return the summary."""
    results = {}
    for name in CASES:
        results[name] = case(name)
    summary = {**results, "misprints": misprints(results)}
    summary["seconds_vs_maple"] = {n: [results[n]["seconds"], MAPLE_SECONDS[n]] for n in CASES}
    summary["random_20_states"] = {
        "4_inputs": random_systems(4),
        "3_inputs": random_systems(3),
        "maple_printed": {
            "4_inputs": "generally < 0.4 s, typically x_a 16 + x_d 4 states",
            "3_inputs": "around 50 s, typically x_b 17 + x_d 3 states",
        },
    }
    return write_reproduction(Path(out_dir), NAME, summary, [])


REPRODUCTION = Reproduction(name=NAME, summary=__doc__, reproduce=reproduce)

__all__ = [
    "NAME",
    "REPRODUCTION",
    "CASES",
    "systems",
    "printed",
    "printed_check",
    "case",
    "misprints",
    "random_systems",
    "reproduce",
]
