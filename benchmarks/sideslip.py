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

Not measured: a NumPy peer (the friction model with the combined-slip Magic Formula and the EKF's Jacobians would
have to be written out by hand).

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

MANOEUVRE = "double_lane_change_120kmh"


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
    timings, problems = time_interleaved(entries, rounds, required=tuple(observers))
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
        "problems": problems,
    }


def report(r: dict) -> str:
    lines = [f"{r['manoeuvre']}, {r['vehicles']} vehicles x {r['samples']} samples (jit(vmap(scan))):"]
    for name, o in r["observers"].items():
        lines.append(
            f"  {name:12s} {format_range(o['step_seconds'], '.3g', ' s')} per step of the batch, "
            f"{format_range(o['vehicle_step_seconds'], '.3g', ' s')} per vehicle-step "
            f"(compile {o['compile_s']:.1f} s); sideslip RMS {o['beta_rms_deg_median']:.3f} deg (median)"
        )
    lines.append(f"  EKF / NVSO cost {format_range(r['ekf_over_nvso'])}; "
                 f"EKF (Bierman) / NVSO {format_range(r['ekf_bierman_over_nvso'])}")  # fmt: skip
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
