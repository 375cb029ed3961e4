"""The masked observability-Gramian estimator (Grip 2010, ch. 8, sampled): exact reconstruction once every output
has been unsaturated, not before; forgetting; the validity mask; jit/vmap; bad inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.observers import EstimatorInputs, run
from jaxobs.observers.gramian import gramian_estimator, make_gramian

A = np.array([[0.0, 1, 1], [0, 0, 0], [0, 0, 0]])  # Grip (2010) §8.5
B = np.array([[0.0, 0], [1, 0], [0, 1]])
C = np.array([[1.0, 0, 0], [1, 1, 0]])
DT = 0.01
RUN = jax.jit(lambda params, y, u: run(gramian_estimator, params, EstimatorInputs(y=y, u_prev=u)))


def _record(x0, steps=400, seed=0):
    """Samples of x' = A x + B u under a held random input; y = sat(C x) (exact discretisation)."""
    p = make_gramian(A, B, C, dt=DT)
    rng = np.random.default_rng(seed)
    u = rng.normal(0, 3, (steps, 2))
    xs, x = [], np.asarray(x0, float)
    for k in range(steps):
        if k:
            x = np.asarray(p.Phi) @ x + np.asarray(p.Gamma) @ u[k - 1]
        xs.append(x)
    xs = np.array(xs)
    u_prev = np.vstack([np.zeros((1, 2)), u[:-1]])
    return xs, np.clip(xs @ C.T, -1, 1), u_prev


def test_ready_exactly_when_every_output_has_been_unsaturated_and_then_exact():
    xs, y, u = _record([2.0, -1.0, 0.5])
    params = make_gramian(A, B, C, dt=DT, cond_max=1e12)
    _, out = RUN(params, jnp.asarray(y), jnp.asarray(u))
    unsat = np.abs(y) < 1
    seen = np.cumsum(unsat, axis=0)  # unsaturated samples of each output so far
    ready = np.asarray(out.ready)
    # (C_i, A) each observe 2 of 3 directions: the Gramian is nonsingular once each output has >= 1 sample and
    # together they span R^3; never while one output has been saturated throughout
    assert not ready[np.min(seen, axis=1) == 0].any()
    assert ready[-1] and ready.sum() > 10 and (seen[:, 1] == 0).any()
    np.testing.assert_allclose(np.asarray(out.x)[ready], xs[ready], atol=1e-8 * np.abs(xs).max())
    assert np.all(np.asarray(out.weights)[np.abs(y) >= 1] == 0)


def test_forgetting_runs_forever_and_keeps_tracking():
    """With forgetting the information stays bounded over a long record and the estimate stays exact."""
    xs, y, u = _record([0.3, -0.2, 0.1], steps=3000, seed=1)
    params = make_gramian(A, B, C, dt=DT, forgetting=2.0)
    state, out = RUN(params, jnp.asarray(y), jnp.asarray(u))
    assert np.all(np.isfinite(np.asarray(state.Y))) and np.linalg.norm(state.Y) < 10
    ready = np.asarray(out.ready)
    assert ready[-1000:].all()
    np.testing.assert_allclose(np.asarray(out.x)[-1000:], xs[-1000:], atol=1e-7 * np.abs(xs).max())


def test_validity_mask_through_missing_samples():
    """weights="valid": every finite sample counts, a clipped sample given as NaN does not."""
    xs, y, u = _record([0.3, -0.2, 0.1], steps=300, seed=2)
    y_true = xs @ C.T  # an unclipped sensor, except where the user marks samples invalid
    masked = np.where(np.abs(y_true) > 0.5, np.nan, y_true)
    params = make_gramian(A, B, C, dt=DT, weights="valid")
    _, out = RUN(params, jnp.asarray(masked), jnp.asarray(u))
    ready = np.asarray(out.ready)
    assert ready[-1]
    np.testing.assert_allclose(np.asarray(out.x)[ready], xs[ready], atol=1e-8)
    np.testing.assert_array_equal(np.asarray(out.weights), np.isfinite(masked).astype(float))


def test_vmap_over_records_matches_single_runs():
    records = [_record(x0, steps=200, seed=i) for i, x0 in enumerate([[2.0, -1, 0.5], [0.1, 0.2, 0.3]])]
    params = make_gramian(A, B, C, dt=DT)
    ys = jnp.asarray(np.array([r[1] for r in records]))
    us = jnp.asarray(np.array([r[2] for r in records]))
    _, batched = jax.vmap(lambda y, u: RUN(params, y, u))(ys, us)
    for i in range(2):
        _, single = RUN(params, ys[i], us[i])
        np.testing.assert_allclose(batched.x[i], single.x, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(dt=0.0), "dt must be a finite positive"),
        (dict(forgetting=-1.0), "forgetting must be a finite non-negative"),
        (dict(weights="soft"), "weights must be one of"),
        (dict(level=[1.0, -1.0]), "level must be positive"),
        (dict(level=[1.0, 1.0, 1.0]), r"level must be a scalar or have shape \(2,\)"),
        (dict(x0=[0.0, 0.0]), r"x0 must have shape \(3,\)"),
    ],
)
def test_bad_inputs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_gramian(A, B, C, **(dict(dt=DT) | kwargs))


def test_wrong_measurement_shape_raises_under_jit():
    params = make_gramian(A, B, C, dt=DT)
    with pytest.raises(ValueError, match=r"inputs.y must have shape \(2,\)"):
        RUN(params, jnp.zeros((5, 3)), jnp.zeros((5, 2)))
