"""Tuning the AOB of the 1-DOF force plant against MJX rollouts: the default ``jaxobs tune`` problem.

The AOB-N of Cortesão 2006 and the MRAC chapter, designed on the nominal analytic plant from the hand-set
``Q``, ``R`` of eq. 62-64, runs against mismatched MJX force plants (:mod:`jaxobs.mjx.force_1dof`) under the
papers' disturbances; the loss is the mean squared force error against the desired closed loop (eq. 43).
Parameterisations ``"diagonal"``, ``"cholesky"`` and ``"structured"`` (eq. 53-55). The problem:
docs/theory/papers.md.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, check_choice, check_range, fail
from jaxobs.closed_loop import ideal_response
from jaxobs.lti import StateSpace
from jaxobs.observers import active
from jaxobs.observers.feedback import FeedbackParams
from jaxobs.papers.cortesao.force_control import (
    EXAMPLE1,
    example1_disturbance,
    nominal_design,
    reference_gain,
    with_feedback,
)
from jaxobs.papers.scenarios import TuningScenario
from jaxobs.papers.tuning_config import (
    BASELINE_DEFAULTS,
    SHIPPED_STRATEGY,
    check_plant_memory,
    optimizer_defaults,
    search_box,
)
from jaxobs.plants import force_plant
from jaxobs.stability import closed_loop_matrix, spectral_radius
from jaxobs.tuning import (
    TuningProblem,
    cholesky_covariance,
    cholesky_labels,
    cholesky_parameters,
    log_labels,
    unit_interval,
    unit_interval_parameters,
)

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "PROBLEM", "build_problem"]

NAME = "force-1dof"
HAND_SET = {"q_plant": 1e-12, "q_active": 1e-5, "R": 2.1e-2}  # The MRAC chapter eq. 62 and 64
PARAMETERISATIONS = ("diagonal", "cholesky", "structured")
MAX_ORDER = 3

DEFAULT_CONFIG = {
    "problem": NAME,
    "seed": 0,
    "plants": {
        "stiffness_scale": [0.5, 1.5],
        "time_constant_scale": [1.0, 1.0],
        "damping": [0.0, 0.0],
        "train": 16,
        "heldout": 64,
        "mjcf": "",
    },
    "scenario": {
        "duration": 2.0,
        "force_step": 10.0,
        "sensor_noise": EXAMPLE1.R,
        "disturbance_window": 7.0,
        "disturbance_scale": 1.0,
        "surface_speed": 2.0,
        "surface_start": 1.5,
        "force_limit": 1000.0,
        "gradient_horizon": 0,
    },
    "design": {
        "order": 1,
        "parameterisation": "diagonal",
        "q_plant": HAND_SET["q_plant"],
        "q_active": HAND_SET["q_active"],
        "R": HAND_SET["R"],
        "spectral_radius_limit": 0.995,
    },
    "optimizer": optimizer_defaults(**SHIPPED_STRATEGY, checkpoint_every=5),
    "baseline": {**BASELINE_DEFAULTS, "spread": 8.0},
}
"""Tune the AOB-1 of the 1-DOF MJX force plant across +-50 % stiffness mismatch (16 training plants,
64 held-out plants, 2 s rollouts)."""

CONFIG_NOTES = {
    "plants": "the mismatched MJX plants, drawn per plant (training and held-out sets from independent keys)",
    "plants.stiffness_scale": "true Ks / nominal Ks (3 N/mm), uniform",
    "plants.time_constant_scale": "true Tp / nominal Tp (32 ms), uniform",
    "plants.damping": "sensor + environment damping (N s/mm), uniform",
    "plants.train": "training plants (one rollout each per gradient evaluation)",
    "plants.heldout": "held-out plants, never used in training, that score the designs",
    "plants.mjcf": "a user's MJCF of the plant (same joint, body and actuator names); empty: the packaged model",
    "scenario": "the rollout every plant runs",
    "scenario.duration": "rollout length (s)",
    "scenario.force_step": "force set-point (N) from t = 0",
    "scenario.sensor_noise": "the true sensor's noise variance (N^2), drawn per plant with a fixed seed",
    "scenario.disturbance_window": "the plant sees D(t + window) of eq. 81-82 (s; 7: its 8 s step at t = 1 s)",
    "scenario.disturbance_scale": "factor on the eq. 81-82 input disturbance",
    "scenario.surface_speed": "receding contact surface speed (mm/s; the stochastic AOB paper §4)",
    "scenario.surface_start": "time the surface starts moving (s)",
    "scenario.force_limit": "a rollout whose force exceeds it (N) counts as diverged",
    "scenario.gradient_horizon": "control steps of truncated backpropagation; 0: the whole rollout",
    "design": "the AOB and its hand-set starting point (the MRAC chapter eq. 62-64)",
    "design.order": "AOB-N order (1 to 3)",
    "design.parameterisation": "'diagonal' (log Q diagonal), 'cholesky' (full Q) or 'structured' (eq. 53-55)",
    "design.q_plant": "hand-set plant-state variance Q_xr",
    "design.q_active": "hand-set active-state variance",
    "design.R": "hand-set measurement variance (N^2)",
    "design.spectral_radius_limit": "threshold of the spectral-radius penalty (enabled by optimizer.penalty_weight)",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    for key in ("plants.stiffness_scale", "plants.time_constant_scale"):
        check_range(config, source, key, positive=True, allow_point=True)
    check_range(config, source, "plants.damping", minimum=0.0, allow_point=True)
    for key, low in (("plants.train", 1), ("plants.heldout", 1), ("scenario.gradient_horizon", 0)):
        check_at_least(config, source, key, low)
    for key in ("duration", "force_step", "sensor_noise", "force_limit"):
        check_at_least(config, source, f"scenario.{key}", 0, strict=True)
    if config["scenario"]["duration"] < EXAMPLE1.h:
        fail(source, "scenario.duration", f"must be at least one sample ({EXAMPLE1.h} s)")
    order = config["design"]["order"]
    if not 1 <= order <= MAX_ORDER:
        fail(source, "design.order", f"must be an AOB order in 1..{MAX_ORDER}, got {order!r}")
    check_choice(config, source, "design.parameterisation", PARAMETERISATIONS)
    for key in ("q_plant", "q_active", "R", "spectral_radius_limit"):
        check_at_least(config, source, f"design.{key}", 0, strict=True)
    check_plant_memory(config, source, int(round(config["scenario"]["duration"] / EXAMPLE1.h)), 1)


# --------------------------------------------------------------------------------------------
# Controller from theta


def _hand_set_q(config: dict, n_plant: int, order: int):
    d = config["design"]
    return active.aob_noise_covariance(n_plant, order, 1, d["q_plant"], d["q_active"])


def initial_theta(config: dict, plant: StateSpace) -> dict:
    """The unconstrained ``theta`` of the hand-set design (``design.q_plant``, ``q_active``, ``R``)."""
    d, order = config["design"], config["design"]["order"]
    log_r = jnp.log(jnp.asarray(d["R"], float))
    kind = d["parameterisation"]
    if kind == "diagonal":
        return {"log_q": jnp.log(jnp.diagonal(_hand_set_q(config, plant.n_states, order))), "log_r": log_r}
    if kind == "cholesky":
        return {"q_cholesky": cholesky_parameters(_hand_set_q(config, plant.n_states, order)), "log_r": log_r}
    c = EXAMPLE1.c
    sigma2 = d["q_active"] / float(active.evolution_variance(1.0, order, c))  # so that Q is eq. 62's
    return {
        "log_q_plant": jnp.log(jnp.asarray(d["q_plant"], float)),
        "log_sigma2": jnp.log(jnp.asarray(sigma2, float)),
        "logit_c": unit_interval_parameters(c),
        "log_r": log_r,
    }


def state_names(n_plant: int, order: int) -> list[str]:
    """The AOB's states: the force, its rate, the commands in flight (oldest first) and the active states."""
    delays = [f"u(k-{n_plant - 2 - i})" for i in range(n_plant - 2)]
    return ["F", "dF/dt", *delays, *(["p"] if order == 1 else [f"p{i + 1}" for i in range(order)])]


def parameter_labels(theta: dict, n_plant: int, order: int) -> dict:
    """What each entry of ``theta`` is, under its parameterisation (:attr:`jaxobs.tuning.TuningProblem.labels`)."""
    names = state_names(n_plant, order)
    labels = {"log_r": "log R[force]"}
    if "log_q" in theta:
        return {**labels, "log_q": log_labels("Q", names)}
    if "q_cholesky" in theta:
        return {**labels, "q_cholesky": cholesky_labels("Q", names)}
    return {**labels, "log_q_plant": "log q_plant", "log_sigma2": "log sigma² (active)", "logit_c": "logit c"}


def covariances(theta: dict, n_plant: int, order: int):
    """``(Q, R)`` of ``theta`` under its parameterisation (told apart by its keys)."""
    R = jnp.exp(theta["log_r"]).reshape(1, 1)
    if "log_q" in theta:
        return jnp.diag(jnp.exp(theta["log_q"])), R
    if "q_cholesky" in theta:
        return cholesky_covariance(theta["q_cholesky"]), R
    q_active = active.evolution_variance(jnp.exp(theta["log_sigma2"]), order, unit_interval(theta["logit_c"]))
    return active.aob_noise_covariance(n_plant, order, 1, jnp.exp(theta["log_q_plant"]), q_active), R


def controller(theta: dict, base: active.ActiveObserverParams, L_r, n_plant: int, order: int) -> FeedbackParams:
    """The steady-state AOB of ``theta`` with the state feedback ``L_r`` (``base`` supplies the model)."""
    Q, R = covariances(theta, n_plant, order)
    return with_feedback(active.with_steady_state_gains(dataclasses.replace(base, Q=Q, R=R, P0=Q)), L_r)


# --------------------------------------------------------------------------------------------
# Plants, scenario, losses


def sample_plants(config: dict, which: str) -> dict:
    """``which`` = "train" or "heldout": stiffness, time constant, damping and sensor noise per plant
    (independent keys for the two sets)."""
    p, sc = config["plants"], config["scenario"]
    count = p[which]
    steps = int(round(sc["duration"] / EXAMPLE1.h))
    key = jax.random.fold_in(jax.random.PRNGKey(config["seed"]), {"train": 0, "heldout": 1}[which])
    k_ks, k_tp, k_d, k_noise = jax.random.split(key, 4)

    def uniform(k, bounds, scale=1.0):
        return scale * jax.random.uniform(k, (count,), minval=bounds[0], maxval=bounds[1])

    return {
        "ks": uniform(k_ks, p["stiffness_scale"], EXAMPLE1.Ks),
        "tp": uniform(k_tp, p["time_constant_scale"], EXAMPLE1.Tp),
        "damping": uniform(k_d, p["damping"]),
        "noise": jnp.sqrt(sc["sensor_noise"]) * jax.random.normal(k_noise, (count, steps)),
    }


def scenario(config: dict) -> dict:
    """The inputs shared by every plant: time, reference, desired force, input disturbance, surface speed."""
    sc, h = config["scenario"], EXAMPLE1.h
    steps = int(round(sc["duration"] / h))
    t = jnp.arange(steps) * h
    plant, L = nominal_design(EXAMPLE1)
    reference = jnp.full((steps,), reference_gain(L) * sc["force_step"])
    return {
        "t": t,
        "reference": reference,
        "desired": ideal_response(plant, L, reference)[:, 0],
        "disturbance": sc["disturbance_scale"] * example1_disturbance(t + sc["disturbance_window"]),
        "surface_velocity": jnp.where(t >= sc["surface_start"], sc["surface_speed"], 0.0),
    }


def spectral_radius_penalty(theta, *, plants: dict, limit: float, base, L, n_plant: int, order: int):
    """Mean squared excess over ``limit`` of the closed-loop spectral radius of the design ``theta`` on the analytic
    true plants (Cortesão 2006, eq. 59) of ``plants`` (its ``ks`` and ``tp``)."""
    ctrl = controller(theta, base, L, n_plant, order)
    h, dead_time = EXAMPLE1.h, EXAMPLE1.dead_time_samples * EXAMPLE1.h

    def radius(ks, tp):
        plant = force_plant(ks, tp, h, dead_time)
        return spectral_radius(closed_loop_matrix(plant, active.active_observer_controller, ctrl))

    rho = jax.vmap(radius)(plants["ks"], plants["tp"])
    return jnp.mean(jnp.maximum(rho - limit, 0.0) ** 2)


def describe(theta, *, base, L, n_plant: int, order: int) -> dict:
    """The design ``theta`` in the paper's terms: Q's diagonal, the active-state variance over R, the Kalman gain
    and the AOB's strategy."""
    Q, R = covariances(theta, n_plant, order)
    aob = controller(theta, base, L, n_plant, order).estimator
    return {
        "Q_diagonal": np.asarray(jnp.diagonal(Q)).tolist(),
        "q_active": float(Q[-1, -1]),
        "R": float(R[0, 0]),
        "q_active_over_R": float(Q[-1, -1] / R[0, 0]),
        "kalman_gain": np.asarray(aob.gain).ravel().tolist(),
        "strategy": active.classify_strategy(np.asarray(aob.gain), np.asarray(aob.C)),
    }


def build_problem(config: dict) -> TuningProblem:
    """The :class:`jaxobs.tuning.TuningProblem` of ``config`` (see the module docstring)."""
    from jaxobs.mjx import ForcePlantParams, closed_loop_rollout, load_model, with_params

    order, sc = config["design"]["order"], config["scenario"]
    plant, L = nominal_design(EXAMPLE1)
    base = active.make_aob(plant, order, config["design"]["R"])
    model = load_model(xml=config["plants"]["mjcf"] or None)[1]
    inputs = scenario(config)
    horizon = sc["gradient_horizon"] or None
    n_plant = plant.n_states

    def rollout(theta, plants):
        ctrl = controller(theta, base, L, n_plant, order)

        def one(ks, tp, damping, noise):
            true = with_params(model, ForcePlantParams(stiffness=ks, time_constant=tp, damping=damping))
            return closed_loop_rollout(
                true, active.active_observer_controller, ctrl, inputs["reference"], noise=noise,
                disturbance=inputs["disturbance"],
                surface_velocity=inputs["surface_velocity"], gradient_horizon=horizon,
            ).force_true  # fmt: skip

        return jax.vmap(one)(plants["ks"], plants["tp"], plants["damping"], plants["noise"])

    def losses(theta, plants):
        force = rollout(theta, plants)
        loss = jnp.mean((force - inputs["desired"]) ** 2, axis=-1)
        peak = jnp.max(jnp.abs(force), axis=-1)
        diverged = ~jnp.isfinite(loss) | ~(peak < sc["force_limit"])
        return loss, diverged

    train = sample_plants(config, "train")
    design = {"base": base, "L": L, "n_plant": n_plant, "order": order}
    limit = config["design"]["spectral_radius_limit"]
    rollout_jit = jax.jit(rollout)

    def responses(theta, plants):
        return {
            "t": inputs["t"],
            "output": rollout_jit(theta, plants),
            "desired": inputs["desired"],
            "setpoint": sc["force_step"],
            "labels": [f"Ks = {float(k):.2f} N/mm" for k in plants["ks"]],
            "ylabel": "force (N)",
        }

    theta0 = initial_theta(config, plant)
    return TuningProblem(
        theta0=theta0,
        losses=losses,
        train=train,
        heldout=sample_plants(config, "heldout"),
        penalty=functools.partial(spectral_radius_penalty, plants=train, limit=limit, **design),
        describe=functools.partial(describe, **design),
        responses=responses,
        search_box=search_box(config, theta0, cholesky=("q_cholesky",)),
        labels=parameter_labels(theta0, plant.n_states, order),
        loss_unit="N²",
    )


PROBLEM = TuningScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=build_problem,
    size_keys=("scenario.duration", "plants.train", "plants.heldout"),
    path_keys=("plants.mjcf",),
)
