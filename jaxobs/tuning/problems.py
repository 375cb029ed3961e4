"""Tuning problems with a known optimum, where the parameters are many and smooth: the time-varying gain schedule
``K_0 .. K_{T-1}`` of a linear filter, whose exact cost is the covariance recursion and whose optimum is the
finite-horizon Riccati recursion (the Kalman filter's gains, optimal among all linear gain sequences: Kalman 1960;
Anderson & Moore 1979, ch. 3)."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.kalman_steps import joseph_covariance, kalman_gain, predict_covariance, riccati_step
from jaxobs.matrix_equations import filter_dare
from jaxobs.tuning.problem import TuningProblem

__all__ = ["Schedule", "schedule_cost", "optimal_schedule", "schedule_plant", "gain_schedule_problem"]


class Schedule(NamedTuple):
    """The optimal gain schedule of :func:`optimal_schedule` (``T`` steps, ``n`` states, ``p`` outputs).

    Attributes:
      gains: (T, n, p) the Kalman gains ``K_t``.  cost: () their :func:`schedule_cost` ``J*``.
      P: (T, n, n) the a-posteriori error covariances under them.
    """

    gains: jax.Array
    cost: jax.Array
    P: jax.Array


def _check(Phi, C, Q, R, P_init, gains=None):
    n = np.shape(Phi)[-1]
    _checks.matrix("Phi", Phi, shape=(n, n), square=True)
    _checks.matrix("C", C, shape=(None, n))
    p = np.shape(C)[0]
    if np.ndim(R) != 3 or np.shape(R)[1:] != (p, p):
        raise ValueError(f"R must have shape (T, {p}, {p}) (one covariance per step), got {np.shape(R)}")
    if gains is not None and np.shape(gains) != (np.shape(R)[0], n, p):
        raise ValueError(
            f"gains must have shape ({np.shape(R)[0]}, {n}, {p}) (one per step of R), got {np.shape(gains)}"
        )
    for name, value in (("Q", Q), ("P_init", P_init)):
        if np.shape(value) != (n, n):
            raise ValueError(f"{name} must have shape ({n}, {n}), got {np.shape(value)}")


def schedule_cost(gains, Phi, C, Q, R, P_init):
    """The mean a-posteriori error variance ``J = (1/T) sum_t tr(P_t)`` of the filter ``x_t^- = Phi x_{t-1}``,
    ``x_t = x_t^- + K_t (y_t - C x_t^-)`` on ``x_t = Phi x_{t-1} + w_t``, ``y_t = C x_t + v_t`` (``E w w' = Q``,
    ``E v_t v_t' = R_t``), computed exactly by the covariance recursion ``P_t^- = Phi P_{t-1} Phi' + Q``,
    ``P_t = (I - K_t C) P_t^- (I - K_t C)' + K_t R_t K_t'`` from ``P_{-1} = P_init``.

    Args:
      gains: (T, n, p) any gains.  Phi: (n, n).  C: (p, n).  Q: (n, n).  R: (T, p, p).  P_init: (n, n).

    Pure: ``jit``, ``vmap`` and ``grad`` (in every argument). Example::

        >>> import jax.numpy as jnp
        >>> from jaxobs.tuning.problems import optimal_schedule, schedule_cost
        >>> Phi, C, Q, R = jnp.array([[0.9]]), jnp.array([[1.0]]), jnp.array([[0.1]]), jnp.full((3, 1, 1), 0.5)
        >>> best = optimal_schedule(Phi, C, Q, R, jnp.eye(1))
        >>> bool(schedule_cost(0.9 * best.gains, Phi, C, Q, R, jnp.eye(1)) > best.cost)
        True
    """
    _check(Phi, C, Q, R, P_init, gains)

    def step(P, inputs):
        K, R_t = inputs
        P = joseph_covariance(predict_covariance(P, Phi, Q), C, R_t, K)
        return P, jnp.trace(P)

    return jnp.mean(jax.lax.scan(step, P_init, (gains, R))[1])


def optimal_schedule(Phi, C, Q, R, P_init) -> Schedule:
    """The gains that minimise :func:`schedule_cost` (every term ``tr(P_t)`` at once): the Kalman gains of the
    finite-horizon Riccati recursion (:func:`jaxobs.kalman_steps.riccati_step`) with ``R_t`` per step."""
    _check(Phi, C, Q, R, P_init)

    def step(P, R_t):
        P, K, _ = riccati_step(P, Phi, C, Q, R_t)
        return P, (K, P)

    K, P = jax.lax.scan(step, P_init, R)[1]
    return Schedule(K, jnp.mean(jnp.trace(P, axis1=-2, axis2=-1)), P)


def schedule_plant(steps: int, states: int = 4, outputs: int = 2, seed: int = 0) -> dict:
    """A plant whose optimal gains change over the whole horizon: ``Phi`` lightly damped rotations (radii 0.95 to
    0.99), ``C`` (outputs, states) drawn from ``seed``, ``Q = 0.01 I``, ``P_init = I`` (an uncertain start), and
    sensor variances ``R_t = diag(0.05 exp(1.5 sin(2 pi t / 50 + 2 pi i / outputs)))`` that swing by a factor of
    20 with a period of 50 steps. A dict of ``Phi, C, Q, R, P_init`` (float64 NumPy arrays)."""
    if states % 2 or states < 2 or outputs < 1 or steps < 1:
        raise ValueError(f"states must be even and >= 2, outputs and steps >= 1; got {states}, {outputs}, {steps}")
    Phi = np.zeros((states, states))
    for i, (radius, angle) in enumerate(zip(np.linspace(0.99, 0.95, states // 2), np.linspace(0.1, 0.8, states // 2),
                                            strict=True)):  # fmt: skip
        c, s = radius * math.cos(angle), radius * math.sin(angle)
        Phi[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = [[c, -s], [s, c]]
    C = np.random.default_rng(seed).normal(size=(outputs, states)) / math.sqrt(states)
    t = np.arange(steps)[:, None]
    variances = 0.05 * np.exp(1.5 * np.sin(2 * np.pi * t / 50 + 2 * np.pi * np.arange(outputs) / outputs))
    R = variances[:, :, None] * np.eye(outputs)
    return {"Phi": Phi, "C": C, "Q": 0.01 * np.eye(states), "R": R, "P_init": np.eye(states)}


def gain_schedule_problem(
    steps: int, states: int = 4, outputs: int = 2, seed: int = 0, half_width: float | None = None
):
    """``(problem, optimum)``: the :class:`jaxobs.tuning.TuningProblem` of tuning the ``d = steps x states x
    outputs`` gains of :func:`schedule_plant`'s filter, and its :class:`Schedule` (the exact optimum, ``J*``).

    ``theta0`` is the hand-set design an engineer would use: the steady-state Kalman gain of the mean sensor
    variance, at every step. The loss of the one plant (training and held-out batch alike: the cost is an exact
    expectation, nothing is sampled) is :func:`schedule_cost`; ``describe`` gives the suboptimality ``(J - J*) /
    J*``. The search box is ``[-half_width, half_width]`` on every gain, by default 1.5 times the largest gain of
    the optimum and of ``theta0`` (rounded up to 0.1): it holds both.
    """
    plant = schedule_plant(steps, states, outputs, seed)
    optimum = optimal_schedule(*(jnp.asarray(plant[k]) for k in ("Phi", "C", "Q", "R", "P_init")))
    mean_R = jnp.asarray(plant["R"]).mean(0)
    steady = kalman_gain(filter_dare(plant["Phi"], plant["C"], plant["Q"], mean_R).X, jnp.asarray(plant["C"]), mean_R)
    theta0 = {"gains": jnp.broadcast_to(steady, (steps, states, outputs))}
    if half_width is None:
        half_width = math.ceil(15 * max(float(jnp.max(jnp.abs(optimum.gains))), float(jnp.max(jnp.abs(steady))))) / 10
    batch = {k: jnp.asarray(v)[None] for k, v in plant.items()}

    def losses(theta, plants):
        cost = jax.vmap(lambda p: schedule_cost(theta["gains"], p["Phi"], p["C"], p["Q"], p["R"], p["P_init"]))(plants)
        return cost, ~jnp.isfinite(cost)

    def describe(theta):
        cost = losses(theta, batch)[0][0]
        return {"cost": float(cost), "suboptimality": float((cost - optimum.cost) / optimum.cost)}

    box = {"gains": (jnp.full(theta0["gains"].shape, -half_width), jnp.full(theta0["gains"].shape, half_width))}
    problem = TuningProblem(theta0, losses, batch, batch, describe=describe, search_box=box)
    return problem, optimum
