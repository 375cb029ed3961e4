"""Accuracy of ``jaxobs.matrix_equations.care`` against ``scipy.linalg.solve_continuous_are``.

Seeded random problems: ``A`` Gaussian plus ``shift I`` (shift -2, 0, +2: stable to unstable), ``(A, B)`` with a
controllability matrix of condition below 1e3, ``Q > 0``, ``R = r H H'`` for ``r`` from 1 down to 1e-12 (precise
inputs), ``n`` in 2, 4, 8 and ``m`` in 1, 2. Both answers are measured against the exact stabilising solution:
the stable invariant subspace of the Hamiltonian in 50-digit mpmath arithmetic, rounded once to float64. Errors
are relative Frobenius errors of ``X``; ``residual`` is care's own relative residual; times are the median of 5
eager calls after the first (compile) one.

Run::

    python benchmarks/care_accuracy.py --out DIR [--quick]

(on a shared machine with ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1``: threaded BLAS contention inflates SciPy's
times up to 50 ms).

Prints the table (worst errors per (n, m, r)) and writes ``DIR/care_accuracy.json`` (every case).
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import mpmath  # noqa: E402
import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402

from jaxobs.matrix_equations import care  # noqa: E402


def exact_care(A, B, Q, R, digits: int = 50):
    """The stabilising CARE solution from the stable eigenvectors of the Hamiltonian in ``digits`` digits."""
    with mpmath.workdps(digits):
        n = A.shape[0]
        Am, Bm, Qm, Rm = (mpmath.matrix(np.asarray(M, float).tolist()) for M in (A, B, Q, R))
        G = Bm * mpmath.inverse(Rm) * Bm.T
        H = mpmath.matrix(2 * n, 2 * n)
        for i in range(n):
            for j in range(n):
                H[i, j], H[i, n + j], H[n + i, j], H[n + i, n + j] = Am[i, j], -G[i, j], -Qm[i, j], -Am[j, i]
        values, vectors = mpmath.eig(H)
        stable = [k for k in range(2 * n) if mpmath.re(values[k]) < 0]
        U = mpmath.matrix(2 * n, n)
        for c, k in enumerate(stable):
            for i in range(2 * n):
                U[i, c] = vectors[i, k]
        X = U[n:, :] * mpmath.inverse(U[:n, :])
        return np.array([[float(mpmath.re(X[i, j])) for j in range(n)] for i in range(n)])


def problem(rng, n, m, r, shift):
    while True:
        A = rng.normal(size=(n, n)) + shift * np.eye(n)
        B = rng.normal(size=(n, m))
        ctrb = np.hstack([np.linalg.matrix_power(A, k) @ B for k in range(n)])
        if np.linalg.cond(ctrb) < 1e3:
            break
    G = rng.normal(size=(n, n))
    H = rng.normal(size=(m, m)) + 2 * np.eye(m)
    return A, B, G @ G.T / n + 0.1 * np.eye(n), r * (H @ H.T)


def median_time(f, repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(f())
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--quick", action="store_true", help="n in 2, 4 and one seed")
    args = parser.parse_args(argv)
    sizes = ((2, 1), (4, 2)) if args.quick else ((2, 1), (4, 1), (4, 2), (8, 2))
    seeds = range(1) if args.quick else range(2)
    rows = []
    err = lambda a, b: float(np.linalg.norm(np.asarray(a) - b) / np.linalg.norm(b))
    header = f"{'n':>2} {'m':>2} {'R/Q':>6} {'cases':>5} {'ours-exact':>10} {'scipy-exact':>11} {'ours-scipy':>10}"
    print(header + f" {'residual':>9} {'not conv':>8} {'t ours':>8} {'t scipy':>8}")
    for n, m in sizes:
        for r in (1.0, 1e-4, 1e-8, 1e-12):
            group = []
            for shift in (-2.0, 0.0, 2.0):
                for seed in seeds:
                    A, B, Q, R = problem(np.random.default_rng([n, m, seed, int(shift) + 2]), n, m, r, shift)
                    sol = care(A, B, Q, R)
                    theirs = scipy.linalg.solve_continuous_are(A, B, Q, R)
                    exact = exact_care(A, B, Q, R)
                    group.append(dict(
                        n=n, m=m, r=r, shift=shift, seed=seed, converged=bool(sol.converged),
                        residual=float(sol.residual), ours_exact=err(sol.X, exact), scipy_exact=err(theirs, exact),
                        ours_scipy=err(sol.X, theirs),
                        t_ours=median_time(lambda A=A, B=B, Q=Q, R=R: care(A, B, Q, R).X),
                        t_scipy=median_time(lambda A=A, B=B, Q=Q, R=R: scipy.linalg.solve_continuous_are(A, B, Q, R)),
                    ))  # fmt: skip
            rows += group
            worst = lambda key, g=group: max(row[key] for row in g)
            t_ours, t_scipy = (np.median([x[key] for x in group]) * 1e3 for key in ("t_ours", "t_scipy"))
            print(
                f"{n:2d} {m:2d} {r:6.0e} {len(group):5d} {worst('ours_exact'):10.1e} {worst('scipy_exact'):11.1e} "
                f"{worst('ours_scipy'):10.1e} {worst('residual'):9.1e} {sum(not x['converged'] for x in group):8d} "
                f"{t_ours:6.2f}ms {t_scipy:6.2f}ms"
            )
    print("errors: worst relative Frobenius error of X per row (shifts -2, 0, +2); times: median eager call")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "care_accuracy.json").write_text(json.dumps({"jax": jax.__version__, "cases": rows}, indent=1))
    return {"cases": rows}


if __name__ == "__main__":
    main()
