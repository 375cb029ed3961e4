"""Closed-loop MJX rollouts with the Active Observer in the loop: plant-steps per second and seconds per gradient
step for batches of 1, 64 and 1024 mismatched plants, against CPU MuJoCo stepping the same model in a Python loop.

Plant: the 1-DOF force plant of :mod:`jaxobs.mjx` (1 ms physics, ``SUBSTEPS = 8`` physics steps per 8 ms
control step, 5-sample command dead time), under the Example 1 AOB-1 with steady-state gains and its state
feedback ``L`` (``jaxobs.papers.cortesao2006.aob_params``), tracking a 10 N force step for ``T`` control steps
(default 250 = 2 s = 2000 physics steps) with the Example 1 input disturbance and sensor noise
``sqrt(R) * normal`` (one noise draw per plant). The batch spreads the sensor stiffness ``ks`` over
[1.5, 4.5] N/mm (nominal 3) with :func:`jaxobs.mjx.with_params`.

Workloads, all in float64:

* jaxobs/MJX forward: ``jit(vmap(closed_loop_rollout))`` over the batch; plant-steps/s = ``B T SUBSTEPS / s``
  (physics steps; control steps/s is that divided by ``SUBSTEPS``).
* jaxobs/MJX gradient step: ``jit(value_and_grad)`` of the batch mean of the mean squared error between the
  true force and the ideal closed-loop response, w.r.t. ``(log R, log q_active)`` of the AOB-1, which is rebuilt
  inside the function (``make_aob(..., steady_state=True)``: a DARE with implicit derivatives) and shared by
  the batch. Reported as seconds per gradient step.
* CPU MuJoCo peer: the same ``MjModel`` (``jnt_stiffness`` set per plant) stepped by ``mujoco.mj_step`` in a
  Python loop, with the same steady-state AOB computed in NumPy (``x1 = Phi x + Gamma u_prev``,
  ``x = x1 + K (y - C x1)``, ``u = r - L x``), a 5-sample FIFO for the dead time, the force read as
  ``Ks x + Ds xdot`` before the step's command, and ``SUBSTEPS`` ``mj_step`` calls per control step with the
  command held. Its force trace is checked once against the MJX rollout for one plant. It is timed on a few
  plants (``--peer-plants``) and extrapolated to ``B`` plants: a sequential loop costs ``B`` times one plant,
  so its plant-steps/s does not depend on ``B``. CPU MuJoCo has no gradient; for reference the JSON gives the
  cost of a central-difference gradient of the two parameters with it (4 rollouts per plant), also
  extrapolated, and the ratio to the MJX gradient step.

jaxobs timings exclude compilation (one warm-up call, reported separately as ``compile_seconds``) and are the
median of ``--repeats`` calls ending in ``block_until_ready``. On a GPU the JSON records the device name; on a
CPU-only machine it says "CPU only".

    python benchmarks/mjx_rollouts.py --out DIR [--steps 250] [--batches 1 64 1024] [--max-batch N]
                                      [--repeats 3] [--peer-plants 20]

Writes ``DIR/mjx_rollouts.json`` and ``DIR/mjx_rollouts.png``.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from jaxobs.closed_loop import ideal_response  # noqa: E402
from jaxobs.mjx import SUBSTEPS, ForcePlantParams, closed_loop_rollout, load_model, with_params  # noqa: E402
from jaxobs.observers.active import make_aob  # noqa: E402
from jaxobs.papers.cortesao2006 import aob_params  # noqa: E402
from jaxobs.papers.force_control import EXAMPLE1, example1_disturbance, nominal_design, reference_gain  # noqa: E402

FORCE_STEP = 10.0  # N
KS_RANGE = (1.5, 4.5)  # N/mm, the batch's sensor stiffnesses
DEAD_TIME = 5  # control samples (closed_loop_rollout's default)
CHECK_KS = 2.0  # N/mm, the mismatched plant of the CPU-vs-MJX trace check


class Problem:
    """Everything both implementations share: the nominal design, the AOB, reference, disturbance, noise."""

    def __init__(self, steps: int):
        self.steps = steps
        self.mj_model, self.model = load_model()
        self.plant, self.L = nominal_design(EXAMPLE1)
        self.params = aob_params(self.plant, self.L, 1)
        self.reference = jnp.full(steps, reference_gain(self.L) * FORCE_STEP)
        self.disturbance = example1_disturbance(jnp.arange(steps) * EXAMPLE1.h)
        self.desired = ideal_response(self.plant, self.L, self.reference)[:, 0]
        self.theta = jnp.array([np.log(EXAMPLE1.R), np.log(EXAMPLE1.sigma2_active)])
        self.forward = jax.jit(jax.vmap(self.force, in_axes=(None, 0, 0)))
        """``jit(vmap(rollout))``: (params, ks (B,), noise (B, T)) -> true forces (B, T)."""

    def plants(self, batch: int):
        """``(ks, noise)`` of a batch: stiffnesses spread over KS_RANGE and one sensor-noise draw per plant."""
        ks = jnp.linspace(*KS_RANGE, batch) if batch > 1 else jnp.array([EXAMPLE1.Ks])
        keys = jax.random.split(jax.random.PRNGKey(0), batch)
        noise = jax.vmap(lambda k: np.sqrt(EXAMPLE1.R) * jax.random.normal(k, (self.steps,)))(keys)
        return ks, noise

    def force(self, params, ks, noise):
        """True force trace of one plant of stiffness ``ks`` under the controller ``params``."""
        model = with_params(self.model, ForcePlantParams(ks=ks))
        trace = closed_loop_rollout(model, params, self.reference, noise=noise, disturbance=self.disturbance)
        return trace.force_true

    def loss(self, theta, ks, noise):
        """Batch mean of the mean squared force tracking error of an AOB-1 with R = exp(theta[0]) and
        active-state variance exp(theta[1])."""
        log_r, log_q = theta
        params = make_aob(
            self.plant, self.L, 1, jnp.exp(log_r), q_plant=EXAMPLE1.q_plant, q_active=jnp.exp(log_q), steady_state=True
        )
        forces = jax.vmap(self.force, in_axes=(None, 0, 0))(params, ks, noise)
        return jnp.mean((forces - self.desired) ** 2)


def _time(fn, *args, repeats: int) -> dict:
    """Compile (first call) and the median of ``repeats`` further calls, in seconds."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_seconds = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return {"seconds": statistics.median(times), "seconds_all": times, "compile_seconds": compile_seconds}


def jaxobs_forward(problem: Problem, batch: int, repeats: int) -> dict:
    ks, noise = problem.plants(batch)
    rec = _time(problem.forward, problem.params, ks, noise, repeats=repeats)
    steps = batch * problem.steps
    rec["plant_steps_per_second"] = steps * SUBSTEPS / rec["seconds"]
    rec["control_steps_per_second"] = steps / rec["seconds"]
    return rec


def jaxobs_gradient(problem: Problem, batch: int, repeats: int) -> dict:
    ks, noise = problem.plants(batch)
    fn = jax.jit(jax.value_and_grad(problem.loss))
    rec = _time(fn, problem.theta, ks, noise, repeats=repeats)
    value, grad = fn(problem.theta, ks, noise)
    rec["loss"] = float(value)
    rec["grad"] = np.asarray(grad).tolist()
    rec["plant_steps_per_second"] = batch * problem.steps * SUBSTEPS / rec["seconds"]
    return rec


class NumpyAOB:
    """The steady-state AOB of ``params`` in NumPy (the controller step of jaxobs.observers.active)."""

    def __init__(self, params):
        self.Phi, self.Gamma, self.C, self.L, self.K = (
            np.asarray(m) for m in (params.Phi, params.Gamma, params.C, params.L, params.gain)
        )

    def rollout(self, m: mujoco.MjModel, reference, noise, disturbance) -> np.ndarray:
        """True force per control step of the CPU MuJoCo plant ``m`` under this controller."""
        d = mujoco.MjData(m)
        Phi, Gamma, C, L, K = self.Phi, self.Gamma, self.C, self.L, self.K
        x, u_prev = np.zeros(Phi.shape[0]), np.zeros(Gamma.shape[1])
        fifo = [0.0] * DEAD_TIME
        ks, ds = m.jnt_stiffness[0], m.dof_damping[0]
        force = np.empty(len(reference))
        for k in range(len(reference)):
            force[k] = ks * d.qpos[0] + ds * d.qvel[0]
            y = force[k] + noise[k]
            x1 = Phi @ x + Gamma @ u_prev
            x = x1 + K @ (y - C @ x1)
            u_prev = reference[k] - L @ x
            fifo.append(float(u_prev[0]) + disturbance[k])
            d.ctrl[0] = fifo.pop(0)
            for _ in range(SUBSTEPS):
                mujoco.mj_step(m, d)
        return force


def peer(problem: Problem, plants: int) -> dict:
    """CPU MuJoCo + NumPy AOB: trace agreement with MJX on one plant, then plant-steps/s over ``plants``."""
    aob = NumpyAOB(problem.params)
    m = problem.mj_model
    reference, disturbance = np.asarray(problem.reference), np.asarray(problem.disturbance)
    ks_check = jnp.array([CHECK_KS])
    noise_check = problem.plants(1)[1]
    mjx_force = np.asarray(problem.forward(problem.params, ks_check, noise_check))[0]
    m.jnt_stiffness[0] = CHECK_KS
    cpu_force = aob.rollout(m, reference, np.asarray(noise_check[0]), disturbance)
    max_diff = float(np.max(np.abs(cpu_force - mjx_force)))

    ks, noise = problem.plants(plants)
    ks, noise = np.asarray(ks), np.asarray(noise)
    start = time.perf_counter()
    for i in range(plants):
        m.jnt_stiffness[0] = ks[i]
        aob.rollout(m, reference, noise[i], disturbance)
    seconds = time.perf_counter() - start
    m.jnt_stiffness[0] = EXAMPLE1.Ks
    rate = plants * problem.steps * SUBSTEPS / seconds
    return {
        "plants_timed": plants,
        "seconds": seconds,
        "seconds_per_plant": seconds / plants,
        "plant_steps_per_second": rate,
        "control_steps_per_second": rate / SUBSTEPS,
        "trace_check": {
            "ks": CHECK_KS,
            "max_abs_force_difference_N": max_diff,
            "max_abs_force_N": float(np.max(np.abs(mjx_force))),
        },
        "mujoco": mujoco.__version__,
    }


def _platform() -> dict:
    device = jax.devices()[0]
    gpu = device.platform == "gpu"
    return {
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "device": device.device_kind if gpu else "CPU only",
        "cpu_count": os.cpu_count(),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=250, help="control steps per rollout (8 physics steps each)")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    parser.add_argument("--max-batch", type=int, default=None, help="skip batches larger than this")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--peer-plants", type=int, default=20)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    batches = [b for b in args.batches if args.max_batch is None or b <= args.max_batch]
    start = time.perf_counter()
    problem = Problem(args.steps)
    timed = {}
    for batch in batches:
        timed[batch] = jaxobs_forward(problem, batch, args.repeats), jaxobs_gradient(problem, batch, args.repeats)
        print(f"batch {batch} done ({time.perf_counter() - start:.0f} s)", flush=True)
    cpu = peer(problem, args.peer_plants)  # after the jaxobs timings, so their compile times include every shape
    rows = {}
    for batch, (fwd, grad) in timed.items():
        cpu_seconds = batch * problem.steps * SUBSTEPS / cpu["plant_steps_per_second"]
        rows[str(batch)] = {
            "jaxobs_forward": fwd,
            "jaxobs_gradient": grad,
            "cpu_mujoco_forward_seconds": cpu_seconds,
            "cpu_mujoco_central_difference_gradient_seconds": 4 * cpu_seconds,
            "forward_ratio": fwd["plant_steps_per_second"] / cpu["plant_steps_per_second"],
            "gradient_ratio_vs_central_differences": 4 * cpu_seconds / grad["seconds"],
        }
    results = {
        "steps": args.steps,
        "substeps": SUBSTEPS,
        "physics_steps_per_rollout": args.steps * SUBSTEPS,
        "ks_range": list(KS_RANGE),
        "batches": rows,
        "cpu_mujoco": cpu,
        "platform": _platform(),
        "total_seconds": time.perf_counter() - start,
    }
    (args.out / "mjx_rollouts.json").write_text(json.dumps(results, indent=2) + "\n")
    _print(results)
    _plot(results, args.out / "mjx_rollouts.png")
    return results


def _print(results: dict) -> None:
    cpu = results["cpu_mujoco"]
    print(f"device: {results['platform']['device']}; {results['steps']} control steps x {SUBSTEPS} physics steps")
    print(
        f"CPU MuJoCo + NumPy AOB: {cpu['plant_steps_per_second']:.3g} plant-steps/s ({cpu['plants_timed']} plants); "
        f"trace vs MJX: max |dF| = {cpu['trace_check']['max_abs_force_difference_N']:.2g} N"
    )
    print(
        f"{'batch':>6} {'MJX plant-steps/s':>18} {'CPU MuJoCo':>12} {'ratio':>8} "
        f"{'MJX s/grad':>11} {'CPU FD s/grad':>14} {'ratio':>8}"
    )
    for batch, row in results["batches"].items():
        fwd, grad = row["jaxobs_forward"], row["jaxobs_gradient"]
        print(
            f"{batch:>6} {fwd['plant_steps_per_second']:>18.3g} {cpu['plant_steps_per_second']:>12.3g} "
            f"{row['forward_ratio']:>7.2f}x {grad['seconds']:>11.3g} "
            f"{row['cpu_mujoco_central_difference_gradient_seconds']:>14.3g} "
            f"{row['gradient_ratio_vs_central_differences']:>7.2f}x"
        )
    print(f"total {results['total_seconds']:.0f} s")


def _plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot

    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    batches = [int(k) for k in results["batches"]]
    rows = list(results["batches"].values())
    cpu_rate = results["cpu_mujoco"]["plant_steps_per_second"]
    device = results["platform"]["device"]
    a.plot(batches, [r["jaxobs_forward"]["plant_steps_per_second"] for r in rows], "o-", label=f"jaxobs/MJX ({device})")
    a.plot(batches, [cpu_rate] * len(batches), "s--", color="tab:gray", label="CPU MuJoCo loop (extrapolated)")
    a.set_xscale("log")
    a.set_yscale("log")
    a.set_xlabel("batch (plants)")
    a.set_ylabel("physics plant-steps / s")
    a.set_title(f"forward, AOB-1 in the loop, {results['physics_steps_per_rollout']} steps/rollout")
    a.legend()
    b.plot(batches, [r["jaxobs_gradient"]["seconds"] for r in rows], "o-", label="jaxobs/MJX value_and_grad")
    fd = [r["cpu_mujoco_central_difference_gradient_seconds"] for r in rows]
    b.plot(batches, fd, "s--", color="tab:gray", label="CPU MuJoCo central differences (est.)")
    b.set_xscale("log")
    b.set_yscale("log")
    b.set_xlabel("batch (plants)")
    b.set_ylabel("s / gradient step")
    b.set_title("gradient w.r.t. (log R, log q_active)")
    b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
