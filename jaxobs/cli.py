"""The jaxobs command: robustness sweeps, tuning against MJX rollouts, reproductions of the papers.

``jaxobs sweep``, ``jaxobs tune`` and ``jaxobs reproduce`` (``--list``, ``--print-config``, ``--config FILE.toml``,
``--out DIR``; several processes with ``--coordinator HOST:PORT --num-processes N --process-id I`` or
``--distributed``). This module maps strings and TOML to the objects of :mod:`jaxobs.papers.registry` and holds no
logic. A user error prints one line and exits with status 2, Ctrl-C exits with status 130; only a bug shows a
traceback. Usage, caching and multi-process runs: docs/cli.md and docs/guides/multi-process.md.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import time
from pathlib import Path

from jaxobs._distributed import DEFAULT_JOIN_TIMEOUT
from jaxobs._resources import InterruptWatch, JobError, Stalled, locked_out_dir

RESUME_HINT = "rerun the same command to resume"
EXAMPLES = {
    "sweep": """examples:
  jaxobs sweep --list                                 scenarios and shipped configs
  jaxobs sweep --example sweep-small --out out/small  a shipped config, from any directory
  jaxobs sweep --config my.toml --set seed=3          a key over the file's""",
    "tune": """examples:
  jaxobs tune --list                                  problems and shipped configs
  jaxobs tune --problem own-robot --steps 5 --out out/robot
  jaxobs tune --example sideslip --seconds 60         a wall-time budget
  jaxobs tune --example cartpole_payload --print-config
  jaxobs tune --config my.toml --set plants.train=4   a key over the file's""",
}
CACHE_MIN_COMPILE_SECONDS = 0.2  # programs that compile faster are not worth a cache file


def _print_list(registry: dict, command: str | None = None) -> None:
    """The registry's entries, one line each; for ``sweep`` and ``tune``, then the shipped configs."""
    width = max(map(len, registry))
    for name, entry in registry.items():
        print(f"{name:{width}s}  {entry.summary}")
    if command is None:
        return
    from jaxobs.papers.shipped import shipped_configs

    configs = shipped_configs(command)
    width = max(len(c.name) for c in configs)
    print(f"\nshipped configs (jaxobs {command} --example NAME; --print-config prints one):")
    for c in configs:
        print(f"{c.name:{width}s}  [{c.job}] {c.summary}")


def _reproduce(args) -> int:
    from jaxobs.papers.registry import reproductions

    registry = reproductions()
    if args.list or not args.names:
        _print_list(registry)
        return 0
    names = list(registry) if args.names == ["all"] else args.names
    unknown = [n for n in names if n not in registry]
    if unknown:
        print(f"unknown reproduction {', '.join(unknown)}; choose from: {', '.join(registry)}", file=sys.stderr)
        return 2
    out = Path(args.out)
    with locked_out_dir(out):
        for name in names:
            _reproduce_one(registry[name], out)
    return 0


def _reproduce_one(reproduction, out: Path) -> None:
    start = time.perf_counter()
    result = reproduction.reproduce(out)
    print(
        f"{reproduction.name}: wrote {out / (reproduction.name + '.json')} and "
        f"{', '.join(result['figures']) or 'no figures'} in {time.perf_counter() - start:.1f} s"
    )
    for key in reproduction.headline:
        value = result[key]
        shown = ", ".join(f"{k}: {v:.4g}" for k, v in value.items()) if isinstance(value, dict) else f"{value:.6g}"
        print(f"  {key} = {shown}")


def _overrides(args, key: str) -> dict:
    """The config keys the command line sets: ``--set KEY=VALUE`` (a TOML value, else a string), ``--problem``
    and ``--steps``, as a nested table; a :class:`jaxobs._config.ConfigError` names a malformed ``--set``."""
    from jaxobs._config import ConfigError, load_toml_text

    table: dict = {}
    pairs = list(args.set or [])
    if getattr(args, "problem", None):
        pairs.append(f"{key}={args.problem!r}".replace("'", '"'))
    if getattr(args, "steps", None) is not None:
        pairs.append(f"optimizer.steps={args.steps}")
    if getattr(args, "seconds", None) is not None:
        pairs.append(f"optimizer.seconds={args.seconds!r}")
    for pair in pairs:
        name, eq, text = pair.partition("=")
        if not eq or not name.strip():
            raise ConfigError(f"--set: {pair!r} must be KEY=VALUE, e.g. --set optimizer.steps=5")
        try:
            value = load_toml_text(f"value = {text}", "--set")["value"]
        except ConfigError:
            value = text  # a bare string: --set robot.mjcf=arm.xml
        *tables, last = name.strip().split(".")
        node = table
        for part in tables:
            node = node.setdefault(part, {})
        node[last] = value
    return table


def _scenario(args, registry: dict, key: str, resolve=None):
    """``(scenario, complete config, source)``: ``--config``'s TOML (or ``--example``'s, or nothing) over the
    defaults of the scenario its ``key`` names, or ``--print-config``'s or ``--scenario``'s, or the default one, then
    the command line's keys (``--set``, checked as ``--set``). A name not in ``registry`` goes to ``resolve`` (a
    user's scenario, the sweep's ``module:ATTRIBUTE``); the config's ``key`` keeps the name as given. Raises
    :class:`jaxobs._config.ConfigError`."""
    from jaxobs._config import deep_merge, fail, load_toml
    from jaxobs.papers.shipped import config_path

    path = args.config
    if getattr(args, "example", None):
        if args.config:
            fail("--example", "--config", "give one of --config and --example")
        try:
            path = str(config_path(args.example, args.command))
        except ValueError as exc:
            fail("--example", args.example, str(exc).partition(": ")[2])
    given = load_toml(path) if path else {}
    source = path or "<default>"
    overrides = _overrides(args, key)
    if key in overrides:  # --problem: the job to run, whatever the file names
        given[key] = overrides.pop(key)
    flags = (("--print-config", getattr(args, "print_config", None)), ("--scenario", getattr(args, "scenario", None)))
    flag, chosen = next(((flag, value) for flag, value in flags if value), (None, None))  # a NAME on the command line
    name = given.get(key, chosen or next(iter(registry)))
    if chosen and name != chosen:
        fail(source, key, f"is {name!r}, not the {chosen!r} of {flag}")
    where = source if key in given else flag
    if name in registry:
        scenario = registry[name]
    elif resolve is None:
        fail(where, key, f"must be one of {', '.join(map(repr, registry))}, got {name!r}")
    else:
        try:
            scenario = resolve(name)
        except ValueError as exc:
            fail(where, key, str(exc))
    config = scenario.validate({**given, key: scenario.name}, source)
    if overrides:
        config = scenario.validate(deep_merge(config, overrides), "--set")
    return scenario, {**config, key: name}, source


def _print_config(args, registry: dict, key: str, resolve=None) -> int:
    from jaxobs._config import to_toml

    with contextlib.redirect_stdout(sys.stderr):  # stdout is the TOML only, whatever an import prints
        scenario, config, source = _scenario(args, registry, key, resolve)
    where = f"{source}'s values over the defaults of" if args.config else "the defaults of"
    header = (
        f"jaxobs {args.command} --config FILE: {where} {key} {scenario.name!r}. {scenario.summary}\n"
        "A config file needs only the keys it changes; the others keep these values."
    )
    print(to_toml(config, scenario.config_notes(), header), end="")
    return 0


def _sweep(args) -> int:
    from jaxobs.papers.registry import sweep_scenario, sweep_scenarios
    from jaxobs.sweep import read_manifest

    registry = sweep_scenarios()
    if args.list:
        _print_list(registry, "sweep")
        return 0
    if args.print_config is not None:
        return _print_config(args, registry, "scenario", sweep_scenario)
    import jax

    scenario, config, source = _scenario(args, registry, "scenario", sweep_scenario)
    config["scenario"] = scenario.name  # the sweep's identity, however the scenario was named
    out = Path(args.out)
    alone = jax.process_count() == 1  # else the engine checks and locks out_dir with every process's agreement
    with locked_out_dir(out) if alone else contextlib.nullcontext():
        if alone and not args.overwrite:
            read_manifest(out)  # a damaged manifest is reported before the sweep is built
        result = scenario.run(config, out, source=source, progress=not args.no_progress, overwrite=args.overwrite)
    if result is None:  # not process 0
        print(f"process {jax.process_index()} of {jax.process_count()}: done; process 0 wrote {out}")
        return 0
    runs = result["runs"]
    ran = f"{result['seconds']:.1f} s in {runs} run{'s' if runs != 1 else ''}, {result['compile_seconds']:.1f} s of it"
    ran += " compiling the step" + ("" if result.get("chunks_computed") else "; nothing left to compute")
    print(
        f"{result['num_configs']} configurations ({ran}); {_command_seconds(args)} (building the scenario, the "
        f"report and figures included); wrote {out / 'summary.json'}, {out / 'report.md'} and "
        f"{', '.join(result['figures'])}"
    )
    for name, s in result.get("controllers", {"all": result}).items():
        if s.get("stable_fraction") is not None:
            print(f"  {name:6s} stable fraction {s['stable_fraction']:.3f}")
    if result.get("invalid") is not None:
        print(f"  invalid configurations: {result['invalid']} of {result['num_configs']}")
    return 0


@contextlib.contextmanager
def _log_to_stderr():
    """The library's INFO messages (what compiles and for how long, screening, resumption) on stderr while a
    command runs, on the ``jaxobs`` logger alone (shown once even where a library configured the root logger);
    the logger is as it was afterwards (``main`` may be called from a program)."""
    logger = logging.getLogger("jaxobs")
    handler, saved = logging.StreamHandler(), (logger.level, logger.propagate)
    handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(saved[0])
        logger.propagate = saved[1]


def _command_seconds(args) -> str:
    return f"the command took {time.perf_counter() - args.started:.1f} s"


def _tune(args) -> int:
    from jaxobs.papers.registry import tuning_problems

    registry = tuning_problems()
    if args.list:
        _print_list(registry, "tune")
        return 0
    if args.print_config is not None:
        return _print_config(args, registry, "problem")
    import jax

    problem, config, source = _scenario(args, registry, "problem")
    out = Path(args.out)
    alone = jax.process_count() == 1  # else process 0 checks and locks out_dir with every process's agreement
    with locked_out_dir(out) if alone else contextlib.nullcontext():
        result = problem.run(config, out, source=source, progress=not args.no_progress, overwrite=args.overwrite)
    if result is None:  # not process 0
        print(f"process {jax.process_index()} of {jax.process_count()}: done; process 0 wrote {out}")
        return 0
    print(
        f"{result['problem']}: {result['evaluations']} gradient evaluations ({result['rollouts']} rollouts, "
        f"{result['seconds_tune']:.1f} s of tuning, screening and {result['compile_seconds_tune']:.1f} s of "
        f"compiling included; stopped: {result['stopped']}); {_command_seconds(args)} (the baseline, held-out "
        f"scores and figures included); wrote {out / 'tuned.json'}, {out / 'report.md'} and "
        f"{', '.join(result['figures'])}"
    )
    for name, s in result["heldout"].items():
        change = s["reduction_vs_hand_set"]
        side = "lower" if change is not None and change >= 0 else "higher"
        note = "" if change is None or name == "hand-set" else f"  ({abs(100 * change):.1f} % {side} than hand-set)"
        print(f"  held-out {name:30s} objective {s['objective']:.4g}  finite {s['finite_fraction']:.3f}{note}")
    return 0


def _join(args) -> None:
    """Join a multi-process run (:func:`jaxobs._distributed.join`) if the command line asks for one; a partner that
    does not come within ``--coordinator-timeout`` ends the process with one line and status 2."""
    from jaxobs._distributed import join

    given = (args.coordinator, args.num_processes, args.process_id)
    if not args.distributed and given == (None, None, None):
        return

    def give_up(message: str) -> None:  # from the watchdog thread, while the main thread waits inside JAX
        print(f"jaxobs {args.command}: {message} (--coordinator-timeout {args.coordinator_timeout:g})",
              file=sys.stderr, flush=True)  # fmt: skip
        sys.stdout.flush()
        os._exit(2)

    join(*given, timeout=args.coordinator_timeout, on_timeout=give_up)


def cache_dir() -> Path:
    """Where the command keeps JAX's persistent compilation cache (see the module docstring)."""
    if os.environ.get("JAXOBS_CACHE_DIR"):
        return Path(os.environ["JAXOBS_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxobs" / "jax-cache"


def _enable_compilation_cache() -> None:
    """JAX's persistent compilation cache in :func:`cache_dir` (unless the user set JAX's own); a directory that
    cannot be created leaves the cache off, with a note on stderr."""
    import jax

    if jax.config.jax_compilation_cache_dir:
        return
    path = cache_dir()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"jaxobs: no compilation cache ({path}: {exc.strerror})", file=sys.stderr)
        return
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_SECONDS)


def build_parser() -> argparse.ArgumentParser:
    """The parser of the ``jaxobs`` command (its help texts are the command-line reference)."""
    from jaxobs import __version__

    parser = argparse.ArgumentParser(prog="jaxobs", description=__doc__.strip().splitlines()[0])
    parser.add_argument("--version", action="version", version=f"jaxobs {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="{sweep,tune,reproduce}")
    for name, func, help_text, what in (
        ("sweep", _sweep, "Monte-Carlo robustness sweep (resumable; rerun to continue)", "scenario"),
        ("tune", _tune, "tune an observer's Q/R by gradient descent against MJX rollouts (resumable)", "problem"),
    ):
        run = commands.add_parser(name, help=help_text, description=help_text)
        run.add_argument("--config", metavar="FILE",
                         help=f"TOML file over the defaults; its '{what}' key picks the {what} (--list)")  # fmt: skip
        run.add_argument("--example", metavar="NAME",
                         help="a shipped config instead of --config (--list names them); with --print-config: print "
                              "it")  # fmt: skip
        run.add_argument("--set", action="append", metavar="KEY=VALUE",
                         help="a config key over the file's, checked like the file's (repeatable): e.g. --set "
                              "seed=3")  # fmt: skip
        run.add_argument("--out", metavar="DIR", default=f"out/{name}", help=f"output directory (default: out/{name})")
        run.add_argument("--overwrite", action="store_true", help="discard a run of another config in --out")
        run.add_argument("--no-progress", action="store_true", help="no progress bar")
        run.add_argument("--list", action="store_true", help=f"list the {what}s with a one-line description")
        run.add_argument("--print-config", nargs="?", const="", metavar=what.upper(),
                         help=f"print the full config of {what.upper()} (default: the default {what}; with "
                              f"--config: that file's) as TOML, every key commented, and exit")  # fmt: skip
        run.set_defaults(func=func)
    commands.choices["sweep"].add_argument(
        "--scenario", metavar="NAME", help="the scenario to run (instead of the config's 'scenario' key): a name "
        "from --list, or your own SweepScenario as MODULE:ATTRIBUTE (e.g. my_sweep:SCENARIO, my_sweep.py in the "
        "current directory)")  # fmt: skip
    tune = commands.choices["tune"]
    tune.add_argument("--problem", metavar="NAME", help="the problem to tune (--list), over the file's")
    tune.add_argument("--steps", type=int, metavar="N", help="the step cap (optimizer.steps), over the file's")
    tune.add_argument("--seconds", type=float, metavar="S",
                      help="a wall-time budget of the tuning (optimizer.seconds), over the file's")  # fmt: skip
    for name in ("sweep", "tune"):
        commands.choices[name].epilog = EXAMPLES[name]
        commands.choices[name].formatter_class = argparse.RawDescriptionHelpFormatter
    for name, engine in (("sweep", "jaxobs.sweep"), ("tune", "jaxobs.tuning")):
        launch = commands.choices[name].add_argument_group(
            "multi-process run", f"every process runs the same command; process 0 writes (see {engine})"
        )
        launch.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0's coordinator")
        launch.add_argument("--num-processes", type=int, metavar="N", help="number of processes")
        launch.add_argument("--process-id", type=int, metavar="I", help="this process's id, 0 .. N-1")
        launch.add_argument("--coordinator-timeout", type=float, metavar="SECONDS", default=DEFAULT_JOIN_TIMEOUT,
                            help="give up (exit status 2) when not every process has reached the coordinator "
                                 f"within SECONDS (default: {DEFAULT_JOIN_TIMEOUT:g})")  # fmt: skip
        launch.add_argument("--distributed", action="store_true",
                            help="join a multi-process run; values not given come from the cluster environment "
                                 "(SLURM, Open MPI, ...) that jax.distributed.initialize detects")  # fmt: skip
    rep = commands.add_parser("reproduce", help="reproduce a paper's numbers and figures",
                              description="reproduce a paper's numbers and figures")  # fmt: skip
    rep.add_argument("names", nargs="*", metavar="NAME", help="reproduction name(s), or 'all'")
    rep.add_argument("--list", action="store_true", help="list the reproductions with a one-line description")
    rep.add_argument("--out", metavar="DIR", default="out", help="output directory (default: out)")
    rep.set_defaults(func=_reproduce)
    for sub in commands.choices.values():
        sub.add_argument("--no-cache", action="store_true", help="no persistent compilation cache")
    return parser


def main(argv=None) -> int:
    """Run the command line ``argv`` (default: ``sys.argv[1:]``, as the ``jaxobs`` command); returns the exit
    status. Only the command (``argv`` omitted) turns the persistent compilation cache on."""
    started = time.perf_counter()
    with InterruptWatch() as watch:  # from the first line: a Ctrl-C whose KeyboardInterrupt is lost still counts
        return _run(argv, watch, started)


def _run(argv, watch: InterruptWatch, started: float) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    as_command = argv is None
    args = build_parser().parse_args(argv)
    args.started = started
    if as_command and not args.no_cache:
        _enable_compilation_cache()
    from jaxobs.tuning import CheckpointError, TuningError

    try:
        if args.command in ("sweep", "tune"):
            _join(args)
        with _log_to_stderr():
            status = args.func(args)
        watch.check()
        return status
    except KeyboardInterrupt as exc:  # jaxobs.errors.Interrupted says where it stopped
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
        if isinstance(exc, Stalled) and as_command:  # the blocked runtime would keep the interpreter from exiting
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(2)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
