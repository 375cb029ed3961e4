"""Eager input validation shared by the public API.

Every check runs only on concrete arrays: under ``jit``/``vmap``/``grad`` the inputs are tracers and
the checks are skipped (traced code reports problems through flags and NaNs instead, never by
raising). Each check raises ``ValueError`` naming the argument and saying how to fix it.
"""

from __future__ import annotations

import jax
import numpy as np


def is_concrete(*values) -> bool:
    """True when none of ``values`` is a JAX tracer (so they can be inspected with NumPy)."""
    return not any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(values))


def matrix(name: str, value, *, shape: tuple | None = None, square: bool = False, batch: bool = False):
    """Check that ``value`` is a finite 2-D matrix (or a stack of them when ``batch``).

    ``shape`` entries may be ``None`` for "any size". Returns nothing; raises ``ValueError``.
    """
    if not is_concrete(value):
        return
    a = np.asarray(value)
    if a.ndim != 2 and not (batch and a.ndim > 2):
        raise ValueError(f"{name} must be a 2-D matrix, got an array of shape {a.shape}")
    rows, cols = a.shape[-2:]
    if square and rows != cols:
        raise ValueError(f"{name} must be square, got shape {a.shape}")
    if shape is not None:
        for axis, (want, got) in enumerate(zip(shape, (rows, cols), strict=True)):
            if want is not None and want != got:
                raise ValueError(
                    f"{name} has shape {a.shape[-2:]}, but dimension {axis} must be {want} to match the other arguments"
                )
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or infinite entries")


def covariance(name: str, value, *, definite: bool, size: int | None = None):
    """Check that ``value`` is a finite symmetric positive (semi)definite matrix of the given size."""
    matrix(name, value, shape=(size, size), square=True, batch=True)
    if not is_concrete(value):
        return
    a = np.asarray(value, dtype=float)
    scale = max(float(np.max(np.abs(a))), np.finfo(float).tiny)
    if not np.allclose(a, np.swapaxes(a, -1, -2), rtol=1e-10, atol=1e-12 * scale):
        raise ValueError(f"{name} must be symmetric; symmetrise it with (M + M.T) / 2")
    lowest = float(np.min(np.linalg.eigvalsh((a + np.swapaxes(a, -1, -2)) / 2)))
    if definite and lowest <= 1e-14 * scale:
        raise ValueError(
            f"{name} must be positive definite (smallest eigenvalue {lowest:.3g}); a singular {name} cannot be inverted"
        )
    if not definite and lowest < -1e-10 * scale:
        raise ValueError(f"{name} must be positive semidefinite (smallest eigenvalue {lowest:.3g})")


def positive_scalar(name: str, value, *, allow_zero: bool = False):
    """Check a finite positive (or non-negative) scalar."""
    if not is_concrete(value):
        return
    a = np.asarray(value, dtype=float)
    if a.ndim != 0:
        raise ValueError(f"{name} must be a scalar, got shape {a.shape}")
    ok = np.isfinite(a) and (a >= 0 if allow_zero else a > 0)
    if not ok:
        bound = "non-negative" if allow_zero else "positive"
        raise ValueError(f"{name} must be a finite {bound} number, got {float(a)}")
