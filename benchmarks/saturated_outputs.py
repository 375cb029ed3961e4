"""The saturated-output controller sweep (Grip 2010, ch. 8) against a NumPy loop.

Throughput: configurations per second of the ``saturated-outputs`` sweep evaluation (``jaxobs sweep --config
tuning/saturated_outputs_sweep.toml``; per configuration the design (exp(A T), Bbar, alpha) and the loop (8.2)-(8.5)
over ``run.intervals`` intervals of ``run.substeps`` RK4 steps on the augmented state [x, mu, v, exp(A t), sigma, xi,
D]): jaxobs ``jit(vmap(evaluate))`` over the first ``--configs`` configurations, compiled once (compile time
reported), against a NumPy peer doing the same arithmetic batched over the configurations (a Python loop over the
intervals, substeps and RK4 stages, every operation on (N, ...) arrays; the designs with SciPy's ``expm`` per
configuration, inside the timing as jaxobs computes them inside its evaluation). A check compares the deadbeat
intervals and final states of both (stored in the JSON).

    python benchmarks/saturated_outputs.py --out DIR [--configs 256] [--rounds 5]

Writes ``DIR/saturated_outputs.json`` and prints a table.
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
import scipy.linalg  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from _timing import format_range, paired_ratio, time_interleaved  # noqa: E402

from jaxobs.papers.grip2010 import saturated_outputs as ex  # noqa: E402
from jaxobs.papers.grip2010 import saturated_outputs_sweep as sweep  # noqa: E402
from jaxobs.sweep import config_key  # noqa: E402


def _draws(config: dict, n: int):
    sampler, _, total, _ = sweep.make_sweep(config)
    rows = [sampler(config_key(config["seed"], i % total), i % total) for i in range(n)]
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *rows)


def peer(T, rho, h_scale, x0, intervals: int, substeps: int, cond_max: float):
    """The sweep's evaluation in NumPy, batched over the N configurations; returns (deadbeat interval, final x)."""
    A, B, C = ex.A, ex.B, ex.C
    n_cfg, n, p = T.shape[0], 3, 2
    expAT, Bbar_inv, alpha = np.empty((n_cfg, n, n)), np.empty((n_cfg, n, n)), np.empty(n_cfg)
    for c in range(n_cfg):  # the designs (8.3)-(8.4)
        expAT[c] = scipy.linalg.expm(A * T[c])
        M = np.block([[A, B @ B.T], [np.zeros((n, n)), -A.T]]) * T[c]
        Bbar_inv[c] = np.linalg.inv(scipy.linalg.expm(M)[:n, n:])
        alpha[c] = rho[c] * np.linalg.norm(expAT[c], 2)
    H = h_scale[:, None, None] * C[None]
    d = T / substeps

    def rhs(s):
        x, mu, v, Psi, sigma, xi, D = s
        u = -v @ B  # -B' v
        y = np.clip(x @ C.T, -1, 1)
        w = 1 - np.abs(y)
        PC = np.einsum("cji,kj->cik", Psi, C)  # exp(A' t) C'
        return (x @ A.T + u @ B.T, mu @ A.T + u @ B.T, -v @ A, np.einsum("ij,cjk->cik", A, Psi), w,
                np.einsum("cik,ck->ci", PC, w * (y - mu @ C.T)), np.einsum("cik,ck,cjk->cij", PC, w, PC))  # fmt: skip

    def axpy(s, k, c):
        return tuple(a + (c.reshape(-1, *([1] * (a.ndim - 1)))) * b for a, b in zip(s, k, strict=True))

    x = x0.copy()
    mu, xi = np.zeros((n_cfg, n)), np.zeros((n_cfg, n))
    Psi = np.broadcast_to(np.eye(n), (n_cfg, n, n)).copy()
    sigma, D = np.zeros((n_cfg, p)), np.zeros((n_cfg, n, n))
    deadbeat = np.zeros(n_cfg, int)
    for k in range(intervals):
        eig = np.linalg.eigvalsh((D + np.swapaxes(D, 1, 2)) / 2)
        cond = np.where(eig[:, 0] > 0, eig[:, -1] / np.where(eig[:, 0] > 0, eig[:, 0], 1), np.inf)
        ready = np.all(sigma > 0, axis=1) & (cond <= cond_max)
        safe = np.where(ready[:, None, None], D, np.eye(n))
        x0_hat = np.where(ready[:, None], np.linalg.solve(safe, xi[..., None])[..., 0], 0)
        x_hat = np.where(ready[:, None], np.einsum("cij,cj->ci", Psi, x0_hat) + mu, 0)
        U_db = np.einsum("cij,cjk,ck->ci", Bbar_inv, expAT, x_hat)
        j = np.where(np.any(sigma == 0, axis=1), np.argmax(sigma == 0, axis=1), np.argmin(sigma, axis=1))
        h = H[np.arange(n_cfg), j]
        y_j = np.clip(np.einsum("ci,ci->c", C[j], x), -1, 1)
        push = alpha[:, None] ** k * (alpha[:, None] * h - np.einsum("cij,cj->ci", expAT, h)) * y_j[:, None]
        U = np.where(ready[:, None], U_db, np.einsum("cij,cj->ci", Bbar_inv, push))
        deadbeat = np.where((deadbeat == 0) & ready, k + 1, deadbeat)
        s = (x, mu, U, Psi, sigma, xi, D)
        for _ in range(substeps):
            k1 = rhs(s)
            k2 = rhs(axpy(s, k1, d / 2))
            k3 = rhs(axpy(s, k2, d / 2))
            k4 = rhs(axpy(s, k3, d))
            slope = tuple(a + 2 * b + 2 * c + e for a, b, c, e in zip(k1, k2, k3, k4, strict=True))
            s = axpy(s, slope, d / 6)
        x, mu, _, Psi, sigma, xi, D = s
    return deadbeat, x


def throughput(n: int, rounds: int) -> dict:
    config = sweep.SCENARIO.validate()
    draws = _draws(config, n)
    _, evaluate, _, _ = sweep.make_sweep(config)
    run = config["run"]
    args = tuple(np.asarray(draws[k]) for k in ("T", "rho", "h_scale", "x0"))
    entries = {
        "jaxobs": (lambda: (jax.vmap(evaluate), (draws,)), True, 1.0),
        "numpy": (lambda: (lambda: peer(*args, run["intervals"], run["substeps"], run["cond_max"]), ()), False, 1.0),
    }
    timings, problems = time_interleaved(entries, rounds, required=("jaxobs", "numpy"))
    mine, (theirs_db, theirs_x) = timings["jaxobs"].result, timings["numpy"].result
    mine_db = np.asarray(mine["deadbeat_interval"])
    done = (mine_db > 0) & (theirs_db > 0)
    return {
        "configs": n,
        "intervals": run["intervals"],
        "substeps": run["substeps"],
        "jaxobs": timings["jaxobs"].record(n, "configs/s"),
        "numpy": timings["numpy"].record(n, "configs/s"),
        "speedup_jaxobs_over_numpy": paired_ratio(timings["jaxobs"], timings["numpy"]),
        "deadbeat_interval_agreement": float(np.mean(mine_db == theirs_db)),
        "max_final_norm_both_deadbeat": {
            "jaxobs": float(np.max(np.asarray(mine["final_norm"])[done], initial=0.0)),
            "numpy": float(np.max(np.linalg.norm(theirs_x[done], axis=1), initial=0.0)),
        },
        "problems": problems,
    }


def report(t: dict) -> str:
    return "\n".join([
        f"saturated-outputs sweep, {t['configs']} configurations of {t['intervals']} intervals x {t['substeps']} RK4 "
        "steps:",
        f"  jaxobs {format_range(t['jaxobs']['throughput'])} configs/s (compile {t['jaxobs']['compile_s']:.1f} s)",
        f"  numpy  {format_range(t['numpy']['throughput'])} configs/s",
        f"  jaxobs / numpy speed-up {format_range(t['speedup_jaxobs_over_numpy'])}; deadbeat intervals agree in "
        f"{100 * t['deadbeat_interval_agreement']:.1f} % of the configurations",
    ])  # fmt: skip


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    parser.add_argument("--configs", type=int, default=256)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    results = throughput(args.configs, args.rounds)
    meta = {"rounds": args.rounds, "platform": platform.platform(), "device": str(jax.devices()[0]),
            "jax": jax.__version__}  # fmt: skip
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "saturated_outputs.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    print(report(results))
    print(f"wrote {out / 'saturated_outputs.json'}")
    return results


if __name__ == "__main__":
    main()
