"""Gradient-based tuning of observer designs with optax: parameterisations, robust objectives, the loop.

A tuning problem (:class:`TuningProblem`) is a set of unconstrained parameters ``theta`` (a dict of arrays,
e.g. the log-diagonal of ``Q`` and ``log R`` of an AOB), a function giving one loss per plant of a batch
of mismatched plants (each a closed-loop rollout, e.g. in MuJoCo MJX), and a training and a held-out
batch. :func:`tune` minimises a robust objective of the training losses with optax; :func:`random_search`
is the gradient-free baseline at the same number of rollouts; :func:`evaluate` scores any ``theta`` on
the held-out batch.

Parameterisations (constrained values from unconstrained ``theta``; each with its inverse for starting
from a hand-set design):

* positive scalars and diagonals by ``exp`` (``log_q``, ``log_r``, ``log_sigma2``);
* full covariances by a Cholesky factor with a log-diagonal (:func:`cholesky_covariance`), so every
  ``theta`` gives a positive-definite ``Q`` and all correlations are reachable;
* factors in ``(0, 1)`` such as ``c`` of seed 000 eq. 55 by the logistic function (:func:`unit_interval`).

Robust objectives over the per-plant losses ``J_1..J_B``: the mean, and the conditional value at risk
``CVaR_alpha`` (the mean of the worst ``ceil(alpha B)`` losses), plus an optional penalty (e.g. on the
closed-loop spectral radius of :mod:`jaxobs.stability`).

The loop (:func:`tune`): optax (adam by default) after global-norm gradient clipping; a step whose
rollouts diverge (a non-finite loss or gradient, or a plant flagged by the problem) is rejected with a
logged message and retried from the last accepted point with half the step; early stopping when the
objective has not improved for ``patience`` evaluations; a progress bar showing the objective; checkpoints
every ``checkpoint_every`` evaluations, from which a rerun resumes (a corrupt or foreign checkpoint is an
error, never silently ignored).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

__all__ = [
    "cholesky_covariance",
    "cholesky_parameters",
    "unit_interval",
    "unit_interval_parameters",
    "cvar",
    "robust_objective",
    "value_and_grad",
    "TuningProblem",
    "TuneSettings",
    "TuneResult",
    "TuningError",
    "CheckpointError",
    "tune",
    "random_search",
    "evaluate",
]

logger = logging.getLogger("jaxobs.tune")

OBJECTIVES = ("mean", "cvar")
GRADIENT_MODES = ("reverse", "forward")
OPTIMIZERS = {"adam": optax.adam, "sgd": optax.sgd, "adabelief": optax.adabelief, "lamb": optax.lamb}


# --------------------------------------------------------------------------------------------
# Parameterisations


def cholesky_covariance(raw):
    """``Q = L L^T`` with ``L = tril(raw, -1) + diag(exp(diag(raw)))``: positive definite for every ``raw``
    (n, n) (the strict upper triangle of ``raw`` is ignored)."""
    lower = jnp.tril(raw, -1) + jnp.diag(jnp.exp(jnp.diagonal(raw)))
    return lower @ lower.T


def cholesky_parameters(cov):
    """The ``raw`` of :func:`cholesky_covariance` for a positive-definite ``cov`` (its inverse)."""
    lower = jnp.linalg.cholesky(jnp.asarray(cov))
    if not bool(jnp.all(jnp.isfinite(lower))):
        raise ValueError("cov must be symmetric positive definite for a Cholesky parameterisation")
    return jnp.tril(lower, -1) + jnp.diag(jnp.log(jnp.diagonal(lower)))


def unit_interval(raw):
    """A factor in ``(0, 1)`` (e.g. ``c`` of seed 000 eq. 55): the logistic function of ``raw``."""
    return jax.nn.sigmoid(raw)


def unit_interval_parameters(value):
    """The ``raw`` of :func:`unit_interval` (the logit); ``value`` must be in ``(0, 1)``."""
    value = jnp.asarray(value, float)
    if bool(jnp.any((value <= 0) | (value >= 1))):
        raise ValueError(f"value must lie strictly between 0 and 1, got {value}")
    return jnp.log(value) - jnp.log1p(-value)


# --------------------------------------------------------------------------------------------
# Robust objectives


def cvar(losses, alpha: float):
    """Conditional value at risk: the mean of the worst ``ceil(alpha B)`` of the ``B`` losses (``alpha`` in
    (0, 1]; ``alpha = 1`` is the mean). Differentiable almost everywhere (through ``lax.top_k``)."""
    if not 0 < alpha <= 1:
        raise ValueError(f"cvar alpha must be in (0, 1], got {alpha}")
    losses = jnp.ravel(losses)
    worst = max(1, math.ceil(alpha * losses.shape[0] - 1e-9))
    return jnp.mean(jax.lax.top_k(losses, worst)[0])


def robust_objective(losses, kind: str = "mean", alpha: float = 0.25):
    """``mean(losses)`` or ``cvar(losses, alpha)``."""
    if kind == "mean":
        return jnp.mean(losses)
    if kind == "cvar":
        return cvar(losses, alpha)
    raise ValueError(f"objective must be one of {OBJECTIVES}, got {kind!r}")


# --------------------------------------------------------------------------------------------
# Problem, settings, results


@dataclasses.dataclass(frozen=True)
class TuningProblem:
    """What to tune and against what.

    Attributes:
      theta0: unconstrained initial parameters, a dict of arrays (the hand-set design, usually).
      losses: ``(theta, batch) -> (losses, diverged)``, one loss and one divergence flag per plant of the
        batch (shape ``(B,)`` each); pure and differentiable in ``theta``. A flagged plant (e.g. a force
        beyond the sensor's range) rejects the optimiser step like a NaN does.
      train, heldout: batches of mismatched plants (pytrees with a leading batch axis), any structure that
        ``losses`` understands.
      penalty: optional ``theta -> scalar >= 0`` added with ``TuneSettings.penalty_weight``.
      describe: ``theta -> dict`` of readable (constrained) values for reports.
      responses: optional ``(theta, batch) -> dict`` of time series for a before/after figure: ``t`` (T,),
        ``output`` (B, T) or (B, T, k), ``desired`` (T,) or (T, k), ``labels`` (one per plant), ``ylabel``.
    """

    theta0: dict
    losses: Callable
    train: Any
    heldout: Any
    penalty: Callable | None = None
    describe: Callable = dict
    responses: Callable | None = None

    def batch_size(self, batch) -> int:
        return int(jax.tree.leaves(batch)[0].shape[0])


@dataclasses.dataclass(frozen=True)
class TuneSettings:
    """Settings of :func:`tune` (the ``[optimizer]`` table of ``jaxobs tune``'s config)."""

    optimizer: str = "adam"
    gradient: str = "reverse"  # "reverse" (value_and_grad) or "forward" (jacfwd: exact, for few parameters)
    learning_rate: float = 0.1
    steps: int = 50  # gradient evaluations at most (rejected ones included)
    objective: str = "mean"
    cvar_alpha: float = 0.25
    penalty_weight: float = 0.0
    clip_norm: float = 1.0  # global-norm gradient clipping; 0 disables it
    patience: int = 15  # early stopping: evaluations without an improvement of min_improvement
    min_improvement: float = 1e-3  # relative
    max_rejections: int = 8  # consecutive rejected steps before giving up
    checkpoint_every: int = 10

    def validate(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {', '.join(OPTIMIZERS)}, got {self.optimizer!r}")
        if self.gradient not in GRADIENT_MODES:
            raise ValueError(f"gradient must be one of {GRADIENT_MODES}, got {self.gradient!r}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {self.objective!r}")
        if not 0 < self.cvar_alpha <= 1:
            raise ValueError(f"cvar_alpha must be in (0, 1], got {self.cvar_alpha}")
        for name, low in (("learning_rate", 0.0), ("steps", 0), ("patience", 0), ("checkpoint_every", 0)):
            if not getattr(self, name) > low:
                raise ValueError(f"{name} must be > {low}, got {getattr(self, name)!r}")
        for name in ("penalty_weight", "clip_norm", "min_improvement", "max_rejections"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")

    def optax_transform(self) -> optax.GradientTransformation:
        base = OPTIMIZERS[self.optimizer](self.learning_rate)
        return optax.chain(optax.clip_by_global_norm(self.clip_norm), base) if self.clip_norm > 0 else base


class TuneResult(NamedTuple):
    theta: dict  # the best accepted parameters
    objective: float  # their training objective
    history: list  # one dict per evaluation: step, objective, accepted, reason, grad_norm, theta, seconds
    stopped: str  # why the loop ended: "steps", "early stopping"
    evaluations: int  # gradient evaluations (each is one rollout per training plant)
    rollouts: int  # evaluations x training batch size


class TuningError(RuntimeError):
    """Tuning cannot go on (e.g. the initial design diverges, or every retry of a step does)."""


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used (corrupt, or written for another problem or configuration)."""


def _objective_fn(problem: TuningProblem, settings: TuneSettings, batch):
    def objective(theta):
        losses, diverged = problem.losses(theta, batch)
        value = robust_objective(losses, settings.objective, settings.cvar_alpha)
        if problem.penalty is not None and settings.penalty_weight > 0:
            value = value + settings.penalty_weight * problem.penalty(theta)
        return value, (losses, diverged)

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


def _as_numpy(theta: dict) -> dict:
    return {k: np.asarray(v).tolist() for k, v in theta.items()}


def _failure(value, grad, diverged) -> str | None:
    """Why an evaluation is unusable, or None."""
    flagged = np.flatnonzero(np.asarray(diverged))
    if flagged.size:
        return f"the rollouts of {flagged.size} plant(s) diverged (first: plant {int(flagged[0])})"
    if not np.isfinite(float(value)):
        return f"the objective is {float(value)}"
    if grad is not None and not all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree.leaves(grad)):
        return "the gradient is not finite"
    return None


# --------------------------------------------------------------------------------------------
# Checkpoints


def _fingerprint(problem: TuningProblem, settings: TuneSettings, tag: str) -> str:
    shapes = {k: list(np.shape(v)) for k, v in problem.theta0.items()}
    fixed = {k: v for k, v in dataclasses.asdict(settings).items() if k != "steps"}  # more steps may continue a run
    text = json.dumps({"tag": tag, "settings": fixed, "theta": shapes}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _save_checkpoint(path: Path, trees: dict, meta: dict) -> None:
    arrays = {f"leaf{i}": np.asarray(leaf) for i, leaf in enumerate(jax.tree.leaves(trees))}
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, meta=np.array(json.dumps(meta)), **arrays)
    os.replace(tmp, path)


def _load_checkpoint(path: Path, template: dict, fingerprint: str) -> tuple[dict, dict]:
    """``(trees, meta)`` from ``path``; :class:`CheckpointError` naming the file for anything unusable."""
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            leaves, treedef = jax.tree.flatten(template)
            loaded = [data[f"leaf{i}"] for i in range(len(leaves))]
            if len(data.files) != len(leaves) + 1:
                raise ValueError(f"{len(data.files) - 1} arrays, expected {len(leaves)}")
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{path}: corrupt or unreadable checkpoint ({exc}); delete it to start over") from exc
    if meta.get("fingerprint") != fingerprint:
        raise CheckpointError(
            f"{path}: written for a different problem or settings; delete it (or use another --out) to start over"
        )
    for i, (new, old) in enumerate(zip(loaded, leaves, strict=True)):
        if new.shape != np.shape(old):
            raise CheckpointError(f"{path}: array {i} has shape {new.shape}, expected {np.shape(old)}")
    return jax.tree.unflatten(treedef, [jnp.asarray(x) for x in loaded]), meta


# --------------------------------------------------------------------------------------------
# The loop


def tune(
    problem: TuningProblem,
    settings: TuneSettings = TuneSettings(),
    *,
    checkpoint: str | Path | None = None,
    progress: bool = True,
    tag: str = "",
) -> TuneResult:
    """Minimise the robust objective of ``problem``'s training losses from ``problem.theta0``.

    Each evaluation computes the objective and its gradient (``jit(value_and_grad)``, one rollout per
    training plant). An accepted evaluation takes an optax step ``theta <- theta + s * update`` with step
    scale ``s`` (1 normally); a rejected one (see the module docstring) is logged, returns to the last
    accepted ``theta`` and retries with ``s / 2`` (``s`` doubles back towards 1 on each acceptance). The
    initial design must not diverge (:class:`TuningError`), nor may ``max_rejections`` retries in a row.

    Args:
      problem: the :class:`TuningProblem`.
      settings: :class:`TuneSettings`.
      checkpoint: a ``.npz`` path: written every ``settings.checkpoint_every`` evaluations and at the end,
        and resumed from when it exists (it must come from the same problem shapes, settings and ``tag``).
      progress: show a progress bar with the objective.
      tag: a string identifying the problem's configuration, checked when resuming.

    Returns:
      :class:`TuneResult` with the best accepted ``theta``.
    """
    from tqdm.auto import tqdm

    settings.validate()
    optimizer = settings.optax_transform()
    evaluate_with_grad = jax.jit(value_and_grad(_objective_fn(problem, settings, problem.train), settings.gradient))
    batch = problem.batch_size(problem.train)
    theta0 = {k: jnp.asarray(v) for k, v in problem.theta0.items()}
    zeros = jax.tree.map(jnp.zeros_like, theta0)
    trees = {"theta": theta0, "anchor": theta0, "update": zeros, "best": theta0, "opt": optimizer.init(theta0)}
    meta = {"evaluations": 0, "scale": 1.0, "best_objective": math.inf, "since_best": 0, "rejections": 0}
    history: list = []
    fingerprint = _fingerprint(problem, settings, tag)
    path = Path(checkpoint) if checkpoint is not None else None
    if path is not None and path.exists():
        trees, meta = _load_checkpoint(path, trees, fingerprint)
        history = meta.pop("history")
        logger.info("resuming from %s at evaluation %d", path, meta["evaluations"])

    def save():
        if path is not None:
            _save_checkpoint(path, trees, {**meta, "fingerprint": fingerprint, "history": history})

    stopped = "steps"
    bar = tqdm(total=settings.steps, initial=meta["evaluations"], desc="tune", disable=not progress, unit="eval")
    try:
        while meta["evaluations"] < settings.steps:
            start = time.perf_counter()
            (value, (_, diverged)), grad = evaluate_with_grad(trees["theta"])
            meta["evaluations"] += 1
            reason = _failure(value, grad, diverged)
            record = {
                "evaluation": meta["evaluations"],
                "objective": float(value) if np.isfinite(float(value)) else None,
                "accepted": reason is None,
                "reason": reason,
                "scale": meta["scale"],
                "grad_norm": float(optax.tree.norm(grad)) if reason is None else None,
                "theta": _as_numpy(trees["theta"]),
            }
            if reason is not None:
                if meta["evaluations"] == 1:
                    raise TuningError(f"the initial parameters fail on the training batch: {reason}")
                meta["rejections"] += 1
                meta["scale"] /= 2
                logger.warning(
                    "evaluation %d: step rejected: %s; retrying from the last accepted point with step scale %g",
                    meta["evaluations"], reason, meta["scale"],
                )  # fmt: skip
                if meta["rejections"] > settings.max_rejections:
                    save()
                    raise TuningError(
                        f"{meta['rejections']} consecutive steps rejected (last: {reason}); lower the learning rate"
                    )
                trees["theta"] = jax.tree.map(lambda a, u: a + meta["scale"] * u, trees["anchor"], trees["update"])
            else:
                meta["rejections"] = 0
                value = float(value)
                if value < meta["best_objective"] * (1 - settings.min_improvement):
                    meta["since_best"] = 0
                else:
                    meta["since_best"] += 1
                if value < meta["best_objective"]:
                    meta["best_objective"], trees["best"] = value, trees["theta"]
                update, trees["opt"] = optimizer.update(grad, trees["opt"], trees["theta"])
                meta["scale"] = min(1.0, 2 * meta["scale"])
                trees["anchor"], trees["update"] = trees["theta"], update
                trees["theta"] = jax.tree.map(lambda a, u: a + meta["scale"] * u, trees["theta"], update)
            record["seconds"] = time.perf_counter() - start
            history.append(record)
            bar.update(1)
            bar.set_postfix(
                objective=f"{value:.4g}" if reason is None else "rejected", best=f"{meta['best_objective']:.4g}"
            )
            if meta["evaluations"] % settings.checkpoint_every == 0:
                save()
            if meta["since_best"] >= settings.patience:
                stopped = "early stopping"
                break
    finally:
        bar.close()
    save()
    return TuneResult(
        trees["best"], meta["best_objective"], history, stopped, meta["evaluations"], meta["evaluations"] * batch
    )


class SearchResult(NamedTuple):
    theta: dict  # the best candidate
    objective: float
    objectives: np.ndarray  # per candidate (inf where it failed)
    rollouts: int


def random_search(
    problem: TuningProblem,
    settings: TuneSettings,
    num_candidates: int,
    *,
    spread: float = 2.0,
    seed: int = 0,
    progress: bool = True,
) -> SearchResult:
    """Gradient-free baseline: ``theta0`` and ``num_candidates - 1`` candidates ``theta0 + U(-spread, spread)``
    (per unconstrained coordinate: a factor up to ``e^spread`` on log-parameters), each scored by the same
    training objective as :func:`tune` (one rollout per training plant); the best finite one wins."""
    from tqdm.auto import tqdm

    settings.validate()
    if num_candidates < 1:
        raise ValueError(f"num_candidates must be >= 1, got {num_candidates}")
    objective = jax.jit(_objective_fn(problem, settings, problem.train))
    key = jax.random.PRNGKey(seed)
    theta0 = {k: jnp.asarray(v) for k, v in problem.theta0.items()}
    best, best_value, values = theta0, math.inf, []
    for i in tqdm(range(num_candidates), desc="random search", disable=not progress, unit="eval"):
        key, sub = jax.random.split(key)
        keys = dict(zip(theta0, jax.random.split(sub, len(theta0)), strict=True))
        candidate = theta0 if i == 0 else {
            k: v + jax.random.uniform(keys[k], v.shape, v.dtype, -spread, spread) for k, v in theta0.items()
        }  # fmt: skip
        value, (_, diverged) = objective(candidate)
        value = math.inf if _failure(value, None, diverged) else float(value)
        values.append(value)
        if value < best_value:
            best, best_value = candidate, value
    return SearchResult(best, best_value, np.asarray(values), num_candidates * problem.batch_size(problem.train))


def evaluate(problem: TuningProblem, theta: dict, settings: TuneSettings = TuneSettings(), batch=None) -> dict:
    """Scores of ``theta`` on ``batch`` (default: the held-out plants): the objective of ``settings``, the
    mean and the CVaR of the per-plant losses, the number of diverged plants, and the losses."""
    batch = problem.heldout if batch is None else batch
    losses, diverged = jax.jit(problem.losses)(theta, batch)
    losses = np.where(np.asarray(diverged), np.inf, np.asarray(losses))
    return {
        "objective": float(robust_objective(jnp.asarray(losses), settings.objective, settings.cvar_alpha)),
        "mean": float(np.mean(losses)),
        "cvar": float(cvar(jnp.asarray(losses), settings.cvar_alpha)),
        "diverged": int(np.sum(np.asarray(diverged))),
        "losses": losses,
    }
