"""Every registered sweep scenario and tuning problem runs end to end at a tiny size, through the object the CLI
runs (``scenario.validate`` then ``scenario.run``): its report and figures are written and its numbers are finite.

The paper-specific properties of each run (common random numbers, deadbeat, a published figure) are checked beside
the paper's other tests; this file keeps one tiny configuration per registered name, so a new scenario or problem
without one fails :func:`test_every_registered_name_has_a_tiny_config`. The runs whose compilation is long are
``slow``.
"""

import json
import math
import re

import jax
import pytest

from jaxobs._config import ConfigError, get, leaf_keys
from jaxobs._resources import LimitError
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
    "state-space": {"chunk_size": 2, "configs": 4, "simulation": {"duration": 0.02}, "margins": {"num_points": 64}},
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


SLOW = {"sideslip", "force-1dof", "peg-on-hole", "own-robot", "sideslip-gains", "state-space"}  # long compiles


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


# ---------------------------------------------------------------------------------------------------------------
# the limits of every registered config (issue 28): one generic check, named by file and key


def _jobs() -> dict:
    return {**registry.sweep_scenarios(), **registry.tuning_problems()}


def _nested(key: str, value) -> dict:
    """``{"a": {"b": value}}`` for the dotted ``key`` ``"a.b"``."""
    for part in reversed(key.split(".")):
        value = {part: value}
    return value


def _integer_keys(job) -> list[str]:
    config = job.validate()
    keys = []
    for key in leaf_keys(config):
        value = get(config, key)
        numbers = value if isinstance(value, list) else [value]
        if numbers and all(isinstance(v, int) and not isinstance(v, bool) for v in numbers):
            keys.append(key)
    return keys


@pytest.mark.parametrize("name", list(_jobs()))
def test_every_integer_key_is_limited_to_int32(name):
    """Every integer of every registered config (counts, seeds, integer grids) beyond 2**31 - 1 in magnitude is a
    ConfigError naming the file and the key, before anything is built (before: seed = 10**20 ended in an
    OverflowError traceback)."""
    job = _jobs()[name]
    keys = _integer_keys(job)
    assert "seed" in keys
    for key in keys:
        default = get(job.defaults, key)
        for bad in (2**31, -(2**31), 10**20):
            given = {job.key: name, **_nested(key, [bad] * len(default) if isinstance(default, list) else bad)}
            with pytest.raises(ConfigError, match=rf"^big.toml: {re.escape(key)}: must be an integer of magnitude"):
                job.validate(given, "big.toml")


@pytest.mark.parametrize("name", list(_jobs()))
def test_the_size_key_raised_most_is_named(name):
    """Every registered job declares the keys that set its sizes (numbers or lists of its defaults, the engine's
    common ones included), and a limit is blamed on the one a config raises most over its default."""
    job = _jobs()[name]
    keys = job.all_size_keys()
    assert len(keys) >= 2 and len(set(keys)) == len(keys)
    assert set(type(job).common_size_keys) <= set(keys)
    assert job.blame(job.validate()) == keys[0]
    for key in keys:
        value = get(job.defaults, key)
        raised = value * 3 if isinstance(value, list) else (value or 1) * 1000  # a default of 0 rises too
        assert job.blame(_merged(job, key, raised)) == key


def _merged(job, key: str, value) -> dict:
    """The defaults with the dotted ``key`` set to ``value`` (without validation)."""
    config = json.loads(json.dumps(job.defaults))
    *parents, last = key.split(".")
    table = config
    for part in parents:
        table = table[part]
    table[last] = value
    return config


def _failing_scenario(error: Exception):
    """A sweep scenario with two size keys whose build raises ``error``."""
    from jaxobs.papers.scenarios import SweepScenario

    def build(config):
        raise error

    defaults = {"scenario": "failing", "seed": 0, "chunk_size": 4, "run": {"steps": 10, "duration": 1.0}}
    notes = {k: "" for k in ("seed", "chunk_size", "run", "run.steps", "run.duration")}
    return SweepScenario(name="failing", summary="fails", defaults=defaults, notes=notes, check=lambda c, s: None,
                         build=build, report=None, size_keys=("run.steps", "run.duration"))  # fmt: skip


@pytest.mark.parametrize(
    "error, reason",
    [
        (LimitError("one step needs about 1 TB, more than the 8 GB of memory available", "lower chunk_size"),
         "one step needs about 1 TB, more than the 8 GB of memory available"),
        (jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 1000000000000 bytes."),
         r"the job's sizes exceed this machine \(JaxRuntimeError: RESOURCE_EXHAUSTED: Out of memory"),
        (MemoryError("no room"), r"the job's sizes exceed this machine \(MemoryError: no room\)"),
        (OverflowError("Python int too large to convert to C long"), r"the job's sizes exceed this machine "),
    ],
    ids=["estimate", "xla-resource-exhausted", "memory-error", "overflow"],
)  # fmt: skip
def test_a_limit_met_while_building_is_named_by_file_and_size_key(tmp_path, error, reason):
    """The generic conversion of every registered job's run: an estimate over the memory, an allocation that fails
    or a size that overflows, as a ConfigError naming the file and the size key raised most (run.duration here)."""
    job = _failing_scenario(error)
    config = job.validate({"run": {"duration": 1e9}}, "sizes.toml")
    with pytest.raises(ConfigError, match=rf"^sizes.toml: run.duration: {reason}.*; lower run.duration "
                                          r"\(sizes are also set by run.steps, chunk_size\)$"):  # fmt: skip
        job.run(config, tmp_path, source="sizes.toml", progress=False)


def test_other_runtime_errors_are_not_taken_for_limits(tmp_path):
    job = _failing_scenario(jax.errors.JaxRuntimeError("INTERNAL: a bug"))
    with pytest.raises(jax.errors.JaxRuntimeError, match="INTERNAL"):
        job.run(job.validate(), tmp_path, progress=False)
