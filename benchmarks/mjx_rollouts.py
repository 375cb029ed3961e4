"""Closed-loop MJX rollouts with the Active Observer in the loop: plant-steps per second and seconds per gradient
step for batches of 1, 64 and 1024 mismatched plants, against CPU MuJoCo stepping the same model (batched with
``mujoco.rollout``, and one plant at a time in a Python loop).

Plant: the 1-DOF force plant of :mod:`jaxobs.mjx` (1 ms physics, ``SUBSTEPS = 8`` physics steps per 8 ms
control step, 5-sample command dead time), under the Example 1 AOB-1 with steady-state gains and its state
feedback ``L`` (``jaxobs.papers.cortesao.example1.aob_params`` with
``jaxobs.papers.cortesao.force_control.with_feedback``),
tracking a 10 N force step for ``T`` control steps (default 250 = 2 s = 2000 physics steps) with the Example 1
input disturbance and sensor noise ``sqrt(R) * normal`` (one noise draw per plant). The batch spreads the sensor
stiffness ``ks`` over [1.5, 4.5] N/mm (nominal 3) with :func:`jaxobs.mjx.with_params`.

Workloads, all in float64:

* jaxobs/MJX forward: ``jit(vmap(closed_loop_rollout))`` over the batch; plant-steps/s = ``B T SUBSTEPS / s``
  (physics steps; control steps/s is that divided by ``SUBSTEPS``).
* jaxobs/MJX gradient step: ``jit(value_and_grad)`` of the batch mean of the mean squared error between the
  true force and the ideal closed-loop response, w.r.t. ``(log R, log q_active)`` of the AOB-1, which is rebuilt
  inside the function (``make_aob(..., steady_state=True)``: a DARE with implicit derivatives) and shared by
  the batch. Reported as seconds per gradient step.
* CPU MuJoCo peers: the same ``MjModel`` (``jnt_stiffness`` set per plant) with the same steady-state AOB in
  NumPy (``x1 = Phi x + Gamma u_prev``, ``x = x1 + K (y - C x1)``, ``u = r - L x``, one function batched over
  plants), a 5-sample FIFO for the dead time, the force read as ``Ks x + Ds xdot`` before the step's command, and
  ``SUBSTEPS`` physics steps per control step with the command held. ``cpu_rollout`` is batched the way MuJoCo
  batches: one ``mujoco.rollout.rollout`` call per control step advances every plant of the batch (one model
  copy per plant, one ``MjData`` per CPU thread) and the AOB step runs on (B, ...) arrays. ``cpu_loop`` steps
  one plant at a time with ``mujoco.mj_step`` in a Python loop; it is timed on a few plants (``--peer-plants``)
  and extrapolated to ``B`` (a sequential loop costs ``B`` times one plant). The batched peer's force traces are
  checked against MJX on every plant of the batch (max abs difference in the JSON). CPU MuJoCo has no
  gradient; for reference the JSON gives the cost of a central-difference gradient of the two parameters with
  the faster CPU peer of each round (4 rollouts per plant, estimated from its measured forward time) and the
  ratio to the MJX gradient step.

Timing (``benchmarks/_timing.py``): per batch, ``--rounds`` interleaved rounds each run every entry once (MJX
forward and gradient compiled first: ``compile_s``); times, rates and the paired ratios are reported as the
median and [min, max] over the rounds. On a GPU the JSON records the device name; on a CPU-only machine it says
"CPU only".

The price of a gradient on every shipped tuning problem (``--problems``, the configs of ``benchmarks/tuning.py``):
one forward evaluation of the training objective on the training batch against ``value_and_grad`` in reverse
mode and ``jacfwd`` in forward mode, each compiled once and timed in ``--rounds`` interleaved rounds (median), with
their compile times and the temporary memory XLA reserves for them (``memory_analysis``), as ratios to the forward
evaluation; ``mode`` is the one ``gradient = "auto"`` picks; and 16 starts' gradients in ``mode``, in one ``vmap``
(the tuner's populations), against one start's.

The floor under reverse mode (``--step-costs [BATCH ...]``): for each MJX model of the shipped problems, 50
physics steps (a ``lax.scan``; ``jaxobs.mjx.common.step`` with the tuner's fixed solver iterations where the problem
sets them) of a batch against their ``jax.vjp`` (forward and backward pass): the ratio of their times over
``--rounds`` interleaved rounds, of their compile times and of the flops XLA's cost analysis counts. A rollout's
reverse-mode gradient runs every step's backward pass at least once (checkpointing only adds forward
recomputation), so where the physics dominates the rollout this ratio bounds the gradient's from below.

    python benchmarks/mjx_rollouts.py --out DIR [--steps 250] [--batches 1 64 1024] [--max-batch N]
                                      [--rounds 5] [--peer-plants 20] [--problems [NAME ...]]
                                      [--step-costs [BATCH ...]]

Writes ``DIR/mjx_rollouts.json`` and ``DIR/mjx_rollouts.png`` (``--batches`` with no value skips them) and, with
``--problems``, ``DIR/gradient_costs.json``, with ``--step-costs``, ``DIR/step_costs.json``.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import copy  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from _timing import Timed, format_range, paired_ratio, time_interleaved  # noqa: E402
from _tuning_problems import PROBLEMS, gradient_costs, load_problem  # noqa: E402
from mujoco import rollout as mj_rollout  # noqa: E402

from jaxobs.closed_loop import ideal_response  # noqa: E402
from jaxobs.mjx import SUBSTEPS, ForcePlantParams, closed_loop_rollout, load_model, with_params  # noqa: E402
from jaxobs.observers.active import active_observer_controller, make_aob  # noqa: E402
from jaxobs.papers.cortesao.example1 import aob_params  # noqa: E402
from jaxobs.papers.cortesao.force_control import (  # noqa: E402
    EXAMPLE1,
    example1_disturbance,
    nominal_design,
    reference_gain,
    with_feedback,
)

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
        self.params = with_feedback(aob_params(self.plant, 1), self.L)
        self.reference = jnp.full(steps, reference_gain(self.L) * FORCE_STEP)
        self.disturbance = example1_disturbance(jnp.arange(steps) * EXAMPLE1.h)
        self.desired = ideal_response(self.plant, self.L, self.reference)[:, 0]
        self.theta = jnp.array([np.log(EXAMPLE1.R), np.log(EXAMPLE1.sigma2_active)])

    def plants(self, batch: int):
        """``(ks, noise)`` of a batch: stiffnesses spread over KS_RANGE and one sensor-noise draw per plant."""
        ks = jnp.linspace(*KS_RANGE, batch) if batch > 1 else jnp.array([EXAMPLE1.Ks])
        keys = jax.random.split(jax.random.PRNGKey(0), batch)
        noise = jax.vmap(lambda k: np.sqrt(EXAMPLE1.R) * jax.random.normal(k, (self.steps,)))(keys)
        return ks, noise

    def force(self, params, ks, noise):
        """True force trace of one plant of stiffness ``ks`` under the controller ``params``."""
        model = with_params(self.model, ForcePlantParams(stiffness=ks))
        trace = closed_loop_rollout(
            model, active_observer_controller, params, self.reference, noise=noise, disturbance=self.disturbance
        )
        return trace.force_true

    def forces(self, params, ks, noise):
        """True force traces (B, T) of the plants of stiffnesses ``ks`` (B,) under ``params``, noise (B, T)."""
        return jax.vmap(self.force, in_axes=(None, 0, 0))(params, ks, noise)

    def loss(self, theta, ks, noise):
        """Batch mean of the mean squared force tracking error of an AOB-1 with R = exp(theta[0]) and
        active-state variance exp(theta[1])."""
        log_r, log_q = theta
        q_plant, q_active = EXAMPLE1.q_plant, jnp.exp(log_q)
        aob = make_aob(self.plant, 1, jnp.exp(log_r), q_plant=q_plant, q_active=q_active, steady_state=True)
        params = with_feedback(aob, self.L)
        return jnp.mean((self.forces(params, ks, noise) - self.desired) ** 2)


class NumpyAOB:
    """The steady-state AOB of ``params`` in NumPy (the controller step of jaxobs.observers.active), batched over
    a leading plant axis, with the dead-time FIFO of the command."""

    def __init__(self, params):
        aob = params.estimator
        self.Phi, self.Gamma, self.C, self.L, self.K = (
            np.asarray(m) for m in (aob.Phi, aob.Gamma, aob.C, params.L, aob.gain)
        )

    def init(self, batch: int):
        """``(x_hat, u_prev, fifo)``: zero estimate, no previous command, an empty dead-time FIFO."""
        return (
            np.zeros((batch, self.Phi.shape[0])),
            np.zeros((batch, self.Gamma.shape[1])),
            np.zeros((batch, DEAD_TIME)),
        )

    def step(self, state, y, r, d):
        """One control step on (B,) measurements ``y``: the new state and the command leaving the FIFO."""
        x, u_prev, fifo = state
        x1 = x @ self.Phi.T + u_prev @ self.Gamma.T
        x = x1 + (y[:, None] - x1 @ self.C.T) @ self.K.T
        u = r - x @ self.L.T
        applied = fifo[:, 0]
        fifo = np.concatenate([fifo[:, 1:], u + d], axis=1)
        return (x, u, fifo), applied


def cpu_loop(problem: Problem, aob: NumpyAOB, ks, noise) -> np.ndarray:
    """True forces (B, T) of CPU MuJoCo plants of stiffnesses ``ks``, one plant at a time (``mj_step``)."""
    m = copy.copy(problem.mj_model)
    reference, disturbance = np.asarray(problem.reference), np.asarray(problem.disturbance)
    forces = np.empty((len(ks), problem.steps))
    for i, k_s in enumerate(ks):
        m.jnt_stiffness[0] = k_s
        d, state = mujoco.MjData(m), aob.init(1)
        for k in range(problem.steps):
            forces[i, k] = k_s * d.qpos[0] + m.dof_damping[0] * d.qvel[0]
            state, applied = aob.step(state, forces[i, k : k + 1] + noise[i, k], reference[k], disturbance[k])
            d.ctrl[0] = applied[0]
            for _ in range(SUBSTEPS):
                mujoco.mj_step(m, d)
    return forces


class CpuRollout:
    """CPU MuJoCo batched over plants: one model copy per plant, one ``MjData`` per thread, and one
    ``mujoco.rollout.rollout`` call per control step advancing every plant by ``SUBSTEPS`` physics steps."""

    SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS

    def __init__(self, problem: Problem, ks):
        self.problem, self.ks = problem, np.asarray(ks)
        self.models = []
        for k_s in self.ks:
            m = copy.copy(problem.mj_model)
            m.jnt_stiffness[0] = k_s
            self.models.append(m)
        self.datas = [mujoco.MjData(problem.mj_model) for _ in range(os.cpu_count() or 1)]
        self.state0 = np.empty(mujoco.mj_stateSize(problem.mj_model, self.SPEC))
        mujoco.mj_getState(problem.mj_model, mujoco.MjData(problem.mj_model), self.state0, self.SPEC)
        self.nq = problem.mj_model.nq
        self.damping = problem.mj_model.dof_damping[0]

    def forces(self, aob: NumpyAOB, noise) -> np.ndarray:
        """True forces (B, T) under the AOB; ``noise`` (B, T)."""
        p = self.problem
        reference, disturbance = np.asarray(p.reference), np.asarray(p.disturbance)
        batch = len(self.ks)
        state, ctrl = aob.init(batch), np.zeros((batch, 1, 1))
        physics = np.tile(self.state0, (batch, 1))
        forces = np.empty((batch, p.steps))
        for k in range(p.steps):  # physics state: [time, qpos, qvel, ...]
            forces[:, k] = self.ks * physics[:, 1] + self.damping * physics[:, 1 + self.nq]
            state, ctrl[:, 0, 0] = aob.step(state, forces[:, k] + noise[:, k], reference[k], disturbance[k])
            physics = mj_rollout.rollout(self.models, self.datas, physics, ctrl, nstep=SUBSTEPS)[0][:, -1]
        return forces


def time_batch(problem: Problem, batch: int, rounds: int, peer_plants: int) -> dict:
    """Interleaved rounds of MJX forward, MJX gradient, the batched and the looped CPU MuJoCo peers."""
    ks, noise = problem.plants(batch)
    ks_np, noise_np = np.asarray(ks), np.asarray(noise)
    aob, cpu = NumpyAOB(problem.params), CpuRollout(problem, ks_np)
    loop_plants = min(peer_plants, batch)
    entries = {
        "mjx_forward": (
            lambda: (jax.vmap(problem.force, in_axes=(None, 0, 0)), (problem.params, ks, noise)),
            True,
            1.0,
        ),
        "mjx_gradient": (lambda: (jax.value_and_grad(problem.loss), (problem.theta, ks, noise)), True, 1.0),
        "cpu_rollout": (lambda: (lambda: cpu.forces(aob, noise_np), ()), False, 1.0),
        "cpu_loop": (
            lambda: (lambda: cpu_loop(problem, aob, ks_np[:loop_plants], noise_np[:loop_plants]), ()),
            False,
            batch / loop_plants,
        ),
    }
    timings, _ = time_interleaved(entries, rounds, required=tuple(entries))
    physics_steps = batch * problem.steps * SUBSTEPS
    rec = {name: t.record(physics_steps, "physics plant-steps/s") for name, t in timings.items()}
    rec["cpu_loop"]["extrapolated_from_plants"] = loop_plants
    mjx_forces = np.asarray(timings["mjx_forward"].result)
    value, grad = timings["mjx_gradient"].result
    rec["mjx_gradient"].update(loss=float(value), grad=np.asarray(grad).tolist())
    faster = zip(timings["cpu_rollout"].seconds, timings["cpu_loop"].seconds, strict=True)
    central = Timed([4 * min(pair) for pair in faster], None, None)  # the faster CPU peer of each round
    diff = {name: float(np.max(np.abs(timings[name].result - mjx_forces[: len(timings[name].result)])))
            for name in ("cpu_rollout", "cpu_loop")}  # fmt: skip
    return {
        **rec,
        "cpu_central_difference_gradient": central.record(physics_steps, "physics plant-steps/s"),
        "forward_ratio_vs_cpu_rollout": paired_ratio(timings["mjx_forward"], timings["cpu_rollout"]),
        "forward_ratio_vs_cpu_loop": paired_ratio(timings["mjx_forward"], timings["cpu_loop"]),
        "gradient_ratio_vs_central_differences": paired_ratio(timings["mjx_gradient"], central),
        "trace_check": {"max_abs_force_difference_N": diff, "max_abs_force_N": float(np.max(np.abs(mjx_forces)))},
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
    parser.add_argument("--batches", type=int, nargs="*", default=[1, 64, 1024])
    parser.add_argument("--max-batch", type=int, default=None, help="skip batches larger than this")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved timed rounds (median and range)")
    parser.add_argument("--peer-plants", type=int, default=20, help="plants the looped CPU peer is timed on")
    parser.add_argument("--problems", nargs="*", choices=list(PROBLEMS), help="the price of a gradient on these "
                        "shipped tuning problems (no name: all)")  # fmt: skip
    parser.add_argument("--step-costs", type=int, nargs="*", help="one physics step against its vjp on each "
                        "shipped MJX model, at these batch sizes (no value: 8 64 512)")  # fmt: skip
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.step_costs is not None:
        step_costs(args.step_costs or [8, 64, 512], args.rounds, args.out)
    if args.problems is not None:
        problem_costs(args.problems or list(PROBLEMS), args.rounds, args.out)
    if not args.batches:
        return {}
    batches = [b for b in args.batches if args.max_batch is None or b <= args.max_batch]
    start = time.perf_counter()
    problem = Problem(args.steps)
    rows = {}
    for batch in batches:
        rows[str(batch)] = time_batch(problem, batch, args.rounds, args.peer_plants)
        print(f"batch {batch} done ({time.perf_counter() - start:.0f} s)", flush=True)
    results = {
        "steps": args.steps,
        "substeps": SUBSTEPS,
        "physics_steps_per_rollout": args.steps * SUBSTEPS,
        "ks_range": list(KS_RANGE),
        "rounds": args.rounds,
        "batches": rows,
        "mujoco": mujoco.__version__,
        "platform": _platform(),
        "total_seconds": time.perf_counter() - start,
    }
    (args.out / "mjx_rollouts.json").write_text(json.dumps(results, indent=2) + "\n")
    _print(results)
    _plot(results, args.out / "mjx_rollouts.png")
    return results


def problem_costs(labels: list, rounds: int, out: Path) -> dict:
    """:func:`gradient_costs` of each shipped tuning problem, printed and written to ``out/gradient_costs.json``."""
    costs = {}
    print(f"{'problem':18s} {'params':>6s} {'auto':>8s}   reverse: time, compile, memory   forward: time, compile, "
          "memory (x the forward evaluation)   16 starts (x one start)")  # fmt: skip
    for label in labels:
        problem, settings, _ = load_problem(label)
        costs[label] = cost = gradient_costs(problem, settings, rounds=rounds, population=16)
        e = cost["entries"]
        cells = [f"{e[m]['ratio']:5.1f} {e[m]['compile_ratio']:5.1f} {e[m]['memory_ratio']:8.3g}"
                 for m in ("reverse_mode", "forward_mode")]  # fmt: skip
        print(f"{label:18s} {cost['parameters']:6d} {cost['mode']:>8s}   {cells[0]:28s}   {cells[1]:28s}   "
              f"{cost['population_ratio']:5.1f}", flush=True)  # fmt: skip
        (out / "gradient_costs.json").write_text(json.dumps({"platform": _platform(), "rounds": rounds,
                                                             "problems": costs}, indent=2) + "\n")  # fmt: skip
    return costs


def _step_models() -> dict:
    """``{label: (mjx.Model, solver_iterations)}``: the MJX models of the shipped tuning problems."""
    from jaxobs.mjx import compliant_6dof, force_1dof
    from jaxobs.mjx.robot import make_robot
    from jaxobs.papers.shipped import ROBOTS as root

    cart = make_robot(root / "cartpole_payload.xml", ["push"], ["cart_position"])
    arm = make_robot(root / "arm_on_table.xml", ["shoulder_motor", "elbow_motor"], ["shoulder_angle"],
                     solver_iterations=4)  # fmt: skip
    return {
        "1-DOF force plant": (force_1dof.load_model()[1], None),
        "6-DOF compliant peg": (compliant_6dof.load_model()[1], None),
        "cart-pole with payload": (cart.model, None),
        "arm on a table (4 solver iterations)": (arm.model, 4),
    }


def _flops(fn, args) -> float:
    """The floating-point operations XLA's cost analysis counts in ``fn`` compiled for ``args`` (a loop body
    once: a ratio of two such counts compares the bodies)."""
    analysis = jax.jit(fn).lower(*args).compile().cost_analysis()
    return float((analysis[0] if isinstance(analysis, list) else analysis)["flops"])


def _vjp(fn, x, cotangent):
    """``fn``'s forward pass and its backward pass of ``cotangent`` (reverse mode)."""
    return jax.vjp(fn, x)[1](cotangent)


def step_costs(batches: list, rounds: int, out: Path, steps: int = 50) -> dict:
    """``steps`` physics steps (a ``lax.scan``, command held) of each MJX model against their ``jax.vjp``, per
    batch size (see the module docstring), printed and written to ``out/step_costs.json``."""
    from jaxobs.mjx.common import initial_data, step

    results = {}
    for label, (model, iterations) in _step_models().items():
        data = initial_data(model, jnp.float64)

        def physics(x, data=data, model=model, iterations=iterations):
            qpos, qvel, ctrl = x

            def advance(carry, _):
                after = step(model, data.replace(qpos=carry[0], qvel=carry[1], ctrl=ctrl), iterations)
                return (after.qpos, after.qvel), None

            return jax.lax.scan(advance, (qpos, qvel), None, length=steps)[0]

        for batch in batches:
            keys = jax.random.split(jax.random.PRNGKey(batch), 3)
            x = tuple(a + 1e-3 * jax.random.normal(k, (batch, *a.shape))
                      for k, a in zip(keys, (data.qpos, data.qvel, data.ctrl), strict=True))  # fmt: skip
            batched = jax.vmap(physics)
            cotangent = jax.tree.map(jnp.ones_like, jax.eval_shape(batched, x))
            calls = {"forward": (batched, (x,)), "vjp": (partial(_vjp, batched), (x, cotangent))}
            entries = {name: (lambda call=call: call, True, 1.0) for name, call in calls.items()}
            timings, _ = time_interleaved(entries, rounds, required=tuple(entries))
            f, v = timings["forward"], timings["vjp"]
            flops = {name: _flops(*call) for name, call in calls.items()}
            row = {
                "forward": f.record(batch * steps, "physics plant-steps/s"),
                "vjp": v.record(batch * steps, "physics plant-steps/s"),
                "ratio": paired_ratio(f, v),
                "compile_ratio": v.compile_s / f.compile_s,
                "flops_ratio": flops["vjp"] / flops["forward"],
            }
            results.setdefault(label, {})[str(batch)] = row
            print(
                f"{label:38s} batch {batch:4d}: {steps} steps {1e3 * row['forward']['seconds']['median']:8.1f} ms,"
                f" vjp {format_range(row['ratio'], '.2g', 'x')} (compile {row['compile_ratio']:.1f}x, XLA's flop count "
                f"{row['flops_ratio']:.1f}x)",
                flush=True,
            )
            (out / "step_costs.json").write_text(
                json.dumps({"platform": _platform(), "rounds": rounds, "steps": steps, "models": results}, indent=2)
                + "\n"
            )
    return results


def _print(results: dict) -> None:
    print(
        f"device: {results['platform']['device']}; {results['steps']} control steps x {SUBSTEPS} physics steps; "
        f"{results['rounds']} interleaved rounds, median [min, max]"
    )
    for batch, row in results["batches"].items():
        diff = row["trace_check"]["max_abs_force_difference_N"]
        print(f"batch {batch} (trace vs MJX: rollout {diff['cpu_rollout']:.2g} N, loop {diff['cpu_loop']:.2g} N)")
        for name in ("mjx_forward", "cpu_rollout", "cpu_loop"):
            print(f"   {name:<13} {format_range(row[name]['throughput'], '.3g')} physics plant-steps/s")
        print(f"   MJX forward / CPU rollout: {format_range(row['forward_ratio_vs_cpu_rollout'], '.3g', 'x')}")
        print(f"   MJX forward / CPU loop:    {format_range(row['forward_ratio_vs_cpu_loop'], '.3g', 'x')}")
        central = format_range(row["cpu_central_difference_gradient"]["seconds"], ".3g")
        print(
            f"   MJX gradient step {format_range(row['mjx_gradient']['seconds'], '.3g')} s; central differences "
            f"with the faster CPU peer {central} s: "
            f"{format_range(row['gradient_ratio_vs_central_differences'], '.3g', 'x')}"
        )
    print(f"total {results['total_seconds']:.0f} s")


def _yerr(summaries: list) -> list:
    """Matplotlib error bars from the median to the [min, max] range of each summary."""
    return [[s["median"] - s["min"] for s in summaries], [s["max"] - s["median"] for s in summaries]]


def _plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot, save_figure

    fig, (a, b) = pyplot().subplots(1, 2, figsize=(11, 4.2))
    batches = [int(k) for k in results["batches"]]
    rows = list(results["batches"].values())
    device = results["platform"]["device"]
    for name, label, style in (
        ("mjx_forward", f"jaxobs/MJX ({device})", "o-"),
        ("cpu_rollout", "CPU MuJoCo, mujoco.rollout batched", "s--"),
        ("cpu_loop", "CPU MuJoCo, Python loop (extrapolated)", "^:"),
    ):
        rates = [r[name]["throughput"] for r in rows]
        a.errorbar(batches, [r["median"] for r in rates], yerr=_yerr(rates), fmt=style, capsize=3, label=label)
    a.set_xscale("log")
    a.set_yscale("log")
    a.set_xlabel("batch (plants)")
    a.set_ylabel("physics plant-steps / s (median, bar: [min, max])")
    a.set_title(f"forward, AOB-1 in the loop, {results['physics_steps_per_rollout']} steps/rollout", fontsize=10)
    a.legend(fontsize=8)
    for name, label, style in (
        ("mjx_gradient", "jaxobs/MJX value_and_grad", "o-"),
        ("cpu_central_difference_gradient", "CPU MuJoCo, central differences (4 rollouts, faster peer)", "s--"),
    ):
        secs = [r[name]["seconds"] for r in rows]
        b.errorbar(batches, [s["median"] for s in secs], yerr=_yerr(secs), fmt=style, capsize=3, label=label)
    b.set_xscale("log")
    b.set_yscale("log")
    b.set_xlabel("batch (plants)")
    b.set_ylabel("s / gradient step (median, bar: [min, max])")
    b.set_title(f"gradient w.r.t. (log R, log q_active), {results['rounds']} interleaved rounds", fontsize=10)
    b.legend(fontsize=8)
    save_figure(fig, path.parent, path.stem)


if __name__ == "__main__":
    main()
