"""The tuner's settings (:class:`TuneSettings`), its default optimiser and the L-BFGS it backtracks itself."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxobs import _checks
from jaxobs.tuning.objectives import GRADIENT_MODES, OBJECTIVES

__all__ = ["DEFAULT_OPTIMIZER", "FORWARD_MAX_PARAMETERS", "CANDIDATE_CHUNK", "TuneSettings", "gradient_mode",
           "lbfgs", "screening_size", "AUTO_SCREENING_MAX"]  # fmt: skip

FORWARD_MAX_PARAMETERS = 10
"""``gradient = "auto"`` differentiates in forward mode up to this many scalar parameters, in reverse mode above:
forward mode costs about one rollout's tangent per parameter, reverse mode a fixed multiple of the rollout (the
measured crossover on the MJX problems: docs/performance.md)."""

CANDIDATE_CHUNK = 16
"""Candidates scored per batched call (one ``vmap`` over candidates and plants) by :func:`jaxobs.tuning.random_search`
and :func:`jaxobs.tuning.batch_objective`; the tuner's exploration scores ``TuneSettings.population`` per call."""

AUTO_SCREENING_MAX = 128
"""The most points (``theta0`` included) of the screening ``TuneSettings(screening="auto")`` sizes to the parameters
(:func:`screening_size`): the shipped problems' 127 candidates and ``theta0``."""

DEFAULT_OPTIMIZER = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(0.1))
"""The tuner's default optimiser: adam with step size 0.1 after clipping the gradient to global norm 1."""


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


@dataclasses.dataclass(frozen=True)
class TuneSettings:
    """Settings of the tuner (:func:`jaxobs.tuning.make_tuner`, :func:`jaxobs.tuning.tune`; the ``[optimizer]``
    table of ``jaxobs tune``'s config).

    Attributes:
      optimizer: an ``optax.GradientTransformation`` (:data:`DEFAULT_OPTIMIZER`); one that takes extra arguments,
        such as ``optax.lbfgs()``, gets the objective as ``value_fn`` for its line search.
      gradient: "auto" (forward mode up to :data:`FORWARD_MAX_PARAMETERS` scalar parameters, else reverse),
        "reverse" (``value_and_grad``) or "forward" (``jacfwd``: exact, cheaper for few parameters).
      steps: the cap: gradient evaluations per start at most (rejected ones included).
      starts: starting points tuned together (one ``vmap`` over their optimiser states and rollouts); the result
        is the best of them on the training objective.
      screening: candidates drawn (scrambled Sobol) in the search box and scored, batched, before the gradient
        runs: one start is the best of them and ``theta0``; more starts are ``theta0`` and the ``starts - 1`` best
        candidates (0: ``theta0`` alone, which needs ``starts == 1`` unless ``evolve``); "auto": a design sized to
        the parameters' count (:func:`screening_size`).
      evolve: CMA-ES generations per round at most (0: none): after the screening, a CMA-ES (Hansen 2016) of
        ``population`` candidates per generation explores the box from the best candidate so far until it stalls
        (``patience`` generations without a relative improvement of ``min_improvement``, or its step below 1e-3 of
        the box) or reaches this cap; the starts are then the best candidates found (``theta0`` among them in the
        first round when ``starts > 1``).
      population: candidates per batched call of the exploration (a chunk of the screening, a CMA-ES generation).
      evolve_sigma: the CMA-ES's initial step, as a fraction of the box's width per coordinate.
      rounds: explore-and-polish rounds: once every start of a round has stopped, the next restarts the CMA-ES at
        a uniformly drawn point of the box (with ``evolve_sigma``) and polishes its best (1: no restart).
      distinct: the starts of a round lie at least this far apart (largest coordinate difference, in box widths)
        where the candidates allow (0: the best candidates, however close).
      bounded: keep every design in the search box (each step is projected onto it), as a search does.
      spread: half-width of the search box ``theta0 +- spread`` (unconstrained coordinates) when the problem has
        no ``search_box``.  seed: seed of the screening's draws and of the CMA-ES.
      objective: "mean" or "cvar" of the per-plant losses.  cvar_alpha: the CVaR fraction of worst plants.
      penalty_weight: weight of the problem's penalty term (0: off).
      divergence_factor: a diverged plant's loss is this times the largest finite loss (see
        :func:`jaxobs.tuning.penalise_diverged`).
      patience: the plateau window: a start has converged after this many evaluations (the CMA-ES: generations)
        without a relative improvement of ``min_improvement`` of its best objective.
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
    screening: int | str = 0
    evolve: int = 0
    population: int = CANDIDATE_CHUNK
    evolve_sigma: float = 0.25
    rounds: int = 1
    distinct: float = 0.0
    bounded: bool = False
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
        if not 0 < self.evolve_sigma <= 1:
            raise ValueError(f"evolve_sigma must be in (0, 1], got {self.evolve_sigma}")
        for name, low in (("steps", 0), ("patience", 0), ("checkpoint_every", 0), ("starts", 0), ("spread", 0),
                          ("population", 1), ("rounds", 0)):  # fmt: skip
            if not getattr(self, name) > low:
                raise ValueError(f"{name} must be > {low}, got {getattr(self, name)!r}")
        for name, low in (("penalty_weight", 0), ("min_improvement", 0), ("max_rejections", 0), ("evolve", 0),
                          ("divergence_factor", 1), ("seed", 0), ("distinct", 0)):  # fmt: skip
            if not getattr(self, name) >= low:
                raise ValueError(f"{name} must be >= {low}, got {getattr(self, name)!r}")
        if self.screening != "auto" and not (isinstance(self.screening, int | np.integer) and self.screening >= 0):
            raise ValueError(f"screening must be an integer >= 0 or 'auto', got {self.screening!r}")
        if self.rounds > 1 and not self.evolve:
            raise ValueError(f"rounds = {self.rounds} restarts the CMA-ES: it needs evolve >= 1")


def gradient_mode(settings: TuneSettings, theta: dict) -> str:
    """The differentiation mode of ``settings.gradient`` for parameters ``theta``: "auto" resolves to "forward" up
    to :data:`FORWARD_MAX_PARAMETERS` scalar parameters and to "reverse" above."""
    if settings.gradient != "auto":
        return settings.gradient
    count = sum(int(np.size(leaf)) for leaf in jax.tree.leaves(theta))
    return "forward" if count <= FORWARD_MAX_PARAMETERS else "reverse"


def screening_size(settings: TuneSettings, parameters: int) -> int:
    """The screening's candidates for ``parameters`` scalar parameters: ``settings.screening``, or for "auto" a
    Sobol design sized to them: with ``theta0``, the power of two at or above ``4 * parameters``, at most
    :data:`AUTO_SCREENING_MAX` points and at least two batches of ``settings.population`` (at the default population
    of 16: 31 candidates up to 8 parameters, 63 up to 16, 127 above: in a wider box the CMA-ES and the gradient do
    the work, a screening of more points would be a random search as costly as the dimension).

    Example::

        >>> from jaxobs.tuning import TuneSettings, screening_size
        >>> [screening_size(TuneSettings(screening="auto"), d) for d in (2, 12, 10_000)]
        [31, 63, 127]
    """
    if settings.screening != "auto":
        return int(settings.screening)
    points = min(AUTO_SCREENING_MAX, 2 ** math.ceil(math.log2(4 * max(parameters, 1))))
    return max(2 * settings.population, points) - 1
