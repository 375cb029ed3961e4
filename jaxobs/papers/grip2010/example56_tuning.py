"""Tuning the gains of the modular estimator of Grip 2010 Example 5.6 against its noisy objective.

Tuned: ``log K_phi`` and ``log adaptation_gain`` of the modular estimator (5.21)-(5.22), from the printed ``(K_phi,
adaptation_gain) = (10, 3)``. Each "plant" is a noise seed: the scenario of the ``grip2010-example5.6`` reproduction
(``theta`` = -2, 4, -2, 4, -2 on consecutive segments, RK4 at 1 ms,
:func:`jaxobs.papers.grip2010.adaptive.simulate_5_6`) with ``sqrt(noise_variance) N(0, 1)`` per 1 ms sample added to the
measured x. The per-seed loss is the mean over the segments of the mean ``|theta_tilde|`` over each segment's last
``window_s`` (the noisy metric of the reproduction); a run that is not finite counts as diverged. Training and held-out
seeds are disjoint (``fold_in(PRNGKey(seed), 0)`` and ``fold_in(PRNGKey(seed), 1)``, split). Two parameters, so
forward-mode gradients ("auto").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, fail
from jaxobs.papers.grip2010 import adaptive as grip
from jaxobs.papers.scenarios import TuningScenario
from jaxobs.papers.tuning_config import (
    BASELINE_DEFAULTS,
    SHIPPED_STRATEGY,
    optimizer_defaults,
    search_box,
)
from jaxobs.tuning import TuningProblem

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "PROBLEM", "build_problem"]

NAME = "grip-example56-gains"

DEFAULT_CONFIG = {
    "problem": NAME,
    "seed": 0,
    "seeds": {"train": 8, "heldout": 32},  # noise seeds (disjoint sets)
    "scenario": {
        "noise_variance": 1.0,  # of the N(0, variance) noise per 1 ms sample on x (the reproduction's)
        "segment_s": grip.SEGMENT_S,  # length of each of the five theta segments (s)
        "window_s": grip.LAST_WINDOW_S,  # the loss averages |theta_tilde| over each segment's last window_s (s)
    },
    # the hand-set start (printed: 10, 3)
    "design": {"K_phi": grip.K_PHI, "adaptation_gain": grip.ADAPTATION_GAIN_MODULAR},
    "optimizer": optimizer_defaults(**SHIPPED_STRATEGY, checkpoint_every=5),
    "baseline": {**BASELINE_DEFAULTS, "spread": 2.0},
}
"""Tune log K_phi, log adaptation_gain of Example 5.6 from the printed (10, 3), unit noise variance (8 / 32 seeds)."""

CONFIG_NOTES = {
    "seeds": "noise seeds of the Example 5.6 runs (training and held-out sets are disjoint)",
    "seeds.train": "training seeds (one rollout each per gradient evaluation)",
    "seeds.heldout": "held-out seeds, never used in training, that score the designs",
    "scenario": "the Example 5.6 run every seed makes (theta = -2, 4, -2, 4, -2 on consecutive segments)",
    "scenario.noise_variance": "variance of the N(0, variance) noise per 1 ms sample on x",
    "scenario.segment_s": "length of each of the five theta segments (s)",
    "scenario.window_s": "the loss averages |theta_tilde| over each segment's last window_s (s)",
    "design": "the modular estimator's hand-set gains, the tuner's start (printed: K_phi = 10, adaptation_gain = 3)",
    "design.K_phi": "K_phi (> 0)",
    "design.adaptation_gain": "adaptation_gain (> 0)",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    for key in ("seeds.train", "seeds.heldout"):
        check_at_least(config, source, key, 1)
    check_at_least(config, source, "scenario.noise_variance", 0)
    for key in ("scenario.segment_s", "scenario.window_s", "design.K_phi", "design.adaptation_gain"):
        check_at_least(config, source, key, 0, strict=True)
    if config["scenario"]["window_s"] > config["scenario"]["segment_s"]:
        fail(source, "scenario.window_s", f"must not exceed segment_s = {config['scenario']['segment_s']}")


def build_problem(config: dict) -> TuningProblem:
    """The tuning problem of a validated configuration (this module's ``DEFAULT_CONFIG`` merged with the user's)."""
    sc = config["scenario"]
    seg, window, std = float(sc["segment_s"]), float(sc["window_s"]), float(np.sqrt(sc["noise_variance"]))
    steps = len(grip.SEGMENT_THETAS) * round(seg / grip.DT)

    def run(theta, key):
        noise = std * jax.random.normal(key, (steps,))
        gains = jnp.exp(theta["log_K_phi"]), jnp.exp(theta["log_adaptation_gain"])
        (xm, thm, _, _), _ = grip.simulate_5_6(noise, *gains, segment_s=seg)
        return xm, thm

    def losses(theta, keys):
        def one(key):
            x, theta_hat = run(theta, key)
            return jnp.mean(grip.segment_metrics(x, theta_hat, segment_s=seg, window_s=window)[3])

        loss = jax.vmap(one)(keys)
        return loss, ~jnp.isfinite(loss)

    def seeds(which):
        base = jax.random.fold_in(jax.random.PRNGKey(config["seed"]), {"train": 0, "heldout": 1}[which])
        return jax.random.split(base, config["seeds"][which])

    _, theta_samples, _ = grip.theta_schedule(grip.DT, seg)
    stride = 10  # the figure's traces at 10 ms
    traces = jax.jit(jax.vmap(lambda theta, key: run(theta, key)[1][::stride], in_axes=(None, 0)))

    def responses(theta, keys):
        return {
            "t": grip.DT * stride * np.arange(theta_samples[::stride].size),
            "output": traces(theta, keys),
            "desired": theta_samples[::stride],
            "labels": [f"noise key {k[0]:08x}{k[1]:08x}" for k in np.asarray(keys).tolist()],
            "ylabel": "theta_hat, modular (dimensionless)",
        }

    def describe(theta):
        return {
            "K_phi": float(np.exp(theta["log_K_phi"])),
            "adaptation_gain": float(np.exp(theta["log_adaptation_gain"])),
        }

    design = config["design"]
    theta0 = {"log_K_phi": jnp.log(jnp.asarray(float(design["K_phi"]))),
              "log_adaptation_gain": jnp.log(jnp.asarray(float(design["adaptation_gain"])))}  # fmt: skip
    return TuningProblem(
        theta0=theta0,
        losses=losses,
        train=seeds("train"),
        heldout=seeds("heldout"),
        describe=describe,
        responses=responses,
        search_box=search_box(config, theta0),
        labels={"log_K_phi": "log K_phi", "log_adaptation_gain": "log adaptation gain"},
        loss_unit="dimensionless, as theta",
    )


PROBLEM = TuningScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=build_problem,
    size_keys=("scenario.segment_s", "seeds.train", "seeds.heldout"),
)
