"""jaxobs.tuning.problem: the labels of theta's components (given, checked against theta0, or by index) and the
label helpers of the parameterisations."""

import jax.numpy as jnp
import pytest

from jaxobs.tuning import TuningProblem, cholesky_labels, log_labels


def _losses(theta, batch):
    return (theta["x"][0] - batch) ** 2, batch < -1e9


def test_component_labels_given_or_by_index():
    theta0 = {"x": jnp.zeros(2), "raw": jnp.zeros((2, 2)), "s": jnp.array(0.0)}
    batch = jnp.array([1.0, 2.0])
    plain = TuningProblem(theta0, _losses, batch, batch)
    assert plain.component_labels() == {"x": ["x[0]", "x[1]"], "raw": [f"raw[{i}]" for i in range(4)], "s": ["s"]}
    labels = {"x": log_labels("Q", ["F", "p"]), "raw": cholesky_labels("R", ["a", "b"]), "s": "log R[y]"}
    named = TuningProblem(theta0, _losses, batch, batch, labels=labels, loss_unit="N²")
    assert named.component_labels() == {
        "x": ["log Q[F]", "log Q[p]"],
        "s": ["log R[y]"],
        "raw": ["log scale R[a]", "unused", "coupling R[b, a]", "log scale R[b]"],
    }
    with pytest.raises(ValueError, match=r"labels\['x'\] must have theta0\['x'\]'s shape \(2,\), got \(3,\)"):
        TuningProblem(theta0, _losses, batch, batch, labels={**labels, "x": ["a", "b", "c"]})
    with pytest.raises(ValueError, match="labels must name theta0's entries"):
        TuningProblem(theta0, _losses, batch, batch, labels={"x": ["a", "b"]})
