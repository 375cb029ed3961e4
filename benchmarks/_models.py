"""Random test models shared by the benchmarks."""

from __future__ import annotations

import numpy as np


def random_models(rng: np.random.Generator, count: int, n: int, p: int, spectral_radius: float = 0.95):
    """``count`` stable random models ``(Phi, C, Q, R)`` (n states, p outputs), each stacked on a leading axis:
    ``Phi`` scaled to the given spectral radius, ``Q`` and ``R`` random positive definite."""
    Phi = rng.standard_normal((count, n, n))
    Phi *= spectral_radius / np.abs(np.linalg.eigvals(Phi)).max(axis=-1)[:, None, None]
    G = rng.standard_normal((count, n, n))
    Q = 0.1 * G @ np.swapaxes(G, -1, -2) / n + 1e-3 * np.eye(n)
    C = rng.standard_normal((count, p, n))
    H = rng.standard_normal((count, p, p))
    R = 0.5 * H @ np.swapaxes(H, -1, -2) / p + 0.5 * np.eye(p)
    return Phi, C, Q, R
