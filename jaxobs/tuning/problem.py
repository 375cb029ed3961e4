"""What a tuning job tunes (:class:`TuningProblem`) and the errors of a job that cannot go on."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

__all__ = ["TuningProblem", "TuningError", "CheckpointError"]


@dataclasses.dataclass(frozen=True)
class TuningProblem:
    """What to tune and against what.

    Attributes:
      theta0: unconstrained initial parameters, a dict of arrays (the hand-set design, usually).
      losses: ``(theta, batch) -> (losses, diverged)``, one loss and one divergence flag per plant of the
        batch (shape ``(B,)`` each); pure and differentiable in ``theta``, each plant's independent of the others
        (the batch is split over devices). A flagged plant (e.g. a force
        beyond the sensor's range) is penalised like a non-finite loss (:func:`jaxobs.tuning.penalise_diverged`).
      train, heldout: batches of mismatched plants (pytrees with a leading batch axis), any structure that
        ``losses`` understands.
      penalty: optional ``theta -> scalar >= 0`` added with ``TuneSettings.penalty_weight``.
      describe: ``theta -> dict`` of readable (constrained) values for reports.
      responses: optional ``(theta, batch) -> dict`` of time series for a before/after figure: ``t`` (T,),
        ``output`` (B, T) or (B, T, k), ``desired`` (T,) or (T, k), ``labels`` (one per plant), ``ylabel`` (one,
        or one per output) and optionally ``setpoint`` (scalar or (k,)).
      search_box: optional ``{name: (low, high)}`` bounds of ``theta`` (arrays of each entry's shape) for the
        tuner's exploration and :func:`jaxobs.tuning.random_search`; entries with ``low == high`` stay fixed.
      labels: optional ``{name: strings shaped like theta0[name]}``, what each component is (e.g. ``"log Q[F]"``;
        :func:`jaxobs.tuning.log_labels`, :func:`jaxobs.tuning.cholesky_labels`) for reports and figures; default
        ``name[i]`` by flat index (:meth:`component_labels`).
      loss_unit: the unit of a plant's loss (e.g. ``"N²"``), for the axes of reports; empty: not given.
    """

    theta0: dict
    losses: Callable
    train: Any
    heldout: Any
    penalty: Callable | None = None
    describe: Callable = dict
    responses: Callable | None = None
    search_box: dict | None = None
    labels: dict | None = None
    loss_unit: str = ""

    def __post_init__(self):  # noqa: D105
        if self.labels is None:
            return
        if set(self.labels) != set(self.theta0):
            raise ValueError(f"labels must name theta0's entries {sorted(self.theta0)}, got {sorted(self.labels)}")
        for name, labels in self.labels.items():
            if np.shape(labels) != np.shape(self.theta0[name]):
                raise ValueError(f"labels[{name!r}] must have theta0[{name!r}]'s shape "
                                 f"{np.shape(self.theta0[name])}, got {np.shape(labels)}")  # fmt: skip

    def component_labels(self) -> dict[str, list[str]]:
        """``{name: [label per component of theta0[name], flattened]}``: :attr:`labels`, or ``name`` for a scalar
        and ``name[i]`` by flat index."""
        if self.labels is not None:
            return {name: [str(x) for x in np.ravel(self.labels[name])] for name in self.theta0}
        sizes = {name: int(np.size(value)) for name, value in self.theta0.items()}
        return {name: [name] if not np.shape(self.theta0[name]) else [f"{name}[{i}]" for i in range(size)]
                for name, size in sizes.items()}  # fmt: skip

    def batch_size(self, batch) -> int:
        """Number of plants in ``batch`` (the leading axis of its leaves)."""
        return int(jax.tree.leaves(batch)[0].shape[0])


class TuningError(RuntimeError):
    """Tuning cannot go on (e.g. every training plant diverges under the initial design, or every retry of a
    step fails)."""


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used (corrupt, damaged, or written for another problem or configuration)."""
