"""Speed of the jaxobs particle filter and ensemble Kalman filter against cuthbert and filterpy.

What is measured (float64), each workload over ``B`` independent measurement sequences of one model:

* ``pf``: the bootstrap particle filter's log-likelihood estimate of the growth model of Kitagawa (1996),
  ``x_k = x/2 + 25 x / (1 + x^2) + 8 cos(1.2 k) + w``, ``y = x^2 / 20 + v`` (``q = 10``, ``r = 1``), with ``N``
  particles over ``T`` samples, systematic resampling when the effective sample size drops below ``N / 2``:
  jaxobs ``make_particle_filter`` against cuthbert's ``smc.particle_filter`` (``systematic.resampling`` in its
  ``ess_decorator``). Both ``jit(vmap(...))`` over the sequences and their keys.
* ``pf_grad``: the same log-likelihood and its gradient with respect to ``(log q, log r)``, stop-gradient
  resampling on both sides (cuthbert's ``stop_gradient_decorator``; jaxobs resamples that way always).
* ``enkf``: the stochastic ensemble Kalman filter (perturbed observations) on Lorenz-96 with 40 states (RK4,
  ``dt = 0.05``, forcing 8), every other state measured, ``N`` members, ``T`` samples: jaxobs ``make_enkf``
  (``jit(vmap)``), cuthbert's ``ensemble_kalman`` filter (``jit(vmap)``) and filterpy's
  ``EnsembleKalmanFilter`` (NumPy, one member at a time through ``fx`` and ``hx``; no batched form: timed on
  one sequence and multiplied by ``B``).

Every filter starts from the same prior of ``x_0`` and updates with ``y_0`` before its first prediction (cuthbert
is given an identity transition into the first sample). The draws differ between libraries, so the agreement
recorded in the JSON is statistical for the particle filters (mean and standard error of the log-likelihood over
64 keys on one sequence, each library) and exact for filterpy's EnKF (fed jaxobs's initial ensemble and draws:
the largest difference of the ensembles over the run).

Timing (``benchmarks/_timing.py``): every JAX function is compiled first (compile times reported apart), then
``--rounds`` interleaved rounds run every entry once; times are the median [min, max] over the rounds and each
ratio ``peer time / jaxobs time`` is taken round by round (paired).

Run::

    python benchmarks/particle_ensemble.py --out DIR [--batches 1 32] [--particles 1000] [--members 50]
        [--steps 100] [--rounds 5] [--workloads pf pf_grad enkf]

Writes ``DIR/particle_ensemble.json`` and ``DIR/particle_ensemble.png`` (the ratios and the compile times) and
prints a table.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import Skipped, format_range, optional_import, paired_ratio, time_interleaved  # noqa: E402

import jaxobs as jo  # noqa: E402
from jaxobs.observers import ensemble  # noqa: E402

cuthbert, CUTHBERT_MISSING = optional_import("cuthbert")
filterpy_enkf, FILTERPY_MISSING = optional_import("filterpy.kalman.ensemble_kalman_filter")

GROWTH_Q, GROWTH_R, GROWTH_P0 = 10.0, 1.0, 5.0
L96_N, L96_DT, L96_F = 40, 0.05, 8.0
L96_Q, L96_R = 0.01, 0.5
PEERS = {"pf": ("cuthbert",), "pf_grad": ("cuthbert",), "enkf": ("cuthbert", "filterpy")}


# --------------------------------------------------------------------------------------------
# Models and data


def growth_f(x, u, t):
    return x / 2 + 25 * x / (1 + x**2) + 8 * jnp.cos(1.2 * (t + 1))


def growth_h(x):
    return x**2 / 20


def _lorenz96(x, xp):
    return (xp.roll(x, -1) - xp.roll(x, 2)) * xp.roll(x, 1) - x + L96_F


def lorenz96_f(x, u=None, t=None, xp=jnp):
    """One RK4 step of Lorenz-96 (``xp``: jax.numpy or NumPy, for filterpy's per-member calls)."""
    k1 = _lorenz96(x, xp)
    k2 = _lorenz96(x + L96_DT / 2 * k1, xp)
    k3 = _lorenz96(x + L96_DT / 2 * k2, xp)
    k4 = _lorenz96(x + L96_DT * k3, xp)
    return x + L96_DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def lorenz96_h(x):
    return x[::2]


def growth_data(B: int, T: int, seed: int = 0) -> np.ndarray:
    """(B, T, 1) measurements of the growth model."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=B) * np.sqrt(GROWTH_P0)
    ys = []
    for k in range(T):
        if k:
            x = np.asarray(growth_f(x, None, k - 1.0)) + np.sqrt(GROWTH_Q) * rng.normal(size=B)
        ys.append(x**2 / 20 + np.sqrt(GROWTH_R) * rng.normal(size=B))
    return np.stack(ys, axis=1)[..., None]


def lorenz96_data(B: int, T: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(x0 (B, 40), y (B, T, 20))``: states spun up onto the attractor, then simulated with noise."""
    rng = np.random.default_rng(seed)
    x = L96_F + rng.normal(size=(B, L96_N))
    step = jax.jit(jax.vmap(lorenz96_f))
    for _ in range(500):
        x = np.asarray(step(x))
    x0, ys = x.copy(), []
    for k in range(T):
        if k:
            x = np.asarray(step(x)) + np.sqrt(L96_Q) * rng.normal(size=x.shape)
        ys.append(x[:, ::2] + np.sqrt(L96_R) * rng.normal(size=(B, L96_N // 2)))
    return x0, np.stack(ys, axis=1)


def lorenz96_model(x0):
    return jo.nonlinear_model(lorenz96_f, lorenz96_h, L96_Q * jnp.eye(L96_N), L96_R * jnp.eye(L96_N // 2), x0=x0,
                              P0=jnp.eye(L96_N))  # fmt: skip


# --------------------------------------------------------------------------------------------
# The particle filters


def ours_pf(N: int):
    def log_likelihood(theta, y, key):
        model = jo.nonlinear_model(growth_f, growth_h, jnp.exp(theta[0]) * jnp.eye(1), jnp.exp(theta[1]) * jnp.eye(1),
                                   x0=[0.0], P0=[[GROWTH_P0]])  # fmt: skip
        params = jo.make_particle_filter(model, N, key=key)
        return jnp.sum(jo.run(jo.particle_filter, params, jo.EstimatorInputs(y=y))[1].log_likelihood)

    return log_likelihood


def cuthbert_pf(N: int, differentiable: bool):
    if cuthbert is None:
        raise Skipped(f"cuthbert not importable: {CUTHBERT_MISSING}")
    from cuthbert.smc import particle_filter
    from cuthbertlib.resampling import adaptive, autodiff, systematic

    resampling = autodiff.stop_gradient_decorator(systematic.resampling) if differentiable else systematic.resampling
    resampling = adaptive.ess_decorator(resampling, 0.5)

    def log_likelihood(theta, y, key):
        q, r = jnp.exp(theta[0]), jnp.exp(theta[1])

        def propagate(key, x, inputs):  # the identity into the first sample: x_0 is drawn from its prior
            moved = growth_f(x, None, inputs["k"] - 1.0) + jnp.sqrt(q) * jax.random.normal(key, (1,))
            return jnp.where(inputs["k"] == 0, x, moved)

        def log_potential(x_prev, x, inputs):
            return jax.scipy.stats.norm.logpdf(inputs["y"][0], growth_h(x)[0], jnp.sqrt(r))

        init_sample = lambda key: jnp.sqrt(GROWTH_P0) * jax.random.normal(key, (1,))
        filter_obj = particle_filter.build_filter(init_sample, propagate, log_potential, N, resampling)
        init_key, run_key = jax.random.split(key)
        init = filter_obj.init_prepare(key=init_key)
        inputs = {"k": jnp.arange(y.shape[0]), "y": y}
        return cuthbert.filter(filter_obj, inputs, init, key=run_key).log_normalizing_constant[-1]

    return log_likelihood


def pf_entries(workload: str, y, N: int) -> tuple[dict, dict]:
    """``{name: (prepare, jit, scale)}`` of one particle-filter cell, and the functions by name."""
    theta = jnp.log(jnp.array([GROWTH_Q, GROWTH_R]))
    keys = jax.random.split(jax.random.key(1), y.shape[0])
    grad = workload == "pf_grad"
    functions = {"jaxobs": lambda: ours_pf(N), "cuthbert": lambda: cuthbert_pf(N, grad)}

    def prepare(name):
        def build():
            one = functions[name]()
            fn, args = jax.vmap(jax.value_and_grad(one) if grad else one, (None, 0, 0)), (theta, jnp.asarray(y), keys)
            if name == "cuthbert":  # its CPU resampling is a Numba callback, compiled on the first call: not timed
                jax.block_until_ready(jax.jit(fn)(*args))
            return fn, args

        return build

    return {name: (prepare(name), True, 1.0) for name in functions}, functions


def pf_agreement(N: int) -> dict:
    """Mean and standard error of each library's log-likelihood estimate over 64 keys on one sequence."""
    y = jnp.asarray(growth_data(1, 50, seed=3)[0])
    theta = jnp.log(jnp.array([GROWTH_Q, GROWTH_R]))
    keys = jax.random.split(jax.random.key(2), 64)
    found = {}
    for name, build in (("jaxobs", lambda: ours_pf(N)), ("cuthbert", lambda: cuthbert_pf(N, False))):
        try:
            values = np.asarray(jax.jit(jax.vmap(build(), (None, None, 0)))(theta, y, keys))
        except Skipped as exc:
            found[name] = {"status": "skipped", "reason": str(exc)}
            continue
        found[name] = {"mean": float(values.mean()), "standard_error": float(values.std() / np.sqrt(len(values)))}
    return found


# --------------------------------------------------------------------------------------------
# The ensemble Kalman filters


def ours_enkf(N: int):
    def means(x0, y, key):
        params = jo.make_enkf(lorenz96_model(x0), N, key=key)
        return jo.run(jo.ensemble_kalman_filter, params, jo.EstimatorInputs(y=y))[1].x

    return means


def cuthbert_enkf(N: int):
    if cuthbert is None:
        raise Skipped(f"cuthbert not importable: {CUTHBERT_MISSING}")
    from cuthbert.ensemble_kalman import ensemble_kalman_filter

    chol_Q, chol_R = np.sqrt(L96_Q) * jnp.eye(L96_N), np.sqrt(L96_R) * jnp.eye(L96_N // 2)

    def means(x0, y, key):
        def get_dynamics(inputs):
            def dynamics(x, key):  # the identity into the first sample, as jaxobs
                moved = lorenz96_f(x) + chol_Q @ jax.random.normal(key, (L96_N,))
                return jnp.where(inputs["k"] == 0, x, moved)

            return dynamics

        init_sample = lambda key: x0 + jax.random.normal(key, (L96_N,))
        observations = lambda inputs: (lorenz96_h, chol_R, inputs["y"])
        filter_obj = ensemble_kalman_filter.build_filter(init_sample, get_dynamics, observations, N)
        init_key, run_key = jax.random.split(key)
        inputs = {"k": jnp.arange(y.shape[0]), "y": y}
        states = cuthbert.filter(filter_obj, inputs, filter_obj.init_prepare(key=init_key), key=run_key)
        return jnp.mean(states.ensemble[1:], axis=-2)

    return means


def filterpy_enkf_run(x0, y, N: int, first_ensemble=None, draws=None):
    """filterpy's EnsembleKalmanFilter over one sequence: its means (T, 40). With ``first_ensemble`` and
    ``draws`` (the process noises and observation perturbations in the order it asks for them) it is fed them
    instead of its own random numbers; returns then also its ensembles."""
    if filterpy_enkf is None:
        raise Skipped(f"filterpy not importable: {FILTERPY_MISSING}")
    peer = filterpy_enkf.EnsembleKalmanFilter(x=np.asarray(x0), P=np.eye(L96_N), dim_z=L96_N // 2, dt=L96_DT, N=N,
                                              hx=lorenz96_h, fx=lambda x, dt: lorenz96_f(x, xp=np))  # fmt: skip
    peer.Q, peer.R = L96_Q * np.eye(L96_N), L96_R * np.eye(L96_N // 2)
    original = filterpy_enkf.multivariate_normal
    if draws is not None:
        peer.sigmas, peer.x = np.array(first_ensemble), np.mean(first_ensemble, axis=0)
        supply = iter(draws)
        filterpy_enkf.multivariate_normal = lambda mean, cov, size: next(supply)
    means, ensembles = [], []
    try:
        for k in range(len(y)):
            if k:
                peer.predict()
            peer.update(np.asarray(y[k]))
            means.append(peer.x.copy())
            ensembles.append(peer.sigmas.copy())
    finally:
        filterpy_enkf.multivariate_normal = original
    return (np.array(means), np.array(ensembles)) if draws is not None else np.array(means)


def enkf_entries(x0, y, N: int) -> dict:
    B = y.shape[0]
    keys = jax.random.split(jax.random.key(1), B)

    def jax_entry(build):
        return lambda: (jax.vmap(build(N)), (jnp.asarray(x0), jnp.asarray(y), keys))

    def filterpy_entry():
        if filterpy_enkf is None:
            raise Skipped(f"filterpy not importable: {FILTERPY_MISSING}")
        return (lambda: filterpy_enkf_run(x0[0], y[0], N)), ()

    return {"jaxobs": (jax_entry(ours_enkf), True, 1.0), "cuthbert": (jax_entry(cuthbert_enkf), True, 1.0),
            "filterpy": (filterpy_entry, False, float(B))}  # fmt: skip


def enkf_agreement(N: int, T: int) -> dict:
    """filterpy fed jaxobs's initial ensemble and draws: the largest difference of the ensembles over ``T``
    samples (exact agreement expected, to rounding)."""
    if filterpy_enkf is None:
        return {"status": "skipped", "reason": FILTERPY_MISSING}
    x0, y = lorenz96_data(1, T, seed=4)
    params = jo.make_enkf(lorenz96_model(jnp.asarray(x0[0])), N, key=jax.random.key(5), output_ensemble=True)
    state = jo.ensemble_kalman_filter.init(params)
    out = jax.jit(lambda p: jo.run(jo.ensemble_kalman_filter, p, jo.EstimatorInputs(y=jnp.asarray(y[0])))[1])(params)
    key, draws, perturbations = state.key, [], jax.jit(ensemble.perturbations)
    for k in range(T):
        key, W, E = perturbations(params, key)
        draws += ([np.asarray(W)] if k else []) + [np.asarray(E)]
    _, ensembles = filterpy_enkf_run(x0[0], y[0], N, np.asarray(state.ensemble), draws)
    return {"samples": T, "max_abs_difference_of_ensembles": float(np.max(np.abs(ensembles - out.ensemble)))}


# --------------------------------------------------------------------------------------------
# Cells, table, figure


def cell(workload: str, B: int, args) -> dict:
    if workload == "enkf":
        x0, y = lorenz96_data(B, args.steps)
        entries = enkf_entries(x0, y, args.members)
    else:
        entries, _ = pf_entries(workload, growth_data(B, args.steps), args.particles)
    timings, problems = time_interleaved(entries, args.rounds, required=("jaxobs",))
    ours = timings["jaxobs"]
    entries = {name: t.record(B * args.steps, "sequence-steps/s") for name, t in timings.items()}
    record = {"batch": B, "entries": entries}
    record["entries"].update(problems)
    record["ratios"] = {name: paired_ratio(ours, t) for name, t in timings.items() if name != "jaxobs"}
    return record


def table(results: dict) -> str:
    lines = [f"{'workload':9} {'B':>4} {'entry':9} {'time per call (s)':>28} {'compile (s)':>11} "
             f"{'peer / jaxobs':>24}"]  # fmt: skip
    for workload, cells in results["workloads"].items():
        for record in cells:
            for name, entry in record["entries"].items():
                if entry["status"] != "ok":
                    lines.append(f"{workload:9} {record['batch']:>4} {name:9} {entry['status']}: {entry['reason']}")
                    continue
                ratio = record["ratios"].get(name)
                compile_s = "-" if entry["compile_s"] is None else f"{entry['compile_s']:.2f}"
                lines.append(f"{workload:9} {record['batch']:>4} {name:9} {format_range(entry['seconds']):>28} "
                             f"{compile_s:>11} {format_range(ratio, '.3g', 'x') if ratio else '':>24}")  # fmt: skip
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot, save_figure

    fig, (ax, bx) = pyplot().subplots(1, 2, figsize=(13, 5), gridspec_kw={"width_ratios": [3, 2]})
    colors = {"cuthbert": "tab:blue", "filterpy": "tab:orange"}
    x, ticks, labels, compile_rows = 0.0, [], [], []
    for workload, cells in results["workloads"].items():
        for record in cells:
            for peer, ratio in record["ratios"].items():
                med = ratio["median"]
                ax.bar(x, med, color=colors[peer], width=0.8)
                ax.errorbar(x, med, yerr=[[med - ratio["min"]], [ratio["max"] - med]], color="k", capsize=3, lw=0.8)
                ax.text(x, ratio["max"], f"{med:.2g}x", ha="center", va="bottom", fontsize=8)
                ticks.append(x)
                labels.append(f"{workload}\nB={record['batch']}\n{peer}")
                x += 1
            x += 0.5
            entries = {n: e for n, e in record["entries"].items() if e["status"] == "ok" and e["compile_s"]}
            compile_rows.append((f"{workload} B={record['batch']}", {n: e["compile_s"] for n, e in entries.items()}))
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_yscale("log")
    ax.set_xticks(ticks, labels, fontsize=7)
    ax.set_ylabel("speedup: peer time / jaxobs time\n(median of paired rounds, bar: [min, max])")
    from matplotlib.patches import Patch

    names = {"cuthbert": "cuthbert (jit(vmap))", "filterpy": "filterpy (NumPy; B > 1: one sequence's time x B)"}
    ax.legend(handles=[Patch(color=c, label=names[p]) for p, c in colors.items()], fontsize=8, loc="upper left")
    for i, name in enumerate(["jaxobs", "cuthbert"]):
        values = [row[1].get(name, np.nan) for row in compile_rows]
        bx.barh(np.arange(len(compile_rows)) + 0.4 * i, values, height=0.4, label=name,
                color={"jaxobs": "tab:green", "cuthbert": "tab:blue"}[name])  # fmt: skip
    bx.set_yticks(np.arange(len(compile_rows)) + 0.2, [row[0] for row in compile_rows], fontsize=8)
    bx.set_xlabel("compile time of the jitted call (s)")
    bx.legend(fontsize=8)
    cfg = results["config"]
    env = results["environment"]
    fig.suptitle(f"Particle filter (N={cfg['particles']}) and EnKF (N={cfg['members']}, Lorenz-96 n=40), "
                 f"T={cfg['steps']}, float64, {env['device_kind']} ({env['cpus']} cores, load average "
                 f"{env['load_average'][0]:.1f}), {cfg['rounds']} interleaved rounds "
                 "(benchmarks/particle_ensemble.py)", fontsize=10)  # fmt: skip
    fig.tight_layout()
    save_figure(fig, path.parent, path.stem, dpi=130)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 32])
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--members", type=int, default=50)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--workloads", nargs="+", default=["pf", "pf_grad", "enkf"], choices=list(PEERS))
    parser.add_argument("--no-plot", action="store_true")
    args = parser.parse_args(argv)
    results = {
        "config": {k: v for k, v in vars(args).items() if k not in ("out", "no_plot")},
        "environment": {
            "platform": platform.platform(),
            "device_kind": jax.devices()[0].device_kind,
            "jax": jax.__version__,
            "cpus": os.cpu_count(),
            "load_average": os.getloadavg(),
        },  # fmt: skip
        "workloads": {},
    }
    for workload in args.workloads:
        results["workloads"][workload] = [cell(workload, B, args) for B in args.batches]
    results["agreement"] = {}
    if {"pf", "pf_grad"} & set(args.workloads):
        results["agreement"]["pf_log_likelihood"] = pf_agreement(args.particles)
    if "enkf" in args.workloads:
        results["agreement"]["enkf_filterpy"] = enkf_agreement(args.members, min(args.steps, 50))
    results["environment"]["load_average_after"] = os.getloadavg()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "particle_ensemble.json").write_text(json.dumps(results, indent=2))
    print(table(results))
    print(json.dumps(results["agreement"], indent=2))
    if not args.no_plot:
        plot(results, args.out / "particle_ensemble.png")
    return results


if __name__ == "__main__":
    main()
