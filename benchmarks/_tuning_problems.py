"""The shipped tuning problems, and the price of a gradient on each, for benchmarks/tuning.py and
benchmarks/mjx_rollouts.py."""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import load_toml
from jaxobs.papers.registry import tuning_problems
from jaxobs.papers.tuning_config import settings as tuning_settings
from jaxobs.tuning import GRADIENT_MODES, gradient_mode, robust_objective, value_and_grad

ROOT = Path(__file__).resolve().parent.parent
PROBLEMS = {  # label -> shipped config (None: jaxobs tune's default problem)
    "force-1dof": None,
    "force-1dof-cvar": "tuning/force_1dof_cvar.toml",
    "peg-on-hole": "tuning/peg_on_hole.toml",
    "grip-example56": "tuning/grip_example56.toml",
    "cartpole-payload": "tuning/cartpole_payload.toml",
    "arm-on-table": "tuning/arm_on_table.toml",
    "sideslip": "tuning/sideslip.toml",
    "peg-on-hole-cholesky": "tuning/peg_on_hole_cholesky.toml",
    "cartpole-payload-aob": "tuning/cartpole_payload_aob.toml",
    "arm-on-table-cholesky": "tuning/arm_on_table_cholesky.toml",
    "arm7-aob-cholesky": "tuning/arm7_aob_cholesky.toml",
}


ORACLES = {"gain-schedule-100": 13, "gain-schedule-1000": 125, "gain-schedule-10000": 1250, "speed-schedule-256": 32}
"""Problems with an exact optimum or bound (:mod:`jaxobs.tuning.problems`): the gain schedules of
``gain_schedule_problem`` (label -> horizon T; T x 4 states x 2 outputs gains: 104, 1000 and 10 000), with the
optimum ``J*``; the speed schedule of ``speed_schedule_problem`` (label -> knots; 32 x 4 x 2 gains), whose losses
are already ``J / J*`` per plant (the bound 1)."""


def load_oracle(label: str):
    """``(problem, settings, optimum)`` of a problem of :data:`ORACLES`, tuned with the shipped strategy."""
    from jaxobs.papers.tuning_config import BASELINE_DEFAULTS, SHIPPED_STRATEGY, optimizer_defaults
    from jaxobs.tuning.problems import gain_schedule_problem, speed_schedule_problem

    if label.startswith("speed"):
        problem, _ = speed_schedule_problem(knots=ORACLES[label], train=32, heldout=32)
        optimum = 1.0
    else:
        problem, schedule = gain_schedule_problem(ORACLES[label])
        optimum = float(schedule.cost)
    config = {"seed": 0, "optimizer": optimizer_defaults(**SHIPPED_STRATEGY), "baseline": dict(BASELINE_DEFAULTS)}
    return problem, tuning_settings(config), optimum


def load_problem(label: str, spread: float | None = None):
    """``(problem, settings, config)`` of a shipped tuning problem; ``spread`` replaces its ``baseline.spread`` (the
    search box of the screening and of the baselines)."""
    registry = tuning_problems()
    path = PROBLEMS[label]
    given = load_toml(ROOT / path) if path else {}
    if spread is not None:
        given.setdefault("baseline", {})["spread"] = spread
    name = given.get("problem", next(iter(registry)))
    config = registry[name].validate({**given, "problem": name}, str(ROOT / path) if path else "defaults")
    return registry[name].build(config), tuning_settings(config), config


def gradient_costs(problem, settings, *, modes=None, rounds: int = 3, population: int | None = None) -> dict:
    """The price of a gradient of the training objective: per differentiation mode (default: both), the compile
    time, the temporary memory XLA reserves and the median wall time over ``rounds`` interleaved rounds, each as
    a ratio to one forward evaluation of the same batch (``mode`` is the one ``settings`` picks); with
    ``population``, the price of that many starts' gradients in one ``vmap`` (the tuner's populations) against one
    start's (``population_ratio``)."""
    mode = gradient_mode(settings, problem.theta0)
    modes = modes or [m for m in GRADIENT_MODES if m != "auto"]
    theta, batch = problem.theta0, problem.train

    def objective(th):
        losses = problem.losses(th, batch)[0]
        return robust_objective(losses, settings.objective, settings.cvar_alpha), None

    entries = {"forward_pass": lambda th: objective(th)[0]}
    entries.update({f"{m}_mode": value_and_grad(objective, m) for m in modes})
    if population:
        starts = jnp.arange(population, dtype=float) * 1e-2  # distinct starts around theta

        def population_gradients(th):
            spread = jax.tree.map(lambda v: v[None] + starts.reshape((-1,) + (1,) * np.ndim(v)), th)
            return jax.vmap(value_and_grad(objective, mode))(spread)

        entries["population"] = population_gradients
    jax.jit(lambda x: x + 1).lower(1.0).compile()  # the process's one-time compilation costs, paid outside
    compiled, record = {}, {}
    for name, fn in entries.items():
        start = time.perf_counter()
        compiled[name] = jax.jit(fn).lower(theta).compile()
        memory = compiled[name].memory_analysis()
        record[name] = {"compile_s": time.perf_counter() - start,
                        "temp_bytes": int(getattr(memory, "temp_size_in_bytes", 0) or 0), "seconds": []}  # fmt: skip
        jax.block_until_ready(compiled[name](theta))
    for _ in range(rounds):
        for name, fn in compiled.items():
            start = time.perf_counter()
            jax.block_until_ready(fn(theta))
            record[name]["seconds"].append(time.perf_counter() - start)
    base = record["forward_pass"]
    for r in record.values():
        r["median_s"] = statistics.median(r["seconds"])
        r["ratio"] = r["median_s"] / statistics.median(base["seconds"])
        r["compile_ratio"] = r["compile_s"] / base["compile_s"]
        r["memory_ratio"] = r["temp_bytes"] / max(base["temp_bytes"], 1)
    chosen = record[f"{mode}_mode"]
    return {"mode": mode, "parameters": int(sum(np.size(v) for v in jax.tree.leaves(theta))),
            "ratio": chosen["ratio"], "compile_ratio": chosen["compile_ratio"], "population": population,
            "population_ratio": record["population"]["median_s"] / chosen["median_s"] if population else None,
            "entries": record}  # fmt: skip
