"""The cost of an MJX physics step stage by stage, forward and in reverse mode, at batch 16 and 128 on the CPU.

A rollout of ``--steps`` physics steps (``jaxobs.mjx.common.step`` in a ``lax.scan``, the control held) of a
``vmap``-ed batch is compiled forward and with its ``jax.vjp`` (the forward and backward pass reverse mode runs,
cotangent ones on the final ``qpos`` and ``qvel``, differentiated with respect to the initial ``qpos``, ``qvel``
and the control). Programs:

* ``forward``: the rollout.
* ``reverse``: its vjp as jaxobs computes it: the constraint solve differentiated implicitly and, where at most
  ``jaxobs.mjx.common.JACOBIAN_MAX`` input entries per step are differentiated, the step's backward pass as its
  forward-mode Jacobian (the 1-DOF plant, the cart-pole, the arm).
* ``reverse, JAX's transpose``: the vjp with that rule off (JAX transposes the step; the solve still implicit).
* ``reverse, 4 fixed iterations`` (models with constraint rows): the former route, the solver unrolled 4 Newton
  iterations per step and differentiated through each.

Each is timed in ``--rounds`` interleaved rounds (median), as wall time and as the process's CPU time (all of XLA's
threads; the machine is shared, so a round's CPU time is the steadier measure and the ratios use it), with its
compile time. Then one profiled run (``jax.profiler``; XLA's CPU thunks) attributes the program's time to the
stages of ``jaxobs.mjx.common.STAGES`` (each runs under its ``jax.named_scope``, which XLA keeps in every operation's
metadata) plus ``solve``, ``sensor_acc`` and ``integrator``, grouped as kinematics, com/inertia (``com_pos``,
``camlight``, ``tendon``, ``crb``, ``tendon_armature``), mass-matrix factorisation (``factor_m``), collision,
constraint build (``make_constraint``), actuation (``transmission``, ``fwd_actuation``), sensors, bias forces
(``fwd_velocity``: ``com_vel``, ``passive``, ``rne``), smooth acceleration (``fwd_acceleration``), constraint solve
and integration; the operations of a stage's backward pass (in the Jacobian rule: its forward-mode recomputation)
apart from its forward ones; what no stage owns (the scan's residual stores, carries, the Jacobian's contraction)
is "loop and residuals".

Models: the shipped MJX problems (the 1-DOF force plant, the 6-DOF compliant peg and the payload cart-pole, all three
with contacts and constraints disabled in their MJCF, and the arm on a table, with a joint limit and a wall contact;
its batch starts with the hand at the wall) and two of MJX's own test models (``mujoco/mjx/test_data``): the
humanoid (27 DOF, capsules on a plane) and the Shadow hand (30 DOF, convex meshes), whose MJCFs set
``iterations="1"`` for MJX's speed tests; here they run MuJoCo's defaults (100 iterations, tolerance 1e-8, 50
line-search iterations), as a user's model would.

``--variants`` times the reverse pass under the options that may change the smooth part: the other Jacobian layout
(``opt.jacobian`` dense or sparse), the disable flags of what a model does not use (``clampctrl``,
``filterparent``, ``eulerdamp`` without damping, ``gravity`` without gravity), JAX's transpose of the step without
the rematerialisation ``jaxobs.mjx.common.step`` applies on that route (every step's residuals stored), and, on a
model with more differentiated entries per step than ``JACOBIAN_MAX``, the
Jacobian rule for all of them; ``--variants-only`` skips the stage breakdown.

    python benchmarks/mjx_stages.py --out DIR [--batches 16 128] [--steps 50] [--rounds 5] [--models NAME ...]
                                    [--variants | --variants-only]

Writes ``DIR/mjx_stages.json`` (merged with an earlier one in DIR) and ``DIR/mjx_stages.png``.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import collections  # noqa: E402
import copy  # noqa: E402
import gzip  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import mjx  # noqa: E402

from jaxobs.mjx import common  # noqa: E402

MJX_TEST_DATA = Path(mujoco.__file__).parent / "mjx" / "test_data"
GROUPS = {
    "kinematics": "kinematics",
    "com_pos": "com/inertia",
    "camlight": "com/inertia",
    "tendon": "com/inertia",
    "crb": "com/inertia",
    "tendon_armature": "com/inertia",
    "factor_m": "mass-matrix factorisation",
    "collision": "collision",
    "make_constraint": "constraint build",
    "transmission": "actuation",
    "sensor_pos": "sensors",
    "fwd_velocity": "bias forces",
    "sensor_vel": "sensors",
    "fwd_actuation": "actuation",
    "fwd_acceleration": "smooth acceleration",
    "solve": "constraint solve",
    "sensor_acc": "sensors",
    "integrator": "integration",
}
LOOP = "loop and residuals"
ORDER = list(dict.fromkeys(GROUPS.values())) + [LOOP]
assert {name for name, _ in common.STAGES} | {"solve", "sensor_acc", "integrator"} == set(GROUPS)


def _mujoco_defaults(mj: mujoco.MjModel) -> mujoco.MjModel:
    """MuJoCo's default solver settings (100 iterations, tolerance 1e-8, 50 line-search iterations)."""
    mj.opt.iterations, mj.opt.tolerance, mj.opt.ls_iterations = 100, 1e-8, 50
    return mj


def load_models(names=None) -> dict:
    """``{label: (MjModel, qpos the batch is spread around or None)}``."""
    from jaxobs.mjx import compliant_6dof, force_1dof
    from jaxobs.papers.shipped import ROBOTS as robots

    loaders = {
        "1-DOF force plant": lambda: force_1dof.load_model()[0],
        "6-DOF compliant peg": lambda: compliant_6dof.load_model()[0],
        "cart-pole with payload": lambda: mujoco.MjModel.from_xml_path(str(robots / "cartpole_payload.xml")),
        "arm on a table": lambda: mujoco.MjModel.from_xml_path(str(robots / "arm_on_table.xml")),
        "humanoid (MJX test model)": lambda: _mujoco_defaults(
            mujoco.MjModel.from_xml_path(str(MJX_TEST_DATA / "humanoid" / "humanoid.xml"))
        ),
        "Shadow hand (MJX test model)": lambda: _mujoco_defaults(
            mujoco.MjModel.from_xml_path(str(MJX_TEST_DATA / "shadow_hand" / "scene_right.xml"))
        ),
    }
    poses = {"arm on a table": np.array([-0.77, 0.0])}  # the hand at the wall: contact rows active
    return {name: (loaders[name](), poses.get(name)) for name in (names or loaders)}


def rollout_programs(mj: mujoco.MjModel, qpos, batch: int, steps: int, step=common.step) -> tuple[dict, tuple]:
    """``({name: function}, args)``: the programs of the module docstring for one model and batch size (``step``:
    the physics step, ``jaxobs.mjx.common.step``'s signature)."""
    model = common.put_model(mj)
    data = common.initial_data(model, jnp.float64)
    data = data if qpos is None else data.replace(qpos=jnp.asarray(qpos, jnp.float64))
    keys = jax.random.split(jax.random.PRNGKey(batch), 3)
    x = tuple(a + 1e-3 * jax.random.normal(k, (batch, *a.shape), a.dtype)
              for k, a in zip(keys, (data.qpos, data.qvel, data.ctrl), strict=True))  # fmt: skip

    def rollout(step):
        def run(x):
            qpos, qvel, ctrl = x

            def body(d, _):
                return step(model, d.replace(ctrl=ctrl)), None

            out = jax.lax.scan(body, data.replace(qpos=qpos, qvel=qvel), None, length=steps)[0]
            return out.qpos, out.qvel

        return jax.vmap(run)

    def reverse(step):
        forward = rollout(step)

        def vjp(x):
            out, pullback = jax.vjp(forward, x)
            return pullback(jax.tree.map(jnp.ones_like, out))

        return vjp

    programs = {"forward": rollout(step), "reverse": reverse(step),
                "reverse, JAX's transpose": _transposed(reverse(step))}  # fmt: skip
    if common.constraint_rows(data):
        programs["reverse, 4 fixed iterations"] = reverse(lambda m, d: step(m, d, 4))
    return programs, (x,)


def _transposed(fn, jacobian_max: int = 0):
    """``fn`` traced with ``jaxobs.mjx.common.JACOBIAN_MAX = jacobian_max``: 0 turns the step's Jacobian rule off
    (JAX transposes the step)."""

    def traced(*args):
        saved, common.JACOBIAN_MAX = common.JACOBIAN_MAX, jacobian_max
        try:
            return fn(*args)
        finally:
            common.JACOBIAN_MAX = saved

    return traced


def compile_and_time(programs: dict, args: tuple, rounds: int) -> dict:
    """Per program: compile time, and per round wall and process CPU time, in interleaved rounds."""
    jax.jit(lambda v: v + 1).lower(1.0).compile()  # the process's one-time compilation costs, paid outside
    compiled, rows = {}, {}
    for name, fn in programs.items():
        start = time.perf_counter()
        compiled[name] = jax.jit(fn).lower(*args).compile()
        rows[name] = {"compile_s": time.perf_counter() - start, "wall_s": [], "cpu_s": []}
        jax.block_until_ready(compiled[name](*args))
    for _ in range(rounds):
        for name, fn in compiled.items():
            wall, cpu = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(*args))
            rows[name]["cpu_s"].append(time.process_time() - cpu)
            rows[name]["wall_s"].append(time.perf_counter() - wall)
    return compiled, rows


_INSTRUCTION = re.compile(r'^\s*(?:ROOT\s+)?%?([\w.\-]+) = .*?op_name="([^"]*)"')
_CONTAINERS = ("while", "conditional", "call")


def _attribution(hlo_text: str) -> dict:
    """``{instruction: (group, "forward" | "backward")}`` from the compiled program's operation metadata."""
    owner = {}
    for line in hlo_text.splitlines():
        match = _INSTRUCTION.match(line)
        if not match:
            continue
        name, op_name = match.groups()
        parts = [re.sub(r"^(?:[\w]+\()+", "", part).rstrip(")") for part in op_name.split("/")]  # jvp(kinematics)
        stage = next((p for p in parts if p in GROUPS), None)
        direction = "backward" if "transpose(" in op_name else "forward"
        owner[name] = (GROUPS[stage] if stage else LOOP, direction)
    return owner


def profile(compiled, args: tuple, runs: int = 3) -> dict:
    """Milliseconds per run of each ``(group, direction)``: a ``jax.profiler`` trace of ``runs`` calls, XLA's CPU
    thunks attributed by :func:`_attribution` (loop, conditional and call thunks, which contain others, left out)."""
    owner = _attribution(compiled.as_text())
    folder = tempfile.mkdtemp(prefix="mjx_stages_")
    try:
        jax.profiler.start_trace(folder, create_perfetto_trace=True)
        for _ in range(runs):
            jax.block_until_ready(compiled(*args))
        jax.profiler.stop_trace()
        trace = next(Path(folder).rglob("perfetto_trace.json.gz"))
        events = json.loads(gzip.decompress(trace.read_bytes()))
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    events = events["traceEvents"] if isinstance(events, dict) else events
    totals = collections.Counter()
    for event in events:
        name = event.get("name", "")
        if event.get("ph") == "X" and name in owner and not name.startswith(_CONTAINERS):
            group, direction = owner[name]
            totals[f"{group}|{direction}"] += event.get("dur", 0) / 1e3 / runs
    return dict(totals)


def measure(mj, qpos, batch: int, steps: int, rounds: int) -> dict:
    """Times, compile times, ratios to the forward program, and the profile of every program."""
    programs, args = rollout_programs(mj, qpos, batch, steps)
    compiled, rows = compile_and_time(programs, args, rounds)
    base = rows["forward"]
    for name, row in rows.items():
        row["cpu_ratio"] = statistics.median(np.divide(row["cpu_s"], base["cpu_s"]))
        row["wall_ratio"] = statistics.median(np.divide(row["wall_s"], base["wall_s"]))
        row["compile_ratio"] = row["compile_s"] / base["compile_s"]
        row["profile_ms"] = profile(compiled[name], args)
    data = common.initial_data(common.put_model(mj), jnp.float64)
    return {"nv": int(mj.nv), "constraint_rows": common.constraint_rows(data), "programs": rows}


def _stored_step(model, data, solver_iterations=None):
    """The physics step without the Jacobian rule and without rematerialisation, for JAX to transpose (storing each
    step's residuals): ``jaxobs.mjx.common.forward`` (the implicit solve) and the model's Euler or implicit-fast
    integrator."""
    data = common.forward(model, data, solver_iterations)
    if mujoco.mjtIntegrator(int(model.opt.integrator)) == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return mjx.implicit(model, data)
    if mujoco.mjtIntegrator(int(model.opt.integrator)) != mujoco.mjtIntegrator.mjINT_EULER:
        raise ValueError("the stored-residuals variant takes Euler and implicit-fast models")
    return mjx.euler(model, data)


def _variant_models(mj: mujoco.MjModel) -> dict:
    """The other Jacobian layout, and the disable flags of features the model does not use."""
    other = copy.copy(mj)
    dense = mj.opt.jacobian == mujoco.mjtJacobian.mjJAC_DENSE or (
        mj.opt.jacobian == mujoco.mjtJacobian.mjJAC_AUTO and mj.nv < 60
    )
    other.opt.jacobian = mujoco.mjtJacobian.mjJAC_SPARSE if dense else mujoco.mjtJacobian.mjJAC_DENSE
    flags = copy.copy(mj)
    disable = mujoco.mjtDisableBit
    unused = disable.mjDSBL_CLAMPCTRL | disable.mjDSBL_FILTERPARENT
    if not np.any(mj.dof_damping):
        unused |= disable.mjDSBL_EULERDAMP
    if not np.any(mj.opt.gravity):
        unused |= disable.mjDSBL_GRAVITY
    flags.opt.disableflags |= unused
    return {"sparse Jacobian" if dense else "dense Jacobian": other, "unused features disabled": flags}


def variants(mj, qpos, batch: int, steps: int, rounds: int) -> dict:
    """The forward and reverse programs of each variant model, and the checkpointed step, against the model as
    written, in one set of interleaved rounds; ratios to the model as written's forward program."""
    programs, args = rollout_programs(mj, qpos, batch, steps)
    chosen = {"as written: forward": programs["forward"], "as written: reverse": programs["reverse"],
              "as written: reverse, JAX's transpose": programs["reverse, JAX's transpose"]}  # fmt: skip
    stored, _ = rollout_programs(mj, qpos, batch, steps, _stored_step)
    chosen["residuals stored: reverse, JAX's transpose"] = stored["reverse"]
    entries = mj.nq + mj.nv + mj.nu + mj.na  # the differentiated entries per step
    if entries > common.JACOBIAN_MAX:
        chosen[f"Jacobian rule for all {entries} entries: reverse"] = _transposed(programs["reverse"], entries)
    for label, variant in _variant_models(mj).items():
        other, _ = rollout_programs(variant, qpos, batch, steps)
        chosen[f"{label}: forward"] = other["forward"]
        chosen[f"{label}: reverse"] = other["reverse"]
    _, rows = compile_and_time(chosen, args, rounds)
    base = rows["as written: forward"]
    return {name: {"cpu_ratio": statistics.median(np.divide(row["cpu_s"], base["cpu_s"])),
                   "compile_ratio": row["compile_s"] / base["compile_s"], "cpu_s": row["cpu_s"]}
            for name, row in rows.items()}  # fmt: skip


def _platform() -> dict:
    return {"jax": jax.__version__, "mujoco": mujoco.__version__, "backend": jax.default_backend(),
            "cpu_count": os.cpu_count()}  # fmt: skip


def _print(label: str, batch: int, result: dict) -> None:
    rows = result["programs"]
    forward = rows["forward"]
    print(
        f"{label} (nv {result['nv']}, {result['constraint_rows']} constraint rows), batch {batch}: forward "
        f"{1e3 * statistics.median(forward['cpu_s']):.2f} ms CPU, compiled in {forward['compile_s']:.1f} s"
    )
    for name, row in rows.items():
        if name == "forward":
            continue
        print(
            f"   {name:32s} {row['cpu_ratio']:5.2f}x CPU time ({row['wall_ratio']:5.2f}x wall), compile "
            f"{row['compile_ratio']:4.2f}x"
        )
    for name, row in rows.items():
        shares = sorted(row["profile_ms"].items(), key=lambda kv: -kv[1])[:6]
        print(f"   profile {name}: " + ", ".join(f"{k} {v:.2f}" for k, v in shares), flush=True)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--batches", type=int, nargs="+", default=[16, 128])
    parser.add_argument("--steps", type=int, default=50, help="physics steps per rollout")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--models", nargs="+", help="labels of the models (default: all)")
    parser.add_argument("--variants", action="store_true", help="Jacobian layout, disable flags, checkpointing")
    parser.add_argument("--variants-only", action="store_true", help="the variants without the stage breakdown")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "mjx_stages.json"
    results = json.loads(path.read_text()) if path.exists() else {"models": {}, "variants": {}}
    results.update(platform=_platform(), steps=args.steps, rounds=args.rounds)
    for label, (mj, qpos) in load_models(args.models).items():
        for batch in args.batches:
            start = time.perf_counter()
            load = os.getloadavg()[0]
            if not args.variants_only:
                result = measure(mj, qpos, batch, args.steps, args.rounds)
                result.update(seconds=time.perf_counter() - start, load_average=[load, os.getloadavg()[0]])
                results["models"].setdefault(label, {})[str(batch)] = result
                _print(label, batch, result)
            if args.variants or args.variants_only:
                result = variants(mj, qpos, batch, args.steps, args.rounds)
                result["load_average"] = [load, os.getloadavg()[0]]
                results["variants"].setdefault(label, {})[str(batch)] = result
                print(json.dumps(result, indent=1), flush=True)
            path.write_text(json.dumps(results, indent=2) + "\n")
    if results["models"]:
        plot(results, args.out / "mjx_stages.png")
    return results


def plot(results: dict, path: Path) -> None:
    """Per batch size, for each model, a bar per program whose height is its CPU time over the forward program's,
    split by stage group in the proportions of its profile."""
    from jaxobs.papers._output import pyplot, save_figure

    models = list(results["models"])
    batches = sorted({int(b) for per in results["models"].values() for b in per})
    names = ("forward", "reverse", "reverse, JAX's transpose", "reverse, 4 fixed iterations")
    hatches = {"forward": "", "backward": "//"}
    colors = dict(zip(ORDER, pyplot().get_cmap("tab20").colors, strict=False))
    size = (14, 4.6 * len(batches))
    fig, axes = pyplot().subplots(len(batches), 1, figsize=size, squeeze=False, layout="constrained")
    for ax, batch in zip(axes[:, 0], batches, strict=True):
        ticks, labels = [], []
        for i, label in enumerate(models):
            result = results["models"][label].get(str(batch))
            if result is None:
                continue
            rows = result["programs"]
            for j, name in enumerate(n for n in names if n in rows):
                x = i * (len(names) + 1) + j
                bottom, scale = 0.0, rows[name]["cpu_ratio"] / sum(rows[name]["profile_ms"].values())
                for group in ORDER:
                    for direction, hatch in hatches.items():
                        ms = rows[name]["profile_ms"].get(f"{group}|{direction}", 0.0) * scale
                        ax.bar(x, ms, bottom=bottom, color=colors[group], hatch=hatch, edgecolor="white", width=0.9)
                        bottom += ms
                ax.text(x, bottom, f"{rows[name]['cpu_ratio']:.1f}x", ha="center", va="bottom", fontsize=7)
                ticks.append(x)
                labels.append({"forward": "fwd", "reverse": "rev", "reverse, JAX's transpose": "rev (JAX)",
                               "reverse, 4 fixed iterations": "rev (K=4)"}[name])  # fmt: skip
            ax.text(i * (len(names) + 1) + 1.5, -0.16, label, transform=ax.get_xaxis_transform(), ha="center",
                    fontsize=8)  # fmt: skip
        ax.set_xticks(ticks, labels, fontsize=7)
        ax.set_ylim(0, 1.08 * ax.get_ylim()[1])  # room for the bar labels
        ax.set_ylabel("CPU time / the forward program's")
        loads = [x for per in results["models"].values() if str(batch) in per for x in per[str(batch)]["load_average"]]
        ax.set_title(f"batch {batch}, {results['steps']} physics steps, CPU (median of {results['rounds']} rounds; "
                     f"load average {min(loads):.0f} to {max(loads):.0f} on {results['platform']['cpu_count']} cores), "
                     "split by the profile's stage shares", fontsize=9)  # fmt: skip
    handles = [pyplot().Rectangle((0, 0), 1, 1, color=colors[g]) for g in ORDER]
    handles.append(pyplot().Rectangle((0, 0), 1, 1, facecolor="white", edgecolor="0.3", hatch="//"))
    fig.legend(handles, [*ORDER, "backward operations"], loc="outside right center", fontsize=8)
    save_figure(fig, path.parent, path.stem)


if __name__ == "__main__":
    main()
