"""A small ``jaxobs.tuning.tune`` run, runnable as a subprocess of a multi-process test.

``python tune_case.py CHECKPOINT [--config CONFIG.toml] [--evaluate] [--lapack] [--starts K --screening N]
[--coordinator HOST:PORT --num-processes N --process-id I]`` builds the problem of the ``jaxobs tune`` config file
CONFIG.toml (over its defaults), or without ``--config`` a cheap analytic problem (:func:`analytic_problem`;
``--lapack``: with a LAPACK kernel), tunes it with the checkpoint CHECKPOINT (resumed when it exists) and prints one
JSON line: each evaluation's objective, diverged count and ``theta``, the best objective and ``theta``, each start's
result (``--starts``, ``--screening``: a population of the analytic problem), the wall time, the device and process
counts, and how many checkpoint files this process wrote; ``--evaluate`` adds the held-out losses of the tuned
``theta`` (:func:`jaxobs.tuning.evaluate`). ``TUNE_SLEEP`` (seconds) makes every checkpoint write sleep first, so
that a test can kill the run mid-way.
"""

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxobs.tuning
from jaxobs._config import load_toml
from jaxobs.papers.registry import tuning_problems
from jaxobs.papers.tuning_config import settings
from jaxobs.tuning import checkpoints

WRITES = []


def _counted_save(path, trees, meta, *, _save=checkpoints.save):
    time.sleep(float(os.environ.get("TUNE_SLEEP", "0")))
    WRITES.append(str(path))
    _save(path, trees, meta)


checkpoints.save = _counted_save


def analytic_problem(lapack: bool = False) -> jaxobs.tuning.TuningProblem:
    """A first-order loop ``x <- a x + g (target - x)`` over 40 steps per plant (pole ``a``, target), the loss its
    mean squared tracking error plus ``1e-3 g^2``, tuned in ``log g``; 3 training and 3 held-out plants. ``lapack``
    adds zero times a ``jnp.linalg.solve`` per plant (jaxlib's batched LAPACK LU once vmapped): the same numbers,
    computed on one CPU device per process."""

    def losses(theta, plants):
        gain = jnp.exp(theta["log_gain"])

        def one(a, target):
            def step(x, _):
                x = a * x + gain * (target - x)
                return x, (x - target) ** 2

            loss = jnp.mean(jax.lax.scan(step, 0.0 * target, None, length=40)[1]) + 1e-3 * gain**2
            if lapack:
                loss = loss + 0.0 * jnp.linalg.solve(jnp.array([[2.0, a], [a, 2.0]]), jnp.array([target, 1.0]))[0]
            return loss

        loss = jax.vmap(one)(plants["a"], plants["target"])
        return loss, loss > 1e6

    def plants(a, target):
        return {"a": jnp.asarray(a), "target": jnp.asarray(target)}

    train, heldout = plants([0.5, 0.8, 0.95], [1.0, -2.0, 0.5]), plants([0.6, 0.9, 0.7], [2.0, 1.0, -1.0])
    return jaxobs.tuning.TuningProblem({"log_gain": jnp.asarray(-2.0)}, losses, train, heldout)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("checkpoint")
    parser.add_argument("--config")
    parser.add_argument("--evaluate", action="store_true")
    parser.add_argument("--lapack", action="store_true")
    parser.add_argument("--starts", type=int, default=1)
    parser.add_argument("--screening", type=int, default=0)
    parser.add_argument("--coordinator")
    parser.add_argument("--num-processes", type=int)
    parser.add_argument("--process-id", type=int)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    if args.coordinator:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    if args.config:
        given = load_toml(args.config)
        registry = tuning_problems()
        name = given.get("problem", next(iter(registry)))  # the CLI's default problem
        scenario = registry[name]
        config = scenario.validate({**given, "problem": name}, args.config)
        problem, tuned, tag = scenario.build(config), settings(config), "tiny"
    else:
        problem, tag = analytic_problem(args.lapack), "analytic"
        tuned = jaxobs.tuning.TuneSettings(
            optax.adam(0.3), steps=5, checkpoint_every=1, starts=args.starts, screening=args.screening
        )
    result = jaxobs.tuning.tune(problem, tuned, checkpoint=args.checkpoint, progress=False, tag=tag)
    out = {
        "history": [{k: h[k] for k in ("objective", "diverged", "accepted", "theta")} for h in result.history],
        "objective": result.objective,
        "theta": {k: np.asarray(v).tolist() for k, v in result.theta.items()},
        "seconds": result.seconds,
        "devices": len(jax.devices()),
        "processes": jax.process_count(),
        "checkpoints_written": len(WRITES),
        "starts": [
            {
                "objective": s.objective,
                "stopped": s.stopped,
                "evaluations": s.evaluations,
                "theta": {k: np.asarray(v).tolist() for k, v in s.theta.items()},
            }
            for s in result.starts
        ],  # fmt: skip
    }
    if args.evaluate:
        out["heldout"] = jaxobs.tuning.evaluate(problem, result.theta, tuned)["losses"].tolist()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
