"""Speed of the jaxobs extended and unscented Kalman filters against dynamax's, on a pendulum.

What is measured (float64): the sampled pendulum of Särkkä 2013, state (angle, rate), ``x_{k+1} = (a + w dt,
w - g sin(a) dt) + noise``, measured ``sin(a)`` with noise; ``T = 1000`` samples, ``B`` in {1, 64} independent
measurement sequences of the same model. Each filter is ``jit(vmap(...))`` over the sequences (one
``lax.scan`` per filter; every sequence runs its own covariance recursion, since the EKF's and UKF's covariances
depend on the data). The UKF is the unscented rule with dynamax's default ``(alpha, beta, kappa) = (sqrt 3, 2,
1)`` on both sides. jaxobs returns the filtered means, covariances, prior means, innovations and gains;
dynamax its filtered means and covariances (and the marginal log-likelihood). The same prior of ``x_0``
(dynamax's convention and ours agree: no prediction before the first update).

Agreement: the filtered means of both libraries on the benchmark data (max relative difference; dynamax adds
1e-9 I to every matrix it inverts, so about 1e-9 is expected here, 1e-15 without it: tests/observers/test_ekf.py and
tests/observers/test_ukf.py).

Timing (``benchmarks/_timing.py``): every function is compiled first (the compile time is reported apart);
then ``--rounds`` interleaved rounds run every entry once; times are the median [min, max] over the rounds,
and the ratio ``dynamax time / jaxobs time`` is taken round by round (paired).

Run (``make bench`` does it with ``--out out/bench``)::

    python benchmarks/nonlinear.py --out DIR [--steps 1000] [--batches 1 64] [--rounds 7]

Writes ``DIR/nonlinear.json`` and prints a table.
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
from _timing import Skipped, format_range, paired_ratio, time_interleaved  # noqa: E402

import jaxobs as jo  # noqa: E402

DT, GRAVITY = 0.0125, 9.81
Q = 1.0 * np.array([[DT**3 / 3, DT**2 / 2], [DT**2 / 2, DT]])
R = np.array([[0.09]])
X0, P0 = np.array([1.4, 0.1]), 0.3 * np.eye(2)
UKF = dict(alpha=float(np.sqrt(3.0)), beta=2.0, kappa=1.0)  # dynamax's default UKFHyperParams


def pendulum_f(x):
    return jnp.array([x[0] + x[1] * DT, x[1] - GRAVITY * jnp.sin(x[0]) * DT])


def pendulum_h(x):
    return jnp.sin(x[:1])


def simulate(B: int, T: int, seed: int = 0) -> np.ndarray:
    """(B, T, 1) measurements of B pendulums started at angles in [1, 2] rad."""
    rng = np.random.default_rng(seed)
    x = np.stack([rng.uniform(1.0, 2.0, B), np.zeros(B)], axis=1)
    noise = rng.multivariate_normal(np.zeros(2), Q, size=(T, B))
    f = jax.jit(jax.vmap(pendulum_f))
    ys = []
    for k in range(T):
        if k:
            x = np.asarray(f(x)) + noise[k]
        ys.append(np.sin(x[:, :1]) + np.sqrt(R[0, 0]) * rng.normal(size=(B, 1)))
    return np.stack(ys, axis=1)


def ours(kind: str):
    model = jo.nonlinear_model(lambda x, u, t: pendulum_f(x), pendulum_h, Q, R, x0=X0, P0=P0, dt=DT)
    params = jo.make_ekf(model) if kind == "ekf" else jo.make_ukf(model, **UKF)
    estimator = jo.extended_kalman_filter if kind == "ekf" else jo.unscented_kalman_filter

    def run(ys):
        return jax.vmap(lambda y: jo.run(estimator, params, jo.EstimatorInputs(y))[1])(ys)

    return run


def dynamax(kind: str):
    try:
        from dynamax.nonlinear_gaussian_ssm import (
            ParamsNLGSSM,
            UKFHyperParams,
            extended_kalman_filter,
            unscented_kalman_filter,
        )
    except ImportError as exc:
        raise Skipped(f"dynamax not installed: {exc}") from exc
    params = ParamsNLGSSM(jnp.asarray(X0), jnp.asarray(P0), pendulum_f, jnp.asarray(Q), pendulum_h, jnp.asarray(R))
    if kind == "ekf":
        one = lambda y: extended_kalman_filter(params, y)
    else:
        one = lambda y: unscented_kalman_filter(params, y, UKFHyperParams(**UKF))
    return lambda ys: jax.vmap(one)(ys)


def measure(batches, T: int, rounds: int) -> dict:
    results = {}
    for B in batches:
        ys = jnp.asarray(simulate(B, T))
        entries = {}
        for kind in ("ekf", "ukf"):
            entries[f"jaxobs_{kind}"] = (lambda kind=kind, ys=ys: (ours(kind), (ys,)), True, 1.0)
            entries[f"dynamax_{kind}"] = (lambda kind=kind, ys=ys: (dynamax(kind), (ys,)), True, 1.0)
        timings, problems = time_interleaved(entries, rounds, required=("jaxobs_ekf", "jaxobs_ukf"))
        record = {"problems": problems}
        for kind in ("ekf", "ukf"):
            mine = timings[f"jaxobs_{kind}"]
            record[f"jaxobs_{kind}"] = mine.record(B * T, "steps/s")
            peer = timings.get(f"dynamax_{kind}")
            if peer is None:
                continue
            record[f"dynamax_{kind}"] = peer.record(B * T, "steps/s")
            record[f"ratio_dynamax_over_jaxobs_{kind}"] = paired_ratio(mine, peer)
            a, b = np.asarray(mine.result.x), np.asarray(peer.result.filtered_means)
            record[f"max_relative_difference_{kind}"] = float(np.max(np.abs(a - b)) / np.max(np.abs(b)))
        results[f"B={B}"] = record
    return results


def _ms(summary: dict) -> str:
    return format_range({k: summary[k] * 1e3 for k in ("median", "min", "max")}, ".3g")


def report(results: dict) -> str:
    lines = [f"{'case':<10} {'jaxobs (ms)':<24} {'compile (s)':<12} {'dynamax (ms)':<24} {'compile (s)':<12} "
             "dynamax/jaxobs        max rel diff"]  # fmt: skip
    for case, r in results.items():
        for kind in ("ekf", "ukf"):
            mine, peer = r[f"jaxobs_{kind}"], r.get(f"dynamax_{kind}")
            row = f"{case + ' ' + kind.upper():<10} {_ms(mine['seconds']):<24} {mine['compile_s']:<12.2f} "
            if peer is None:
                lines.append(row + f"dynamax: {r['problems'].get(f'dynamax_{kind}')}")
                continue
            lines.append(row + f"{_ms(peer['seconds']):<24} {peer['compile_s']:<12.2f} "
                         f"{format_range(r[f'ratio_dynamax_over_jaxobs_{kind}'], '.2f'):<21} "
                         f"{r[f'max_relative_difference_{kind}']:.1e}")  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args(argv)
    results = measure(args.batches, args.steps, args.rounds)
    meta = {"steps": args.steps, "rounds": args.rounds, "platform": platform.platform(),
            "device": str(jax.devices()[0]), "jax": jax.__version__}  # fmt: skip
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "nonlinear.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    print(report(results))
    print(f"wrote {out / 'nonlinear.json'}")
    return results


if __name__ == "__main__":
    main()
