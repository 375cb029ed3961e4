"""Configurations per second of the default ``jaxobs sweep`` evaluation against a NumPy + python-control
loop doing the same work per configuration, and the scaling over 1, 2 and 4 host devices.

Per configuration (both sides): the true plant by exact ZOH with fractional dead time, the loop
transfer function and closed-loop matrix of eq. 59/65, its spectral radius, gain/phase/stability
margins, and a 2500-step closed loop under the Example 1 disturbance with sensor noise, scored by the
RMS force error. The controller designs (steady-state gains) are computed once by jaxobs and shared.

jaxobs runs through :func:`jaxobs.sweep.run_sweep` (Parquet output included, compilation excluded).
The peer loops over a few configurations (``--peer-configs``) with ``scipy.linalg.expm``,
``numpy.linalg.eigvals``, ``control.stability_margins`` and a Python time loop, and is extrapolated.
Device scaling reruns the jaxobs measurement in subprocesses with
``XLA_FLAGS=--xla_force_host_platform_device_count=D`` for two workloads: the default evaluation, which the
engine computes on one CPU device whatever D (it calls jaxlib's batched LAPACK kernels, which can deadlock
several CPU devices; see ``jaxobs.sweep``), and its LAPACK-free closed-loop simulation alone (true plants
from a table discretised beforehand), which shards over the D devices. Forced host devices share the
machine's cores, so more devices than cores cannot help.

    python benchmarks/sweep_throughput.py --out DIR [--configs 8000] [--peer-configs 20]

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
import tempfile  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402

from jaxobs.lti import n_delay_slots  # noqa: E402
from jaxobs.papers import force_robustness as fr  # noqa: E402
from jaxobs.papers.force_control import (  # noqa: E402
    EXAMPLE1,
    example1_disturbance,
    force_plant,
    nominal_design,
    reference_gain,
)
from jaxobs.sweep import config_key, run_sweep  # noqa: E402

TARGET = 100.0
PLANT_TABLE = 1000  # true plants of the simulation-only workload


def _simulation_only(config: dict):
    """A LAPACK-free workload for the device scaling: the default sweep's 2500-step closed loop and RMS force
    error, with the true plants drawn from a table discretised beforehand (the full evaluation's ``c2d`` and
    eigenvalues call LAPACK kernels, which make the engine compute on one CPU device; see ``jaxobs.sweep``)."""
    sampler, _, _, designs = fr.make_sweep(config)
    n_delay, closed_loop = fr._scenario(config)[1], fr.tracking(config)
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


def jaxobs_rate(configs: int, chunk: int, workload: str = "default") -> dict:
    """Configurations per second of ``run_sweep`` on ``workload`` ("default" or "simulation")."""
    config = fr.validate_config({"chunk_size": chunk})
    if workload == "default":
        sampler, evaluate, _, _ = fr.make_sweep(config)
    else:
        sampler, evaluate = _simulation_only(config)
    with tempfile.TemporaryDirectory() as tmp:
        result = run_sweep(sampler, evaluate, configs, tmp, chunk_size=chunk, progress=False)
        used = json.loads((Path(tmp) / "manifest.json").read_text())["device_count"]
    return {
        "configs": configs,
        "configs_per_second": result.configs_per_second,
        "devices": jax.device_count(),
        "devices_used": used,
        "seconds_with_compile": result.seconds,
    }


def _true_plant_numpy(Ks, Tp, dead_samples, n_delay):
    """Exact ZOH with dead time (seed 000 eq. 11-18) in NumPy/SciPy, padded to ``n_delay`` slots."""
    h = EXAMPLE1.h
    A = np.array([[0.0, 1.0], [0.0, -1.0 / Tp]])
    B = np.array([[0.0], [Ks / Tp]])
    tau = dead_samples * h
    d = max(int(np.ceil(tau / h - 1e-12)), 1)
    frac = tau - (d - 1) * h

    def zoh(t):
        M = np.zeros((3, 3))
        M[:2, :2], M[:2, 2:] = A, B
        E = scipy.linalg.expm(M * t)
        return E[:2, :2], E[:2, 2:]

    Phi1, _ = zoh(h)
    Ea, G0 = zoh(h - frac)
    _, Gf = zoh(frac)
    G1 = Ea @ Gf
    n = 2 + n_delay
    Phi, Gamma = np.zeros((n, n)), np.zeros((n, 1))
    Phi[:2, :2] = Phi1
    slots = np.arange(n_delay)  # state 2 + j of x_k holds u_{k - n_delay + j}
    Phi[2 + slots[:-1], 3 + slots[:-1]] = 1.0
    Gamma[-1, 0] = 1.0
    # x'_{k+1} gets Gamma_0 u_{k+1-d} and Gamma_1 u_{k-d} (lags d and d + 1; lag 1 is u_k itself)
    for lag, G in ((d, G0), (d + 1, G1)):
        if lag == 1:
            Gamma[:2] += G
        else:
            Phi[:2, 2 + n_delay + 1 - lag] += G[:, 0]
    C = np.zeros((1, n))
    C[0, 0] = 1.0
    return Phi, Gamma, C


def peer_rate(count: int) -> dict:
    """The same evaluation per configuration with NumPy, SciPy and python-control."""
    import control

    config = fr.validate_config()
    sampler, _, _, designs = fr.make_sweep(config)
    table = jax.tree.map(np.asarray, designs.controller)
    steps = int(round(config["simulation"]["duration"] / EXAMPLE1.h))
    n_delay = n_delay_slots(config["plant"]["dead_time_samples"][1] * EXAMPLE1.h, EXAMPLE1.h)
    nominal, L_r = nominal_design()
    r = reference_gain(L_r) * config["simulation"]["force_step"]
    disturbance = np.asarray(example1_disturbance(np.arange(steps) * EXAMPLE1.h))
    A_cl = np.asarray(nominal.A) - np.asarray(nominal.B) @ np.asarray(L_r)
    params = [jax.tree.map(np.asarray, sampler(config_key(0, i), i)) for i in range(count)]
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    for p in params:
        Phi, Gamma, C = _true_plant_numpy(float(p["stiffness"]), float(p["time_constant"]),
                                          float(p["dead_time_samples"]), n_delay)  # fmt: skip
        d = int(p["design"])
        Pn, Gn, Cn, K, L = (M[d] for M in (table.Phi, table.Gamma, table.C, table.K, table.L))
        n, m = Phi.shape[0], Pn.shape[0]
        KC = K @ C
        A = np.block([[Phi, np.zeros((n, m))], [KC @ Phi, (np.eye(m) - K @ Cn) @ (Pn - Gn @ L)]])
        B = np.vstack([Gamma, KC @ Gamma])
        Cl = np.hstack([np.zeros((1, n)), L])
        np.abs(np.linalg.eigvals(A - B @ Cl)).max()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            control.stability_margins(control.ss(A, B, Cl, 0, EXAMPLE1.h))
        x, xh, u = np.zeros(n), np.zeros(m), np.zeros(1)
        xd = np.zeros(A_cl.shape[0])
        noise = np.sqrt(config["simulation"]["sensor_noise"]) * rng.normal(size=steps)
        err = 0.0
        for k in range(steps):
            y = C @ x
            x1 = Pn @ xh + Gn @ u
            xh = x1 + K @ (y + noise[k] - Cn @ x1)
            u = r - L @ xh
            err += float((y[0] - xd[0]) ** 2)
            x = Phi @ x + Gamma @ (u + disturbance[k])
            xd = A_cl @ xd + np.asarray(nominal.B)[:, 0] * r
        np.sqrt(err / steps)
    seconds = time.perf_counter() - start
    return {"configs": count, "configs_per_second": count / seconds}


def device_scaling(configs: int, chunk: int, counts=(1, 2, 4)) -> dict:
    """``{workload: {devices: rate}}``, each in a subprocess with ``devices`` forced host devices."""
    out = {}
    for workload in ("default", "simulation"):
        out[workload] = {}
        for devices in counts:
            env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu")
            code = (
                "import json, sys; sys.path.insert(0, 'benchmarks'); import sweep_throughput as s; "
                f"print(json.dumps(s.jaxobs_rate({configs}, {chunk}, {workload!r})))"
            )
            run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
            out[workload][str(devices)] = json.loads(run.stdout.strip().splitlines()[-1])
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--configs", type=int, default=8000)
    parser.add_argument("--chunk", type=int, default=2000)
    parser.add_argument("--peer-configs", type=int, default=20)
    parser.add_argument("--no-scaling", action="store_true")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    ours = jaxobs_rate(args.configs, args.chunk)
    peer = peer_rate(args.peer_configs)
    ratio = ours["configs_per_second"] / peer["configs_per_second"]
    results = {
        "jaxobs": ours,
        "numpy_python_control": peer,
        "ratio": ratio,
        "target": {"min_ratio": TARGET, "met": bool(ratio >= TARGET)},
        "platform": {"jax": jax.__version__, "backend": jax.default_backend(), "cpu_count": os.cpu_count()},
    }
    if not args.no_scaling:
        results["device_scaling"] = device_scaling(args.configs, args.chunk // 2)
    (args.out / "sweep_throughput.json").write_text(json.dumps(results, indent=2) + "\n")
    print(f"jaxobs: {ours['configs_per_second']:.0f} configs/s ({ours['devices']} device)")
    print(f"NumPy + python-control: {peer['configs_per_second']:.2f} configs/s ({peer['configs']} configs)")
    verdict = "MET" if ratio >= TARGET else "MISSED"
    print(f"ratio {ratio:.0f}x (target >= {TARGET:g}x): {verdict}")
    for workload, rates in results.get("device_scaling", {}).items():
        base = rates["1"]["configs_per_second"]
        for devices, rec in rates.items():
            print(
                f"  {workload}, {devices} host device(s) ({rec['devices_used']} used): "
                f"{rec['configs_per_second']:.0f} configs/s ({rec['configs_per_second'] / base:.2f}x)"
            )
    _plot(results, args.out / "sweep_throughput.png")
    return results


def _plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot

    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    labels = ["jaxobs", "NumPy +\npython-control"]
    rates = [results["jaxobs"]["configs_per_second"], results["numpy_python_control"]["configs_per_second"]]
    a.bar(labels, rates, color=["tab:green" if results["target"]["met"] else "tab:red", "tab:gray"])
    a.set_yscale("log")
    a.set_ylabel("configurations / s")
    a.set_title(f"default sweep evaluation: {results['ratio']:.0f}x (target {TARGET:g}x)")
    scaling = results.get("device_scaling", {})
    for workload, rates in scaling.items():
        used = sorted({r["devices_used"] for r in rates.values()})
        label = f"{workload} (devices used: {', '.join(map(str, used))})"
        b.plot([int(d) for d in rates], [r["configs_per_second"] for r in rates.values()], "o-", label=label)
        b.set_xticks([int(d) for d in rates])
    if scaling:
        b.legend()
        b.set_xlabel("forced host devices")
        b.set_ylabel("configurations / s")
        b.set_title(f"device scaling ({results['platform']['cpu_count']} CPU cores)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
