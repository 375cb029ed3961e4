"""The noise-versus-gain trade-off of Grip 2010, section 6.7, on the DC motor with LuGre friction of section 6.8.

A grid eps x noise sigma x true alpha_0 x noise seeds. Per configuration, traced and ``vmap``ped by
:func:`jaxobs.sweep.run_sweep`: the plant with the drawn alpha_0 (:func:`jaxobs.papers.grip2010.dc_motor.truth`,
u = sin(pi t), y at 1 kHz with N(0, sigma^2) noise of the configuration's seed), observer 1 and the cascaded
observer 2 with the gains ``K(eps)`` (:meth:`jaxobs.observers.hgo.HGOGains.at`, designed once on the sigma_1 = 0
system) and the pure extended-state observer (g = 0) with observer 1's gains. Metrics: the RMS errors of omega of
the three observers over t > ``rms_start``, the mean of theta_hat over the same window and whether everything
stayed finite. ``jaxobs sweep --config tuning/dc_motor_hgo_sweep.toml``.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, fail
from jaxobs.observers.hgo import hgo_gains
from jaxobs.papers._output import pyplot, save_figure, write_sweep_report
from jaxobs.papers.grip2010 import dc_motor as dc
from jaxobs.papers.scenarios import Sweep, SweepScenario
from jaxobs.sweep import load_results

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "SCENARIO", "make_sweep", "report"]

NAME = "dc-motor-hgo"
OBSERVERS = ("observer1", "observer2", "pure_eso")
DEFAULT_CONFIG = {
    "scenario": NAME,
    "seed": 0,
    "chunk_size": 8,
    "grid": {
        "eps": [1.0, 0.5, 0.2, 0.1],  # the high-gain parameter of all three observers
        "sigma": [0.0, 1e-3, 1e-2],  # measurement noise (rad)
        "alpha_0": [0.1, 0.28, 0.6],  # the true static Coulomb friction (Nm), in Theta = [0.05, 1]
        "seeds": 2,  # noise seeds per grid point
    },
    "simulation": {"duration": 20.0, "rms_start": 10.0},
}
"""4 eps x 3 sigma x 3 alpha_0 x 2 seeds = 72 configurations of 20 s."""

CONFIG_NOTES = {
    "seed": "base of every configuration's random key (noise seeds are drawn from it)",
    "chunk_size": "configurations per device and step, and rows per Parquet chunk file",
    "grid": "the configurations: every combination of eps, sigma, alpha_0 and noise seed",
    "grid.eps": "high-gain parameter of the three observers, each in (0, 1]",
    "grid.sigma": "standard deviation of the measurement noise on the angle (rad), each >= 0",
    "grid.alpha_0": "true static Coulomb friction (Nm), each in the projection set Theta = [0.05, 1]",
    "grid.seeds": "noise seeds per grid point",
    "simulation": "the run of each configuration (u = sin(pi t) Nm, RK4 at 0.1 ms, y sampled at 1 kHz)",
    "simulation.duration": "simulated time (s)",
    "simulation.rms_start": "the RMS errors and the mean of theta_hat are taken over t > rms_start (s)",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    grid = config["grid"]
    low, high = dc.THETA_SET
    rules = (
        ("eps", lambda v: 0 < v <= 1, "in (0, 1]"),
        ("sigma", lambda v: v >= 0, ">= 0"),
        ("alpha_0", lambda v: low <= v <= high, f"in [{low}, {high}] (Theta)"),
    )
    for key, ok, what in rules:
        values = grid[key]
        if not (isinstance(values, list) and values and all(isinstance(v, int | float) and ok(v) for v in values)):
            fail(source, f"grid.{key}", f"must be a non-empty list of numbers {what}, got {values!r}")
    if isinstance(grid["seeds"], bool) or not isinstance(grid["seeds"], int):
        fail(source, "grid.seeds", f"must be an integer >= 1, got {grid['seeds']!r}")
    for key, low in (("seed", 0), ("chunk_size", 1), ("grid.seeds", 1), ("simulation.duration", dc.DT)):
        check_at_least(config, source, key, low)
    sim = config["simulation"]
    if not 0 <= sim["rms_start"] < sim["duration"]:
        fail(source, "simulation.rms_start", f"must be in [0, duration = {sim['duration']}), got {sim['rms_start']}")


def _grid(config: dict):
    g = config["grid"]
    axes = (g["eps"], g["sigma"], g["alpha_0"], list(range(g["seeds"])))
    return [jnp.asarray(a, float) for a in axes], tuple(len(a) for a in axes)


def make_sweep(config: dict):
    """``(sampler, evaluate, num_configs)`` for :func:`jaxobs.sweep.run_sweep`."""
    axes, shape = _grid(config)
    A, _, E, C = dc.matrices(dc.TABLE_6_1["sigma_1"])
    nominal = dc.matrices(0.0)
    d = (nominal[0], nominal[2], nominal[3])
    gains1 = hgo_gains(A, E, C, dc.POLES_1, 1.0, design=d)
    gains2 = hgo_gains(A, E, C, dc.POLES_2, 1.0, design=d, extended=False)
    duration, start = float(config["simulation"]["duration"]), float(config["simulation"]["rms_start"])

    def sampler(key, index):
        idx = jnp.unravel_index(index, shape)
        seed = jax.random.randint(key, (), 0, jnp.iinfo(jnp.int32).max, dtype=jnp.int32)
        return {"eps": axes[0][idx[0]], "sigma": axes[1][idx[1]], "alpha_0": axes[2][idx[2]], "noise_seed": seed}

    def evaluate(p):
        t, xs, _, inputs = dc.truth(p["alpha_0"], p["sigma"], jax.random.key(p["noise_seed"]), duration)
        K1 = gains1.at(p["eps"])
        out = dc.observers(K1, gains2.at(p["eps"]), inputs)
        late = t > start
        rms = lambda e: jnp.sqrt(jnp.sum(jnp.where(late, e, 0.0) ** 2) / jnp.sum(late))  # noqa: E731
        omega = xs[:, 1]
        errors = {
            "observer1": rms(omega - out.x[:, 1]),
            "observer2": rms(omega - out.x2[:, 1]),
            "pure_eso": rms(omega - dc.pure_eso(K1, inputs)[:, 1]),
        }
        theta_mean = jnp.sum(jnp.where(late, out.theta[:, 0], 0.0)) / jnp.sum(late)
        finite = jnp.all(jnp.stack([jnp.isfinite(v) for v in (*errors.values(), theta_mean)]))
        return {"rms_omega": errors, "theta_hat_mean": theta_mean, "finite": finite}

    return Sweep(sampler, evaluate, int(np.prod(shape)))


def report(config: dict, out_dir: Path, result=None, context=None) -> dict:
    """Median RMS omega errors per (eps, sigma) and observer, theta_hat means per alpha_0, and the figure."""
    cols = load_results(out_dir)
    g = config["grid"]
    table = {}
    for obs in OBSERVERS:
        per = {}
        for sigma in g["sigma"]:
            row = {}
            for eps in g["eps"]:
                sel = (cols["param.eps"] == eps) & (cols["param.sigma"] == sigma)
                row[str(eps)] = float(np.median(cols[f"metric.rms_omega.{obs}"][sel]))
            per[str(sigma)] = row
        table[obs] = per
    theta = {str(a): float(np.median(cols["metric.theta_hat_mean"][cols["param.alpha_0"] == a])) for a in g["alpha_0"]}
    summary = {
        "scenario": NAME,
        "num_configs": int(cols["index"].size),
        "finite_fraction": float(np.mean(cols["metric.finite"])),
        "median_rms_omega_error": table,
        "median_theta_hat_mean_by_alpha_0": theta,
    }
    return write_sweep_report(out_dir, summary, config, result, [_plot(table, g, out_dir)], _markdown)


def _plot(table: dict, grid: dict, out_dir: Path) -> str:
    plt = pyplot()
    fig, axes = plt.subplots(1, len(grid["sigma"]), figsize=(4 * len(grid["sigma"]), 3.5), squeeze=False)
    for ax, sigma in zip(axes[0], grid["sigma"], strict=True):
        for obs in OBSERVERS:
            ax.plot(grid["eps"], [table[obs][str(sigma)][str(e)] for e in grid["eps"]], "o-", label=obs)
        ax.set(xscale="log", yscale="log", xlabel="eps", title=f"sigma = {sigma} rad")
        ax.grid(alpha=0.3, which="both")
    axes[0, 0].set_ylabel("median RMS omega error (rad/s)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Grip 2010 §6.7: gain versus noise, DC motor with LuGre friction")
    return save_figure(fig, out_dir, "tradeoff")


def _markdown(summary: dict) -> str:
    lines = [
        "# DC motor with LuGre friction: the noise-versus-gain trade-off (Grip 2010, section 6.7)",
        "",
        f"{summary['num_configs']} configurations; all finite in a fraction {summary['finite_fraction']:.3f}.",
        "",
        "Median RMS omega error (rad/s) over the seeds and alpha_0:",
        "",
    ]
    for obs, per in summary["median_rms_omega_error"].items():
        eps = list(next(iter(per.values())))
        lines += [
            f"## {obs}",
            "",
            "| sigma | " + " | ".join(f"eps = {e}" for e in eps) + " |",
            "| --- |" + " --- |" * len(eps),
        ]
        lines += [f"| {s} | " + " | ".join(f"{v:.3g}" for v in row.values()) + " |" for s, row in per.items()]
        lines.append("")
    theta = summary["median_theta_hat_mean_by_alpha_0"]
    lines += [
        "Median theta_hat over the window, by the true alpha_0: "
        + ", ".join(f"{a}: {v:.4g}" for a, v in theta.items()),
        "",
    ]
    return "\n".join(lines) + "\n"


SCENARIO = SweepScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=make_sweep,
    report=report,
    size_keys=("simulation.duration", "grid.seeds", "grid.eps", "grid.sigma", "grid.alpha_0"),
)
