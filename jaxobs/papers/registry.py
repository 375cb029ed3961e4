"""The one registry of the paper layer: every reproduction, sweep scenario and tuning problem, one line each.

An entry is ``"module:ATTRIBUTE"`` under ``jaxobs.papers``, the attribute a :class:`~jaxobs.papers.scenarios.
Reproduction`, :class:`~jaxobs.papers.scenarios.SweepScenario` or :class:`~jaxobs.papers.scenarios.TuningScenario`
defined beside its code. Adding a paper's example is one module and one line here. A kind's modules are imported
only when that kind is asked for (the MJX problems import ``mujoco.mjx``). The first sweep and the first tuning
problem are the defaults of ``jaxobs sweep`` and ``jaxobs tune``. Names are unique across the three kinds.

A user's own sweep scenario is the same :class:`~jaxobs.papers.scenarios.SweepScenario` in the user's module:
:func:`sweep_scenario` loads a ``"module:ATTRIBUTE"`` reference (the module found from the current directory
too), and :func:`sweep_scenarios` adds the installed ones, entry points of the group :data:`SWEEP_ENTRY_POINTS`.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import sys

from jaxobs.papers.scenarios import Reproduction, SweepScenario, TuningScenario

__all__ = [
    "REPRODUCTIONS",
    "SWEEPS",
    "TUNING_PROBLEMS",
    "SWEEP_ENTRY_POINTS",
    "reproductions",
    "sweep_scenarios",
    "sweep_scenario",
    "tuning_problems",
]

SWEEP_ENTRY_POINTS = "jaxobs.sweeps"
"""The entry-point group of installed sweep scenarios: ``[project.entry-points."jaxobs.sweeps"]`` with
``NAME = "my_package.my_module:SCENARIO"`` in a package's ``pyproject.toml``."""

REPRODUCTIONS = (
    "cortesao.example1:REPRODUCTION",
    "cortesao.stochastic:REPRODUCTION",
    "cortesao.steer_by_wire:REPRODUCTION",
    "liu_peng.vehicle_lateral:REPRODUCTION",
    "grip2010.scb:REPRODUCTION",
    "grip2010.adaptive:REPRODUCTION_1_1",
    "grip2010.adaptive:REPRODUCTION_5_6",
    "grip2010.adaptive:REPRODUCTION_DRILLING",
    "grip2010.dc_motor:REPRODUCTION",
    "grip2010.saturated_outputs:REPRODUCTION",
    "grip2010.sandwich:REPRODUCTION",
    "grip2010.sideslip:REPRODUCTION",
)

SWEEPS = (
    "cortesao.force_sweep:SCENARIO",
    "cortesao.steer_by_wire_sweep:SCENARIO",
    "liu_peng.vehicle_lateral_sweep:SCENARIO",
    "grip2010.dc_motor_sweep:SCENARIO",
    "grip2010.example56_sweep:SCENARIO",
    "grip2010.saturated_outputs_sweep:SCENARIO",
    "grip2010.sideslip_sweep:SCENARIO",
    "state_space_sweep:SCENARIO",
)

TUNING_PROBLEMS = (
    "cortesao.force_tuning:PROBLEM",
    "cortesao.peg_tuning:PROBLEM",
    "grip2010.example56_tuning:PROBLEM",
    "robot_tuning:PROBLEM",
    "grip2010.sideslip_tuning:PROBLEM",
)


def _load(entries: tuple[str, ...], kind: type) -> dict:
    loaded = {}
    for entry in entries:
        module, attribute = entry.split(":")
        obj = getattr(importlib.import_module(f"jaxobs.papers.{module}"), attribute)
        if not isinstance(obj, kind):
            raise TypeError(f"registry entry {entry} is a {type(obj).__name__}, not a {kind.__name__}")
        if obj.name in loaded:
            raise ValueError(f"registry entry {entry}: the name {obj.name!r} is taken")
        loaded[obj.name] = obj
    return loaded


def reproductions() -> dict[str, Reproduction]:
    """Every reproduction by name, in the order of :data:`REPRODUCTIONS`."""
    return _load(REPRODUCTIONS, Reproduction)


def sweep_scenarios() -> dict[str, SweepScenario]:
    """Every sweep scenario by name, the shipped ones first (the first is ``jaxobs sweep``'s default), then the
    installed ones (:data:`SWEEP_ENTRY_POINTS`, by their entry point's name, which must be the scenario's)."""
    scenarios = _load(SWEEPS, SweepScenario)
    for entry in importlib.metadata.entry_points(group=SWEEP_ENTRY_POINTS):
        scenario = _checked(entry.load(), f"entry point {entry.name} = {entry.value}", SweepScenario)
        if scenario.name != entry.name or entry.name in scenarios:
            problem = "is taken" if entry.name in scenarios else f"is not its scenario's name, {scenario.name!r}"
            raise ValueError(f"entry point {entry.name} = {entry.value} ({SWEEP_ENTRY_POINTS}): the name {problem}")
        scenarios[entry.name] = scenario
    return scenarios


def sweep_scenario(reference: str) -> SweepScenario:
    """The :class:`~jaxobs.papers.scenarios.SweepScenario` of ``reference``: a name of :func:`sweep_scenarios`,
    or ``"module:ATTRIBUTE"`` (``my_package.my_module:SCENARIO``; the current directory is searched first, so a
    ``my_sweep.py`` beside the command is found). A reference that cannot be loaded is a ``ValueError`` saying why;
    an error inside the module itself is raised as it is."""
    module, colon, attribute = reference.partition(":")
    if not colon:
        scenarios = sweep_scenarios()
        if reference not in scenarios:
            raise ValueError(f"must be one of {', '.join(map(repr, scenarios))} or 'module:ATTRIBUTE', got "
                             f"{reference!r}")  # fmt: skip
        return scenarios[reference]
    if not module or not attribute:
        raise ValueError(f"{reference!r} is not a reference 'module:ATTRIBUTE' (e.g. 'my_sweep:SCENARIO')")
    here = os.getcwd()
    sys.path.insert(0, here)  # the user's module beside the command, as `python -m` finds it
    try:
        loaded = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name is None or not module.startswith(exc.name):
            raise  # the user's module imports something missing: their error, with its traceback
        raise ValueError(f"cannot import {module!r} (no module {exc.name!r} in {here} or on the Python path)") from exc
    finally:
        sys.path.remove(here)
    if not hasattr(loaded, attribute):
        raise ValueError(f"module {module!r} ({loaded.__file__}) has no attribute {attribute!r}")
    return _checked(getattr(loaded, attribute), reference, SweepScenario)


def _checked(obj, what: str, kind: type):
    if not isinstance(obj, kind):
        raise ValueError(f"{what} is a {type(obj).__name__}, not a {kind.__module__}.{kind.__name__}")
    return obj


def tuning_problems() -> dict[str, TuningScenario]:
    """Every tuning problem by name; the first is ``jaxobs tune``'s default."""
    return _load(TUNING_PROBLEMS, TuningScenario)
