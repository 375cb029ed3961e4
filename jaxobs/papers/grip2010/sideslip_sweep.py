"""The sideslip observers of Grip 2010 ch. 2 over manoeuvres, road friction, sensor errors and vehicle mismatch.

Each configuration is one point of the grid of manoeuvre, friction, accelerometer bias and drift, mass, cornering
stiffness and seed; the NVSO and the EKF of §2.9, built on the nominal vehicle, run on the true vehicle's ESC
sensors. Metrics per observer: sideslip, friction, bank and inclination errors and the share of samples with
friction estimation on. ``jaxobs sweep --config tuning/sideslip_sweep.toml``. Details: docs/theory/papers.md.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, fail
from jaxobs.observers.base import run as run_observer
from jaxobs.papers._output import pyplot, save_figure, write_sweep_report
from jaxobs.papers.scenarios import Sweep, SweepScenario
from jaxobs.sweep import load_results
from jaxobs.vehicle import (
    MANOEUVRES,
    Command,
    Manoeuvre,
    SensorParams,
    VehicleParams,
    make_nvso,
    make_vehicle_ekf,
    measure,
    nvso,
    sensor_inputs,
    simulate,
    vehicle_ekf,
)

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "SCENARIO", "drive", "mismatched_vehicle", "make_sweep", "report"]

NAME = "sideslip"
OBSERVERS = ("nvso", "ekf")
NUMERIC = ("friction", "acc_bias", "drift", "mass", "cornering_stiffness")
DEFAULT_CONFIG = {
    "scenario": NAME,
    "seed": 0,
    "chunk_size": 8,
    "grid": {
        "manoeuvre": ["sine_steer", "double_lane_change_120kmh", "mountain_road"],
        "friction": [1.0, 0.7],  # scale on the manoeuvre's road friction
        "acc_bias": [0.0, 0.3],  # m/s^2 on both accelerometers
        "drift": [0.0, 0.05],  # accelerometer random walk, m/s^2 per sqrt(s)
        "mass": [1.0, 1.2],  # true mass over the observers' nominal
        "cornering_stiffness": [1.0, 0.8],  # true tyres' cornering stiffness over the nominal
        "seeds": 1,  # sensor noise seeds per grid point
    },
    "simulation": {"duration": 10.0, "error_start": 1.0},
}
"""3 manoeuvres x 2 frictions x 2 biases x 2 drifts x 2 masses x 2 stiffnesses x 1 seed = 96 configurations."""

CONFIG_NOTES = {
    "seed": "base of every configuration's random key (sensor noise and drift seeds are drawn from it)",
    "chunk_size": "configurations per device and step, and rows per Parquet chunk file",
    "grid": "the configurations: every combination of the lists below and the noise seeds",
    "grid.manoeuvre": f"test drives (Grip 2010 §2.10), each one of {', '.join(MANOEUVRES)}",
    "grid.friction": "scale on the manoeuvre's road friction, each > 0 (1: as the drive was designed)",
    "grid.acc_bias": "bias of both accelerometers (m/s^2); Grip 2010 §2.8 allows up to 1.0 with the drift",
    "grid.drift": "random-walk intensity of both accelerometers (m/s^2 per sqrt(s)), each >= 0",
    "grid.mass": "true vehicle mass over the observers' nominal, each > 0",
    "grid.cornering_stiffness": "true cornering stiffness of all four tyres over the nominal, each > 0",
    "grid.seeds": "sensor noise seeds per grid point",
    "simulation": "the run of each configuration (RK4 at 1 ms, sensors at 100 Hz)",
    "simulation.duration": "simulated time of every manoeuvre (s; a shorter drive continues with its last command)",
    "simulation.error_start": "the RMS and largest errors are taken over t >= error_start (s)",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    grid = config["grid"]
    unknown = [m for m in grid["manoeuvre"] if m not in MANOEUVRES]
    if unknown:
        fail(source, "grid.manoeuvre", f"unknown {unknown}; choose from {', '.join(MANOEUVRES)}")
    rules = {"acc_bias": (lambda v: True, ""), "drift": (lambda v: v >= 0, " >= 0")}
    for key in NUMERIC:
        ok, what = rules.get(key, (lambda v: v > 0, " > 0"))
        if not (grid[key] and all(ok(v) for v in grid[key])):
            fail(source, f"grid.{key}", f"must be a non-empty list of numbers{what}, got {grid[key]!r}")
    if isinstance(grid["seeds"], bool) or not isinstance(grid["seeds"], int):
        fail(source, "grid.seeds", f"must be an integer >= 1, got {grid['seeds']!r}")
    for key, low in (("seed", 0), ("chunk_size", 1), ("grid.seeds", 1), ("simulation.duration", 0.1)):
        check_at_least(config, source, key, low)
    sim = config["simulation"]
    if not 0 <= sim["error_start"] < sim["duration"]:
        duration = sim["duration"]
        fail(source, "simulation.error_start", f"must be in [0, duration = {duration}), got {sim['error_start']}")


def _grid(config: dict):
    g = config["grid"]
    axes = [list(range(len(g["manoeuvre"]))), *(g[k] for k in NUMERIC), list(range(g["seeds"]))]
    return [jnp.asarray(a, float) for a in axes], tuple(len(a) for a in axes)


def drive(names, index, friction) -> Manoeuvre:
    """The manoeuvre ``names[index]`` (``names`` keys of :data:`jaxobs.vehicle.MANOEUVRES`, ``index`` may be traced)
    with its road friction scaled by ``friction``."""
    drives = [MANOEUVRES[n] for n in names]

    def branch(m):
        return lambda t: Command(*(jnp.asarray(v, float) for v in m.command(t)))

    def command(t):
        c = jax.lax.switch(index, [branch(m) for m in drives], t)
        return c._replace(friction=c.friction * friction)

    speed = jnp.asarray([m.initial_speed for m in drives])[index]
    return Manoeuvre("sweep", command, 0.0, speed)


def mismatched_vehicle(mass, stiffness) -> VehicleParams:
    """The default vehicle with its ``mass`` and the cornering stiffness of all four tyres scaled (``stiffness``)."""
    v = VehicleParams()
    scale = lambda tyre: dataclasses.replace(tyre, cornering_stiffness=tyre.cornering_stiffness * stiffness)  # noqa: E731
    return dataclasses.replace(v, mass=v.mass * mass, tyre_front=scale(v.tyre_front), tyre_rear=scale(v.tyre_rear))


def make_sweep(config: dict):
    """``(sampler, evaluate, num_configs)`` for :func:`jaxobs.sweep.run_sweep`."""
    axes, shape = _grid(config)
    names = tuple(config["grid"]["manoeuvre"])
    duration, start = float(config["simulation"]["duration"]), float(config["simulation"]["error_start"])
    nominal = VehicleParams()
    nvso_params, ekf_params = make_nvso(nominal), make_vehicle_ekf(nominal)

    def sampler(key, index):
        idx = jnp.unravel_index(index, shape)
        seed = jax.random.randint(key, (), 0, jnp.iinfo(jnp.int32).max, dtype=jnp.int32)
        drawn = {name: axes[i + 1][idx[i + 1]] for i, name in enumerate(NUMERIC)}
        return {"manoeuvre": idx[0].astype(jnp.int32), **drawn, "noise_seed": seed}

    def evaluate(p):
        truth = mismatched_vehicle(p["mass"], p["cornering_stiffness"])
        tr = simulate(drive(names, p["manoeuvre"], p["friction"]), truth, duration=duration)
        sensors = SensorParams(bias_ax=p["acc_bias"], bias_ay=p["acc_bias"], drift_acc=p["drift"])
        meas = measure(tr, truth, sensors, jax.random.key(p["noise_seed"]))
        inputs = sensor_inputs(meas)
        _, out_n = run_observer(nvso, nvso_params._replace(vx0=meas.vx_ref[0]), inputs)
        _, out_e = run_observer(vehicle_ekf, ekf_params, inputs)  # starts from the first v_x,ref itself
        samples = jax.tree_util.tree_map(lambda a: a[::10], tr)  # the plant at the sensor times
        beta = samples.beta
        bank = jnp.cos(samples.inputs.inclination) * jnp.sin(samples.inputs.bank)
        incline = jnp.sin(samples.inputs.inclination)
        friction = samples.inputs.friction[-1]
        late = meas.time >= start
        rms = lambda e: jnp.rad2deg(jnp.sqrt(jnp.sum(jnp.where(late, e, 0.0) ** 2) / jnp.sum(late)))  # noqa: E731
        peak = lambda e: jnp.rad2deg(jnp.max(jnp.where(late, jnp.abs(e), 0.0)))  # noqa: E731
        estimates = {  # (sideslip, friction, inclination, bank, mode)
            "nvso": (out_n.beta, out_n.x[:, 2], out_n.x[:, 3], out_n.x[:, 4], out_n.mode),
            "ekf": (out_e.beta, out_e.x[:, 4], out_e.x[:, 2], out_e.x[:, 3], out_e.mode),
        }
        metrics = {}
        for name, (b, mu, ti, tb, mode) in estimates.items():
            metrics[name] = {
                "beta_rms_deg": rms(b - beta),
                "beta_max_deg": peak(b - beta),
                "friction_error": mu[-1] - friction,
                "bank_rms_deg": rms(tb - bank),
                "inclination_rms_deg": rms(ti - incline),
                "excited_fraction": jnp.mean(mode),
            }
        values = jnp.stack([v for m in metrics.values() for v in m.values()])
        return {**metrics, "true_beta_max_deg": jnp.rad2deg(jnp.max(jnp.abs(beta))),
                "finite": jnp.all(jnp.isfinite(values))}  # fmt: skip

    return Sweep(sampler, evaluate, int(np.prod(shape)))


_METRICS = ("beta_rms_deg", "beta_max_deg", "friction_error", "bank_rms_deg", "inclination_rms_deg",
            "excited_fraction")  # fmt: skip


def report(config: dict, out_dir: Path, result=None, context=None) -> dict:
    """Medians of every metric per observer by manoeuvre, and by each other grid axis; the figure."""
    cols = load_results(out_dir)
    g = config["grid"]

    def medians(select):
        return {obs: {m: float(np.median(cols[f"metric.{obs}.{m}"][select])) for m in _METRICS} for obs in OBSERVERS}

    by_manoeuvre = {name: medians(cols["param.manoeuvre"] == i) for i, name in enumerate(g["manoeuvre"])}
    by_axis = {key: {str(v): medians(cols[f"param.{key}"] == v) for v in g[key]} for key in NUMERIC}
    summary = {
        "scenario": NAME,
        "num_configs": int(cols["index"].size),
        "finite_fraction": float(np.mean(cols["metric.finite"])),
        "median_by_manoeuvre": by_manoeuvre,
        "median_by_axis": by_axis,
        "true_beta_max_deg_by_manoeuvre": {
            name: float(np.median(cols["metric.true_beta_max_deg"][cols["param.manoeuvre"] == i]))
            for i, name in enumerate(g["manoeuvre"])
        },
    }
    return write_sweep_report(out_dir, summary, config, result, [_plot(cols, g, out_dir)], _markdown)


_AXIS_LABELS = {"manoeuvre": "manoeuvre", "friction": "road friction scale", "acc_bias": "accelerometer bias (m/s^2)",
                "drift": "drift (m/s^2/sqrt(s))", "mass": "true / nominal mass",
                "cornering_stiffness": "true / nominal cornering stiffness"}  # fmt: skip


def _plot(cols: dict, grid: dict, out_dir: Path) -> str:
    """Median sideslip RMS error of both observers along each grid axis (all other axes pooled)."""
    plt = pyplot()
    panels = [("manoeuvre", list(range(len(grid["manoeuvre"]))), grid["manoeuvre"])]
    panels += [(key, grid[key], [f"{v:g}" for v in grid[key]]) for key in NUMERIC]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.6), squeeze=False, sharey=True)
    for ax, (key, values, labels) in zip(axes[0], panels, strict=True):
        x = np.arange(len(values))
        for j, (obs, marker) in enumerate(zip(OBSERVERS, "os", strict=True)):
            metric = cols[f"metric.{obs}.beta_rms_deg"]
            med = [np.median(metric[cols[f"param.{key}"] == v]) for v in values]
            ax.plot(x + (j - 0.5) * 0.15, med, marker, ls="none", ms=7, label=obs.upper())
        ax.set_xticks(x, [label.replace("_", "\n") for label in labels], fontsize=7)
        ax.set(xlabel=_AXIS_LABELS[key], yscale="log", xlim=(-0.6, len(values) - 0.4))
        ax.grid(alpha=0.3, axis="y", which="both")
    axes[0, 0].set_ylabel("median sideslip RMS error (deg)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Grip 2010 ch. 2: NVSO and EKF sideslip errors over the sweep (other axes pooled)")
    fig.tight_layout()
    return save_figure(fig, out_dir, "sideslip")


def _markdown(summary: dict) -> str:
    lines = [
        "# Vehicle sideslip: the NVSO and the EKF of Grip 2010 ch. 2 over manoeuvres, friction, sensors and mismatch",
        "",
        f"{summary['num_configs']} configurations; all finite in a fraction {summary['finite_fraction']:.3f}.",
        "Medians over the configurations (errors in deg; friction error = final estimate minus true road friction).",
        "",
        "| grid value | observer | " + " | ".join(_METRICS) + " |",
        "| --- | --- |" + " --- |" * len(_METRICS),
    ]
    rows = [(f"manoeuvre = {k}", v) for k, v in summary["median_by_manoeuvre"].items()]
    rows += [(f"{key} = {k}", v) for key, per in summary["median_by_axis"].items() for k, v in per.items()]
    for label, per in rows:
        for obs, m in per.items():
            lines.append(f"| {label} | {obs} | " + " | ".join(f"{m[k]:.3g}" for k in _METRICS) + " |")
    peaks = summary["true_beta_max_deg_by_manoeuvre"]
    lines += ["", "Largest true sideslip (deg, median): " + ", ".join(f"{k}: {v:.2f}" for k, v in peaks.items()), ""]
    return "\n".join(lines) + "\n"


SCENARIO = SweepScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=make_sweep,
    report=report,
    size_keys=(
        "simulation.duration",
        "grid.seeds",
        "grid.manoeuvre",
        "grid.friction",
        "grid.acc_bias",
        "grid.drift",
        "grid.mass",
        "grid.cornering_stiffness",
    ),
)
