"""A small ``jaxobs.tuning.tune`` run of a shipped tuning problem, runnable as a subprocess of a multi-process test.

``python tune_case.py CONFIG.toml CHECKPOINT [--evaluate] [--coordinator HOST:PORT --num-processes N --process-id I]``
builds the problem of the ``jaxobs tune`` config file CONFIG.toml (over its defaults), tunes it with the checkpoint
CHECKPOINT (resumed when it exists) and prints one JSON line: each evaluation's objective, diverged count and
``theta``, the best objective and ``theta``, the wall time, the device and process counts, and how many
checkpoint files this process wrote; ``--evaluate`` adds the held-out losses of the tuned ``theta``
(:func:`jaxobs.tuning.evaluate`). ``TUNE_SLEEP`` (seconds) makes every checkpoint write sleep first, so that a
test can kill the run mid-way.
"""

import argparse
import json
import os
import time

import jax
import numpy as np

import jaxobs.tuning
from jaxobs._config import load_toml
from jaxobs.papers import tuning as papers
from jaxobs.papers._tuning_config import config_tag, settings

WRITES = []


def _counted_save(path, trees, meta, *, _save=jaxobs.tuning._save_checkpoint):
    time.sleep(float(os.environ.get("TUNE_SLEEP", "0")))
    WRITES.append(str(path))
    _save(path, trees, meta)


jaxobs.tuning._save_checkpoint = _counted_save


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("config")
    parser.add_argument("checkpoint")
    parser.add_argument("--evaluate", action="store_true")
    parser.add_argument("--coordinator")
    parser.add_argument("--num-processes", type=int)
    parser.add_argument("--process-id", type=int)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    if args.coordinator:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    config = papers.validate_config(load_toml(args.config), args.config)
    problem = papers.PROBLEMS[config["problem"]].build_problem(config)
    tuned = settings(config)
    result = jaxobs.tuning.tune(problem, tuned, checkpoint=args.checkpoint, progress=False, tag=config_tag(config))
    out = {
        "history": [{k: h[k] for k in ("objective", "diverged", "accepted", "theta")} for h in result.history],
        "objective": result.objective,
        "theta": {k: np.asarray(v).tolist() for k, v in result.theta.items()},
        "seconds": result.seconds,
        "devices": len(jax.devices()),
        "processes": jax.process_count(),
        "checkpoints_written": len(WRITES),
    }
    if args.evaluate:
        out["heldout"] = jaxobs.tuning.evaluate(problem, result.theta, tuned)["losses"].tolist()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
