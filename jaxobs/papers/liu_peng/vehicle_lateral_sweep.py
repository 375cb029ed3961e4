"""Monte-Carlo comparison of the four Liu & Peng §4.2 estimators over random vehicle mismatch and noise seeds.

The estimators are designed once on the nominal parameter model
(:func:`jaxobs.papers.liu_peng.vehicle_lateral.design_estimators`); each configuration draws a true vehicle (mass,
yaw inertia, cornering stiffnesses, steering offset) and a noise seed, simulates the §4.2 scenario and scores the
RMS errors of ``v_y`` and ``d`` of each method. ``jaxobs sweep --config tuning/liu_peng_sweep.toml``. Details:
docs/theory/papers.md.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, check_range
from jaxobs.lti import c2d, ss
from jaxobs.papers._output import pyplot, save_figure, write_sweep_report
from jaxobs.papers.liu_peng import vehicle_lateral as lp
from jaxobs.papers.scenarios import Sweep, SweepScenario
from jaxobs.sweep import load_results

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "SCENARIO", "make_sweep", "report"]

NAME = "liu-peng"
SCALES = ("mass_scale", "inertia_scale", "front_stiffness_scale", "rear_stiffness_scale")
ERRORS = ("v_y", "d")
UNITS = {"v_y": "m/s", "d": "m/s^2"}

DEFAULT_CONFIG = {
    "scenario": NAME,
    "seed": 0,
    "chunk_size": 100,
    "vehicle": {
        "mass_scale": [0.8, 1.2],
        "inertia_scale": [0.8, 1.2],
        "front_stiffness_scale": [0.7, 1.1],
        "rear_stiffness_scale": [0.7, 1.1],
        "steer_offset_deg": [-0.02, 0.02],
        "count": 500,
    },
    "noise": {
        "std": lp.NOISE_STD,
        "sine": lp.NOISE_SINE,
    },
    "estimators": {
        "lowpass": True,
    },
}
"""500 vehicles: m, I_z +-20 %, C_f, C_r -30..+10 %, steering offset +-0.02 deg, the §4.2 robustness noise."""

CONFIG_NOTES = {
    "seed": "base of every configuration's random key",
    "chunk_size": "configurations per device and step, and rows per Parquet chunk file",
    "vehicle": "the true vehicles, every factor drawn independently and uniformly per configuration",
    "vehicle.mass_scale": "true mass m / nominal",
    "vehicle.inertia_scale": "true yaw inertia I_z / nominal",
    "vehicle.front_stiffness_scale": "true front cornering stiffness C_f / nominal",
    "vehicle.rear_stiffness_scale": "true rear cornering stiffness C_r / nominal",
    "vehicle.steer_offset_deg": "true road-wheel angle minus the measured 0.33 deg (deg)",
    "vehicle.count": "number of vehicles (configurations); a larger value extends a sweep in the same directory",
    "noise": "the measured yaw rate's noise, a fresh seed per configuration",
    "noise.std": "standard deviation of the white yaw-rate noise (rad/s)",
    "noise.sine": "amplitude of the 1 Hz sine on the yaw rate (rad/s)",
    "estimators": "the four estimators, designed once on the nominal vehicle",
    "estimators.lowpass": "the fifth-order 3 Hz low-pass on y before the inverse-dynamics observer (§4.2 robustness)",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    for name in SCALES:
        check_range(config, source, f"vehicle.{name}", positive=True, allow_point=True)
    check_range(config, source, "vehicle.steer_offset_deg", allow_point=True)
    for key, low in (("seed", 0), ("chunk_size", 1), ("vehicle.count", 1), ("noise.std", 0), ("noise.sine", 0)):
        check_at_least(config, source, key, low)


def _sampler(config: dict):
    v = config["vehicle"]
    names = (*SCALES, "steer_offset_deg")
    low = jnp.asarray([v[n][0] for n in names], float)
    high = jnp.asarray([v[n][1] for n in names], float)

    def sampler(key, index):
        k_draw, k_noise = jax.random.split(key)
        draws = jax.random.uniform(k_draw, (len(names),), minval=low, maxval=high)
        noise_seed = jax.random.randint(k_noise, (), 0, jnp.iinfo(jnp.int32).max, dtype=jnp.int32)
        return {**{n: draws[i] for i, n in enumerate(names)}, "noise_seed": noise_seed}

    return sampler


def true_plant(p: dict):
    """``(A, B)`` of eq. 31 (``B = [B_u, B_d]``) for the drawn scales (traceable; the parameter model)."""
    v = lp.NOMINAL
    cf, cr = 2 * v.Cf * p["front_stiffness_scale"], 2 * v.Cr * p["rear_stiffness_scale"]
    m, iz = v.m * p["mass_scale"], v.Iz * p["inertia_scale"]
    A = jnp.stack(
        [
            jnp.stack([-(cf + cr) / (m * v.vx), -v.vx + (-v.a * cf + v.b * cr) / (m * v.vx)]),
            jnp.stack([(-v.a * cf + v.b * cr) / (iz * v.vx), -(v.a**2 * cf + v.b**2 * cr) / (iz * v.vx)]),
        ]
    )
    Bu = jnp.stack([cf / m, v.a * cf / iz])
    return A, jnp.stack([Bu, jnp.asarray([1.0, 0.0], Bu.dtype)], axis=1)


def simulate(p: dict, noise_std: float, noise_sine: float):
    """True ``v_y``, ``d`` and the measured yaw rate at the 100 Hz samples (traceable)."""
    n = int(round(lp.DURATION / lp.H))
    hf = lp.H / lp.FINE
    t = np.arange(n) * lp.H
    d_fine = lp.disturbance(np.arange(n * lp.FINE) * hf).reshape(n, lp.FINE)
    A, B = true_plant(p)
    sysd = c2d(ss(A, B, jnp.asarray([[0.0, 1.0]])), hf)
    steer = lp.STEER + jnp.deg2rad(p["steer_offset_deg"])
    x0 = -jnp.linalg.solve(A, B[:, 0] * steer)  # the true vehicle's steady turn

    def fine_step(x, d):
        return sysd.A @ x + sysd.B[:, 0] * steer + sysd.B[:, 1] * d, None

    def sample_step(x, d_interval):
        return jax.lax.scan(fine_step, x, d_interval)[0], x

    xs = jax.lax.scan(sample_step, x0, jnp.asarray(d_fine))[1]
    noise = jax.random.normal(jax.random.key(p["noise_seed"]), (n,), xs.dtype)
    y = xs[:, 1] + noise_std * noise + noise_sine * jnp.sin(2 * np.pi * t)
    return xs[:, 0], d_fine[:, 0], y


def make_sweep(config: dict):
    """``(sampler, evaluate, num_configs)`` for :func:`jaxobs.sweep.run_sweep`."""
    n = int(round(lp.DURATION / lp.H))
    after = jnp.asarray(np.arange(n) * lp.H >= lp.RMS_START)
    est = lp.design_estimators("parameters", config["estimators"]["lowpass"], n)
    u = jnp.full((n,), lp.STEER)
    std, sine = float(config["noise"]["std"]), float(config["noise"]["sine"])

    def rms(e):
        value = jnp.sqrt(jnp.sum(jnp.where(after, e, 0.0) ** 2) / jnp.sum(after))
        return jnp.where(jnp.isfinite(value), value, jnp.inf)

    def evaluate(p):
        v_y, d, y = simulate(p, std, sine)
        out = lp.run_estimators(est, y, u)
        return {
            f"{err}_rms": {m: rms(out[m][i] - (v_y if err == "v_y" else d)) for m in lp.METHODS}
            for i, err in enumerate(ERRORS)
        }

    return Sweep(_sampler(config), evaluate, config["vehicle"]["count"])


QUANTILES = (("p10", 0.1), ("median", 0.5), ("p90", 0.9), ("max", 1.0))


def report(config: dict, out_dir: Path, result=None, context=None) -> dict:
    """Summarise the sweep's results in ``out_dir`` (``summary.json``, ``report.md``); returns the summary."""
    cols = load_results(out_dir)
    errors = {e: np.stack([cols[f"metric.{e}_rms.{m}"] for m in lp.METHODS], axis=1) for e in ERRORS}
    finite = np.all(np.isfinite(np.concatenate(list(errors.values()), axis=1)), axis=1)
    summary = {
        "scenario": NAME,
        "num_configs": int(finite.size),
        # every method's errors finite (bounded error dynamics on this vehicle); the key `jaxobs sweep` prints
        "finite_fraction": float(finite.mean()),
        "units": UNITS,
    }
    for e, table in errors.items():
        per_method = {}
        best = np.argmin(np.where(np.isfinite(table), table, np.inf), axis=1)
        for j, m in enumerate(lp.METHODS):
            x = table[:, j]
            finite = x[np.isfinite(x)]
            per_method[m] = {
                **({q: float(np.quantile(finite, p)) for q, p in QUANTILES} if finite.size else {}),
                "non_finite": int(x.size - finite.size),
                "best_fraction": float(np.mean(best == j)),
            }
        summary[f"{e}_rms"] = per_method
    return write_sweep_report(out_dir, summary, config, result, [_plot(errors, out_dir)], _markdown)


def _plot(errors: dict, out_dir: Path) -> str:
    """Box plots (left) and empirical CDFs (right) of the v_y and d RMS errors of each method."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    labels = [lp.LABELS[m] for m in lp.METHODS]
    for row, e in enumerate(ERRORS):
        cols = [c[np.isfinite(c)] for c in errors[e].T]
        axes[row, 0].boxplot(cols, whis=(5, 95), showfliers=True, flierprops=dict(markersize=2))
        axes[row, 0].set_xticks(range(1, len(labels) + 1), labels, fontsize=8)
        axes[row, 0].set(yscale="log", ylabel=f"RMS {e} error ({UNITS[e]})", title=f"{e}: whiskers 5-95 %")
        for j, c in enumerate(cols):
            axes[row, 1].step(np.sort(c), np.arange(1, c.size + 1) / max(c.size, 1), where="post", label=labels[j])
        axes[row, 1].set(xscale="log", xlabel=f"RMS {e} error ({UNITS[e]})", ylabel="fraction of vehicles",
                         title=f"{e}: empirical CDF")  # fmt: skip
        axes[row, 1].legend(fontsize=8)
        axes[row, 1].xaxis.set_minor_formatter(plt.NullFormatter())  # the log axis' minor labels overlap
        for ax in axes[row]:
            ax.grid(alpha=0.3, which="both")
    fig.suptitle(f"Liu & Peng §4.2 estimators over {errors['v_y'].shape[0]} mismatched vehicles and noise seeds")
    return save_figure(fig, out_dir, "estimators")


def _markdown(summary: dict) -> str:
    c = summary["config"]
    v = c["vehicle"]
    lines = [
        "# Liu & Peng §4.2: the four estimators over vehicle mismatch and noise",
        "",
        f"{summary['num_configs']} vehicles: m x {v['mass_scale']}, I_z x {v['inertia_scale']}, "
        f"C_f x {v['front_stiffness_scale']}, C_r x {v['rear_stiffness_scale']}, steering offset "
        f"{v['steer_offset_deg']} deg (uniform); yaw-rate noise {c['noise']['std']} rad/s white + "
        f"{c['noise']['sine']} rad/s at 1 Hz; inverse-dynamics low-pass "
        f"{'on' if c['estimators']['lowpass'] else 'off'}. "
        "RMS errors over t >= 0.5 s; estimators designed on the nominal model.",
        "",
        f"Every method's errors finite in a fraction {summary['finite_fraction']:.3f} of the vehicles.",
        "",
    ]
    for e in ERRORS:
        lines += [
            f"## RMS {e} error ({UNITS[e]})",
            "",
            "| method | 10 % | median | 90 % | max | best in | not finite |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for m, q in summary[f"{e}_rms"].items():
            vals = " | ".join(f"{q[k]:.3g}" if k in q else "-" for k, _ in QUANTILES)
            lines.append(f"| {lp.LABELS[m]} | {vals} | {100 * q['best_fraction']:.1f} % | {q['non_finite']} |")
        lines.append("")
    return "\n".join(lines) + "\n"


SCENARIO = SweepScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=make_sweep,
    report=report,
    size_key="vehicle.count",
    size_keys=("vehicle.count",),
)
