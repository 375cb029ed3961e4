"""The ``jaxobs`` command.

jaxobs sweep [--config FILE.toml] [--out DIR] [--overwrite]   (no config: the embedded default)
jaxobs tune [--config FILE.toml] [--out DIR] [--overwrite]    (no config: the embedded 1-DOF default)
jaxobs reproduce --list
jaxobs reproduce NAME [NAME ...] [--out DIR]     (NAME "all" runs every reproduction)

A user error (a bad config file or key, an output directory that cannot be written or is held by another
jaxobs process, a run that cannot fit in memory, a sweep or checkpoint of something else in DIR) prints one
line and exits with status 2; the output directory is checked and locked before anything is built or compiled.
Ctrl-C prints where to resume and exits with status 130 (at once, skipping the interpreter's shutdown, when
run as the command). Only a bug shows a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from jaxobs._resources import JobError, locked_out_dir

RESUME_HINT = "rerun the same command to resume"


def _reproduce(args) -> int:
    from jaxobs.papers import REPRODUCTIONS

    if args.list or not args.names:
        for name, fn in REPRODUCTIONS.items():
            doc = (sys.modules[fn.__module__].__doc__ or "").strip().splitlines()[0]
            print(f"{name:28s} {doc}")
        return 0
    names = list(REPRODUCTIONS) if args.names == ["all"] else args.names
    unknown = [n for n in names if n not in REPRODUCTIONS]
    if unknown:
        print(f"unknown reproduction {', '.join(unknown)}; choose from: {', '.join(REPRODUCTIONS)}", file=sys.stderr)
        return 2
    out = Path(args.out)
    with locked_out_dir(out):
        for name in names:
            _reproduce_one(name, REPRODUCTIONS[name], out)
    return 0


def _reproduce_one(name: str, reproduction, out: Path) -> None:
    start = time.perf_counter()
    summary = reproduction(out)
    print(
        f"{name}: wrote {out / (name + '.json')} and {', '.join(summary['figures']) or 'no figures'} "
        f"in {time.perf_counter() - start:.1f} s"
    )
    for key, value in summary.items():
        if key.startswith(("rms_", "delta_f_ss", "kalman_gains_", "L_r_max")) and not isinstance(value, dict | list):
            print(f"  {key} = {value:.6g}")
        elif key == "rms_force_error":
            print("  rms_force_error = " + ", ".join(f"{k}: {v:.4f}" for k, v in value.items()))


def _config(args, validate):
    """``validate(the TOML of args.config, its name)`` (the embedded default without one); raises
    :class:`jaxobs._config.ConfigError`."""
    from jaxobs._config import load_toml

    given = load_toml(args.config) if args.config else {}
    return validate(given, args.config or "<default>")


def _sweep_module(given: dict, source: str):
    """The sweep named by the config's ``scenario`` key (default: the force-control sweep)."""
    from jaxobs._config import fail
    from jaxobs.papers import force_robustness, grip_example56_sweep, liu_peng_sweep, sbw_robustness

    sweeps = {
        "force-control": force_robustness,
        sbw_robustness.NAME: sbw_robustness,
        liu_peng_sweep.NAME: liu_peng_sweep,
        grip_example56_sweep.NAME: grip_example56_sweep,
    }
    name = given.get("scenario", "force-control")
    if name not in sweeps:
        fail(source, "scenario", f"must be one of {', '.join(map(repr, sweeps))}, got {name!r}")
    return sweeps[name]


def _sweep(args) -> int:
    def validate(given, source):
        module = _sweep_module(given, source)
        return module, module.validate_config(given, source)

    from jaxobs.sweep import read_manifest

    module, config = _config(args, validate)
    out = Path(args.out)
    with locked_out_dir(out):
        if not args.overwrite:
            read_manifest(out)  # a damaged manifest is reported before the sweep is built
        summary = module.run(config, out, progress=not args.no_progress, overwrite=args.overwrite)
    print(
        f"{summary['num_configs']} configurations in {summary.get('seconds', 0.0):.1f} s; "
        f"wrote {out / 'summary.json'}, {out / 'report.md'} and {', '.join(summary['figures'])}"
    )
    for name, s in summary.get("controllers", {"all": summary}).items():
        if "stable_fraction" in s:
            print(f"  {name:6s} stable fraction {s['stable_fraction']:.3f}")
    return 0


def _tune(args) -> int:
    import logging

    from jaxobs.papers import tuning

    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    logging.getLogger("jaxobs").addHandler(handler)
    logging.getLogger("jaxobs").setLevel(logging.INFO)
    logging.getLogger("jaxobs").propagate = False  # once, even where a library configured the root logger
    config = _config(args, tuning.validate_config)
    out = Path(args.out)
    with locked_out_dir(out):
        summary = tuning.run(config, out, progress=not args.no_progress, overwrite=args.overwrite)
    print(
        f"{summary['problem']}: {summary['evaluations']} gradient evaluations ({summary['rollouts']} rollouts, "
        f"{summary['seconds_tune']:.1f} s, stopped: {summary['stopped']}); wrote {out / 'tuned.json'} and "
        f"{', '.join(summary['figures'])}"
    )
    for name, s in summary["heldout"].items():
        change = s["reduction_vs_hand_set"]
        note = "" if change is None or name == "hand-set" else f"  ({100 * change:+.1f} % lower than hand-set)"
        print(f"  held-out {name:30s} objective {s['objective']:.4g}  finite {s['finite_fraction']:.3f}{note}")
    return 0


def main(argv=None) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    parser = argparse.ArgumentParser(prog="jaxobs", description=__doc__.strip().splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for name, func, help_text, config_help in (
        ("sweep", _sweep, "Monte-Carlo robustness sweep (resumable; rerun to continue)",
         "its 'scenario' key picks the sweep: force-control (default), steer_by_wire, liu_peng, grip-example56"),
        ("tune", _tune, "tune an observer's Q/R (or gains) by gradient descent against rollouts (resumable)",
         "its 'problem' key picks the problem: force_1dof (default), peg_on_hole, grip-example56"),
    ):  # fmt: skip
        run = commands.add_parser(name, help=help_text)
        run.add_argument("--config", help=f"TOML file overriding the embedded default; {config_help}")
        run.add_argument("--out", default=f"out/{name}", help=f"output directory (default: out/{name})")
        run.add_argument("--overwrite", action="store_true", help="discard a run of another config in --out")
        run.add_argument("--no-progress", action="store_true", help="no progress bar")
        run.set_defaults(func=func)
    rep = commands.add_parser("reproduce", help="reproduce a paper's numbers and figures")
    rep.add_argument("names", nargs="*", help="reproduction name(s), or 'all'")
    rep.add_argument("--list", action="store_true", help="list the available reproductions")
    rep.add_argument("--out", default="out", help="output directory (default: out)")
    rep.set_defaults(func=_reproduce)
    as_command = argv is None
    args = parser.parse_args(argv)
    from jaxobs.tuning import CheckpointError, TuningError

    try:
        return args.func(args)
    except KeyboardInterrupt as exc:  # jaxobs._resources.Interrupted says where it stopped
        resumable = args.command != "reproduce"
        message = str(exc) or ("interrupted; " + RESUME_HINT if resumable else "interrupted")
        print(f"jaxobs {args.command}: {message}", file=sys.stderr)
        if as_command:  # the process ends here: after Ctrl-C stopped an XLA compilation, jaxlib 0.10 can crash
            sys.stdout.flush()  # (SIGSEGV) while the interpreter shuts down; every file is already in place
            sys.stderr.flush()
            os._exit(130)
        return 130
    except (JobError, CheckpointError, TuningError) as exc:  # ConfigError and SweepError are JobErrors
        print(f"jaxobs {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
