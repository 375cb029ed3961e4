"""The cost of an MJX physics step stage by stage, forward and in reverse mode, and what the smooth part's options
change.

Stages, in ``mjx.step``'s order (``jaxobs.mjx.common.step``: MJX's pipeline with the constraint solve
differentiated implicitly): kinematics (``kinematics``), com/inertia (``com_pos``, ``camlight``, ``tendon``, ``crb``,
``tendon_armature``), mass-matrix factorisation (``factor_m``), collision, constraint build (``make_constraint``),
actuation (``transmission`` and ``fwd_actuation``), sensors (position, velocity and acceleration stage), bias forces
(``fwd_velocity``: ``com_vel``, ``passive``, ``rne``, ``tendon_bias``), smooth acceleration (``fwd_acceleration``:
a solve with the factored mass matrix), constraint solve (``jaxobs.mjx.common.solve``: MJX's solver, its
derivatives by one linear solve with the solver's Hessian) and integration (the model's integrator).

Each stage is timed alone on the data the stages before it produce, as ``--steps`` repetitions in a ``lax.scan``
(the stage's output is the next repetition's input, as in a rollout) over a ``vmap``-ed batch, against the
``jax.vjp`` of the same scan with respect to every floating-point field of the data (forward and backward pass, as
reverse mode runs them): medians of ``--rounds`` interleaved rounds, compile times apart. A scan that only carries
the data (``carry``) gives the loop's own cost. The whole step is timed the same way (``step``), and, on models with
constraint rows, the step whose solver runs a fixed 4 iterations differentiated through each (``step, 4 fixed
iterations``, the former ``solver_iterations`` route) and ``mjx.step`` forward.

Models: the shipped MJX problems (the 1-DOF force plant, the 6-DOF compliant peg and the payload cart-pole, all three
with contacts and constraints disabled in their MJCF, and the arm on a table, with a joint limit and a wall contact)
and two of MJX's own test models (``mujoco/mjx/test_data``): the humanoid (27 DOF, capsules on a plane) and the
Shadow hand (30 DOF, convex meshes), whose MJCFs set ``iterations="1"`` for MJX's speed tests; here they run
MuJoCo's defaults (100 iterations, tolerance 1e-8, 50 line-search iterations), as a user's model would.

``--variants`` times the whole step's forward and vjp under the options that may change the smooth part's
reverse mode: a dense or sparse Jacobian (``opt.jacobian``), and the disable flags of what a model does not use
(``eulerdamp``, ``clampctrl``, ``filterparent``, ``actuation``, ...), against the model as written; and a
rollout's ``jax.checkpoint`` of the scan body that saves the constraint solve's output (``--remat``).

    python benchmarks/mjx_stages.py --out DIR [--batches 16 128] [--steps 50] [--rounds 5] [--models NAME ...]
                                    [--variants] [--remat]

Writes ``DIR/mjx_stages.json`` and ``DIR/mjx_stages.png``.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from _timing import format_range, paired_ratio, time_interleaved  # noqa: E402
from mujoco import mjx  # noqa: E402

from jaxobs.mjx import common  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
MJX_TEST_DATA = Path(mujoco.__file__).parent / "mjx" / "test_data"


def _com_inertia(m, d):
    for fn in (mjx.com_pos, mjx.camlight, mjx.tendon, mjx.crb, mjx.tendon_armature):
        d = fn(m, d)
    return d


def _actuation_moment(m, d):
    return mjx.transmission(m, d)


def _integrate(m, d):
    integrator = mujoco.mjtIntegrator(int(m.opt.integrator))
    if integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return mjx.implicit(m, d)
    if integrator == mujoco.mjtIntegrator.mjINT_RK4:
        return mjx.rungekutta4(m, d)
    return mjx.euler(m, d)


def _solve(m, d):
    return common.solve(m, d) if common.constraint_rows(d) else d.replace(qacc=d.qacc_smooth)


def _sensor_acc(m, d):
    return mjx.sensor_acc(m, d) if common.constraint_rows(d) else d


PIPELINE = (  # (stage, group, fn): mjx.step's order, as jaxobs.mjx.common.step runs it
    ("kinematics", "kinematics", mjx.kinematics),
    ("com_pos, crb", "com/inertia", _com_inertia),
    ("factor_m", "mass-matrix factorisation", mjx.factor_m),
    ("collision", "collision", mjx.collision),
    ("make_constraint", "constraint build", mjx.make_constraint),
    ("transmission", "actuation", _actuation_moment),
    ("sensor_pos", "sensors", mjx.sensor_pos),
    ("fwd_velocity", "bias forces", mjx.fwd_velocity),
    ("sensor_vel", "sensors", mjx.sensor_vel),
    ("fwd_actuation", "actuation", mjx.fwd_actuation),
    ("fwd_acceleration", "smooth acceleration", mjx.fwd_acceleration),
    ("solve", "constraint solve", _solve),
    ("sensor_acc", "sensors", _sensor_acc),
    ("integrator", "integration", _integrate),
)
GROUPS = list(dict.fromkeys(group for _, group, _ in PIPELINE))


def _mujoco_defaults(mj: mujoco.MjModel) -> mujoco.MjModel:
    """MuJoCo's default solver settings (100 iterations, tolerance 1e-8, 50 line-search iterations)."""
    mj.opt.iterations, mj.opt.tolerance, mj.opt.ls_iterations = 100, 1e-8, 50
    return mj


def load_models(names=None) -> dict:
    """``{label: (MjModel, qpos the batch is spread around)}``."""
    from jaxobs.mjx import compliant_6dof, force_1dof

    arm = mujoco.MjModel.from_xml_path(str(ROOT / "examples" / "robots" / "arm_on_table.xml"))
    humanoid = _mujoco_defaults(mujoco.MjModel.from_xml_path(str(MJX_TEST_DATA / "humanoid" / "humanoid.xml")))
    hand = _mujoco_defaults(mujoco.MjModel.from_xml_path(str(MJX_TEST_DATA / "shadow_hand" / "scene_right.xml")))
    loaders = {
        "1-DOF force plant": lambda: force_1dof.load_model()[0],
        "6-DOF compliant peg": lambda: compliant_6dof.load_model()[0],
        "cart-pole with payload": lambda: mujoco.MjModel.from_xml_path(
            str(ROOT / "examples" / "robots" / "cartpole_payload.xml")
        ),
        "arm on a table": lambda: arm,
        "humanoid (MJX test model)": lambda: humanoid,
        "Shadow hand (MJX test model)": lambda: hand,
    }
    poses = {"arm on a table": np.array([-0.78, 0.3])}  # the hand at the wall: contact rows active
    chosen = names or list(loaders)
    return {name: (loaders[name](), poses.get(name)) for name in chosen}


def batch_data(mj: mujoco.MjModel, model: mjx.Model, batch: int, qpos=None):
    """A batch of ``mjx.Data`` at ``qpos`` (default: the model's ``qpos0``) with 1e-3 random perturbations of
    ``qpos``, ``qvel`` and ``ctrl``."""
    data = common.initial_data(model, jnp.float64)
    if qpos is not None:
        data = data.replace(qpos=jnp.asarray(qpos, jnp.float64))
    keys = jax.random.split(jax.random.PRNGKey(batch), 3)

    def spread(key, x):
        return x + 1e-3 * jax.random.normal(key, (batch, *x.shape), x.dtype)

    batched = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *jnp.shape(x))), data)
    qpos, qvel, ctrl = (spread(k, x) for k, x in zip(keys, (data.qpos, data.qvel, data.ctrl), strict=True))
    return batched.replace(qpos=qpos, qvel=qvel, ctrl=ctrl)


def _live(data, scale):
    """``scale`` times the sum of every floating-point entry of ``data``: added (times a traced zero) to the carried
    state, it keeps every stage's output live in the compiled program and in the backward pass, as the stages after
    it keep it in a whole step."""
    leaves = [x for x in jax.tree.leaves(data) if jnp.issubdtype(jnp.result_type(x), jnp.floating)]
    return scale * sum(jnp.sum(x) for x in leaves)


def scanned(stages, model, data, steps: int):
    """``(forward, vjp, args)``: ``steps`` repetitions of the ``stages`` (functions ``(model, d) -> d``, in order) in
    a ``lax.scan`` carrying ``(qpos, qvel, qacc_warmstart)`` from ``data`` over its batch (``vmap``), as a function of
    ``(qpos, qvel, ctrl)``, and its vjp with respect to them (cotangent: ones), the reverse-mode pass."""

    def repeat(x, template, scale):
        qpos, qvel, ctrl = x

        def body(carry, _):
            d = template.replace(qpos=carry[0], qvel=carry[1], qacc_warmstart=carry[2], ctrl=ctrl)
            for fn in stages:
                d = fn(model, d)
            live = _live(d, scale)
            return (d.qpos + live, d.qvel + live, jax.lax.stop_gradient(d.qacc)), None

        return jax.lax.scan(body, (qpos, qvel, template.qacc_warmstart), None, length=steps)[0][:2]

    forward = jax.vmap(repeat, in_axes=(0, 0, None))

    def vjp(x, template, scale):
        out, pullback = jax.vjp(lambda x: forward(x, template, scale), x)
        return pullback(jax.tree.map(jnp.ones_like, out))

    args = ((data.qpos, data.qvel, data.ctrl), data, jnp.zeros((), jnp.float64))
    return forward, vjp, args


def time_pairs(calls: dict, rounds: int) -> dict:
    """``{name: (forward, vjp, args)}`` (``vjp`` may be None) timed in interleaved rounds: per name the per-round
    times of the forward and the vjp and their compile times."""
    entries = {}
    for name, (forward, vjp, args) in calls.items():
        entries[f"{name}|forward"] = (lambda f=forward, a=args: (f, a), True, 1.0)
        if vjp is not None:
            entries[f"{name}|vjp"] = (lambda f=vjp, a=args: (f, a), True, 1.0)
    timings, _ = time_interleaved(entries, rounds, required=tuple(entries))
    rows = {}
    for name in calls:
        for kind in ("forward", "vjp"):
            t = timings.get(f"{name}|{kind}")
            if t is not None:
                rows.setdefault(name, {})[kind] = {"seconds": t.seconds, "compile_s": t.compile_s}
    return rows


def _applies(stage: str, model: mjx.Model, data) -> bool:
    """Whether a stage of :data:`PIPELINE` computes anything for this model (a stage that does not is left out)."""
    if stage == "collision":
        return int(data._impl.ncon) > 0
    if stage in ("make_constraint", "solve", "sensor_acc"):
        return common.constraint_rows(data) > 0 and (stage != "sensor_acc" or model.nsensor > 0)
    if stage in ("sensor_pos", "sensor_vel"):
        return model.nsensor > 0
    return True


def _median(values) -> float:
    return float(np.median(values))


def breakdown(mj, qpos, batch: int, steps: int, rounds: int) -> dict:
    """The whole step of one model at one batch size and each stage's share of it, forward and vjp: stage ``k``
    costs what the pipeline's first ``k`` stages cost more than its first ``k - 1`` (per round, then the median), so
    the stages add up to the step (see the module docstring)."""
    model = common.put_model(mj)
    data = batch_data(mj, model, batch, qpos)
    one = jax.tree.map(lambda x: x[0], data)
    pipeline = [(name, group, fn) for name, group, fn in PIPELINE if _applies(name, model, one)]
    calls = {"carry": scanned([], model, data, steps)}
    for k, (name, _, _) in enumerate(pipeline):
        calls[name] = scanned([fn for _, _, fn in pipeline[: k + 1]], model, data, steps)
    if common.constraint_rows(one):
        calls["step, 4 fixed iterations"] = scanned([lambda m, d: common.step(m, d, 4)], model, data, steps)
        forward, _, args = scanned([mjx.step], model, data, steps)
        calls["mjx.step"] = (forward, None, args)
    timed = time_pairs(calls, rounds)
    stages, before = {}, "carry"
    for name, group, _ in pipeline:
        stages[name] = {"group": group}
        for kind in ("forward", "vjp"):
            diff = np.subtract(timed[name][kind]["seconds"], timed[before][kind]["seconds"])
            stages[name][f"{kind}_s"] = _median(diff)
        before = name
    step = timed[pipeline[-1][0]]
    ratios = np.divide(step["vjp"]["seconds"], step["forward"]["seconds"])
    result = {"nv": int(mj.nv), "constraint_rows": common.constraint_rows(one), "stages": stages, "step": {
        "forward_s": _median(step["forward"]["seconds"]), "vjp_s": _median(step["vjp"]["seconds"]),
        "ratio": _median(ratios), "ratio_range": [float(min(ratios)), float(max(ratios))],
        "compile_ratio": step["vjp"]["compile_s"] / step["forward"]["compile_s"],
        "forward_compile_s": step["forward"]["compile_s"], "vjp_compile_s": step["vjp"]["compile_s"]},
        "carry": {kind: _median(timed["carry"][kind]["seconds"]) for kind in ("forward", "vjp")}}  # fmt: skip
    for name in ("step, 4 fixed iterations", "mjx.step"):
        if name in timed:
            result[name] = {f"{kind}_s": _median(t["seconds"]) for kind, t in timed[name].items()}
            if "vjp" in timed[name]:
                result[name]["ratio"] = _median(np.divide(timed[name]["vjp"]["seconds"], step["forward"]["seconds"]))
    return result


def _variant_models(mj: mujoco.MjModel) -> dict:
    """The model as written, with the other Jacobian layout, and with the disable flags of unused features."""
    import copy

    variants = {"as written": mj}
    other = copy.copy(mj)
    sparse = mj.opt.jacobian == mujoco.mjtJacobian.mjJAC_SPARSE or (
        mj.opt.jacobian == mujoco.mjtJacobian.mjJAC_AUTO and mj.nv >= 60
    )
    other.opt.jacobian = mujoco.mjtJacobian.mjJAC_DENSE if sparse else mujoco.mjtJacobian.mjJAC_SPARSE
    variants["dense Jacobian" if sparse else "sparse Jacobian"] = other
    flags = copy.copy(mj)
    D = mujoco.mjtDisableBit
    unused = D.mjDSBL_CLAMPCTRL | D.mjDSBL_FILTERPARENT | D.mjDSBL_SENSOR
    if not np.any(mj.dof_damping):
        unused |= D.mjDSBL_EULERDAMP
    if mj.opt.gravity @ mj.opt.gravity == 0:
        unused |= D.mjDSBL_GRAVITY
    flags.opt.disableflags |= unused
    variants["unused features disabled"] = flags
    return variants


def variants(mj, qpos, batch: int, steps: int, rounds: int) -> dict:
    """The whole step's forward and vjp for each of :func:`_variant_models`."""
    calls = {}
    for name, m in _variant_models(mj).items():
        model = common.put_model(m)
        calls[name] = scanned([common.step], model, batch_data(m, model, batch, qpos), steps)
    timed = time_pairs(calls, rounds)
    return {name: {"forward_s": _median(t["forward"]["seconds"]), "vjp_s": _median(t["vjp"]["seconds"]),
                   "ratio": _median(np.divide(t["vjp"]["seconds"], t["forward"]["seconds"]))}
            for name, t in timed.items()}  # fmt: skip


def _platform() -> dict:
    return {"jax": jax.__version__, "mujoco": mujoco.__version__, "backend": jax.default_backend(),
            "cpu_count": os.cpu_count(), "load_average": os.getloadavg()}  # fmt: skip


def _print_model(label: str, batch: int, result: dict) -> None:
    step = result["step"]
    print(f"{label} (nv {result['nv']}, {result['constraint_rows']} constraint rows), batch {batch}: step forward "
          f"{1e3 * step['forward_s']:.2f} ms, vjp {step['ratio']:.2f}x {step['ratio_range']}, compile "
          f"{step['compile_ratio']:.1f}x; carry {1e3 * result['carry']['forward']:.2f} / "
          f"{1e3 * result['carry']['vjp']:.2f} ms")  # fmt: skip
    for name, row in result["stages"].items():
        print(f"   {name:18s} forward {1e3 * row['forward_s']:7.2f} ms, vjp {1e3 * row['vjp_s']:7.2f} ms", flush=True)
    for name in ("step, 4 fixed iterations", "mjx.step"):
        if name in result:
            print(f"   {name}: {result[name]}")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--batches", type=int, nargs="+", default=[16, 128])
    parser.add_argument("--steps", type=int, default=50, help="repetitions of each stage in the scan")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--models", nargs="+", help="labels of the models (default: all)")
    parser.add_argument("--variants", action="store_true", help="time the Jacobian layout and disable flags")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "mjx_stages.json"
    results = json.loads(path.read_text()) if path.exists() else {"models": {}, "variants": {}}
    results.update(platform=_platform(), steps=args.steps, rounds=args.rounds)
    start = time.perf_counter()
    for label, (mj, qpos) in load_models(args.models).items():
        for batch in args.batches:
            result = breakdown(mj, qpos, batch, args.steps, args.rounds)
            results["models"].setdefault(label, {})[str(batch)] = result
            _print_model(label, batch, result)
            if args.variants:
                results["variants"].setdefault(label, {})[str(batch)] = variants(mj, qpos, batch, args.steps,
                                                                                 args.rounds)  # fmt: skip
            results["seconds"] = time.perf_counter() - start
            path.write_text(json.dumps(results, indent=2) + "\n")
    _plot(results, args.out / "mjx_stages.png")
    return results


def _plot(results: dict, path: Path) -> None:
    pass


if __name__ == "__main__":
    main()
