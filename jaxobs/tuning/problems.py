"""Tuning problems with a known optimum or bound, where the parameters are many and smooth: the time-varying gain
schedule ``K_0 .. K_{T-1}`` of a linear filter, whose exact cost is the covariance recursion and whose optimum is the
finite-horizon Riccati recursion (the Kalman filter's gains, optimal among all linear gain sequences: Kalman 1960;
Anderson & Moore 1979, ch. 3), and a gain scheduled over an operating range (a car's speed), bounded below by the
Riccati gains of each speed profile."""

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

__all__ = ["Schedule", "schedule_cost", "optimal_schedule", "schedule_plant", "gain_schedule_problem",
           "lateral_model", "speed_schedule_problem"]  # fmt: skip


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
    if np.ndim(Phi) not in (2, 3) or np.shape(Phi)[-2] != n:
        raise ValueError(f"Phi must have shape (n, n) or (T, n, n), got {np.shape(Phi)}")
    if np.ndim(C) not in (2, 3) or np.shape(C)[-1] != n:
        raise ValueError(f"C must have shape (p, {n}) or (T, p, {n}), got {np.shape(C)}")
    p = np.shape(C)[-2]
    if np.ndim(R) != 3 or np.shape(R)[1:] != (p, p):
        raise ValueError(f"R must have shape (T, {p}, {p}) (one covariance per step), got {np.shape(R)}")
    for name, value in (("Phi", Phi), ("C", C)):
        if np.ndim(value) == 3 and np.shape(value)[0] != np.shape(R)[0]:
            raise ValueError(f"{name} must have one matrix per step of R ({np.shape(R)[0]}), got {np.shape(value)[0]}")
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
      gains: (T, n, p) any gains.  Phi: (n, n), or (T, n, n) for a time-varying plant.  C: (p, n) or (T, p, n).
      Q: (n, n).  R: (T, p, p).  P_init: (n, n).

    Pure: ``jit``, ``vmap`` and ``grad`` (in every argument). Example::

        >>> import jax.numpy as jnp
        >>> from jaxobs.tuning.problems import optimal_schedule, schedule_cost
        >>> Phi, C, Q, R = jnp.array([[0.9]]), jnp.array([[1.0]]), jnp.array([[0.1]]), jnp.full((3, 1, 1), 0.5)
        >>> best = optimal_schedule(Phi, C, Q, R, jnp.eye(1))
        >>> bool(schedule_cost(0.9 * best.gains, Phi, C, Q, R, jnp.eye(1)) > best.cost)
        True
    """
    gains, Phi, C, Q, R, P_init = _checks.float_arrays(gains=gains, Phi=Phi, C=C, Q=Q, R=R, P_init=P_init)
    _check(Phi, C, Q, R, P_init, gains)

    def step(P, inputs):
        K, R_t, Phi_t, C_t = inputs
        P = joseph_covariance(predict_covariance(P, Phi_t, Q), C_t, R_t, K)
        return P, jnp.trace(P)

    return jnp.mean(jax.lax.scan(step, P_init, (gains, R, _per_step(Phi, R), _per_step(C, R)))[1])


def _invalid(cost, bound):
    """Where ``cost`` is no value of the covariance recursion: not finite, or below ``bound`` (the Riccati
    optimum, which no gain schedule beats: a lower number is the roundoff of a covariance that blew up, e.g. a
    negative one after an unstable schedule's growth to 1e80)."""
    return ~jnp.isfinite(cost) | (cost < bound * (1 - 1e-6))


def _per_step(matrix, R):
    """``matrix`` (a, b) or (T, a, b) as one matrix per step of ``R``."""
    return jnp.broadcast_to(matrix, (R.shape[0], *np.shape(matrix)[-2:]))


def optimal_schedule(Phi, C, Q, R, P_init) -> Schedule:
    """The gains that minimise :func:`schedule_cost` (every term ``tr(P_t)`` at once): the Kalman gains of the
    finite-horizon Riccati recursion (:func:`jaxobs.kalman_steps.riccati_step`) with ``R_t`` per step.
    Shapes as :func:`schedule_cost`'s."""
    Phi, C, Q, R, P_init = _checks.float_arrays(Phi=Phi, C=C, Q=Q, R=R, P_init=P_init)
    _check(Phi, C, Q, R, P_init)

    def step(P, inputs):
        R_t, Phi_t, C_t = inputs
        P, K, _ = riccati_step(P, Phi_t, C_t, Q, R_t)
        return P, (K, P)

    K, P = jax.lax.scan(step, P_init, (R, _per_step(Phi, R), _per_step(C, R)))[1]
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
    expectation, nothing is sampled) is :func:`schedule_cost`, diverged where it is not finite or below ``J*`` (the
    roundoff of an unstable schedule's covariance); ``describe`` gives the suboptimality ``(J - J*) /
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
        return cost, _invalid(cost, optimum.cost)

    def describe(theta):
        cost = losses(theta, batch)[0][0]
        return {"cost": float(cost), "suboptimality": float((cost - optimum.cost) / optimum.cost)}

    box = {"gains": (jnp.full(theta0["gains"].shape, -half_width), jnp.full(theta0["gains"].shape, half_width))}
    problem = TuningProblem(theta0, losses, batch, batch, describe=describe, search_box=box)
    return problem, optimum


@_checks.design_time()
def lateral_model(speed, h: float = 0.05, vehicle=None):
    """``(Phi, C)`` of a car's lateral dynamics at ``speed`` (m/s; any shape ``S``, giving ``S + (4, 4)`` and
    ``S + (2, 4)``) sampled at ``h`` (s): the linear single track (Rajamani 2012, §2.3) with the cornering
    stiffnesses of :class:`jaxobs.vehicle.VehicleParams` (per unit load times the static axle load), states ``(v_y,
    r, b_r, b_a)``: lateral velocity, yaw rate, and the biases of the yaw-rate gyro and of the lateral accelerometer
    (random walks); outputs the gyro ``r + b_r`` and the accelerometer ``a_y + b_a = dv_y/dt + v r + b_a``.
    ``Phi = expm(A h)`` (NumPy: a design-time step)."""
    from scipy.linalg import expm

    from jaxobs.vehicle import VehicleParams

    p = VehicleParams() if vehicle is None else vehicle
    v = np.asarray(speed, float)
    g, wheelbase = 9.81, p.lf + p.lr
    cf = p.tyre_front.cornering_stiffness * p.mass * g * p.lr / wheelbase
    cr = p.tyre_rear.cornering_stiffness * p.mass * g * p.lf / wheelbase
    a11, a12 = -(cf + cr) / (p.mass * v), -(p.lf * cf - p.lr * cr) / (p.mass * v) - v
    a21, a22 = -(p.lf * cf - p.lr * cr) / (p.yaw_inertia * v), -(p.lf**2 * cf + p.lr**2 * cr) / (p.yaw_inertia * v)
    A = np.zeros((*v.shape, 4, 4))
    A[..., 0, 0], A[..., 0, 1], A[..., 1, 0], A[..., 1, 1] = a11, a12, a21, a22
    C = np.zeros((*v.shape, 2, 4))
    C[..., 0, 1] = C[..., 0, 2] = C[..., 1, 3] = 1.0
    C[..., 1, 0], C[..., 1, 1] = a11, a12 + v
    return expm(A * h), C


def _speed_profiles(count: int, steps: int, h: float, rng) -> np.ndarray:
    """``count`` speed profiles (count, steps) between 5 and 40 m/s: a random start, then accelerations of -3 to 3
    m/s^2 held for 1 to 4 s each."""
    profiles = np.empty((count, steps))
    for i in range(count):
        v, t = rng.uniform(5, 40), 0
        while t < steps:
            hold = int(rng.uniform(1, 4) / h)
            accel = rng.uniform(-3, 3)
            profiles[i, t : t + hold] = np.clip(v + accel * h * np.arange(1, min(hold, steps - t) + 1), 5, 40)
            v, t = profiles[i, min(t + hold, steps) - 1], t + hold
    return profiles


def _hat_weights(speeds, knots: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation weights (..., len(knots)) of ``speeds`` over the ``knots`` (one knot: 1)."""
    if len(knots) == 1:
        return np.ones((*np.shape(speeds), 1))
    index = np.clip(np.searchsorted(knots, speeds) - 1, 0, len(knots) - 2)
    share = np.clip((speeds - knots[index]) / (knots[index + 1] - knots[index]), 0.0, 1.0)
    weights = np.zeros((*np.shape(speeds), len(knots)))
    np.put_along_axis(weights, index[..., None], (1 - share)[..., None], -1)
    np.put_along_axis(weights, index[..., None] + 1, share[..., None], -1)
    return weights


def _speed_plants(profiles: np.ndarray, knots: np.ndarray, h: float) -> dict:
    """A batch of plants from speed profiles: per step ``Phi``, ``C``, the knots' interpolation weights."""
    Phi, C = lateral_model(profiles, h)
    noise = np.diag([0.5**2 * h, 0.05**2 * h, 1e-6 * h, 1e-4 * h])  # side forces, yaw moments, bias drifts
    R = np.broadcast_to(np.diag([0.005**2, 0.1**2]), (*profiles.shape, 2, 2))  # gyro rad/s, accelerometer m/s^2
    count = len(profiles)
    return {"Phi": Phi, "C": C, "R": R, "Q": np.broadcast_to(noise, (count, 4, 4)),
            "P_init": np.broadcast_to(np.diag([1.0, 0.1, 0.01**2, 0.2**2]), (count, 4, 4)),
            "weights": _hat_weights(profiles, knots)}  # fmt: skip


def speed_schedule_problem(knots: int = 32, train: int = 8, heldout: int = 32, steps: int = 400, seed: int = 0):
    """``(problem, bounds)``: tuning the gains of :func:`lateral_model`'s filter as a schedule over speed,
    ``K(v)`` interpolated linearly between ``knots`` speeds from 5 to 40 m/s (``4 x 2`` gains each), on random speed
    profiles of ``steps`` 0.05 s steps (training and held-out plants drawn from ``seed``).

    Each plant's loss is :func:`schedule_cost` of the scheduled gains over its own optimum, the Riccati gains of
    that profile (:func:`optimal_schedule`: the best any causal linear filter does), so the objective is at least 1
    and ``describe`` gives its excess. ``theta0`` is the steady-state Kalman gain at 22.5 m/s at every knot (a fixed
    gain); the search box is +-1.5 times the largest Riccati gain of the training plants. ``bounds`` holds the
    Riccati costs ``J*`` of the training and held-out plants.
    """
    rng = np.random.default_rng(seed)
    speeds = np.linspace(5.0, 40.0, knots)
    batches = {name: _speed_plants(_speed_profiles(count, steps, 0.05, rng), speeds, 0.05)
               for name, count in (("train", train), ("heldout", heldout))}  # fmt: skip
    model = ("Phi", "C", "Q", "R", "P_init")
    optimum = {name: jax.vmap(lambda p: optimal_schedule(*(p[k] for k in model)))({k: jnp.asarray(b[k]) for k in model})
               for name, b in batches.items()}  # fmt: skip
    for name, batch in batches.items():
        batch["optimum"] = np.asarray(optimum[name].cost)
    Phi, C = lateral_model(22.5)
    mean_R = batches["train"]["R"][0, 0]
    steady = kalman_gain(filter_dare(Phi, C, batches["train"]["Q"][0], mean_R).X, jnp.asarray(C), jnp.asarray(mean_R))
    theta0 = {"gains": jnp.broadcast_to(steady, (knots, 4, 2))}
    half = math.ceil(15 * float(jnp.max(jnp.abs(optimum["train"].gains)))) / 10

    def losses(theta, plants):
        def one(p):
            gains = jnp.einsum("tk,knp->tnp", p["weights"], theta["gains"])
            return schedule_cost(gains, p["Phi"], p["C"], p["Q"], p["R"], p["P_init"]) / p["optimum"]

        cost = jax.vmap(one)(plants)
        return cost, _invalid(cost, 1.0)

    batches = {name: {k: jnp.asarray(v) for k, v in b.items()} for name, b in batches.items()}

    def describe(theta):
        return {"excess": float(jnp.mean(losses(theta, batches["heldout"])[0]) - 1)}

    box = {"gains": (jnp.full((knots, 4, 2), -half), jnp.full((knots, 4, 2), half))}
    problem = TuningProblem(theta0, losses, batches["train"], batches["heldout"], describe=describe, search_box=box)
    return problem, {name: b["optimum"] for name, b in batches.items()}
