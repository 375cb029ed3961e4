"""Every registered sweep scenario and tuning problem runs end to end at a tiny size, through the object the CLI
runs (``scenario.validate`` then ``scenario.run``): its report and figures are written and its numbers are finite.

The paper-specific properties of each run (common random numbers, deadbeat, a published figure) are checked beside
the paper's other tests; this file keeps one tiny configuration per registered name, so a new scenario or problem
without one fails :func:`test_every_registered_name_has_a_tiny_config`. The runs whose compilation is long are
``slow``.
"""

import json
import math

import pytest

from jaxobs.papers import registry
from jaxobs.sweep import load_results

TINY_SWEEPS = {
    "force-control": {
        "chunk_size": 4,
        "controllers": {"grid_points": 2},
        "simulation": {"configs_per_design": 2, "duration": 0.5},
        "margins": {"num_points": 64},
    },
    "steer-by-wire": {"chunk_size": 2, "plants": {"count": 2}},
    "liu-peng": {"chunk_size": 2, "vehicle": {"count": 2}},
    "dc-motor-hgo": {
        "chunk_size": 2,
        "grid": {"eps": [1.0], "sigma": [0.0, 1e-2], "alpha_0": [0.28], "seeds": 1},
        "simulation": {"duration": 1.0, "rms_start": 0.5},
    },
    "grip-example56": {
        "chunk_size": 2,
        "grid": {"K_phi": [10.0], "adaptation_gain": [3.0], "noise_variance": [0.0, 1.0], "seeds": 1},
        "scenario_timing": {"segment_s": 1.0, "window_s": 0.5},
    },
    "saturated-outputs": {
        "chunk_size": 2,
        "grid": {"T": [0.5], "rho": [1.1], "h_scale": [1.0], "initial_states": 2},
        "run": {"intervals": 10, "substeps": 10},
    },
    "sideslip": {
        "chunk_size": 2,
        "grid": {
            "manoeuvre": ["sine_steer"],
            "friction": [1.0, 0.7],
            "acc_bias": [0.0],
            "drift": [0.0],
            "mass": [1.0],
            "cornering_stiffness": [1.0],
        },
        "simulation": {"duration": 1.0, "error_start": 0.5},
    },
}

TINY_OPTIMIZER = {"steps": 2, "checkpoint_every": 1, "screening": 15}
TINY_TUNING = {
    "force-1dof": {"plants": {"train": 2, "heldout": 2}, "scenario": {"duration": 0.2}},
    "peg-on-hole": {
        "plants": {"train": 1, "heldout": 1},
        "scenario": {"duration": 0.4, "alignment_start": 0.1, "alignment_end": 0.3},
    },
    "grip-example56-gains": {"seeds": {"train": 1, "heldout": 1}, "scenario": {"segment_s": 1.0, "window_s": 0.5}},
    "own-robot": {"plants": {"train": 2, "heldout": 2}, "scenario": {"duration": 0.3}},
    "sideslip-gains": {
        "plants": {"train": 2, "heldout": 2},
        "scenario": {"manoeuvres": ["sine_steer"], "duration": 1.0, "error_start": 0.5},
    },
}


SLOW = {"sideslip", "force-1dof", "peg-on-hole", "own-robot", "sideslip-gains"}  # NVSO, MJX: long compiles


def _names(tiny: dict) -> list:
    return [pytest.param(name, marks=pytest.mark.slow if name in SLOW else ()) for name in tiny]


def test_every_registered_name_has_a_tiny_config():
    assert list(TINY_SWEEPS) == list(registry.sweep_scenarios())
    assert list(TINY_TUNING) == list(registry.tuning_problems())


def _finite_numbers(tree) -> bool:
    """Whether every number in a JSON tree is finite (None, strings and booleans pass)."""
    if isinstance(tree, dict):
        return all(_finite_numbers(v) for v in tree.values())
    if isinstance(tree, list):
        return all(_finite_numbers(v) for v in tree)
    return not isinstance(tree, float) or math.isfinite(tree)


def _assert_written(out, summary: dict, summary_file: str) -> None:
    assert summary["figures"], "the report has no figure"
    for name in [*summary["figures"], summary_file]:
        assert (out / name).stat().st_size > 0, name


@pytest.mark.parametrize("name", _names(TINY_SWEEPS))
def test_sweep_scenario_runs_end_to_end(name, tmp_path):
    scenario = registry.sweep_scenarios()[name]
    config = scenario.validate({"scenario": name, **TINY_SWEEPS[name]}, "tiny")
    summary = scenario.run(config, tmp_path, progress=False)
    _assert_written(tmp_path, summary, "report.md")
    rows = load_results(tmp_path)
    assert rows["index"].tolist() == list(range(summary["num_configs"]))
    written = json.loads((tmp_path / "summary.json").read_text())
    assert written["num_configs"] == summary["num_configs"] and _finite_numbers(written)


@pytest.mark.parametrize("name", _names(TINY_TUNING))
def test_tuning_problem_runs_end_to_end(name, tmp_path):
    problem = registry.tuning_problems()[name]
    given = {"problem": name, "optimizer": TINY_OPTIMIZER, "baseline": {"random_search": False}, **TINY_TUNING[name]}
    summary = problem.run(problem.validate(given, "tiny"), tmp_path, progress=False)
    _assert_written(tmp_path, summary, "tuned.json")
    starts = summary["starts"]  # the shipped strategy: theta0 and the best screened candidate, each at most 2 steps
    assert len(starts) == 2 and all(0 < s["evaluations"] <= TINY_OPTIMIZER["steps"] for s in starts)
    assert summary["evaluations"] == sum(s["evaluations"] for s in starts)
    assert summary["train_diverged"] == {"hand-set": 0, "tuned": 0}
    assert summary["train_objective"]["tuned"] < summary["train_objective"]["hand-set"]
    for design in ("hand-set", "tuned"):
        assert math.isfinite(summary["heldout"][design]["objective"]), design
    assert _finite_numbers(json.loads((tmp_path / "tuned.json").read_text())["heldout"])
