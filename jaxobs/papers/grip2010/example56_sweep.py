"""Example 5.6 of Grip 2010 over a grid of the modular estimator's gains, noise levels and noise seeds.

Each configuration is one point of ``grid.K_phi x grid.adaptation_gain x grid.noise_variance x grid.seeds`` (the index
runs over the seeds fastest). It runs both closed loops of :func:`jaxobs.papers.grip2010.adaptive.simulate_5_6` (the
scenario of the ``grip2010-example5.6`` reproduction: ``theta`` = -2, 4, -2, 4, -2 on consecutive segments, RK4 at 1
ms): the modular estimator with the configuration's ``(K_phi, adaptation_gain)`` and the gradient-type law with the
fixed ``gradient.adaptation_gain``, on the same noise ``sqrt(noise_variance) N(0, 1)`` per 1 ms sample added to the x
both laws use. Noise seed ``s`` is ``fold_in(PRNGKey(seed), s)`` at every grid point (common random numbers: the grid
points and the two laws are compared on the same noise). Metrics per law and configuration: the mean ``|theta_tilde|``
over the last ``scenario.window_s`` of each segment, the peak ``|x|`` per segment, whether the projection (modular) or
the limit to [-5, 5] (gradient) acted; ``inf`` where a run is not finite. ``jaxobs sweep --config
tuning/grip_example56_sweep.toml``.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, fail
from jaxobs.papers._output import pyplot, save_figure, write_sweep_report
from jaxobs.papers.grip2010 import adaptive as grip
from jaxobs.papers.scenarios import Sweep, SweepScenario
from jaxobs.sweep import load_results

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "SCENARIO", "make_sweep", "report"]

NAME = "grip-example56"
LAWS = ("modular", "gradient")
GRID = ("K_phi", "adaptation_gain", "noise_variance")

DEFAULT_CONFIG = {
    "scenario": NAME,
    "seed": 0,
    "chunk_size": 16,
    "grid": {
        "K_phi": [1.0, 3.0, 10.0, 30.0],  # the modular estimator's K_phi (printed: 10)
        "adaptation_gain": [0.3, 1.0, 3.0, 10.0],  # its adaptation_gain (printed: 3)
        "noise_variance": [0.0, 0.25, 1.0],  # of the N(0, variance) noise per 1 ms sample on x
        "seeds": 4,  # noise seeds per grid point (the same seeds at every point)
    },
    "gradient": {"adaptation_gain": grip.ADAPTATION_GAIN_GRADIENT},  # the gradient-type law's gain, fixed
    "scenario_timing": {
        "segment_s": grip.SEGMENT_S,  # length of each of the five theta segments (s)
        "window_s": grip.LAST_WINDOW_S,  # mean |theta_tilde| over each segment's last window_s (s)
    },
}
"""4 K_phi x 4 adaptation_gain x 3 noise variances x 4 seeds = 192 configurations of the 100 s scenario."""

CONFIG_NOTES = {
    "seed": "base of the noise keys (seed s is the same at every grid point, so both laws see the same noise)",
    "chunk_size": "configurations per device and step, and rows per Parquet chunk file",
    "grid": "the configurations: every combination of K_phi, adaptation_gain, noise variance and seed",
    "grid.K_phi": "the modular estimator's K_phi, each > 0 (printed: 10)",
    "grid.adaptation_gain": "its adaptation_gain, each > 0 (printed: 3)",
    "grid.noise_variance": "variance of the N(0, variance) noise per 1 ms sample on x, each >= 0",
    "grid.seeds": "noise seeds per grid point",
    "gradient": "the gradient-type law it is compared with",
    "gradient.adaptation_gain": "its gain (> 0; printed: 1), theta_hat limited to [-5, 5]",
    "scenario_timing": "the theta schedule and the error window",
    "scenario_timing.segment_s": "length of each of the five theta segments (s)",
    "scenario_timing.window_s": "mean |theta_tilde| over each segment's last window_s (s)",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    for key in GRID:
        values = config["grid"][key]
        if not isinstance(values, list) or not values:
            fail(source, f"grid.{key}", f"must be a non-empty list of numbers, got {values!r}")
        positive = key != "noise_variance"  # the gains must be positive, a variance may be 0
        if any(isinstance(v, bool) or not isinstance(v, int | float) or v < 0 or (positive and v == 0) for v in values):
            kind = "positive" if positive else "non-negative"
            fail(source, f"grid.{key}", f"must hold {kind} numbers, got {values!r}")
    for key, low, strict in (("seed", 0, False), ("chunk_size", 1, False), ("grid.seeds", 1, False),
                             ("gradient.adaptation_gain", 0, True), ("scenario_timing.segment_s", 0, True),
                             ("scenario_timing.window_s", 0, True)):  # fmt: skip
        check_at_least(config, source, key, low, strict=strict)
    timing = config["scenario_timing"]
    if timing["window_s"] > timing["segment_s"]:
        fail(source, "scenario_timing.window_s", f"must not exceed segment_s = {timing['segment_s']}")


def _num_configs(config: dict) -> int:
    g = config["grid"]
    return len(g["K_phi"]) * len(g["adaptation_gain"]) * len(g["noise_variance"]) * g["seeds"]


def _sampler(config: dict):
    g = config["grid"]
    tables = {key: jnp.asarray(g[key], float) for key in GRID}
    sizes = [len(g[key]) for key in GRID]
    seeds, base = g["seeds"], jax.random.PRNGKey(config["seed"])

    def sampler(key, index):  # the grid point and noise seed of configuration `index` (the key is unused)
        seed, rest = index % seeds, index // seeds
        picks = {}
        for name, size in zip(GRID[::-1], sizes[::-1], strict=True):
            rest, picks[name] = rest // size, rest % size
        return {**{name: tables[name][picks[name]] for name in GRID}, "noise_seed": seed}

    return sampler, base


def make_sweep(config: dict):
    """``(sampler, evaluate, num_configs)`` for :func:`jaxobs.sweep.run_sweep`."""
    sampler, base = _sampler(config)
    timing = config["scenario_timing"]
    seg, window = float(timing["segment_s"]), float(timing["window_s"])
    steps = len(grip.SEGMENT_THETAS) * round(seg / grip.DT)
    gamma_gradient = float(config["gradient"]["adaptation_gain"])

    def finite(a):
        return jnp.where(jnp.isfinite(a), a, jnp.inf)

    def evaluate(p):
        noise = jnp.sqrt(p["noise_variance"]) * jax.random.normal(jax.random.fold_in(base, p["noise_seed"]), (steps,))
        (xm, thm, xg, thg), (changed, limited) = grip.simulate_5_6(
            noise, p["K_phi"], p["adaptation_gain"], gamma_gradient, segment_s=seg
        )
        out = {}
        for law, x, th, active in (("modular", xm, thm, changed), ("gradient", xg, thg, limited)):
            _, peak, _, mean = grip.segment_metrics(x, th, segment_s=seg, window_s=window)
            out[law] = {"mean_abs_theta_error": finite(mean), "peak_abs_x": finite(peak),
                        "projection_active": jnp.any(active)}  # fmt: skip
        return out

    return Sweep(sampler, evaluate, _num_configs(config))


def _columns(cols: dict, law: str, metric: str) -> np.ndarray:
    """``(configs, segments)`` of a per-segment metric."""
    n = len(grip.SEGMENT_THETAS)
    return np.stack([cols[f"metric.{law}.{metric}[{i}]"] for i in range(n)], axis=1)


def _grid_table(config: dict, cols: dict) -> dict:
    """Per law, metric arrays shaped ``(K_phi, adaptation_gain, noise_variance, seeds, ...)``."""
    g = config["grid"]
    shape = (len(g["K_phi"]), len(g["adaptation_gain"]), len(g["noise_variance"]), g["seeds"])
    table = {}
    for law in LAWS:
        table[law] = {
            "mean": _columns(cols, law, "mean_abs_theta_error").reshape(*shape, -1),
            "peak": _columns(cols, law, "peak_abs_x").reshape(*shape, -1),
            "active": cols[f"metric.{law}.projection_active"].astype(bool).reshape(shape),
        }
    return table


def report(config: dict, out_dir: Path, result=None, context=None) -> dict:
    """Summarise the sweep's results in ``out_dir`` (``summary.json``, ``report.md``); returns the summary."""
    cols = load_results(out_dir)
    g = config["grid"]
    t = _grid_table(config, cols)
    points = []
    for i, k_phi in enumerate(g["K_phi"]):
        for j, gamma in enumerate(g["adaptation_gain"]):
            for v, variance in enumerate(g["noise_variance"]):
                point = {"K_phi": k_phi, "adaptation_gain": gamma, "noise_variance": variance}
                for law in LAWS:
                    mean, peak = t[law]["mean"][i, j, v], t[law]["peak"][i, j, v]  # (seeds, segments)
                    point[law] = {
                        "median_mean_abs_theta_error": float(np.median(mean)),
                        "median_mean_abs_theta_error_per_segment": np.median(mean, axis=0),
                        "median_peak_abs_x": float(np.median(np.max(peak, axis=1))),
                        "projection_active_fraction": float(np.mean(t[law]["active"][i, j, v])),
                        "finite_fraction": float(np.mean(np.all(np.isfinite(mean), axis=1))),
                    }
                better = t["modular"]["mean"][i, j, v] < t["gradient"]["mean"][i, j, v]
                point["modular_better_fraction"] = float(np.mean(better))
                points.append(point)
    summary = {
        "scenario": NAME,
        "num_configs": int(cols["index"].size),
        "metric_definitions": {
            "mean_abs_theta_error": "mean |theta_tilde| over each segment's last "
            f"{config['scenario_timing']['window_s']} s; median over the seeds (and the segments)",
            "peak_abs_x": "max |x| over the run; median over the seeds",
            "projection_active_fraction": "fraction of seeds in which the projection (modular) or the limit to "
            "[-5, 5] (gradient) acted",
            "modular_better_fraction": "fraction of seed x segment pairs with a lower modular mean |theta_tilde|",
        },
        "grid": points,
    }
    for v, variance in enumerate(g["noise_variance"]):  # the best modular gains per noise level
        med = np.median(t["modular"]["mean"][:, :, v].reshape(len(g["K_phi"]), len(g["adaptation_gain"]), -1), axis=2)
        i, j = np.unravel_index(np.argmin(np.where(np.isfinite(med), med, np.inf)), med.shape)
        summary.setdefault("best_modular_gains", {})[str(variance)] = {
            "K_phi": g["K_phi"][i], "adaptation_gain": g["adaptation_gain"][j],
            "median_mean_abs_theta_error": float(med[i, j]),
            "gradient_median_mean_abs_theta_error": float(np.median(t["gradient"]["mean"][0, 0, v])),
        }  # fmt: skip
    return write_sweep_report(out_dir, summary, config, result, [_plot(config, t, out_dir)], _markdown)


def _plot(config: dict, t: dict, out_dir: Path) -> str:
    """Per noise variance (rows): heat maps over (K_phi, adaptation_gain) of the modular estimator's median mean
    |theta_tilde|, the fraction of seed x segment pairs it beats the gradient law in, and its median peak |x|."""
    g = config["grid"]
    plt = pyplot()
    from matplotlib.colors import LogNorm

    rows = len(g["noise_variance"])
    fig, axes = plt.subplots(rows, 3, figsize=(14, 3.6 * rows), squeeze=False)
    nk, ng = len(g["K_phi"]), len(g["adaptation_gain"])
    med = np.median(t["modular"]["mean"].reshape(nk, ng, rows, -1), axis=3)
    better = np.mean((t["modular"]["mean"] < t["gradient"]["mean"]).reshape(nk, ng, rows, -1), axis=3)
    peak = np.median(np.max(t["modular"]["peak"], axis=4), axis=3)
    for v, variance in enumerate(g["noise_variance"]):
        grad = np.median(t["gradient"]["mean"][0, 0, v])
        finite = med[:, :, v][np.isfinite(med[:, :, v]) & (med[:, :, v] > 0)]  # one log scale per noise level
        norm = LogNorm(finite.min(), max(finite.max(), 1.001 * finite.min())) if finite.size else None
        panels = (
            (med[:, :, v], dict(norm=norm, cmap="viridis"), "median mean |theta_tilde| (modular)", ".3g"),
            (better[:, :, v], dict(vmin=0, vmax=1, cmap="RdBu"), "fraction better than gradient law", ".2f"),
            (peak[:, :, v], dict(cmap="magma"), "median peak |x| (modular)", ".3g"),
        )
        for ax, (values, style, title, fmt) in zip(axes[v], panels, strict=True):
            image = ax.imshow(np.where(np.isfinite(values), values, np.nan), origin="lower", aspect="auto", **style)
            for (i, j), value in np.ndenumerate(values):
                box = dict(facecolor="white", alpha=0.7, lw=0, pad=1)
                ax.text(j, i, format(value, fmt), ha="center", va="center", fontsize=7, bbox=box)
            ax.set_xticks(range(ng), [f"{x:g}" for x in g["adaptation_gain"]])
            ax.set_yticks(range(nk), [f"{x:g}" for x in g["K_phi"]])
            ax.set(xlabel="adaptation_gain (modular)", ylabel="K_phi", title=f"{title}\nnoise variance {variance:g}")
            fig.colorbar(image, ax=ax)
        axes[v, 0].set_title(axes[v, 0].get_title() + f"; gradient law: {grad:.3g}", fontsize=9)
        for ax in axes[v, 1:]:
            ax.title.set_fontsize(9)
    gradient_gain = config["gradient"]["adaptation_gain"]
    fig.suptitle(f"Grip 2010 Example 5.6: modular estimator over (K_phi, adaptation_gain), {g['seeds']} noise seeds "
                 f"per point (gradient-type law: adaptation_gain = {gradient_gain:g})")  # fmt: skip
    fig.tight_layout()
    return save_figure(fig, out_dir, "grid")


def _markdown(summary: dict) -> str:
    c = summary["config"]
    g, timing = c["grid"], c["scenario_timing"]
    lines = [
        "# Grip 2010 Example 5.6: the modular estimator over its gains and the noise level",
        "",
        f"{summary['num_configs']} configurations: K_phi in {g['K_phi']}, adaptation_gain in {g['adaptation_gain']}, "
        f"noise variance in {g['noise_variance']} (per 1 ms sample on x), {g['seeds']} noise seeds per point (the same "
        f"at every point); the gradient-type law with adaptation_gain = {c['gradient']['adaptation_gain']:g}. theta = "
        f"{list(grip.SEGMENT_THETAS)} on {timing['segment_s']:g} s segments; mean |theta_tilde| over each segment's "
        f"last {timing['window_s']:g} s.",
        "",
        "| noise var. | K_phi | adaptation_gain | mean abs theta err. modular | gradient | modular better | "
        "peak abs x modular | gradient | projection active modular | gradient |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for p in sorted(summary["grid"], key=lambda p: (p["noise_variance"], p["K_phi"], p["adaptation_gain"])):
        m, gr = p["modular"], p["gradient"]
        lines.append(
            f"| {p['noise_variance']:g} | {p['K_phi']:g} | {p['adaptation_gain']:g} | "
            f"{m['median_mean_abs_theta_error']:.3g} | "
            f"{gr['median_mean_abs_theta_error']:.3g} | {100 * p['modular_better_fraction']:.0f} % | "
            f"{m['median_peak_abs_x']:.3g} | {gr['median_peak_abs_x']:.3g} | "
            f"{100 * m['projection_active_fraction']:.0f} % | {100 * gr['projection_active_fraction']:.0f} % |"
        )
    lines += ["", "Best modular gains per noise variance (lowest median mean |theta_tilde|):", ""]
    for variance, b in summary["best_modular_gains"].items():
        lines.append(f"- variance {variance}: K_phi = {b['K_phi']:g}, adaptation_gain = {b['adaptation_gain']:g}: "
                     f"{b['median_mean_abs_theta_error']:.3g} "
                     f"(gradient law {b['gradient_median_mean_abs_theta_error']:.3g})")  # fmt: skip
    return "\n".join(lines) + "\n"


SCENARIO = SweepScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=make_sweep,
    report=report,
    size_keys=("scenario_timing.segment_s", "grid.seeds", "grid.K_phi", "grid.adaptation_gain", "grid.noise_variance"),
)
