"""Robustness of the steer-by-wire model matching (Cortesão 2006 §8) to errors in the identified actuator models.

The Example 2 design (:mod:`jaxobs.papers.cortesao.steer_by_wire`) on the nominal SBW model runs against true
plants whose four identified transfer functions (eq. 95-98) have their gains and poles scaled (+-30 % by default):
per configuration the spectral radius (eq. 59), the model-matching errors of Fig. 8 and the disturbance rejection
of Fig. 9. ``jaxobs sweep --config tuning/steer_by_wire_sweep.toml``. The scenario: docs/theory/papers.md.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, check_range
from jaxobs.lti import StateSpace, c2d
from jaxobs.observers.active import active_observer_controller, with_steady_state_gains
from jaxobs.observers.base import LinearObserver
from jaxobs.observers.feedback import FeedbackParams
from jaxobs.observers.linear import linear_controller
from jaxobs.papers._output import pyplot, save_figure, write_sweep_report
from jaxobs.papers.cortesao import steer_by_wire as sbw
from jaxobs.papers.scenarios import Sweep, SweepScenario
from jaxobs.stability import closed_loop_matrix, spectral_radius
from jaxobs.sweep import config_key, load_results

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "SCENARIO", "make_sweep"]

NAME = "steer-by-wire"
FACTORS = tuple(f"{model}_{kind}" for model in sbw.ACTUATOR_MODELS for kind in ("gain", "pole"))

DEFAULT_CONFIG = {
    "scenario": NAME,
    "seed": 0,
    "chunk_size": 250,
    "plants": {
        "gain_scale": [0.7, 1.3],
        "pole_scale": [0.7, 1.3],
        "count": 1000,
    },
}
"""1000 SBW plants with every gain and pole of eq. 95-98 off by up to +-30 %."""

CONFIG_NOTES = {
    "seed": "base of every configuration's random key",
    "chunk_size": "configurations per device and step, and rows per Parquet chunk file",
    "plants": "the true SBW plants: the four identified actuator models of eq. 95-98, each factor drawn independently",
    "plants.gain_scale": "true / identified gain of each actuator model, uniform",
    "plants.pole_scale": "true / identified poles of each actuator model (all its poles by one factor), uniform",
    "plants.count": "number of true plants (configurations); another count is another sweep",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    check_range(config, source, "plants.gain_scale", positive=True, allow_point=True)
    check_range(config, source, "plants.pole_scale", positive=True, allow_point=True)
    for key, low in (("seed", 0), ("chunk_size", 1), ("plants.count", 1)):
        check_at_least(config, source, key, low)


def _sampler(config: dict):
    lo_g, hi_g = config["plants"]["gain_scale"]
    lo_p, hi_p = config["plants"]["pole_scale"]
    low = jnp.asarray([lo_g if f.endswith("gain") else lo_p for f in FACTORS])
    high = jnp.asarray([hi_g if f.endswith("gain") else hi_p for f in FACTORS])

    def sampler(key, index):
        factors = jax.random.uniform(key, (len(FACTORS),), minval=low, maxval=high)
        return {"plant": index, **{name: factors[i] for i, name in enumerate(FACTORS)}}

    return sampler


def _true_plants(config: dict, sampler) -> tuple[StateSpace, StateSpace]:
    """The discrete true plants of every configuration, stacked: without and with the position states."""
    count, seed = config["plants"]["count"], config["seed"]
    draws = jax.jit(jax.vmap(lambda i: sampler(config_key(seed, i), i)))(jnp.arange(count))
    factors = np.stack([np.asarray(draws[name]) for name in FACTORS], axis=1)
    bare, positions = [], []
    for row in factors:
        mismatch = {m: (row[2 * i], row[2 * i + 1]) for i, m in enumerate(sbw.ACTUATOR_MODELS)}
        model = sbw.sbw_model(mismatch)
        bare.append(c2d(model, sbw.H))
        positions.append(c2d(sbw.with_positions(model), sbw.H))

    def stack(systems):
        return StateSpace(*(jnp.stack([getattr(s, f) for s in systems]) for f in "ABCD"), sbw.H)

    return stack(bare), stack(positions)


def _without_locked_states(params: FeedbackParams) -> FeedbackParams:
    """The steady-state AOB controller as a fixed-gain linear one (params of ``linear_controller``) without
    the active states that eq. 109 locks at 0 (``Q_p = 0``, no gain, never excited): they are eigenvalues at
    exactly 1 that no input or measurement reaches, so they would make every loop look marginally stable."""
    lin = active_observer_controller.linear(params)
    c, aob = lin.estimator, params.estimator
    q = np.diagonal(np.asarray(aob.Q))
    n = q.size
    keep = np.array([i for i in range(n) if i < n - aob.n_active or q[i] > 0])
    observer = LinearObserver(c.Phi[np.ix_(keep, keep)], c.Gamma[keep], c.C[:, keep], c.K[keep])
    return FeedbackParams(observer, lin.L[:, keep])


def make_sweep(config: dict):
    """``(sampler, evaluate, num_configs)`` for :func:`jaxobs.sweep.run_sweep`."""
    sampler = _sampler(config)
    bare, positions = _true_plants(config, sampler)
    d = sbw.design()
    design = sbw.aob(d["plant"], d["L_r"])
    controller = dataclasses.replace(design, estimator=with_steady_state_gains(design.estimator))
    loop_controller = _without_locked_states(controller)
    _, torque, road = sbw.scenarios()
    no_torque, no_road = np.zeros_like(torque), np.zeros_like(road)
    target = sbw.simulate_target(d, torque, no_road)  # Fig. 8: model matching
    peaks = {k: float(np.max(np.abs(np.asarray(target[k])))) for k in ("delta_h", "x_r")}

    def pick(table: StateSpace, i) -> StateSpace:
        return StateSpace(table.A[i], table.B[i], table.C[i], table.D[i], sbw.H)

    def evaluate(p):
        rho = spectral_radius(closed_loop_matrix(pick(bare, p["plant"]), linear_controller, loop_controller))
        true = pick(positions, p["plant"])
        matching = sbw.simulate_sbw(d, torque, no_road, true_plant=true, controller=controller)
        rejection = sbw.simulate_sbw(d, no_torque, road, true_plant=true, controller=controller)  # Fig. 9

        def relative_rms(key):
            e = matching[key] - target[key]
            value = jnp.sqrt(jnp.mean(e**2)) / peaks[key]
            return jnp.where(jnp.isfinite(value), value, jnp.inf)

        final = jnp.abs(rejection["x_r"][-1])
        return {
            "spectral_radius": rho,
            "stable": rho < 1.0,
            "steering_rms_rel": relative_rms("delta_h"),
            "rack_rms_rel": relative_rms("x_r"),
            "rack_final_error": jnp.where(jnp.isfinite(final), final, jnp.inf),
        }

    return Sweep(sampler, evaluate, config["plants"]["count"])


def report(config: dict, out_dir: Path, result=None, context=None) -> dict:
    cols = load_results(out_dir)
    stable = cols["metric.stable"].astype(bool)
    largest = 100 * np.max(np.abs(np.stack([cols[f"param.{f}"] for f in FACTORS], axis=1) - 1), axis=1)

    def quantiles(x):
        return {q: float(np.quantile(x, p)) for q, p in (("median", 0.5), ("p90", 0.9), ("max", 1.0))} if x.size else {}

    bins = [(lo, lo + 10) for lo in range(0, max(10, int(np.ceil(largest.max() / 10)) * 10), 10)]

    def fraction(mask):
        return float(stable[mask].mean()) if mask.any() else None

    by_largest = {f"{lo}-{hi} %": fraction((largest >= lo) & (largest < hi)) for lo, hi in bins}
    by_factor = {}
    for f in FACTORS:
        x = cols[f"param.{f}"]
        by_factor[f] = {"low": fraction(x < np.quantile(x, 0.2)), "high": fraction(x > np.quantile(x, 0.8))}
    summary = {
        "scenario": NAME,
        "num_configs": int(stable.size),
        "stable_fraction": float(stable.mean()),
        "stable_fraction_by_largest_error": by_largest,
        "stable_fraction_by_factor_quintile": by_factor,
        "steering_rms_rel": quantiles(cols["metric.steering_rms_rel"][stable]),
        "rack_rms_rel": quantiles(cols["metric.rack_rms_rel"][stable]),
        "rack_final_error_m": quantiles(cols["metric.rack_final_error"][stable]),
    }
    return write_sweep_report(out_dir, summary, config, result, [_plot(cols, stable, largest, out_dir)], _markdown)


def _plot(cols, stable, pct, out_dir: Path) -> str:
    """Spectral radius and model-matching errors against the largest of the eight errors (in %)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    axes[0].scatter(pct, cols["metric.spectral_radius"], c=np.where(stable, "C0", "C3"), s=6)
    axes[0].axhline(1.0, color="k", lw=0.8)
    axes[0].set(xlabel="largest gain/pole error (%)", ylabel="spectral radius (eq. 59)", title="Stability")
    for ax, key, label in ((axes[1], "steering_rms_rel", "steering angle"), (axes[2], "rack_rms_rel", "rack position")):
        ax.scatter(pct[stable], cols[f"metric.{key}"][stable], s=6)
        ax.set(xlabel="largest gain/pole error (%)", ylabel="RMS error / target peak", yscale="log",
               title=f"Model matching: {label} (stable plants)")  # fmt: skip
    return save_figure(fig, out_dir, "robustness")


def _markdown(summary: dict) -> str:
    lines = [
        "# Steer-by-wire model matching under actuator-model errors",
        "",
        f"{summary['num_configs']} plants; stable fraction {summary['stable_fraction']:.3f}.",
        "",
        "Stable fraction by the largest of the eight gain/pole errors: "
        + ", ".join(f"{k}: {v:.3f}" for k, v in summary["stable_fraction_by_largest_error"].items() if v is not None),
        "",
        "Stable fraction in the lowest / highest quintile of each factor: "
        + ", ".join(
            f"{k} {v['low']:.2f}/{v['high']:.2f}"
            for k, v in summary["stable_fraction_by_factor_quintile"].items()
            if None not in v.values()
        ),
        "",
        "| metric (stable plants) | median | 90 % | max |",
        "| --- | --- | --- | --- |",
    ]
    for key in ("steering_rms_rel", "rack_rms_rel", "rack_final_error_m"):
        q = summary[key]
        if q:
            lines.append(f"| {key} | {q['median']:.3g} | {q['p90']:.3g} | {q['max']:.3g} |")
    return "\n".join(lines) + "\n"


SCENARIO = SweepScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=make_sweep,
    report=report,
    size_keys=("plants.count",),
)
