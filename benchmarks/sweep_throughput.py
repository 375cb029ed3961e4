"""Configurations per second of the default ``jaxobs sweep`` evaluation against a NumPy/SciPy + python-control
peer doing the same work, and the scaling over 1, 2 and 4 host devices.

Per configuration (both sides): the true plant by exact ZOH with fractional dead time, the loop transfer
function and closed-loop matrix of eq. 59/65, its spectral radius, gain/phase/stability margins, and a 2500-step
closed loop under the Example 1 disturbance with sensor noise, scored by the RMS force error. What every
configuration shares (the controller designs, the desired response, the disturbance) is computed once, before
the timing, on both sides.

jaxobs: ``jit(vmap(sample + evaluate))`` of the default sweep over ``--configs`` configurations, compiled once
(compile time reported). The peer is batched over the configurations wherever NumPy batches: the true plants
from one ``scipy.linalg.expm`` call on the stacked (N, 3, 3) ZOH blocks, the loop and closed-loop matrices by
broadcasting, the spectral radii from one ``numpy.linalg.eigvals`` call on the stacked closed loops, and the
closed loop as one 2500-step time loop over (N, ...) arrays (the linear closed loop's state update as one
stacked ``numpy.matmul`` per step). ``control.stability_margins`` has no batched form: it runs configuration by
configuration on the first ``--peer-margin-configs`` configurations and is extrapolated to N (a loop costs N
times one). A check on a few configurations compares the peer's spectral radius, RMS error (same noise) and
margins with jaxobs's (stored in the JSON).

Timing (``benchmarks/_timing.py``): ``--rounds`` interleaved rounds, each running jaxobs, the batched peer and
the peer's margin loop once; times, throughputs and the paired ratio jaxobs / peer are reported as the median
and [min, max] over the rounds.

Device scaling reruns the jaxobs measurement in subprocesses with
``XLA_FLAGS=--xla_force_host_platform_device_count=D`` for two workloads, each through the sweep engine's
compiled, sharded step (``jaxobs.sweep``; Parquet writing excluded), ``--rounds`` timed passes per subprocess
(compiled once): the default evaluation (its LAPACK calls in the blocks of ``jaxobs.batching``) and its
closed-loop simulation alone (true plants from a table discretised beforehand), both sharded over the D devices.
Forced host devices share the machine's cores, so more devices than cores cannot help; the subprocesses run one
after the other (not interleaved).

    python benchmarks/sweep_throughput.py --out DIR [--configs 2000] [--rounds 7] [--peer-margin-configs 40]

Writes ``DIR/sweep_throughput.json`` and ``DIR/sweep_throughput.png``.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
from _timing import Timed, format_range, paired_ratio, summary, time_interleaved  # noqa: E402

from jaxobs.observers.linear import linear_controller  # noqa: E402
from jaxobs.papers.cortesao import force_sweep as fr  # noqa: E402
from jaxobs.papers.cortesao.force_control import EXAMPLE1  # noqa: E402
from jaxobs.plants import force_plant  # noqa: E402
from jaxobs.stability import closed_loop_matrix, spectral_radius  # noqa: E402
from jaxobs.sweep import config_key  # noqa: E402

TARGET = 100.0
PLANT_TABLE = 1000  # true plants of the simulation-only workload
CHECK_CONFIGS = 24  # configurations of the peer-vs-jaxobs agreement check


# ---------------------------------------------------------------------------------------------
# jaxobs


def _sampled(config: dict, configs: int):
    """``(sampler, evaluate, designs, params of configurations 0..configs-1 as NumPy arrays)``."""
    sampler, evaluate, _, designs = fr.make_sweep(config)
    params = jax.jit(jax.vmap(lambda i: sampler(config_key(config["seed"], i), i)))(jnp.arange(configs))
    return sampler, evaluate, designs, jax.tree.map(np.asarray, params)


def prepare_jaxobs(config: dict, configs: int, margins: bool = True):
    """``jit(vmap(sample + evaluate))`` over the indices ``0..configs-1`` (what each sweep chunk computes).
    ``margins=False``: the same evaluation without the margins (spectral radius of the closed-loop matrix and the
    closed loop only), the part the NumPy peer batches."""
    sampler, evaluate, _, designs = fr.make_sweep(config)
    if not margins:
        n_delay, closed_loop, h = fr._timing(config)[1], fr.tracking(config), EXAMPLE1.h

        def evaluate(p):
            ctrl = jax.tree.map(lambda M: M[p["design"]], designs.controller)
            true = force_plant(p["stiffness"], p["time_constant"], h, p["dead_time_samples"] * h, n_delay=n_delay)
            rho = spectral_radius(closed_loop_matrix(true, linear_controller, ctrl))
            return {"spectral_radius": rho, "rms_force_error": closed_loop(true, ctrl, p["noise_seed"])[1]}

    def evaluate_all(indices):
        return jax.vmap(lambda i: evaluate(sampler(config_key(config["seed"], i), i)))(indices)

    return evaluate_all, (jnp.arange(configs),)


def _simulation_only(config: dict):
    """The default sweep's 2500-step closed loop and RMS force error alone, with the true plants drawn from a table
    discretised beforehand: the workload without the LAPACK calls (``c2d``, eigenvalues) and margins."""
    sampler, _, _, designs = fr.make_sweep(config)
    n_delay, closed_loop = fr._timing(config)[1], fr.tracking(config)
    params = jax.vmap(lambda i: sampler(config_key(0, i), i))(jnp.arange(PLANT_TABLE))
    plants = jax.jit(
        jax.vmap(
            lambda p: force_plant(
                p["stiffness"], p["time_constant"], EXAMPLE1.h, p["dead_time_samples"] * EXAMPLE1.h, n_delay=n_delay
            )
        )
    )(params)

    def sample(key, index):
        return {"design": index % len(designs), "plant": (index // len(designs)) % PLANT_TABLE,
                "noise_seed": jax.random.bits(key, (), jnp.uint32)}  # fmt: skip

    def evaluate(p):
        ctrl = jax.tree.map(lambda M: M[p["design"]], designs.controller)
        true = jax.tree.map(lambda M: M[p["plant"]], plants)
        return {"rms_force_error": closed_loop(true, ctrl, p["noise_seed"])[1]}

    return sample, evaluate


def engine_rate(configs: int, chunk: int, workload: str, rounds: int) -> dict:
    """Configurations per second of the sweep engine's compiled, sharded step on ``workload`` ("default" or
    "simulation") over ``configs`` configurations, ``rounds`` passes after one compilation (no Parquet)."""
    from jaxobs.sweep import _compile

    config = fr.SCENARIO.validate({"chunk_size": chunk})
    if workload == "default":
        sampler, evaluate, _, _ = fr.make_sweep(config)
    else:
        sampler, evaluate = _simulation_only(config)

    def row(index):
        return evaluate(sampler(config_key(0, index), index))

    start = time.perf_counter()
    devices = jax.devices()
    compiled, sharding = _compile(row, devices, chunk)
    compile_s = time.perf_counter() - start
    per_call = len(devices) * chunk
    batches = [np.arange(s, s + per_call, dtype=np.int32) % configs for s in range(0, configs, per_call)]
    seconds = []
    for _ in range(rounds):
        start = time.perf_counter()
        for batch in batches:
            jax.block_until_ready(compiled(jax.device_put(batch, sharding)))
        seconds.append(time.perf_counter() - start)
    done = len(batches) * per_call
    return {
        "configs": done,
        "devices": jax.device_count(),
        "devices_used": len(devices),
        "compile_s": compile_s,
        "configs_per_second": summary([done / s for s in seconds]),
    }


# ---------------------------------------------------------------------------------------------
# The NumPy / SciPy / python-control peer


class NumpyPeer:
    """The default sweep's evaluation batched over configurations in NumPy/SciPy, margins by python-control.

    The shared work (designs from jaxobs, desired response, disturbance, reference) is done here once."""

    def __init__(self, config: dict, designs):
        self.config = config
        h, sim = EXAMPLE1.h, config["simulation"]
        self.steps, self.n_delay = fr._timing(config)
        reference, desired, disturbance = fr._signals(config, self.steps)()
        self.r = float(reference[0])
        self.desired, self.disturbance = np.asarray(desired), np.asarray(disturbance)
        self.std = float(np.sqrt(sim["sensor_noise"]))
        self.table = jax.tree.map(np.asarray, designs.controller)
        self.h = h

    def true_plants(self, Ks, Tp, dead_samples):
        """Stacked delay-augmented plants ``(Phi (N, n, n), Gamma (N, n, 1))`` by exact ZOH with fractional dead
        time (Cortesão 2006 eq. 11-18), state ``[x', u_{k-n_delay}, ..., u_{k-1}]``."""
        h, n_delay, N = self.h, self.n_delay, Ks.size
        tau = dead_samples * h
        d = np.maximum(np.ceil(tau / h - 1e-9), 1).astype(int)  # the input of lag d enters through Gamma_0
        frac = tau - (d - 1) * h

        def zoh(t):
            M = np.zeros((N, 3, 3))
            M[:, 0, 1], M[:, 1, 1], M[:, 1, 2] = 1.0, -1.0 / Tp, Ks / Tp
            E = scipy.linalg.expm(M * t[:, None, None])
            return E[:, :2, :2], E[:, :2, 2]

        Phi1, _ = zoh(np.full(N, h))
        Ea, G0 = zoh(h - frac)
        _, Gf = zoh(frac)
        G1 = np.einsum("bij,bj->bi", Ea, Gf)
        n = 2 + n_delay
        Phi, Gamma = np.zeros((N, n, n)), np.zeros((N, n, 1))
        Phi[:, :2, :2] = Phi1
        slots = np.arange(n_delay - 1)
        Phi[:, 2 + slots, 3 + slots] = 1.0
        Gamma[:, -1, 0] = 1.0
        rows = np.arange(N)
        for lag, G in ((d, G0), (d + 1, G1)):  # u_{k-lag} sits in slot 2 + n_delay - lag (lag 1: u_k itself)
            direct = lag == 1
            Gamma[rows[direct], :2, 0] += G[direct]
            cols = 2 + n_delay + 1 - lag
            Phi[rows[~direct], :2, cols[~direct]] += G[~direct]
        return Phi, Gamma

    def loops(self, p):
        """Loop transfer functions at the plant input (eq. 65) ``(A, B, C)`` and the closed-loop matrices."""
        Phi, Gamma = self.true_plants(p["stiffness"], p["time_constant"], p["dead_time_samples"])
        N, n = Phi.shape[:2]
        obs = self.table.estimator
        Pn, Gn, Cn, K, L = (M[p["design"]] for M in (obs.Phi, obs.Gamma, obs.C, obs.K, self.table.L))
        m = Pn.shape[-1]
        KC = K[:, :, :1]  # K C with C = [1, 0, ...]: the first column of the (N, m, n) product
        observer = (np.eye(m) - K @ Cn) @ (Pn - Gn @ L)
        A = np.zeros((N, n + m, n + m))
        A[:, :n, :n] = Phi
        A[:, n:, :n] = KC @ Phi[:, :1, :]
        A[:, n:, n:] = observer
        B = np.concatenate([Gamma, KC @ Gamma[:, :1, :]], axis=1)
        C = np.concatenate([np.zeros((N, 1, n)), L], axis=2)
        return (A, B, C), A - B @ C, (Phi, Gamma, Pn, Gn, Cn, K, L)

    def evaluate(self, p, noise=None):
        """Spectral radius and RMS force error of every configuration of ``p`` (a dict of (N,) arrays)."""
        _, closed, (Phi, Gamma, Pn, Gn, Cn, K, L) = self.loops(p)
        rho = np.abs(np.linalg.eigvals(closed)).max(axis=-1)
        N, n, m = Phi.shape[0], Phi.shape[1], Pn.shape[-1]
        if noise is None:
            noise = self.std * np.random.default_rng(0).standard_normal((N, self.steps))
        # the linear closed loop in z_k = [x_k; x_hat_{k-1}; u_{k-1}]:
        #   x_hat_k = F x_hat_{k-1} + G u_{k-1} + K (C x_k + v_k),  u_k = r - L x_hat_k,
        #   x_{k+1} = Phi x_k + Gamma (u_k + d_k)
        IKC = np.eye(m) - K @ Cn
        F, G = IKC @ Pn, IKC @ Gn
        KC = np.zeros((N, m, n))
        KC[:, :, 0] = K[:, :, 0]
        xhat_rows = np.concatenate([KC, F, G], axis=2)  # (N, m, n + m + 1)
        u_row = -L @ xhat_rows  # (N, 1, n + m + 1), plus r - L K v_k
        x_rows = np.concatenate([Phi, np.zeros((N, n, m + 1))], axis=2) + Gamma @ u_row
        M = np.concatenate([x_rows, xhat_rows, u_row], axis=1)
        LK = (L @ K)[:, 0, 0]
        noise_in = np.concatenate([-Gamma[:, :, 0] * LK[:, None], K[:, :, 0], -LK[:, None]], axis=1)  # times v_k
        ref_in = np.concatenate([Gamma[:, :, 0] * self.r, np.zeros((N, m)), np.full((N, 1), self.r)], axis=1)
        dist_in = np.concatenate([Gamma[:, :, 0], np.zeros((N, m + 1))], axis=1)
        z = np.zeros((N, n + m + 1))
        err = np.zeros(N)
        with np.errstate(invalid="ignore", over="ignore"):  # unstable loops overflow to inf, as in jaxobs
            for k in range(self.steps):
                err += (z[:, 0] - self.desired[k]) ** 2
                inputs = ref_in + dist_in * self.disturbance[k] + noise_in * noise[:, k : k + 1]
                z = (M @ z[:, :, None])[:, :, 0] + inputs
            rms = np.sqrt(err / self.steps)
        return {"spectral_radius": rho, "rms_force_error": np.where(np.isfinite(rms), rms, np.inf)}

    def margins(self, p, count: int):
        """``control.stability_margins`` (gain, phase and stability margins) of the first ``count`` loops, one at
        a time: python-control has no batched form."""
        import control

        part = {k: v[:count] for k, v in p.items()}
        (A, B, C), _, _ = self.loops(part)
        out = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for i in range(count):
                out.append(control.stability_margins(control.ss(A[i], B[i], C[i], 0, self.h))[:3])
        return np.array(out)


def agreement(config: dict, evaluate, peer: NumpyPeer, params: dict, count: int = CHECK_CONFIGS) -> dict:
    """Peer vs jaxobs on the first ``count`` configurations, the same noise on both sides."""
    part = {k: v[:count] for k, v in params.items()}
    ours = jax.tree.map(np.asarray, jax.jit(jax.vmap(evaluate))(jax.tree.map(jnp.asarray, part)))
    steps = peer.steps
    noise = np.stack([peer.std * np.asarray(jax.random.normal(jax.random.PRNGKey(s), (steps,)))
                      for s in part["noise_seed"]])  # fmt: skip
    theirs = peer.evaluate(part, noise)
    gm_pm_sm = peer.margins(part, count)
    stable = ours["stable"]

    def rel(a, b, mask):
        a, b = np.asarray(a)[mask], np.asarray(b)[mask]
        ok = np.isfinite(a) & np.isfinite(b)
        return float(np.max(np.abs(a[ok] - b[ok]) / np.abs(b[ok]))) if ok.any() else None

    return {
        "configs": count,
        "stable": int(stable.sum()),
        "spectral_radius_max_rel_diff": rel(theirs["spectral_radius"], ours["spectral_radius"], np.ones(count, bool)),
        "rms_force_error_max_rel_diff_stable": rel(theirs["rms_force_error"], ours["rms_force_error"], stable),
        "gain_margin_max_rel_diff_stable": rel(gm_pm_sm[:, 0], ours["gain_margin"], stable),
        "phase_margin_max_rel_diff_stable": rel(gm_pm_sm[:, 1], ours["phase_margin"], stable),
        "note": "python-control picks its own crossover where a loop has several with equal |margin|; the RMS "
        "errors use the same noise on both sides",
    }


# ---------------------------------------------------------------------------------------------


def measure(configs: int, rounds: int, margin_configs: int) -> dict:
    config = fr.SCENARIO.validate()
    _, evaluate, designs, params = _sampled(config, configs)
    peer = NumpyPeer(config, designs)
    check = agreement(config, evaluate, peer, params)
    margin_configs = min(margin_configs, configs)
    entries = {
        "jaxobs": (lambda: prepare_jaxobs(config, configs), True, 1.0),
        "jaxobs_no_margins": (lambda: prepare_jaxobs(config, configs, margins=False), True, 1.0),
        "peer_batched": (lambda: (lambda: peer.evaluate(params), ()), False, 1.0),
        "peer_margins": (lambda: (lambda: peer.margins(params, margin_configs), ()), False, configs / margin_configs),
    }
    timings, _ = time_interleaved(entries, rounds, required=tuple(entries))
    batched, margins = timings["peer_batched"], timings["peer_margins"]
    total = Timed([a + b for a, b in zip(batched.seconds, margins.seconds, strict=True)], None, None)
    records = {name: t.record(configs, "configurations/s") for name, t in timings.items()}
    records["peer_margins"]["extrapolated_from_configs"] = margin_configs
    return {
        "configs": configs,
        "rounds": rounds,
        "full": {
            "description": "the default evaluation: plants, spectral radius, margins, closed loop",
            "jaxobs": records["jaxobs"],
            "peer": total.record(configs, "configurations/s"),
            "peer_parts": {
                "batched: plants, eigenvalues, closed loop": records["peer_batched"],
                "python-control margins, one loop at a time": records["peer_margins"],
            },  # fmt: skip
            "ratio": paired_ratio(timings["jaxobs"], total),
        },
        "no_margins": {
            "description": "without the margins: plants, spectral radius, closed loop (all batched in NumPy)",
            "jaxobs": records["jaxobs_no_margins"],
            "peer": records["peer_batched"],
            "ratio": paired_ratio(timings["jaxobs_no_margins"], batched),
        },
        "agreement": check,
    }


def device_scaling(configs: int, chunk: int, rounds: int, counts=(1, 2, 4)) -> dict:
    """``{workload: {devices: record}}``, each in a subprocess with ``devices`` forced host devices."""
    out = {}
    for workload in ("default", "simulation"):
        out[workload] = {}
        for devices in counts:
            env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu")
            code = (
                "import json, sys; sys.path.insert(0, 'benchmarks'); import sweep_throughput as s; "
                f"print(json.dumps(s.engine_rate({configs}, {chunk}, {workload!r}, {rounds})))"
            )
            run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
            out[workload][str(devices)] = json.loads(run.stdout.strip().splitlines()[-1])
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--configs", type=int, default=2000, help="configurations per round (one sweep chunk)")
    parser.add_argument("--rounds", type=int, default=7, help="interleaved timed rounds (median and range)")
    parser.add_argument("--peer-margin-configs", type=int, default=40, help="python-control margins timed on these")
    parser.add_argument("--scaling-configs", type=int, default=4000, help="configurations per device-scaling pass")
    parser.add_argument("--no-scaling", action="store_true")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results = measure(args.configs, args.rounds, args.peer_margin_configs)
    results["target"] = {"min_ratio": TARGET, "met": bool(results["full"]["ratio"]["median"] >= TARGET)}
    results["platform"] = {"jax": jax.__version__, "backend": jax.default_backend(), "cpu_count": os.cpu_count()}
    if not args.no_scaling:
        results["device_scaling"] = device_scaling(args.scaling_configs, 1000, args.rounds)
    (args.out / "sweep_throughput.json").write_text(json.dumps(results, indent=2) + "\n")
    _print(results)
    _plot(results, args.out / "sweep_throughput.png")
    return results


def _print(results: dict) -> None:
    print(f"{results['configs']} configurations, {results['rounds']} interleaved rounds: median [min, max]")
    for key in ("full", "no_margins"):
        row = results[key]
        ours, peer = row["jaxobs"], row["peer"]
        print(f"{row['description']}:")
        print(f"   jaxobs: {format_range(ours['throughput'], '.4g')} configs/s (compile {ours['compile_s']:.1f} s)")
        print(f"   NumPy/SciPy peer: {format_range(peer['throughput'], '.4g')} configs/s")
        for part, rec in row.get("peer_parts", {}).items():
            print(f"      {part}: {format_range(rec['seconds'], '.3g')} s per round")
        print(f"   ratio {format_range(row['ratio'], '.3g', 'x')}")
    verdict = "MET" if results["target"]["met"] else "MISSED"
    print(f"target >= {TARGET:g}x on the full evaluation (median): {verdict}")
    check = results["agreement"]
    print(
        f"agreement on {check['configs']} configurations ({check['stable']} stable): spectral radius "
        f"{check['spectral_radius_max_rel_diff']:.2g}, RMS error {check['rms_force_error_max_rel_diff_stable']:.2g}, "
        f"gain margin {check['gain_margin_max_rel_diff_stable']:.2g}, phase margin "
        f"{check['phase_margin_max_rel_diff_stable']:.2g} (max relative differences)"
    )
    for workload, rates in results.get("device_scaling", {}).items():
        base = rates["1"]["configs_per_second"]["median"]
        for devices, rec in rates.items():
            rate = rec["configs_per_second"]
            print(
                f"  {workload}, {devices} host device(s) ({rec['devices_used']} used): "
                f"{format_range(rate, '.4g')} configs/s ({rate['median'] / base:.2f}x of 1 device, medians)"
            )


def _yerr(summaries: list) -> list:
    """Matplotlib error bars from the median to the [min, max] range of each summary."""
    return [[s["median"] - s["min"] for s in summaries], [s["max"] - s["median"] for s in summaries]]


def _plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot, save_figure

    scaling = results.get("device_scaling", {})
    fig, axes = pyplot().subplots(1, 2 if scaling else 1, figsize=(11 if scaling else 6, 4.6), squeeze=False)
    a = axes[0, 0]
    x = np.arange(2)
    for offset, (name, color) in enumerate((("jaxobs", "tab:green"), ("peer", "tab:gray"))):
        recs = [results[key][name]["throughput"] for key in ("full", "no_margins")]
        label = "jaxobs" if name == "jaxobs" else "NumPy/SciPy (+ python-control margins)"
        a.bar(x + (offset - 0.5) * 0.4, [r["median"] for r in recs], 0.4, yerr=_yerr(recs), capsize=4,
              color=color, label=label)  # fmt: skip
    ratios = [results[key]["ratio"] for key in ("full", "no_margins")]
    a.set_xticks(x, [f"{t}\n{r['median']:.3g}x [{r['min']:.3g}, {r['max']:.3g}]"
                     for t, r in zip(("default evaluation", "without margins"), ratios, strict=True)])  # fmt: skip
    a.set_yscale("log")
    a.set_ylabel("configurations / s (median, bar: [min, max])")
    a.set_xlabel("ratio jaxobs / peer, paired by round: median [min, max]", fontsize=9)
    a.legend(fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.08), ncols=2)  # above the bars
    a.set_title(f"{results['rounds']} interleaved rounds of {results['configs']} configurations", fontsize=10)
    for workload, rates in scaling.items():
        b = axes[0, 1]
        used = sorted({r["devices_used"] for r in rates.values()})
        label = f"{workload} (devices used: {', '.join(map(str, used))})"
        devices = [int(d) for d in rates]
        rs = [r["configs_per_second"] for r in rates.values()]
        b.errorbar(devices, [r["median"] for r in rs], yerr=_yerr(rs), fmt="o-", capsize=4, label=label)
        b.set_xticks(devices)
        b.legend(fontsize=8)
        b.set_xlabel("forced host devices")
        b.set_ylabel("configurations / s (median, bar: [min, max])")
        b.set_title(f"device scaling ({results['platform']['cpu_count']} CPU cores)", fontsize=10)
    save_figure(fig, path.parent, path.stem)


if __name__ == "__main__":
    main()
