"""CMA-ES in JAX: the tuner's exploration, as a pure ask/tell pair on the unit cube of the search box.

The (mu/mu_w, lambda)-CMA-ES of Hansen (2016, "The CMA evolution strategy: a tutorial"), with its default
parameters (eq. 48-58 and Table 1), cumulative step-size adaptation and rank-one plus rank-mu covariance updates;
above :data:`FULL_MAX` coordinates the separable variant of Ros & Hansen (2008): a diagonal covariance whose
learning rates are ``(n + 2) / 3`` times larger, ``O(n)`` per candidate instead of ``O(n^2)`` and no
eigendecomposition. Candidates are repaired onto the cube (clipped) and the repaired steps enter the update, so the
mean stays in the box. Coordinates that ``free`` marks ``False`` (fixed entries of the box) do not move.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks

__all__ = ["FULL_MAX", "CMAState", "init", "ask", "tell"]

FULL_MAX = 100
"""Above this many coordinates the covariance is diagonal (separable CMA-ES)."""


class CMAState(NamedTuple):
    """State of the CMA-ES (``d`` coordinates of the unit cube).

    Attributes:
      mean: (d,) the distribution's mean.  sigma: () the step size.
      cov: (d, d) the covariance, or (d,) its diagonal above :data:`FULL_MAX` coordinates.
      root, inverse_root: its symmetric square root ``A`` (``C = A A^T``) and ``A^-1`` (diagonals above
        :data:`FULL_MAX`), one eigendecomposition per generation.
      path_sigma, path_c: (d,) the evolution paths of the step size and of the covariance.
      generation: () generations told.  free: (d,) bool, the coordinates that move.
    """

    mean: jax.Array
    sigma: jax.Array
    cov: jax.Array
    root: jax.Array
    inverse_root: jax.Array
    path_sigma: jax.Array
    path_c: jax.Array
    generation: jax.Array
    free: jax.Array


def init(mean, sigma, free) -> CMAState:
    """A CMA-ES at ``mean`` (d,) in the unit cube with step ``sigma`` () and identity covariance; ``free`` (d,)."""
    _checks.shapes("mean (d,), sigma (), free (d,)", mean, sigma, free)
    mean = _checks.real_array("mean", mean)
    d = mean.shape[0]
    cov = jnp.eye(d, dtype=mean.dtype) if d <= FULL_MAX else jnp.ones(d, mean.dtype)
    zeros = jnp.zeros_like(mean)
    sigma = jnp.asarray(sigma, mean.dtype)
    return CMAState(mean, sigma, cov, cov, cov, zeros, zeros, jnp.zeros((), jnp.int32), jnp.asarray(free, bool))


def _weights(population: int, dtype):
    mu = population // 2
    w = jnp.log((population + 1) / 2) - jnp.log(jnp.arange(1, mu + 1, dtype=dtype))
    w = w / jnp.sum(w)
    return w, 1.0 / jnp.sum(w**2)


def _constants(state: CMAState, population: int):
    """Hansen (2016) Table 1 (and Ros & Hansen 2008 for the diagonal): weights, mu_eff, c_sigma, d_sigma, c_c, c_1,
    c_mu and E||N(0, I)|| for the free coordinates' count ``n``."""
    w, mu_eff = _weights(population, state.mean.dtype)
    n = jnp.maximum(jnp.sum(state.free), 1).astype(state.mean.dtype)
    c_sigma = (mu_eff + 2) / (n + mu_eff + 5)
    d_sigma = 1 + 2 * jnp.maximum(0.0, jnp.sqrt((mu_eff - 1) / (n + 1)) - 1) + c_sigma
    c_c = (4 + mu_eff / n) / (n + 4 + 2 * mu_eff / n)
    c_1 = 2 / ((n + 1.3) ** 2 + mu_eff)
    c_mu = jnp.minimum(1 - c_1, 2 * (mu_eff - 2 + 1 / mu_eff) / ((n + 2) ** 2 + mu_eff))
    if state.cov.ndim == 1:  # separable: larger learning rates, still summing to at most 1
        c_1, c_mu = c_1 * (n + 2) / 3, c_mu * (n + 2) / 3
        c_mu = jnp.minimum(c_mu, 1 - c_1)
    chi = jnp.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n**2))
    return w, mu_eff, c_sigma, d_sigma, c_c, c_1, c_mu, chi


def _factor(cov):
    """``(A, A^-1)`` with ``C = A A^T`` symmetric (the eigendecomposition's ``B D B^T``), or diagonals."""
    if cov.ndim == 1:
        root = jnp.sqrt(cov)
        return root, 1.0 / root
    values, vectors = jnp.linalg.eigh(cov)
    root = jnp.sqrt(jnp.maximum(values, 1e-300))
    return (vectors * root) @ vectors.T, (vectors / root) @ vectors.T


def _check_state(state: CMAState) -> int:
    """The coordinate count ``d`` of one state (not a batch: ``vmap`` over states), checked at trace time."""
    d = _checks.fields("state", state, "mean (d,), sigma (), path_sigma (d,), path_c (d,), free (d,)")["d"]
    square = (d, d) if d <= FULL_MAX else (d,)
    for name in ("cov", "root", "inverse_root"):
        _checks.shape(f"state.{name}", getattr(state, name), square, f"{d} coordinates")
    return d


def _apply(matrix, rows):
    return rows * matrix if matrix.ndim == 1 else rows @ matrix.T


def ask(state: CMAState, key, population: int):
    """``population`` candidates (population, d): ``mean + sigma A z`` with ``z ~ N(0, I)``, clipped to the cube."""
    d = _check_state(state)
    population = _checks.count("population", population, minimum=1, maximum=_checks.MAX_INDEX)
    z = jax.random.normal(_checks.key("key", key), (population, d), state.mean.dtype) * state.free
    return jnp.clip(state.mean + state.sigma * _apply(state.root, z), 0.0, 1.0)


def tell(state: CMAState, ranked) -> CMAState:
    """The state after a generation whose candidates (as :func:`ask` returned them, so repaired) are ``ranked``
    (population, d), best first (Hansen 2016 eq. 41-47)."""
    _checks.shape("ranked", ranked, (None, _check_state(state)), "one row per candidate")
    ranked = jnp.asarray(ranked, state.mean.dtype)
    population = ranked.shape[0]
    w, mu_eff, c_sigma, d_sigma, c_c, c_1, c_mu, chi = _constants(state, population)
    steps = (ranked[: w.shape[0]] - state.mean) / state.sigma * state.free
    step = w @ steps
    path_sigma = (1 - c_sigma) * state.path_sigma + jnp.sqrt(c_sigma * (2 - c_sigma) * mu_eff) * _apply(
        state.inverse_root, step
    )
    norm = jnp.linalg.norm(path_sigma)
    generation = state.generation + 1
    n = jnp.maximum(jnp.sum(state.free), 1)
    h_sigma = norm / jnp.sqrt(1 - (1 - c_sigma) ** (2 * generation)) < (1.4 + 2 / (n + 1)) * chi
    path_c = (1 - c_c) * state.path_c + h_sigma * jnp.sqrt(c_c * (2 - c_c) * mu_eff) * step
    lost = (1 - h_sigma) * c_c * (2 - c_c)
    if state.cov.ndim == 1:
        rank_one, rank_mu = path_c**2, w @ steps**2
    else:
        rank_one, rank_mu = jnp.outer(path_c, path_c), (steps.T * w) @ steps
    cov = (1 + c_1 * lost - c_1 - c_mu) * state.cov + c_1 * rank_one + c_mu * rank_mu
    sigma = state.sigma * jnp.exp(jnp.minimum(c_sigma / d_sigma * (norm / chi - 1), 1.0))
    return CMAState(state.mean + state.sigma * step, sigma, cov, *_factor(cov), path_sigma, path_c, generation,
                    state.free)  # fmt: skip
