"""Accuracy of jaxobs.matrix_equations.dare against SciPy (issue 13 §1): on the DAREX collection (Abels & Benner
1999), on precise sensors and the papers' AOB designs, and on random systems, the solution and the gain are within 10x
SciPy's own error plus the float64 rounding floor, both measured against an exact-residual Newton reference
(tests/darex.py). The checks compile one DARE per shape (minutes in all), so they are @pytest.mark.slow; the default
suite's DARE tests (tests/test_matrix_equations.py) compare with SciPy on random problems."""

import numpy as np
import pytest

from tests import darex


def check(rows):
    """Every case: the reference exists, ours converged, and ours <= 10 scipy + floor for X and the gain; where
    SciPy fails, ours within 100x the rounding floor of X and within the gain's floor."""
    failures = []
    for row in rows:
        if not row["reference"]:
            failures.append((row["name"], "no reference"))
            continue
        if not row["converged"]:
            failures.append((row["name"], "not converged"))
        if row["scipy_failed"]:
            if row["ours_X"] > 100 * row["floor_X"] or row["ours_K"] > row["floor_K"]:
                failures.append((row["name"], f"X {row['ours_X']:.2e} K {row['ours_K']:.2e} (SciPy failed)"))
            continue
        for q in ("X", "K"):
            if darex.ratio(row, q) > 10:
                failures.append((row["name"], f"{q} ours {row[f'ours_{q}']:.2e} scipy {row[f'scipy_{q}']:.2e}"))
    assert not failures, failures


def test_reference_is_exact_on_darex_closed_forms():
    """The reference reproduces the collection's closed-form solutions (Examples 1.3, 2.1, 2.3-2.5, 4.1) to
    float64 rounding (2.5 at tau = 1e6: the closed form itself cancels, so 1e-14)."""
    for ex in darex.collection():
        if ex.X is None:
            continue
        ref = darex.reference_solution(ex.A, ex.B, ex.Q, ex.R, ex.X)
        error = np.linalg.norm(ref.X.astype(float) - ex.X) / np.linalg.norm(ex.X)
        assert error < (1e-13 if ex.name.startswith("2.5") else 1e-15), (ex.name, error)


@pytest.mark.slow
@pytest.mark.parametrize("family", ["darex", "hard", "random"])
def test_dare_accuracy_full_within_10x_scipy(family):
    """The whole DAREX collection, all hard cases (CKF, AOB-1/2/3), and the random grid of 352 systems (n up to
    20, m up to 4, spectral radius up to 2, R/Q down to 1e-12)."""
    cases = {"darex": darex.collection, "hard": darex.hard_cases, "random": darex.random_cases}[family]()
    check(darex.compare(cases))
