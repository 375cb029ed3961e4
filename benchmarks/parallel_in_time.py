"""Estimation over a record: sequential against parallel-in-time filtering and smoothing, and the float32 drift of
the covariance and square-root Kalman filters.

1. ``timing``: for T in {100, 10000} samples of a random stable model (n = 3 states, p = 2 outputs, one input,
   float64, on the default JAX device), the wall time of

   * ``filter``: ``run(kalman_filter, ...)`` (``jax.lax.scan``, depth T) / ``parallel_filter`` (Särkkä &
     García-Fernández 2021, ``jax.lax.associative_scan``, depth O(log T));
   * ``smooth``: ``smooth(kalman_filter, ..., parallel=False)`` / ``parallel=True`` (filter and RTS smoother);

   each compiled ahead of time (the compile time is reported apart) and timed in interleaved rounds
   (``benchmarks/_timing.py``: median and [min, max]; the speed-up parallel / sequential paired round by round).

2. ``float32_drift``: the AOB-2 of Cortesão 2006 Example 1 (the delay-augmented force plant, 9 states, its tiny
   plant noise ``q_plant = 1e-12`` making the covariance nearly singular) as the Kalman filter of its augmented
   model, run over ``--drift-steps`` samples of a recorded-like random-walk measurement in float32, in covariance
   form (``kalman_filter``) and square-root form (``square_root_kalman_filter``), against the float64 covariance
   form: the largest error of the estimate relative to the largest float64 estimate, the largest relative error of
   the summed log-likelihood, the most negative eigenvalue of any a-posteriori covariance relative to its largest
   one (negative = definiteness lost), and the number of non-finite estimates.

Run (``make bench`` does it with ``--out out/bench``)::

    python benchmarks/parallel_in_time.py --out DIR [--rounds 7] [--drift-steps 20000]

Writes ``DIR/parallel_in_time.json`` and prints a table.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import format_range, paired_ratio, time_interleaved  # noqa: E402

from jaxobs.observers import EstimatorInputs, active, run  # noqa: E402
from jaxobs.observers.kalman import kalman_filter, make_kalman, square_root_form, square_root_kalman_filter  # noqa: E402
from jaxobs.papers.cortesao.force_control import EXAMPLE1, nominal_design  # noqa: E402
from jaxobs.smoothing import parallel_filter, smooth  # noqa: E402


def random_problem(T: int, seed: int = 0):
    """A random stable model (n = 3, p = 2, m = 1) and T samples simulated from it."""
    rng = np.random.default_rng(seed)
    n, p, m = 3, 2, 1
    Phi = rng.normal(size=(n, n))
    Phi *= 0.97 / np.max(np.abs(np.linalg.eigvals(Phi)))
    Gamma, C, G = rng.normal(size=(n, m)), rng.normal(size=(p, n)), 0.3 * rng.normal(size=(n, n))
    Q, R = G @ G.T + 0.01 * np.eye(n), np.array([[0.5, 0.2], [0.2, 0.3]])
    u, x, ys = rng.normal(size=(T, m)), np.zeros(n), []
    for u_k in u:
        x = Phi @ x + Gamma @ u_k + np.linalg.cholesky(Q) @ rng.normal(size=n)
        ys.append(C @ x + np.linalg.cholesky(R) @ rng.normal(size=p))
    params = make_kalman(Phi, C, Q, R, Gamma=Gamma, P0=np.eye(n))
    return params, EstimatorInputs(y=jnp.asarray(np.array(ys)), u_prev=jnp.asarray(u))


def with_covariances(params):
    return dataclasses.replace(params, output_covariance=True)


def timing(T: int, rounds: int) -> dict:
    params, inputs = random_problem(T)
    sequential_filter = lambda p, i: run(kalman_filter, p, i)
    entries = {
        "filter/sequential": (lambda: (sequential_filter, (params, inputs)), True, 1.0),
        "filter/parallel": (lambda: (parallel_filter, (params, inputs)), True, 1.0),
        "smooth/sequential": (lambda: (lambda p, i: smooth(kalman_filter, p, i), (params, inputs)), True, 1.0),
        "smooth/parallel": (
            lambda: (lambda p, i: smooth(kalman_filter, p, i, parallel=True), (params, inputs)),
            True,
            1.0,
        ),
    }
    timings, problems = time_interleaved(entries, rounds, required=tuple(entries))
    assert not problems, problems
    seq, par = timings["filter/sequential"].result[1], timings["filter/parallel"].result[1]
    agreement = float(jnp.max(jnp.abs(seq.x - par.x)) / jnp.max(jnp.abs(seq.x)))
    out = {name: t.record(T, "samples/s") for name, t in timings.items()}
    for what in ("filter", "smooth"):
        out[f"{what}/speedup_parallel"] = paired_ratio(timings[f"{what}/parallel"], timings[f"{what}/sequential"])
    out["filter/max_relative_difference_of_x"] = agreement
    return out


def float32_drift(steps: int) -> dict:
    plant, _ = nominal_design(EXAMPLE1)
    aob = active.make_aob(plant, 2, EXAMPLE1.R, q_plant=EXAMPLE1.q_plant, q_active=EXAMPLE1.sigma2_active)
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    y = jnp.cumsum(jax.random.normal(k1, (steps, 1)), axis=0) * 0.1
    u_prev = jax.random.normal(k2, (steps, 1))
    model = lambda dtype: make_kalman(*(jnp.asarray(M, dtype) for M in (aob.Phi, aob.C, aob.Q, aob.R)),
                                      Gamma=jnp.asarray(aob.Gamma, dtype), P0=jnp.asarray(aob.P0, dtype))  # fmt: skip
    inputs = lambda dtype: EstimatorInputs(y=y.astype(dtype), u_prev=u_prev.astype(dtype))
    run_jit = jax.jit(run, static_argnums=0)
    reference = run_jit(kalman_filter, with_covariances(model(jnp.float64)), inputs(jnp.float64))[1]
    results = {}
    for name, estimator, params in (
        ("covariance form", kalman_filter, model(jnp.float32)),
        ("square-root form", square_root_kalman_filter, square_root_form(model(jnp.float32))),
    ):
        out = run_jit(estimator, with_covariances(params), inputs(jnp.float32))[1]
        x, P = np.asarray(out.x, np.float64), np.asarray(out.P, np.float64)
        eig = np.linalg.eigvalsh(0.5 * (P + np.swapaxes(P, -1, -2)))
        finite = np.isfinite(x).all(axis=1)
        err = np.abs(x - np.asarray(reference.x))[finite]
        ll, ll_ref = float(np.sum(np.asarray(out.log_likelihood, np.float64))), float(jnp.sum(reference.log_likelihood))
        results[name] = {
            "max_error_x_relative": float(err.max() / np.abs(np.asarray(reference.x)).max()) if err.size else None,
            "error_x_relative_last_1000": float(
                np.abs(x[-1000:] - np.asarray(reference.x[-1000:])).max() / np.abs(np.asarray(reference.x)).max()
            ),
            "log_likelihood_relative_error": abs(ll - ll_ref) / abs(ll_ref),
            "min_eigenvalue_of_P_relative": float(np.nanmin(eig[:, 0] / eig[:, -1])),
            "non_finite_estimates": int((~finite).sum()),
        }
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory for parallel_in_time.json")
    parser.add_argument("--rounds", type=int, default=7, help="interleaved timing rounds")
    parser.add_argument("--drift-steps", type=int, default=20000, help="samples of the float32 drift runs")
    args = parser.parse_args(argv)
    meta = {"device": str(jax.devices()[0]), "platform": platform.platform(), "processor": platform.processor(),
            "jax": jax.__version__, "rounds": args.rounds}  # fmt: skip
    results = {"timing": {str(T): timing(T, args.rounds) for T in (100, 10_000)},
               "float32_drift": float32_drift(args.drift_steps)}  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "parallel_in_time.json").write_text(json.dumps({"meta": meta, "results": results}, indent=2))
    print(f"{'T':>6} {'entry':<20} {'time [s]':<34} {'compile [s]':>11}")
    for T, r in results["timing"].items():
        for name in ("filter/sequential", "filter/parallel", "smooth/sequential", "smooth/parallel"):
            print(f"{T:>6} {name:<20} {format_range(r[name]['seconds']):<34} {r[name]['compile_s']:>11.2f}")
        for what in ("filter", "smooth"):
            print(f"{T:>6} {what + ' speed-up':<20} {format_range(r[what + '/speedup_parallel'], suffix='x')}")
    for name, r in results["float32_drift"].items():
        print(f"float32 {name}: " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                                              for k, v in r.items()))  # fmt: skip
    print(f"wrote {args.out / 'parallel_in_time.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
