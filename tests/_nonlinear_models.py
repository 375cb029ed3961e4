"""Nonlinear test models shared by tests/observers/test_ekf.py and tests/observers/test_ukf.py, with data simulated from
them.

* ``pendulum``: the sampled pendulum of Särkkä 2013 (here with a torque input), state (angle, rate),
  ``x_{k+1} = (a + w dt, w - g sin(a) dt + u dt)``, measured ``sin(a)``.
* ``bearings``: a target moving at nearly constant velocity in the plane, state (px, py, vx, vy), observed by two
  sensors measuring only the bearing ``atan2(py - sy, px - sx)`` (the bearings-only example of Särkkä 2013).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

import jaxobs as jo

DT = 0.0125
GRAVITY = 9.81
SENSORS = np.array([[-1.5, 0.5], [1.0, 1.0]])


@dataclasses.dataclass(frozen=True)
class Problem:
    f: Callable  # f(x, u, t), the library's signature
    h: Callable  # h(x)
    Q: np.ndarray
    R: np.ndarray
    x0: np.ndarray
    P0: np.ndarray
    y: np.ndarray  # (T, p) measurements
    u_prev: np.ndarray | None  # (T, m) inputs u_{k-1} (u_prev[0] unused), None without inputs
    x: np.ndarray  # (T, n) true states

    def model(self, **kwargs) -> jo.NonlinearModel:
        m = 0 if self.u_prev is None else self.u_prev.shape[1]
        return jo.nonlinear_model(self.f, self.h, self.Q, self.R, x0=self.x0, P0=self.P0, n_inputs=m, **kwargs)

    def inputs(self) -> jo.EstimatorInputs:
        return jo.EstimatorInputs(jnp.asarray(self.y), None if self.u_prev is None else jnp.asarray(self.u_prev))


def pendulum_f(x, u, t, g=GRAVITY):
    return jnp.array([x[0] + x[1] * DT, x[1] - g * jnp.sin(x[0]) * DT + u[0] * DT])


def pendulum_h(x):
    return jnp.sin(x[:1])


def bearings_f(x, u, t, dt=0.1):
    return jnp.array([x[0] + dt * x[2], x[1] + dt * x[3], x[2], x[3]])


def bearings_h(x):
    return jnp.arctan2(x[1] - SENSORS[:, 1], x[0] - SENSORS[:, 0])


def _simulate(f, h, Q, R, x_true0, u_prev, T, rng):
    n = x_true0.shape[0]
    x, xs = np.asarray(x_true0, float), []
    f, h = jax.jit(f), jax.jit(h)
    for k in range(T):
        if k:
            x = np.asarray(f(x, u_prev[k], 0.0)) + rng.multivariate_normal(np.zeros(n), Q)
        xs.append(x)
    xs = np.array(xs)
    y = np.array([np.asarray(h(x)) for x in xs]) + rng.multivariate_normal(np.zeros(R.shape[0]), R, size=T)
    return xs, y


def pendulum(T=120, seed=0) -> Problem:
    rng = np.random.default_rng(seed)
    q = 1.0
    Q = q * np.array([[DT**3 / 3, DT**2 / 2], [DT**2 / 2, DT]])
    R = np.array([[0.09]])
    u_prev = 2.0 * np.sin(np.arange(T) * DT * 3.0)[:, None]
    x, y = _simulate(pendulum_f, pendulum_h, Q, R, np.array([1.5, 0.0]), u_prev, T, rng)
    return Problem(pendulum_f, pendulum_h, Q, R, np.array([1.4, 0.1]), 0.3 * np.eye(2), y, u_prev, x)


def bearings(T=60, seed=1) -> Problem:
    rng = np.random.default_rng(seed)
    dt, q = 0.1, 0.1
    Q = q * np.kron(np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]), np.eye(2))
    R = 0.05**2 * np.eye(2)
    x, y = _simulate(bearings_f, bearings_h, Q, R, np.array([0.0, 0.0, 1.0, 0.0]), np.zeros((T, 0)), T, rng)
    return Problem(bearings_f, bearings_h, Q, R, np.array([0.1, -0.1, 0.9, 0.1]), np.diag([0.1, 0.1, 0.5, 0.5]),
                   y, None, x)  # fmt: skip


def dynamax_params(problem: Problem):
    """dynamax's ``ParamsNLGSSM`` of the same model and prior. dynamax predicts into ``z_t`` with ``inputs[t]``
    (its prediction after step ``t`` uses ``inputs[t + 1]``), so its inputs are our ``u_prev``; with inputs its
    ``h`` takes ``(x, u)``."""
    from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM

    if problem.u_prev is None:
        f, h = (lambda x: problem.f(x, jnp.zeros(0), 0.0)), problem.h
    else:
        f, h = (lambda x, u: problem.f(x, u, 0.0)), (lambda x, u: problem.h(x))
    arrays = [jnp.asarray(a) for a in (problem.x0, problem.P0, problem.Q, problem.R)]
    return ParamsNLGSSM(arrays[0], arrays[1], f, arrays[2], h, arrays[3])


def without_dynamax_regularisation(monkeypatch):
    """dynamax adds ``1e-9 I`` to every matrix it inverts (``psd_solve``'s ``diagonal_boost``), a relative change
    of about 1e-9/|S| of the gain; set it to zero in its EKF and UKF modules so the filters can be compared to
    rounding."""
    import functools

    from dynamax.nonlinear_gaussian_ssm import inference_ekf, inference_ukf
    from dynamax.utils.utils import psd_solve

    exact = functools.partial(psd_solve, diagonal_boost=0.0)
    monkeypatch.setattr(inference_ekf, "psd_solve", exact)
    monkeypatch.setattr(inference_ukf, "psd_solve", exact)


def linear_problem(seed=0, n=3, m=1, p=2, T=40, missing=True):
    """A random linear model ``x_k = A x_{k-1} + B u_{k-1} + w``, ``y = C x + v`` with data, as ``(Problem, A, B, C)``;
    a few measurement components NaN when ``missing``."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A *= 0.95 / np.max(np.abs(np.linalg.eigvals(A)))
    B, C = rng.normal(size=(n, m)), rng.normal(size=(p, n))
    G = 0.3 * rng.normal(size=(n, n))
    Q, R = G @ G.T + 0.01 * np.eye(n), np.array([[0.5, 0.1], [0.1, 0.3]])[:p, :p]
    f = lambda x, u, t: jnp.asarray(A) @ x + jnp.asarray(B) @ u
    h = lambda x: jnp.asarray(C) @ x
    u_prev = rng.normal(size=(T, m))
    x, y = _simulate(f, h, Q, R, rng.normal(size=n), u_prev, T, rng)
    if missing:
        y[3, 0] = np.nan
        y[7, :] = np.nan
        y[11, 1] = np.inf
    problem = Problem(f, h, Q, R, rng.normal(size=n), np.eye(n), y, u_prev, x)
    return problem, A, B, C


def relative_error(a, b) -> float:
    """``max |a - b| / max |b|``."""
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b))))


def van_loan(A, Qc, h):
    """``Q_d = int_0^h e^{As} Qc e^{A's} ds``, the covariance of the sampled process noise (Van Loan 1978)."""
    n = A.shape[0]
    E = jax.scipy.linalg.expm(jnp.block([[-A, Qc], [jnp.zeros((n, n)), A.T]]) * h)
    return E[n:, n:].T @ E[:n, n:]
