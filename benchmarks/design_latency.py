"""Latency of eager design calls (a control engineer's Python loop) against python-control's equivalents.

Measured for the papers' sizes (the delay-augmented force plant of Cortesão 2006 Example 1, 7 states, and its
AOB-2, 9 states), float64, on the CPU:

* ``first_call_s``: the first call in a fresh Python process (after the imports; compilation included), one
  subprocess per function;
* ``call_s``: later calls in one process, timed in interleaved rounds with the python-control peer
  (``benchmarks/_timing.py``: median and [min, max] over the rounds, ratios paired round by round).

Targets (issue 14): every later call <= 20 ms, every first call <= 3 s.

Pairs (jaxobs / python-control):

* ``c2d``: ``jaxobs.c2d`` with five samples of dead time / ``control.c2d`` (zero-order hold, no dead time: python-
  control has no fractional dead time, so it does less work);
* ``acker``: ``jaxobs.acker`` / ``control.acker``;
* ``dare``: ``jaxobs.dare`` / ``control.dare`` (both the control equation of SciPy);
* ``dlqr``: ``jaxobs.dlqr`` / ``control.dlqr``;
* ``make_kalman``: ``jaxobs.make_kalman(..., steady_state=True)`` (checks, DARE, gain) / ``control.dlqe``;
* ``make_aob``: ``jaxobs.make_aob(plant, 2, R, steady_state=True)`` (augmentation, checks, two DAREs) /
  ``control.dlqe`` on the same augmented model.

Run (``make bench`` does it with ``--out out/bench``)::

    python benchmarks/design_latency.py --out DIR [--rounds 30]

Writes ``DIR/design_latency.json`` and prints a table.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import textwrap  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import format_range, paired_ratio, time_interleaved  # noqa: E402

TARGET_CALL_S = 0.020
TARGET_FIRST_S = 3.0

# The Example 1 force plant: 3 / (s (0.032 s + 1)) in N and mm/s, h = 8 ms, five samples of dead time. The
# delay-augmented matrices are built with SciPy, so that no jaxobs function runs before the one being timed.
SETUP = """
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import scipy.linalg
import jaxobs as jo
A = np.array([[0.0, 1.0], [0.0, -1 / 0.032]]); B = np.array([[0.0], [3 / 0.032]]); C = np.array([[1.0, 0.0]])
H, DELAY, D = 0.008, 0.040, 5
E = scipy.linalg.expm(np.block([[A, B], [np.zeros((1, 3))]]) * H)
PHI = np.zeros((2 + D, 2 + D)); PHI[:2, :2] = E[:2, :2]; PHI[:2, 2] = E[:2, 2]
PHI[2:-1, 3:] = np.eye(D - 1)
GAMMA = np.zeros((2 + D, 1)); GAMMA[-1, 0] = 1.0
CD = np.zeros((1, 2 + D)); CD[0, 0] = 1.0
CONT, PLANT = jo.ss(A, B, C), jo.ss(PHI, GAMMA, CD, dt=H)
POLES = [0.975, 0.975, 0.0, 0.0, 0.0, 0.0, 0.0]
Q, R = 1e-3 * np.eye(7), np.array([[2.1e-2]])
"""

# The AOB-2's augmented model, for the python-control peer of make_aob (built in the timing process only).
AOB_MODEL = """
AOB = jo.make_aob(PLANT, 2, 2.1e-2, q_active=4e-6)
PHI_A, C_A, Q_A = (np.asarray(M) for M in (AOB.Phi, AOB.C, AOB.Q))
"""

CALLS = {
    "c2d": ("jo.c2d(CONT, H, DELAY)", "control.c2d(control.ss(A, B, C, 0), H)"),
    "acker": ("jo.acker(PHI, GAMMA, POLES)", "control.acker(PHI, GAMMA, POLES)"),
    "dare": ("jo.dare(PHI, GAMMA, Q, R)", "control.dare(PHI, GAMMA, Q, R)"),
    "dlqr": ("jo.dlqr(PHI, GAMMA, Q, R)", "control.dlqr(PHI, GAMMA, Q, R)"),
    "make_kalman": ("jo.make_kalman(PHI, CD, Q, R, steady_state=True)", "control.dlqe(PHI, np.eye(7), CD, Q, R)"),
    "make_aob": (
        "jo.make_aob(PLANT, 2, 2.1e-2, q_active=4e-6, steady_state=True)",
        "control.dlqe(PHI_A, np.eye(9), C_A, Q_A, R)",
    ),
}


def first_call_seconds(call: str) -> float:
    """Seconds of the first ``call`` in a fresh process, after the imports and the set-up (which runs no jaxobs
    function but ``ss``)."""
    program = SETUP + textwrap.dedent(f"""
        import time
        start = time.perf_counter()
        jax.block_until_ready(jax.tree_util.tree_leaves({call}))
        print(time.perf_counter() - start)
    """)
    out = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def warmed(call: str, namespace: dict):
    """``(fn, ())`` for the timing helper, ``fn`` evaluating ``call``, after one call (the first call, compilation
    included, is measured apart by :func:`first_call_seconds`)."""
    fn = lambda: eval(call, namespace)  # noqa: S307  (our own fixed expressions)
    jax.block_until_ready(jax.tree_util.tree_leaves(fn()))
    return fn, ()


def measure(rounds: int) -> dict:
    import control  # noqa: F401  (the peer; the benchmark needs it)

    namespace: dict = {"control": control}
    exec(SETUP + AOB_MODEL, namespace)  # noqa: S102  (our own fixed set-up code)
    results = {}
    for name, (ours, peer) in CALLS.items():
        entries = {
            "jaxobs": (lambda ours=ours: warmed(ours, namespace), False, 1.0),
            "python-control": (lambda peer=peer: warmed(peer, namespace), False, 1.0),
        }
        timings, problems = time_interleaved(entries, rounds, required=("jaxobs",))
        first = first_call_seconds(ours)
        record = {
            "jaxobs": timings["jaxobs"].record(1, "calls/s") | {"first_call_s": first},
            "problems": problems,
        }
        if "python-control" in timings:
            record["python-control"] = timings["python-control"].record(1, "calls/s")
            record["ratio_peer_over_ours"] = paired_ratio(timings["jaxobs"], timings["python-control"])
        median = record["jaxobs"]["seconds"]["median"]
        record["targets"] = {"call_s": TARGET_CALL_S, "call_met": median <= TARGET_CALL_S,
                             "first_s": TARGET_FIRST_S, "first_met": first <= TARGET_FIRST_S}  # fmt: skip
        results[name] = record
    return results


def report(results: dict) -> str:
    lines = [f"{'call':<12} {'jaxobs later call (ms)':<28} {'first call (s)':<15} {'python-control (ms)':<26} ratio"]
    for name, r in results.items():
        ours = r["jaxobs"]["seconds"]
        ms = {k: 1e3 * v for k, v in ours.items() if k in ("median", "min", "max")}
        peer = r.get("python-control", {}).get("seconds")
        peer_ms = {k: 1e3 * v for k, v in peer.items() if k in ("median", "min", "max")} if peer else None
        ratio = format_range(r["ratio_peer_over_ours"], ".2g", "x") if peer else "-"
        flags = "" if r["targets"]["call_met"] else " MISSED 20 ms"
        flags += "" if r["targets"]["first_met"] else " MISSED 3 s"
        lines.append(
            f"{name:<12} {format_range(ms, '.3g'):<28} {r['jaxobs']['first_call_s']:<15.3g} "
            f"{format_range(peer_ms, '.3g') if peer_ms else '-':<26} {ratio}{flags}"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory for design_latency.json")
    parser.add_argument("--rounds", type=int, default=30, help="interleaved timing rounds (default 30)")
    args = parser.parse_args(argv)
    results = measure(args.rounds)
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"platform": platform.platform(), "python": platform.python_version(), "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()], "rounds": args.rounds}  # fmt: skip
    (args.out / "design_latency.json").write_text(json.dumps({"meta": meta, "results": results}, indent=2))
    table = report(results)
    print(table)
    print(f"wrote {args.out / 'design_latency.json'}")
    return 0 if all(r["targets"]["call_met"] and r["targets"]["first_met"] for r in results.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
