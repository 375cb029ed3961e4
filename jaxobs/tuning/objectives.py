"""Robust objectives over the per-plant losses of a batch, the penalty of diverged plants, and the objective and
gradient the tuner and the searches evaluate."""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp

from jaxobs import _checks

__all__ = ["OBJECTIVES", "GRADIENT_MODES", "cvar", "robust_objective", "penalise_diverged", "make_objective",
           "value_and_grad"]  # fmt: skip

OBJECTIVES = ("mean", "cvar")
GRADIENT_MODES = ("auto", "reverse", "forward")


def cvar(losses, alpha: float):
    """Conditional value at risk: the mean of the worst ``ceil(alpha B)`` of the ``B`` losses (``alpha`` in
    (0, 1]; ``alpha = 1`` is the mean). Differentiable almost everywhere (through ``lax.top_k``)."""
    if not 0 < alpha <= 1:
        raise ValueError(f"cvar alpha must be in (0, 1], got {alpha}")
    (losses,) = _checks.float_arrays(losses=losses)
    losses = jnp.ravel(losses)
    worst = max(1, math.ceil(alpha * losses.shape[0] - 1e-9))
    return jnp.mean(jax.lax.top_k(losses, worst)[0])


def robust_objective(losses, kind: str = "mean", alpha: float = 0.25):
    """``mean(losses)`` or ``cvar(losses, alpha)``."""
    (losses,) = _checks.float_arrays(losses=losses)
    if kind == "mean":
        return jnp.mean(losses)
    if kind == "cvar":
        return cvar(losses, alpha)
    raise ValueError(f"objective must be one of {OBJECTIVES}, got {kind!r}")


def penalise_diverged(losses, failed, factor: float, own=None):
    """``losses`` (B,) with each ``failed`` plant's loss ``L`` replaced by a penalty above every sound plant's:
    with ``P = factor x`` the largest loss of the sound plants (held constant in derivatives),
    ``P (1 + log(1 + L / P))`` where ``L >= 0`` is finite and ``own`` (default: all) allows it, else ``P``.
    The failed plant's own gradient thus enters with the weight ``P / (P + L) <= 1``, which shrinks as it
    diverges further. NaN if every plant failed."""
    (losses,) = _checks.float_arrays(losses=losses)
    failed = jnp.asarray(failed, bool)
    own = jnp.ones_like(failed) if own is None else jnp.asarray(own, bool)
    worst = jax.lax.stop_gradient(factor * jnp.max(jnp.where(failed, -jnp.inf, losses)))
    usable = failed & own & jnp.isfinite(losses)
    excess = jnp.log1p(jnp.maximum(jnp.where(usable, losses, 0.0), 0.0) / worst)
    return jnp.where(failed, worst * (1.0 + jnp.where(usable, excess, 0.0)), losses)


def make_objective(losses: Callable, settings, penalty: Callable | None = None) -> Callable:
    """The tuner's training objective of ``losses: (theta, batch) -> (losses (B,), diverged (B,))``:
    ``(theta, batch, replaced=None) -> (objective, failed (B,))``, the robust objective of ``settings`` (a
    :class:`jaxobs.tuning.TuneSettings`) of the penalised losses (:func:`penalise_diverged`) plus
    ``settings.penalty_weight * penalty(theta)``; ``replaced`` (B,) marks plants whose inputs were replaced, which
    count as failed without a loss of their own."""

    def objective(theta, batch, replaced=None):
        values, diverged = losses(theta, batch)
        failed, own = jnp.asarray(diverged) | ~jnp.isfinite(values), None
        if replaced is not None:
            failed, own = failed | replaced, ~replaced
        penalised = penalise_diverged(values, failed, settings.divergence_factor, own)
        value = robust_objective(penalised, settings.objective, settings.cvar_alpha)
        if penalty is not None and settings.penalty_weight > 0:
            value = value + settings.penalty_weight * penalty(theta)
        return value, failed

    return objective


def value_and_grad(objective: Callable, mode: str = "reverse") -> Callable:
    """``theta -> ((value, aux), grad)`` of ``objective: theta -> (value, aux)``: reverse mode
    (``jax.value_and_grad``; one backward pass whatever the number of parameters) or forward mode
    (``jax.jacfwd``; one tangent per parameter, exact through ``while`` loops, and the cheaper choice
    for a few parameters on long rollouts since nothing is stored for a backward pass)."""
    if mode == "reverse":
        return jax.value_and_grad(objective, has_aux=True)
    if mode != "forward":
        raise ValueError(f"mode must be one of {GRADIENT_MODES}, got {mode!r}")

    def with_value(theta):
        value, aux = objective(theta)
        return value, (value, aux)

    def forward(theta):
        grad, (value, aux) = jax.jacfwd(with_value, has_aux=True)(theta)
        return (value, aux), grad

    return forward
