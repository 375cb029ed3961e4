"""Why the NVSO's friction estimate ends at 0.85 on the friction-0.3 check drive (issue 30, item 1): a diagnosis.

The drive is ``sine_steer_low_friction`` of :mod:`jaxobs.papers.grip2010.sideslip` (80 km/h, steering-wheel sine of
25 deg at 0.5 Hz, 10 s, road friction 0.3, exact sensors with the 15 Hz low-pass). Three questions, each answered
with numbers and one panel of the figure:

(a) Excitation and gating. The update law (Grip 2010 (2.25)) is ``theta' = K_theta phi e`` with the regressor
    ``phi = Lambda a_y*`` and ``e = a_y - theta a_y*``; it acts only in mode 2 (the switching of §2.5). Reported:
    ``phi`` along the drive, the fraction of time in mode 2, and the adaptation rate ``K_theta phi a_y*`` (1/s, the
    rate at which a theta error decays while the model is exact) averaged over mode 2.
(b) Model mismatch. The simulator's tyres on friction 0.3 keep their cornering stiffness and saturate at 0.3 F_z
    (a Magic Formula with ``B = c / (C mu)``); the observer's model is ``theta`` times the friction-1 tyre. At the
    simulator's own slips, loads and wheel slips, the per-axle ratio ``F_y,sim / F_y*`` is the theta the
    observer's model needs to reproduce the simulator's force; it is 0.3 only if the model can represent the tyre.
(c) Identifiability. The NVSO rerun with an observer tyre equal to the simulator's at friction 0.3, normalised to
    ``mu_H* = 1`` (cornering and slip stiffness divided by 0.3, so ``0.3 a_y*`` is exactly the simulator's
    ``a_y``): the estimate must then converge to 0.3 if the update law is right. Run with the switching of §2.5
    and with friction estimation held on, with and without the NVSO's tyre-relaxation filter (Grip 2010 §2.8).

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
from jaxobs.papers.grip2010.sideslip import DRIVES, EXACT, PERIOD  # noqa: E402
from jaxobs.vehicle import Manoeuvre, VehicleParams, make_nvso, measure, nvso, sensor_inputs, simulate  # noqa: E402
from jaxobs.vehicle.model import GRAVITY, friction_model  # noqa: E402
from jaxobs.vehicle.sensors import AX, AY, STEERING_WHEEL, WHEEL_SPEED, YAW_RATE  # noqa: E402
from jaxobs.vehicle.tyres import TyreParams, tyre_forces  # noqa: E402

DRIVE = "sine_steer_low_friction"
ALWAYS_ON = dict(vy_dot_threshold=1e-9, yaw_rate_threshold=1e-9, oversteer_threshold=1e-9, off_delay=1e6)
"""Switching settings that keep friction estimation on from the start (with the initial mode set to 2)."""
SUSTAINED = 30.0  # s, the drive continued (the same sine) for the convergence runs of (c)
SHORT_RELAXATION = 0.02  # m: the relaxation length of the simulator without (appreciable) tyre relaxation
EXCITED_AY = 0.5  # |a_y| / (friction g) above which a sample counts as excited in the per-axle statistics


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


def _regressor(params, out, y):
    """``phi = Lambda a_y*`` and ``a_y*`` of every sample at the estimate and the measurement of that sample."""
    v = params.vehicle
    roll = 1.0 + v.roll_gradient * GRAVITY

    def one(x, m):
        def ay_star(vy):
            return friction_model(v, x[0], vy, m[YAW_RATE], m[STEERING_WHEEL], m[WHEEL_SPEED], m[AX],
                                  m[AY] / roll).ay  # fmt: skip

        a, xi = jax.jvp(ay_star, (x[1],), (jnp.ones_like(x[1]),))
        return a / jnp.sqrt(xi**2 + a**2), a

    # the estimate x_k was driven by the measurement held over [t_{k-1}, t_k]
    x_prev = jnp.concatenate([out.x[:1], out.x[:-1]])
    y_prev = jnp.concatenate([y[:1], y[:-1]])
    return jax.vmap(one)(x_prev, y_prev)


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


def _drive(vehicle, duration=None):
    """The check drive (optionally lengthened: the same sine continued) at the 100 Hz samples and its sensors."""
    drive = DRIVES[DRIVE]
    duration = drive.duration if duration is None else duration
    tr_fine = simulate(Manoeuvre(DRIVE, drive.command, duration, drive.initial_speed), vehicle)
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
    for name, sim_vehicle, matched, settings in (
        ("default_model", vehicle, False, {}),
        ("matched_model", vehicle, True, {}),
        ("matched_model_without_relaxation_filter", vehicle, True, {"relaxation_length": 0.0}),
        ("matched_model_simulator_without_relaxation", no_relaxation, True, {}),
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


def diagnose(vehicle: VehicleParams | None = None) -> tuple[dict, dict]:
    """The numbers (a), (b), (c) of the module docstring and the series the figure draws."""
    vehicle = VehicleParams() if vehicle is None else vehicle
    tr, y, vx0 = _drive(vehicle)
    friction = float(tr.inputs.friction[-1])
    t = np.asarray(tr.time)
    beta = np.rad2deg(np.asarray(tr.beta))

    runs, series = {}, {"t": t}
    matched = matched_vehicle(vehicle, friction)
    for name, obs_vehicle, always_on in (
        ("default_switching", vehicle, False),
        ("default_always_on", vehicle, True),
        ("matched_switching", matched, False),
        ("matched_always_on", matched, True),
    ):
        params, out = _run(obs_vehicle, y, vx0, always_on)
        phi, ay_star = (np.asarray(a) for a in _regressor(params, out, y))
        theta, mode = np.asarray(out.x[:, 2]), np.asarray(out.mode)
        on = mode > 0.5
        rate = float(params.K_theta) * phi * ay_star  # d theta~ / dt = -rate theta~ when the model is exact
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
        "a_regressor_and_gating": {k: runs[k] for k in ("default_switching", "default_always_on")},
        "b_axle_forces": {
            **axles,
            "theta_eff_whole_model_median_excited": float(np.nanmedian(theta_eff)),
            "model_over_sim_at_slip_of_sim_peak": float(curve_model[np.argmax(curve_sim)] * friction / curve_sim.max()),
            "sim_peak_slip_deg": float(a[np.argmax(curve_sim)]),
            "model_peak_slip_deg": float(a[np.argmax(curve_model)]),
        },
        "c_identifiability": {k: runs[k] for k in ("matched_switching", "matched_always_on")},
    }
    summary["c_identifiability"]["sustained_always_on"], series["sustained"] = _sustained(vehicle, friction)
    return summary, series


def figure(summary: dict, series: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = series["t"]
    friction = summary["road_friction"]
    fig, ax = plt.subplots(2, 3, figsize=(17, 8.5), constrained_layout=True)

    p = ax[0, 0]
    for name, label, style in (
        ("default_switching", "NVSO, default model, switching (§2.5)", "C3-"),
        ("default_always_on", "NVSO, default model, estimation always on", "C1--"),
        ("matched_switching", "NVSO, model = simulator's tyre, switching", "C2-"),
        ("matched_always_on", "NVSO, model = simulator's tyre, always on", "C0--"),
    ):
        p.plot(t, series[name]["theta"], style, label=label)
    p.plot(t, series["theta_eff"], "k.", ms=2, label="theta the default model needs at the true state")
    p.axhline(friction, color="k", lw=1, ls=":", label=f"road friction {friction:g}")
    p.set(xlabel="time (s)", ylabel="friction estimate theta (-)", title="(c) friction estimate", ylim=(0, 1.15))
    p.legend(fontsize=7, loc="lower left")

    p = ax[0, 1]
    s = series["default_switching"]
    p.plot(t, s["phi"], "C3-", label="regressor phi = Lambda a_y* (default model)")
    p.plot(t, series["matched_switching"]["phi"], "C2-", lw=1, label="regressor phi (model = simulator's)")
    p.fill_between(t, -1, 1, where=s["mode"] > 0.5, color="C3", alpha=0.12, step="pre",
                   label="friction estimation on (default, switching)")  # fmt: skip
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
        (("default_model", "default model"), ("matched_model", "model = simulator's tyre"),
         ("matched_model_without_relaxation_filter", "model = simulator's tyre, no relaxation filter (§2.8)"),
         ("matched_model_simulator_without_relaxation", "model = simulator's tyre; simulator's relaxation length\n"
          f"{SHORT_RELAXATION:g} m instead of 0.5 m")),
        ("C1", "C0", "C3", "C2"), strict=True,
    ):  # fmt: skip
        p.plot(*series["sustained"][name], color=c, label=label)
    p.axhline(friction, color="k", lw=1, ls=":", label=f"road friction {friction:g}")
    p.axhspan(0.98 * friction, 1.02 * friction, color="k", alpha=0.1, label="+-2 %")
    p.set(xlabel="time (s)", ylabel="friction estimate theta (-)", ylim=(0, 1.15),
          title=f"(c) the same sine for {SUSTAINED:g} s, estimation held on")  # fmt: skip
    p.legend(fontsize=7, loc="upper right")
    ax[1, 2].axis("off")
    fig.suptitle(f"NVSO friction adaptation on the friction-{friction:g} check drive ({DRIVE})")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary, series = diagnose()
    (out / "sideslip_friction.json").write_text(json.dumps(summary, indent=1))
    figure(summary, series, out / "sideslip_friction.png")
    print(json.dumps(summary, indent=1))
    print(f"wrote {out / 'sideslip_friction.json'} and {out / 'sideslip_friction.png'}")


if __name__ == "__main__":
    main()
