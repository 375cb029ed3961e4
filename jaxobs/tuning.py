"""Gradient-based tuning of observer designs with optax: parameterisations, robust objectives, the loop.

A :class:`TuningProblem` is unconstrained parameters ``theta``, a function giving one loss per plant of a batch of
mismatched plants, and a training and a held-out batch. :func:`tune` minimises a robust objective (mean or CVaR)
of the training losses with any optax optimiser, with diverged plants penalised (:func:`penalise_diverged`),
checkpoints, and a stop when the objective has converged (a plateau); :func:`random_search` is the gradient-free
baseline; :func:`evaluate` scores a ``theta`` on the held-out batch. Parameterisations:
:func:`cholesky_covariance`, :func:`unit_interval`. The design of the loop: docs/theory/jobs.md and
docs/guides/tuning.md.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import json
import logging
import math
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxobs import _checks
from jaxobs._distributed import agree, from_process_0, json_from_process_0
from jaxobs._jit import Compiling
from jaxobs._resources import Interrupted, InterruptWatch, Stalled, StallWatch, compile_checked, temporary_path
from jaxobs.batching import safe_vmap

__all__ = [
    "cholesky_covariance",
    "cholesky_parameters",
    "unit_interval",
    "unit_interval_parameters",
    "cvar",
    "robust_objective",
    "penalise_diverged",
    "value_and_grad",
    "DEFAULT_OPTIMIZER",
    "lbfgs",
    "TuningProblem",
    "TuneSettings",
    "TuneResult",
    "StartResult",
    "gradient_mode",
    "FORWARD_MAX_PARAMETERS",
    "SearchResult",
    "TuningError",
    "CheckpointError",
    "tune",
    "random_search",
    "batch_objective",
    "evaluate",
]

logger = logging.getLogger("jaxobs.tuning")

OBJECTIVES = ("mean", "cvar")
GRADIENT_MODES = ("auto", "reverse", "forward")

FORWARD_MAX_PARAMETERS = 10
"""``gradient = "auto"`` differentiates in forward mode up to this many scalar parameters, in reverse mode above:
forward mode costs about one rollout's tangent per parameter, reverse mode a fixed multiple of the rollout (the
measured crossover on the MJX problems: docs/performance.md)."""

CANDIDATE_CHUNK = 16
"""Candidates scored per batched call (one ``vmap`` over candidates and plants) by the screening of :func:`tune` and
by :func:`random_search`."""

DEFAULT_OPTIMIZER = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(0.1))
"""The tuner's default optimiser: adam with step size 0.1 after clipping the gradient to global norm 1."""


# --------------------------------------------------------------------------------------------
# Parameterisations


def cholesky_covariance(raw):
    """``Q = L L^T`` with ``L = diag(exp(diag(raw))) (I + tril(raw, -1))``: positive definite for every ``raw``
    (..., n, n). The diagonal of ``raw`` holds log standard-deviation scales, its strict lower triangle
    dimensionless couplings (a row's entries relative to its own scale), so one search box fits covariances of any
    units; the strict upper triangle is ignored. Leading axes are batch axes.

    Example:
      >>> import jax.numpy as jnp
      >>> from jaxobs.tuning import cholesky_covariance
      >>> cholesky_covariance(jnp.array([[0.0, 0.0], [0.5, jnp.log(2.0)]])).tolist()
      [[1.0, 1.0], [1.0, 5.0]]
    """
    raw = jnp.asarray(raw)
    scale = jnp.exp(jnp.diagonal(raw, axis1=-2, axis2=-1))
    lower = scale[..., :, None] * (jnp.tril(raw, -1) + jnp.eye(raw.shape[-1], dtype=raw.dtype))
    return lower @ jnp.swapaxes(lower, -1, -2)


def cholesky_parameters(cov):
    """The ``raw`` of :func:`cholesky_covariance` for a positive-definite ``cov`` (..., n, n) (its inverse)."""
    lower = jnp.linalg.cholesky(jnp.asarray(cov))
    if not bool(jnp.all(jnp.isfinite(lower))):
        raise ValueError("cov must be symmetric positive definite for a Cholesky parameterisation")
    scale = jnp.diagonal(lower, axis1=-2, axis2=-1)
    n = lower.shape[-1]
    return jnp.tril(lower / scale[..., :, None], -1) + jnp.log(scale)[..., :, None] * jnp.eye(n, dtype=lower.dtype)


def unit_interval(raw):
    """A factor in ``(0, 1)`` (e.g. ``c`` of Cortesão 2006 eq. 55): the logistic function of ``raw``."""
    (raw,) = _checks.float_arrays(raw=raw)
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


def lbfgs(learning_rate: float = 1.0, memory_size: int = 10) -> optax.GradientTransformation:
    """L-BFGS directions (``optax.scale_by_lbfgs``) for a tuner that backtracks itself (``TuneSettings(lbfgs(),
    backtrack=True)``): no line search of its own, and its memory restarts whenever a pair of steps has
    non-positive curvature ``s'y <= 0`` (which a decrease-only line search does not exclude, and which would make
    the inverse-Hessian estimate indefinite, its direction possibly uphill); a restart's first step has norm at most
    ``learning_rate``."""
    inner = optax.scale_by_lbfgs(memory_size)

    def update(grads, state, params):
        curvature = optax.tree.vdot(optax.tree.sub(params, state.params), optax.tree.sub(grads, state.updates))
        restart = (state.count > 0) & ~(curvature > 0)
        state = jax.tree.map(lambda fresh, old: jnp.where(restart, fresh, old), inner.init(params), state)
        direction, state = inner.update(grads, state, params)
        return optax.tree.scale(-learning_rate, direction), state

    return optax.GradientTransformation(inner.init, update)


# --------------------------------------------------------------------------------------------
# Problem, settings, results


@dataclasses.dataclass(frozen=True)
class TuningProblem:
    """What to tune and against what.

    Attributes:
      theta0: unconstrained initial parameters, a dict of arrays (the hand-set design, usually).
      losses: ``(theta, batch) -> (losses, diverged)``, one loss and one divergence flag per plant of the
        batch (shape ``(B,)`` each); pure and differentiable in ``theta``, each plant's independent of the others
        (the batch is split over devices). A flagged plant (e.g. a force
        beyond the sensor's range) is penalised like a non-finite loss (see the module docstring).
      train, heldout: batches of mismatched plants (pytrees with a leading batch axis), any structure that
        ``losses`` understands.
      penalty: optional ``theta -> scalar >= 0`` added with ``TuneSettings.penalty_weight``.
      describe: ``theta -> dict`` of readable (constrained) values for reports.
      responses: optional ``(theta, batch) -> dict`` of time series for a before/after figure: ``t`` (T,),
        ``output`` (B, T) or (B, T, k), ``desired`` (T,) or (T, k), ``labels`` (one per plant), ``ylabel`` (one,
        or one per output) and optionally ``setpoint`` (scalar or (k,)).
      search_box: optional ``{name: (low, high)}`` bounds of ``theta`` (arrays of each entry's shape) for
        :func:`random_search`; entries with ``low == high`` stay fixed.
    """

    theta0: dict
    losses: Callable
    train: Any
    heldout: Any
    penalty: Callable | None = None
    describe: Callable = dict
    responses: Callable | None = None
    search_box: dict | None = None

    def batch_size(self, batch) -> int:
        """Number of plants in ``batch`` (the leading axis of its leaves)."""
        return int(jax.tree.leaves(batch)[0].shape[0])


@dataclasses.dataclass(frozen=True)
class TuneSettings:
    """Settings of :func:`tune` (the ``[optimizer]`` table of ``jaxobs tune``'s config).

    Attributes:
      optimizer: an ``optax.GradientTransformation`` (:data:`DEFAULT_OPTIMIZER`); one that takes extra arguments,
        such as ``optax.lbfgs()``, gets the objective as ``value_fn`` for its line search.
      gradient: "auto" (forward mode up to :data:`FORWARD_MAX_PARAMETERS` scalar parameters, else reverse),
        "reverse" (``value_and_grad``) or "forward" (``jacfwd``: exact, cheaper for few parameters).
      steps: the cap: gradient evaluations per start at most (rejected ones included).
      starts: starting points tuned together (one ``vmap`` over their optimiser states and rollouts); the result
        is the best of them on the training objective.
      screening: candidates drawn (scrambled Sobol) in the problem's search box and scored, batched, before the
        gradient runs: one start is the best of them and ``theta0``; more starts are ``theta0`` and the
        ``starts - 1`` best candidates (0: ``theta0`` alone, which needs ``starts == 1``).
      spread: half-width of the search box ``theta0 +- spread`` (unconstrained coordinates) when the problem has
        no ``search_box``.  seed: seed of the screening's draws.
      objective: "mean" or "cvar" of the per-plant losses.  cvar_alpha: the CVaR fraction of worst plants.
      penalty_weight: weight of the problem's penalty term (0: off).
      divergence_factor: a diverged plant's loss is this times the largest finite loss (see
        :func:`penalise_diverged`).
      patience: the plateau window: the run has converged after this many evaluations without a relative
        improvement of ``min_improvement`` of the best objective.
      min_improvement: relative improvement that resets ``patience``.
      max_rejections: consecutive rejected (diverging) steps before giving up.
      backtrack: also reject a step that does not lower the training objective below the start's best (a
        backtracking line search on the compiled evaluation: the step is halved; after ``max_rejections`` halvings
        in a row the start has converged), for a quasi-Newton direction without a line search of its own, such as
        :func:`lbfgs`: it then costs no evaluation beyond the tuner's own, and no compilation.
      checkpoint_every: evaluations between checkpoints.
    """

    optimizer: optax.GradientTransformation = DEFAULT_OPTIMIZER
    gradient: str = "auto"
    steps: int = 50
    starts: int = 1
    screening: int = 0
    spread: float = 2.0
    seed: int = 0
    objective: str = "mean"
    cvar_alpha: float = 0.25
    penalty_weight: float = 0.0
    divergence_factor: float = 10.0
    patience: int = 15
    min_improvement: float = 1e-3
    max_rejections: int = 8
    backtrack: bool = False
    checkpoint_every: int = 10

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid setting."""
        _checks.optimizer("optimizer", self.optimizer, "optax.adam(0.1)")
        if self.gradient not in GRADIENT_MODES:
            raise ValueError(f"gradient must be one of {GRADIENT_MODES}, got {self.gradient!r}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {self.objective!r}")
        if not 0 < self.cvar_alpha <= 1:
            raise ValueError(f"cvar_alpha must be in (0, 1], got {self.cvar_alpha}")
        for name, low in (("steps", 0), ("patience", 0), ("checkpoint_every", 0), ("starts", 0), ("spread", 0)):
            if not getattr(self, name) > low:
                raise ValueError(f"{name} must be > {low}, got {getattr(self, name)!r}")
        for name, low in (("penalty_weight", 0), ("min_improvement", 0), ("max_rejections", 0),
                          ("divergence_factor", 1), ("screening", 0), ("seed", 0)):  # fmt: skip
            if not getattr(self, name) >= low:
                raise ValueError(f"{name} must be >= {low}, got {getattr(self, name)!r}")


class StartResult(NamedTuple):
    """One starting point of :func:`tune`.

    Attributes:
      start: the starting ``theta``
      theta: its best accepted parameters (fewest diverged training plants, then lowest objective)
      objective: their training objective (inf when no evaluation was accepted)
      diverged: diverged training plants of ``theta``
      stopped: "converged" (the plateau rule of ``TuneSettings.patience``), "steps" (the cap), "rejected"
        (``max_rejections`` rejected steps in a row) or "failed" (the start fails on the training batch)
      evaluations: its gradient evaluations
      history: one dict per evaluation: evaluation, objective, diverged, accepted, reason, grad_norm, theta, ...
    """

    start: dict
    theta: dict
    objective: float
    diverged: int
    stopped: str
    evaluations: int
    history: list


class TuneResult(NamedTuple):
    """Result of :func:`tune`: the best of its starting points.

    Attributes:
      theta: the best accepted parameters of every start (fewest diverged training plants, then lowest objective)
      objective: their training objective
      history: the best start's evaluations, one dict each: evaluation, objective, diverged, accepted, reason,
        grad_norm, theta, ...
      stopped: why the best start ended: "converged" (the plateau rule) or "steps" (the cap), see
        :class:`StartResult`
      evaluations: gradient evaluations of every start together
      rollouts: rollouts computed, one per training plant for each screened candidate and for each start at each
        step of the loop (a start that has stopped is computed along with the others until all have)
      diverged: diverged training plants of the best theta
      seconds: wall time of the tuning over all runs that built this checkpoint, screening and compilation
        included
      starts: one :class:`StartResult` per starting point
      screened: candidates scored by the screening (``theta0`` included), 0 without one
      compile_seconds: this call's tracing and compiling of the gradient evaluation (part of ``seconds``; the
        screening's scorer is compiled before it, logged at INFO level)
    """

    theta: dict
    objective: float
    history: list
    stopped: str
    evaluations: int
    rollouts: int
    diverged: int
    seconds: float
    starts: tuple = ()
    screened: int = 0
    compile_seconds: float = 0.0

    @property
    def converged(self) -> bool:
        """Whether the best start stopped on the plateau rule (not on the cap ``TuneSettings.steps``)."""
        return self.stopped == "converged"


class TuningError(RuntimeError):
    """Tuning cannot go on (e.g. every training plant diverges under the initial design, or every retry of a
    step fails)."""


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used (corrupt, damaged, or written for another problem or configuration)."""


def _objective_fn(problem: TuningProblem, settings: TuneSettings, losses_fn: Callable):
    """``(theta, batch, replaced=None) -> (objective, failed)``: the robust objective of the penalised losses
    ``losses_fn(theta, batch)`` (plus the problem's penalty); ``replaced`` (B,) marks plants whose inputs were
    replaced, which count as failed without a loss of their own."""

    def objective(theta, batch, replaced=None):
        losses, diverged = losses_fn(theta, batch)
        failed, own = jnp.asarray(diverged) | ~jnp.isfinite(losses), None
        if replaced is not None:
            failed, own = failed | replaced, ~replaced
        penalised = penalise_diverged(losses, failed, settings.divergence_factor, own)
        value = robust_objective(penalised, settings.objective, settings.cvar_alpha)
        if problem.penalty is not None and settings.penalty_weight > 0:
            value = value + settings.penalty_weight * problem.penalty(theta)
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


# --------------------------------------------------------------------------------------------
# Rollouts spread over devices and processes

_AXIS = "plants"


def _mesh(devices: list) -> Mesh | None:
    """A 1-D mesh (axis "plants") over ``devices``; None for a single device."""
    return None if len(devices) == 1 else Mesh(np.array(devices), (_AXIS,))


def _place(batch, mesh: Mesh | None):
    """``batch`` padded to a multiple of the mesh's size with copies of its last plant, each process placing its
    own devices' rows (``NamedSharding`` over the batch axis); ``batch`` itself without a mesh."""
    if mesh is None:
        return batch
    size = int(jax.tree.leaves(batch)[0].shape[0])
    rows = np.minimum(np.arange(-(-size // mesh.size) * mesh.size), size - 1)
    sharding = NamedSharding(mesh, PartitionSpec(_AXIS))

    def put(leaf):
        padded = np.asarray(leaf)[rows]
        return jax.make_array_from_callback(padded.shape, sharding, padded.__getitem__)

    return jax.tree.map(put, batch)


@functools.lru_cache(maxsize=8)  # the same function for the same problem: jax.jit's caches hold across calls
def _spread(losses: Callable, mesh: Mesh | None, size: int) -> Callable:
    """``losses`` over a batch of ``size`` plants placed by :func:`_place`: each device runs the rollouts of its
    own rows (``jax.shard_map``), and the padding rows' losses are dropped, so that what follows (the objective,
    its gradient) is that of ``losses`` on the batch itself; the gradient's terms are summed across devices.
    ``losses`` itself without a mesh. ``losses`` must treat the plants independently (as a ``vmap`` does)."""
    if mesh is None:
        return losses
    spec = PartitionSpec(_AXIS)  # check_vma=False: rollouts may scan from constant carries
    per_device = jax.shard_map(losses, mesh=mesh, in_specs=(PartitionSpec(), spec), out_specs=spec, check_vma=False)
    return lambda theta, batch: jax.tree.map(lambda x: x[:size], per_device(theta, batch))


def _jit(fn: Callable, mesh: Mesh | None, rows: tuple[bool, ...]) -> Callable:
    """``jax.jit(fn)``; over a mesh, the arguments flagged in ``rows`` are batches placed by :func:`_place`, the
    others (and the outputs) replicated, so every process gets the whole result."""
    if mesh is None:
        return jax.jit(fn)
    replicated, placed = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec(_AXIS))
    return jax.jit(fn, in_shardings=tuple(placed if r else replicated for r in rows), out_shardings=replicated)


def _host(tree):
    """``tree``'s leaves as NumPy arrays (a replicated result of every process, or the arguments of a call)."""
    return jax.tree.map(np.asarray, tree)


def _compile_spread(build: Callable, batch, theta, what: str, hint: str, alone=None):
    """``(compiled, placed batch, mesh, seconds)``: ``build(mesh) -> fn(theta, batch)`` compiled over every device
    of every process (:func:`_jit`, memory checked by :func:`jaxobs._resources.compile_checked`), in ``seconds``
    (logged at INFO level). ``alone``: the program already lowered for a single device, used when there is one."""
    mesh = _mesh(jax.devices())
    placed = _place(batch, mesh)
    with Compiling(logger, what) as timer:
        if mesh is None and alone is not None:
            lowered = alone
        else:
            lowered = _jit(build(mesh), mesh, (False, True)).lower(_host(theta), placed)
        compiled = compile_checked(lowered, what, hint=hint)
    return compiled, placed, mesh, timer.seconds


_STALL_HINT = (
    "use fewer training plants, starts or screening candidates, or set NPROC=1 in the environment (one XLA "
    "intra-op thread); a checkpoint keeps the accepted steps"
)


def _stall_watch(what: str) -> StallWatch:
    """The :class:`jaxobs._resources.StallWatch` of a tuning job's computations."""
    return StallWatch(what, _STALL_HINT, cpu=jax.devices()[0].platform == "cpu")


def _watched(stall: StallWatch, label: str, fn: Callable, *args):
    """``fn(*args)`` (a computation, compiled or compiled on its first call) brought to the host under ``stall``'s
    watch."""
    with stall.waiting(label, program=id(fn)) as wait:
        wait["pending"] = fn(*args)
        return _host(wait["pending"])


def gradient_mode(settings: TuneSettings, theta: dict) -> str:
    """The differentiation mode of ``settings.gradient`` for parameters ``theta``: "auto" resolves to "forward" up
    to :data:`FORWARD_MAX_PARAMETERS` scalar parameters and to "reverse" above."""
    if settings.gradient != "auto":
        return settings.gradient
    count = sum(int(np.size(leaf)) for leaf in jax.tree.leaves(theta))
    return "forward" if count <= FORWARD_MAX_PARAMETERS else "reverse"


def _evaluations(problem: TuningProblem, settings: TuneSettings, mesh: Mesh | None):
    """``(evaluation, sound_gradient)`` of a stack of starting points (a leading axis on every leaf of ``theta``)
    on the training batch placed by :func:`_place`: ``(thetas, batch) -> ((objective, failed), grad)`` per start,
    and ``(thetas, batch, failed) -> grad`` with the failed plants' inputs replaced by the first sound plant's (so
    without their own gradient terms), for a reverse-mode gradient that a diverged rollout made non-finite (None in
    forward mode, where a failed plant's tangents stay in its own lane)."""
    size = problem.batch_size(problem.train)
    mode = gradient_mode(settings, problem.theta0)
    objective = _objective_fn(problem, settings, _spread(problem.losses, mesh, size))

    def evaluation(theta, batch):
        return value_and_grad(lambda th: objective(th, batch), mode)(theta)

    def sound_gradient(theta, batch, failed):
        keep = jnp.where(failed, jnp.argmin(failed), jnp.arange(size))
        keep = keep[np.minimum(np.arange(problem.batch_size(batch)), size - 1)]  # the padding rows copy the last
        sound = jax.tree.map(lambda x: x[keep], batch)
        return value_and_grad(lambda th: objective(th, sound, failed), mode)(theta)[1]

    starts = safe_vmap(evaluation, in_axes=(0, None))
    return starts, (safe_vmap(sound_gradient, in_axes=(0, None, 0)) if mode == "reverse" else None)


def _lower_gradient(evaluation: Callable, theta, batch, mode: str):
    """``jax.jit(evaluation)`` lowered on one device: traced, not run, so that a rollout reverse mode cannot
    differentiate is reported (:class:`TuningError`, one line) before anything is compiled or run."""
    try:
        return jax.jit(evaluation).lower(_host(theta), batch)
    except ValueError as exc:
        if mode == "reverse" and "Reverse-mode differentiation does not work for lax.while_loop" in str(exc):
            raise TuningError(
                "reverse mode cannot differentiate a while loop in the rollouts: give the loop a fixed count or a "
                "custom derivative (as jaxobs.mjx.common.solve does for MJX's constraint solver), or tune with "
                "gradient = 'forward'"
            ) from None
        raise


def _finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(tree))


def _failure(value, grad, failed, allowed: int) -> str | None:
    """Why an evaluation is rejected (more than ``allowed`` plants diverged, or a non-finite objective or
    gradient), or None."""
    failed = np.asarray(failed)
    count = int(failed.sum())
    if count == failed.size:
        return f"every one of the {count} plants diverged"
    if count > allowed:
        return f"{count} plant(s) diverged, {allowed} at the last accepted point"
    if not np.isfinite(float(value)):
        return f"the objective is {float(value)}"
    if grad is not None and not _finite(grad):
        return "the gradient is not finite"
    return None


def _agree(error: Exception | None, digest: bytes = b"") -> None:
    """:func:`jaxobs._distributed.agree` for a tuning run."""
    agree(error, digest, job="the tuning", kind="tuning", error_type=CheckpointError,
          differs="problem, training plants, settings or tag differ")  # fmt: skip


def _strong(theta: dict) -> dict:
    """``theta`` as JAX arrays of fixed (not weak) dtypes, the types the compiled evaluation is called with."""
    return {k: jnp.asarray(v).astype(jnp.asarray(v).dtype) for k, v in theta.items()}


def _as_numpy(theta: dict) -> dict:
    return {k: np.asarray(v).tolist() for k, v in theta.items()}


# --------------------------------------------------------------------------------------------
# Checkpoints

_META = {"iterations": int, "screened": int, "seconds": float, "lanes": list, "fingerprint": str, "arrays": int}
_LANE = {"evaluations": int, "scale": float, "best_objective": float, "best_diverged": int, "diverged": int,
         "since_best": int, "rejections": int, "stopped": str, "history": list}  # fmt: skip
_STOPS = ("", "converged", "steps", "rejected", "failed")  # "": still running


def _fingerprint(problem: TuningProblem, settings: TuneSettings, tag: str, program: str) -> str:
    """What a checkpoint was written for: the settings (but ``steps``: more may continue a run), the optimiser's
    state structure, ``tag``, ``theta``'s shapes, the ``program`` of one evaluation on one device (lowered text) and
    the training batch's values (an argument of it). An optimiser's hyperparameters are not visible in its state:
    ``tag`` names them (the TOML layer's tag does)."""
    shapes = {k: list(np.shape(v)) for k, v in problem.theta0.items()}
    fixed = {
        f.name: getattr(settings, f.name) for f in dataclasses.fields(settings) if f.name not in ("steps", "optimizer")
    }
    state = jax.eval_shape(settings.optimizer.init, _strong(problem.theta0))
    fixed["optimizer"] = f"{jax.tree.structure(state)} {[(x.shape, str(x.dtype)) for x in jax.tree.leaves(state)]}"
    text = json.dumps({"tag": tag, "settings": fixed, "theta": shapes, "jax": jax.__version__}, sort_keys=True)
    digest = hashlib.sha256((text + program).encode())
    for leaf in jax.tree.leaves(problem.train):
        leaf = np.asarray(leaf)
        digest.update(f"{leaf.dtype}{leaf.shape}".encode() + np.ascontiguousarray(leaf).tobytes())
    return digest.hexdigest()[:16]


def _save_checkpoint(path: Path, trees: dict, meta: dict) -> None:
    arrays = {f"leaf{i}": np.asarray(leaf) for i, leaf in enumerate(jax.tree.leaves(trees))}
    tmp = temporary_path(path, ".tmp.npz")
    try:
        np.savez(tmp, meta=np.array(json.dumps({**meta, "arrays": len(arrays)})), **arrays)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def _fields_problem(record: dict, fields: dict, where: str) -> str | None:
    """What makes ``record`` (a JSON object) miss or mistype one of ``fields``, or None."""
    for key, kind in fields.items():
        value = record.get(key)
        ok = isinstance(value, int | float) if kind is float else isinstance(value, kind)
        if not ok or isinstance(value, bool):
            return f"{where}{key} is {'missing' if key not in record else repr(value)}, expected {kind.__name__}"
    numbers = [record[k] for k, kind in fields.items() if kind in (int, float)]
    if not all(math.isfinite(v) and v >= 0 for v in numbers if v != math.inf):
        return f"{where[:-1]} holds a negative or non-finite count, scale or objective"
    return None


def _meta_problem(meta) -> str | None:
    """What makes a checkpoint's ``meta`` unusable, or None."""
    if not isinstance(meta, dict):
        return f"meta is a JSON {type(meta).__name__}, not an object"
    problem = _fields_problem(meta, _META, "meta.")
    if problem is not None:
        return problem
    if not meta["lanes"]:
        return "meta.lanes is empty"
    for k, lane in enumerate(meta["lanes"]):
        where = f"meta.lanes[{k}]."
        problem = _fields_problem(lane, _LANE, where) if isinstance(lane, dict) else f"{where[:-1]} is not an object"
        if problem is not None:
            return problem
        if lane["scale"] <= 0 or lane["stopped"] not in _STOPS:
            return f"{where[:-1]} holds a scale or stop reason out of range"
        if len(lane["history"]) != lane["evaluations"] or not all(isinstance(h, dict) for h in lane["history"]):
            return f"{where}history has {len(lane['history'])} entries for {lane['evaluations']} evaluations"
    return None


def _load_checkpoint(path: Path, template: dict) -> tuple[dict, dict]:
    """``(trees, meta)`` from ``path``; :class:`CheckpointError` naming the file for anything unusable but the
    fingerprint (checked by the caller)."""
    leaves, treedef = jax.tree.flatten(template)
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            count = len(data.files) - 1
            loaded = [data[f"leaf{i}"] for i in range(min(count, len(leaves)))]
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise CheckpointError(f"{path}: corrupt or unreadable checkpoint ({exc}); delete it to start over") from exc
    problem = _meta_problem(meta)
    if problem is None and count != meta["arrays"]:
        problem = f"{count} arrays, written with {meta['arrays']}"
    if problem is not None:
        raise CheckpointError(f"{path}: damaged checkpoint ({problem}); delete it to start over")
    other = f"{count} arrays, expected {len(leaves)}" if count != len(leaves) else None
    for i, (new, old) in enumerate(zip(loaded, leaves, strict=False)):
        if other is None and new.shape != np.shape(old):
            other = f"array {i} has shape {new.shape}, expected {np.shape(old)}"
    if other is None and len(meta["lanes"]) != np.shape(leaves[0])[0]:
        other = f"{len(meta['lanes'])} starts, expected {np.shape(leaves[0])[0]}"
    if other is not None:  # another optimiser, parameter layout or number of starts
        raise CheckpointError(
            f"{path}: written for a different problem, program or settings ({other}); delete it (or use another "
            "--out) to start over"
        )
    for i, new in enumerate(loaded):
        if new.dtype.kind in "fc" and not np.all(np.isfinite(new)):
            raise CheckpointError(f"{path}: array {i} holds NaN or infinite values; delete it to start over")
    meta.pop("arrays")
    return jax.tree.unflatten(treedef, list(loaded)), meta


# --------------------------------------------------------------------------------------------
# Candidates: the screening of tune and the random search


def _search_box(problem: TuningProblem, spread: float) -> dict:
    if problem.search_box is not None:
        return {k: (np.asarray(lo), np.asarray(hi)) for k, (lo, hi) in problem.search_box.items()}
    return {k: (np.asarray(v) - spread, np.asarray(v) + spread) for k, v in problem.theta0.items()}


def _in_box(box: dict, theta0: dict, unit: np.ndarray) -> dict:
    """Candidates (a leading axis of ``len(unit)``) at the points ``unit`` (N, size) of the unit cube mapped onto
    ``box``, coordinate by coordinate in the order of ``theta0``'s entries; entries with ``low == high`` stay."""
    stacked, offset = {}, 0
    for name, value in theta0.items():
        low, high = (np.broadcast_to(np.asarray(b, value.dtype), value.shape) for b in box[name])
        size = value.size
        part = unit[:, offset : offset + size].reshape((len(unit), *value.shape))
        stacked[name] = (low + part * (high - low)).astype(value.dtype)
        offset += size
    return stacked


def _row(stacked: dict, i: int) -> dict:
    return {k: v[i] for k, v in stacked.items()}


def batch_objective(problem: TuningProblem, settings: TuneSettings = TuneSettings()) -> Callable:
    """A compiled scorer of candidate parameters for gradient-free searches: ``candidates -> (objectives,
    diverged)`` for ``candidates``, a dict like ``theta0`` with a leading axis of any length N, scored
    :data:`CANDIDATE_CHUNK` at a time (one ``vmap`` over candidates and training plants per call, spread over the
    devices like :func:`tune`'s rollouts). ``objectives`` (N,) is :func:`tune`'s training objective (inf where
    every plant diverged or it is not finite), ``diverged`` (N,) the count of diverged training plants. The
    screening of :func:`tune` and :func:`random_search` use it; so can CMA-ES or any ask/tell optimiser.

    Example::

        >>> import jax.numpy as jnp, numpy as np
        >>> from jaxobs.tuning import TuningProblem, batch_objective
        >>> losses = lambda theta, t: ((theta["x"] - t) ** 2, t < -1e9)
        >>> problem = TuningProblem({"x": jnp.array(0.0)}, losses, jnp.array([1.0, 3.0]), jnp.array([2.0]))
        >>> batch_objective(problem)({"x": np.array([0.0, 2.0])})[0].tolist()
        [5.0, 1.0]
    """
    size = problem.batch_size(problem.train)
    chunk = {k: np.repeat(np.asarray(v)[None], CANDIDATE_CHUNK, 0) for k, v in _strong(problem.theta0).items()}
    score, train, _, _ = _compile_spread(
        lambda mesh: safe_vmap(_objective_fn(problem, settings, _spread(problem.losses, mesh, size)), (0, None)),
        problem.train, chunk, f"{CANDIDATE_CHUNK} candidates' {size} training rollouts each",
        hint="use fewer training plants",
    )  # fmt: skip

    def scores(candidates: dict):
        count = len(next(iter(candidates.values())))
        rows = np.minimum(np.arange(-(-count // CANDIDATE_CHUNK) * CANDIDATE_CHUNK), count - 1)  # pad with the last
        values, diverged = [], []
        with _stall_watch(f"scoring {count} candidates") as stall:
            for first in range(0, rows.size, CANDIDATE_CHUNK):
                part = {k: v[rows[first : first + CANDIDATE_CHUNK]] for k, v in candidates.items()}
                value, failed = _watched(stall, f"candidates {first} to {first + CANDIDATE_CHUNK - 1}", score, part,
                                         train)  # fmt: skip
                counts = np.sum(np.asarray(failed), axis=1)
                values.append(np.where((counts < size) & np.isfinite(value), value, np.inf))
                diverged.append(counts)
        return np.concatenate(values)[:count], np.concatenate(diverged)[:count]

    return scores


def _screen(problem: TuningProblem, settings: TuneSettings, count: int) -> tuple[dict, dict]:
    """``(starts, report)``: ``settings.screening`` scrambled-Sobol candidates in the search box and ``theta0``
    scored, and the starts stacked: the best of them (fewest diverged plants, then lowest objective) for one start;
    for ``count > 1``, ``theta0`` and the ``count - 1`` best others. The report gives the screened count and the
    starts' objectives."""
    from scipy.stats import qmc

    theta0 = {k: np.asarray(v) for k, v in _strong(problem.theta0).items()}
    dim = sum(v.size for v in theta0.values())
    sobol = qmc.Sobol(dim, scramble=True, seed=settings.seed)
    unit = sobol.random_base2(max(0, math.ceil(math.log2(settings.screening))))[: settings.screening]
    drawn = _in_box(_search_box(problem, settings.spread), theta0, unit)
    candidates = {k: np.concatenate([theta0[k][None], drawn[k]]) for k in theta0}
    values, diverged = batch_objective(problem, settings)(candidates)
    order = np.lexsort((values, diverged))
    if count > 1:  # theta0 first, its basin may hold a better minimum than a lower screened point's
        order = np.concatenate([[0], order[order != 0]])
    order = order[:count]
    starts = {k: v[order] for k, v in candidates.items()}
    return starts, {"screened": int(values.size), "theta0": float(values[0]), "best": values[order].tolist()}


# --------------------------------------------------------------------------------------------
# The loop


def _new_lane(batch: int) -> dict:
    return {"evaluations": 0, "scale": 1.0, "best_objective": math.inf, "best_diverged": batch, "diverged": batch,
            "since_best": 0, "rejections": 0, "stopped": ""}  # fmt: skip


def _per_start(values: np.ndarray, leaf) -> np.ndarray:
    """``values`` (K,), one per start, shaped to broadcast against ``leaf`` (K, ...)."""
    return values.reshape((-1,) + (1,) * (np.ndim(leaf) - 1))


def _where(mask: np.ndarray, new, old):
    """Per start (the leading axis): ``new`` where ``mask``, else ``old``, leaf by leaf."""
    return jax.tree.map(lambda a, b: np.where(_per_start(mask, a), a, b), new, old)


def _initial(problem: TuningProblem, settings: TuneSettings, initial) -> tuple[dict, int]:
    """The stacked starting points and their count: ``initial`` (a list of ``theta``), else ``theta0`` repeated
    ``settings.starts`` times (the screening, if any, replaces them)."""
    theta0 = {k: np.asarray(v) for k, v in _strong(problem.theta0).items()}
    if initial is None:
        if settings.starts > 1 and settings.screening < settings.starts - 1:
            raise ValueError(
                f"starts = {settings.starts} needs screening >= {settings.starts - 1} candidates to start from (or "
                "pass initial=)"
            )
        return {k: np.repeat(v[None], settings.starts, 0) for k, v in theta0.items()}, settings.starts
    initial = list(initial)
    if not initial:
        raise ValueError("initial must hold at least one theta")
    for i, theta in enumerate(initial):
        shapes = {k: np.shape(v) for k, v in theta.items()} if isinstance(theta, dict) else None
        if shapes != {k: v.shape for k, v in theta0.items()}:
            want = {k: v.shape for k, v in theta0.items()}
            raise ValueError(f"initial[{i}] must have theta0's entries and shapes {want}, got {shapes}")
    return {k: np.stack([np.asarray(t[k], v.dtype) for t in initial]) for k, v in theta0.items()}, len(initial)


def tune(
    problem: TuningProblem,
    settings: TuneSettings = TuneSettings(),
    *,
    initial: list[dict] | None = None,
    checkpoint: str | Path | None = None,
    progress: bool = True,
    tag: str = "",
) -> TuneResult:
    """Minimise the robust objective of ``problem``'s training losses from one or more starting points.

    The starting points are ``initial`` if given, else ``theta0``, or with ``settings.screening`` candidates: the
    best of them and ``theta0`` for one start, ``theta0`` and the ``settings.starts - 1`` best for more. They run
    together: each step evaluates the objective and its gradient at every start in one call (one rollout per
    training plant and start). An accepted evaluation takes an optax step ``theta <- theta + s * update`` with step
    scale ``s`` (1 normally); a rejected one (see the module docstring; with ``backtrack``, also a step that does
    not improve) returns to the start's last accepted ``theta`` and retries with ``s / 2`` (``s`` doubles back
    towards 1 on each acceptance). A start stops when it has converged (no relative improvement of
    ``min_improvement`` in ``patience`` evaluations, or ``max_rejections`` backtracking halvings in a row), at the
    cap ``steps``, or after ``max_rejections`` diverging steps in a row; each start's run is the run :func:`tune`
    makes from it alone. Training
    plants that diverge at a start are penalised and logged; a start that fails on every plant is dropped, and
    when every start fails (or every one ends in rejections) a :class:`TuningError` says why.

    Args:
      problem: the :class:`TuningProblem`.
      settings: :class:`TuneSettings`.
      initial: starting points (a list of dicts shaped like ``theta0``), replacing ``theta0`` and the screening.
      checkpoint: a ``.npz`` path: written after the screening, every ``settings.checkpoint_every`` steps, at the
        end and on Ctrl-C, and resumed from when it exists (it must come from the same problem, program, settings
        and ``tag``).
      progress: show a progress bar with the objective.
      tag: a string identifying the problem's configuration, checked when resuming.

    Returns:
      :class:`TuneResult` with the best accepted ``theta`` over the starts. Ctrl-C raises
      :class:`jaxobs._resources.Interrupted` after saving the checkpoint.

    Example::

        >>> import jax.numpy as jnp, optax
        >>> from jaxobs.tuning import TuneSettings, TuningProblem, tune
        >>> losses = lambda theta, t: ((theta["x"] - t) ** 2, t < -1e9)
        >>> problem = TuningProblem({"x": jnp.array(0.0)}, losses, jnp.array([1.0, 3.0]), jnp.array([2.0]))
        >>> result = tune(problem, TuneSettings(optax.adam(0.3), starts=4, screening=15), progress=False)
        >>> round(float(result.theta["x"]), 2), len(result.starts)
        (2.0, 4)
    """
    from tqdm.auto import tqdm

    settings.validate()
    start = time.perf_counter()
    optimizer = optax.with_extra_args_support(settings.optimizer)
    batch = problem.batch_size(problem.train)
    thetas, count = _initial(problem, settings, initial)
    mode = gradient_mode(settings, problem.theta0)

    def fresh(thetas):
        zeros = jax.tree.map(np.zeros_like, thetas)
        opt = _host(jax.vmap(optimizer.init)(thetas))
        return {"start": thetas, "theta": thetas, "anchor": thetas, "update": zeros, "best": thetas, "opt": opt}

    trees = fresh(thetas)
    meta = {"iterations": 0, "screened": 0, "seconds": 0.0, "lanes": [_new_lane(batch) for _ in range(count)]}
    path = Path(checkpoint) if checkpoint is not None else None
    writer = jax.process_index() == 0  # process 0 alone reads and writes the checkpoint; the others follow it
    resume, error = writer and path is not None and path.exists(), None
    if resume:  # a damaged checkpoint is reported before the evaluation is traced
        try:
            trees, meta = _load_checkpoint(path, trees)
        except CheckpointError as exc:
            error = exc
    _agree(error)
    evaluation = _evaluations(problem, settings, None)[0]
    what = f"one evaluation of the {batch} training rollouts at {count} start(s), {mode}-mode gradient"
    with Compiling(logger, f"{what} (tracing)") as tracing:
        lowered = _lower_gradient(evaluation, thetas, problem.train, mode)  # the fingerprint's program
    given = "" if initial is None else json.dumps(_as_numpy(thetas))  # the starting points, when given
    fingerprint = _fingerprint(problem, settings, tag + given, lowered.as_text())
    if resume and meta.pop("fingerprint") != fingerprint:
        error = CheckpointError(
            f"{path}: written for a different problem, program or settings; delete it (or use another --out) "
            "to start over"
        )
    _agree(error, bytes.fromhex(fingerprint))
    trees, meta = _host(from_process_0(trees)), json_from_process_0(meta)
    lanes = meta["lanes"]
    histories = [lane.pop("history", []) for lane in lanes]
    for lane in lanes:  # a larger cap continues the starts the former one stopped
        if lane["stopped"] == "steps" and lane["evaluations"] < settings.steps:
            lane["stopped"] = ""
    previous_seconds = meta["seconds"]

    def save(trees, meta, histories):
        meta["seconds"] = previous_seconds + time.perf_counter() - start
        if path is not None and writer:
            lanes = [{**lane, "history": h} for lane, h in zip(meta["lanes"], histories, strict=True)]
            _save_checkpoint(path, trees, {**meta, "lanes": lanes, "fingerprint": fingerprint})

    if resume:
        logger.info("resuming from %s at step %d", path, meta["iterations"])
    elif initial is None and settings.screening > 0:
        screened, report = _screen(problem, settings, count)
        trees, meta["screened"] = fresh(screened), report["screened"]
        logger.info("screened %d candidates: objective %.4g at theta0, best %s", report["screened"],
                    report["theta0"], ", ".join(f"{v:.4g}" for v in report["best"]))  # fmt: skip
        save(trees, meta, histories)
    evaluate_with_grad, train, mesh, compile_seconds = _compile_spread(
        lambda mesh: _evaluations(problem, settings, mesh)[0], problem.train, trees["theta"], what,
        hint="use fewer training plants or starts, shorter rollouts or a gradient_horizon", alone=lowered,
    )  # fmt: skip
    compile_seconds += tracing.seconds
    sound_gradient = _evaluations(problem, settings, mesh)[1]
    sound_gradient = sound_gradient and _jit(sound_gradient, mesh, (False, True, False))  # compiled if ever needed
    objective = _objective_fn(problem, settings, _spread(problem.losses, mesh, batch))

    def step_update(grad, state, theta, value, placed):  # value_fn: the objective, for a line search (L-BFGS)
        return optimizer.update(
            grad, state, theta, value=value, grad=grad, value_fn=lambda th: objective(th, placed)[0]
        )

    update_step = _jit(jax.vmap(step_update, in_axes=(0, 0, 0, 0, None)), mesh, (False,) * 4 + (True,))
    named = (lambda k: f"start {k}: ") if count > 1 else (lambda k: "")
    bar = tqdm(total=settings.steps, initial=meta["iterations"], desc=f"tune (compiled in {compile_seconds:.1f} s)",
               disable=not (progress and writer), unit="step")  # fmt: skip
    saved = (dict(trees), copy.deepcopy(meta), [len(h) for h in histories])
    with InterruptWatch() as watch, _stall_watch("the tuning") as stall:
        try:
            while meta["iterations"] < settings.steps and not all(lane["stopped"] for lane in lanes):
                watch.check()
                saved = (dict(trees), copy.deepcopy(meta), [len(h) for h in histories])  # consistent, for Ctrl-C
                step_start = time.perf_counter()
                label = f"evaluation {meta['iterations'] + 1}"
                (values, failed), grads = _watched(stall, label, evaluate_with_grad, trees["theta"], train)
                counts = np.sum(failed, axis=1)
                running = np.array([not lane["stopped"] for lane in lanes])
                poisoned = running & (counts > 0) & (counts < batch)
                poisoned &= ~np.all(
                    [np.all(np.isfinite(g), axis=tuple(range(1, g.ndim))) for g in jax.tree.leaves(grads)], 0
                )
                if sound_gradient is not None and poisoned.any():
                    sound = _watched(stall, label, sound_gradient, trees["theta"], train, failed)
                    grads = _where(poisoned, sound, grads)
                meta["iterations"] += 1
                accepted, rejected = np.zeros(count, bool), np.zeros(count, bool)
                for k in np.flatnonzero(running):
                    lane, grad = lanes[k], jax.tree.map(lambda g, k=k: g[k], grads)
                    first = lane["evaluations"] == 0
                    lane["evaluations"] += 1
                    value, diverged = values[k], int(counts[k])
                    reason = _failure(value, grad, failed[k], batch - 1 if first else lane["diverged"])
                    best = (lane["best_diverged"], lane["best_objective"])
                    rose = reason is None and settings.backtrack and not first and (diverged, float(value)) >= best
                    if rose:
                        reason = f"the objective rose to {float(value):.6g} from {best[1]:.6g}"
                    record = {
                        "evaluation": lane["evaluations"],
                        "objective": float(value) if np.isfinite(float(value)) else None,
                        "diverged": diverged,
                        "accepted": reason is None,
                        "reason": reason,
                        "scale": lane["scale"],
                        "grad_norm": float(optax.tree.norm(grad)) if reason is None else None,
                        "theta": _as_numpy(_row(trees["theta"], k)),
                        "seconds": time.perf_counter() - step_start,
                    }
                    histories[k].append(record)
                    if reason is not None and first:
                        lane["stopped"] = "failed"
                        logger.warning("%sthe starting point fails on the training batch: %s", named(k), reason)
                    elif rose:  # backtracking: a shorter step along the same update; none improves: a minimum
                        rejected[k] = True
                        lane["rejections"] += 1
                        lane["scale"] /= 2
                        logger.info("%sevaluation %d: %s; step scale %g", named(k), lane["evaluations"], reason,
                                    lane["scale"])  # fmt: skip
                        if lane["rejections"] > settings.max_rejections:
                            lane["stopped"] = "converged"
                    elif reason is not None:
                        rejected[k] = True
                        lane["rejections"] += 1
                        lane["scale"] /= 2
                        logger.warning(
                            "%sevaluation %d: step rejected: %s; retrying from the last accepted point with step "
                            "scale %g", named(k), lane["evaluations"], reason, lane["scale"],
                        )  # fmt: skip
                        if lane["rejections"] > settings.max_rejections:
                            lane["stopped"] = "rejected"
                    else:
                        if first and diverged:
                            logger.warning(
                                "%s%d of %d training plants diverge under the initial design; each counts as at "
                                "least %g times the largest loss of the others", named(k), diverged, batch,
                                settings.divergence_factor,
                            )  # fmt: skip
                        accepted[k] = True
                        lane["rejections"], lane["diverged"], value = 0, diverged, float(value)
                        improved = diverged < lane["best_diverged"] or value < lane["best_objective"] * (
                            1 - settings.min_improvement
                        )
                        lane["since_best"] = 0 if improved else lane["since_best"] + 1
                        if (diverged, value) < (lane["best_diverged"], lane["best_objective"]):
                            lane["best_diverged"], lane["best_objective"] = diverged, value
                            trees["best"] = _where(np.arange(count) == k, trees["theta"], trees["best"])
                        lane["scale"] = min(1.0, 2 * lane["scale"])
                        if lane["since_best"] >= settings.patience:
                            lane["stopped"] = "converged"
                    if not lane["stopped"] and lane["evaluations"] >= settings.steps:
                        lane["stopped"] = "steps"
                if all(lane["stopped"] == "failed" for lane in lanes):
                    reasons = "; ".join(h[-1]["reason"] for h in histories if h)
                    raise TuningError(
                        f"the initial parameters fail on the training batch: {reasons}" if count == 1 else
                        f"every one of the {count} starting points fails on the training batch: {reasons}"
                    )  # fmt: skip
                scale = np.array([lane["scale"] for lane in lanes])
                if accepted.any():
                    update, opt = _watched(stall, label, update_step, grads, trees["opt"], trees["theta"], values,
                                           train)  # fmt: skip
                    trees["opt"] = _where(accepted, opt, trees["opt"])
                    trees["anchor"] = _where(accepted, trees["theta"], trees["anchor"])
                    trees["update"] = _where(accepted, update, trees["update"])
                moved = jax.tree.map(lambda a, u, s=scale: a + _per_start(s, a) * u, trees["anchor"], trees["update"])
                trees["theta"] = _where(accepted | rejected, moved, trees["theta"])
                bar.update(1)
                best = min(lane["best_objective"] for lane in lanes)
                bar.set_postfix(best=f"{best:.4g}", running=int(sum(not lane["stopped"] for lane in lanes)))
                if meta["iterations"] % settings.checkpoint_every == 0:
                    save(trees, meta, histories)
                if all(lane["stopped"] in ("rejected", "failed") for lane in lanes):
                    save(trees, meta, histories)
                    last = next(h[-1]["reason"] for h in histories if h and h[-1]["reason"])
                    rejections = max(lane["rejections"] for lane in lanes)
                    raise TuningError(
                        f"{rejections} consecutive steps rejected (last: {last}); lower the learning rate"
                    )
        except (KeyboardInterrupt, Stalled) as exc:
            trees, meta, done = saved
            histories = [h[:n] for h, n in zip(histories, done, strict=True)]
            where = ""
            if meta["iterations"] > 0 and path is not None and writer:
                save(trees, meta, histories)
                where = f"; checkpoint saved to {path}"
            if isinstance(exc, Stalled):
                raise Stalled(f"{exc}{where}") from None
            raise Interrupted(
                f"interrupted after {meta['iterations']} of {settings.steps} evaluations{where}; "
                "rerun the same command to resume"
            ) from exc
        finally:
            bar.close()
    save(trees, meta, histories)
    starts = tuple(
        StartResult(
            _row(trees["start"], k),
            _row(trees["best"], k),
            lane["best_objective"],
            lane["best_diverged"],
            lane["stopped"] or "steps",
            lane["evaluations"],
            histories[k],
        )  # fmt: skip
        for k, lane in enumerate(lanes)
    )
    best = min(range(count), key=lambda k: (starts[k].diverged, starts[k].objective))
    return TuneResult(
        starts[best].theta, starts[best].objective, starts[best].history, starts[best].stopped,
        sum(s.evaluations for s in starts), (meta["screened"] + meta["iterations"] * count) * batch,
        starts[best].diverged, meta["seconds"], starts, meta["screened"], compile_seconds,
    )  # fmt: skip


class SearchResult(NamedTuple):
    """Result of :func:`random_search`.

    Attributes:
      candidates: every candidate theta, the first being theta0
      objectives: training objective per candidate (inf where every plant diverged)
      diverged: diverged training plants per candidate
      elapsed: wall time (s) when each candidate's score was known, compilation included
      rollouts_per_candidate: training plants each candidate was rolled out on
    """

    candidates: list
    objectives: np.ndarray
    diverged: np.ndarray
    elapsed: np.ndarray
    rollouts_per_candidate: int

    def best(self, count: int | None = None) -> tuple[dict, float, int]:
        """``(theta, objective, diverged)`` of the best of the first ``count`` candidates (default: all): the
        fewest diverged plants, then the lowest objective."""
        count = len(self.candidates) if count is None else count
        i = min(range(count), key=lambda j: (self.diverged[j], self.objectives[j]))
        return self.candidates[i], float(self.objectives[i]), int(self.diverged[i])

    def within(self, seconds: float) -> int:
        """How many candidates were scored within ``seconds`` (at least 1)."""
        return max(1, int(np.searchsorted(self.elapsed, seconds, side="right")))


def random_search(
    problem: TuningProblem,
    settings: TuneSettings,
    num_candidates: int,
    *,
    seconds: float = 0.0,
    spread: float | None = None,
    seed: int = 0,
    progress: bool = True,
) -> SearchResult:
    """Gradient-free baseline: ``theta0``, then candidates drawn uniformly from ``problem.search_box`` (default:
    ``theta0 +- spread`` per unconstrained coordinate, a factor up to ``e^spread`` on log-parameters), each
    scored by the same penalised training objective as :func:`tune` (one rollout per training plant),
    :data:`CANDIDATE_CHUNK` candidates per batched call. Draws at least ``num_candidates`` and goes on, a chunk at
    a time, until ``seconds`` of wall time (compilation included) have passed, so that one search gives the
    baseline at equal rollouts (:meth:`SearchResult.best` of the first ones) and at equal wall time
    (:meth:`SearchResult.within`).

    Args:
      problem: the :class:`TuningProblem`.  settings: the objective's settings (as for :func:`tune`).
      num_candidates: candidates drawn at least.  seconds: keep drawing until this much wall time has passed.
      spread: half-width of the default box in unconstrained coordinates (default ``settings.spread``).
      seed: seed of the draws.  progress: show a progress bar.
    """
    from tqdm.auto import tqdm

    settings.validate()
    if num_candidates < 1:
        raise ValueError(f"num_candidates must be >= 1, got {num_candidates}")
    start = time.perf_counter()
    scores = batch_objective(problem, settings)
    theta0 = {k: np.asarray(v) for k, v in _strong(problem.theta0).items()}
    box = _search_box(problem, settings.spread if spread is None else spread)
    dim, rng = sum(v.size for v in theta0.values()), np.random.default_rng(seed)
    candidates, values, diverged, elapsed = [], [], [], []
    bar = tqdm(total=num_candidates, desc="random search", disable=not (progress and jax.process_index() == 0),
               unit="candidate")  # fmt: skip
    while len(candidates) < num_candidates or from_process_0(np.bool_(elapsed[-1] < seconds)):  # process 0's clock
        drawn = _in_box(box, theta0, rng.random((CANDIDATE_CHUNK, dim)))
        if not candidates:
            drawn = {k: np.concatenate([theta0[k][None], v[:-1]]) for k, v in drawn.items()}
        value, count = scores(drawn)
        now = time.perf_counter() - start
        short = num_candidates - len(candidates)  # a last chunk past the time budget keeps only what is missing
        keep = CANDIDATE_CHUNK if short <= 0 or from_process_0(np.bool_(now < seconds)) else min(short, CANDIDATE_CHUNK)
        candidates += [_row(drawn, i) for i in range(keep)]
        values += value[:keep].tolist()
        diverged += count[:keep].tolist()
        elapsed += [now] * keep
        bar.update(keep)
    bar.close()
    return SearchResult(candidates, np.asarray(values), np.asarray(diverged), np.asarray(elapsed),
                        problem.batch_size(problem.train))  # fmt: skip


def evaluate(problem: TuningProblem, theta: dict, settings: TuneSettings = TuneSettings(), batch=None) -> dict:
    """Scores of ``theta`` on ``batch`` (default: the held-out plants): ``objective`` (the robust objective of
    ``settings`` with diverged plants penalised as in training: finite unless every plant diverges),
    ``finite_fraction`` (of plants that did not diverge), ``diverged`` (their count), the ``mean``, ``cvar`` and
    quantiles ``p50``, ``p90``, ``max`` of the finite losses (None if there are none), and ``losses`` (inf where
    diverged)."""
    batch = problem.heldout if batch is None else batch
    size = problem.batch_size(batch)
    compiled, placed, _, _ = _compile_spread(
        lambda mesh: _spread(problem.losses, mesh, size), batch, theta, f"the {size} rollouts of an evaluation",
        hint="use fewer plants",
    )  # fmt: skip
    losses, diverged = _host(compiled(_host(theta), placed))
    failed = np.asarray(diverged) | ~np.isfinite(losses)
    penalised = penalise_diverged(jnp.asarray(losses), jnp.asarray(failed), settings.divergence_factor)
    finite = losses[~failed]
    stats = dict.fromkeys(("mean", "cvar", "p50", "p90", "max"))
    if finite.size:
        quantiles = np.quantile(finite, [0.5, 0.9, 1.0])
        stats = {"mean": float(np.mean(finite)), "cvar": float(cvar(jnp.asarray(finite), settings.cvar_alpha)),
                 "p50": float(quantiles[0]), "p90": float(quantiles[1]), "max": float(quantiles[2])}  # fmt: skip
    objective = float(robust_objective(penalised, settings.objective, settings.cvar_alpha)) if finite.size else math.inf
    return {
        "objective": objective,
        "finite_fraction": float(finite.size / failed.size),
        "diverged": int(failed.sum()),
        **stats,
        "losses": np.where(failed, np.inf, losses),
    }
