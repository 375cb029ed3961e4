"""Classical Kalman filter (CKF): time-varying and steady-state gain.

Model ``x_k = Phi x_{k-1} + Gamma u_{k-1} + w_k``, ``y_k = C x_k + v_k`` with ``E[w w'] = Q``,
``E[v v'] = R``; the recursion of seed 000 eq. 27-29 (covariances in :mod:`jaxobs.riccati`).

Missing data: a non-finite measurement component is treated as missing. Its row of ``C`` and its
correlations in ``R`` are removed for that step (an exact marginalisation), so the update uses only
the finite components; when all are missing the update is skipped. ``state.missing`` counts the
skipped components.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.observers.base import Observer, run
from jaxobs.riccati import covariance_sequence, dare, predict_covariance, require_converged, update_covariance

__all__ = [
    "KalmanParams",
    "KalmanState",
    "KalmanInputs",
    "KalmanOutputs",
    "kalman_filter",
    "make_kalman",
    "with_steady_state_gain",
    "filter_shared_model",
    "measurement_update",
    "predict_and_update",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class KalmanParams:
    """Parameters of a Kalman filter. ``gain=None``: time-varying gain from the Riccati recursion;
    an ``(n, p)`` array: the fixed (steady-state) gain, no covariance propagation. ``gain_converged``:
    whether the DARE behind a steady-state gain found its stabilising solution (a boolean array when
    :func:`with_steady_state_gain` ran under tracing, else True or None)."""

    Phi: jax.Array
    Gamma: jax.Array
    C: jax.Array
    Q: jax.Array
    R: jax.Array
    x0: jax.Array
    P0: jax.Array
    gain: jax.Array | None = None
    gain_converged: jax.Array | None = None


class KalmanState(NamedTuple):
    x: jax.Array  # a-posteriori estimate x_hat_{k}
    P: jax.Array  # a-posteriori covariance P_k
    missing: jax.Array  # number of measurement components skipped so far


class KalmanInputs(NamedTuple):
    u_prev: jax.Array  # input u_{k-1} applied over the last interval
    y: jax.Array  # measurement y_k (NaN entries are missing)
    gain: jax.Array | None = None  # optional K_k from a precomputed gain schedule


class KalmanOutputs(NamedTuple):
    x: jax.Array  # a-posteriori estimate
    x_prior: jax.Array  # a-priori estimate Phi x_{k-1} + Gamma u_{k-1}
    innovation: jax.Array  # y_k - C x_prior (0 for missing components)
    gain: jax.Array  # K_k used at this step
    converged: jax.Array  # the steady-state gain's DARE converged (True for time-varying gains)


def make_kalman(Phi, Gamma, C, Q, R, *, x0=None, P0=None, steady_state: bool = False) -> KalmanParams:
    """Build and validate :class:`KalmanParams`: ``Phi`` (n, n), ``Gamma`` (n, m), ``C`` (p, n), ``Q`` (n, n),
    ``R`` (p, p), ``x0`` (n,) (default zeros), ``P0`` (n, n) (default ``Q``: ``P_{-1} = Q_0``).

    All arrays are cast to their common floating dtype (integers become float, float32 mixed with float64
    becomes float64), so the filter's state keeps one dtype over a run.
    """
    Phi, Gamma, C = (jnp.atleast_2d(jnp.asarray(M)) for M in (Phi, Gamma, C))
    Q, R = jnp.atleast_2d(jnp.asarray(Q)), jnp.atleast_2d(jnp.asarray(R))
    P0 = Q if P0 is None else jnp.atleast_2d(jnp.asarray(P0))
    dtype = _checks.float_dtype(Phi=Phi, Gamma=Gamma, C=C, Q=Q, R=R, P0=P0, x0=x0)
    _checks.matrix("Phi", Phi, square=True)
    n = Phi.shape[-1]
    _checks.matrix("Gamma", Gamma, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True, size=C.shape[0])
    _checks.covariance("P0", P0, definite=False, size=n)
    x0 = jnp.zeros((n,), dtype) if x0 is None else _checks.vector("x0", x0, n, dtype, what="one entry per state")
    params = KalmanParams(*(M.astype(dtype) for M in (Phi, Gamma, C, Q, R)), x0, P0.astype(dtype))
    return with_steady_state_gain(params) if steady_state else params


def with_steady_state_gain(params: KalmanParams) -> KalmanParams:
    """Same filter with the fixed steady-state gain from :func:`jaxobs.riccati.dare`.

    ``P`` is then set to the steady-state a-posteriori covariance and no longer propagated. Eagerly,
    raises ``ValueError`` with the reason when the DARE has no stabilising solution or did not converge
    (e.g. in float32); under tracing the flag is stored in ``gain_converged`` and reported by every step
    (``KalmanOutputs.converged``).
    """
    sol = dare(params.Phi, params.C, params.Q, params.R)
    require_converged(sol, params.Phi, params.C, params.Q, params.R, what="the steady-state Kalman filter's DARE")
    P, gain = update_covariance(sol.P, params.C, params.R)
    return dataclasses.replace(params, gain=gain, P0=P, gain_converged=sol.converged)


def measurement_update(x1, P1, C, R, y, gain=None):
    """Update ``(x1, P1)`` with ``y``; non-finite components of ``y`` are skipped exactly.

    Returns ``(x, P, K, innovation, n_missing)``. With a fixed ``gain``, ``P`` is returned unchanged
    and the innovation of missing components is zeroed.
    """
    observed = jnp.isfinite(y)
    y0 = jnp.where(observed, y, 0.0)
    mask = observed.astype(x1.dtype)
    C_obs = C * mask[:, None]
    innovation = (y0 - C @ x1) * mask
    if gain is None:
        # drop the missing rows of C and their correlations in R (unit variance placeholder)
        R_obs = R * jnp.outer(mask, mask) + jnp.diag(1.0 - mask)
        P, K = update_covariance(P1, C_obs, R_obs)
    else:
        P, K = P1, gain
    x = x1 + K @ innovation
    return x, P, K, innovation, jnp.sum(~observed)


def predict_and_update(x, P, u_prev, y, Phi, Gamma, C, Q, R, gain=None):
    """One filter step (eq. 27-29): predict with ``u_{k-1}``, then update with ``y_k``.

    With a fixed ``gain`` the covariance is not propagated. Returns
    ``(x, P, K, innovation, n_missing, x_prior)``; non-finite measurements are handled by
    :func:`measurement_update`.
    """
    x_prior = Phi @ x + Gamma @ jnp.atleast_1d(u_prev)
    P_prior = P if gain is not None else predict_covariance(P, Phi, Q)
    return *measurement_update(x_prior, P_prior, C, R, jnp.atleast_1d(y), gain), x_prior


def _init(params: KalmanParams) -> KalmanState:
    return KalmanState(params.x0, params.P0, jnp.zeros((), jnp.int32))


def _step(params: KalmanParams, state: KalmanState, inputs: KalmanInputs):
    n, m = params.Gamma.shape[-2:]
    p, dtype = params.C.shape[-2], params.Phi.dtype
    u_prev = _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype, what="one entry per column of Gamma",
                            check_finite=False)  # fmt: skip
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    gain = params.gain
    if inputs.gain is not None:
        _checks.shape("inputs.gain", inputs.gain, (n, p), "a gain K_k of shape (n_states, n_outputs)")
        gain = jnp.asarray(inputs.gain, dtype)
    x, P, K, innovation, n_missing, x_prior = predict_and_update(
        state.x, state.P, u_prev, y, params.Phi, params.Gamma, params.C, params.Q, params.R, gain
    )
    state = KalmanState(x, P, state.missing + n_missing.astype(jnp.int32))
    converged = jnp.asarray(True) if params.gain_converged is None else params.gain_converged
    return state, KalmanOutputs(x, x_prior, innovation, K, converged)


kalman_filter = Observer(_init, _step)
"""The classical Kalman filter in the (init, step) protocol; inputs are :class:`KalmanInputs` ``(u_{k-1}, y_k, K_k)`` of
shapes ``(m,)``, ``(p,)`` (scalars where the size is 1) and ``(n, p)`` or None. Each step checks the inputs' shapes
against the params while tracing (a ``ValueError`` naming the field) and casts them to the params' dtype."""


def filter_shared_model(params: KalmanParams, inputs: KalmanInputs):
    """Filter a batch of sequences (``inputs.u_prev`` of shape ``(B, T, m)``, ``inputs.y`` of shape ``(B, T, p)``)
    with one model: the Riccati recursion runs once (:func:`jaxobs.riccati.covariance_sequence`) and only
    the means are batched, the fast path for Monte-Carlo runs over noise seeds.

    The gain schedule assumes every measurement is present: a non-finite component has its
    innovation zeroed (the update uses the scheduled gain for the others) and is counted in
    ``state.missing``. Where missing data are common, ``vmap`` :func:`run` with
    :data:`kalman_filter` instead (exact, one covariance per sequence).
    Returns ``(final_states, outputs)`` with the batch axis first; every final state carries the
    schedule's last covariance.
    """
    y, u_prev = jnp.asarray(inputs.y), jnp.asarray(inputs.u_prev)
    p, m = params.C.shape[-2], params.Gamma.shape[-1]
    _checks.shape("inputs.y", y, (None, None, p), "(batch, time, outputs) measurements")
    _checks.shape("inputs.u_prev", u_prev, (y.shape[0], y.shape[1], m), "(batch, time, inputs) like inputs.y")
    num_steps = y.shape[1]
    schedule = covariance_sequence(params.P0, params.Phi, params.C, params.Q, params.R, num_steps)

    def one(u_prev, y):
        return run(kalman_filter, params, KalmanInputs(u_prev, y, schedule.K))

    final, outputs = jax.vmap(one)(u_prev, y)
    P = schedule.P[-1] if num_steps else params.P0  # a given gain leaves the state's P untouched
    return final._replace(P=jnp.broadcast_to(P, final.P.shape)), outputs
