"""The one registry of the paper layer: every reproduction, sweep scenario and tuning problem, one line each.

An entry is ``"module:ATTRIBUTE"`` under ``jaxobs.papers``, the attribute a :class:`~jaxobs.papers.scenarios.
Reproduction`, :class:`~jaxobs.papers.scenarios.SweepScenario` or :class:`~jaxobs.papers.scenarios.TuningScenario`
defined beside its code. Adding a paper's example is one module and one line here. A kind's modules are imported
only when that kind is asked for (the MJX problems import ``mujoco.mjx``). The first sweep and the first tuning
problem are the defaults of ``jaxobs sweep`` and ``jaxobs tune``. Names are unique across the three kinds.
"""

from __future__ import annotations

import importlib

from jaxobs.papers.scenarios import Reproduction, SweepScenario, TuningScenario

__all__ = ["REPRODUCTIONS", "SWEEPS", "TUNING_PROBLEMS", "reproductions", "sweep_scenarios", "tuning_problems"]

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
    """Every sweep scenario by name; the first is ``jaxobs sweep``'s default."""
    return _load(SWEEPS, SweepScenario)


def tuning_problems() -> dict[str, TuningScenario]:
    """Every tuning problem by name; the first is ``jaxobs tune``'s default."""
    return _load(TUNING_PROBLEMS, TuningScenario)
