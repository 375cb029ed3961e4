"""Learning Q and R from data: the errors of the maximum-likelihood estimates against the record length T, and the
fitted filter's one-step prediction error against the true model's.

The true model (n = 2 states, p = 2 outputs, full Q and R)::

    Phi = [[0.9, 0.2], [0, 0.7]],  C = [[1, 0], [1, 1]],  Q = [[0.5, 0.1], [0.1, 0.3]],  R = [[0.2, 0.05], [0.05, 0.4]]

with the prior ``x0 = 0``, ``P0 = I`` known. For each T in ``--lengths`` and each seed, one record is drawn
(:func:`jaxobs.learning.sample`) and full ``Q`` and ``R`` are fitted from ``Q = R = I`` by
:func:`jaxobs.learning.fit` (L-BFGS, Cholesky parameterisation) and by :func:`jaxobs.learning.em` (EM, until the
relative log-likelihood change is below 1e-12). Reported per (T, seed): the relative Frobenius errors
``|Q_hat - Q| / |Q|`` and ``|R_hat - R| / |R|`` of the fit, the largest difference between the fit's and EM's
estimates, both log-likelihoods; then, on a fresh record of ``--test-length`` samples, the mean squared one-step
prediction error ``mean_k |y_k - C x_{k|k-1}|^2 / p`` of the fitted and of the true filter, with the standard
error of the true filter's (its innovations are white) and of the paired difference.

Per T: the root-mean-square error over the seeds; between the shortest and the longest T, the slope of
``log RMS error`` against ``log T`` (the theory: -1/2).

Run::

    python benchmarks/learning.py --out DIR [--lengths 1000 10000] [--seeds 5] [--test-length 10000]

Writes ``DIR/learning.json`` and prints the tables.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxobs.learning import FitSettings, covariance_model, em, fit, sample  # noqa: E402
from jaxobs.observers import EstimatorInputs, run  # noqa: E402
from jaxobs.observers.kalman import kalman_filter, make_kalman  # noqa: E402

PHI = [[0.9, 0.2], [0.0, 0.7]]
C = [[1.0, 0.0], [1.0, 1.0]]
Q = [[0.5, 0.1], [0.1, 0.3]]
R = [[0.2, 0.05], [0.05, 0.4]]


def true_model():
    return make_kalman(PHI, C, Q, R, P0=jnp.eye(2))


def initial_model():
    return make_kalman(PHI, C, jnp.eye(2), jnp.eye(2), P0=jnp.eye(2))


_filter = jax.jit(lambda params, y: run(kalman_filter, params, EstimatorInputs(y=y))[1].innovation)


def prediction_error(fitted, truth, y) -> dict:
    """Mean squared one-step prediction errors of the fitted and true filters on ``y`` (T, p), with standard
    errors."""
    e_fit = np.sum(np.asarray(_filter(fitted, y)) ** 2, axis=1) / y.shape[1]
    e_true = np.sum(np.asarray(_filter(truth, y)) ** 2, axis=1) / y.shape[1]
    T = y.shape[0]
    return {"mse_fitted": float(e_fit.mean()), "mse_true": float(e_true.mean()),
            "se_true": float(e_true.std(ddof=1) / math.sqrt(T)),
            "se_paired_difference": float((e_fit - e_true).std(ddof=1) / math.sqrt(T))}  # fmt: skip


def relative_error(estimate, truth) -> float:
    return float(np.linalg.norm(np.asarray(estimate) - np.asarray(truth)) / np.linalg.norm(np.asarray(truth)))


def one_case(T: int, seed: int, test_length: int) -> dict:
    truth = true_model()
    _, y = sample(truth, jax.random.PRNGKey(seed), T)
    inputs = EstimatorInputs(y=y[None])
    build, theta0 = covariance_model(initial_model())
    start = time.perf_counter()
    result = fit(kalman_filter, build, theta0, inputs, FitSettings(steps=300), progress=False)
    fit_seconds = time.perf_counter() - start
    start = time.perf_counter()
    by_em = em(initial_model(), inputs, iterations=3000, tolerance=1e-12)
    jax.block_until_ready(by_em.params.Q)
    em_seconds = time.perf_counter() - start
    iterations = int(by_em.iterations)
    _, y_test = sample(truth, jax.random.PRNGKey(10_000 + seed), test_length)
    return {
        "T": T, "seed": seed,
        "error_Q": relative_error(result.params.Q, Q), "error_R": relative_error(result.params.R, R),
        "fit_steps": len(result.loss), "fit_stopped": result.stopped, "fit_seconds": fit_seconds,
        "log_likelihood_fit": -result.best_loss * y.size,
        "em_iterations": iterations, "em_converged": bool(by_em.converged), "em_seconds": em_seconds,
        "log_likelihood_em": float(by_em.log_likelihood[iterations - 1]),
        "max_difference_fit_em": float(max(np.max(np.abs(result.params.Q - by_em.params.Q)),
                                           np.max(np.abs(result.params.R - by_em.params.R)))),
        **prediction_error(result.params, truth, y_test),
        "Q_hat": np.asarray(result.params.Q).tolist(), "R_hat": np.asarray(result.params.R).tolist(),
    }  # fmt: skip


def summary(cases: list[dict]) -> dict:
    """RMS errors over the seeds per T and the slope of log RMS error against log T (shortest to longest T)."""
    lengths = sorted({c["T"] for c in cases})
    rms = {T: {k: float(np.sqrt(np.mean([c[k] ** 2 for c in cases if c["T"] == T]))) for k in ("error_Q", "error_R")}
           for T in lengths}  # fmt: skip
    slopes = {}
    if len(lengths) > 1:
        lo, hi = lengths[0], lengths[-1]
        slopes = {k: math.log(rms[hi][k] / rms[lo][k]) / math.log(hi / lo) for k in ("error_Q", "error_R")}
    return {"rms": {str(T): v for T, v in rms.items()}, "slope": slopes}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--lengths", type=int, nargs="+", default=[1000, 10000])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--test-length", type=int, default=10000)
    args = parser.parse_args(argv)
    cases = []
    print(f"{'T':>6} {'seed':>4} {'err Q':>8} {'err R':>8} {'|fit-EM|':>9} {'steps':>5} {'EM it':>6} "
          f"{'mse fit':>9} {'mse true':>9} {'se true':>8} {'se diff':>8} {'fit s':>6} {'EM s':>6}")  # fmt: skip
    for T in args.lengths:
        for seed in range(args.seeds):
            c = one_case(T, seed, args.test_length)
            cases.append(c)
            print(f"{T:>6} {seed:>4} {c['error_Q']:8.4f} {c['error_R']:8.4f} {c['max_difference_fit_em']:9.2e} "
                  f"{c['fit_steps']:>5} {c['em_iterations']:>6} {c['mse_fitted']:9.5f} {c['mse_true']:9.5f} "
                  f"{c['se_true']:8.5f} {c['se_paired_difference']:8.1e} {c['fit_seconds']:6.1f} "
                  f"{c['em_seconds']:6.1f}", flush=True)  # fmt: skip
    result = {"platform": platform.platform(), "jax": jax.__version__, "cases": cases, **summary(cases)}
    for T, v in result["rms"].items():
        print(f"T = {T:>6}: RMS relative error over {args.seeds} seeds: Q {v['error_Q']:.4f}, R {v['error_R']:.4f}")
    if result["slope"]:
        print(f"slope of log RMS error against log T: Q {result['slope']['error_Q']:.2f}, "
              f"R {result['slope']['error_R']:.2f} (theory -0.5)")  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "learning.json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
