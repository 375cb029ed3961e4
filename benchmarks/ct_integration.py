"""Speed of jaxobs.ct's fixed-step RK4 against diffrax on small batched systems, forward and in reverse mode.

What is measured (float64): a sampled trajectory of the forced Van der Pol oscillator ``x1' = x2,
x2' = mu (1 - x1^2) x2 - x1 + u`` with a random input held over each of ``K = 200`` samples of ``h = 0.05`` s,
``S = 4`` RK4 substeps per sample, ``B`` in {1, 64} initial states (``vmap``). Both sides run the same method
with the same steps: jaxobs ``ct.trajectory`` (one ``lax.scan`` over samples, one over substeps) and diffrax
``diffeqsolve`` per sample (inside a ``lax.scan`` over samples, as a sampled filter calls it) with the classical
RK4 tableau as an explicit Runge-Kutta solver of diffrax stepping to ``t_k + i h / S`` (``StepTo``). The two
trajectories agree to rounding (max abs difference reported).

* forward: the trajectories;
* reverse: the gradient of the sum of squared states with respect to ``mu`` (``jax.grad``; diffrax's default
  adjoint, recursive checkpointing; jaxobs plain reverse mode and with ``checkpoint=True``).

Timing (``benchmarks/_timing.py``): compiled first (compile time apart), interleaved rounds, median [min, max],
paired ratios ``diffrax time / jaxobs time``.

Run (``make bench`` does it with ``--out out/bench``)::

    python benchmarks/ct_integration.py --out DIR [--samples 200] [--substeps 4] [--batches 1 64] [--rounds 7]

Writes ``DIR/ct_integration.json`` and prints a table.
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

from jaxobs import ct  # noqa: E402

H = 0.05


def van_der_pol(x, u, t, mu):
    return jnp.stack([x[1], mu * (1 - x[0] ** 2) * x[1] - x[0] + u[0]])


def ours(substeps: int, checkpoint: bool = False):
    def trajectory(mu, x0s, u):
        f = lambda x, u, t: van_der_pol(x, u, t, mu)
        one = lambda x0: ct.trajectory(f, x0, u, h=H, substeps=substeps, checkpoint=checkpoint)
        return jax.vmap(one)(x0s)

    return trajectory


def diffrax_rk4_solver():
    """The classical RK4 rule as a diffrax solver (raises :class:`Skipped` without diffrax)."""
    try:
        import diffrax
    except ImportError as exc:
        raise Skipped(f"diffrax not installed: {exc}") from exc

    class RK4(diffrax.AbstractERK):
        """The classical fourth-order Runge-Kutta rule as a diffrax explicit Runge-Kutta solver."""

        tableau = diffrax.ButcherTableau(
            c=np.array([0.5, 0.5, 1.0]),
            b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
            b_error=np.zeros(4),
            a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
        )
        # dense output only (unused: the solves save the end point); RK4's k4 is not f(x1), so it is approximate
        interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

        def order(self, terms):
            return 4

    return RK4()


def diffrax_rk4(substeps: int):
    solver = diffrax_rk4_solver()
    import diffrax

    def trajectory(mu, x0s, u):
        term = diffrax.ODETerm(lambda t, x, u: van_der_pol(x, u, t, mu))

        def one(x0):
            def sample(x, inputs):
                u_k, t_k = inputs
                steps = diffrax.StepTo(t_k + H / substeps * jnp.arange(substeps + 1, dtype=x.dtype))
                sol = diffrax.diffeqsolve(term, solver, t_k, t_k + H, None, x, args=u_k, stepsize_controller=steps,
                                          saveat=diffrax.SaveAt(t1=True), max_steps=substeps)  # fmt: skip
                return sol.ys[-1], sol.ys[-1]

            _, xs = jax.lax.scan(sample, x0, (u, H * jnp.arange(u.shape[0], dtype=x0.dtype)))
            return jnp.concatenate([x0[None], xs])

        return jax.vmap(one)(x0s)

    return trajectory


def gradient(trajectory):
    return jax.grad(lambda mu, x0s, u: jnp.sum(trajectory(mu, x0s, u) ** 2))


def measure(batches, K: int, substeps: int, rounds: int) -> dict:
    results = {}
    rng = np.random.default_rng(0)
    for B in batches:
        args = (jnp.asarray(1.0), jnp.asarray(rng.normal(size=(B, 2))), jnp.asarray(rng.normal(size=(K, 1))))
        functions = {
            "jaxobs_forward": lambda: ours(substeps),
            "diffrax_forward": lambda: diffrax_rk4(substeps),
            "jaxobs_reverse": lambda: gradient(ours(substeps)),
            "jaxobs_reverse_checkpoint": lambda: gradient(ours(substeps, checkpoint=True)),
            "diffrax_reverse": lambda: gradient(diffrax_rk4(substeps)),
        }
        entries = {name: (lambda make=make, args=args: (make(), args), True, 1.0) for name, make in functions.items()}
        timings, problems = time_interleaved(entries, rounds, required=("jaxobs_forward", "jaxobs_reverse"))
        record = {"problems": problems}
        for name, timed in timings.items():
            record[name] = timed.record(B * K, "samples/s")
        for mode, mine in (("forward", "jaxobs_forward"), ("reverse", "jaxobs_reverse"),
                           ("reverse_checkpoint", "jaxobs_reverse_checkpoint")):  # fmt: skip
            peer = timings.get(f"diffrax_{mode.split('_')[0]}")
            if peer is not None and mine in timings:
                record[f"ratio_diffrax_over_jaxobs_{mode}"] = paired_ratio(timings[mine], peer)
        if "diffrax_forward" in timings:
            a, b = (np.asarray(timings[k].result) for k in ("jaxobs_forward", "diffrax_forward"))
            record["max_abs_difference_forward"] = float(np.max(np.abs(a - b)))
            a, b = (float(timings[k].result) for k in ("jaxobs_reverse", "diffrax_reverse"))
            record["relative_difference_gradient"] = abs(a - b) / abs(b)
        results[f"B={B}"] = record
    return results


def _ms(summary: dict) -> str:
    return format_range({k: summary[k] * 1e3 for k in ("median", "min", "max")}, ".3g")


def report(results: dict) -> str:
    lines = [f"{'case':<8} {'entry':<27} {'time (ms)':<26} {'compile (s)':<12} diffrax/jaxobs"]
    for case, r in results.items():
        for name in ("jaxobs_forward", "diffrax_forward", "jaxobs_reverse", "jaxobs_reverse_checkpoint",
                     "diffrax_reverse"):  # fmt: skip
            if name not in r:
                lines.append(f"{case:<8} {name:<27} {r['problems'].get(name)}")
                continue
            ratio = r.get(f"ratio_diffrax_over_jaxobs_{name.removeprefix('jaxobs_')}")
            lines.append(f"{case:<8} {name:<27} {_ms(r[name]['seconds']):<26} {r[name]['compile_s']:<12.2f} "
                         + (format_range(ratio, ".2f") if name.startswith("jaxobs") and ratio else ""))  # fmt: skip
        if "max_abs_difference_forward" in r:
            lines.append(f"{case:<8} agreement: trajectories {r['max_abs_difference_forward']:.1e} abs, "
                         f"gradients {r['relative_difference_gradient']:.1e} rel")  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    parser.add_argument("--samples", type=int, default=200)
    parser.add_argument("--substeps", type=int, default=4)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args(argv)
    results = measure(args.batches, args.samples, args.substeps, args.rounds)
    meta = {"samples": args.samples, "substeps": args.substeps, "h": H, "rounds": args.rounds,
            "platform": platform.platform(), "device": str(jax.devices()[0]), "jax": jax.__version__}  # fmt: skip
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ct_integration.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    print(report(results))
    print(f"wrote {out / 'ct_integration.json'}")
    return results


if __name__ == "__main__":
    main()
