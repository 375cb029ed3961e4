"""Cost per step of the sideslip observers of Grip 2010 ch. 2, batched over vehicles: the NVSO
(:data:`jaxobs.vehicle.nvso`) against the EKF baseline of §2.9 (:data:`jaxobs.vehicle.vehicle_ekf`, Joseph update;
Bierman's U-D update as a third entry). Grip 2010 §2.10 reports the NVSO at about a third of the EKF's computational
cost.

Workload: the 120 km/h double lane change simulated once for the default vehicle, measured ``--vehicles`` times
with independent sensor noise (one :class:`~jaxobs.vehicle.SensorParams` draw each); each observer runs over
``--samples`` sensor samples (100 Hz) of every vehicle, ``jit(vmap(run))``, compiled once (compile time reported
apart). Interleaved rounds (benchmarks/_timing.py): per-step cost (the run's time over the samples), the cost per
vehicle-step, and the paired EKF / NVSO cost ratio. The sideslip RMS errors of both (against the simulated
sideslip) are stored as a check that both did the work.

NumPy peers: the NVSO (exact switching) and the EKF (Joseph update) written out in NumPy, every operation on
(V, ...) arrays of all the vehicles and one Python loop over the samples (``d a_y* / d v_y`` and the EKF's
measurement Jacobian by central differences where jaxobs uses autodiff); their sideslip is compared with jaxobs'
(stored in the JSON), and the paired NumPy / jaxobs cost ratios are reported.

    python benchmarks/sideslip.py --out DIR [--vehicles 1024] [--samples 800] [--rounds 5]

Writes ``DIR/sideslip.json`` and prints a table.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from _timing import format_range, paired_ratio, summary, time_interleaved  # noqa: E402

from jaxobs.observers.base import run  # noqa: E402
from jaxobs.vehicle import (  # noqa: E402
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
from jaxobs.vehicle.model import AIR_DENSITY, GRAVITY, MIN_SPEED  # noqa: E402

MANOEUVRE = "double_lane_change_120kmh"


def _magic_ratio(s, stiffness, shape, curvature, mu, fz):
    small = s < 1e-12
    s_safe = np.where(small, 1.0, s)
    bs = stiffness / (shape * mu) * s_safe
    force = mu * fz * np.sin(shape * np.arctan(bs - curvature * (bs - np.arctan(bs))))
    return np.where(small, stiffness * fz, force / s_safe)


def _forces(v, vx, vy, r, sw, omega, ax, ay, friction=1.0):
    """(a_x, a_y, yaw moment) of the friction model at the road ``friction``, batched: scalars (V,), omega (V, 4)."""
    gx = np.array([v.lf, v.lf, -v.lr, -v.lr])
    gy = np.array([v.track_front / 2, -v.track_front / 2, v.track_rear / 2, -v.track_rear / 2])
    d = (sw / v.steering_ratio)[:, None]
    delta = np.concatenate([d, d, 0 * d, 0 * d], axis=1)
    vwx, vwy = vx[:, None] - r[:, None] * gy, vy[:, None] + r[:, None] * gx
    c, s = np.cos(delta), np.sin(delta)
    v_l, v_s = vwx * c + vwy * s, -vwx * s + vwy * c
    speed = np.maximum(np.abs(v_l), MIN_SPEED)
    tan_alpha, kappa = -v_s / speed, (omega * v.wheel_radius - v_l) / speed
    L, m, h = v.lf + v.lr, v.mass, v.cg_height
    w = m * GRAVITY
    front = (w * v.lr / L - m * ax * h / L) / 2
    rear = (w * v.lf / L + m * ax * h / L) / 2
    dyf = m * ay * h * v.roll_share_front / v.track_front
    dyr = m * ay * h * (1 - v.roll_share_front) / v.track_rear
    fz = np.maximum(np.stack([front - dyf / 2, front + dyf / 2, rear - dyr / 2, rear + dyr / 2], axis=1), 0.0)
    denom = 1.0 + np.maximum(kappa, -0.99)
    sx, sy = kappa / denom, tan_alpha / denom
    s2 = sx**2 + sy**2
    sl = np.where(s2 < 1e-24, 0.0, np.sqrt(np.where(s2 < 1e-24, 1.0, s2)))
    fxw, fyw = np.empty_like(sx), np.empty_like(sy)
    scale = np.asarray(friction, float)[..., None]  # (V, 1) or (1,)
    for axle, tyre in ((slice(0, 2), v.tyre_front), (slice(2, 4), v.tyre_rear)):
        fxw[:, axle] = (
            _magic_ratio(sl[:, axle], tyre.slip_stiffness, tyre.shape_x, tyre.curvature_x, tyre.mu * scale, fz[:, axle])
            * sx[:, axle]
        )
        fyw[:, axle] = (
            _magic_ratio(
                sl[:, axle], tyre.cornering_stiffness, tyre.shape_y, tyre.curvature_y, tyre.mu * scale, fz[:, axle]
            )
            * sy[:, axle]
        )
    fx, fy = fxw * c - fyw * s, fxw * s + fyw * c
    drag = 0.5 * AIR_DENSITY * v.drag_area * vx * np.abs(vx)
    return (np.sum(fx, axis=1) - drag) / m, np.sum(fy, axis=1) / m, np.sum(gx * fy - gy * fx, axis=1)


def _switch(f, r, r_ref, ay, vx, esc, low_pass, timer, dead, dt):
    """One step of the switching rule of ``jaxobs.vehicle.switching`` in NumPy, per vehicle: ``(mode, timer,
    low_pass, same)``; ``mode`` 1 selects the nonlinear injection, ``same`` marks yaw rates of the reference's sign."""
    high_pass = ay - r * vx - low_pass
    same = r * r_ref > dead
    lateral_motion = np.abs(high_pass) > f("vy_dot_threshold")
    excited = lateral_motion & (np.abs(r_ref) > f("yaw_rate_threshold"))
    opposite = -r * r_ref > dead  # counter-steering
    over = (same & ((np.abs(r) - np.abs(r_ref)) * vx > f("oversteer_threshold"))) | (
        opposite & ((np.abs(r) + np.abs(r_ref)) * vx > f("oversteer_threshold"))
    )
    understeer = same & ((np.abs(r_ref) - np.abs(r)) * vx > f("understeer_threshold"))
    esc_on = (esc > 0.5) & ~(understeer & ~lateral_motion)  # the ESC, not for steady-state understeer
    timer = np.where(excited | over | esc_on, 0.0, timer + dt)
    mode = (f("off_delay") + dt / 2 - timer > 0).astype(float)
    return mode, timer, low_pass + dt / f("high_pass_time") * high_pass, same


def numpy_nvso(p, y):
    """The NVSO (exact switching) in NumPy over V vehicles at once, a Python loop over the K samples:
    y (V, K, 10) finite -> sideslip (V, K)."""
    v, dt, g = p.vehicle, p.dt, GRAVITY
    f = lambda name: float(getattr(p, name))  # noqa: E731
    V, K, _ = y.shape
    roll = 1.0 + v.roll_gradient * g
    L = v.lf + v.lr
    K_us = (1 / v.tyre_front.cornering_stiffness - 1 / v.tyre_rear.cornering_stiffness) / g
    lateral = np.array([v.track_front / 2, -v.track_front / 2, v.track_rear / 2, -v.track_rear / 2])
    dead = (f("yaw_rate_threshold") / 10) ** 2
    out = np.empty((V, K))
    y0 = y[:, 0]
    x = np.zeros((V, 5))
    x[:, 0], x[:, 2] = y0[:, 8], f("theta_default")
    mode, timer = np.zeros(V), np.full(V, f("off_delay"))
    peak = f("peak_friction")
    relaxed = np.zeros((V, 2))  # the relaxation filter starts at the straight initial estimate's zero output
    low_pass = y0[:, 1] / roll - y0[:, 2] * y0[:, 8]
    out[:, 0] = np.arctan2(x[:, 1], np.maximum(x[:, 0], f("min_speed")))
    held = y0
    for k in range(1, K):
        now = y[:, k]
        ax, ay, r, sw, omega, vref = held[:, 0], held[:, 1] / roll, held[:, 2], held[:, 3], held[:, 4:8], held[:, 8]
        vx, vy, theta, ti, tb = x.T
        friction, scale = peak * theta + (1 - peak), peak + (1 - peak) * theta
        _, ay_static, moment_static = _forces(v, vx, vy, r, sw, omega, ax, ay, friction)
        hstep = 1e-6
        xi = (
            _forces(v, vx, vy + hstep, r, sw, omega, ax, ay)[1] - _forces(v, vx, vy - hstep, r, sw, omega, ax, ay)[1]
        ) / (2 * hstep)
        T = f("relaxation_time") + f("relaxation_length") / np.maximum(vx, f("min_speed"))
        alpha = -np.expm1(-dt / np.maximum(T, 1e-3 * dt))
        relaxed += alpha[:, None] * (np.stack([ay_static, moment_static / v.yaw_inertia], axis=1) - relaxed)
        ay_model, yaw_acc_model = scale * relaxed[:, 0], scale * relaxed[:, 1]
        regressor = ay_model / np.maximum(theta, f("theta_min"))
        lam = 1.0 / np.sqrt(np.maximum(xi**2 + regressor**2, 1e-12))
        e = ay - ay_model
        delta = sw / v.steering_ratio
        steer = np.stack([np.cos(delta), np.cos(delta), np.ones(V), np.ones(V)], axis=1)
        wheel_vx = omega * v.wheel_radius / steer + r[:, None] * lateral
        spread = np.sqrt(np.mean((wheel_vx - wheel_vx.mean(axis=1, keepdims=True)) ** 2, axis=1) + 1e-12)
        K_vx = np.maximum(f("K_vx_min"), f("K_vx") / (1.0 + (spread / f("wheel_spread")) ** 2))
        r_ref = vx * delta / (L + K_us * vx**2)
        next_mode, timer, low_pass, same = _switch(f, r, r_ref, ay, vx, held[:, 9], low_pass, timer, dead, dt)
        yaw_acc = (now[:, 2] - r) / dt
        reduce = (
            (np.abs(e) > f("c1"))
            | (np.abs(yaw_acc - yaw_acc_model) > f("c2"))
            | (same & ((np.abs(r_ref) - np.abs(r)) * vx > f("c3")))
        )
        K_theta_b = f("K_theta_b") * np.where(reduce, f("theta_b_reduction"), 1.0)
        moving = (vx > f("min_speed")).astype(float)
        kin_x = ax + r * vy + g * ti + K_vx * (vref - vx)
        injection = (1 - mode) * (-f("K_vy") * e) + mode * f("K_vy") * lam * xi * e
        d_vy = moving * (ay - r * vx - g * tb + injection) - (1 - moving) * K_vx * vy
        d_theta = (1 - moving * mode) * f("K_e") * (f("theta_default") - theta) + moving * mode * f(
            "K_theta"
        ) * lam * regressor * e
        d_ti = ((1 - mode) * f("K_theta_i") + mode * f("K_theta_i_on")) * K_vx * (vref - vx)
        d_tb = moving * K_theta_b * ((1 - mode) * e - mode * lam * xi * e)
        x = x + dt * np.stack([kin_x, d_vy, d_theta, d_ti, d_tb], axis=1)
        lower = np.maximum(f("theta_min"), np.hypot(ax, ay) / (f("accel_margin") * g))
        x[:, 2] = np.clip(x[:, 2], np.minimum(lower, f("theta_max")), f("theta_max"))
        mode, held = next_mode, now
        out[:, k] = np.arctan2(x[:, 1], np.maximum(x[:, 0], f("min_speed")))
    return out


def numpy_ekf(params, y):
    """The vehicle EKF (Joseph update) in NumPy over V vehicles at once, a Python loop over the K samples:
    y (V, K, 10) finite -> sideslip (V, K). The measurement Jacobian by central differences (jaxobs: autodiff)."""
    v, model, sw_p = params.vehicle, params.ekf.model, params.switching
    dt, tau, k_mu, mu0 = (float(c) for c in model.f.args[0])
    gate = np.inf if params.ekf.gate is None else float(params.ekf.gate)
    g = GRAVITY
    f = lambda name: float(getattr(sw_p, name))  # noqa: E731
    Q0, R = np.asarray(model.Q), np.asarray(model.R)
    q_mu, (lo, hi) = np.asarray(params.q_mu), np.asarray(params.mu_bounds)
    V, K, _ = y.shape
    roll = 1.0 + v.roll_gradient * g
    L = v.lf + v.lr
    K_us = (1 / v.tyre_front.cornering_stiffness - 1 / v.tyre_rear.cornering_stiffness) / g
    dead = (f("yaw_rate_threshold") / 10) ** 2
    x = np.tile(np.asarray(model.x0), (V, 1))
    P = np.tile(np.asarray(model.P0), (V, 1, 1))
    sensors = np.zeros((V, 10))
    sensors[:, 8], sensors[:, 4:8] = x[:, 0:1].T[0], (x[:, 0] / v.wheel_radius)[:, None]
    mode, timer, low_pass = np.zeros(V), np.full(V, f("off_delay")), np.zeros(V)
    eye = np.eye(8)
    out = np.empty((V, K))

    def h(x, s):
        mu = np.clip(x[:, 4], lo, hi)
        ax, ay, moment = _forces(v, x[:, 0], x[:, 1], s[:, 2], s[:, 3], s[:, 4:8], s[:, 0], s[:, 1] / roll, mu)
        return np.stack([ax, ay, moment / v.yaw_inertia, x[:, 0]], axis=1)

    for k in range(K):
        now, previous = y[:, k], sensors
        if k:  # prediction (none before the first update: x0, P0 are the prior of x_0)
            ax, ay, r = previous[:, 0], previous[:, 1] / roll, previous[:, 2]
            vx, vy, d_i, d_b, d_mu = x[:, 0], x[:, 1], x[:, 5], x[:, 6], x[:, 7]
            attraction = (1 - mode) * k_mu  # slow friction estimation draws mu to mu0
            d_mu_total = d_mu - attraction * (x[:, 4] - mu0)
            rate = np.stack([ax + r * vy + g * x[:, 2], ay - r * vx - g * x[:, 3], d_i, d_b, d_mu_total,
                             -d_i / tau, -d_b / tau, -d_mu / tau], axis=1)  # fmt: skip
            F = np.tile(eye, (V, 1, 1))
            F[:, 0, 1], F[:, 0, 2], F[:, 1, 0], F[:, 1, 3] = dt * r, dt * g, -dt * r, -dt * g
            F[:, 4, 4] = 1 - dt * attraction
            for i in range(3):
                F[:, 2 + i, 5 + i] = dt
                F[:, 5 + i, 5 + i] = 1 - dt / tau
            Q = np.tile(Q0, (V, 1, 1))
            Q[:, 7, 7] = dt * ((1 - mode) * q_mu[0] ** 2 + mode * q_mu[1] ** 2)
            x = x + dt * rate
            P = F @ P @ F.transpose(0, 2, 1) + Q
        else:  # the prior mean of v_x is the first v_x,ref
            x[:, 0] = now[:, 8]
        z = np.stack([now[:, 0], now[:, 1] / roll, (now[:, 2] - previous[:, 2]) / dt, now[:, 8]], axis=1)
        h0 = h(x, now)
        H = np.zeros((V, 4, 8))
        for j in (0, 1, 4):
            step = np.zeros(8)
            step[j] = 1e-6
            H[:, :, j] = (h(x + step, now) - h(x - step, now)) / 2e-6
        innovation = z - h0
        if k == 0:  # no yaw acceleration from a single yaw-rate sample: skipped
            H[:, 2, :], innovation[:, 2] = 0.0, 0.0
        # innovation gate: a component beyond gate standard deviations is skipped (R is diagonal: a zero row of H
        # and a zero innovation remove it exactly)
        spread = np.sqrt(np.einsum("vij,vjk,vik->vi", H, P, H) + np.diagonal(R))
        outlier = np.abs(innovation) > gate * spread
        H[outlier], innovation[outlier] = 0.0, 0.0
        CP = H @ P
        S = CP @ H.transpose(0, 2, 1) + R
        S = (S + S.transpose(0, 2, 1)) / 2
        Kg = np.linalg.solve(S, CP).transpose(0, 2, 1)
        IKC = eye - Kg @ H
        P = IKC @ P @ IKC.transpose(0, 2, 1) + Kg @ R @ Kg.transpose(0, 2, 1)
        P = (P + P.transpose(0, 2, 1)) / 2
        x = x + np.einsum("vij,vj->vi", Kg, innovation)
        ax, ay, r, sw = now[:, 0], now[:, 1] / roll, now[:, 2], now[:, 3]
        lower = np.maximum(lo, np.hypot(ax, ay) / (f("accel_margin") * g))
        x[:, 4] = np.clip(x[:, 4], np.minimum(lower, hi), hi)
        vx = x[:, 0]
        if k == 0:
            low_pass = ay - r * vx
        else:
            r_ref = vx * (sw / v.steering_ratio) / (L + K_us * vx**2)
            mode, timer, low_pass, _ = _switch(f, r, r_ref, ay, vx, now[:, 9], low_pass, timer, dead, dt)
        sensors = now
        out[:, k] = np.arctan2(x[:, 1], x[:, 0])
    return out


def workload(vehicles: int, samples: int):
    """``(inputs, true sideslip, vx0)``: ``vehicles`` noisy measurements of one simulated drive, (V, K, ...)."""
    p = VehicleParams()
    duration = samples / 100.0
    tr = jax.jit(lambda: simulate(MANOEUVRE, p, duration=duration))()
    keys = jax.random.split(jax.random.PRNGKey(0), vehicles)
    meas = jax.jit(jax.vmap(lambda k: measure(tr, p, SensorParams(), k)))(keys)
    inputs = jax.vmap(sensor_inputs)(meas)
    inputs = jax.tree_util.tree_map(lambda a: a[:, :samples], inputs)
    return inputs, tr.beta[::10][:samples], float(meas.vx_ref[0, 0])


def batched(system, params):
    """``inputs (V, K, ...) -> sideslip (V, K)`` of ``system`` with the same ``params`` for every vehicle."""
    return jax.vmap(lambda inputs: run(system, params, inputs)[1].beta)


def measure_costs(vehicles: int, samples: int, rounds: int) -> dict:
    inputs, beta, vx0 = workload(vehicles, samples)
    observers = {
        "nvso": batched(nvso, make_nvso(vx0=vx0)),
        "ekf": batched(vehicle_ekf, make_vehicle_ekf(vx0=vx0)),
        "ekf_bierman": batched(vehicle_ekf, make_vehicle_ekf(vx0=vx0, bierman=True)),
    }
    entries = {name: ((lambda f=f: (f, (inputs,))), True, 1.0) for name, f in observers.items()}
    y, nvso_params = np.asarray(inputs.y), make_nvso(vx0=vx0)
    ekf_params = make_vehicle_ekf(vx0=vx0)
    entries["nvso_numpy"] = ((lambda: ((lambda: numpy_nvso(nvso_params, y)), ())), False, 1.0)
    entries["ekf_numpy"] = ((lambda: ((lambda: numpy_ekf(ekf_params, y)), ())), False, 1.0)
    timings, problems = time_interleaved(entries, rounds, required=tuple(entries))
    results = {}
    for name, t in timings.items():
        rms = np.sqrt(np.mean(np.asarray(t.result - beta[None]) ** 2, axis=1))
        per_step = [s / samples for s in t.seconds]
        results[name] = {
            **t.record(vehicles * samples, "vehicle-steps/s"),
            "step_seconds": summary(per_step),
            "vehicle_step_seconds": summary([s / vehicles for s in per_step]),
            "beta_rms_deg_median": float(np.rad2deg(np.median(rms))),
        }
    return {
        "manoeuvre": MANOEUVRE,
        "vehicles": vehicles,
        "samples": samples,
        "observers": results,
        "ekf_over_nvso": paired_ratio(timings["nvso"], timings["ekf"]),
        "ekf_bierman_over_nvso": paired_ratio(timings["nvso"], timings["ekf_bierman"]),
        "numpy_over_nvso": paired_ratio(timings["nvso"], timings["nvso_numpy"]),
        "numpy_over_ekf": paired_ratio(timings["ekf"], timings["ekf_numpy"]),
        "numpy_max_difference_deg": {
            name: float(np.rad2deg(np.max(np.abs(np.asarray(timings[name].result) - timings[f"{name}_numpy"].result))))
            for name in ("nvso", "ekf")
        },
        "problems": problems,
    }


def report(r: dict) -> str:
    lines = [f"{r['manoeuvre']}, {r['vehicles']} vehicles x {r['samples']} samples (jit(vmap(scan))):"]
    for name, o in r["observers"].items():
        lines.append(
            f"  {name:12s} {format_range(o['step_seconds'], '.3g', ' s')} per step of the batch, "
            f"{format_range(o['vehicle_step_seconds'], '.3g', ' s')} per vehicle-step "
            + ("(no compile)" if o["compile_s"] is None else f"(compile {o['compile_s']:.1f} s)")
            + f"; sideslip RMS {o['beta_rms_deg_median']:.3f} deg (median)"
        )
    lines.append(f"  EKF / NVSO cost {format_range(r['ekf_over_nvso'])}; "
                 f"EKF (Bierman) / NVSO {format_range(r['ekf_bierman_over_nvso'])}")  # fmt: skip
    diff = r["numpy_max_difference_deg"]
    lines.append(f"  NumPy loop / jaxobs: NVSO {format_range(r['numpy_over_nvso'])}, "
                 f"EKF {format_range(r['numpy_over_ekf'])}; "
                 f"largest sideslip differences {diff['nvso']:.1e} and {diff['ekf']:.1e} deg")  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    parser.add_argument("--vehicles", type=int, default=1024)
    parser.add_argument("--samples", type=int, default=800)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    results = measure_costs(args.vehicles, args.samples, args.rounds)
    meta = {"rounds": args.rounds, "platform": platform.platform(), "device": str(jax.devices()[0]),
            "jax": jax.__version__}  # fmt: skip
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "sideslip.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    print(report(results))
    print(f"wrote {out / 'sideslip.json'}")
    return results


if __name__ == "__main__":
    main()
