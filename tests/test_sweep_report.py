"""jaxobs.sweep_report: the generic report of any sweep from its rows (stable fraction per swept parameter, metric
distributions over the valid and stable configurations only, the worst and the invalid configurations, the time the
runs took, kept by a rerun), on a synthetic sweep whose answers are known."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.lti import c2d, ss
from jaxobs.observers import FeedbackParams, observer_controller
from jaxobs.observers.kalman import kalman_filter, make_kalman
from jaxobs.stability import robustness_metrics
from jaxobs.sweep import load_results, run_sweep
from jaxobs.sweep_report import quantiles, summarize, write_report

N = 2000


def _sampler(key, index):
    k_k, k_tau, k_seed = jax.random.split(key, 3)
    return {
        "stiffness": jax.random.uniform(k_k, minval=0.7, maxval=1.3),  # stable below 1.15
        "dead_time": jax.random.uniform(k_tau, minval=0.0, maxval=1.0),  # invalid above 0.9
        "order": index % 3,
        "seed": jax.random.bits(k_seed, (), jnp.uint32),
    }


def _evaluate(p):
    valid = p["dead_time"] < 0.9
    stable = valid & (p["stiffness"] < 1.15)
    # a margin that is huge where the loop is unstable, NaN where invalid, infinite for order 2: only the stable
    # configurations' values may enter a statistic
    margin = jnp.where(stable, 1.0 / p["stiffness"], 1e6)
    margin = jnp.where(p["order"] == 2, jnp.inf, margin)
    return {"valid": valid, "stable": stable, "gain_margin": jnp.where(valid, margin, jnp.nan),
            "spectral_radius": jnp.where(valid, p["stiffness"] / 1.15, jnp.nan)}  # fmt: skip


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "sweep"
    run_sweep(_sampler, _evaluate, N, out, chunk_size=500, progress=False)
    return out


def test_summary_from_the_rows(sweep):
    rows = load_results(sweep)
    summary = summarize(rows, worst_count=5)
    valid, stable = rows["metric.valid"], rows["metric.stable"]
    assert summary["invalid"] == int((~valid).sum()) > 0 and summary["stable"] == int(stable.sum())
    assert summary["stable_fraction_of_valid"] == pytest.approx(stable[valid].mean())
    assert list(summary["parameters"]) == ["dead_time", "order", "stiffness"]  # the seed is not binned
    assert summary["not_binned"] == ["seed"]
    bins = summary["parameters"]["stiffness"]["bins"]
    assert len(bins) == 10 and sum(b["configs"] for b in bins) == N
    for b in bins:
        sel = (rows["param.stiffness"] >= b["low"]) & (rows["param.stiffness"] <= b["high"])
        assert b["stable_fraction"] == pytest.approx(stable[sel].mean(), abs=2 / b["configs"])
    assert bins[0]["stable_fraction"] > 0.85 and bins[-1]["stable_fraction"] == 0.0
    dead = summary["parameters"]["dead_time"]["bins"]
    assert dead[-1]["invalid_fraction"] > 0.95 and dead[0]["invalid_fraction"] == 0.0  # invalid above 0.9
    assert [b["low"] for b in summary["parameters"]["order"]["bins"]] == [0, 1, 2]
    # no margin of an unstable or invalid configuration: the 1e6 never enters, the infinite ones are counted apart
    gm = summary["metrics"]["gain_margin"]
    kept = rows["metric.gain_margin"][stable]
    assert gm["count"] == int(np.isfinite(kept).sum()) and gm["infinite"] == int(np.isinf(kept).sum()) > 0
    assert gm["p95"] < 1.5 and gm["median"] == pytest.approx(np.median(kept[np.isfinite(kept)]))
    # the worst: the largest spectral radius among the valid configurations
    radii = [case["metric.spectral_radius"] for case in summary["worst"]]
    assert radii == sorted(radii, reverse=True) and radii[0] == pytest.approx(np.nanmax(rows["metric.spectral_radius"]))
    assert all(case["metric.valid"] for case in summary["worst"])
    assert all(case["param.dead_time"] >= 0.9 for case in summary["invalid_examples"])


def test_quantiles_leave_out_nan_and_count_infinities():
    assert quantiles([np.nan, np.inf, 1.0, 2.0, 3.0]) == {"count": 3, "infinite": 1, "p05": 1.1, "median": 2.0,
                                                          "p95": 2.9}  # fmt: skip
    assert quantiles([np.nan]) == {"count": 0, "infinite": 0}


def test_write_report_files_and_a_rerun_keeps_the_measured_time(sweep):
    summary = write_report(sweep, title="Synthetic sweep", units={"stiffness": "N/m"})
    assert summary["figures"] == ["stable_fraction.png", "metrics.png"]
    assert all((sweep / name).stat().st_size > 10_000 for name in summary["figures"])
    written = json.loads((sweep / "summary.json").read_text())
    assert written["invalid"] == summary["invalid"] and written["config"] == {}
    report = (sweep / "report.md").read_text()
    assert report.startswith("# Synthetic sweep\n") and f"{summary['invalid']} invalid" in report
    assert f"Invalid configurations: {summary['invalid']} of {N}." in report
    assert "| stiffness (N/m) | 0.7" in report and "conditionally stable" in report
    assert summary["runs"] == 1 and summary["configs_computed"] == N and summary["configs_per_second"] > 0
    run_sweep(_sampler, _evaluate, N, sweep, chunk_size=500, progress=False)  # nothing left to compute
    again = write_report(sweep, title="Synthetic sweep", units={"stiffness": "N/m"})
    for key in ("seconds", "compile_seconds", "configs_per_second", "configs_computed", "runs"):
        assert again[key] == summary[key], key
    assert (sweep / "report.md").read_text() == report


def test_worst_by_another_column(sweep):
    rows = load_results(sweep)
    summary = summarize(rows, worst_by=("param.stiffness", "min"), worst_count=3)
    assert summary["worst_by"] == "param.stiffness (smallest first)"
    valid = rows["metric.valid"]
    assert summary["worst"][0]["param.stiffness"] == rows["param.stiffness"][valid].min()
    with pytest.raises(ValueError, match="worst_by: no column 'metric.nope'"):
        summarize(rows, worst_by="metric.nope")


@pytest.mark.slow  # compiles a sweep step with margins (~30 s on a loaded 2-core machine)
def test_a_sweep_with_invalid_plants_reports_them(tmp_path):
    """The issue's case, small: a zero inertia in about 10 % of the configurations makes the discretised plant
    non-finite: those rows are invalid with NaN margins (never inf), counted by the report, and no statistic
    includes them."""
    h = 0.01
    kf = make_kalman(jnp.eye(1), jnp.eye(1), 1e-2 * jnp.eye(1), jnp.eye(1), Gamma=h * jnp.eye(1), steady_state=True)
    params = FeedbackParams(kf, 5.0 * jnp.eye(1))

    def sampler(key, index):
        k_j, k_zero = jax.random.split(key)
        inertia = jax.random.uniform(k_j, minval=0.5, maxval=1.5)
        return {"inertia": jnp.where(jax.random.uniform(k_zero) < 0.1, 0.0, inertia)}

    def evaluate(p):  # an integrator 1 / (J s)
        true = c2d(ss([[0.0]], [[1.0 / p["inertia"]]], [[1.0]]), h, 0.0)
        return robustness_metrics(true, observer_controller(kalman_filter), params, num_points=64)

    run_sweep(sampler, evaluate, 400, tmp_path / "out", chunk_size=200, progress=False)
    rows = load_results(tmp_path / "out")
    zero = rows["param.inertia"] == 0
    assert 20 < zero.sum() < 60 and (rows["metric.valid"] == ~zero).all()
    for name in ("spectral_radius", "gain_margin", "phase_margin", "delay_margin", "stability_margin"):
        assert np.isnan(rows[f"metric.{name}"][zero]).all(), name
    assert rows["metric.stable"][~zero].all() and np.isfinite(rows["metric.gain_margin"][~zero]).all()
    summary = write_report(tmp_path / "out")
    assert summary["invalid"] == int(zero.sum()) and summary["metrics"]["gain_margin"]["count"] == int((~zero).sum())
    assert f"Invalid configurations: {int(zero.sum())} of 400." in (tmp_path / "out" / "report.md").read_text()
