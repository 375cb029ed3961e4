"""The NVSO's friction adaptation on low friction (issue 30): why the thesis's friction scale ends far from the road's
friction, and what the NVSO's default, the adapted ``mu_H``, reaches on four road frictions.

The check drive is ``sine_steer_low_friction`` of :mod:`jaxobs.papers.grip2010.sideslip` (80 km/h, steering-wheel
sine of 25 deg at 0.5 Hz, 10 s, road friction 0.3, exact sensors with the 15 Hz low-pass). Four questions, each
answered with numbers and a panel of the figure:

(a) Excitation and gating, for the thesis's scale (``peak_friction = 0``): the update law (Grip 2010 (2.25)) is
    ``theta' = K_theta phi e`` with the regressor ``phi = Lambda a_y*`` and ``e = a_y - theta a_y*``; it acts only
    in mode 2 (the switching of §2.5). Reported: ``phi`` along the drive, the fraction of time in mode 2, and the
    adaptation rate ``K_theta phi a_y*`` (1/s, the rate at which a theta error decays while the model is exact)
    averaged over mode 2.
(b) Model mismatch. The simulator's tyres on friction 0.3 keep their cornering stiffness and saturate at 0.3 F_z
    (a Magic Formula with ``B = c / (C mu)``); the scaled model is ``theta`` times the friction-1 tyre. At the
    simulator's own slips, loads and wheel slips, the per-axle ratio ``F_y,sim / F_y*`` is the theta the scaled
    model needs to reproduce the simulator's force; it is 0.3 only if the model can represent the tyre.
(c) Identifiability. The scaled NVSO rerun with an observer tyre equal to the simulator's at friction 0.3,
    normalised to ``mu_H* = 1`` (cornering and slip stiffness divided by 0.3, so ``0.3 a_y*`` is exactly the
    simulator's ``a_y``): the estimate must then converge to 0.3 if the update law is right; with the switching of
    §2.5 and with friction estimation held on, with and without the tyre-relaxation filter (Grip 2010 §2.8); and
    the NVSO's default, ``theta`` as the model's ``mu_H`` (``peak_friction = 1``).
(d) Per road friction (FRICTION_LEVELS), a sine at TARGET_USE of the friction for SUSTAINED s: the final estimate,
    its settling times, and the sideslip errors without adaptation and with either parameterisation.
(e) The ESC-active condition (iii) of §2.5, on drives where a simulated ESC (:class:`jaxobs.vehicle.ESCParams`)
    intervenes on low friction (ESC_DRIVES): the NVSO without adaptation, with conditions (i) and (ii) only (the
    ESC status hidden from it) and with (i)-(iii); the time the ESC intervenes, the time in mode 2, the final
    estimate and the sideslip errors.

    python benchmarks/sideslip_friction.py [--out out/bench]

Writes ``OUT/sideslip_friction.json`` and ``OUT/sideslip_friction.png`` and prints the numbers.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxobs.observers.base import EstimatorInputs, run  # noqa: E402
from jaxobs.papers.grip2010.sideslip import DEG, DRIVES, EXACT, LOW_FRICTION, NEVER, PERIOD, SINE_AMPLITUDE_DEG  # noqa: E402
from jaxobs.vehicle import (  # noqa: E402
    ESCParams,
    Manoeuvre,
    VehicleParams,
    make_nvso,
    manoeuvre,
    measure,
    nvso,
    sensor_inputs,
    simulate,
)
from jaxobs.vehicle.model import GRAVITY  # noqa: E402
from jaxobs.vehicle.sensors import ESC_ACTIVE  # noqa: E402
from jaxobs.vehicle.tyres import TyreParams, tyre_forces  # noqa: E402

DRIVE = "sine_steer_low_friction"
ALWAYS_ON = dict(vy_dot_threshold=1e-9, yaw_rate_threshold=1e-9, oversteer_threshold=1e-9, off_delay=1e6)
"""Switching settings that keep friction estimation on from the start (with the initial mode set to 2)."""
SUSTAINED = 30.0  # s, the drive continued (the same sine) for the convergence runs of (c)
SHORT_RELAXATION = 0.02  # m: the relaxation length of the simulator without (appreciable) tyre relaxation
EXCITED_AY = 0.5  # |a_y| / (friction g) above which a sample counts as excited in the per-axle statistics
FRICTION_LEVELS = (0.3, 0.5, 0.8, 1.0)  # road frictions of the per-level table
TARGET_USE = 0.9  # peak |a_y| / (friction g) of each level's sine
ESC_SINE_OVERDRIVE = 1.5  # times the check drive's steering amplitude: beyond the limit (spins without an ESC)
ESC_DRIVES = ("sine_beyond_limit_0.3", "circle_40m_ramp_0.3", "ice_lake_circles")
"""The drives of (e): the check sine at ESC_SINE_OVERDRIVE its amplitude, the 40 m circle with its speed ramp on
friction 0.3 and the ice lake (friction 0.25)."""
MODE1 = {"vy_dot_threshold": NEVER, "oversteer_threshold": NEVER}  # with the ESC status hidden: no adaptation


def matched_vehicle(vehicle: VehicleParams, friction: float) -> VehicleParams:
    """``vehicle`` whose friction-1 tyres are the simulator's tyres on ``friction``, normalised to ``mu_H* = 1``:
    ``friction`` times this tyre's forces equal the simulator's at every slip (Magic Formula: ``B = c / (C mu)``
    and ``D = mu F_z``, so dividing the stiffnesses by ``friction`` at ``mu = 1`` gives the same ``B``)."""

    def scaled(t: TyreParams) -> TyreParams:
        return dataclasses.replace(t, cornering_stiffness=t.cornering_stiffness / friction,
                                   slip_stiffness=t.slip_stiffness / friction)  # fmt: skip

    return dataclasses.replace(vehicle, tyre_front=scaled(vehicle.tyre_front), tyre_rear=scaled(vehicle.tyre_rear))


def _run(observer_vehicle, y, vx0, always_on, **nvso_settings):
    settings = {"vx0": vx0, **(ALWAYS_ON if always_on else {}), **nvso_settings}
    params = make_nvso(observer_vehicle, **settings)
    state = nvso.init(params)
    if always_on:
        state = state._replace(mode=jnp.ones_like(state.mode), off_timer=jnp.zeros_like(state.off_timer))
    _, out = jax.jit(lambda p, s, yy: run(nvso, p, EstimatorInputs(y=yy), s))(params, state, y)
    return params, out


def _axle_forces(vehicle, tr):
    """Per axle, at the simulator's states: its lateral force and the observer's friction-1 model force at the same
    (relaxed) slips, wheel slips and loads."""
    from jaxobs.vehicle.model import Inputs, forces

    def one(x, u):
        f = forces(vehicle, x, u)
        front = tyre_forces(vehicle.tyre_front, f.kappa[:2], x.tan_alpha[:2], f.fz[:2])[1]
        rear = tyre_forces(vehicle.tyre_rear, f.kappa[2:], x.tan_alpha[2:], f.fz[2:])[1]
        sim = jnp.stack([f.fy_wheel[:2].sum(), f.fy_wheel[2:].sum()])
        model = jnp.stack([front.sum(), rear.sum()])
        alpha = jnp.rad2deg(jnp.arctan(jnp.stack([x.tan_alpha[:2].mean(), x.tan_alpha[2:].mean()])))
        return sim, model, alpha

    u = Inputs(tr.inputs.steering_wheel, tr.inputs.torque, tr.inputs.bank, tr.inputs.inclination, tr.inputs.friction)
    return jax.vmap(one)(tr.state, u)


def settling_time(t, theta, target, tol):
    """First time after which ``theta`` stays within ``tol`` (relative) of ``target``; ``nan`` if never."""
    inside = np.abs(theta - target) <= tol * abs(target)
    outside = np.nonzero(~inside)[0]
    if len(outside) == 0:
        return float(t[0])
    return float(t[outside[-1] + 1]) if outside[-1] + 1 < len(t) else float("nan")


def _drive(vehicle, duration=None, drive=None, esc=None):
    """The check drive, or ``drive`` (optionally lengthened: the same sine continued; with the ``esc``) at the 100 Hz
    samples and its sensors."""
    drive = DRIVES[DRIVE] if drive is None else drive
    duration = drive.duration if duration is None else duration
    tr_fine = simulate(Manoeuvre(drive.name, drive.command, duration, drive.initial_speed), vehicle, esc=esc)
    every = round(PERIOD / float(tr_fine.time[1] - tr_fine.time[0]))
    tr = jax.tree_util.tree_map(lambda a: a[::every], tr_fine)
    meas = measure(tr, vehicle, EXACT, jax.random.PRNGKey(0), dt=PERIOD)
    return tr, sensor_inputs(meas).y, float(meas.vx_ref[0])


def _sustained(vehicle, friction):
    """Friction estimation held on over the drive continued to SUSTAINED s: the default model, the matched one
    (with the NVSO's tyre-relaxation filter of Grip 2010 §2.8 at the simulator's relaxation length), the matched one
    without that filter, and the matched one on a simulator whose tyre relaxation is nearly instantaneous (0.02 m
    instead of 0.5 m; the filter then at 0.02 m too)."""
    no_relaxation = dataclasses.replace(vehicle, relaxation_length=SHORT_RELAXATION)
    result, series, drives = {}, {}, {}
    scaled = {"peak_friction": 0.0}
    for name, sim_vehicle, matched, settings in (
        ("scaled_model", vehicle, False, scaled),
        ("matched_model", vehicle, True, scaled),
        ("matched_model_without_relaxation_filter", vehicle, True, {**scaled, "relaxation_length": 0.0}),
        ("matched_model_simulator_without_relaxation", no_relaxation, True, scaled),
        ("peak_friction", vehicle, False, {}),
        ("peak_friction_simulator_without_relaxation", no_relaxation, False, {}),
    ):
        key = sim_vehicle.relaxation_length
        if key not in drives:
            drives[key] = _drive(sim_vehicle, SUSTAINED)
        tr, y, vx0 = drives[key]
        obs = matched_vehicle(sim_vehicle, friction) if matched else sim_vehicle
        _, out = _run(obs, y, vx0, True, **settings)
        theta = np.asarray(out.x[:, 2])
        t = np.asarray(tr.time)
        result[name] = {
            "theta_final": float(theta[-1]),
            "theta_mean_last_10s": float(theta[t > t[-1] - 10.0].mean()),
            "settling_time_15pct_s": settling_time(t, theta, friction, 0.15),
            "settling_time_2pct_s": settling_time(t, theta, friction, 0.02),
        }
        series[name] = (t, theta)
    return result, series


def _sine(friction: float, amplitude_deg: float) -> Manoeuvre:
    """The check drive's sine (80 km/h, 0.5 Hz) of ``amplitude_deg`` on a road of ``friction``, SUSTAINED s."""
    base = DRIVES[DRIVE]

    def command(t):
        return base.command(t)._replace(steering_wheel=amplitude_deg * DEG * jnp.sin(jnp.pi * t), friction=friction)

    return Manoeuvre(f"sine_steer_friction_{friction:g}", command, SUSTAINED, base.initial_speed)


def _errors(t, beta_true_deg, out) -> dict:
    err = np.abs(np.rad2deg(np.asarray(out.beta)) - beta_true_deg)
    return {"max_abs_beta_error_deg": float(err.max()), "rms_beta_error_deg": float(np.sqrt(np.mean(err**2))),
            "max_abs_beta_error_after_10s_deg": float(err[t > 10.0].max())}  # fmt: skip


def friction_levels(vehicle: VehicleParams | None = None, **nvso_settings) -> tuple[list, dict]:
    """Per road friction of FRICTION_LEVELS, the sine steer of SUSTAINED s whose amplitude puts the peak ``|a_y|`` at
    about TARGET_USE of the friction (one linear correction of an amplitude proportional to the friction), with
    the NVSO's switching (§2.5): mode 1 only (no friction adaptation), adaptation of ``mu_H`` (``peak_friction =
    1``, the default) and of the thesis's scale (``peak_friction = 0``). Rows of the table and theta series."""
    vehicle = VehicleParams() if vehicle is None else vehicle
    rows, series = [], {}
    for friction in FRICTION_LEVELS:
        amplitude = SINE_AMPLITUDE_DEG * friction / LOW_FRICTION
        trial, _, _ = _drive(vehicle, 10.0, _sine(friction, amplitude))
        amplitude *= TARGET_USE / (float(np.abs(np.asarray(trial.ay)).max()) / (friction * GRAVITY))
        tr, y, vx0 = _drive(vehicle, SUSTAINED, _sine(friction, amplitude))
        t, beta = np.asarray(tr.time), np.rad2deg(np.asarray(tr.beta))
        row = {"friction": friction, "steering_amplitude_deg": amplitude,
               "peak_ay_over_friction_g": float(np.abs(np.asarray(tr.ay)).max() / (friction * GRAVITY)),
               "peak_beta_deg": float(np.abs(beta).max())}  # fmt: skip
        for name, settings in (("mode1", MODE1), ("peak_friction", {"peak_friction": 1.0}),
                               ("scaled", {"peak_friction": 0.0})):  # fmt: skip
            _, out = _run(vehicle, y, vx0, False, **{**nvso_settings, **settings})
            theta = np.asarray(out.x[:, 2])
            row[name] = {
                "theta_final": float(theta[-1]),
                "theta_mean_last_10s": float(theta[t > t[-1] - 10.0].mean()),
                "settling_time_15pct_s": settling_time(t, theta, friction, 0.15),
                "settling_time_2pct_s": settling_time(t, theta, friction, 0.02),
                "mode2_fraction": float(np.mean(np.asarray(out.mode) > 0.5)),
                **_errors(t, beta, out),
            }
            series[(friction, name)] = (t, theta)
        rows.append(row)
    return rows, series


def _esc_drive(name: str) -> Manoeuvre:
    """The drive ``name`` of ESC_DRIVES."""
    if name == "ice_lake_circles":
        return manoeuvre(name)
    friction = float(name.rsplit("_", 1)[1])
    if name.startswith("sine_beyond_limit"):
        sine = _sine(friction, ESC_SINE_OVERDRIVE * SINE_AMPLITUDE_DEG)
        return Manoeuvre(name, sine.command, DRIVES[DRIVE].duration * 2, sine.initial_speed)
    base = manoeuvre("circle_40m_ramp")
    return Manoeuvre(name, lambda t: base.command(t)._replace(friction=friction), base.duration, base.initial_speed)


def esc_drives(vehicle: VehicleParams | None = None, esc: ESCParams | None = None) -> tuple[list, dict]:
    """(e) of the module docstring: per drive of ESC_DRIVES, simulated with the ``esc`` (default
    :class:`~jaxobs.vehicle.ESCParams`), the NVSO without adaptation (``mode1``), with the switching conditions (i)
    and (ii) only (``without_esc_condition``: the ESC status column zeroed) and with (i)-(iii) (``with_esc_condition``).
    Rows of the table and the series of the figure."""
    vehicle = VehicleParams() if vehicle is None else vehicle
    esc = ESCParams() if esc is None else esc
    rows, series = [], {}
    for name in ESC_DRIVES:
        drive = _esc_drive(name)
        free = simulate(drive, vehicle)  # the same drive without ESC, for the peak sideslip it would reach
        tr, y, vx0 = _drive(vehicle, drive=drive, esc=esc)
        t, beta = np.asarray(tr.time), np.rad2deg(np.asarray(tr.beta))
        active = np.asarray(tr.esc_active) > 0.5
        hidden = y.at[:, ESC_ACTIVE].set(0.0)
        row = {"drive": name, "road_friction": float(np.asarray(tr.inputs.friction).min()),
               "peak_beta_without_esc_deg": float(np.abs(np.rad2deg(np.asarray(free.beta))).max()),
               "peak_beta_deg": float(np.abs(beta).max()), "esc_active_fraction": float(active.mean())}  # fmt: skip
        series[name] = {"t": t, "beta": beta, "esc": active}
        for run_name, yy, settings in (("mode1", hidden, MODE1), ("without_esc_condition", hidden, {}),
                                       ("with_esc_condition", y, {})):  # fmt: skip
            _, out = _run(vehicle, yy, vx0, False, **settings)
            theta, on = np.asarray(out.x[:, 2]), np.asarray(out.mode) > 0.5
            err = np.abs(np.rad2deg(np.asarray(out.beta)) - beta)
            row[run_name] = {
                "mode2_fraction": float(on.mean()),
                "theta_final": float(theta[-1]),
                "theta_min": float(theta.min()),
                "max_abs_beta_error_deg": float(err.max()),
                "rms_beta_error_deg": float(np.sqrt(np.mean(err**2))),
                "fraction_under_3deg": float(np.mean(err < 3.0)),
            }
            series[name][run_name] = np.rad2deg(np.asarray(out.beta))
        rows.append(row)
    return rows, series


def _markdown(header: list, cells: list) -> str:
    """A markdown table of the ``header`` and one row of ``cells`` per entry."""
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in cells])


def esc_table(rows: list) -> str:
    """The markdown table of :func:`esc_drives`."""

    def err(r):
        return f"{r['max_abs_beta_error_deg']:.2f} / {r['rms_beta_error_deg']:.2f}"

    def row(r):
        a, b = r["without_esc_condition"], r["with_esc_condition"]
        return [f"{r['drive']} ({r['road_friction']:g})",
                f"{r['peak_beta_without_esc_deg']:.1f} / {r['peak_beta_deg']:.1f}", f"{r['esc_active_fraction']:.0%}",
                f"{a['mode2_fraction']:.0%} / {b['mode2_fraction']:.0%}",
                f"{a['theta_final']:.2f} / {b['theta_final']:.2f}", err(r["mode1"]), err(a), err(b)]  # fmt: skip

    header = ["drive (friction)", "peak sideslip without / with ESC (deg)", "ESC active",
              "mode 2: (i)-(ii) / (i)-(iii)", "final theta: (i)-(ii) / (i)-(iii)",
              "sideslip error max / rms (deg): no adaptation", "(i)-(ii)", "(i)-(iii)"]  # fmt: skip
    return _markdown(header, [row(r) for r in rows])


def levels_table(rows: list) -> str:
    """The markdown table of :func:`friction_levels`."""

    def settle(r):
        return f"{r['settling_time_15pct_s']:.1f} s, {r['settling_time_2pct_s']:.1f} s"

    def err(r):
        return f"{r['max_abs_beta_error_deg']:.3f} / {r['max_abs_beta_error_after_10s_deg']:.3f}"

    def row(r):
        return [f"{r['friction']:g} ({r['peak_ay_over_friction_g']:.2f})",
                f"{r['peak_friction']['theta_final']:.3f} ({settle(r['peak_friction'])})",
                f"{r['scaled']['theta_final']:.3f}", err(r["mode1"]), err(r["peak_friction"]),
                err(r["scaled"])]  # fmt: skip

    header = ["road friction (peak a_y / friction g)", "theta, mu_H adapted (settling 15 %, 2 %)",
              "theta, scale adapted", "sideslip error max / after 10 s (deg): no adaptation", "mu_H adapted",
              "scale adapted"]  # fmt: skip
    return _markdown(header, [row(r) for r in rows])


def diagnose(vehicle: VehicleParams | None = None) -> tuple[dict, dict]:
    """The numbers (a), (b), (c) of the module docstring and the series the figure draws."""
    vehicle = VehicleParams() if vehicle is None else vehicle
    tr, y, vx0 = _drive(vehicle)
    friction = float(tr.inputs.friction[-1])
    t = np.asarray(tr.time)
    beta = np.rad2deg(np.asarray(tr.beta))

    runs, series = {}, {"t": t}
    matched = matched_vehicle(vehicle, friction)
    for name, obs_vehicle, always_on, peak in (
        ("scaled_switching", vehicle, False, 0.0),
        ("scaled_always_on", vehicle, True, 0.0),
        ("matched_switching", matched, False, 0.0),
        ("matched_always_on", matched, True, 0.0),
        ("peak_switching", vehicle, False, 1.0),
        ("peak_always_on", vehicle, True, 1.0),
    ):
        params, out = _run(obs_vehicle, y, vx0, always_on, peak_friction=peak)
        ay_star, xi = np.asarray(out.regressor), np.asarray(out.xi)
        phi = ay_star / np.sqrt(xi**2 + ay_star**2)  # Lambda a_y*
        theta, mode = np.asarray(out.x[:, 2]), np.asarray(out.mode)
        on = mode > 0.5
        rate = float(params.K_theta) * phi * ay_star  # d theta~ / dt = -rate theta~ when the scaled model is exact
        err = np.rad2deg(np.asarray(out.beta)) - beta
        runs[name] = {
            "theta_final": float(theta[-1]),
            "theta_min": float(theta.min()),
            "settling_time_15pct_s": settling_time(t, theta, friction, 0.15),
            "settling_time_2pct_s": settling_time(t, theta, friction, 0.02),
            "mode2_fraction": float(on.mean()),
            "phi_abs_mean_mode2": float(np.abs(phi[on]).mean()) if on.any() else 0.0,
            "phi_abs_max": float(np.abs(phi).max()),
            "adaptation_rate_mean_mode2_per_s": float(rate[on].mean()) if on.any() else 0.0,
            "adaptation_integral": float(np.sum(rate * on) * PERIOD),  # integral of the rate: e-folds available
            "max_abs_beta_error_deg": float(np.abs(err).max()),
            "rms_beta_error_deg": float(np.sqrt(np.mean(err**2))),
        }
        series[name] = {"theta": theta, "mode": mode, "phi": phi}

    # (b) per-axle forces at the simulator's own slips
    sim, model, alpha = (np.asarray(a) for a in _axle_forces(vehicle, tr))
    excited = np.abs(np.asarray(tr.ay)) > EXCITED_AY * friction * GRAVITY
    need = np.where(np.abs(model) > 1.0, sim / np.where(np.abs(model) > 1.0, model, 1.0), np.nan)
    axles = {}
    for j, axle in enumerate(("front", "rear")):
        ratio = need[excited, j]
        k = int(np.nanargmax(np.abs(sim[:, j])))
        axles[axle] = {
            "theta_needed_median_excited": float(np.nanmedian(ratio)),
            "theta_needed_range_excited": [float(np.nanmin(ratio)), float(np.nanmax(ratio))],
            "theta_needed_at_peak_force": float(need[k, j]),
            "peak_force_N": float(abs(sim[k, j])),
            "peak_slip_angle_deg": float(np.abs(alpha[:, j]).max()),
            "force_at_peak_over_fz_sim": float(abs(sim[k, j]) / np.asarray(tr.fz)[k, 2 * j : 2 * j + 2].sum()),
        }
    # the theta that makes the whole model exact at the true state: a_y(sim) / a_y*(true state)
    ay_true = np.asarray(tr.ay)
    ay_star_true = (model[:, 0] * np.cos(np.asarray(tr.inputs.steering_wheel) / vehicle.steering_ratio)
                    + model[:, 1]) / vehicle.mass  # fmt: skip
    theta_eff = np.where(excited, ay_true / np.where(excited, ay_star_true, 1.0), np.nan)
    series.update(need=need, alpha=alpha, excited=excited, theta_eff=theta_eff)

    # the static curves: simulator's tyre at friction 0.3 against theta times the friction-1 model (front, 1 N load)
    a = np.linspace(0.0, 12.0, 241)
    fz = 1.0
    tf = vehicle.tyre_front
    curve_sim = np.asarray(tyre_forces(dataclasses.replace(tf, mu=tf.mu * friction), 0.0, np.tan(np.deg2rad(a)), fz)[1])
    curve_model = np.asarray(tyre_forces(tf, 0.0, np.tan(np.deg2rad(a)), fz)[1])
    series.update(curve_alpha=a, curve_sim=curve_sim, curve_model=curve_model)

    summary = {
        "drive": DRIVE,
        "road_friction": friction,
        "peak_ay_over_friction_g": float(np.abs(ay_true).max() / (friction * GRAVITY)),
        "peak_beta_deg": float(np.abs(beta).max()),
        "excited_fraction": float(excited.mean()),
        "a_regressor_and_gating": {k: runs[k] for k in ("scaled_switching", "scaled_always_on")},
        "b_axle_forces": {
            **axles,
            "theta_eff_whole_model_median_excited": float(np.nanmedian(theta_eff)),
            "model_over_sim_at_slip_of_sim_peak": float(curve_model[np.argmax(curve_sim)] * friction / curve_sim.max()),
            "sim_peak_slip_deg": float(a[np.argmax(curve_sim)]),
            "model_peak_slip_deg": float(a[np.argmax(curve_model)]),
        },
        "c_identifiability": {k: runs[k] for k in ("matched_switching", "matched_always_on")},
        "d_peak_friction": {k: runs[k] for k in ("peak_switching", "peak_always_on")},
    }
    summary["c_identifiability"]["sustained_always_on"], series["sustained"] = _sustained(vehicle, friction)
    return summary, series


def figure(summary: dict, series: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot, save_figure

    t = series["t"]
    friction = summary["road_friction"]
    fig, ax = pyplot().subplots(3, 3, figsize=(17, 12.5), constrained_layout=True)

    p = ax[0, 0]
    for name, label, style in (
        ("scaled_switching", "theta x friction-1 model (Grip 2010 §2.4), switching (§2.5)", "C3-"),
        ("scaled_always_on", "theta x friction-1 model, estimation always on", "C1--"),
        ("matched_switching", "theta x simulator's tyre (normalised), switching", "C2-"),
        ("matched_always_on", "theta x simulator's tyre (normalised), always on", "C0--"),
        ("peak_switching", "theta = mu_H of the model (the default), switching", "C4-"),
    ):
        p.plot(t, series[name]["theta"], style, label=label)
    p.plot(t, series["theta_eff"], "k.", ms=2, label="theta the scaled model needs at the true state")
    p.axhline(friction, color="k", lw=1, ls=":", label=f"road friction {friction:g}")
    p.set(xlabel="time (s)", ylabel="friction estimate theta (-)", title="(c) friction estimate", ylim=(0, 1.15))
    p.legend(fontsize=7, loc="lower left")

    p = ax[0, 1]
    s = series["scaled_switching"]
    p.plot(t, s["phi"], "C3-", label="regressor phi = Lambda a_y* (scaled model)")
    p.plot(t, series["matched_switching"]["phi"], "C2-", lw=1, label="regressor phi (model = simulator's)")
    p.fill_between(t, -1, 1, where=s["mode"] > 0.5, color="C3", alpha=0.12, step="pre",
                   label="friction estimation on (scaled, switching)")  # fmt: skip
    p.set(xlabel="time (s)", ylabel="phi (-)", title="(a) update-law regressor and the gate", ylim=(-1.05, 1.05))
    p.legend(fontsize=7, loc="lower left")

    p = ax[1, 0]
    need = series["need"]
    exc = series["excited"]
    for j, (axle, c) in enumerate((("front", "C0"), ("rear", "C1"))):
        p.plot(t[exc], need[exc, j], ".", color=c, ms=3, label=f"{axle} axle: F_y,sim / F_y,model(theta=1)")
    p.axhline(friction, color="k", lw=1, ls=":", label=f"road friction {friction:g}")
    p.set(xlabel="time (s)", ylabel="theta needed per axle (-)", ylim=(0, 1.15),
          title=f"(b) per-axle theta at the simulator's slips (|a_y| > {EXCITED_AY:g} mu g)")  # fmt: skip
    p.legend(fontsize=7, loc="lower left")

    p = ax[1, 1]
    a = series["curve_alpha"]
    p.plot(a, series["curve_sim"], "k-", lw=2, label=f"simulator's tyre on friction {friction:g}")
    theta_eff = summary["b_axle_forces"]["theta_eff_whole_model_median_excited"]
    for th, c in ((friction, "C2"), (theta_eff, "C3"), (1.0, "C7")):
        p.plot(a, th * series["curve_model"], "--", color=c, label=f"{th:.2f} x observer's friction-1 model")
    amax = max(summary["b_axle_forces"]["front"]["peak_slip_angle_deg"],
               summary["b_axle_forces"]["rear"]["peak_slip_angle_deg"])  # fmt: skip
    p.axvspan(0, amax, color="C3", alpha=0.1, label="slip angles the drive reaches")
    p.set(xlabel="slip angle alpha (deg)", ylabel="F_y / F_z (-)", ylim=(0, 1.05),
          title="(b) front tyre, pure lateral slip")  # fmt: skip
    p.legend(fontsize=7, loc="upper right")
    p = ax[0, 2]
    for (name, label), c in zip(
        (("scaled_model", "theta x friction-1 model"), ("matched_model", "theta x simulator's tyre (normalised)"),
         ("matched_model_without_relaxation_filter", "the same, no relaxation filter (§2.8)"),
         ("matched_model_simulator_without_relaxation", "the same; simulator's relaxation length\n"
          f"{SHORT_RELAXATION:g} m instead of 0.5 m"),
         ("peak_friction", "theta = mu_H of the model (the default)")),
        ("C1", "C0", "C3", "C2", "C4"), strict=True,
    ):  # fmt: skip
        p.plot(*series["sustained"][name], color=c, label=label)
    p.axhline(friction, color="k", lw=1, ls=":", label=f"road friction {friction:g}")
    p.axhspan(0.98 * friction, 1.02 * friction, color="k", alpha=0.1, label="+-2 %")
    p.set(xlabel="time (s)", ylabel="friction estimate theta (-)", ylim=(0, 1.15),
          title=f"(c) the same sine for {SUSTAINED:g} s, estimation held on")  # fmt: skip
    p.legend(fontsize=7, loc="upper right")
    p = ax[1, 2]
    for i, level in enumerate(FRICTION_LEVELS):
        for name, style in (("peak_friction", "-"), ("scaled", "--")):
            t_level, theta = series["levels"][(level, name)]
            p.plot(t_level, theta, style, color=f"C{i}", lw=1.2)
        p.axhline(level, color=f"C{i}", lw=0.8, ls=":")
    p.plot([], [], "k-", label="theta = mu_H of the model (the default)")
    p.plot([], [], "k--", label="theta x friction-1 model (Grip 2010 §2.4)")
    p.plot([], [], "k:", label="road friction")
    p.set(xlabel="time (s)", ylabel="friction estimate theta (-)", ylim=(0, 1.15),
          title=f"(d) sines at {TARGET_USE:g} of each road's friction, switching (§2.5)")  # fmt: skip
    p.legend(fontsize=7, loc="lower right")
    for p, row in zip(ax[2], summary["esc_drives"], strict=True):
        e = series["esc"][row["drive"]]
        p.plot(e["t"], e["beta"], "k-", lw=2, label="true")
        for run_name, label, style in (("mode1", "NVSO, no adaptation", "C7-"),
                                       ("without_esc_condition", "NVSO, conditions (i)-(ii)", "C1--"),
                                       ("with_esc_condition", "NVSO, conditions (i)-(iii)", "C0-")):  # fmt: skip
            p.plot(e["t"], e[run_name], style, lw=1.2, label=label)
        low, high = p.get_ylim()
        p.fill_between(e["t"], low, high, where=e["esc"], color="C3", alpha=0.12, step="pre", label="ESC intervenes")
        p.set(xlabel="time (s)", ylabel="sideslip (deg)", ylim=(low, high),
              title=f"(e) {row['drive']} with ESC (friction {row['road_friction']:g})")  # fmt: skip
        p.legend(fontsize=7, loc="lower left")
    fig.suptitle(f"NVSO friction adaptation on the friction-{friction:g} check drive ({DRIVE})")
    save_figure(fig, path.parent, path.stem)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary, series = diagnose()
    summary["friction_levels"], series["levels"] = friction_levels()
    summary["esc_drives"], series["esc"] = esc_drives()
    print(levels_table(summary["friction_levels"]))
    print(esc_table(summary["esc_drives"]))
    (out / "sideslip_friction.json").write_text(json.dumps(summary, indent=1))
    figure(summary, series, out / "sideslip_friction.png")
    print(json.dumps(summary, indent=1))
    print(f"wrote {out / 'sideslip_friction.json'} and {out / 'sideslip_friction.png'}")


if __name__ == "__main__":
    main()
