"""Hand-made mutants: plausible bugs planted one at a time in a copy of the package; the suite must catch each.

Run from the repository root::

    python -m tests.mutants                 # every mutant against the tests of the module it changes
    python -m tests.mutants joseph-sign     # one (or several) by name
    python -m tests.mutants --list

Each mutant replaces one snippet (found by its text anywhere under ``jaxobs/``, so modules may move) in a
temporary copy of the repository and runs the default-marked tests that cover that module (``-x``: the first
failure is enough). A mutant is *caught* when those tests fail; the run exits with status 1 if any survives.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

from tests import ROOT


class Mutant(NamedTuple):
    name: str
    what: str
    old: str
    new: str
    tests: tuple[str, ...]  # paths relative to the repository root; the first that exist are run


MUTANTS = (
    Mutant("delay-margin-degrees", "the delay margin from the phase lag in degrees, not radians",
           "jnp.where(has_gc, jnp.radians(lag_dm) / (theta_dm / sys.dt), inf)",
           "jnp.where(has_gc, lag_dm / (theta_dm / sys.dt), inf)", ("tests/test_stability.py",)),
    Mutant("delay-margin-phase-crossover", "the delay margin divided by the phase-crossover frequency",
           "jnp.where(has_gc, jnp.radians(lag_dm) / (theta_dm / sys.dt), inf)",
           "jnp.where(has_gc, jnp.radians(lag_dm) / (theta_pc / sys.dt), inf)", ("tests/test_stability.py",)),
    Mutant("c2d-limit-one-sample", "c2d accepts a dead time one sample longer than its delay slots",
           "out_of_range = tau > n_delay * h * (1 + 1e-9)", "out_of_range = tau > (n_delay + 1) * h * (1 + 1e-9)",
           ("tests/test_lti.py",)),
    Mutant("c2d-gamma-swap", "c2d's fractional-delay input matrices (Cortesão 2006 eq. 16-17) swapped",
           "Gamma0 = F_rest  # eq. 16", "Gamma0 = F_h - F_rest  # eq. 16", ("tests/test_lti.py",)),
    Mutant("schedule-shift", "the time-varying Kalman gain schedule shifted by one sample",
           "gains = jnp.concatenate([first_K[None], later.K])", "gains = jnp.concatenate([later.K[:1], later.K])",
           ("tests/observers/test_kalman.py",)),
    Mutant("aob-oldest-active-state", "the AOB reports its oldest active state as the disturbance",
           "        d = x[newest]\n",
           "        d = x[newest.start - params.n_active + params.n_channels : newest.stop - params.n_active"
           " + params.n_channels]\n", ("tests/observers/test_active.py",)),
    Mutant("joseph-sign", "the Joseph-form update subtracts K R K'",
           "return CovarianceUpdate(symmetrize(congruence + K @ R @ K.T), K, S, S_chol)",
           "return CovarianceUpdate(symmetrize(congruence - K @ R @ K.T), K, S, S_chol)",
           ("tests/test_kalman_steps.py",)),
    Mutant("dare-dq-sign", "the DARE's implicit derivative with the sign of dQ flipped",
           "M = Ac.T @ X @ (dA - dB @ K)\n    E = M + M.T + K.T @ dR @ K + dQ",
           "M = Ac.T @ X @ (dA - dB @ K)\n    E = M + M.T + K.T @ dR @ K - dQ",
           ("tests/test_matrix_equations.py",)),
    Mutant("tyre-force-sign", "the pure-slip tyre force loses its sign for negative slip",
           "return _curve_ratio(tyre, jnp.abs(slip), fz, direction) * slip",
           "return _curve_ratio(tyre, jnp.abs(slip), fz, direction) * jnp.abs(slip)", ("tests/vehicle/test_tyres.py",)),
    Mutant("scb-minimum-phase-boundary", "a zero on the imaginary axis counts as minimum phase (numeric SCB)",
           "return bool(all(np.real(z) < 0 for z in zeros))", "return bool(all(np.real(z) <= 0 for z in zeros))",
           ("tests/test_scb.py",)),
    Mutant("saturation-interval-sign", "the interval map of Grip 2010 (8.7) adds Bbar U instead of subtracting",
           "return design.expAT @ x - design.Bbar @ U", "return design.expAT @ x + design.Bbar @ U",
           ("tests/test_saturation.py",)),
    Mutant("rts-gain-transpose", "the RTS smoother corrects with the transposed smoother gain",
           "x_smoothed = x_k + E_k @ (x_later - x_prior_next)", "x_smoothed = x_k + E_k.T @ (x_later - x_prior_next)",
           ("tests/test_smoothing.py",)),
    Mutant("em-q-normalisation", "EM's Q update divides by one more transition than there are",
           'new["Q"] = symmetrize(s.S11 - AS - AS.T + A @ s.S00 @ A.T) / transitions',
           'new["Q"] = symmetrize(s.S11 - AS - AS.T + A @ s.S00 @ A.T) / (transitions + 1)',
           ("tests/test_learning.py",)),
)  # fmt: skip


def _plant(copy: Path, mutant: Mutant) -> Path:
    """Apply ``mutant`` in the repository copy; returns the changed file. The snippet must occur exactly once."""
    hits = [(path, path.read_text()) for path in sorted((copy / "jaxobs").rglob("*.py"))]
    hits = [(path, text) for path, text in hits if mutant.old in text]
    counts = sum(text.count(mutant.old) for _, text in hits)
    if counts != 1:
        raise SystemExit(f"{mutant.name}: its snippet occurs {counts} times under jaxobs/ (need exactly one)")
    path, text = hits[0]
    path.write_text(text.replace(mutant.old, mutant.new))
    return path


def run(mutant: Mutant, workers: int) -> tuple[bool, float, str]:
    """``(caught, seconds, where)``: the mutant planted in a fresh copy and its tests run there."""
    tests = [t for t in mutant.tests if (ROOT / t).exists()]
    if not tests:
        raise SystemExit(f"{mutant.name}: none of its test files exist: {mutant.tests}")
    with tempfile.TemporaryDirectory(prefix=f"mutant-{mutant.name}-") as tmp:
        copy = Path(tmp) / "repo"
        skipped = (".git", ".venv", "out", "site", "__pycache__", ".pytest_cache", ".hypothesis", ".jax_cache")
        shutil.copytree(ROOT, copy, ignore=shutil.ignore_patterns(*skipped))
        changed = _plant(copy, mutant)
        start = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-x", "-m", "not slow", "-p", "no:cacheprovider", "-n",
             str(workers), *tests],
            cwd=copy, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(copy)},
        )  # fmt: skip
        seconds = time.perf_counter() - start
    failed = done.returncode == 1 or (done.returncode == 2 and re.search(r"\b\d+ failed\b", done.stdout))
    if done.returncode != 0 and not failed:  # xdist reports a -x stop as interrupted (2) with the failure counted
        raise SystemExit(f"{mutant.name}: pytest exited with {done.returncode}:\n{done.stdout[-3000:]}")
    return bool(failed), seconds, f"{changed.relative_to(copy)} ({', '.join(tests)})"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.mutants", description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="mutants to run (default: all)")
    parser.add_argument("--list", action="store_true", help="list the mutants")
    parser.add_argument("--workers", type=int, default=2, help="pytest-xdist workers (default 2)")
    args = parser.parse_args(argv)
    by_name = {m.name: m for m in MUTANTS}
    if args.list:
        for m in MUTANTS:
            print(f"{m.name:28s} {m.what}")
        return 0
    unknown = [n for n in args.names if n not in by_name]
    if unknown:
        parser.error(f"unknown mutants {unknown}; --list shows them")
    survivors = []
    for mutant in [by_name[n] for n in args.names] or MUTANTS:
        caught, seconds, where = run(mutant, args.workers)
        print(f"{'caught  ' if caught else 'SURVIVED'} {mutant.name:28s} {seconds:6.1f} s  {where}", flush=True)
        if not caught:
            survivors.append(mutant.name)
    total = len(args.names) or len(MUTANTS)
    print(f"{len(survivors)} of {total} mutants survived" + (f": {survivors}" if survivors else ""))
    return 1 if survivors else 0


if __name__ == "__main__":
    raise SystemExit(main())
