"""jaxobs.tuning: parameterisations, robust objectives and the optax loop (penalised divergence, rejection,
early stopping, checkpoints, Ctrl-C), the random search and evaluate, on cheap problems: a quadratic and the
analytic force loop of jaxobs.closed_loop."""

import dataclasses
import json
import logging

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from hypothesis import given
from hypothesis import strategies as st
from jax.test_util import check_grads

from jaxobs import tuning
from jaxobs._resources import Interrupted
from jaxobs.closed_loop import ideal_response, simulate
from jaxobs.observers import active
from jaxobs.papers.cortesao.force_control import (
    EXAMPLE1,
    example1_disturbance,
    nominal_design,
    reference_gain,
    with_feedback,
)
from jaxobs.plants import force_plant
from jaxobs.tuning import (
    CheckpointError,
    TuneSettings,
    TuningError,
    TuningProblem,
    cholesky_covariance,
    cholesky_parameters,
    cvar,
    evaluate,
    job,
    penalise_diverged,
    random_search,
    robust_objective,
    tune,
    unit_interval,
    unit_interval_parameters,
    value_and_grad,
)


@given(st.lists(st.floats(-3, 3), min_size=9, max_size=9))
def test_cholesky_covariance_is_positive_definite_and_inverts(values):
    raw = jnp.asarray(values).reshape(3, 3)
    Q = cholesky_covariance(raw)
    np.testing.assert_allclose(Q, Q.T, atol=0)
    assert float(jnp.min(jnp.linalg.eigvalsh(Q))) > 0
    back = cholesky_parameters(Q)
    np.testing.assert_allclose(back, jnp.tril(raw), rtol=1e-9, atol=1e-9)


def test_cholesky_couplings_are_scale_free_and_batched():
    """Rescaling the states (Q -> D Q D) moves only the log scales, not the couplings; leading axes are a batch."""
    cov = jnp.array([[2.0, 0.6, 0.1], [0.6, 1.0, 0.3], [0.1, 0.3, 0.5]])
    scale = jnp.array([1e-3, 10.0, 1e2])
    raw, scaled = cholesky_parameters(cov), cholesky_parameters(scale[:, None] * cov * scale[None, :])
    np.testing.assert_allclose(jnp.tril(scaled, -1), jnp.tril(raw, -1), rtol=1e-12)
    np.testing.assert_allclose(jnp.diagonal(scaled) - jnp.diagonal(raw), jnp.log(scale), rtol=1e-12)
    batch = jnp.stack([raw, scaled])
    np.testing.assert_allclose(cholesky_covariance(batch)[1], scale[:, None] * cov * scale[None, :], rtol=1e-12)
    np.testing.assert_allclose(cholesky_parameters(cholesky_covariance(batch)), batch, rtol=1e-9, atol=1e-12)


def _adam(rate):
    """The tuner's default optimiser with another step size: adam after global-norm clipping to 1."""
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adam(rate))


def test_parameterisations_under_transformations():
    raw = jnp.array([[0.1, 9.0], [0.3, -0.2]])
    Q = cholesky_covariance(raw)
    np.testing.assert_allclose(jax.jit(cholesky_covariance)(raw), Q)
    batch = jax.vmap(cholesky_covariance)(jnp.stack([raw, 2 * raw]))
    np.testing.assert_allclose(batch[1], cholesky_covariance(2 * raw))
    check_grads(lambda r: cholesky_covariance(r)[1, 0], (raw,), order=1, modes=["fwd", "rev"])
    assert float(jax.grad(lambda r: jnp.sum(cholesky_covariance(r)))(raw)[0, 1]) == 0.0  # upper triangle unused
    c = jnp.array([1e-3, 0.5, 0.9])
    np.testing.assert_allclose(unit_interval(unit_interval_parameters(c)), c, rtol=1e-12)
    check_grads(unit_interval, (jnp.array([0.3]),), order=2)
    with pytest.raises(ValueError, match="between 0 and 1"):
        unit_interval_parameters(1.0)
    with pytest.raises(ValueError, match="positive definite"):
        cholesky_parameters(jnp.array([[1.0, 2.0], [2.0, 1.0]]))


def test_cvar_is_the_mean_of_the_worst_fraction():
    losses = jnp.array([1.0, 7.0, 3.0, 5.0, 2.0, 4.0, 6.0, 0.0])
    assert float(cvar(losses, 0.25)) == 6.5
    assert float(cvar(losses, 1.0)) == float(jnp.mean(losses))
    assert float(cvar(losses, 0.01)) == 7.0
    assert float(jax.jit(cvar, static_argnums=1)(losses, 0.5)) == 5.5
    g = jax.grad(cvar)(losses, 0.25)
    np.testing.assert_array_equal(g, jnp.where(losses >= 6, 0.5, 0.0))
    assert float(robust_objective(losses, "mean")) == 3.5
    with pytest.raises(ValueError, match="alpha"):
        cvar(losses, 0.0)
    with pytest.raises(ValueError, match="objective"):
        robust_objective(losses, "max")


def quadratic_problem(limit=np.inf, start=0.0, targets=(1.0, 2.0, 3.0)):
    """Per-plant loss ``(theta - target_i)^2`` (for targets 1, 2, 6: mean optimum 3, CVaR_1/3 = worst-case
    optimum 3.5); a plant 'diverges' when ``theta > limit``."""

    def losses(theta, targets):
        x = theta["x"]
        return (x - targets) ** 2, jnp.broadcast_to(x > limit, targets.shape)

    targets = jnp.asarray(targets)
    return TuningProblem({"x": jnp.asarray(start)}, losses, targets, targets + 0.5)


def test_tune_finds_the_mean_and_cvar_optima():
    s = TuneSettings(_adam(0.2), steps=200, patience=200, checkpoint_every=1000)
    problem = quadratic_problem(targets=(1.0, 2.0, 6.0))
    result = tune(problem, s, progress=False)
    assert float(result.theta["x"]) == pytest.approx(3.0, abs=1e-2)
    assert result.evaluations == 200 and result.rollouts == 600 and result.stopped == "steps"
    worst = tune(problem, dataclasses.replace(s, objective="cvar", cvar_alpha=0.3), progress=False)
    assert float(worst.theta["x"]) == pytest.approx(3.5, abs=2e-2)
    scores = evaluate(problem, result.theta, s)
    assert scores["losses"].shape == (3,) and scores["diverged"] == 0
    assert scores["mean"] == pytest.approx(float(np.mean((result.theta["x"] - np.array([1.5, 2.5, 6.5])) ** 2)))


def test_diverging_steps_are_rejected_with_a_message(caplog):
    """With ``theta > 1.5`` flagged as divergence, adam (lr 0.5) overshoots into it; those steps are
    rejected, logged, retried from the last accepted point with half the step, and tuning ends below 1.5."""
    s = TuneSettings(optax.adam(0.5), steps=40, patience=40, checkpoint_every=1000)
    with caplog.at_level(logging.WARNING, logger="jaxobs.tuning"):
        result = tune(quadratic_problem(limit=1.5), s, progress=False)
    rejected = [h for h in result.history if not h["accepted"]]
    assert rejected and all("diverged" in h["reason"] for h in rejected)
    assert "step rejected" in caplog.text and "step scale 0.5" in caplog.text
    assert float(result.theta["x"]) <= 1.5
    assert float(result.theta["x"]) > 1.3


def test_unrecoverable_divergence_is_an_error():
    with pytest.raises(TuningError, match="initial parameters"):
        tune(quadratic_problem(limit=-1.0), TuneSettings(steps=5), progress=False)

    def losses(theta, targets):  # every move away from 0 diverges
        return (theta["x"] - targets) ** 2, jnp.broadcast_to(theta["x"] != 0.0, targets.shape)

    problem = TuningProblem({"x": jnp.asarray(0.0)}, losses, jnp.array([1.0]), jnp.array([1.0]))
    with pytest.raises(TuningError, match="consecutive steps rejected"):
        tune(problem, TuneSettings(steps=50, max_rejections=3), progress=False)


def test_nan_loss_is_rejected():
    def losses(theta, targets):
        x = theta["x"]
        return jnp.where(x > 1.0, jnp.nan, (x - targets) ** 2), jnp.zeros(targets.shape, bool)

    problem = TuningProblem({"x": jnp.asarray(0.0)}, losses, jnp.array([3.0]), jnp.array([3.0]))
    result = tune(problem, TuneSettings(optax.adam(0.6), steps=30), progress=False)
    reasons = {h["reason"] for h in result.history if not h["accepted"]}
    assert reasons == {"every one of the 1 plants diverged"}  # a NaN loss counts as a diverged plant
    assert float(result.theta["x"]) <= 1.0


def test_penalise_diverged():
    losses = jnp.array([1.0, 4.0, jnp.inf, 12.0])
    failed = jnp.array([False, False, True, True])
    p = 40.0  # 10 x the worst sound loss
    want = [1.0, 4.0, p, p * (1 + np.log1p(12.0 / p))]
    np.testing.assert_allclose(penalise_diverged(losses, failed, 10.0), want, rtol=1e-15)
    np.testing.assert_allclose(penalise_diverged(losses, failed, 10.0, own=~failed), [1.0, 4.0, p, p])
    g = jax.grad(lambda x: jnp.sum(penalise_diverged(x, failed, 10.0)))(jnp.array([1.0, 4.0, 3.0, 12.0]))
    np.testing.assert_allclose(g, [1.0, 1.0, p / (p + 3.0), p / (p + 12.0)], rtol=1e-15)  # P held constant
    assert not jnp.isfinite(penalise_diverged(losses, jnp.ones(4, bool), 10.0)).any()


def reach_problem():
    """Per-plant loss ``(x - t)^2`` for t = 1, 2, 3, 8; a plant diverges when ``|x - t| > 5`` (t = 8 at the
    start, x = 0). Its penalised loss pulls x up until it is rescued at x = 3; then the mean optimum is 3.5."""

    def losses(theta, t):
        return (theta["x"] - t) ** 2, jnp.abs(theta["x"] - t) > 5.0

    train = jnp.array([1.0, 2.0, 3.0, 8.0])
    return TuningProblem({"x": jnp.asarray(0.0)}, losses, train, jnp.array([1.0, 2.0, 8.0, 20.0]))


def test_a_few_diverging_plants_are_penalised_not_refused(caplog):
    s = TuneSettings(optax.adam(0.3), steps=80, patience=80, checkpoint_every=1000)
    with caplog.at_level(logging.WARNING, logger="jaxobs.tuning"):
        result = tune(reach_problem(), s, progress=False)
    assert "1 of 4 training plants diverge under the initial design" in caplog.text
    first, p = result.history[0], 10.0 * 9  # plant t = 8 at x = 0: L = 64, P = 10 x the worst sound loss
    assert first["accepted"] and first["diverged"] == 1
    assert first["objective"] == pytest.approx((1 + 4 + 9 + p * (1 + np.log1p(64 / p))) / 4)
    assert first["grad_norm"] == pytest.approx(abs(-2 - 4 - 6 - 16 * p / (p + 64)) / 4)
    assert result.diverged == 0 and float(result.theta["x"]) == pytest.approx(3.5, abs=0.05)
    counts = [h["diverged"] for h in result.history if h["accepted"]]
    assert counts == sorted(counts, reverse=True)  # accepted steps never lose a plant

    scores = evaluate(reach_problem(), result.theta, s)  # held-out t = 1, 2, 8, 20: the last diverges
    assert scores["diverged"] == 1 and scores["finite_fraction"] == 0.75
    finite = (float(result.theta["x"]) - np.array([1.0, 2.0, 8.0])) ** 2
    assert scores["mean"] == pytest.approx(finite.mean()) and scores["max"] == pytest.approx(finite.max())
    assert scores["p50"] == pytest.approx(np.median(finite))
    p, own = 10 * finite.max(), (float(result.theta["x"]) - 20.0) ** 2
    assert scores["objective"] == pytest.approx((finite.sum() + p * (1 + np.log1p(own / p))) / 4)
    assert np.isinf(scores["losses"][3])
    with pytest.raises(TuningError, match="every one of the 4 plants diverged"):
        tune(dataclasses.replace(reach_problem(), theta0={"x": jnp.asarray(50.0)}), s, progress=False)


@pytest.mark.parametrize("mode", ["reverse", "forward"])
def test_a_diverged_rollout_does_not_poison_the_gradient(mode):
    """Plant 3's loss overflows (exp(800 x) at x = 1): in reverse mode its zero cotangent times an infinite
    derivative is NaN, so the evaluation is redone with its input replaced by a sound plant's."""

    def losses(theta, p):
        x = theta["x"]
        loss = (x - p["t"]) ** 2 + jnp.exp(p["s"] * x) - 1.0
        return loss, jnp.zeros(loss.shape, bool)

    batch = {"t": jnp.array([0.0, 3.0, 0.0]), "s": jnp.array([0.0, 0.0, 800.0])}
    problem = TuningProblem({"x": jnp.asarray(1.0)}, losses, batch, batch)
    objective = tuning.make_objective(losses, TuneSettings(gradient=mode))
    plain = jax.jit(value_and_grad(lambda theta: objective(theta, batch), mode))  # without the tuner's recomputation
    grad = plain({"x": jnp.asarray(1.0)})[1]["x"]
    assert bool(jnp.isnan(grad)) == (mode == "reverse")
    result = tune(problem, TuneSettings(gradient=mode, steps=1), progress=False)
    first = result.history[0]
    assert first["accepted"] and first["diverged"] == 1
    assert first["objective"] == pytest.approx((1 + 4 + 10 * 4) / 3)  # l = 1, 4 and P = 10 x 4 (no own loss)
    assert first["grad_norm"] == pytest.approx(abs(2 * 1 + 2 * (1 - 3)) / 3)  # P is held constant


def test_early_stopping():
    problem = TuningProblem({"x": jnp.asarray(0.0)}, lambda t, b: (0 * t["x"] + b, b < 0), jnp.ones(2), jnp.ones(2))
    result = tune(problem, TuneSettings(steps=100, patience=5), progress=False)
    assert result.stopped == "converged" and result.converged and result.evaluations == 6


def test_checkpoint_resume_is_identical_and_bad_checkpoints_raise(tmp_path):
    s = TuneSettings(_adam(0.1), steps=12, checkpoint_every=3, patience=100)
    straight = tune(quadratic_problem(), s, progress=False)
    path = tmp_path / "ckpt.npz"
    first = tune(quadratic_problem(), dataclasses.replace(s, steps=7), checkpoint=path, progress=False)
    assert first.evaluations == 7 and path.exists()
    resumed = tune(quadratic_problem(), s, checkpoint=path, progress=False)
    assert resumed.evaluations == 12 and len(resumed.history) == 12
    assert float(resumed.theta["x"]) == float(straight.theta["x"])
    assert [h["objective"] for h in resumed.history] == [h["objective"] for h in straight.history]
    assert resumed.seconds > first.seconds > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.npz"]  # no temporary file left
    with pytest.raises(CheckpointError, match="different problem, program or settings"):
        tune(quadratic_problem(), dataclasses.replace(s, optimizer=optax.sgd(0.1)), checkpoint=path)
    with pytest.raises(CheckpointError, match="different problem, program or settings"):
        tune(quadratic_problem(), s, checkpoint=path, tag="another config")
    with pytest.raises(CheckpointError, match="different problem, program or settings"):  # same shapes, other losses
        tune(quadratic_problem(targets=(1.0, 2.0, 4.0)), s, checkpoint=path)


def _rewrite(path, edit_meta=None, edit_arrays=None):
    with np.load(path) as data:
        meta, arrays = json.loads(str(data["meta"])), {k: data[k] for k in data.files if k != "meta"}
    meta = edit_meta(meta) if edit_meta else meta
    arrays = edit_arrays(arrays) if edit_arrays else arrays
    np.savez(path, meta=np.array(json.dumps(meta)), **arrays)


def _edit_lane(meta, edit):
    edit(meta["lanes"][0])
    return meta


def _nan_floats(arrays):
    return {k: np.full_like(v, np.nan) if v.dtype.kind == "f" else v for k, v in arrays.items()}


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda p: p.write_bytes(b""), "corrupt or unreadable"),
        (lambda p: p.write_bytes(b"not a checkpoint"), "corrupt or unreadable"),
        (lambda p: _rewrite(p, edit_meta=lambda m: [m]), "meta is a JSON list"),
        (
            lambda p: _rewrite(p, edit_meta=lambda m: _edit_lane(m, lambda lane: lane.pop("scale"))),
            r"meta.lanes\[0\].scale is missing",
        ),  # fmt: skip
        (lambda p: _rewrite(p, edit_meta=lambda m: {**m, "iterations": "3"}), "meta.iterations"),
        (
            lambda p: _rewrite(p, edit_meta=lambda m: _edit_lane(m, lambda lane: lane["history"].pop())),
            "history has 2 entries",
        ),  # fmt: skip
        (
            lambda p: _rewrite(p, edit_meta=lambda m: _edit_lane(m, lambda lane: lane.update(stopped="tired"))),
            "stop reason out of range",
        ),  # fmt: skip
        (lambda p: _rewrite(p, edit_arrays=_nan_floats), "holds NaN"),
        (
            lambda p: _rewrite(p, edit_arrays=lambda a: dict(list(a.items())[:-1])),
            "damaged checkpoint .7 arrays, written with 8",
        ),
    ],
)
def test_damaged_checkpoints_raise(tmp_path, damage, message):
    """Each damaged checkpoint (the NaN one keeps a valid fingerprint) is a CheckpointError naming the file."""
    path = tmp_path / "ckpt.npz"
    s = TuneSettings(steps=3, checkpoint_every=1, patience=100)
    tune(quadratic_problem(), s, checkpoint=path, progress=False)
    damage(path)
    with pytest.raises(CheckpointError, match=message) as info:
        tune(quadratic_problem(), dataclasses.replace(s, steps=5), checkpoint=path, progress=False)
    assert str(path) in str(info.value)


def test_ctrl_c_saves_the_checkpoint_and_the_rerun_resumes(tmp_path, monkeypatch):
    s = TuneSettings(_adam(0.1), steps=10, checkpoint_every=100, patience=100)
    straight = tune(quadratic_problem(), s, progress=False)
    record, calls = job._record, []  # the record of each start's evaluation, made after each step

    def interrupted(*args):
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return record(*args)

    monkeypatch.setattr(job, "_record", interrupted)
    path = tmp_path / "ckpt.npz"
    with pytest.raises(Interrupted, match=r"after 4 of 10 evaluations; checkpoint saved to .*ckpt.npz; rerun"):
        tune(quadratic_problem(), s, checkpoint=path, progress=False)
    monkeypatch.setattr(job, "_record", record)
    resumed = tune(quadratic_problem(), s, checkpoint=path, progress=False)
    assert [h["objective"] for h in resumed.history] == [h["objective"] for h in straight.history]
    assert float(resumed.theta["x"]) == float(straight.theta["x"])


def test_random_search_box_budgets_and_best():
    s = TuneSettings()
    search = random_search(quadratic_problem(start=0.0), s, 30, spread=3.0, seed=1, progress=False)
    assert search.objectives.shape == (30,) and search.rollouts_per_candidate == 3
    assert search.objectives[0] == pytest.approx(14 / 3)  # theta0 = 0: (1 + 4 + 9) / 3
    theta, value, diverged = search.best()
    assert value == float(np.min(search.objectives)) < 1.0 and diverged == 0
    assert all(-3.0 <= float(c["x"]) <= 3.0 for c in search.candidates)
    assert search.best(1)[1] == search.objectives[0]
    assert np.all(np.diff(search.elapsed) >= 0) and search.within(0.0) == 1 and search.within(1e9) == 30

    boxed = dataclasses.replace(quadratic_problem(), search_box={"x": (jnp.asarray(5.0), jnp.asarray(6.0))})
    timed = random_search(boxed, s, 2, seconds=0.5, progress=False)
    assert len(timed.candidates) > 2 and timed.elapsed[-1] >= 0.5  # goes on for the wall-time budget
    assert all(5.0 <= float(c["x"]) <= 6.0 for c in timed.candidates[1:])
    with pytest.raises(ValueError, match="num_candidates"):
        random_search(quadratic_problem(), s, 0)


def test_forward_mode_gives_the_reverse_mode_gradient():
    def objective(theta):
        v = jnp.sum(jnp.sin(theta["a"]) * theta["b"] ** 2)
        return v, v > 0

    theta = {"a": jnp.array([0.3, -1.2]), "b": jnp.array(0.7)}
    (v_rev, aux_rev), g_rev = jax.jit(value_and_grad(objective, "reverse"))(theta)
    (v_fwd, aux_fwd), g_fwd = jax.jit(value_and_grad(objective, "forward"))(theta)
    assert float(v_rev) == float(v_fwd) and bool(aux_rev) == bool(aux_fwd)
    for k in theta:
        np.testing.assert_allclose(g_fwd[k], g_rev[k], rtol=1e-14)
    s = TuneSettings(_adam(0.2), steps=30, patience=30, gradient="forward")
    assert float(tune(quadratic_problem(), s, progress=False).theta["x"]) == pytest.approx(2.0, abs=0.05)
    with pytest.raises(ValueError, match="mode"):
        value_and_grad(objective, "central")


def test_settings_are_validated():
    for bad in ({"optimizer": "adam"}, {"objective": "max"}, {"cvar_alpha": 1.5}, {"steps": 0},
                {"gradient": "central"}, {"divergence_factor": 0.5}):  # fmt: skip
        with pytest.raises(ValueError, match=next(iter(bad))):
            TuneSettings(**bad).validate()


@pytest.mark.slow
def test_tuning_the_analytic_force_loop_lowers_the_held_out_error():
    """The gradient flows through DARE-based steady-state gains and the closed loop: tuning log q_active
    and log R of an AOB-1 on 4 analytic plants (Ks = 1.5..4.5 N/mm) under the eq. 81-82 disturbance lowers
    the held-out mean squared force error (measured 35.6 -> 6.8 N^2 in 15 evaluations)."""
    plant, L = nominal_design(EXAMPLE1)
    T = 250
    reference = jnp.full((T,), reference_gain(L) * 10.0)
    desired = ideal_response(plant, L, reference)[:, 0]
    dist = example1_disturbance(jnp.arange(T) * EXAMPLE1.h + 7.0)
    base = active.make_aob(plant, 1, EXAMPLE1.R, q_plant=1e-12, q_active=1e-5)

    def losses(theta, ks):
        Q = base.Q.at[-1, -1].set(jnp.exp(theta["log_q_active"]))
        aob = active.with_steady_state_gains(dataclasses.replace(base, Q=Q, R=jnp.exp(theta["log_r"]).reshape(1, 1)))
        ctrl = with_feedback(aob, L)

        def one(k):
            true = force_plant(k, EXAMPLE1.Tp, EXAMPLE1.h, 5 * EXAMPLE1.h)
            trace = simulate(true, active.active_observer_controller, ctrl, reference, disturbance=dist)
            return jnp.mean((trace.y_true[:, 0] - desired) ** 2)

        loss = jax.vmap(one)(ks)
        return loss, ~jnp.isfinite(loss)

    theta0 = {"log_q_active": jnp.log(1e-5), "log_r": jnp.log(EXAMPLE1.R)}
    problem = TuningProblem(theta0, losses, jnp.array([1.5, 2.5, 3.5, 4.5]), jnp.array([2.0, 3.0, 4.0]))
    s = TuneSettings(_adam(0.3), steps=15)
    result = tune(problem, s, progress=False)
    before, after = evaluate(problem, theta0, s)["mean"], evaluate(problem, result.theta, s)["mean"]
    assert after < 0.5 * before


def test_a_while_loop_in_reverse_mode_is_refused_before_anything_runs():
    """A rollout with a while loop (as MJX's constraint solver): one TuningError line, raised while tracing."""

    def losses(theta, batch):
        count = jax.lax.while_loop(lambda c: c[0] < 3, lambda c: (c[0] + 1, c[1] * theta["a"]), (0, batch))[1]
        return count, jnp.zeros(batch.shape, bool)

    problem = TuningProblem(theta0={"a": jnp.array(0.5)}, losses=losses, train=jnp.ones(4), heldout=jnp.ones(4))
    with pytest.raises(TuningError, match="reverse mode cannot differentiate a while loop in the rollouts"):
        tune(problem, TuneSettings(steps=2, gradient="reverse"), progress=False)
    result = tune(problem, TuneSettings(steps=2, gradient="forward"), progress=False)
    assert result.evaluations == 2


def test_any_optax_optimiser_is_an_object_and_lbfgs_gets_its_line_search():
    """L-BFGS (an optimiser that takes the objective for its line search) reaches the quadratic's minimum in a few
    evaluations and stops on the plateau rule; a name instead of an object is refused."""
    result = tune(quadratic_problem(), TuneSettings(optax.lbfgs(), steps=40, patience=3), progress=False)
    assert result.converged and result.evaluations < 40
    assert float(result.theta["x"]) == pytest.approx(2.0, abs=1e-6)
    with pytest.raises(ValueError, match="optimizer must be an optax.GradientTransformation"):
        tune(quadratic_problem(), TuneSettings("lbfgs"), progress=False)


def test_k_starts_run_together_as_k_separate_runs(caplog):
    """Three starting points in one vmapped run (one of them beyond the divergence limit, so it fails at once) give
    each start the history of its own run; the result is the best start."""
    s = TuneSettings(optax.adam(0.5), steps=25, patience=6, checkpoint_every=1000)
    problem = quadratic_problem(limit=1.5)
    starts = [{"x": jnp.asarray(x)} for x in (0.0, -2.0, 2.5)]
    with caplog.at_level(logging.WARNING, logger="jaxobs.tuning"):
        together = tune(problem, s, initial=starts, progress=False)
    assert "start 2: the starting point fails on the training batch" in caplog.text
    assert [r.stopped for r in together.starts][2] == "failed"
    for start, got in zip(starts[:2], together.starts[:2], strict=True):
        alone = tune(problem, s, initial=[start], progress=False)
        assert got.stopped == alone.stopped and got.evaluations == alone.evaluations
        assert [h["accepted"] for h in got.history] == [h["accepted"] for h in alone.history]
        objectives = [[np.nan if h["objective"] is None else h["objective"] for h in r.history] for r in (got, alone)]
        np.testing.assert_allclose(*objectives, rtol=1e-13)
        np.testing.assert_allclose(got.theta["x"], alone.theta["x"], rtol=1e-13)
        assert float(got.start["x"]) == float(start["x"])
    best = min(together.starts[:2], key=lambda r: r.objective)
    assert together.objective == best.objective and together.history is best.history
    assert together.evaluations == sum(r.evaluations for r in together.starts)
    with pytest.raises(TuningError, match="every one of the 2 starting points fails"):
        tune(problem, s, initial=starts[2:] * 2, progress=False)
    with pytest.raises(ValueError, match=r"initial\[1\] must have theta0's entries"):
        tune(problem, s, initial=[starts[0], {"y": 1.0}], progress=False)


def test_screening_seeds_the_starts_with_the_best_candidates(caplog):
    """15 Sobol candidates in theta0 +- 2 and theta0 are scored in batched calls; theta0 and the 3 best are the
    starts, in order; every start converges to the mean optimum (2); the rollouts count the screening. With one
    start, the best candidate is it. What compiles is said once per program (the tracing of all of them, then each
    program as it is compiled), with its seconds, which the result keeps."""
    s = TuneSettings(optax.adam(0.3), steps=60, patience=5, starts=4, screening=15, seed=3)
    problem = quadratic_problem(start=-1.0)
    with caplog.at_level(logging.INFO, logger="jaxobs.tuning"):
        result = tune(problem, s, progress=False)
    assert "screened 16 candidates" in caplog.text
    what = "the tuner's step (3 training rollouts at 4 start(s), forward-mode gradient)"
    for program in ("tracing its 4 programs", "the explore program", "the polish program"):
        assert caplog.text.count(f"compiling {what}: {program} ...") == 1, program
        assert caplog.text.count(f"compiled {what}: {program} in ") == 1, program
    assert 0 < result.compile_seconds <= result.seconds
    firsts = [r.history[0]["objective"] for r in result.starts]
    assert float(result.starts[0].start["x"]) == -1.0 and firsts[0] == pytest.approx(29 / 3)  # theta0
    assert firsts[1:] == sorted(firsts[1:]) and firsts[1] < 29 / 3
    assert all(-3.0 <= float(r.start["x"]) <= 1.0 for r in result.starts)
    one = tune(problem, dataclasses.replace(s, starts=1), progress=False)
    assert one.starts[0].history[0]["objective"] == firsts[1]
    assert all(r.stopped == "converged" for r in result.starts) and result.converged
    assert float(result.theta["x"]) == pytest.approx(2.0, abs=0.05)
    steps = max(r.evaluations for r in result.starts)
    assert result.rollouts == (16 + 4 * steps) * 3
    with pytest.raises(ValueError, match="starts = 4 needs screening >= 3"):
        tune(problem, dataclasses.replace(s, screening=2), progress=False)


def test_auto_picks_forward_mode_for_few_parameters():
    few = {"a": jnp.zeros(tuning.FORWARD_MAX_PARAMETERS)}
    assert tuning.gradient_mode(TuneSettings(), few) == "forward"
    assert tuning.gradient_mode(TuneSettings(), {**few, "b": jnp.zeros(())}) == "reverse"
    assert tuning.gradient_mode(TuneSettings(gradient="reverse"), few) == "reverse"


def test_backtracking_lbfgs_descends_monotonically_to_the_rosenbrock_minimum():
    """jaxobs' L-BFGS (no line search of its own, a restart on non-positive curvature) and the tuner's backtracking: a
    step that does not lower the objective is rejected and halved; the accepted objectives fall strictly and the
    run converges at (1, 1)."""

    def losses(theta, a):
        x, y = theta["xy"][0], theta["xy"][1]
        loss = (a - x) ** 2 + 100.0 * (y - x**2) ** 2
        return loss, jnp.zeros(a.shape, bool)

    problem = TuningProblem({"xy": jnp.array([-1.2, 1.0])}, losses, jnp.array([1.0]), jnp.array([1.0]))
    s = TuneSettings(tuning.lbfgs(), backtrack=True, steps=300, patience=6, min_improvement=1e-6)
    result = tune(problem, s, progress=False)
    accepted = [h["objective"] for h in result.history if h["accepted"]]
    assert np.all(np.diff(accepted) < 0)
    assert any("rose" in (h["reason"] or "") for h in result.history)
    assert result.converged and result.objective < 1e-10
    np.testing.assert_allclose(result.theta["xy"], [1.0, 1.0], atol=1e-5)
