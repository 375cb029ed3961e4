"""Smoke tests of benchmarks/estimation.py on its smallest grid: it runs, every peer that is installed returns the
same numbers as jaxobs (the agreement check of the benchmark), and cells over the work budget are listed as
skipped, never dropped silently, and the watchdog that lists a wedged peer as hung. The speed targets themselves
are measured by the benchmark, not tested."""

import functools
import importlib.util
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests import ROOT

SCRIPT = ROOT / "benchmarks" / "estimation.py"


@pytest.fixture(scope="module")
def estimation():
    pytest.importorskip("dynamax")
    pytest.importorskip("cuthbert")
    spec = importlib.util.spec_from_file_location("estimation_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(estimation, tmp_path, workloads, budget=1e9):
    argv = ["--out", str(tmp_path), "--batches", "2", "--states", "2", "--lengths", "12", "--rounds", "1",
            "--budget", str(budget), "--idle-timeout", "0", "--workloads", *workloads]  # fmt: skip
    # --idle-timeout 0: in this process (the module is loaded from its path, which a spawned child cannot import)
    summary = estimation.main(argv)
    assert json.loads((tmp_path / "estimation.json").read_text())["targets"] == summary["targets"]
    return summary


def _check_agreement(summary, workloads):
    assert [r["workload"] for r in summary["results"]] == list(workloads)
    for r in summary["results"]:
        for peer, record in r["record"]["peers"].items():
            if peer == "cuthbert" and r["workload"] == "ukf":
                assert record["status"] == "skipped"  # cuthbert has no unscented filter
                continue
            assert record["status"] == "ok", (r["cell"], peer, record)
            assert record["agrees"], (r["cell"], peer, record["max_relative_difference"])


@pytest.mark.slow
def test_every_workload_smallest_grid(estimation, tmp_path):
    _check_agreement(_run(estimation, tmp_path, list(estimation.WORKLOADS)), estimation.WORKLOADS)


def test_over_budget_cells_are_listed_as_skipped(estimation, tmp_path):
    summary = _run(estimation, tmp_path, ["filter", "ukf"], budget=1.0)
    assert summary["results"] == []
    assert summary["skipped"] == ["filter B=2 n=2 T=12", "ukf B=2 n=2 T=12"]


def test_gradient_floor_is_a_true_gradient(estimation):
    """The floor's hand-scheduled reverse pass equals jax.grad of what it differentiates (its timing bounds a
    gradient, so it must compute one)."""
    (Phi, C, Q, R), Y = estimation.linear_problem(2, 3, 7)
    floor, args = estimation.floor_linear("grad", (Phi, C, Q, R), Y)
    dPhi, dQ = floor(*args)

    def traces(Phi, Q):
        step = lambda P, _: (Phi @ P @ Phi.T + Q,) * 2
        return jnp.sum(jnp.trace(jax.lax.scan(step, Q, None, length=Y.shape[1])[1], axis1=1, axis2=2))

    expected = jax.vmap(jax.grad(traces, argnums=(0, 1)))(Phi, Q)
    np.testing.assert_allclose(dPhi, expected[0], rtol=1e-12)
    np.testing.assert_allclose(dQ, expected[1], rtol=1e-12)


def _wedged(progress, *, done: int):
    """A watched target: ``done`` entries finish, then ``"wedged"`` sleeps without using CPU (as XLA does when
    its CPU runtime wedges)."""
    for i in range(done):
        progress(f"entry {i}")
        progress(None)
    progress("wedged")
    time.sleep(600)


def _finishes(progress):
    progress("only")
    progress(None)
    return {"answer": 42}


@pytest.mark.slow  # ~10 s: two spawned interpreters import JAX
def test_watchdog_kills_an_idle_entry_and_names_it():
    """``run_watched`` returns a child's result, and kills a child that stops reporting and computing, naming the
    entry it was in (the mechanism that lists a wedged peer as hung instead of hanging ``make bench``)."""
    sys.path.insert(0, str(SCRIPT.parent))
    from _timing import Hung, run_watched

    assert run_watched(_finishes, (), idle_timeout=30) == {"answer": 42}
    start = time.monotonic()
    with pytest.raises(Hung, match="wedged made no progress and used no CPU for 2 s") as caught:
        run_watched(functools.partial(_wedged, done=2), (), idle_timeout=2)
    assert caught.value.entry == "wedged"
    assert time.monotonic() - start < 60
