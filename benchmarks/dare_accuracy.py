"""Accuracy of ``jaxobs.matrix_equations.dare`` against ``scipy.linalg.solve_discrete_are``.

Case families (``tests/darex.py``):

* ``darex``: the DAREX benchmark collection (Abels & Benner 1999, SLICOT BB02AD), every example the library's
  DARE poses, the parameterised ones at several parameter values;
* ``hard``: a well-conditioned filter with a sensor of ``R`` from 1e-4 down to 1e-12 of ``Q`` (SciPy-accurate
  problems the old doubling solver lost digits on), and the steady-state DAREs of the CKF and AOB-1/2/3 of
  Cortesão 2006, Example 1 (``Q`` entries of 1e-12 next to 1e-3);
* ``random``: seeded random filter problems, ``n`` up to 20, ``m`` up to 4, spectral radius 0.5 to 2, ``R/Q``
  from 1 down to 1e-12, full-rank and rank-1 ``Q`` (``--quick``: a subset).

Both answers are measured against a reference: Newton's method started from SciPy's answer (from ours where SciPy
fails) with the residual evaluated exactly in rational arithmetic (``tests/darex.py``). Errors are relative
Frobenius errors of the solution ``X`` and of the gain ``K = (R + B'XB)^{-1} B'XA`` computed from it. ``floor``:
what no float64 answer can be expected to beat (the effect of rounding the exact solution to float64). The test
``tests/benchmarks/test_dare_accuracy.py`` asserts ``ours <= 10 * scipy + floor`` on every case.

Run::

    python benchmarks/dare_accuracy.py --out DIR [--quick]

Prints the table (worst errors per family) and writes ``DIR/dare_accuracy.json`` (every case).
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import darex  # noqa: E402

QUICK_GRID = dict(nm=((2, 1), (5, 2), (10, 4), (20, 1)), rho=(0.5, 2.0), ratio=(1.0, 1e-12), rank_q=(None, 1))


def summarise(rows: list[dict]) -> dict:
    """Worst errors of ours and SciPy's, worst ratio ``ours / (scipy + floor)``, counts."""
    ref = [r for r in rows if r["reference"]]
    both = [r for r in ref if not r["scipy_failed"]]

    def worst(key, items):
        return max((r[key] for r in items), default=float("nan"))

    def ratio(r, q):
        return darex.ratio(r, q)

    failed = [r for r in ref if r["scipy_failed"]]
    return {
        "cases": len(rows),
        "with_reference": len(ref),
        "scipy_failed": len(failed),
        "ours_not_converged": sum(not r["converged"] for r in rows),
        "ours_X": worst("ours_X", both),
        "scipy_X": worst("scipy_X", both),
        "ours_K": worst("ours_K", both),
        "scipy_K": worst("scipy_K", both),
        "ours_X_where_scipy_failed": worst("ours_X", failed),
        "ours_K_where_scipy_failed": worst("ours_K", failed),
        "worst_ratio_X": max((ratio(r, "X") for r in both), default=float("nan")),
        "worst_ratio_K": max((ratio(r, "K") for r in both), default=float("nan")),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--quick", action="store_true", help="a subset of the random grid")
    args = parser.parse_args(argv)
    if not darex.extended_precision_available():
        print("warning: np.longdouble is float64 here; the reference keeps X in float64 (uncertainty ~1e-16)")
    families = {
        "darex": darex.collection(),
        "hard": darex.hard_cases(),
        "random": darex.random_cases(QUICK_GRID if args.quick else darex.RANDOM_GRID),
    }
    results = {"jax": jax.__version__, "families": {}}
    columns = ("X ours", "X scipy", "K ours", "K scipy")
    print(f"{'family':8} {'cases':>5} " + " ".join(f"{c:>9}" for c in columns) + f" {'ratio X':>8} {'ratio K':>8}")
    for name, cases in families.items():
        start = time.perf_counter()
        rows = darex.compare(cases)
        summary = summarise(rows)
        summary["seconds"] = time.perf_counter() - start
        results["families"][name] = {"summary": summary, "cases": rows}
        print(
            f"{name:8} {summary['cases']:5d} {summary['ours_X']:9.1e} {summary['scipy_X']:9.1e} "
            f"{summary['ours_K']:9.1e} {summary['scipy_K']:9.1e} {summary['worst_ratio_X']:8.2f} "
            f"{summary['worst_ratio_K']:8.2f}   ours not converged on {summary['ours_not_converged']}"
        )
        if summary["scipy_failed"]:
            print(
                f"{'':8} SciPy failed on {summary['scipy_failed']}: ours X {summary['ours_X_where_scipy_failed']:.1e}, "
                f"K {summary['ours_K_where_scipy_failed']:.1e} there (converged; the gain is as ill-conditioned)"
            )
    print("errors: worst over the cases SciPy solves; ratio: worst ours / (scipy + floor), the test asserts <= 10")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "dare_accuracy.json").write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
