"""Robustness sweep of the Example 1 force controllers (Cortesão 2006 §6-7): the default ``jaxobs sweep``.

AOB-1, AOB-2, AOB-3 and a CKF designed on the nominal plant for a grid of Q/R strategies, run against plants with
stiffness, time-constant and dead-time mismatch; per configuration the closed loop's spectral radius (eq. 59), the
margins (eq. 65) and the RMS force error of a 20 s run under the disturbance of eq. 81-82. The scenario:
docs/theory/papers.md.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, check_range, fail
from jaxobs._resources import compile_checked
from jaxobs.closed_loop import ideal_response, rms, simulate
from jaxobs.lti import n_delay_slots
from jaxobs.observers import active
from jaxobs.observers.feedback import FeedbackParams
from jaxobs.observers.linear import linear_controller
from jaxobs.papers._output import pyplot, save_figure, write_sweep_report
from jaxobs.papers.cortesao.force_control import (
    EXAMPLE1,
    example1_disturbance,
    nominal_design,
    reference_gain,
    with_feedback,
)
from jaxobs.papers.scenarios import Sweep, SweepScenario
from jaxobs.plants import force_plant
from jaxobs.stability import robustness_metrics
from jaxobs.sweep import load_results
from jaxobs.sweep_report import MARGIN_NOTES, quantiles

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "SCENARIO", "build_designs", "make_sweep", "report"]

NAME = "force-control"

DEFAULT_CONFIG = {
    "scenario": NAME,
    "seed": 0,
    "chunk_size": 2000,
    "plant": {
        "stiffness": [0.3, 30.0],
        "time_constant_scale": [0.5, 1.5],
        "dead_time_samples": [3.0, 8.0],
    },
    "controllers": {
        "orders": [1, 2, 3, 0],
        "active_variance": [1e-6, 1.0],
        "R": [1e-3, 1.0],
        "grid_points": 10,
    },
    "simulation": {
        "configs_per_design": 250,
        "duration": 20.0,
        "force_step": 10.0,
        "sensor_noise": EXAMPLE1.R,
    },
    "margins": {"num_points": 512},
}
"""The embedded default: 4 controllers x 10 x 10 strategies x 250 plants = 100 000 configurations."""

CONFIG_NOTES = {
    "seed": "base of every configuration's random key (configuration i draws from its own key)",
    "chunk_size": "configurations per device and step, and rows per Parquet chunk file",
    "plant": "the true plants, drawn independently per configuration",
    "plant.stiffness": "true sensor stiffness Ks (N/mm, nominal 3), log-uniform in [low, high]",
    "plant.time_constant_scale": "true Tp / nominal Tp (32 ms), uniform",
    "plant.dead_time_samples": "true dead time in samples of h = 8 ms (nominal 5), uniform; fractions allowed",
    "controllers": "the designs, all on the nominal plant: every order x grid_points x grid_points Q/R strategies",
    "controllers.orders": "AOB-N orders to design; 0 is the CKF (no active state)",
    "controllers.active_variance": "range of sigma^2 of eq. 55 (the CKF: its plant-state variance Q_xr), log grid",
    "controllers.R": "range of the designs' measurement variance R (N^2), log grid",
    "controllers.grid_points": "points of each log grid (one point: the geometric mean of the range)",
    "simulation": "the closed-loop run of each configuration (eq. 81-82 disturbance at the plant input)",
    "simulation.configs_per_design": "true plants per design; a larger value extends a sweep in the same directory",
    "simulation.duration": "simulated time (s)",
    "simulation.force_step": "force set-point (N) from t = 0",
    "simulation.sensor_noise": "the true sensor's noise variance (N^2)",
    "margins": "the loop transfer function's margins (eq. 65)",
    "margins.num_points": "frequency points of the margin search (at least 16)",
}

MAX_DEAD_TIME_SAMPLES = 100
MAX_ORDER = 5


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    check_range(config, source, "plant.stiffness", positive=True)
    check_range(config, source, "plant.time_constant_scale", positive=True)
    check_range(config, source, "plant.dead_time_samples", minimum=0.0, maximum=MAX_DEAD_TIME_SAMPLES)
    check_range(config, source, "controllers.active_variance", positive=True)
    check_range(config, source, "controllers.R", positive=True)
    orders = config["controllers"]["orders"]
    if not orders or any(not isinstance(n, int) or not 0 <= n <= MAX_ORDER for n in orders):
        fail(source, "controllers.orders", f"must be a non-empty list of integers in 0..{MAX_ORDER}, got {orders!r}")
    if len(set(orders)) != len(orders):
        fail(source, "controllers.orders", f"has duplicates: {orders!r}")
    for key, low in (
        ("seed", 0),
        ("chunk_size", 1),
        ("controllers.grid_points", 1),
        ("simulation.configs_per_design", 1),
        ("margins.num_points", 16),
    ):
        check_at_least(config, source, key, low)
    for key in ("duration", "force_step", "sensor_noise"):
        check_at_least(config, source, f"simulation.{key}", 0, strict=True)
    if config["simulation"]["duration"] < EXAMPLE1.h:
        fail(source, "simulation.duration", f"must be at least one sample ({EXAMPLE1.h} s)")


# --------------------------------------------------------------------------------------------
# Designs and the per-configuration evaluation


@dataclasses.dataclass(frozen=True)
class Designs:
    """Stacked controllers (leading axis: design), padded to a common observer size."""

    controller: FeedbackParams  # params of jaxobs.observers.linear.linear_controller
    order: np.ndarray  # 0 = CKF
    active_variance: np.ndarray
    R: np.ndarray

    def __len__(self) -> int:
        return len(self.order)


def _log_grid(bounds, points: int) -> np.ndarray:
    return np.geomspace(bounds[0], bounds[1], points) if points > 1 else np.array([np.sqrt(bounds[0] * bounds[1])])


def build_designs(config: dict) -> Designs:
    """Every (order, sigma^2, R) controller of the grid, with steady-state gains (batched DAREs)."""
    plant, L_r = nominal_design()
    ctl = config["controllers"]
    variances, Rs = _log_grid(ctl["active_variance"], ctl["grid_points"]), _log_grid(ctl["R"], ctl["grid_points"])
    V, R = (a.ravel() for a in np.meshgrid(variances, Rs, indexing="ij"))
    n_obs = plant.n_states + max(ctl["orders"])
    parts, orders = [], []
    for order in ctl["orders"]:

        def design(v, r, order=order):
            if order == 0:
                params = active.make_ckf(plant, r, q_plant=v, steady_state=True)
            else:
                q = active.evolution_variance(v, order, EXAMPLE1.c)
                params = active.make_aob(plant, order, r, q_plant=EXAMPLE1.q_plant, q_active=q, steady_state=True)
            return active.active_observer_controller.linear(with_feedback(params, L_r)).padded(n_obs)

        V_, R_ = jnp.asarray(V), jnp.asarray(R)
        build = compile_checked(jax.jit(jax.vmap(design)).lower(V_, R_), f"the {V.size} designs of order {order}",
                                hint="lower controllers.grid_points")  # fmt: skip
        parts.append(build(V_, R_))
        orders.append(np.full(V.size, order))
    stacked = jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)
    count = len(ctl["orders"])
    return Designs(stacked, np.concatenate(orders), np.tile(V, count), np.tile(R, count))


def _timing(config: dict) -> tuple[int, int]:
    """``(steps, n_delay)``: the samples of a run and the dead-time slots of the plants."""
    h = EXAMPLE1.h
    steps = int(round(config["simulation"]["duration"] / h))
    return steps, n_delay_slots(config["plant"]["dead_time_samples"][1] * h, h)


def _signals(config: dict, steps: int):
    """``f() -> (reference, desired force, disturbance)``, each (steps,), shared by every configuration. Called inside
    the traced closed loop, their size counts in the sweep step's memory estimate instead of being allocated while
    the sweep is built (the nominal design is computed here, eagerly)."""
    h = EXAMPLE1.h
    nominal, L_r = nominal_design()
    level = reference_gain(L_r) * config["simulation"]["force_step"]

    def signals():
        reference = jnp.full((steps,), level)
        desired = ideal_response(nominal, L_r, reference)[:, 0]
        return reference, desired, example1_disturbance(jnp.arange(steps) * h)

    return signals


def tracking(config: dict):
    """``(true plant, controller, noise seed) -> (force, RMS force error, peak |force|)``: the closed loop of
    the scenario (the two scores are inf where it diverges)."""
    steps = _timing(config)[0]
    signals = _signals(config, steps)
    std = jnp.sqrt(config["simulation"]["sensor_noise"])

    def run(true, ctrl, noise_seed):
        reference, desired, disturbance = signals()
        noise = std * jax.random.normal(jax.random.PRNGKey(noise_seed), (steps,))
        trace = simulate(true, linear_controller, ctrl, reference, disturbance=disturbance, noise=noise)
        force = trace.y_true[:, 0]
        error, peak = rms(force - desired), jnp.max(jnp.where(jnp.isfinite(force), jnp.abs(force), jnp.inf))
        return force, jnp.where(jnp.isfinite(error), error, jnp.inf), peak

    return run


def make_sweep(config: dict):
    """The sweep of ``config``: its context is the :class:`Designs`."""
    designs = build_designs(config)
    plant_cfg, h = config["plant"], EXAMPLE1.h
    n_delay = _timing(config)[1]
    closed_loop = tracking(config)
    table = designs.controller
    order, variance, R = (jnp.asarray(a) for a in (designs.order, designs.active_variance, designs.R))
    log_ks = np.log(plant_cfg["stiffness"])
    count = len(designs)

    def sampler(key, index):
        k_ks, k_tp, k_dead, k_noise = jax.random.split(key, 4)
        design = index % count
        return {
            "design": design,
            "order": order[design],
            "active_variance": variance[design],
            "R": R[design],
            "stiffness": jnp.exp(jax.random.uniform(k_ks, (), minval=log_ks[0], maxval=log_ks[1])),
            "time_constant": EXAMPLE1.Tp * jax.random.uniform(k_tp, (), minval=plant_cfg["time_constant_scale"][0],
                                                              maxval=plant_cfg["time_constant_scale"][1]),
            "dead_time_samples": jax.random.uniform(k_dead, (), minval=plant_cfg["dead_time_samples"][0],
                                                    maxval=plant_cfg["dead_time_samples"][1]),
            "noise_seed": jax.random.bits(k_noise, (), jnp.uint32),
        }  # fmt: skip

    def evaluate(p):
        ctrl = jax.tree.map(lambda M: M[p["design"]], table)
        true = force_plant(p["stiffness"], p["time_constant"], h, p["dead_time_samples"] * h, n_delay=n_delay)
        row = robustness_metrics(true, linear_controller, ctrl, num_points=config["margins"]["num_points"])
        _, error, peak = closed_loop(true, ctrl, p["noise_seed"])
        return row | {"rms_force_error": error, "peak_force": peak}

    return Sweep(sampler, evaluate, count * config["simulation"]["configs_per_design"], designs)


# --------------------------------------------------------------------------------------------
# Report: summary.json, report.md, figures

NAMES = {0: "CKF"}


def _name(order: int) -> str:
    return NAMES.get(order, f"AOB-{order}")


def summarize(config: dict, cols: dict) -> dict:
    """Per-controller statistics of a completed sweep."""
    stable = cols["metric.stable"].astype(bool)
    ks_ratio = cols["param.stiffness"] / EXAMPLE1.Ks
    per = {}
    for order in config["controllers"]["orders"]:
        sel = cols["param.order"] == order
        s = sel & stable
        near = sel & (np.abs(np.log(ks_ratio)) < np.log(1.5))
        conditional = cols["metric.gain_margin_lower"][s] > 0  # a gain reduction destabilises them
        per[_name(order)] = {
            "configs": int(sel.sum()),
            "invalid": int((sel & ~cols["metric.valid"]).sum()),
            "stable_fraction": float(stable[sel].mean()),
            "stable_fraction_within_50pct_stiffness": float(stable[near].mean()) if near.any() else None,
            "conditionally_stable_fraction": float(conditional.mean()) if s.any() else None,
            "rms_force_error_stable": quantiles(cols["metric.rms_force_error"][s]),
            **{f"{m}_stable": quantiles(cols[f"metric.{m}"][s]) for m in ("gain_margin", "gain_margin_lower",
                                                                         "gain_margin_upper", "phase_margin")},
            "delay_margin_stable_s": quantiles(cols["metric.delay_margin"][s]),
        }  # fmt: skip
    return per


MARGIN_RADIUS = 0.99
"""A closed loop with this spectral radius or less has a margin: its slowest mode decays to 1/e within 100
samples (0.8 s); the figures show each controller's worst case among these beside its worst stable one."""


def _worst_cases(cols: dict, orders, radius: float = 1.0) -> dict:
    """Per controller, the configuration of spectral radius below ``radius`` with the largest RMS force error."""
    worst = {}
    for order in orders:
        sel = np.flatnonzero((cols["param.order"] == order) & (cols["metric.spectral_radius"] < radius))
        if sel.size:
            i = sel[np.argmax(cols["metric.rms_force_error"][sel])]
            worst[_name(order)] = {k.split(".", 1)[1]: cols[k][i].item() for k in cols if k != "index"}
            worst[_name(order)]["index"] = int(cols["index"][i])
    return worst


def report(config: dict, out_dir: Path, result=None, designs: Designs | None = None) -> dict:
    """Write ``summary.json``, ``report.md`` and the figures for the sweep in ``out_dir``."""
    cols = load_results(out_dir)
    orders = config["controllers"]["orders"]
    summary = {
        "num_configs": int(cols["index"].size),
        "invalid": int((~cols["metric.valid"]).sum()),
        "stable_fraction": float(cols["metric.stable"].mean()),
        "controllers": summarize(config, cols),
        "worst_cases": _worst_cases(cols, orders),
        "worst_cases_with_margin": _worst_cases(cols, orders, MARGIN_RADIUS),
    }
    figures = [
        _plot_stability_maps(cols, orders, out_dir),
        _plot_distributions(cols, orders, out_dir),
        _plot_worst_cases(config, designs or build_designs(config), summary, out_dir),
    ]
    return write_sweep_report(out_dir, summary, config, result, figures, _markdown)


def _plot_stability_maps(cols, orders, out_dir: Path) -> str:
    """Stable fraction over stiffness mismatch and sigma^2 / R, a heat map per controller (a row per value of
    sigma^2 / R where there are at most 10); a sweep of one sigma^2 / R (``grid_points = 1``) is drawn as a line
    per controller over the stiffness mismatch."""
    plt = pyplot()
    ks_ratio = np.log10(cols["param.stiffness"] / EXAMPLE1.Ks)
    ratio = np.log10(cols["param.active_variance"] / cols["param.R"])
    x_edges = np.linspace(ks_ratio.min(), ks_ratio.max(), 13)
    stable = cols["metric.stable"].astype(float)
    y_label = "log10 sigma^2 / R" + (" (CKF: Q_xr / R)" if 0 in orders else "")
    if np.ptp(ratio) < 1e-6:
        fig, ax = plt.subplots(figsize=(6.5, 3.6), layout="constrained")
        centres = 0.5 * (x_edges[:-1] + x_edges[1:])
        for order in orders:
            sel = cols["param.order"] == order
            total = np.histogram(ks_ratio[sel], x_edges)[0]
            with np.errstate(invalid="ignore"):
                frac = np.histogram(ks_ratio[sel], x_edges, weights=stable[sel])[0] / total
            ax.plot(centres, frac, "o-", color=_colour(order), label=_name(order))
        ax.axvline(0.0, color="k", lw=0.6)
        ax.set(xlabel="log10 Ks_true / Ks_nominal", ylabel="stable fraction", ylim=(-0.03, 1.03),
               title=f"Stable fraction vs stiffness mismatch\n(one strategy: {y_label} = {ratio[0]:.2f})")  # fmt: skip
        ax.title.set_fontsize(10)
        ax.legend(loc="lower left")
        return save_figure(fig, out_dir, "stability_maps")
    levels = np.unique(np.round(ratio, 9))
    if levels.size <= 10:  # a row per strategy, edges halfway between them
        mid = 0.5 * (levels[1:] + levels[:-1])
        y_edges = np.concatenate([[2 * levels[0] - mid[0]], mid, [2 * levels[-1] - mid[-1]]])
    else:
        y_edges = np.linspace(ratio.min(), ratio.max(), 11)
    fig, axes = plt.subplots(1, len(orders), figsize=(3.6 * len(orders), 3.6), squeeze=False, layout="constrained")
    for ax, order in zip(axes[0], orders, strict=True):
        sel = cols["param.order"] == order
        total, _, _ = np.histogram2d(ks_ratio[sel], ratio[sel], [x_edges, y_edges])
        count, _, _ = np.histogram2d(ks_ratio[sel], ratio[sel], [x_edges, y_edges], weights=stable[sel])
        with np.errstate(invalid="ignore"):
            frac = count / total
        mesh = ax.pcolormesh(x_edges, y_edges, frac.T, vmin=0, vmax=1, cmap="RdYlGn")
        if levels.size <= 10:
            ax.set_yticks(levels)
        ax.set_title(_name(order))
        ax.set_xlabel("log10 Ks_true / Ks_nominal")
        ax.axvline(0.0, color="k", lw=0.6)
    axes[0, 0].set_ylabel(y_label)
    fig.colorbar(mesh, ax=axes[0].tolist(), label="stable fraction (white: no configuration)")
    fig.suptitle("Stable fraction vs stiffness mismatch and Q/R strategy")
    return save_figure(fig, out_dir, "stability_maps")


def _plot_distributions(cols, orders, out_dir: Path) -> str:
    """Histograms of the stable configurations' margins and RMS errors, in report.md's units; the quantities that
    span decades on log axes (log-spaced bins shared by the controllers)."""
    plt = pyplot()
    stable = cols["metric.stable"].astype(bool)
    panels = [  # key, label, scale to report.md's unit, log axis
        (
            "metric.gain_margin_lower",
            "lower gain margin (factor < 1;\n0: not conditionally stable, left out)",
            1.0,
            True,
        ),
        ("metric.gain_margin_upper", "upper gain margin (factor > 1)", 1.0, True),
        ("metric.phase_margin", "phase margin (deg)", 1.0, False),
        ("metric.delay_margin", "delay margin (ms)", 1e3, True),
        ("metric.rms_force_error", "RMS force error (N)", 1.0, True),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(19, 3.8), layout="constrained")
    for ax, (key, label, scale, log) in zip(axes, panels, strict=True):
        values = {}
        for order in orders:
            v = scale * cols[key][(cols["param.order"] == order) & stable]
            values[order] = v[np.isfinite(v) & (v > 0)] if log else v[np.isfinite(v)]
        pooled = np.concatenate(list(values.values()))
        if not pooled.size:
            continue
        low, high = pooled.min(), pooled.max()
        bins = np.geomspace(low, high * (1 + 1e-9), 41) if log and high > low else 40
        for order, v in values.items():
            if v.size:
                ax.hist(v, bins=bins, histtype="step", label=_name(order), color=_colour(order))
        if log:
            ax.set_xscale("log")
        ax.set_xlabel(label)
    axes[0].set_ylabel("stable configurations")
    fullest = max(axes, key=lambda ax: len(ax.get_legend_handles_labels()[0]))  # every controller with a value
    if fullest.get_legend_handles_labels()[0]:  # not for a sweep without a stable configuration
        fullest.legend()
    fig.suptitle("Margins and tracking error over the stable configurations (infinite margins left out)")
    return save_figure(fig, out_dir, "distributions")


def _colour(order: int) -> str:
    """One colour per controller in every figure (AOB-1, AOB-2, AOB-3, CKF)."""
    return {1: "C0", 2: "C1", 3: "C2", 0: "C3"}.get(order, "C4")


def _decay_time(radius: float) -> float:
    """Seconds for a mode of the spectral ``radius`` to decay to 1/e."""
    return EXAMPLE1.h / -np.log(radius) if radius < 1.0 else np.inf


def _plot_worst_cases(config: dict, designs: Designs, summary: dict, out_dir: Path) -> str:
    """Re-simulate each controller's worst stable case and its worst case with a margin (spectral radius at most
    :data:`MARGIN_RADIUS`), same noise, against the desired force; one panel per controller, each case labelled by
    its spectral radius and the decay time of its slowest mode, the disturbance step (eq. 82) marked."""
    plt = pyplot()
    steps, n_delay = _timing(config)
    desired = _signals(config, steps)()[1]
    closed_loop = tracking(config)
    t = np.arange(steps) * EXAMPLE1.h
    orders = {_name(order): order for order in config["controllers"]["orders"]}
    worst, margin = summary["worst_cases"], summary["worst_cases_with_margin"]
    rows = max(len(worst), 1)  # a sweep without a stable configuration still gets its (empty) figure
    fig, axes = plt.subplots(rows, 1, figsize=(12, 2.8 * rows + 0.6), sharex=True, squeeze=False,
                             layout="constrained")  # fmt: skip
    for ax in axes[:, 0]:
        ax.plot(t, np.asarray(desired), "k--", lw=1, label="desired")
        if t[-1] >= 8.0:
            ax.axvline(8.0, color="0.4", lw=0.8, ls=":", label="disturbance step (eq. 82)")
        ax.set_ylabel("force (N)")
    if not worst:
        axes[0, 0].set_title("no stable configuration")
    for ax, name in zip(axes[: len(worst), 0], worst, strict=True):
        cases = [("worst stable", worst[name], 0.8)]
        if name in margin and margin[name]["index"] != worst[name]["index"]:
            cases.append((f"worst with radius <= {MARGIN_RADIUS}", margin[name], 1.6))
        for label, case, lw in cases:
            ctrl = jax.tree.map(lambda M, d=case["design"]: M[d], designs.controller)
            true = force_plant(case["stiffness"], case["time_constant"], EXAMPLE1.h,
                               case["dead_time_samples"] * EXAMPLE1.h, n_delay=n_delay)  # fmt: skip
            force = closed_loop(true, ctrl, case["noise_seed"])[0]
            rho = case["spectral_radius"]
            ax.plot(t, np.asarray(force), lw=lw, alpha=0.9 if lw > 1 else 0.6, color=_colour(orders[name]),
                    label=f"{label}: spectral radius {rho:.4f}\n(slowest mode to 1/e in {_decay_time(rho):.2g} s), "
                          f"Ks = {case['stiffness']:.2g} N/mm,\ndead time {case['dead_time_samples']:.1f} samples, "
                          f"RMS error {case['rms_force_error']:.2f} N")  # fmt: skip
        ax.set_title(name, loc="left", fontsize=10, fontweight="bold")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle("Worst cases per controller (largest RMS force error), each with its closed loop's spectral radius "
                 "(stable below 1)")  # fmt: skip
    return save_figure(fig, out_dir, "worst_cases")


def _markdown(summary: dict) -> str:
    lines = [
        "# Robustness sweep: Example 1 force controllers",
        "",
        f"{summary['num_configs']} configurations; overall stable fraction {summary['stable_fraction']:.3f}; "
        f"{summary['invalid']} invalid.",
    ]
    lines += [
        "",
        "| controller | stable | stable, Ks within x1.5 | conditionally stable | median RMS force error (N) "
        "| median lower GM | median upper GM | median PM (deg) | median delay margin (ms) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    fmt = lambda q, scale=1.0: f"{q['median'] * scale:.3g}" if q.get("count") else "-"
    share = lambda x: "-" if x is None else f"{x:.3f}"
    for name, s in summary["controllers"].items():
        lines.append(
            f"| {name} | {s['stable_fraction']:.3f} | {share(s['stable_fraction_within_50pct_stiffness'])} "
            f"| {share(s['conditionally_stable_fraction'])} | {fmt(s['rms_force_error_stable'])} "
            f"| {fmt(s['gain_margin_lower_stable'])} | {fmt(s['gain_margin_upper_stable'])} "
            f"| {fmt(s['phase_margin_stable'])} | {fmt(s['delay_margin_stable_s'], 1e3)} |"
        )
    lines += ["", "Over the stable configurations; conditionally stable: the share of them with a lower gain margin. "
              + MARGIN_NOTES]  # fmt: skip
    lines += ["", "Worst stable case per controller (largest RMS force error):", ""]
    for name, case in summary["worst_cases"].items():
        lines.append(
            f"- {name}: config {case['index']}, Ks = {case['stiffness']:.3g} N/mm, Tp = {case['time_constant']:.4f} s, "
            f"dead time {case['dead_time_samples']:.2f} samples, sigma^2 = {case['active_variance']:.2g}, "
            f"R = {case['R']:.2g}: RMS {case['rms_force_error']:.3g} N, spectral radius {case['spectral_radius']:.4f}"
        )
    lines += ["", f"Worst case with a margin (spectral radius at most {MARGIN_RADIUS}):", ""]
    for name, case in summary["worst_cases_with_margin"].items():
        lines.append(
            f"- {name}: config {case['index']}, Ks = {case['stiffness']:.3g} N/mm, "
            f"RMS {case['rms_force_error']:.3g} N, spectral radius {case['spectral_radius']:.4f}"
        )
    return "\n".join(lines) + "\n"


SCENARIO = SweepScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=make_sweep,
    report=report,
    size_key="simulation.configs_per_design",
    size_keys=(
        "simulation.duration",
        "simulation.configs_per_design",
        "controllers.grid_points",
        "controllers.orders",
        "margins.num_points",
    ),
)
