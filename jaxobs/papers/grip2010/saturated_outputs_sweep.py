"""The saturated-output controller of Grip 2010, ch. 8 over its tuning parameters and random initial states.

Each configuration is one point of ``grid.T x grid.rho x grid.h_scale x grid.initial_states`` (the index runs over the
initial states fastest) on the §8.5 plant (``jaxobs.papers.grip2010.saturated_outputs``): ``h_i = h_scale C_i'``,
and an initial state with a uniformly random direction and a log-uniform radius in ``[initial.radius_min,
initial.radius_max]`` (the same states at every grid point: common random numbers). It runs
:func:`jaxobs.saturation.simulate_saturated_outputs` for ``run.intervals`` intervals and reports the trade-offs of
§8.4: each output's first unsaturated interval (1-based, 0 if never), the deadbeat interval (0 if never), the condition
number of the masked Gramian ``D`` when the deadbeat command is decided, and ``||x||`` at the end. ``jaxobs sweep
--config tuning/saturated_outputs_sweep.toml``.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, fail
from jaxobs.papers._output import pyplot, save_figure, write_sweep_report
from jaxobs.papers.grip2010 import saturated_outputs as example
from jaxobs.papers.scenarios import Sweep, SweepScenario
from jaxobs.saturation import saturated_output_design, simulate_saturated_outputs
from jaxobs.sweep import load_results

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "SCENARIO", "make_sweep", "report"]

NAME = "saturated-outputs"
GRID = ("T", "rho", "h_scale")

DEFAULT_CONFIG = {
    "scenario": NAME,
    "seed": 0,
    "chunk_size": 64,
    "grid": {
        "T": [0.25, 0.5, 1.0],  # interval length (printed: 0.5)
        "rho": [1.1, 1.5, 2.0],  # alpha = rho ||exp(A T)||_2 (printed: 1.1)
        "h_scale": [0.5, 1.0, 2.0],  # h_i = h_scale C_i' (printed: 1)
        "initial_states": 64,  # random initial states per grid point (the same at every point)
    },
    "initial": {"radius_min": 1e-2, "radius_max": 1e3},
    "run": {"intervals": 40, "substeps": 50, "cond_max": 1e12},
}
"""3 T x 3 rho x 3 h scalings x 64 initial states = 1728 configurations."""

CONFIG_NOTES = {
    "seed": "key of the random initial states (the same states at every grid point)",
    "chunk_size": "configurations per device and step, and rows per Parquet chunk file",
    "grid": "the configurations: every combination of T, rho, h_scale and initial state",
    "grid.T": "interval length T (s), each > 0 (printed: 0.5)",
    "grid.rho": "alpha = rho ||exp(A T)||_2, each > 1 (printed: 1.1)",
    "grid.h_scale": "h_i = h_scale C_i', each > 0 (printed: 1)",
    "grid.initial_states": "random initial states per grid point",
    "initial": "the initial states: a uniform direction and a log-uniform radius",
    "initial.radius_min": "smallest radius (> 0)",
    "initial.radius_max": "largest radius (>= radius_min)",
    "run": "the simulation",
    "run.intervals": "number of intervals simulated",
    "run.substeps": "RK4 steps per interval",
    "run.cond_max": "largest condition number of D that the deadbeat command inverts",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    for key in GRID:
        values = config["grid"][key]
        low = 1.0 if key == "rho" else 0.0
        if (not isinstance(values, list) or not values
                or any(isinstance(v, bool) or not isinstance(v, int | float) or v <= low for v in values)):  # fmt: skip
            fail(source, f"grid.{key}", f"must be a non-empty list of numbers > {low:g}, got {values!r}")
    for key, low, strict in (("seed", 0, False), ("chunk_size", 1, False), ("grid.initial_states", 1, False),
                             ("initial.radius_min", 0, True), ("run.intervals", 1, False),
                             ("run.substeps", 1, False), ("run.cond_max", 1, True)):  # fmt: skip
        check_at_least(config, source, key, low, strict=strict)
    if config["initial"]["radius_max"] < config["initial"]["radius_min"]:
        fail(source, "initial.radius_max", f"must be >= radius_min = {config['initial']['radius_min']}")


def _num_configs(config: dict) -> int:
    g = config["grid"]
    return len(g["T"]) * len(g["rho"]) * len(g["h_scale"]) * g["initial_states"]


def initial_state(config: dict, number):
    """Initial state ``number`` (the same at every grid point): a uniform direction, a log-uniform radius."""
    key = jax.random.fold_in(jax.random.PRNGKey(config["seed"]), number)
    k_dir, k_rad = jax.random.split(key)
    direction = jax.random.normal(k_dir, (3,))
    lo, hi = np.log(config["initial"]["radius_min"]), np.log(config["initial"]["radius_max"])
    radius = jnp.exp(jax.random.uniform(k_rad, (), minval=lo, maxval=hi))
    return radius * direction / jnp.linalg.norm(direction), radius


def make_sweep(config: dict):
    """``(sampler, evaluate, num_configs)`` for :func:`jaxobs.sweep.run_sweep`."""
    g = config["grid"]
    tables = {key: jnp.asarray(g[key], float) for key in GRID}
    sizes = [len(g[key]) for key in GRID]
    states = g["initial_states"]
    intervals, substeps = int(config["run"]["intervals"]), int(config["run"]["substeps"])
    cond_max = float(config["run"]["cond_max"])

    def sampler(key, index):  # the grid point and initial state of configuration `index` (the key is unused)
        number, rest = index % states, index // states
        picks = {}
        for name, size in zip(GRID[::-1], sizes[::-1], strict=True):
            rest, picks[name] = rest // size, rest % size
        x0, radius = initial_state(config, number)
        return {**{name: tables[name][picks[name]] for name in GRID}, "x0": x0, "radius": radius}

    def evaluate(p):
        design = saturated_output_design(example.A, example.B, example.C, T=p["T"], rho=p["rho"],
                                         H=p["h_scale"] * example.C)  # fmt: skip
        trace = simulate_saturated_outputs(design, p["x0"], intervals, substeps=substeps, cond_max=cond_max)
        unsat, mode = trace.unsaturated, trace.mode == 1
        first = jnp.where(unsat.any(axis=0), jnp.argmax(unsat, axis=0) + 1, 0)
        deadbeat = jnp.where(mode.any(), jnp.argmax(mode) + 1, 0)
        final = jnp.linalg.norm(trace.x_end[-1])
        return {
            "radius": p["radius"],
            "first_unsaturated_interval": first,
            "deadbeat_interval": deadbeat,
            "gramian_condition": jnp.where(mode.any(), trace.condition[jnp.argmax(mode)], jnp.inf),
            "final_norm": jnp.where(jnp.isfinite(final), final, jnp.inf),
            "ill_conditioned_intervals": jnp.sum(trace.ill_conditioned),
        }

    return Sweep(sampler, evaluate, _num_configs(config))


def report(config: dict, out_dir: Path, result=None, context=None) -> dict:
    """Summarise the sweep's results in ``out_dir`` (``summary.json``, ``report.md``); returns the summary."""
    cols = load_results(out_dir)
    g = config["grid"]
    shape = (len(g["T"]), len(g["rho"]), len(g["h_scale"]), g["initial_states"])
    radius = cols["metric.radius"].reshape(shape)
    deadbeat = cols["metric.deadbeat_interval"].reshape(shape)
    first = np.stack([cols[f"metric.first_unsaturated_interval[{i}]"] for i in range(2)], -1).reshape(*shape, 2)
    cond = cols["metric.gramian_condition"].reshape(shape)
    final = cols["metric.final_norm"].reshape(shape)
    points = []
    for i, T in enumerate(g["T"]):
        for j, rho in enumerate(g["rho"]):
            for k, hs in enumerate(g["h_scale"]):
                d, c, f = deadbeat[i, j, k], cond[i, j, k], final[i, j, k]
                done = d > 0
                points.append({
                    "T": T, "rho": rho, "h_scale": hs,
                    "deadbeat_fraction": float(np.mean(done)),
                    "median_deadbeat_interval": float(np.median(d[done])) if done.any() else None,
                    "max_deadbeat_interval": int(d.max()),
                    "median_first_unsaturated_interval": np.median(first[i, j, k], axis=0),
                    "median_gramian_condition": float(np.median(c[done])) if done.any() else None,
                    "max_gramian_condition": float(np.max(c[done])) if done.any() else None,
                    "stabilised_fraction": float(np.mean(f < 1e-6 * np.maximum(radius[i, j, k], 1))),
                    "max_final_norm": float(np.max(f)),
                })  # fmt: skip
    summary = {
        "scenario": NAME,
        "num_configs": int(cols["index"].size),
        "metric_definitions": {
            "deadbeat_interval": "1-based interval of the deadbeat command (0: not within run.intervals)",
            "first_unsaturated_interval": "per output, the first interval in which it was unsaturated (0: never)",
            "gramian_condition": "cond(D) when the deadbeat command is decided",
            "stabilised_fraction": "final ||x|| < 1e-6 max(radius, 1)",
        },
        "grid": points,
    }
    figures = [_plot(config, radius, deadbeat, cond, out_dir)]
    return write_sweep_report(out_dir, summary, config, result, figures, _markdown)


def _plot(config: dict, radius, deadbeat, cond, out_dir: Path) -> str:
    """Deadbeat interval and cond(D) against the initial radius, one colour per T (all rho, h_scale pooled)."""
    g = config["grid"]
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for i, T in enumerate(g["T"]):
        r, d, c = radius[i].ravel(), deadbeat[i].ravel(), cond[i].ravel()
        ax[0].scatter(r, d, s=6, alpha=0.5, label=f"T = {T:g}")
        ax[1].scatter(r[d > 0], c[d > 0], s=6, alpha=0.5, label=f"T = {T:g}")
    ax[0].set(xscale="log", xlabel="||x(0)||", ylabel="deadbeat interval (0: none)")
    ax[1].set(xscale="log", yscale="log", xlabel="||x(0)||", ylabel="cond(D) at the deadbeat decision")
    for a in ax:
        a.legend(fontsize=8)
    fig.suptitle("Grip 2010 §8.5 plant: desaturation and deadbeat over T, rho, h scaling and the initial radius")
    return save_figure(fig, out_dir, "grid")


def _markdown(summary: dict) -> str:
    lines = [
        "# Grip 2010 ch. 8: the saturated-output controller over T, rho, h scaling and the initial state",
        "",
        f"{summary['num_configs']} configurations. Per grid point: the fraction of initial states that reached the "
        "deadbeat command, the median and largest deadbeat interval, cond(D) at the decision, the fraction "
        "stabilised.",
        "",
        "| T | rho | h scale | deadbeat | median interval | max interval | median cond(D) | stabilised |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for p in summary["grid"]:
        med = "-" if p["median_deadbeat_interval"] is None else f"{p['median_deadbeat_interval']:g}"
        cond = "-" if p["median_gramian_condition"] is None else f"{p['median_gramian_condition']:.3g}"
        lines.append(f"| {p['T']:g} | {p['rho']:g} | {p['h_scale']:g} | {100 * p['deadbeat_fraction']:.0f} % | {med} | "
                     f"{p['max_deadbeat_interval']} | {cond} | {100 * p['stabilised_fraction']:.0f} % |")  # fmt: skip
    return "\n".join(lines) + "\n"


SCENARIO = SweepScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=make_sweep,
    report=report,
    size_keys=("run.intervals", "run.substeps", "grid.initial_states", "grid.T", "grid.rho", "grid.h_scale"),
)
