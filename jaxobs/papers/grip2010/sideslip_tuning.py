"""Tuning the gains and switching thresholds of the NVSO of Grip 2010 ch. 2 on mismatched vehicles.

Tuned on a log scale from the defaults of :class:`jaxobs.vehicle.NVSOParams`: the gains (``log_gains``) and the
thresholds of the friction-estimation switch (``log_thresholds``, §2.5), with sigmoid gates so that the thresholds
have gradients. The plants are drawn like points of the ``sideslip`` sweep; the loss is the RMS sideslip error
(deg). The problem: docs/theory/papers.md.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, check_range, fail
from jaxobs.observers.base import EstimatorInputs
from jaxobs.observers.base import run as run_observer
from jaxobs.papers.grip2010.sideslip_sweep import drive, mismatched_vehicle
from jaxobs.papers.scenarios import TuningScenario
from jaxobs.papers.tuning_config import (
    BASELINE_DEFAULTS,
    SHIPPED_STRATEGY,
    optimizer_defaults,
    search_box,
)
from jaxobs.tuning import TuningProblem
from jaxobs.vehicle import (
    MANOEUVRES,
    NVSOParams,
    SensorParams,
    VehicleParams,
    make_nvso,
    measure,
    nvso,
    sensor_inputs,
    simulate,
)

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "GAINS", "THRESHOLDS", "PROBLEM", "build_problem"]

NAME = "sideslip-gains"
GAINS = ("K_vx", "K_vy", "K_theta", "K_theta_b")
THRESHOLDS = ("vy_dot_threshold", "yaw_rate_threshold", "oversteer_threshold")
_DEFAULTS = NVSOParams._field_defaults

DEFAULT_CONFIG = {
    "problem": NAME,
    "seed": 0,
    "plants": {
        "train": 36,
        "heldout": 36,
        "friction": [0.9, 1.2],  # scale on the drive's road friction, uniform
        "mass": [0.9, 1.2],  # true / nominal, uniform
        "cornering_stiffness": [0.85, 1.1],  # true / nominal, uniform
        "acc_bias_std": 0.1,  # m/s^2
    },
    "scenario": {
        "manoeuvres": ["sine_steer", "double_lane_change_120kmh", "mountain_road"],
        "duration": 10.0,
        "error_start": 1.0,
        "smooth": 50.0,
    },
    "design": {name: float(_DEFAULTS[name]) for name in (*GAINS, *THRESHOLDS)},
    "optimizer": optimizer_defaults(**SHIPPED_STRATEGY, checkpoint_every=5),
    "baseline": {**BASELINE_DEFAULTS, "spread": 2.0},
}
"""Tune 4 gains and 3 thresholds of the NVSO from its hand-set defaults on 36 training / 36 held-out vehicles."""

CONFIG_NOTES = {
    "plants": "the mismatched vehicles, drawn per plant (training and held-out sets from independent keys)",
    "plants.train": "training vehicles (one NVSO rollout each per gradient evaluation)",
    "plants.heldout": "held-out vehicles, never used in training, that score the designs",
    "plants.friction": "scale on the drive's road friction, uniform in [low, high] (> 0; below about 0.85 the lane "
    "change and the mountain road spin the car, true sideslip 60 to 170 deg)",
    "plants.mass": "true mass / the observer's nominal, uniform in [low, high] (> 0)",
    "plants.cornering_stiffness": "true cornering stiffness of the four tyres / nominal, uniform in [low, high] (> 0)",
    "plants.acc_bias_std": "standard deviation of the bias on both accelerometers (m/s^2, >= 0)",
    "scenario": "the drive of every vehicle and the loss",
    "scenario.manoeuvres": "test drives (Grip 2010 §2.10) taken in turn by the plants, each one of "
    + ", ".join(MANOEUVRES),
    "scenario.duration": "simulated time of every drive (s; a shorter drive continues with its last command)",
    "scenario.error_start": "the loss is the RMS sideslip error (deg) over t >= error_start (s)",
    "scenario.smooth": "sharpness of the NVSO's sigmoid switching gates (NVSOParams.smooth, > 0)",
    "design": "the NVSO's hand-set gains and thresholds (NVSOParams defaults), the tuner's start",
    **{f"design.{name}": f"{name} (> 0)" for name in (*GAINS, *THRESHOLDS)},
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    for key in ("plants.train", "plants.heldout"):
        check_at_least(config, source, key, 1)
    for key in ("plants.friction", "plants.mass", "plants.cornering_stiffness"):
        check_range(config, source, key, positive=True, allow_point=True)
    check_at_least(config, source, "plants.acc_bias_std", 0)
    unknown = [m for m in config["scenario"]["manoeuvres"] if m not in MANOEUVRES]
    if unknown:
        fail(source, "scenario.manoeuvres", f"unknown {unknown}; choose from {', '.join(MANOEUVRES)}")
    for key in ("scenario.duration", "scenario.smooth", *(f"design.{n}" for n in (*GAINS, *THRESHOLDS))):
        check_at_least(config, source, key, 0, strict=True)
    sc = config["scenario"]
    if not 0 <= sc["error_start"] < sc["duration"]:
        fail(source, "scenario.error_start", f"must be in [0, duration = {sc['duration']}), got {sc['error_start']}")


def _plants(config: dict):
    """``(train, heldout)``, each ``{"y": (B, K, 10), "beta": (B, K), "vx0": (B,), "manoeuvre": (B,)}``: the simulated
    drives' sensors and true sideslip at the sensor samples (both sets in one compiled batch)."""
    p, sc = config["plants"], config["scenario"]
    names = tuple(sc["manoeuvres"])

    def draw(which):
        count = p[which]
        key = jax.random.fold_in(jax.random.PRNGKey(config["seed"]), {"train": 0, "heldout": 1}[which])
        keys = jax.random.split(key, 5)
        uniform = lambda k, bounds: jax.random.uniform(k, (count,), minval=bounds[0], maxval=bounds[1])  # noqa: E731
        return {
            "manoeuvre": jnp.arange(count) % len(names),
            "friction": uniform(keys[0], p["friction"]),
            "mass": uniform(keys[1], p["mass"]),
            "cornering_stiffness": uniform(keys[2], p["cornering_stiffness"]),
            "acc_bias": p["acc_bias_std"] * jax.random.normal(keys[3], (count,)),
            "noise": jax.random.split(keys[4], count),
        }

    def one(d):
        truth = mismatched_vehicle(d["mass"], d["cornering_stiffness"])
        tr = simulate(drive(names, d["manoeuvre"], d["friction"]), truth, duration=float(sc["duration"]))
        meas = measure(tr, truth, SensorParams(bias_ax=d["acc_bias"], bias_ay=d["acc_bias"]), d["noise"])
        return {"y": sensor_inputs(meas).y, "beta": tr.beta[::10], "vx0": meas.vx_ref[0], "manoeuvre": d["manoeuvre"]}

    both = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), draw("train"), draw("heldout"))
    plants = jax.jit(jax.vmap(one))(both)
    n = p["train"]
    return jax.tree.map(lambda a: a[:n], plants), jax.tree.map(lambda a: a[n:], plants)


def build_problem(config: dict) -> TuningProblem:
    """The tuning problem of a validated configuration (this module's ``DEFAULT_CONFIG`` merged with the user's)."""
    sc = config["scenario"]
    base = make_nvso(VehicleParams(), smooth=float(sc["smooth"]))
    late = base.dt * np.arange(round(float(sc["duration"]) / float(base.dt)) + 1) >= float(sc["error_start"])

    def params(theta):
        values = jnp.exp(jnp.concatenate([theta["log_gains"], theta["log_thresholds"]]))
        return base._replace(**dict(zip((*GAINS, *THRESHOLDS), values, strict=True)))

    def sideslip(theta, plant):
        _, out = run_observer(nvso, params(theta)._replace(vx0=plant["vx0"]), EstimatorInputs(y=plant["y"]))
        return out.beta

    def losses(theta, plants):
        def one(plant):
            error = jnp.where(late, sideslip(theta, plant) - plant["beta"], 0.0)
            return jnp.rad2deg(jnp.sqrt(jnp.sum(error**2) / np.sum(late)))

        loss = jax.vmap(one)(plants)
        return loss, ~jnp.isfinite(loss)

    errors = jax.jit(jax.vmap(lambda theta, plant: jnp.rad2deg(sideslip(theta, plant) - plant["beta"]),
                              in_axes=(None, 0)))  # fmt: skip

    def responses(theta, plants):
        names = config["scenario"]["manoeuvres"]
        return {
            "t": np.asarray(base.dt * np.arange(late.size)),
            "output": errors(theta, plants),
            "desired": np.zeros(late.size),
            "labels": [names[int(m)] for m in np.asarray(plants["manoeuvre"])],
            "ylabel": "NVSO sideslip error (deg)",
        }

    def describe(theta):
        return {name: float(v) for name, v in params(theta)._asdict().items() if name in (*GAINS, *THRESHOLDS)}

    design = config["design"]
    theta0 = {
        "log_gains": jnp.log(jnp.asarray([float(design[n]) for n in GAINS])),
        "log_thresholds": jnp.log(jnp.asarray([float(design[n]) for n in THRESHOLDS])),
    }
    train, heldout = _plants(config)
    return TuningProblem(
        theta0=theta0,
        losses=losses,
        train=train,
        heldout=heldout,
        describe=describe,
        responses=responses,
        search_box=search_box(config, theta0),
        labels={"log_gains": [f"log {n}" for n in GAINS], "log_thresholds": [f"log {n}" for n in THRESHOLDS]},
        loss_unit="deg",
    )


PROBLEM = TuningScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=build_problem,
    size_keys=("scenario.duration", "plants.train", "plants.heldout", "scenario.manoeuvres"),
)
