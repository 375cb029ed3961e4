"""The tuner's compile time per program: the whole step (one ``lax.switch`` over the exploration, the polish and
the restart, as a user's own jitted loop compiles it) against each program alone (``tuner.step_in``, as
``jaxobs.tuning.tune`` compiles them: the exploration first, the others in the background while it runs).

Per problem and program: the seconds to trace and lower, to compile, and to run one step (the exploration's first
screening batch, the polish's first gradient evaluation of every start), the persistent compilation cache off.

    python benchmarks/tuner_programs.py --out DIR [--configs tuning/grip_example56.toml tuning/tune-small.toml]
                                        [--spread 3]

Writes ``DIR/tuner_programs.json`` and ``DIR/tuner_programs.png``.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)  # every program compiled here

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from jaxobs._config import load_toml  # noqa: E402
from jaxobs.papers.registry import tuning_problems  # noqa: E402
from jaxobs.papers.tuning_config import settings as tuning_settings  # noqa: E402
from jaxobs.tuning import make_tuner  # noqa: E402
from jaxobs.tuning.tuner import PROGRAMS  # noqa: E402

RUN = ("step", *PROGRAMS[:3])  # the whole step, then each program but "done" (which computes nothing)


def load(path: str, spread: float):
    """``(problem, settings)`` of a ``jaxobs tune`` config, its box ``theta0 +- spread`` kept (``bounded``)."""
    registry, given = tuning_problems(), load_toml(path)
    given.setdefault("baseline", {})["spread"] = spread
    name = given.get("problem", next(iter(registry)))
    config = registry[name].validate({**given, "problem": name}, path)
    return registry[name].build(config), dataclasses.replace(tuning_settings(config), bounded=True, rounds=2)


def measure(path: str, spread: float) -> dict:
    problem, settings = load(path, spread)
    tuner = make_tuner(settings, penalty=problem.penalty)
    state = tuner.init(problem.theta0, box=problem.search_box)
    polishing = state._replace(phase=jax.numpy.asarray(PROGRAMS.index("polish"), jax.numpy.int32))
    out = {"parameters": sum(v.size for v in jax.tree.leaves(problem.theta0)), "starts": settings.starts,
           "plants": problem.batch_size(problem.train), "population": settings.population}  # fmt: skip
    for name in RUN:
        index = PROGRAMS.index(name) if name in PROGRAMS else None
        if index is None:
            fn = lambda s, b: tuner.step(s, problem.losses, b)  # noqa: E731
        else:
            fn = lambda s, b, i=index: tuner.step_in(i, s, problem.losses, b)  # noqa: E731
        given = polishing if name == "polish" else state
        start = time.perf_counter()
        lowered = jax.jit(fn).lower(given, problem.train)
        traced = time.perf_counter()
        compiled = lowered.compile()
        built = time.perf_counter()
        jax.block_until_ready(compiled(given, problem.train))
        out[name] = {"trace": traced - start, "compile": built - traced, "run": time.perf_counter() - built,
                     "load": os.getloadavg()[0]}  # fmt: skip
        print(f"{Path(path).stem:20s} {name:8s} trace {out[name]['trace']:6.2f} s  compile {out[name]['compile']:6.2f} "
              f"s  one step {out[name]['run']:6.2f} s  (load {out[name]['load']:.1f})", flush=True)  # fmt: skip
    return out


def plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot, save_figure

    fig, axes = pyplot().subplots(1, len(results), figsize=(5 * len(results), 3.8), squeeze=False,
                                  layout="constrained")  # fmt: skip
    for ax, (label, r) in zip(axes.flat, results.items(), strict=True):
        trace = [r[n]["trace"] for n in RUN]
        compile_ = [r[n]["compile"] for n in RUN]
        ax.bar(RUN, trace, color="C0", label="trace and lower")
        ax.bar(RUN, compile_, bottom=trace, color="C1", label="compile")
        ax.set(ylabel="seconds", title=f"{label} ({r['parameters']} parameters, {r['plants']} plants)")
        ax.legend(fontsize=8)
    fig.suptitle("The tuner's whole step against each of its programs alone: seconds before it can run (load "
                 f"{min(r[n]['load'] for r in results.values() for n in RUN):.3g} to "
                 f"{max(r[n]['load'] for r in results.values() for n in RUN):.3g})")  # fmt: skip
    save_figure(fig, path.parent, path.stem, dpi=110)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--configs", nargs="+", default=["tuning/grip_example56.toml", "tuning/tune-small.toml"])
    parser.add_argument("--spread", type=float, default=3.0, help="the search box theta0 +- spread")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {Path(path).stem: measure(path, args.spread) for path in args.configs}
    (out / "tuner_programs.json").write_text(json.dumps({"device": jax.devices()[0].device_kind,
                                                         "results": results}, indent=2) + "\n")  # fmt: skip
    plot(results, out / "tuner_programs.png")
    return results


if __name__ == "__main__":
    main()
