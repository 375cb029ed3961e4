"""Speed of the jaxobs IMM against filterpy's and of its cubature and Gauss-Hermite filters against cuthbert's
quadrature filter, on the same workloads.

What is measured (float64, ``T`` samples, ``B`` in {1, 64} independent measurement sequences):

* ``imm``: a two-mode interacting multiple model (Blom & Bar-Shalom 1988) over Kalman filters, a
  constant-velocity and a constant-acceleration mode (3 states, 1 output), on manoeuvring targets (the model
  tests/observers/test_imm.py checks against filterpy). jaxobs: ``jit(vmap(run(imm(kalman_filter,
  kalman_filter))))``. filterpy: its ``IMMEstimator`` over two ``KalmanFilter``s, ``predict`` and ``update`` per
  sample, in Python; it is timed on one sequence and its time multiplied by ``B`` (a Python loop over sequences
  does exactly that work).
* ``cubature``, ``gauss_hermite``: the sampled pendulum of Särkkä 2013 (2 states, measured ``sin`` of the
  angle; the model and data of benchmarks/nonlinear.py), filtered with the cubature rule (4 points) and the
  Gauss-Hermite rule of order 3 (9 points). jaxobs: ``jit(vmap(run(unscented_kalman_filter)))`` with
  ``make_ukf(model, rule=...)``. cuthbert has the quadrature atoms but no filter object for them: its filter here
  is its statistical linear regression ``cuthbertlib.quadrature.functional`` of ``f`` and ``h`` around the
  current Gaussian followed by its square-root Kalman ``predict`` and ``update`` (``cuthbertlib.kalman.filtering``),
  in a ``lax.scan``, jitted and vmapped alike (the oracle of tests/observers/test_ukf.py).

Agreement: the filtered means of both sides on the benchmark data (max relative difference).

Timing (``benchmarks/_timing.py``): every JAX function is compiled first (the compile time is reported apart);
then ``--rounds`` interleaved rounds run every entry once; times are the median [min, max] over the rounds and
the ratio ``peer time / jaxobs time`` is taken round by round (paired).

Run::

    python benchmarks/estimation_breadth.py --out DIR [--steps 1000] [--batches 1 64] [--rounds 7]

Writes ``DIR/estimation_breadth.json`` and ``DIR/estimation_breadth.png`` and prints a table.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from _timing import Skipped, format_range, paired_ratio, time_interleaved  # noqa: E402
from nonlinear import DT, P0, X0, pendulum_f, pendulum_h  # noqa: E402
from nonlinear import Q as Q_P  # noqa: E402
from nonlinear import R as R_P  # noqa: E402
from nonlinear import simulate as pendulums  # noqa: E402

import jaxobs as jo  # noqa: E402

# IMM: constant velocity and constant acceleration, period 0.5 s (tests/observers/test_imm.py)
DT_IMM = 0.5
F_CV = np.array([[1.0, DT_IMM, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
F_CA = np.array([[1.0, DT_IMM, DT_IMM**2 / 2], [0.0, 1.0, DT_IMM], [0.0, 0.0, 1.0]])
H = np.array([[1.0, 0.0, 0.0]])
Q_CV, Q_CA, R_IMM = np.diag([1e-4, 1e-3, 1e-6]), np.diag([1e-3, 1e-2, 0.5]), np.array([[0.4]])
TRANSITION, MU = np.array([[0.97, 0.03], [0.05, 0.95]]), np.array([0.6, 0.4])
X_PRIOR, P_PRIOR = np.array([0.0, 1.0, 0.0]), np.diag([1.0, 0.5, 0.2])

RULES = {"cubature": {}, "gauss_hermite": {"order": 3}}


def manoeuvre(T: int, start: int, length: int, rng: np.random.Generator) -> np.ndarray:
    """(T, 1) noisy positions of a target that cruises at unit speed and accelerates (1.5) from sample ``start``
    for ``length`` samples."""
    x, ys = np.array([0.0, 1.0, 0.0]), np.zeros((T, 1))
    for k in range(T):
        x = F_CA @ x
        x[2] = 1.5 if start <= k < start + length else 0.0
        ys[k] = H @ x + np.sqrt(R_IMM[0, 0]) * rng.normal(size=1)
    return ys


def manoeuvres(B: int, T: int, seed: int = 0) -> np.ndarray:
    """(B, T, 1): B records of :func:`manoeuvre`, each accelerating for a tenth of the record from a random
    sample."""
    rng = np.random.default_rng(seed)
    return np.stack([manoeuvre(T, rng.integers(0, max(T - T // 10, 1)), T // 10, rng) for _ in range(B)])


def imm_params(transition=TRANSITION):
    """The IMM's params: each mode's prior of ``x_0`` is its prediction of filterpy's prior of ``x_{-1}``, the
    mode prior filterpy's predicted mode probabilities ``mu M`` (the first jaxobs step has no transition)."""
    modes = [jo.make_kalman(F, H, Q, R_IMM, x0=F @ X_PRIOR, P0=F @ P_PRIOR @ F.T + Q)
             for F, Q in ((F_CV, Q_CV), (F_CA, Q_CA))]  # fmt: skip
    return jo.make_imm(modes, transition, MU @ TRANSITION)


def filterpy_imm_estimates(y: np.ndarray):
    """filterpy's IMMEstimator over two KalmanFilters on one record ``y`` (T, 1), ``predict`` then ``update`` per
    sample: the combined means (T, 3), covariances (T, 3, 3) and mode probabilities (T, 2)."""
    from filterpy.kalman import IMMEstimator, KalmanFilter

    filters = []
    for F, Q in ((F_CV, Q_CV), (F_CA, Q_CA)):
        kf = KalmanFilter(dim_x=3, dim_z=1)
        kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = X_PRIOR.copy(), P_PRIOR.copy(), F, Q, H, R_IMM
        filters.append(kf)
    estimator = IMMEstimator(filters, MU, TRANSITION)
    xs, Ps, mus = [], [], []
    for z in y:
        estimator.predict()
        estimator.update(z)
        xs.append(estimator.x.copy())
        Ps.append(estimator.P.copy())
        mus.append(estimator.mu.copy())
    return np.array(xs), np.array(Ps), np.array(mus)


def jaxobs_imm():
    params, imm = imm_params(), jo.imm(jo.kalman_filter, jo.kalman_filter)
    return lambda ys: jax.vmap(lambda y: jo.run(imm, params, jo.EstimatorInputs(y))[1].x)(ys)


def filterpy_imm(ys: np.ndarray):
    """filterpy's IMM over the first sequence (its time is scaled by B)."""
    if importlib.util.find_spec("filterpy") is None:
        raise Skipped("filterpy not installed")
    return lambda y: filterpy_imm_estimates(y)[0][None], (ys[0],)


def jaxobs_quadrature(rule: str):
    model = jo.nonlinear_model(lambda x, u, t: pendulum_f(x), pendulum_h, Q_P, R_P, x0=X0, P0=P0, dt=DT)
    params = jo.make_ukf(model, rule=rule, **RULES[rule])
    return lambda ys: jax.vmap(lambda y: jo.run(jo.unscented_kalman_filter, params, jo.EstimatorInputs(y))[1].x)(ys)


def cuthbert_quadrature(rule: str):
    """cuthbert's statistical linear regression and square-root Kalman steps in a scan (no prediction at the first
    sample, as jaxobs)."""
    try:
        from cuthbertlib.kalman import filtering
        from cuthbertlib.quadrature import cubature, functional, gauss_hermite
    except ImportError as exc:
        raise Skipped(f"cuthbert not installed: {exc}") from exc
    quadrature = cubature.weights(2) if rule == "cubature" else gauss_hermite.weights(2, **RULES[rule])
    Q, R = jnp.asarray(Q_P), jnp.asarray(R_P)

    def step(carry, y):
        m, chol_P, first = carry
        F, c, Q_lin = functional(pendulum_f, Q, m, chol_P @ chol_P.T, quadrature)
        m_pred, chol_pred = filtering.predict(m, chol_P, F, c, jnp.linalg.cholesky(Q_lin))
        m, chol_P = jnp.where(first, m, m_pred), jnp.where(first, chol_P, chol_pred)
        H_lin, d, R_lin = functional(pendulum_h, R, m, chol_P @ chol_P.T, quadrature)
        (m, chol_P), _ = filtering.update(m, chol_P, H_lin, d, jnp.linalg.cholesky(R_lin), y)
        return (m, chol_P, False), m

    def one(y):
        return jax.lax.scan(step, (jnp.asarray(X0), jnp.linalg.cholesky(jnp.asarray(P0)), True), y)[1]

    return lambda ys: jax.vmap(one)(ys)


CASES = {  # case: (data, jaxobs, peer)
    "imm": (manoeuvres, jaxobs_imm, "filterpy"),
    "cubature": (pendulums, lambda: jaxobs_quadrature("cubature"), "cuthbert"),
    "gauss_hermite": (pendulums, lambda: jaxobs_quadrature("gauss_hermite"), "cuthbert"),
}


def measure(batches, T: int, rounds: int) -> dict:
    results = {}
    for B in batches:
        entries, data = {}, {}
        for case, (make_data, ours, peer_name) in CASES.items():
            if make_data not in data:
                data[make_data] = jnp.asarray(make_data(B, T))
            ys = data[make_data]
            entries[f"jaxobs_{case}"] = (lambda ours=ours, ys=ys: (ours(), (ys,)), True, 1.0)
            if peer_name == "filterpy":
                entries[f"{peer_name}_{case}"] = (lambda ys=ys: filterpy_imm(np.asarray(ys)), False, float(B))
            else:
                peer = lambda rule=case, ys=ys: (cuthbert_quadrature(rule), (ys,))  # noqa: E731
                entries[f"{peer_name}_{case}"] = (peer, True, 1.0)
        timings, problems = time_interleaved(entries, rounds, required=tuple(f"jaxobs_{c}" for c in CASES))
        record = {"problems": problems}
        for case, (_, _, peer_name) in CASES.items():
            mine, peer = timings[f"jaxobs_{case}"], timings.get(f"{peer_name}_{case}")
            entry = {"jaxobs": mine.record(B * T, "steps/s"), "peer_name": peer_name}
            if peer is not None:
                entry["peer"] = peer.record(B * T, "steps/s")
                entry["ratio_peer_over_jaxobs"] = paired_ratio(mine, peer)
                theirs = np.asarray(peer.result)  # filterpy: the first sequence only
                ours = np.asarray(mine.result)[: theirs.shape[0]]
                entry["max_relative_difference"] = float(np.max(np.abs(ours - theirs)) / np.max(np.abs(theirs)))
            record[case] = entry
        results[f"B={B}"] = record
    return results


def report(results: dict) -> str:
    """A Markdown table: per case and batch, both sides' times and compile times, the paired ratio, the
    agreement."""
    scaled = lambda s: {k: s[k] * 1e3 for k in ("median", "min", "max")}  # noqa: E731  seconds -> ms
    rows = ["| case | B | jaxobs [ms] | peer [ms] | peer / jaxobs | compile jaxobs / peer [s] | max rel. diff. |",
            "|---|---|---|---|---|---|---|"]  # fmt: skip
    for batch, record in results.items():
        for case in CASES:
            r = record[case]
            peer = r.get("peer")
            if peer is None:
                rows.append(
                    f"| {case} | {batch} | {r['peer_name']}: {record['problems'].get(r['peer_name'] + '_' + case)} |"
                )
                continue
            compile_peer = "none" if peer["compile_s"] is None else f"{peer['compile_s']:.2g}"
            cells = [f"{case} vs {r['peer_name']}", batch.removeprefix("B="),
                     format_range(scaled(r["jaxobs"]["seconds"])), format_range(scaled(peer["seconds"])),
                     format_range(r["ratio_peer_over_jaxobs"], ".3g", "x"),
                     f"{r['jaxobs']['compile_s']:.2g} / {compile_peer}",
                     f"{r['max_relative_difference']:.1e}"]  # fmt: skip
            rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)


def plot(results: dict, meta: dict, path: Path) -> None:
    """Left: the paired speed ratio peer time / jaxobs time per case and batch (log scale, bar: [min, max]);
    right: the compile times of both sides (filterpy compiles nothing)."""
    from jaxobs.papers._output import pyplot, save_figure

    fig, (speed, compile_ax) = pyplot().subplots(1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [3, 2]})
    labels, x = [], 0
    colors = {"filterpy": "tab:orange", "cuthbert": "tab:purple"}
    for batch, record in results.items():
        for case in CASES:
            r = record[case]
            if "ratio_peer_over_jaxobs" not in r:
                continue
            ratio = r["ratio_peer_over_jaxobs"]
            med = ratio["median"]
            speed.bar(x, med, color=colors[r["peer_name"]], width=0.7)
            speed.errorbar(x, med, yerr=[[med - ratio["min"]], [ratio["max"] - med]], color="k", capsize=3, lw=0.8)
            speed.text(x, ratio["max"], f"{med:.3g}x", ha="center", va="bottom", fontsize=8)
            width = 0.35
            compile_ax.bar(x - width / 2, r["jaxobs"]["compile_s"], width, color="tab:blue")
            if r["peer"]["compile_s"] is not None:
                compile_ax.bar(x + width / 2, r["peer"]["compile_s"], width, color=colors[r["peer_name"]])
            labels.append(f"{case}\nvs {r['peer_name']}\n{batch}")
            x += 1
    speed.axhline(1.0, color="grey", lw=0.8)
    speed.set_yscale("log")
    speed.set_xticks(range(len(labels)), labels, fontsize=8)
    speed.set_ylabel("peer time / jaxobs time\n(median of paired rounds, bar: [min, max])")
    speed.set_title("speed: above 1, jaxobs is faster")
    compile_ax.set_xticks(range(len(labels)), labels, fontsize=8)
    compile_ax.set_ylabel("first-call compile time [s]")
    compile_ax.set_title("compile time (filterpy: none, pure Python)")
    from matplotlib.patches import Patch

    compile_ax.legend(handles=[Patch(color="tab:blue", label="jaxobs"), Patch(color="tab:orange", label="filterpy"),
                               Patch(color="tab:purple", label="cuthbert")], fontsize=8)  # fmt: skip
    fig.suptitle(f"benchmarks/estimation_breadth.py: T={meta['steps']}, float64, {meta['rounds']} interleaved rounds, "
                 f"{meta['device']}, load {meta['load_average']}", fontsize=9)  # fmt: skip
    save_figure(fig, path.parent, path.stem)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args(argv)
    load = lambda: round(os.getloadavg()[0], 1) if hasattr(os, "getloadavg") else None  # noqa: E731
    before = load()
    results = measure(args.batches, args.steps, args.rounds)
    meta = {"steps": args.steps, "rounds": args.rounds, "platform": platform.platform(), "cpus": os.cpu_count(),
            "device": str(jax.devices()[0]), "jax": jax.__version__,
            "load_average": f"{before} to {load()}"}  # fmt: skip
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "estimation_breadth.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    plot(results, meta, out / "estimation_breadth.png")
    print(report(results))
    print(f"wrote {out / 'estimation_breadth.json'} and {out / 'estimation_breadth.png'}")
    return results


if __name__ == "__main__":
    main()
