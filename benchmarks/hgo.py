"""The modified high-gain observer sweep (Grip 2010, ch. 6) against a NumPy RK4 loop, and the sympy SCB timings of
the worked examples of Grip 2010, section 7.5, next to the printed Maple 12 times (section 7.6).

Throughput: configurations per second of the ``dc-motor-hgo`` sweep evaluation (``jaxobs sweep --config
tuning/dc_motor_hgo_sweep.toml``; per configuration the LuGre plant with RK4 at 1e-4 s, observer 1 (6.3) with the
Proposition 6.2 law and projection, the cascaded observer 2 and the pure ESO, each sampled at 1 kHz with 10 RK4
substeps): jaxobs ``jit(vmap(sample + evaluate))`` over ``--configs`` configurations, compiled once (compile time
reported), against a NumPy peer doing the same arithmetic batched over the configurations (one Python loop over
the samples, substeps and RK4 stages, every operation on (N, ...) arrays; the derivatives of g written out by
hand where jaxobs uses autodiff). A check on the same configurations compares the RMS errors of both (stored in the
JSON). ``--duration`` shortens the simulated horizon (default 2 s; the sweep's default is 20 s).

SCB timings: :func:`jaxobs.scb.scb` on the five cases of ``grip2010-scb`` (exact sympy arithmetic, symbols for the
vehicle and motor parameters), interleaved rounds, next to the printed Maple 12 CPU times (another machine and
system: a context, not a comparison).

    python benchmarks/hgo.py --out DIR [--configs 32] [--duration 2.0] [--rounds 5]

Writes ``DIR/hgo.json`` and prints a table.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from _timing import format_range, paired_ratio, time_interleaved  # noqa: E402

from jaxobs.observers.hgo import hgo_gains  # noqa: E402
from jaxobs.papers.grip2010 import dc_motor as dc  # noqa: E402
from jaxobs.papers.grip2010 import dc_motor_sweep as sweep  # noqa: E402
from jaxobs.papers.grip2010 import scb as grip_scb  # noqa: E402
from jaxobs.scb import scb  # noqa: E402
from jaxobs.sweep import config_key  # noqa: E402


def _config(duration: float) -> dict:
    return sweep.SCENARIO.validate({"simulation": {"duration": duration, "rms_start": duration / 2}})


def _draws(config: dict, n: int):
    """The first ``n`` configurations of the sweep (the sampler's draws, the same on both sides)."""
    sampler, _, total, _ = sweep.make_sweep(config)
    rows = [sampler(config_key(config["seed"], i % total), i % total) for i in range(n)]
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *rows)


def ours(config: dict):
    _, evaluate, _, _ = sweep.make_sweep(config)
    return jax.vmap(evaluate)


def _peer_inputs(draws, duration: float):
    """Noise (generated with JAX, as the sweep does) and the per-configuration gains, outside the timing."""
    steps = int(round(duration / dc.DT))
    noise = np.asarray(
        jax.vmap(lambda s: jax.random.normal(jax.random.key(s), (steps, 1)))(draws["noise_seed"])[:, :, 0]
    )
    A, _, E, C = dc.matrices(dc.TABLE_6_1["sigma_1"])
    nominal = dc.matrices(0.0)
    d = (nominal[0], nominal[2], nominal[3])
    g1 = hgo_gains(A, E, C, dc.POLES_1, 1.0, design=d)
    g2 = hgo_gains(A, E, C, dc.POLES_2, 1.0, design=d, extended=False)
    eps = np.asarray(draws["eps"])
    K1 = np.stack([np.asarray(g1.at(e))[:, 0] for e in eps])
    K2 = np.stack([np.asarray(g2.at(e))[:, 0] for e in eps])
    return noise, K1, K2, np.asarray(draws["sigma"]), np.asarray(draws["alpha_0"])


def peer(noise, K1, K2, sigma, alpha_0, duration: float, rms_start: float):
    """The sweep's evaluation in NumPy, batched over the N configurations."""
    p = dc.TABLE_6_1
    A, B, E, _ = (np.asarray(M) for M in dc.matrices(p["sigma_1"]))
    s0, a1, w0, kappa = p["sigma_0"], p["alpha_1"], p["omega_0"], dc.KAPPA
    lo, hi = dc.THETA_SET
    h = dc.DT / dc.SUBSTEPS
    steps = noise.shape[1]

    def lin(x, u, phi):  # A x + B u + E phi over (N, 3)
        return x @ A.T + u[:, None] * B[:, 0] + phi[:, None] * E[:, 0]

    def zeta(w, a0):
        return a0 + a1 * np.exp(-((w / w0) ** 2))

    def smooth(w):
        inside = np.abs(w) <= kappa
        return np.where(inside, w**2 / (2 * kappa) + kappa / 2, np.abs(w)), np.where(inside, w / kappa, np.sign(w))

    def g_and_grads(x, th):
        a, da = smooth(x[:, 1])
        z = zeta(x[:, 1], th)
        dz = a1 * np.exp(-((x[:, 1] / w0) ** 2)) * (-2 * x[:, 1] / w0**2)
        g = s0 * x[:, 2] * a / z
        gx = np.stack([0 * g, s0 * x[:, 2] * (da * z - a * dz) / z**2, s0 * a / z], axis=1)
        return g, gx, -g / z

    def plant(x, t):
        phi = s0 * x[:, 2] * np.abs(x[:, 1]) / zeta(x[:, 1], alpha_0)
        return lin(x, np.full(x.shape[0], np.sin(np.pi * t)), phi)

    def observer(s, u, y):
        xh, zz, th, x2, xe, ze = s
        innov = y - xh[:, 0]
        g, gx, gth = g_and_grads(xh, th)
        phi = g + zz
        a, _ = smooth(xh[:, 1])
        active = np.abs(phi) >= dc.THRESHOLD
        safe = np.where(active, phi, dc.THRESHOLD)
        rate = np.where(active, s0 * xh[:, 2] * a / safe - (zeta(xh[:, 1], 0.0)) - th, 0.0)
        uu = (2 * th - lo - hi) / (hi - lo)  # Box(order 4): P = u^8 - 1, projected with epsilon = 0.05
        P, dP = uu**8 - 1, 8 * uu**7 * 2 / (hi - lo)
        rate = np.where((P > 0) & (dP * rate > 0), rate * (1 - np.minimum(1, P / 0.05)), rate)
        kx = K1[:, :3] * innov[:, None]
        dxh = lin(xh, u, phi) + kx
        dz = K1[:, 3] * innov - gth * rate - np.sum(gx * kx, axis=1)
        g2 = s0 * x2[:, 2] * np.abs(x2[:, 1]) / zeta(x2[:, 1], th)  # observer 2: the exact |omega|
        dx2 = lin(x2, u, g2) + K2 * (y - x2[:, 0])[:, None]
        ie = y - xe[:, 0]
        dxe = lin(xe, u, ze) + K1[:, :3] * ie[:, None]
        return dxh, dz, rate, dx2, dxe, K1[:, 3] * ie

    def rk4(f, s, *args):
        add = lambda s, k, c: tuple(a + c * b for a, b in zip(s, k, strict=True))  # noqa: E731
        k1 = f(s, *args)
        k2 = f(add(s, k1, h / 2), *args)
        k3 = f(add(s, k2, h / 2), *args)
        k4 = f(add(s, k3, h), *args)
        return tuple(a + h / 6 * (b + 2 * c + 2 * d + e) for a, b, c, d, e in zip(s, k1, k2, k3, k4, strict=True))

    n = noise.shape[0]
    x = np.zeros((n, 3))
    s = (np.zeros((n, 3)), np.zeros(n), np.ones(n), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n))
    err = np.zeros((3, n))
    count = 0
    y_prev = None
    for k in range(steps):
        t = k * dc.DT
        if k:
            u = np.full(n, np.sin(np.pi * (t - dc.DT)))
            for _ in range(dc.SUBSTEPS):
                s = rk4(observer, s, u, y_prev)
        y_prev = x[:, 0] + sigma * noise[:, k]
        if t > rms_start:
            count += 1
            err += np.stack([x[:, 1] - s[0][:, 1], x[:, 1] - s[3][:, 1], x[:, 1] - s[4][:, 1]]) ** 2
        for i in range(dc.SUBSTEPS):  # the plant to the next sample
            x = _plant_rk4(plant, x, t + i * h, h)
    return np.sqrt(err / count)


def _plant_rk4(f, x, t, h):
    k1 = f(x, t)
    k2 = f(x + h / 2 * k1, t + h / 2)
    k3 = f(x + h / 2 * k2, t + h / 2)
    k4 = f(x + h * k3, t + h)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def throughput(n: int, duration: float, rounds: int) -> dict:
    config = _config(duration)
    draws = _draws(config, n)
    inputs = _peer_inputs(draws, duration)
    start = config["simulation"]["rms_start"]
    entries = {
        "jaxobs": (lambda: (ours(config), (draws,)), True, 1.0),
        "numpy": (lambda: (lambda: peer(*inputs, duration, start), ()), False, 1.0),
    }
    timings, problems = time_interleaved(entries, rounds, required=("jaxobs", "numpy"))
    mine = timings["jaxobs"].result["rms_omega"]
    mine = np.stack([np.asarray(mine[k]) for k in ("observer1", "observer2", "pure_eso")])
    theirs = np.asarray(timings["numpy"].result)
    return {
        "configs": n,
        "duration_s": duration,
        "jaxobs": timings["jaxobs"].record(n, "configs/s"),
        "numpy": timings["numpy"].record(n, "configs/s"),
        "speedup_jaxobs_over_numpy": paired_ratio(timings["jaxobs"], timings["numpy"]),
        "max_relative_difference_rms": float(np.max(np.abs(mine - theirs) / np.abs(theirs))),
        "problems": problems,
    }


def scb_timings(rounds: int) -> dict:
    systems = grip_scb.systems()
    entries = {name: ((lambda s=systems[name]: (lambda: scb(*s), ())), False, 1.0) for name in grip_scb.CASES}
    timings, _ = time_interleaved(entries, rounds, required=tuple(grip_scb.CASES))
    return {
        name: {
            "seconds": timings[name].record(1, "calls/s")["seconds"],
            "maple_printed_s": grip_scb.MAPLE_SECONDS[name],
        }
        for name in grip_scb.CASES
    }


def report(results: dict) -> str:
    t = results["throughput"]
    lines = [
        f"dc-motor-hgo sweep, {t['configs']} configurations of {t['duration_s']} s:",
        f"  jaxobs {format_range(t['jaxobs']['throughput'])} configs/s (compile {t['jaxobs']['compile_s']:.1f} s)",
        f"  numpy  {format_range(t['numpy']['throughput'])} configs/s",
        f"  jaxobs / numpy speed-up {format_range(t['speedup_jaxobs_over_numpy'])}; "
        f"RMS agreement {t['max_relative_difference_rms']:.1e} relative",
        "SCB (sympy, exact) vs printed Maple 12:",
    ]
    for name, r in results["scb"].items():
        lines.append(f"  {name:22s} {format_range(r['seconds'], '.3f', ' s')}   Maple {r['maple_printed_s']} s")
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    parser.add_argument("--configs", type=int, default=32)
    parser.add_argument("--duration", type=float, default=2.0)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    results = {
        "throughput": throughput(args.configs, args.duration, args.rounds),
        "scb": scb_timings(args.rounds),
    }
    meta = {"rounds": args.rounds, "platform": platform.platform(), "device": str(jax.devices()[0]),
            "jax": jax.__version__}  # fmt: skip
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "hgo.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    print(report(results))
    print(f"wrote {out / 'hgo.json'}")
    return results


if __name__ == "__main__":
    main()
