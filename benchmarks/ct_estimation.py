"""Speed of the batched, jitted Example 5.6 of Grip 2010 (modular estimator and gradient-type law in closed loop)
against NumPy RK4 loops and diffrax, forward and for the gradient with respect to the gains.

What is measured (float64): :func:`jaxobs.papers.grip2010.adaptive.simulate_5_6`, both closed loops over the five
segments of ``--segment-s`` seconds at 1 ms (RK4, ``theta`` and the noise held over each step), for ``B`` noise
seeds (N(0, 1) per sample) at the printed gains (K_phi, adaptation_gain) = (10, 3):

* ``jaxobs_forward``: ``jit(vmap(simulate_5_6))`` over the seeds, returning every seed's per-segment mean
  |theta_tilde| over each segment's last half (:func:`~jaxobs.papers.grip2010.adaptive.segment_metrics`);
* ``jaxobs_gradient``: the derivative of the mean of those (over seeds and segments, modular law) with respect to
  ``(log K_phi, log adaptation_gain)``, forward mode (``jax.jacfwd``: two parameters, no stored trajectory);
* ``diffrax_forward``: the same ``simulate_5_6`` with each 1 ms step taken by ``diffrax.diffeqsolve`` (the
  classical RK4 tableau, one ``StepTo`` step) instead of :func:`jaxobs.ct.integrate`, so only the integrator
  differs; skipped without diffrax;
* ``numpy_per_seed``: a NumPy RK4 loop over the steps for one seed at a time (scalars in length-1 arrays), the
  seeds in a Python loop; ``numpy_vectorised``: one loop over the steps with every seed's state a length-B array.
  The NumPy entries run the first ``--numpy-steps`` steps (and ``numpy_per_seed`` at most ``--numpy-seeds``
  seeds) and are scaled to the whole run (a fixed-step loop costs the same per step); their states after those
  steps are checked against jaxobs's (max abs difference reported).

Timing (``benchmarks/_timing.py``): compiled first (compile time apart), interleaved rounds, median [min, max],
paired ratios ``peer time / jaxobs_forward time``.

Run (``make bench`` does it with ``--out out/bench``)::

    python benchmarks/ct_estimation.py --out DIR [--segment-s 2] [--batches 1 64 1024] [--rounds 3]

The default ``--segment-s 2`` (10 000 steps) keeps a CPU run to minutes; the cost per step does not depend on it.

Writes ``DIR/ct_estimation.json`` and prints a table.
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
from _timing import format_range, paired_ratio, time_interleaved  # noqa: E402
from ct_integration import diffrax_rk4_solver  # noqa: E402

from jaxobs.papers.grip2010 import adaptive as grip  # noqa: E402

ENTRIES = ("jaxobs_forward", "jaxobs_gradient", "diffrax_forward", "numpy_vectorised", "numpy_per_seed")


def _metrics(seg: float):
    def run(noise, log_gains, integrate):
        (xm, thm, _, _), _ = grip.simulate_5_6(noise, *jnp.exp(log_gains), segment_s=seg, integrate=integrate)
        return grip.segment_metrics(xm, thm, segment_s=seg, window_s=seg / 2)[3]

    return run


def jaxobs_forward(seg: float, integrate=grip.ct.integrate):
    run = _metrics(seg)
    return lambda noise, log_gains: jax.vmap(lambda n: run(n, log_gains, integrate))(noise)


def jaxobs_gradient(seg: float):
    forward = jaxobs_forward(seg)
    return jax.jacfwd(lambda noise, log_gains: jnp.mean(forward(noise, log_gains)), argnums=1)


def diffrax_integrate():
    solver = diffrax_rk4_solver()
    import diffrax

    def integrate(f, x, u, t, h):
        term = diffrax.ODETerm(lambda s, y, args: f(y, args, s))
        sol = diffrax.diffeqsolve(term, solver, t, t + h, None, x, args=u, saveat=diffrax.SaveAt(t1=True),
                                  stepsize_controller=diffrax.StepTo(jnp.stack([t, t + h])), max_steps=1)  # fmt: skip
        return jax.tree.map(lambda leaf: leaf[-1], sol.ys)

    return integrate


def numpy_closed_loops(noise: np.ndarray, K: float, G: float, seg: float) -> tuple:
    """Both closed loops of Example 5.6 by a NumPy RK4 loop over the steps, every seed's state a length-B array
    (``noise`` (B, steps)); the same equations as ``simulate_5_6`` written out for the scalar case: the modular law
    ``theta_hat' = Proj(Gamma sin t (phi_hat - exp(sin t theta_hat)))`` on the box [-5, 5] (order 4, epsilon 0.1),
    ``phi_hat = z + K x + exp(sin t theta_hat)``, ``z' = -K (-x + u + phi_hat) - sin t exp(sin t theta_hat)
    theta_hat'``; the gradient law limited to [-5, 5]. Returns ``(x_m, z, theta_hat_m, x_g, theta_hat_g)``."""
    B, steps = noise.shape
    theta_steps = grip.theta_schedule(grip.DT, seg)[0][:steps]
    bound, eps, order, gg, dt = grip.THETA_BOUND, grip.EPSILON, grip.BOX_ORDER, grip.ADAPTATION_GAIN_GRADIENT, grip.DT

    def modular(xm, z, th, theta, n, t):
        s = np.sin(t)
        y = xm + n
        g_hat = np.exp(s * th)
        u = -g_hat
        phi = z + K * y + g_hat
        tau = G * s * (phi - g_hat)
        P = (th / bound) ** (2 * order) - 1
        grad = 2 * order * th ** (2 * order - 1) / bound ** (2 * order)
        c = np.minimum(1.0, P / eps)
        rate = np.where((P < 0) | (grad * tau <= 0), tau, (1 - c) * tau)
        z_dot = -K * (-y + u + phi) - s * g_hat * rate
        return -xm + np.exp(s * theta) + u, z_dot, rate

    def gradient(xg, th, theta, n, t):
        s = np.sin(t)
        thc = np.clip(th, -bound, bound)
        g_hat = np.exp(s * thc)
        rate = gg * s * g_hat * (xg + n)
        rate = np.where(((thc >= bound) & (rate > 0)) | ((thc <= -bound) & (rate < 0)), 0.0, rate)
        return -xg + np.exp(s * theta) - g_hat, rate

    def rk4(f, state, args, t):
        k1 = f(*state, *args, t)
        k2 = f(*(a + dt / 2 * k for a, k in zip(state, k1, strict=True)), *args, t + dt / 2)
        k3 = f(*(a + dt / 2 * k for a, k in zip(state, k2, strict=True)), *args, t + dt / 2)
        k4 = f(*(a + dt * k for a, k in zip(state, k3, strict=True)), *args, t + dt)
        return tuple(a + dt / 6 * (p + 2 * q + 2 * r + w) for a, p, q, r, w in zip(state, k1, k2, k3, k4, strict=True))

    zeros = np.zeros(B)
    mod, grad = (zeros, zeros, zeros), (zeros, zeros)
    for k in range(steps):
        t, theta, n = k * dt, theta_steps[k], noise[:, k]
        mod = rk4(modular, mod, (theta, n), t)
        grad = rk4(gradient, grad, (theta, n), t)
        grad = (grad[0], np.clip(grad[1], -bound, bound))
    return (*mod, *grad)


def _entries(noise: np.ndarray, log_gains, seg: float, numpy_steps: int, per_seed: int) -> dict:
    """The entries of :func:`_timing.time_interleaved` for ``noise`` (B, steps)."""
    B, steps = noise.shape
    K, G = grip.K_PHI, grip.ADAPTATION_GAIN_MODULAR
    prefix = noise[:, :numpy_steps]
    args = (jnp.asarray(noise), log_gains)

    def per_seed_loop():
        return [numpy_closed_loops(prefix[i : i + 1], K, G, seg) for i in range(per_seed)]

    return {
        "jaxobs_forward": (lambda: (jaxobs_forward(seg), args), True, 1.0),
        "jaxobs_gradient": (lambda: (jaxobs_gradient(seg), args), True, 1.0),
        "diffrax_forward": (lambda: (jaxobs_forward(seg, diffrax_integrate()), args), True, 1.0),
        "numpy_vectorised": (
            lambda: (lambda p: numpy_closed_loops(p, K, G, seg), (prefix,)),
            False,
            steps / numpy_steps,
        ),  # fmt: skip
        "numpy_per_seed": (lambda: (per_seed_loop, ()), False, steps / numpy_steps * B / per_seed),
    }


def measure(batches, seg: float, rounds: int, numpy_steps: int, numpy_seeds: int) -> dict:
    steps = len(grip.SEGMENT_THETAS) * round(seg / grip.DT)
    numpy_steps = min(numpy_steps, steps)
    log_gains = jnp.log(jnp.array([grip.K_PHI, grip.ADAPTATION_GAIN_MODULAR]))
    results = {}
    for B in batches:
        noise = np.asarray(jax.random.normal(jax.random.PRNGKey(B), (B, steps)))
        per_seed = min(B, numpy_seeds)
        entries = _entries(noise, log_gains, seg, numpy_steps, per_seed)
        timings, problems = time_interleaved(entries, rounds, required=("jaxobs_forward", "jaxobs_gradient"))
        record = {"problems": problems, "numpy_steps": numpy_steps, "numpy_per_seed_seeds": per_seed}
        for name, timed in timings.items():
            record[name] = timed.record(B * steps, "steps/s (both loops, per seed)")
        for name in ENTRIES[1:]:
            if name in timings:
                record[f"ratio_{name}_over_jaxobs_forward"] = paired_ratio(timings["jaxobs_forward"], timings[name])
        if "diffrax_forward" in timings:
            a, b = (np.asarray(timings[k].result) for k in ("jaxobs_forward", "diffrax_forward"))
            record["max_abs_difference_diffrax"] = float(np.max(np.abs(a - b)))
        # the NumPy states after numpy_steps against jaxobs's (modular x, theta_hat; gradient x, theta_hat)
        m = min(B, 4)
        sim = jax.jit(jax.vmap(lambda n: grip.simulate_5_6(n, segment_s=seg)[0]))
        padded = np.zeros((m, steps))
        padded[:, :numpy_steps] = noise[:m, :numpy_steps]
        ours = np.stack([np.asarray(a)[:, numpy_steps] for a in sim(jnp.asarray(padded))], axis=1)
        xm, _, thm, xg, thg = numpy_closed_loops(noise[:m, :numpy_steps], grip.K_PHI, grip.ADAPTATION_GAIN_MODULAR, seg)
        record["max_abs_difference_numpy"] = float(np.max(np.abs(ours - np.stack([xm, thm, xg, thg], axis=1))))
        record["gradient"] = np.asarray(timings["jaxobs_gradient"].result).tolist()
        results[f"B={B}"] = record
    return results


def _s(summary: dict) -> str:
    return format_range(summary, ".3g")


def report(results: dict) -> str:
    lines = [f"{'case':<8} {'entry':<18} {'time (s)':<28} {'compile (s)':<12} time / jaxobs_forward"]
    for case, r in results.items():
        for name in ENTRIES:
            if name not in r:
                lines.append(f"{case:<8} {name:<18} {r['problems'].get(name)}")
                continue
            ratio = r.get(f"ratio_{name}_over_jaxobs_forward")
            compile_s = "-" if r[name]["compile_s"] is None else f"{r[name]['compile_s']:.2f}"
            lines.append(f"{case:<8} {name:<18} {_s(r[name]['seconds']):<28} {compile_s:<12} "
                         + (format_range(ratio, ".3g") if ratio else ""))  # fmt: skip
        lines.append(f"{case:<8} agreement: NumPy states after {r['numpy_steps']} steps "
                     f"{r['max_abs_difference_numpy']:.1e} abs"
                     + (f", diffrax metrics {r['max_abs_difference_diffrax']:.1e} abs"
                        if "max_abs_difference_diffrax" in r else ""))  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    parser.add_argument(
        "--segment-s", type=float, default=2.0, help="each of the five segments (s); 20 in the reproduction"
    )
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--numpy-steps", type=int, default=2000, help="steps the NumPy entries run (scaled up)")
    parser.add_argument("--numpy-seeds", type=int, default=4, help="seeds numpy_per_seed runs at most (scaled up)")
    args = parser.parse_args(argv)
    results = measure(args.batches, args.segment_s, args.rounds, args.numpy_steps, args.numpy_seeds)
    meta = {"segment_s": args.segment_s, "dt": grip.DT, "rounds": args.rounds, "numpy_steps": args.numpy_steps,
            "numpy_seeds": args.numpy_seeds, "platform": platform.platform(), "device": str(jax.devices()[0]),
            "jax": jax.__version__}  # fmt: skip
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ct_estimation.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    print(report(results))
    print(f"wrote {out / 'ct_estimation.json'}")
    return results


if __name__ == "__main__":
    main()
