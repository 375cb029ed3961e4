"""Learning a model from recorded data: maximum likelihood by gradient (optax) for any estimator with a
log-likelihood, expectation-maximisation for the linear-Gaussian model, and ``Q``, ``R`` from a steady-state
filter's innovations by autocovariance least squares.

Data are ``B`` sequences of ``T`` samples: ``EstimatorInputs`` with ``y`` (B, T, p) (NaN components missing) and
``u_prev`` (B, T, m) or ``None``. :func:`fit` minimises :func:`negative_log_likelihood` over unconstrained
``theta`` (:func:`covariance_model` for full ``Q``, ``R``); :func:`em` is EM for the linear-Gaussian model (Shumway
& Stoffer 1982; Ghahramani & Hinton 1996), exact with missing data; :func:`als` is autocovariance least squares
(Odelson, Rajamani & Rawlings 2006); :func:`sample` draws records. The algorithms: docs/learning.md.
"""

from __future__ import annotations

import dataclasses
import math
from functools import lru_cache, partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxobs import _checks
from jaxobs._linalg import symmetrize
from jaxobs.consistency import autocovariance
from jaxobs.nonlinear import NonlinearModel
from jaxobs.observers.base import Estimator, EstimatorInputs
from jaxobs.observers.kalman import KalmanParams, kalman_filter
from jaxobs.smoothing import log_likelihood, smooth
from jaxobs.tuning import cholesky_covariance, cholesky_parameters

__all__ = [
    "sample",
    "negative_log_likelihood",
    "covariance_model",
    "FitSettings",
    "FitResult",
    "fit",
    "EMResult",
    "em",
    "EM_FIELDS",
    "ALSResult",
    "als",
]

EM_FIELDS = ("Phi", "Gamma", "C", "Q", "R", "x0", "P0")
"""The fields of :class:`~jaxobs.observers.kalman.KalmanParams` that :func:`em` can update."""


# --------------------------------------------------------------------------------------------
# Data


def _psd_sqrt(M):
    """A factor ``L`` with ``L L' = M`` for a symmetric positive semidefinite ``M`` (eigen-decomposition: also for a
    singular ``M``)."""
    values, vectors = jnp.linalg.eigh(symmetrize(M))
    return vectors * jnp.sqrt(jnp.maximum(values, 0.0))


def sample(params: KalmanParams, key, num_steps: int, u_prev=None):
    """Draw one record of the linear-Gaussian model of ``params`` (prior convention of
    :mod:`jaxobs.observers.kalman`): ``x_0 ~ N(x0, P0)``, ``x_k = Phi x_{k-1} + Gamma u_{k-1} + w_k``,
    ``y_k = C x_k + v_k``, ``w ~ N(0, Q)``, ``v ~ N(0, R)``.

    Args:
      params: :class:`~jaxobs.observers.kalman.KalmanParams` (``Q``, ``P0`` may be singular).
      key: a PRNG key (``vmap`` over keys for a batch of records).
      num_steps: ``T``, the number of samples.
      u_prev: (T, m) inputs ``u_{k-1}`` as the filter reads them (row 0 unused), or ``None``.

    Returns:
      ``(x, y)`` of shapes (T, n) and (T, p).
    """
    if not isinstance(params, KalmanParams):
        raise ValueError(f"params must be KalmanParams (make_kalman), got {type(params).__name__}")
    T = _checks.count("num_steps", num_steps, minimum=1)
    m, dtype = params.Gamma.shape[-1], params.Phi.dtype
    if u_prev is not None:
        u_prev = jnp.asarray(u_prev, dtype)
        _checks.shape("u_prev", u_prev, (T, m), "(num_steps, inputs)")
    return _sample(params, key, u_prev, num_steps=T)


@partial(jax.jit, static_argnames=("num_steps",))
def _sample(params: KalmanParams, key, u_prev, *, num_steps: int):
    n, p, dtype = params.Phi.shape[-1], params.C.shape[-2], params.Phi.dtype
    k0, kw, kv = jax.random.split(key, 3)
    x0 = params.x0 + _psd_sqrt(params.P0) @ jax.random.normal(k0, (n,), dtype)
    w = jax.random.normal(kw, (num_steps, n), dtype) @ _psd_sqrt(params.Q).T
    v = jax.random.normal(kv, (num_steps, p), dtype) @ _psd_sqrt(params.R).T
    drive = w[1:] if u_prev is None else w[1:] + u_prev[1:] @ params.Gamma.T

    def body(x, d):
        x = params.Phi @ x + d
        return x, x

    _, rest = jax.lax.scan(body, x0, drive)
    x = jnp.concatenate([x0[None], rest])
    return x, x @ params.C.T + v


def _sizes(params) -> tuple[int, int]:
    """``(p, m)``: the outputs and inputs of the model of a linear estimator's params (``C``, ``Gamma``) or of a
    nonlinear filter's (its :class:`~jaxobs.nonlinear.NonlinearModel` ``model``)."""
    model = getattr(params, "model", None)
    if isinstance(model, NonlinearModel):
        return model.R.shape[-1], model.n_inputs
    return params.C.shape[-2], params.Gamma.shape[-1]


def _batched(params, inputs: EstimatorInputs, what: str = "inputs"):
    """``(y, u_prev)`` as (B, T, p) and (B, T, m) or None, shapes checked (static) against ``params``."""
    if not isinstance(inputs, EstimatorInputs):
        raise ValueError(f"{what} must be EstimatorInputs(y, u_prev), got {type(inputs).__name__}")
    if inputs.model is not None:
        raise ValueError(f"{what}.model: fitting takes a constant model; a time-varying one is not supported here")
    p, m = _sizes(params)
    y = jnp.asarray(inputs.y)
    if y.ndim == 2:
        y = y[None]
    _checks.shape(f"{what}.y", y, (None, None, p), "(sequences, time, outputs) or (time, outputs) measurements")
    if y.shape[0] == 0 or y.shape[1] == 0:
        raise ValueError(f"{what}.y has shape {y.shape}: give at least one sequence of at least one sample")
    u = inputs.u_prev
    if u is not None:
        u = jnp.asarray(u)
        u = u[None] if u.ndim == 2 else u
        _checks.shape(f"{what}.u_prev", u, (y.shape[0], y.shape[1], m), "(sequences, time, inputs) like y")
        _checks.finite(f"{what}.u_prev", u)
    if _checks.is_concrete(y) and not np.any(np.isfinite(np.asarray(y))):
        raise ValueError(f"{what}.y has no finite (observed) component: there is nothing to learn from")
    return y, u


# --------------------------------------------------------------------------------------------
# Maximum likelihood by gradient


def _nll(estimator: Estimator, params, y, u):
    per_sequence = jax.vmap(lambda yb, ub: log_likelihood(estimator, params, EstimatorInputs(yb, ub)),
                            (0, None if u is None else 0))(y, u)  # fmt: skip
    return -jnp.sum(per_sequence) / jnp.maximum(jnp.sum(jnp.isfinite(y)), 1)


def negative_log_likelihood(estimator: Estimator, params, inputs: EstimatorInputs):
    """``-log p(Y) / N``: the negative log-likelihood of ``B`` records under the estimator's model per observed
    measurement component (``N`` finite entries of ``y``), the loss :func:`fit` minimises. Works under ``jit``,
    ``vmap`` and ``grad``.

    Args:
      estimator: an estimator with a ``log_likelihood`` output (:data:`~jaxobs.observers.kalman.kalman_filter`,
        :data:`~jaxobs.observers.kalman.square_root_kalman_filter`, :data:`~jaxobs.observers.active.active_observer`,
        :data:`~jaxobs.observers.ekf.extended_kalman_filter`, :data:`~jaxobs.observers.ukf.unscented_kalman_filter`).
      params: its params.
      inputs: ``EstimatorInputs`` with ``y`` (B, T, p) or (T, p) and ``u_prev`` (B, T, m), (T, m) or ``None``.
    """
    return _nll(estimator, params, *_batched(params, inputs))


def _replace(obj, path: str, value):
    """``obj`` with the field at the dotted ``path`` of nested dataclasses (``"Q"``, ``"model.Q"``) set to
    ``value``."""
    head, _, rest = path.partition(".")
    return dataclasses.replace(obj, **{head: _replace(getattr(obj, head), rest, value) if rest else value})


def _lookup(params, path: str):
    """The field at the dotted ``path`` of ``params``, or ``None`` when it is not a field of nested dataclasses."""
    value = params
    for part in path.split("."):
        if not (dataclasses.is_dataclass(value) and part in {f.name for f in dataclasses.fields(value)}):
            return None
        value = getattr(value, part)
    return value


def _replace_covariances(params, theta: dict):
    for name, raw in theta.items():
        params = _replace(params, name, cholesky_covariance(raw))
    return params


def covariance_model(params, names=("Q", "R")):
    """``(build_params, theta0)`` for :func:`fit` to learn the covariances ``names`` of ``params`` (full positive
    definite matrices through :func:`jaxobs.tuning.cholesky_covariance`), starting from their current values; the
    other fields stay fixed (``P0`` among them unless named).

    Args:
      params: the estimator's params (a dataclass with the fields ``names``, e.g.
        :class:`~jaxobs.observers.kalman.KalmanParams`).
      names: the covariance fields to learn; a dotted name reaches into a field, e.g. ``("model.Q", "model.R")``
        for the :class:`~jaxobs.nonlinear.NonlinearModel` of :class:`~jaxobs.observers.ekf.EKFParams`.

    Example:
      >>> import jaxobs as jo
      >>> model = jo.nonlinear_model(lambda x, u, t: jnp.sin(x), lambda x: x, [[0.1]], [[0.2]], x0=[0.0])
      >>> build, theta0 = jo.covariance_model(jo.make_ekf(model), ("model.Q", "model.R"))
      >>> sorted(theta0), bool(jnp.allclose(build(theta0).model.R, 0.2))
      (['model.Q', 'model.R'], True)
    """
    values = {name: _lookup(params, name) for name in names}
    unknown = [name for name, value in values.items() if value is None]
    if unknown or not names:
        raise ValueError(f"names must be fields of {type(params).__name__} (dotted for nested ones, e.g. "
                         f"'model.Q'), got {list(names)}")  # fmt: skip
    theta0 = {}
    for name, value in values.items():
        try:
            theta0[name] = cholesky_parameters(value)
        except ValueError as exc:
            raise ValueError(f"params.{name}: {exc}") from exc
    return jax.tree_util.Partial(_replace_covariances, params), theta0


DEFAULT_FIT_OPTIMIZER = optax.lbfgs()
"""The default optimiser of :func:`fit`: optax's L-BFGS with its zoom line search."""


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """Settings of :func:`fit`.

    Attributes:
      optimizer: an ``optax.GradientTransformation``: L-BFGS with a zoom line search by default
        (:data:`DEFAULT_FIT_OPTIMIZER`), or any other (e.g. ``optax.adam(0.05)``); each update gets the loss as
        ``value_fn`` for a line search.
      steps: optimizer steps at most.
      tolerance: early stopping: the loss (nats per observed component) counts as improved when it falls more
        than ``tolerance`` below the best so far.
      patience: stop after this many steps without improvement.
    """

    optimizer: optax.GradientTransformation = DEFAULT_FIT_OPTIMIZER
    steps: int = 200
    tolerance: float = 1e-10
    patience: int = 10

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid setting."""
        _checks.optimizer("settings.optimizer", self.optimizer, "optax.lbfgs() or optax.adam(0.05)")
        for name in ("steps", "patience"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"settings.{name} must be an integer >= 1, got {value!r}")
        _checks.positive_scalar("settings.tolerance", self.tolerance, allow_zero=True)


class FitResult(NamedTuple):
    """Result of :func:`fit`.

    Attributes:
      theta: the best parameters found (lowest loss)
      params: build_params(theta)
      loss: (steps taken,) the loss at each iterate, the loss curve (nats per observed component)
      grad_norm: (steps taken,) the gradient's global norm at each iterate
      stopped: "converged" (no improvement for settings.patience steps), "steps", or "non-finite"
      best_loss: the loss of theta
    """

    theta: Any
    params: Any
    loss: np.ndarray
    grad_norm: np.ndarray
    stopped: str
    best_loss: float


@lru_cache(maxsize=64)
def _stepper(estimator: Estimator, settings: FitSettings):
    """One jitted optimizer step ``(build, theta, opt_state, y, u) -> (theta, opt_state, loss, grad_norm)`` (the loss
    and gradient are those of the given ``theta``) and the optimizer; cached so that fits with the same estimator,
    settings, ``build_params`` function and shapes compile once."""
    optimizer = optax.with_extra_args_support(settings.optimizer)

    def step(build, theta, state, y, u):
        loss = lambda th: _nll(estimator, build(th), y, u)  # noqa: E731
        if optax.tree.get(state, "value") is not None:  # a line search's state holds the value and gradient
            value, grad = optax.value_and_grad_from_state(loss)(theta, state=state)
        else:
            value, grad = jax.value_and_grad(loss)(theta)
        updates, state = optimizer.update(grad, state, theta, value=value, grad=grad, value_fn=loss)
        return optax.apply_updates(theta, updates), state, value, optax.tree.norm(grad)

    return jax.jit(step), optimizer


def fit(estimator: Estimator, build_params, theta0, inputs: EstimatorInputs, settings: FitSettings = FitSettings(),
        *, progress: bool = True) -> FitResult:  # fmt: skip
    """Maximum-likelihood fit of ``build_params(theta)`` to ``B`` recorded sequences.

    Minimises :func:`negative_log_likelihood` over the unconstrained ``theta`` with optax, one jitted step per
    iteration (compiled once per estimator, settings, ``build_params`` function and shapes), with a progress bar
    and early stopping (:class:`FitSettings`). Eager: the loop runs in Python.

    Args:
      estimator: an estimator with a ``log_likelihood`` output, e.g. :data:`~jaxobs.observers.kalman.kalman_filter`.
      build_params: ``theta -> params``, pure and differentiable, e.g. from :func:`covariance_model` (a function or a
        ``jax.tree_util.Partial``, whose bound arrays are arguments, not constants, of the compiled step).
      theta0: the initial unconstrained parameters (a pytree of arrays).
      inputs: ``EstimatorInputs`` with ``y`` (B, T, p) or (T, p), NaN where missing, and ``u_prev`` or ``None``.
      settings: :class:`FitSettings`.
      progress: show a progress bar with the loss.

    Returns:
      :class:`FitResult`: the best ``theta``, its params, the loss curve.

    Example:
      >>> import jax, jaxobs as jo
      >>> true = jo.make_kalman([[0.9]], [[1.0]], [[0.5]], [[0.2]])
      >>> _, y = jax.vmap(lambda k: jo.sample(true, k, 200))(jax.random.split(jax.random.PRNGKey(0), 4))
      >>> build, theta0 = jo.covariance_model(jo.make_kalman([[0.9]], [[1.0]], [[1.0]], [[1.0]], P0=[[0.5]]))
      >>> result = jo.fit(jo.kalman_filter, build, theta0, jo.EstimatorInputs(y=y), progress=False)
      >>> result.stopped, bool(result.loss[-1] < result.loss[0])
      ('converged', True)
      >>> bool(abs(result.params.Q[0, 0] - 0.5) < 0.2)
      True
    """
    from tqdm.auto import tqdm

    if not isinstance(settings, FitSettings):
        raise ValueError(f"settings must be FitSettings, got {type(settings).__name__}")
    settings.validate()
    if not isinstance(estimator, Estimator):
        raise ValueError(f"estimator must be an Estimator, got {type(estimator).__name__}")
    build = _checks.function("build_params", build_params)
    theta = jax.tree.map(lambda a: jnp.asarray(a).astype(jnp.result_type(a, float)), theta0)
    if not jax.tree.leaves(theta):
        raise ValueError("theta0 has no parameters to fit")
    for leaf in jax.tree.leaves(theta):
        _checks.finite("theta0", leaf)
    y, u = _batched(build(theta), inputs)
    step, optimizer = _stepper(estimator, settings)
    # strongly typed, as the step returns it (optax's L-BFGS starts with weakly typed counters): one compilation
    state = jax.tree.map(lambda a: jnp.asarray(a, dtype=a.dtype), optimizer.init(theta))
    best, best_loss, since_best, stopped = theta, math.inf, 0, "steps"
    losses, norms = [], []
    bar = tqdm(total=settings.steps, desc="fit", disable=not progress, unit="step")
    try:
        for i in range(settings.steps):
            new_theta, state, value, norm = step(build, theta, state, y, u)
            value, norm = float(value), float(norm)
            if not (math.isfinite(value) and math.isfinite(norm)):
                if i == 0:
                    raise ValueError(f"theta0: the loss or its gradient is not finite there ({value}, {norm})")
                stopped = "non-finite"
                break
            losses.append(value)
            norms.append(norm)
            if value < best_loss - settings.tolerance:
                since_best = 0
            else:
                since_best += 1
            if value < best_loss:
                best, best_loss = theta, value
            bar.update(1)
            bar.set_postfix(loss=f"{value:.6g}")
            if since_best >= settings.patience:
                stopped = "converged"
                break
            theta = new_theta
    finally:
        bar.close()
    return FitResult(best, build(best), np.asarray(losses), np.asarray(norms), stopped, best_loss)


# --------------------------------------------------------------------------------------------
# Expectation-maximisation, linear-Gaussian


class EMResult(NamedTuple):
    """Result of :func:`em`.

    Attributes:
      params: after the last update
      log_likelihood: (iterations,) log p(Y) of the params before each update (NaN after the last)
      iterations: () updates made
      converged: () the relative log-likelihood change fell below the tolerance
    """

    params: KalmanParams
    log_likelihood: jax.Array
    iterations: jax.Array
    converged: jax.Array


class _Statistics(NamedTuple):
    """Sums over the sequences of the expected complete-data statistics (``z = [x; u]`` the regressor of the
    transition, ``y`` with its missing components latent)."""

    S11: jax.Array  # sum_k E[x_k x_k'], k >= 1
    S10: jax.Array  # sum_k E[x_k z_{k-1}']
    S00: jax.Array  # sum_k E[z_{k-1} z_{k-1}']
    Sxx: jax.Array  # sum_k E[x_k x_k'], all k
    Syx: jax.Array  # sum_k E[y_k x_k']
    Syy: jax.Array  # sum_k E[y_k y_k']
    m0: jax.Array  # (B, n) E[x_0]
    V0: jax.Array  # (B, n, n) Cov(x_0)
    log_likelihood: jax.Array  # () log p(Y)


def _sequence_statistics(params: KalmanParams, y, u):
    """The E-step of one sequence: the smoother's moments turned into the complete-data statistics."""
    filtered, smoothed = smooth(kalman_filter, params, EstimatorInputs(y, u))
    m, V, E = smoothed.x, smoothed.P, smoothed.gain
    T, n = m.shape
    dtype = m.dtype
    u = jnp.zeros((T, params.Gamma.shape[-1]), dtype) if u is None else u.astype(dtype)
    Exx = V + m[:, :, None] * m[:, None, :]
    # lag one: Cov(x_k, x_{k-1} | Y) = P_{k|T-1} E_{k-1}' (de Jong 1989)
    cross = V[1:] @ jnp.swapaxes(E[:-1], -1, -2) + m[1:, :, None] * m[:-1, None, :]
    z_mean = jnp.concatenate([m[:-1], u[1:]], axis=1)
    S10 = jnp.concatenate([jnp.sum(cross, 0), m[1:].T @ u[1:]], axis=1)
    S00 = z_mean.T @ z_mean + jnp.pad(jnp.sum(V[:-1], 0), ((0, u.shape[1]), (0, u.shape[1])))
    # measurements with missing components latent: E[y | x, Y] = H x + G y_o, Cov[y | x, Y] = R - G R_o.
    mask = jnp.isfinite(y).astype(dtype)
    y_o = jnp.where(mask > 0, y, 0.0).astype(dtype)

    def measurement(mask_k, y_k, m_k, Exx_k):
        R_o = params.R * jnp.outer(mask_k, mask_k) + jnp.diag(1.0 - mask_k)
        G = jnp.linalg.solve(R_o, (params.R * mask_k[None, :]).T).T  # R_.o R_oo^{-1}, zero columns where missing
        H = params.C - G @ (params.C * mask_k[:, None])
        Gy = G @ y_k
        Eyx = H @ Exx_k + jnp.outer(Gy, m_k)
        Hm = H @ m_k
        Eyy = H @ Exx_k @ H.T + jnp.outer(Hm, Gy) + jnp.outer(Gy, Hm) + jnp.outer(Gy, Gy)
        return Eyx, Eyy + params.R - G @ (params.R * mask_k[:, None])

    Eyx, Eyy = jax.vmap(measurement)(mask, y_o, m, Exx)
    return (jnp.sum(Exx[1:], 0), S10, S00, jnp.sum(Exx, 0), jnp.sum(Eyx, 0), jnp.sum(Eyy, 0), m[0], V[0],
            jnp.sum(filtered.log_likelihood))  # fmt: skip


def _statistics(params: KalmanParams, y, u) -> _Statistics:
    parts = jax.vmap(_sequence_statistics, (None, 0, None if u is None else 0))(params, y, u)
    *sums, m0, V0, ll = parts
    return _Statistics(*(jnp.sum(s, 0) for s in sums), m0, V0, jnp.sum(ll))


def _maximise(params: KalmanParams, s: _Statistics, counts: tuple[int, int], update: frozenset) -> KalmanParams:
    """The M-step: each field in ``update`` set to its maximiser given the others' new values (``[Phi, Gamma]`` by
    least squares on the free columns, then ``Q``; ``C``, then ``R``; ``x0``, then ``P0``)."""
    n = params.Phi.shape[-1]
    transitions, measurements = counts
    A = jnp.concatenate([params.Phi, params.Gamma], axis=1)
    free = np.array([("Phi" in update)] * n + [("Gamma" in update)] * params.Gamma.shape[-1])
    if free.any():
        F, X = np.flatnonzero(free), np.flatnonzero(~free)
        rhs = s.S10[:, F] - A[:, X] @ s.S00[np.ix_(X, F)]
        A = A.at[:, F].set(jnp.linalg.solve(s.S00[np.ix_(F, F)], rhs.T).T)
    new = {}
    if "Phi" in update:
        new["Phi"] = A[:, :n]
    if "Gamma" in update:
        new["Gamma"] = A[:, n:]
    if "Q" in update:
        AS = A @ s.S10.T
        new["Q"] = symmetrize(s.S11 - AS - AS.T + A @ s.S00 @ A.T) / transitions
    C = jnp.linalg.solve(s.Sxx, s.Syx.T).T if "C" in update else params.C
    if "C" in update:
        new["C"] = C
    if "R" in update:
        CS = C @ s.Syx.T
        new["R"] = symmetrize(s.Syy - CS - CS.T + C @ s.Sxx @ C.T) / measurements
    x0 = jnp.mean(s.m0, 0) if "x0" in update else params.x0
    if "x0" in update:
        new["x0"] = x0
    if "P0" in update:
        d = s.m0 - x0
        new["P0"] = symmetrize(jnp.mean(s.V0, 0) + d.T @ d / s.m0.shape[0])
    return dataclasses.replace(params, **new)


def em(params: KalmanParams, inputs: EstimatorInputs, *, iterations: int = 100, update=("Q", "R"),
       tolerance: float = 1e-9) -> EMResult:  # fmt: skip
    """Expectation-maximisation of the linear-Gaussian model's likelihood over ``B`` recorded sequences.

    Each iteration smooths every sequence with the current model (E-step, with the lag-one cross-covariances) and
    sets the fields in ``update`` to the maximisers of the expected complete-data log-likelihood (M-step), e.g.
    ``Q = sum_k E[(x_k - Phi x_{k-1} - Gamma u_{k-1})(...)'] / (B (T - 1))`` and
    ``R = sum_k E[(y_k - C x_k)(...)'] / (B T)`` (Shumway & Stoffer 1982; Ghahramani & Hinton 1996),
    missing components included (module docstring). The log-likelihood never decreases; it stops when its relative
    change falls below ``tolerance``. Works under ``jit`` (``iterations`` and ``update`` static) and ``vmap``.

    Args:
      params: :class:`~jaxobs.observers.kalman.KalmanParams` with the time-varying gain, the initial model.
      inputs: ``EstimatorInputs`` with ``y`` (B, T, p) or (T, p), NaN where missing, and ``u_prev`` or ``None``.
      iterations: EM iterations at most.
      update: the fields to learn, a subset of :data:`EM_FIELDS` (``x0``, ``P0`` from a single sequence collapse
        to its smoothed ``x_0``: give several sequences).
      tolerance: stop when ``ll_i - ll_{i-1} <= tolerance |ll_i|``.

    Returns:
      :class:`EMResult`.

    Example:
      >>> import jax, jaxobs as jo
      >>> true = jo.make_kalman([[0.9]], [[1.0]], [[0.5]], [[0.2]])
      >>> _, y = jax.vmap(lambda k: jo.sample(true, k, 200))(jax.random.split(jax.random.PRNGKey(0), 4))
      >>> result = jo.em(jo.make_kalman([[0.9]], [[1.0]], [[1.0]], [[1.0]], P0=[[0.5]]), jo.EstimatorInputs(y=y))
      >>> ll = result.log_likelihood[: int(result.iterations)]
      >>> bool(jnp.all(jnp.diff(ll) >= -1e-9 * jnp.abs(ll[1:])))
      True
    """
    if not isinstance(params, KalmanParams):
        raise ValueError(f"params must be KalmanParams (make_kalman), got {type(params).__name__}")
    if params.gain is not None:
        raise ValueError("params has a fixed gain: EM needs the time-varying filter's covariances (gain None)")
    iterations = _checks.count("iterations", iterations, minimum=1)
    update = (update,) if isinstance(update, str) else tuple(update)
    unknown = [f for f in update if f not in EM_FIELDS]
    if unknown or not update:
        raise ValueError(f"update must name fields among {EM_FIELDS}, got {list(update)}")
    _checks.positive_scalar("tolerance", tolerance, allow_zero=True)
    y, u = _batched(params, inputs)
    if u is None and "Gamma" in update:
        raise ValueError("update names Gamma but inputs.u_prev is None: there is no input to fit it on")
    if y.shape[1] < 2 and {"Phi", "Gamma", "Q"} & set(update):
        raise ValueError(f"inputs.y has {y.shape[1]} sample per sequence: Phi, Gamma and Q need at least 2")
    params = dataclasses.replace(params, output_covariance=False)
    return _em(params, y, u, tolerance, iterations=iterations, update=frozenset(update))


@partial(jax.jit, static_argnames=("iterations", "update"))
def _em(params, y, u, tolerance, *, iterations: int, update: frozenset) -> EMResult:
    counts = (y.shape[0] * (y.shape[1] - 1), y.shape[0] * y.shape[1])
    dtype = params.Phi.dtype
    y = y.astype(dtype)

    def cond(carry):
        i, _, _, done = carry
        return (i < iterations) & ~done

    def body(carry):
        i, current, lls, _ = carry
        stats = _statistics(current, y, u)
        previous = lls[jnp.maximum(i - 1, 0)]
        done = (i > 0) & (stats.log_likelihood - previous <= tolerance * jnp.abs(stats.log_likelihood))
        return i + 1, _maximise(current, stats, counts, update), lls.at[i].set(stats.log_likelihood), done

    start = (jnp.zeros((), jnp.int32), params, jnp.full((iterations,), jnp.nan, dtype), jnp.zeros((), bool))
    i, params, lls, done = jax.lax.while_loop(cond, body, start)
    return EMResult(params, lls, i, done)


# --------------------------------------------------------------------------------------------
# Autocovariance least squares


class ALSResult(NamedTuple):
    """Result of :func:`als`.

    Attributes:
      Q: (g, g) the estimate of the covariance of the process noise ``w`` (``G w`` drives the state)
      R: (p, p) the estimate of the measurement noise covariance
      autocovariance: (lags, p, p) the innovations' sample autocovariances ``C_0 .. C_{lags-1}`` it fits
      residual: () the norm of the least-squares residual
      identifiable: () bool: the least-squares matrix has full column rank, so ``Q`` and ``R`` are determined by
        the autocovariances of ``lags`` lags (otherwise the estimate is the minimum-norm one)
    """

    Q: jax.Array
    R: jax.Array
    autocovariance: jax.Array
    residual: jax.Array
    identifiable: jax.Array


def _structure(size: int, diagonal: bool) -> np.ndarray:
    """The (size^2, k) matrix ``D`` with ``vec(M) = D theta`` (row-major ``vec``) for a symmetric (``k = size (size
    + 1) / 2``, the lower triangle) or a diagonal (``k = size``) ``M``."""
    pairs = [(i, i) for i in range(size)] if diagonal else [(i, j) for i in range(size) for j in range(i + 1)]
    D = np.zeros((size * size, len(pairs)))
    for column, (i, j) in enumerate(pairs):
        D[i * size + j, column] = D[j * size + i, column] = 1.0
    return D


def _als_matrix(Phi, C, K, G, D_q, D_r, lags: int):
    """The matrix ``A`` of ``[vec C_0; ...; vec C_{lags-1}] = A [theta_Q; theta_R]`` (Odelson, Rajamani & Rawlings
    2006; ``vec`` row-major): with ``A_bar = Phi (I - K C)`` the predictor's error dynamics and
    ``vec P = (I - A_bar (x) A_bar)^{-1} ((G (x) G) vec Q + (Phi K (x) Phi K) vec R)`` its stationary covariance,
    ``C_0 = C P C' + R`` and ``C_j = C A_bar^j P C' - C A_bar^(j-1) Phi K R``."""
    n, p = Phi.shape[-1], C.shape[-2]
    A_bar, AK = Phi - Phi @ K @ C, Phi @ K
    noise = jnp.concatenate([jnp.kron(G, G) @ D_q, jnp.kron(AK, AK) @ D_r], axis=1)
    vec_P = jnp.linalg.solve(jnp.eye(n * n, dtype=Phi.dtype) - jnp.kron(A_bar, A_bar), noise)
    blocks, O, previous = [], C, None  # O = C A_bar^j, previous = C A_bar^(j-1)
    direct_q = jnp.zeros((p * p, D_q.shape[1]), Phi.dtype)
    for j in range(lags):
        direct_r = D_r if j == 0 else -jnp.kron(previous @ AK, jnp.eye(p, dtype=Phi.dtype)) @ D_r
        blocks.append(jnp.kron(O, C) @ vec_P + jnp.concatenate([direct_q, direct_r], axis=1))
        previous, O = O, O @ A_bar
    return jnp.concatenate(blocks)


def als(params: KalmanParams, innovation, *, lags: int = 15, G=None, diagonal=()) -> ALSResult:
    """Autocovariance least squares (Odelson, Rajamani & Rawlings 2006): ``Q`` and ``R`` from the innovations of a
    filter with a fixed gain, by matching their sample autocovariances ``C_j``
    (:func:`jaxobs.consistency.autocovariance`) with the ones the model implies, which are linear in ``(Q, R)``.

    The filter ``params`` may use any stabilising gain (typically the steady-state gain of a guess of ``Q`` and
    ``R``): its innovations are correlated when the guess is wrong, and that correlation identifies the true
    noise covariances. The estimate is the unconstrained least-squares solution over symmetric (or diagonal)
    matrices: unbiased, but it can be indefinite on short records (no semidefinite constraint).

    Args:
      params: :class:`~jaxobs.observers.kalman.KalmanParams` with a fixed gain (e.g. ``steady_state=True``): the
        model ``Phi``, ``C`` and the gain ``K`` the innovations were filtered with (``Q``, ``R`` unused).
      innovation: (T, p) or (B, T, p) the innovations ``outputs.innovation`` of ``run(kalman_filter, params,
        ...)`` once the filter's start-up transient has decayed, without missing components.
      lags: the number of autocovariance lags fitted (an integer >= 1, fewer than ``T``).
      G: (n, g) the noise input matrix, ``x_{k+1} = Phi x_k + Gamma u_k + G w_k``; ``None`` for the identity.
      diagonal: the names among ``("Q", "R")`` estimated as diagonal matrices (fewer unknowns).

    Returns:
      :class:`ALSResult`. Works under ``jit`` and ``vmap`` (over records or plants).

    Example:
      >>> import jax, jaxobs as jo
      >>> true = jo.make_kalman([[0.9]], [[1.0]], [[0.5]], [[0.2]])
      >>> guess = jo.make_kalman([[0.9]], [[1.0]], [[1.0]], [[1.0]], steady_state=True)
      >>> _, y = jax.vmap(lambda k: jo.sample(true, k, 2000))(jax.random.split(jax.random.PRNGKey(0), 8))
      >>> _, out = jax.vmap(lambda y: jo.run(jo.kalman_filter, guess, jo.EstimatorInputs(y)))(y)
      >>> result = jo.als(guess, out.innovation[:, 100:], lags=10)
      >>> [round(float(result.Q[0, 0]), 1), round(float(result.R[0, 0]), 1)]
      [0.5, 0.2]
    """
    if not isinstance(params, KalmanParams) or params.gain is None:
        raise ValueError("params must be KalmanParams with the fixed gain the innovations were filtered with "
                         "(make_kalman(..., steady_state=True))")  # fmt: skip
    n, p = params.Phi.shape[-1], params.C.shape[-2]
    dtype = params.Phi.dtype
    G = jnp.eye(n, dtype=dtype) if G is None else jnp.asarray(_checks.real_array("G", G), dtype)
    _checks.matrix("G", G, shape=(n, None))
    diagonal = (diagonal,) if isinstance(diagonal, str) else tuple(diagonal)
    if any(name not in ("Q", "R") for name in diagonal):
        raise ValueError(f"diagonal must name among ('Q', 'R'), got {list(diagonal)}")
    e = jnp.asarray(innovation)
    if e.ndim not in (2, 3) or e.shape[-1] != p:
        raise ValueError(f"innovation must have shape (T, {p}) or (B, T, {p}) (innovations), got {e.shape}")
    lags = _checks.count("lags", lags, minimum=1, maximum=e.shape[-2] - 1, hint="autocovariance lags")
    if _checks.is_concrete(params.Phi, params.gain):
        A_bar = np.asarray(params.Phi - params.Phi @ params.gain @ params.C)
        if np.max(np.abs(np.linalg.eigvals(A_bar))) >= 1:
            raise ValueError("params.gain does not stabilise the predictor Phi (I - K C): no stationary innovations")
    D_q, D_r = (jnp.asarray(_structure(size, name in diagonal), dtype) for size, name in ((G.shape[1], "Q"), (p, "R")))
    return _als(params.Phi, params.C, params.gain, G, D_q, D_r, e.astype(dtype), lags=lags)


@partial(jax.jit, static_argnames=("lags",))
def _als(Phi, C, K, G, D_q, D_r, innovation, *, lags: int) -> ALSResult:
    covariances = autocovariance(innovation, lags)
    A = _als_matrix(Phi, C, K, G, D_q, D_r, lags)
    b = jnp.reshape(covariances, (-1,))
    theta, _, rank, _ = jnp.linalg.lstsq(A, b)
    g, p = G.shape[1], C.shape[-2]
    Q = jnp.reshape(D_q @ theta[: D_q.shape[1]], (g, g))
    R = jnp.reshape(D_r @ theta[D_q.shape[1] :], (p, p))
    return ALSResult(Q, R, covariances, jnp.linalg.norm(A @ theta - b), rank == theta.shape[0])
