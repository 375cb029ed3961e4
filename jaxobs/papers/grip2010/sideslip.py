"""Grip 2010, ch. 2: the nonlinear vehicle sideslip observer (NVSO) against its EKF baseline (§2.9) on simulated
test drives, and the chapter's claims as checks.

The thesis's experiments used test-vehicle data that are not published, so no number of §2.10 can be reproduced;
the qualitative claims of §2.12 are checked on :data:`jaxobs.vehicle.MANOEUVRES` and five further drives, each
stage in one ``vmap`` (:func:`estimate`). The checks: docs/theory/papers.md.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs.observers.base import EstimatorInputs, run
from jaxobs.papers._output import pyplot, save_figure, write_reproduction
from jaxobs.papers.scenarios import Reproduction
from jaxobs.vehicle import (
    GRAVITY,
    MANOEUVRES,
    PLANT_STEP,
    SENSOR_RATE,
    Command,
    Manoeuvre,
    Measurements,
    NVSOOutputs,
    SensorParams,
    Trajectory,
    VehicleEKFOutputs,
    VehicleParams,
    make_nvso,
    make_vehicle_ekf,
    measure,
    nvso,
    sensor_inputs,
    simulate,
    vehicle_ekf,
)
from jaxobs.vehicle.lateral import lemma_3_1_check
from jaxobs.vehicle.road_angles import lemma_check

NAME = "grip2010-sideslip"
PERIOD = 1.0 / SENSOR_RATE  # s, the observers' and sensors' sample period (Grip 2010 §2.8)
DEG = np.pi / 180
BIAS_AY = 0.5  # m/s^2, half the 1.0 m/s^2 bias + drift maximum of Grip 2010 §2.8
BANK_DEG, INCLINATION_DEG = 3.0, 5.0
LOW_FRICTION = 0.3
# The gain-bound checks of Lemmas 4.1 and 4.2 at the design of the chapter 4 estimators' mountain-road test:
# K_vx = 5 (so a = 4 < K_vx,min), K_vy = 10 and delta_min = min(-xi) = 0.90 measured along that run.
LEMMA_4_1_A = 4.0
LEMMA_4_2_K_VY, LEMMA_4_2_DELTA_MIN = 10.0, 0.8995
SINE_AMPLITUDE_DEG = 25.0  # steering wheel; the sine_steer manoeuvre's 45 deg spins the car on friction 0.3
THETA0_STRAIGHT, VY0_ERROR = 0.5, 0.5  # straight_no_excitation: initial theta (true 1) and v_y error (m/s)
CHECK_DURATION = 30.0  # s, the straight check drives
ADAPTED_AFTER = 5.0  # s: the low-friction check's errors also from here on, after 2.5 periods of its sine
NEVER = 1e6  # a switching threshold / off delay no signal reaches: friction estimation never on / never off
EXACT = SensorParams(noise_acc=0.0, noise_yaw_rate=0.0, noise_steering=0.0, noise_wheel=0.0)
COST_REPEATS = 5


_LANE, _SINE = MANOEUVRES["double_lane_change_120kmh"], MANOEUVRES["sine_steer"]


def _straight(bank=0.0, inclination=0.0):
    def command(t):
        return Command(speed=100 / 3.6, curvature_gain=10.0, bank=bank * DEG, inclination=inclination * DEG)

    return command


def _flat(manoeuvre):
    return lambda t: manoeuvre.command(t)._replace(bank=0.0)


def _sine_low_friction(t):
    return _SINE.command(t)._replace(steering_wheel=SINE_AMPLITUDE_DEG * DEG * jnp.sin(jnp.pi * t),
                                     friction=LOW_FRICTION)  # fmt: skip


CHECK_DRIVES = {
    "lane_change_flat": Manoeuvre("lane_change_flat", _flat(_LANE), _LANE.duration, _LANE.initial_speed),
    "straight_flat": Manoeuvre("straight_flat", _straight(), CHECK_DURATION, 100 / 3.6),
    "straight_bank": Manoeuvre("straight_bank", _straight(bank=BANK_DEG), CHECK_DURATION, 100 / 3.6),
    "straight_inclination": Manoeuvre(
        "straight_inclination", _straight(inclination=INCLINATION_DEG), CHECK_DURATION, 100 / 3.6
    ),
    "sine_steer_low_friction": Manoeuvre(
        "sine_steer_low_friction", _sine_low_friction, _SINE.duration, _SINE.initial_speed
    ),
}
"""The drives of the checks (module docstring), besides :data:`jaxobs.vehicle.MANOEUVRES`."""
DRIVES = {**MANOEUVRES, **CHECK_DRIVES}


def _typed(command):
    return lambda t: Command(*(jnp.asarray(v, jnp.result_type(t)) for v in command(t)))


def _stack(trees):
    return jax.tree_util.tree_map(lambda *a: jnp.stack([jnp.asarray(x) for x in a]), *trees)


MEASUREMENTS = {
    **{name: (name, SensorParams()) for name in MANOEUVRES},
    "known_friction_flat": ("lane_change_flat", dataclasses.replace(EXACT, cutoff=float("inf"))),
    "ay_bias": ("straight_flat", dataclasses.replace(EXACT, bias_ay=BIAS_AY)),
    "bank": ("straight_bank", EXACT),
    "inclination": ("straight_inclination", EXACT),
    "friction_adaptation": ("sine_steer_low_friction", EXACT),
    "straight_no_excitation": ("straight_flat", EXACT),
}
"""Measured drives: name -> (drive, sensor errors). The manoeuvres get the default white noise and the 15 Hz
low-pass (:class:`~jaxobs.vehicle.SensorParams`), the checks exact sensors (with the bias of ``ay_bias``; without the
low-pass for ``known_friction_flat``)."""

_OFF = dict(vy_dot_threshold=NEVER, oversteer_threshold=NEVER)
NVSO_RUNS = {
    **{name: (name, {}) for name in MANOEUVRES},
    "known_friction_flat": ("known_friction_flat", {**_OFF, "K_theta_i": 0.0, "K_theta_b": 0.0}),
    "ay_bias": ("ay_bias", {}),
    "bank": ("bank", {}),
    "inclination": ("inclination", {}),
    "friction_mode1": ("friction_adaptation", _OFF),
    "friction_mode2": ("friction_adaptation", {}),
    "straight_no_excitation": ("straight_no_excitation", {"off_delay": NEVER}),
}
"""NVSO runs: name -> (measured drive, settings over :func:`~jaxobs.vehicle.make_nvso`'s defaults).
``known_friction_flat`` is the basic observer (friction estimation never on, no angle estimation);
``friction_mode1`` never estimates friction; ``straight_no_excitation`` starts in mode 2 at ``theta =
THETA0_STRAIGHT``, ``v_y = -VY0_ERROR`` (true 0) and never leaves it."""


def simulate_drives(vehicle: VehicleParams, names, dt: float = PLANT_STEP):
    """The drives ``names`` (keys of :data:`DRIVES`) simulated in one ``vmap`` up to the longest duration and kept
    at the 100 Hz sensor samples: a :class:`~jaxobs.vehicle.Trajectory` with a leading drive axis."""
    return _simulator(tuple(names), dt)(vehicle)


@functools.cache
def _simulator(names: tuple, dt: float):
    """The jitted batch simulation of the drives ``names`` (compiled once per set of drives and step)."""
    drives = [DRIVES[n] for n in names]
    horizon = max(d.duration for d in drives)
    branches = [_typed(d.command) for d in drives]
    every = round(PERIOD / dt)
    speeds = jnp.asarray([d.initial_speed for d in drives])

    def one(vehicle, i, speed):
        tr = simulate(Manoeuvre("batch", lambda t: jax.lax.switch(i, branches, t), horizon, speed), vehicle, dt=dt)
        return jax.tree_util.tree_map(lambda a: a[::every], tr)

    batch = jax.vmap(one, in_axes=(None, 0, 0))
    return jax.jit(lambda vehicle: batch(vehicle, jnp.arange(len(drives)), speeds))


@jax.jit
def _measure_all(vehicle, trajectories, drive_index, sensors, seeds):
    def one(i, s, seed):
        tr = jax.tree_util.tree_map(lambda a: a[i], trajectories)
        return measure(tr, vehicle, s, jax.random.PRNGKey(seed), dt=PERIOD)

    return jax.vmap(one)(drive_index, sensors, seeds)


@jax.jit
def _run_nvso(params, state, y):
    return jax.vmap(lambda p, s, yy: run(nvso, p, EstimatorInputs(y=yy), s))(params, state, y)


@jax.jit
def _run_ekf(params, y):
    return jax.vmap(lambda p, yy: run(vehicle_ekf, p, EstimatorInputs(y=yy)))(params, y)


class Estimates(NamedTuple):
    """Result of :func:`estimate`: the names along each leading axis and the batched results.

    Attributes:
      manoeuvres: the manoeuvres (keys of jaxobs.vehicle.MANOEUVRES), the EKF's batch
      drives: keys of DRIVES, the batch of ``trajectory``
      measurements: keys of MEASUREMENTS, the batch of ``measurements``
      runs: keys of NVSO_RUNS, the NVSO's batch
      trajectory: the simulated drives, batched over ``drives``
      measurements_data: the sensor signals, batched over ``measurements``
      nvso: the NVSO's outputs over time, batched over ``runs``
      ekf: the vehicle EKF's outputs over time, batched over ``manoeuvres``
      inputs: "nvso": (params, initial states, sensors), "ekf": (params, sensors) of the batched runs
    """

    manoeuvres: list
    drives: list
    measurements: list
    runs: list
    trajectory: Trajectory
    measurements_data: Measurements
    nvso: NVSOOutputs
    ekf: VehicleEKFOutputs
    inputs: dict


def estimate(vehicle: VehicleParams | None = None, manoeuvres=None) -> Estimates:
    """Simulate, measure and estimate the ``manoeuvres`` (names; default all of :data:`jaxobs.vehicle.MANOEUVRES`)
    and the checks' drives: one ``vmap`` per stage, all at the 100 Hz samples up to the longest drive."""
    vehicle = VehicleParams() if vehicle is None else vehicle
    requested = list(MANOEUVRES) if manoeuvres is None else list(manoeuvres)
    if not requested or set(requested) - set(MANOEUVRES):
        raise ValueError(f"manoeuvres must be a non-empty subset of {sorted(MANOEUVRES)}, got {requested!r}")
    manoeuvres = [k for k in MANOEUVRES if k in requested]  # the order of MANOEUVRES, the first rows below
    keep = lambda table: [k for k in table if k not in MANOEUVRES or k in manoeuvres]
    drives, names, runs = keep(DRIVES), keep(MEASUREMENTS), keep(NVSO_RUNS)
    tr = simulate_drives(vehicle, drives)
    drive_index = jnp.asarray([drives.index(MEASUREMENTS[n][0]) for n in names])
    sensors = _stack([MEASUREMENTS[n][1] for n in names])
    seeds = jnp.asarray([list(MEASUREMENTS).index(n) for n in names])
    meas = _measure_all(vehicle, tr, drive_index, sensors, seeds)
    y = jax.vmap(lambda m: sensor_inputs(m).y)(meas)
    rows = [names.index(NVSO_RUNS[r][0]) for r in runs]
    vx0 = np.asarray(meas.vx_ref[:, 0])
    params = _stack([make_nvso(vehicle, vx0=float(vx0[i]), **NVSO_RUNS[r][1]) for i, r in zip(rows, runs, strict=True)])
    state = jax.vmap(nvso.init)(params)
    j = runs.index("straight_no_excitation")  # mode 2 from the start, theta = THETA0_STRAIGHT
    state = state._replace(mode=state.mode.at[j].set(1.0), off_timer=state.off_timer.at[j].set(0.0),
                           x=state.x.at[j, 2].set(THETA0_STRAIGHT).at[j, 1].set(-VY0_ERROR))  # fmt: skip
    _, nv = _run_nvso(params, state, y[jnp.asarray(rows)])
    m = len(manoeuvres)
    ekf_params = _stack([make_vehicle_ekf(vehicle)] * m)  # its v_x starts from the first v_x,ref
    _, ekf = _run_ekf(ekf_params, y[:m])
    inputs = {"nvso": (params, state, y[jnp.asarray(rows)]), "ekf": (ekf_params, y[:m])}
    return Estimates(manoeuvres, drives, names, runs, tr, meas, nv, ekf, inputs)


def _errors(beta_hat, beta, n):
    e = np.rad2deg(np.asarray(beta_hat[:n]) - np.asarray(beta[:n]))
    return {"max_abs_beta_error_deg": float(np.abs(e).max()), "rms_beta_error_deg": float(np.sqrt(np.mean(e**2)))}


def _angle_deg(s):
    return float(np.rad2deg(np.arcsin(np.clip(float(s), -1.0, 1.0))))


def _samples(duration):
    return int(round(duration / PERIOD)) + 1


def manoeuvre_table(est: Estimates) -> dict:
    """Per manoeuvre: peaks of the drive and, for the NVSO and the EKF, the sideslip errors over the drive and the
    final friction, bank and inclination estimates (with the road's final bank and inclination)."""
    drives, runs, tr, nv, ekf = est.drives, est.runs, est.trajectory, est.nvso, est.ekf
    out = {}
    for k, name in enumerate(est.manoeuvres):
        m = MANOEUVRES[name]
        d, n = drives.index(name), _samples(m.duration)
        beta = tr.beta[d]
        nx, ex = np.asarray(nv.x[runs.index(name), n - 1]), np.asarray(ekf.x[k, n - 1])
        out[name] = {
            "duration_s": m.duration,
            "peak_ay_g": float(np.abs(np.asarray(tr.ay[d, :n])).max() / GRAVITY),
            "peak_beta_deg": float(np.rad2deg(np.abs(np.asarray(beta[:n])).max())),
            "road_friction": float(tr.inputs.friction[d, n - 1]),
            "bank_true_deg": float(np.rad2deg(tr.inputs.bank[d, n - 1])),
            "inclination_true_deg": float(np.rad2deg(tr.inputs.inclination[d, n - 1])),
            "nvso": {
                **_errors(nv.beta[runs.index(name)], beta, n),
                "theta_hat_final": float(nx[2]),
                "bank_estimate_deg": _angle_deg(nx[4]),
                "inclination_estimate_deg": _angle_deg(nx[3]),
                "friction_estimation_on_fraction": float(np.asarray(nv.mode[runs.index(name), :n]).mean()),
            },
            "ekf": {
                **_errors(ekf.beta[k], beta, n),
                "theta_hat_final": float(ex[4]),
                "bank_estimate_deg": _angle_deg(ex[3]),
                "inclination_estimate_deg": _angle_deg(ex[2]),
                "fast_friction_estimation_fraction": float(np.asarray(ekf.mode[k, :n]).mean()),
            },
        }
    return out


def checks(vehicle: VehicleParams, est: Estimates) -> dict:
    """The chapter's claims (module docstring) from the NVSO runs of :data:`NVSO_RUNS`."""
    drives, runs, tr, nv = est.drives, est.runs, est.trajectory, est.nvso

    def run_of(name):
        r = runs.index(name)
        drive = MEASUREMENTS[NVSO_RUNS[name][0]][0]
        return r, drives.index(drive), _samples(DRIVES[drive].duration)

    r, d, n = run_of("known_friction_flat")
    known = _errors(nv.beta[r], tr.beta[d], n)
    roll = 1.0 + vehicle.roll_gradient * GRAVITY
    r, d, n = run_of("ay_bias")
    ay_bias = {"bias": BIAS_AY, "theta_b_final": float(nv.x[r, n - 1, 4]), "expected": BIAS_AY / (GRAVITY * roll),
               "b_over_g": BIAS_AY / GRAVITY, "roll_factor": roll}  # fmt: skip
    r, d, n = run_of("bank")
    bank = {"bank_deg": BANK_DEG, "theta_b_final": float(nv.x[r, n - 1, 4]), "expected": float(np.sin(BANK_DEG * DEG))}
    r, d, n = run_of("inclination")
    incl = {"incl_deg": INCLINATION_DEG, "theta_i_final": float(nv.x[r, n - 1, 3]),
            "expected": float(np.sin(INCLINATION_DEG * DEG))}  # fmt: skip
    r1, d, n = run_of("friction_mode1")
    r2, _, _ = run_of("friction_mode2")
    friction = {
        "theta_true": LOW_FRICTION,
        "theta_hat_final": float(nv.x[r2, n - 1, 2]),
        "theta_hat_final_mode1": float(nv.x[r1, n - 1, 2]),
        "peak_beta_deg": float(np.rad2deg(np.abs(np.asarray(tr.beta[d, :n])).max())),
        "peak_ay_g": float(np.abs(np.asarray(tr.ay[d, :n])).max() / GRAVITY),
        "friction_estimation_on_fraction": float(np.asarray(nv.mode[r2, :n]).mean()),
        "max_abs_beta_error_deg": {
            "mode1": _errors(nv.beta[r1], tr.beta[d], n)["max_abs_beta_error_deg"],
            "mode2": _errors(nv.beta[r2], tr.beta[d], n)["max_abs_beta_error_deg"],
        },
        "max_abs_beta_error_after_first_cycles_deg": {  # once the sine has excited the estimate
            mode: float(np.rad2deg(np.abs(np.asarray(nv.beta[r, first:n] - tr.beta[d, first:n])).max()))
            for mode, r, first in (("mode1", r1, _samples(ADAPTED_AFTER)), ("mode2", r2, _samples(ADAPTED_AFTER)))
        },
    }
    r, d, n = run_of("straight_no_excitation")
    straight = {
        "theta_true": 1.0,
        "theta_hat_initial": THETA0_STRAIGHT,
        "theta_hat_change": float(nv.x[r, n - 1, 2] - THETA0_STRAIGHT),
        "vy_error_final": float(tr.state.vy[d, n - 1] - nv.x[r, n - 1, 1]),
        "vy_error_initial": float(tr.state.vy[d, 0] - nv.x[r, 0, 1]),
        "mode_on_fraction": float(np.asarray(nv.mode[r, :n]).mean()),
    }
    lemma_4_1 = lemma_check("4.1", a=LEMMA_4_1_A)
    lemma_4_2 = lemma_check("4.2", K_vy=LEMMA_4_2_K_VY, delta_min=LEMMA_4_2_DELTA_MIN)
    return {"known_friction_flat": known, "ay_bias": ay_bias, "bank": bank, "inclination": incl,
            "friction_adaptation": friction, "straight_no_excitation": straight,
            "lemma_4_1": {"a": LEMMA_4_1_A, **lemma_4_1._asdict()},
            "lemma_4_2": {"K_vy": LEMMA_4_2_K_VY, "delta_min": LEMMA_4_2_DELTA_MIN, **lemma_4_2._asdict()},
            "lemma_3_1": {"max_relative_V_increase": float(lemma_3_1_check().max_relative_V_increase)}}  # fmt: skip


def cost(est: Estimates, repeats: int = COST_REPEATS) -> dict:
    """Microseconds per step and drive of the NVSO and the EKF: the batched runs of :func:`estimate` (already
    compiled) timed again, ``repeats`` interleaved rounds; the medians and the median of the per-round ratios."""
    fns = {"nvso": lambda: _run_nvso(*est.inputs["nvso"]), "ekf": lambda: _run_ekf(*est.inputs["ekf"])}
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, f in fns.items():
            y = est.inputs[k][-1]
            t0 = time.perf_counter()
            jax.block_until_ready(f())
            times[k].append((time.perf_counter() - t0) / (y.shape[0] * y.shape[1]) * 1e6)
    nv, ek = np.asarray(times["nvso"]), np.asarray(times["ekf"])
    return {"nvso_step_us": float(np.median(nv)), "ekf_step_us": float(np.median(ek)),
            "ratio": float(np.median(nv / ek)), "repeats": repeats,
            "timed": "one step of one drive within the vmapped batches of the reproduction (CPU, float64)"}  # fmt: skip


def assumed(vehicle: VehicleParams) -> dict:
    """Every value this reproduction assumes (the thesis gives none of them, §2.7-§2.8)."""
    return {
        "vehicle": dataclasses.asdict(vehicle),
        "nvso": {k: v for k, v in make_nvso(vehicle)._asdict().items() if k not in ("vehicle", "vx0")},
        "nvso_vx0": "the first v_x,ref sample of each drive (the EKF starts from it by itself)",
        "ekf": {**{k: p.default for k, p in inspect.signature(make_vehicle_ekf).parameters.items()
                    if k not in ("vehicle", "vx0", "switching")},
                "update": "Joseph (bierman = False)",
                "switching": "the NVSO's (same thresholds)"},  # fmt: skip
        "sensors": {
            "manoeuvres": dataclasses.asdict(SensorParams()),
            "checks": dataclasses.asdict(EXACT),
            "known_friction_flat_cutoff": "none (no low-pass)",
            "ay_bias": BIAS_AY,
            "seeds": "the index of the measured drive in MEASUREMENTS",
        },
        "plant": {"integrator": "RK4", "step_s": PLANT_STEP, "sensor_rate_hz": SENSOR_RATE},
        "observers": "forward Euler at the 10 ms sensor period (Grip 2010 §2.8)",
        "manoeuvres": "jaxobs.vehicle.MANOEUVRES (amplitudes chosen for the default vehicle)",
        "checks": {
            "known_friction_flat": "double_lane_change_120kmh with bank 0; friction estimation never on "
                                   f"(vy_dot_threshold = oversteer_threshold = {NEVER:g}); K_theta_i = K_theta_b = 0",
            "straight_drives": f"100 km/h, curvature tracking (gain 10), {CHECK_DURATION:g} s",
            "bank_deg": BANK_DEG, "inclination_deg": INCLINATION_DEG,
            "friction_adaptation": f"80 km/h, steering-wheel sine {SINE_AMPLITUDE_DEG:g} deg at 0.5 Hz, 10 s, "
                                   f"friction {LOW_FRICTION}; mode1: friction estimation never on; mode2: the "
                                   "switching logic of Grip 2010 §2.5",
            "straight_no_excitation": f"flat straight, mode 2 held (off_delay = {NEVER:g}), theta(0) = "
                                      f"{THETA0_STRAIGHT}, v_y error(0) = {VY0_ERROR} m/s",
        },  # fmt: skip
        "not_modelled": "the NVSO's caster correction (jaxobs.vehicle.nvso); the drives run without an ESC",
    }  # fmt: skip


MISPRINTS = {
    "(2.13)": "printed without the dot on v_x; read as the derivative, as in (2.18)",
    "(2.20) vs ch. 4": "K_e and K_c are the same gain (the attraction of theta to theta*)",
    "sideslip sign": "beta = arctan(v_y / v_x) as in ch. 2 and 4 (ch. 3 uses the opposite sign)",
}
"""The errata of the thesis that matter for ch. 2 (Grip 2010)."""


def reproduce(out_dir: Path, *, manoeuvres=None, cost_repeats: int = COST_REPEATS) -> dict:
    """Simulate, measure and estimate the ``manoeuvres`` (default all) and the checks' drives; write
    ``grip2010-sideslip.json`` and the figure."""
    out_dir = Path(out_dir)
    vehicle = VehicleParams()
    est = estimate(vehicle, manoeuvres)
    summary = {
        "manoeuvres": manoeuvre_table(est),
        "checks": checks(vehicle, est),
        "cost": cost(est, cost_repeats),
        "thesis": {
            "cost_ratio": "NVSO execution time about one third of the EKF's (Grip 2010 §2.9)",
            "numbers": "the §2.10 numbers come from test-vehicle data and are not comparable",
        },
        "assumed": assumed(vehicle),
        "misprints": MISPRINTS,
    }
    return write_reproduction(out_dir, NAME, summary, [_figure(out_dir, est)])


def _figure(out_dir: Path, est: Estimates) -> str:
    plt = pyplot()
    drives, runs, tr, nv = est.drives, est.runs, est.trajectory, est.nvso
    panels = [
        (n, MANOEUVRES[n].duration, [("NVSO", nv.beta[runs.index(n)], "C3"), ("EKF", est.ekf.beta[k], "C2")])
        for k, n in enumerate(est.manoeuvres)
    ]
    panels.append(("sine_steer_low_friction (friction 0.3)", DRIVES["sine_steer_low_friction"].duration,
                   [("NVSO, mode 1 only", nv.beta[runs.index("friction_mode1")], "C1"),
                    ("NVSO, switching", nv.beta[runs.index("friction_mode2")], "C3")]))  # fmt: skip
    rows = (len(panels) + 1) // 2
    fig, axes = plt.subplots(rows, 2, figsize=(11, 2.75 * rows + 0.8), squeeze=False, layout="constrained")
    for ax in axes.ravel()[len(panels) :]:
        ax.set_axis_off()
    for ax, (name, duration, estimates) in zip(axes.ravel(), panels, strict=False):
        drive = name.split(" ")[0]
        n = _samples(duration)
        t = np.asarray(tr.time[drives.index(drive), :n])
        ax.plot(t, np.rad2deg(np.asarray(tr.beta[drives.index(drive), :n])), "C0", lw=1.5, label="true")
        for label, beta, colour in estimates:
            ax.plot(t, np.rad2deg(np.asarray(beta[:n])), colour, lw=0.9, label=label)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("t [s]")
        ax.set_ylabel("sideslip beta [deg]")
    legend = {}  # one legend for every panel, below them: a panel's own would cover its traces
    for ax in axes.ravel()[: len(panels)]:
        legend.update({label: handle for handle, label in zip(*ax.get_legend_handles_labels(), strict=True)})
    fig.legend(legend.values(), legend.keys(), loc="outside lower center", ncol=len(legend), fontsize=8)
    fig.suptitle("Grip 2010 ch. 2: true sideslip, NVSO and EKF on simulated drives", fontsize=11)
    return save_figure(fig, out_dir, "grip2010_sideslip")


__all__ = [
    "NAME",
    "REPRODUCTION",
    "Estimates",
    "DRIVES",
    "CHECK_DRIVES",
    "MEASUREMENTS",
    "NVSO_RUNS",
    "MISPRINTS",
    "simulate_drives",
    "estimate",
    "manoeuvre_table",
    "checks",
    "cost",
    "assumed",
    "reproduce",
]

REPRODUCTION = Reproduction(name=NAME, summary=__doc__, reproduce=reproduce)
