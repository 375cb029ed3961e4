"""Tuning the per-DOF AOBs of the 6-DOF peg-on-hole alignment (the MRAC chapter §7) against MJX rollouts.

Tuned, from the hand-set design of eq. 62-68, the process noise of the four DOF whose AOB acts (x, y, rx, rz):
their active-state variances ``log_q_active`` (``design.parameterisation = "diagonal"``), or per DOF a full
covariance of the force, its rate and the active state, ``q_cholesky`` (4, 3, 3) (``"cholesky"``, 24 parameters;
the dead-time slots keep eq. 62's entries), on plants with scaled stiffnesses, tilt and contact lever
(:func:`jaxobs.papers.cortesao.mrac.peg_on_hole_scenario`). The loss is each DOF's squared error against its
desired closed-loop response (eq. 43), in units of its sensor noise variance. The problem: docs/theory/papers.md.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import check_at_least, check_choice, check_range, fail
from jaxobs.closed_loop import ideal_response
from jaxobs.observers.active import active_observer_controller
from jaxobs.papers.scenarios import TuningScenario
from jaxobs.papers.tuning_config import (
    BASELINE_DEFAULTS,
    SHIPPED_STRATEGY,
    check_plant_memory,
    optimizer_defaults,
    search_box,
)
from jaxobs.plants import force_plant
from jaxobs.tuning import TuningProblem, cholesky_covariance, cholesky_labels, cholesky_parameters

__all__ = ["NAME", "DEFAULT_CONFIG", "CONFIG_NOTES", "PROBLEM", "build_problem"]

NAME = "peg-on-hole"
PARAMETERISATIONS = ("diagonal", "cholesky")

DEFAULT_CONFIG = {
    "problem": NAME,
    "seed": 0,
    "plants": {
        "stiffness_scale": [0.5, 1.5],
        "tilt": [0.02, 0.06],
        "contact_radius": [10.0, 13.0],
        "train": 8,
        "heldout": 32,
    },
    "scenario": {
        "duration": 3.0,
        "alignment_start": 1.0,
        "alignment_end": 2.5,
        "insertion_velocity_bias": 0.05,
        "force_limit": 1000.0,
    },
    "design": {"parameterisation": "diagonal"},
    "optimizer": optimizer_defaults(**SHIPPED_STRATEGY, checkpoint_every=5),
    "baseline": {**BASELINE_DEFAULTS, "spread": 6.0},
}
"""Tune the x, y, rx, rz active-state variances over +-50 % stiffness mismatch (8 training, 32 held-out plants)."""

CONFIG_NOTES = {
    "plants": "the mismatched 6-DOF MJX plants (training and held-out sets from independent keys)",
    "plants.stiffness_scale": "true / nominal stiffness, each of the six DOF drawn independently, uniform",
    "plants.tilt": "initial peg tilt (rad), uniform",
    "plants.contact_radius": "contact lever (mm; the peg radius is 11.5 mm), uniform",
    "plants.train": "training plants (one rollout each per gradient evaluation)",
    "plants.heldout": "held-out plants, never used in training, that score the designs",
    "scenario": "the alignment task every plant runs (the MRAC chapter §7)",
    "scenario.duration": "rollout length (s)",
    "scenario.alignment_start": "start of the alignment rotation w_y (s)",
    "scenario.alignment_end": "end of the alignment rotation (s), at most the duration",
    "scenario.insertion_velocity_bias": "feedforward bias on v_z (mm/s)",
    "scenario.force_limit": "a rollout whose force (N) or moment (N m) exceeds it counts as diverged",
    "design": "what is tuned of the per-DOF AOB-1 of x, y, rx, rz (the z CKF keeps its sensor-based gain)",
    "design.parameterisation": "'diagonal' (the active-state variances, 4) or 'cholesky' (per DOF the full "
    "covariance of force, force rate and active state, 4 x 6)",
}


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    check_choice(config, source, "design.parameterisation", PARAMETERISATIONS)
    check_range(config, source, "plants.stiffness_scale", positive=True, allow_point=True)
    check_range(config, source, "plants.tilt", allow_point=True, minimum=-0.3, maximum=0.3)
    check_range(config, source, "plants.contact_radius", positive=True, allow_point=True)
    for key in ("plants.train", "plants.heldout"):
        check_at_least(config, source, key, 1)
    for key in ("duration", "force_limit"):
        check_at_least(config, source, f"scenario.{key}", 0, strict=True)
    check_at_least(config, source, "scenario.alignment_start", 0.0)
    check_at_least(config, source, "scenario.alignment_end", config["scenario"]["alignment_start"], strict=True)
    if config["scenario"]["alignment_end"] > config["scenario"]["duration"]:
        fail(source, "scenario.alignment_end", "must not exceed scenario.duration")
    from jaxobs.mjx.compliant_6dof import CONTROL_PERIOD

    check_plant_memory(config, source, int(round(config["scenario"]["duration"] / CONTROL_PERIOD)), 6)


def _desired(nominal, L, reference, h: float, d: int) -> jax.Array:
    """(T, 6) the ideal closed-loop wrench of each axis's force plant under the hand-set feedback ``L`` (6, ...)."""

    def one(ks, L, r):
        plant = force_plant(ks, nominal.time_constant, h, d * h)
        return ideal_response(plant, L[:, : plant.n_states], r)[:, 0]

    return jax.vmap(one, in_axes=(0, 0, 1), out_axes=1)(nominal.per_dof("stiffness", float), L, reference)


def _sample_plants(config: dict, which: str, noise_variance, steps: int) -> dict:
    """The ``which`` ("train" or "heldout") plants: stiffness scales (n, 6), tilts and contact radii (n,), sensor
    noise (n, steps, 6)."""
    pl = config["plants"]
    count = pl[which]
    key = jax.random.fold_in(jax.random.PRNGKey(config["seed"]), {"train": 0, "heldout": 1}[which])
    k_s, k_t, k_r, k_n = jax.random.split(key, 4)
    lo, hi = pl["stiffness_scale"]
    return {
        "stiffness_scale": jax.random.uniform(k_s, (count, 6), minval=lo, maxval=hi),
        "tilt": jax.random.uniform(k_t, (count,), minval=pl["tilt"][0], maxval=pl["tilt"][1]),
        "contact_radius": jax.random.uniform(
            k_r, (count,), minval=pl["contact_radius"][0], maxval=pl["contact_radius"][1]
        ),  # fmt: skip
        "noise": jnp.sqrt(noise_variance) * jax.random.normal(k_n, (count, steps, 6)),
    }


def _describe(theta: dict, *, dofs: list, noise_variance) -> dict:
    """The tuned covariances by axis (``noise_variance``: the tuned axes' R)."""
    if "q_cholesky" in theta:
        Q = np.asarray(cholesky_covariance(theta["q_cholesky"]))
        return {"Q_force_rate_active": dict(zip(dofs, Q.tolist(), strict=True))}
    q = np.exp(np.asarray(theta["log_q_active"]))
    return {"q_active": dict(zip(dofs, q.tolist(), strict=True)),
            "q_active_over_R": dict(zip(dofs, (q / noise_variance).tolist(), strict=True))}  # fmt: skip


def _start(cholesky: bool, blocks, q_active, dofs: list) -> tuple[dict, dict]:
    """``(theta0, labels)`` of the hand-set design: the Cholesky factors of the (F, dF/dt, p) blocks ``blocks``
    (k, 3, 3), or the log active-state variances ``q_active`` (k,), of the tuned axes ``dofs``."""
    if cholesky:
        return ({"q_cholesky": cholesky_parameters(blocks)},
                {"q_cholesky": [cholesky_labels(f"Q_{dof}", ("F", "dF/dt", "p")) for dof in dofs]})  # fmt: skip
    return {"log_q_active": jnp.log(q_active)}, {"log_q_active": [f"log Q_{dof}[p]" for dof in dofs]}


def build_problem(config: dict) -> TuningProblem:
    """The tuning problem of a validated configuration (this module's ``DEFAULT_CONFIG`` merged with the user's)."""
    from jaxobs.mjx import compliant_6dof as c6
    from jaxobs.papers.cortesao import mrac

    sc = config["scenario"]
    nominal = c6.Compliant6Params()
    scenario = mrac.peg_on_hole_scenario(
        nominal, duration=sc["duration"], alignment=(sc["alignment_start"], sc["alignment_end"]),
        insertion_velocity_bias=sc["insertion_velocity_bias"],
    )  # fmt: skip
    tuned = np.array([c6.X, c6.Y, c6.RX, c6.RZ])
    hand_set = scenario.controllers
    noise_variance = jnp.asarray(mrac.SENSOR_NOISE_VARIANCE)
    q_hand = mrac.Q_ACTIVE_FX * noise_variance / noise_variance[c6.X]  # eq. 62, 65
    h, d = c6.CONTROL_PERIOD, 5
    stiffness = nominal.per_dof("stiffness", float)

    desired = _desired(nominal, hand_set.L, scenario.reference, h, d)
    model = c6.load_model()[1]
    steps = scenario.t.shape[0]

    hand_set_q = hand_set.estimator.Q  # (6, 8, 8), eq. 62
    block = np.array([0, 1, hand_set_q.shape[-1] - 1])  # F, dF/dt and the active state p
    cholesky = config["design"]["parameterisation"] == "cholesky"

    def controllers(theta):
        if not cholesky:
            q = q_hand.at[tuned].set(jnp.exp(theta["log_q_active"]))
            return mrac.design(nominal, q_active=q, feedback_off=(c6.RY,))
        Q = hand_set_q.at[np.ix_(tuned, block, block)].set(cholesky_covariance(theta["q_cholesky"]))
        return mrac.design(nominal, process_noise=Q, feedback_off=(c6.RY,))

    def rollout(theta, plants):
        ctrl = controllers(theta)

        def one(scale, tilt, radius, noise):
            true = dataclasses.replace(
                scenario.plant, stiffness=scenario.plant.per_dof("stiffness", float) * scale, tilt=tilt,
                contact_radius=radius,
            )  # fmt: skip
            return c6.closed_loop_rollout(
                c6.with_params(model, true), active_observer_controller, ctrl, scenario.reference,
                feedforward=scenario.feedforward, noise=noise,
            ).wrench_true  # fmt: skip

        return jax.vmap(one)(plants["stiffness_scale"], plants["tilt"], plants["contact_radius"], plants["noise"])

    def losses(theta, plants):
        wrench = rollout(theta, plants)
        error = (wrench - desired)[..., tuned] ** 2 / noise_variance[tuned]
        loss = jnp.mean(error, axis=(-2, -1))
        peak = jnp.max(jnp.abs(wrench), axis=(-2, -1))
        return loss, ~jnp.isfinite(loss) | ~(peak < sc["force_limit"])

    rollout_jit = jax.jit(rollout)

    def responses(theta, plants):
        return {
            "t": scenario.t,
            "output": rollout_jit(theta, plants)[..., c6.X],
            "desired": desired[:, c6.X],
            "labels": [f"Kx = {float(stiffness[c6.X] * s[c6.X]):.2f} N/mm" for s in plants["stiffness_scale"]],
            "ylabel": "f_x (N)",
        }

    dofs = [c6.DOF_NAMES[i] for i in tuned]
    theta0, labels = _start(cholesky, hand_set_q[np.ix_(tuned, block, block)], q_hand[tuned], dofs)
    return TuningProblem(
        theta0=theta0,
        losses=losses,
        train=_sample_plants(config, "train", noise_variance, steps),
        heldout=_sample_plants(config, "heldout", noise_variance, steps),
        describe=functools.partial(_describe, dofs=dofs, noise_variance=np.asarray(noise_variance)[tuned]),
        responses=responses,
        search_box=search_box(config, theta0, cholesky=("q_cholesky",)),
        labels=labels,
        loss_unit="sensor noise variances",
    )


PROBLEM = TuningScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=build_problem,
    size_keys=("scenario.duration", "plants.train", "plants.heldout"),
)
