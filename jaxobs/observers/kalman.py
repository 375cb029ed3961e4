"""The Kalman filter: time-varying gain (Riccati recursion) or a fixed steady-state gain.

Model (Cortesão 2006 eq. 27-29; the steps are those of :mod:`jaxobs.kalman_steps`): ``x_k = Phi x_{k-1} + Gamma
u_{k-1} + w_k``, ``y_k = C x_k + v_k``, ``E[w w'] = Q``, ``E[v v'] = R``, with the prior ``x0``, ``P0`` of ``x_0``,
the state at the first measurement. :func:`make_kalman`, :data:`kalman_filter`; non-finite measurement components
are skipped and counted. :data:`square_root_kalman_filter` (:func:`square_root_form`) is the same filter with
factors of the covariances (Bierman 1977). A time-varying model (``Phi_k``, ``Gamma_k``, ``C_k``, ``Q_k``,
``R_k``) travels in the inputs or comes from the params' ``schedule`` (:func:`step_model`). Prior convention and
outputs: docs/theory/estimators.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs._linalg import symmetrize
from jaxobs.kalman_steps import (
    covariance_sequence,
    predict,
    square_root_predict,
    square_root_update,
    tria,
    update,
    update_covariance,
)
from jaxobs.matrix_equations import filter_dare
from jaxobs.observers.base import Estimator, EstimatorInputs, LinearObserver

__all__ = [
    "KalmanParams",
    "KalmanState",
    "KalmanOutputs",
    "kalman_filter",
    "make_kalman",
    "with_steady_state_gain",
    "filter_shared_model",
    "SquareRootKalmanParams",
    "SquareRootKalmanState",
    "square_root_kalman_filter",
    "square_root_form",
    "step_model",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class KalmanParams:
    """Parameters of a Kalman filter (``n`` states, ``m`` inputs, ``p`` outputs).

    Attributes:
      Phi: (n, n) state transition.  Gamma: (n, m) input matrix (m = 0 for a model without inputs).
      C: (p, n) output matrix.  Q: (n, n) process noise covariance.  R: (p, p) measurement noise covariance.
      x0: (n,) prior mean of ``x_0``.  P0: (n, n) prior covariance of ``x_0``.
      gain: ``None`` for the time-varying gain of the Riccati recursion, or a fixed (n, p) gain (no covariance
        propagation; see :func:`with_steady_state_gain`).
      gain_converged: () whether the DARE behind a steady-state gain found its stabilising solution (an array
        when :func:`with_steady_state_gain` ran under tracing, else True or ``None``).
      output_covariance: static; every step also outputs the a-posteriori and a-priori covariances ``P``,
        ``P_prior`` (what the smoothers need): ``2 T n^2`` more numbers over ``T`` steps (16 MB for ``n = 10``,
        ``T = 10^4`` in float64). Time-varying gain only (a fixed gain propagates no covariance).
      joseph: static; ``False`` (default): the standard-form covariance update ``P1 - K S K'`` (symmetrised), as
        dynamax; ``True``: the Joseph form, positive semidefinite by construction, for measurements far more
        precise than the prior, where the standard form's difference cancels and can lose definiteness
        (:func:`jaxobs.kalman_steps.update_covariance_factors`). The Joseph form costs up to 1.7x the time per step
        (docs/estimation.md).
      schedule: ``None``, or a time-varying model as a function of the inputs' ``model`` (e.g. the step index
        ``k``): a ``jax.tree_util.Partial`` returning a dict of the step's values of some of :attr:`model_fields`
        (:func:`step_model`); its bound arrays are leaves (``grad`` and ``vmap`` reach them).
    """

    model_fields: ClassVar[tuple[str, ...]] = ("Phi", "Gamma", "C", "Q", "R")

    Phi: jax.Array
    Gamma: jax.Array
    C: jax.Array
    Q: jax.Array
    R: jax.Array
    x0: jax.Array
    P0: jax.Array
    gain: jax.Array | None = None
    gain_converged: jax.Array | None = None
    output_covariance: bool = dataclasses.field(default=False, metadata=dict(static=True))
    joseph: bool = dataclasses.field(default=False, metadata=dict(static=True))
    schedule: Callable | None = None


class KalmanState(NamedTuple):
    """State of :data:`kalman_filter` between steps.

    Attributes:
      x: (n,) a-posteriori estimate x_hat_{k-1|k-1} (the prior mean before the first step)
      P: (n, n) its covariance
      started: () bool: a measurement has been processed (the next step predicts)
      missing: () int32, measurement components skipped so far
    """

    x: jax.Array
    P: jax.Array
    started: jax.Array
    missing: jax.Array


class KalmanOutputs(NamedTuple):
    """Outputs of one step of :data:`kalman_filter`.

    Attributes:
      x: (n,) a-posteriori estimate x_hat_{k|k}
      x_prior: (n,) a-priori estimate x_hat_{k|k-1}
      innovation: (p,) y_k - C x_prior (0 for missing components)
      gain: (n, p) gain K_k used at this step
      converged: () the steady-state gain's DARE converged (True for time-varying gains)
      S: (p, p) innovation covariance C P_prior C' + R of the observed components (1 on a missing diagonal)
      log_likelihood: () log p(y_k | y_0..y_{k-1}) of the observed components (0 when all are missing)
      P: (n, n) a-posteriori covariance P_{k|k} (with output_covariance, else None)
      P_prior: (n, n) a-priori covariance P_{k|k-1} (with output_covariance, else None)
    """

    x: jax.Array
    x_prior: jax.Array
    innovation: jax.Array
    gain: jax.Array
    converged: jax.Array
    S: jax.Array
    log_likelihood: jax.Array
    P: jax.Array | None = None
    P_prior: jax.Array | None = None


def make_kalman(Phi, C, Q, R, *, Gamma=None, x0=None, P0=None, steady_state: bool = False,
                joseph: bool = False, schedule=None) -> KalmanParams:  # fmt: skip
    """Build and check :class:`KalmanParams`.

    Args:
      Phi: (n, n).  C: (p, n).  Q: (n, n) positive semidefinite.  R: (p, p) positive definite.
      Gamma: (n, m) input matrix; ``None`` for a model without inputs.
      x0: (n,) prior mean of ``x_0`` (default zeros).  P0: (n, n) prior covariance of ``x_0`` (default ``Q``).
      steady_state: use the steady-state gain (:func:`with_steady_state_gain`).
      joseph: ``False`` (default): the standard-form covariance update, one product per step; ``True``: the Joseph
        form, for measurements far more precise than the prior (see :class:`KalmanParams`).
      schedule: ``None``, or a function of the inputs' ``model`` (e.g. the step index) returning a dict of the
        step's model values (:func:`step_model`); ``Phi`` ... ``R`` then give the shapes and the constant fields.

    All arrays are cast to their common floating dtype (integers become float, float32 mixed with float64
    becomes float64), so the filter's state keeps one dtype over a run.

    Example:
      >>> from jaxobs.observers import kalman
      >>> params = kalman.make_kalman(Phi=[[1.0, 0.1], [0.0, 1.0]], C=[[1.0, 0.0]], Q=0.01 * jnp.eye(2), R=[[0.5]])
      >>> params.gain is None, params.Gamma.shape
      (True, (2, 0))
    """
    Phi, C, Q, R = (jnp.atleast_2d(_checks.real_array(k, M)) for k, M in (("Phi", Phi), ("C", C), ("Q", Q), ("R", R)))
    P0 = Q if P0 is None else jnp.atleast_2d(_checks.real_array("P0", P0))
    dtype = _checks.float_dtype(Phi=Phi, Gamma=Gamma, C=C, Q=Q, R=R, P0=P0, x0=x0)
    _checks.matrix("Phi", Phi, square=True)
    n = Phi.shape[-1]
    Gamma = jnp.zeros((n, 0), dtype) if Gamma is None else jnp.atleast_2d(jnp.asarray(Gamma))
    _checks.matrix("Gamma", Gamma, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True, size=C.shape[0])
    _checks.covariance("P0", P0, definite=False, size=n)
    x0 = jnp.zeros((n,), dtype) if x0 is None else _checks.vector("x0", x0, n, dtype, what="one entry per state")
    joseph = _checks.boolean("joseph", joseph)
    schedule = None if schedule is None else _checks.function("schedule", schedule)
    params = KalmanParams(*(M.astype(dtype) for M in (Phi, Gamma, C, Q, R)), x0, P0.astype(dtype), joseph=joseph,
                          schedule=schedule)  # fmt: skip
    return with_steady_state_gain(params) if _checks.boolean("steady_state", steady_state) else params


def with_steady_state_gain(params: KalmanParams) -> KalmanParams:
    """The same filter with the fixed steady-state gain ``K = P C' (C P C' + R)^{-1}``, ``P`` the a-priori
    solution of the filter DARE (:func:`jaxobs.matrix_equations.filter_dare`); ``P0`` becomes the steady-state
    a-posteriori covariance. Eagerly, raises ``ValueError`` with the reason when the DARE has no stabilising
    solution or did not converge (e.g. in float32); under tracing the flag is stored in ``gain_converged`` and
    reported by every step (``KalmanOutputs.converged``).
    """
    if params.schedule is not None:
        raise ValueError("params.schedule: a time-varying model has no steady-state gain; use the time-varying one")
    sol = filter_dare(params.Phi, params.C, params.Q, params.R, what="the steady-state Kalman filter's DARE")
    P, gain = update_covariance(sol.X, params.C, params.R)
    return dataclasses.replace(params, gain=gain, P0=P, gain_converged=sol.converged)


def _inputs(params: KalmanParams, inputs: EstimatorInputs):
    """``(y, u_prev)`` checked against the params' shapes (at trace time) and cast to their dtype."""
    m, p, dtype = params.Gamma.shape[-1], params.C.shape[-2], params.Phi.dtype
    y = _checks.vector("inputs.y", inputs.y, p, dtype, what="one entry per row of C", check_finite=False)
    if inputs.u_prev is None:
        return y, None
    u_prev = _checks.vector("inputs.u_prev", inputs.u_prev, m, dtype, what="one entry per column of Gamma",
                            check_finite=False)  # fmt: skip
    return y, u_prev


def _require_time_varying(params, what: str) -> None:
    """The covariance outputs exist only where a covariance is propagated (static check)."""
    if params.output_covariance:
        raise ValueError(
            f"params.output_covariance: {what} propagates no covariance; use the time-varying gain (params.gain None)"
        )


def step_model(params, model) -> dict:
    """The model of one step of a time-varying filter: the values that replace fields of ``params`` at this step.

    ``model`` is the inputs' ``model`` of the step (:class:`~jaxobs.observers.base.EstimatorInputs`): a dict of
    per-step values of ``params.model_fields`` (``Phi``, ``Gamma``, ``C``, ``Q``, ``R``; ``Q_sqrt``, ``R_sqrt`` for
    :class:`SquareRootKalmanParams`), or, when ``params.schedule`` is set, its argument (e.g. the step index
    ``k``). ``Phi_k``, ``Gamma_k`` and ``Q_k`` are those of the transition into sample ``k`` (unused at the first
    sample, which has no prediction); ``C_k``, ``R_k`` those of ``y_k``. Each value has the shape of the params'
    field (checked while tracing) and is cast to its dtype; fields not named keep the params' value. Returns
    ``{}`` for a constant model (``model`` and ``params.schedule`` ``None``).

    Example:
      >>> from jaxobs.observers import kalman, EstimatorInputs, run
      >>> params = kalman.make_kalman([[1.0]], [[1.0]], [[0.1]], [[1.0]])
      >>> Phi = jnp.linspace(0.5, 1.0, 20)[:, None, None]  # Phi_k for k = 0 .. 19
      >>> _, out = run(kalman.kalman_filter, params, EstimatorInputs(y=jnp.ones((20, 1)), model={"Phi": Phi}))
      >>> out.x.shape
      (20, 1)
    """
    schedule = params.schedule
    if model is None:
        if schedule is not None:
            raise ValueError("inputs.model is None: params.schedule maps it (e.g. the step index k) to the model")
        return {}
    values = model if schedule is None else schedule(model)
    what = "inputs.model" if schedule is None else "params.schedule(inputs.model)"
    fields = params.model_fields
    if not isinstance(values, Mapping) or any(name not in fields for name in values):
        given = sorted(values) if isinstance(values, Mapping) else type(values).__name__
        raise ValueError(f"{what} must be a dict of per-step values of {fields}, got {given}")
    if getattr(params, "gain", None) is not None:
        raise ValueError("params has a fixed gain: a time-varying model needs the time-varying gain (gain None)")
    out = {}
    for name, value in values.items():
        constant = getattr(params, name)
        value = jnp.asarray(value)
        _checks.shape(f"{what}['{name}']", value, constant.shape, f"that of params.{name}, at one step")
        out[name] = value.astype(constant.dtype)
    return out


def _at_step(params, inputs: EstimatorInputs):
    """``params`` with the model of this step (:func:`step_model`)."""
    values = step_model(params, inputs.model)
    return dataclasses.replace(params, **values) if values else params


def _filter_step(params: KalmanParams, state: KalmanState, y, u_prev, gain):
    P = None if gain is not None else state.P
    if gain is not None:
        _require_time_varying(params, "a fixed-gain filter")
    x_prior, P_prior = predict(state.x, P, params.Phi, params.Q, params.Gamma, u_prev, skip=~state.started)
    result = update(x_prior, state.P if P_prior is None else P_prior, params.C, params.R, y, gain,
                    joseph=params.joseph)  # fmt: skip
    missing = state.missing + result.n_missing.astype(jnp.int32)
    new_state = KalmanState(result.x, result.P, jnp.ones((), bool), missing)
    converged = jnp.asarray(True) if params.gain_converged is None else params.gain_converged
    covariances = (result.P, P_prior) if params.output_covariance else ()
    outputs = KalmanOutputs(result.x, x_prior, result.innovation, result.K, converged, result.S,
                            result.log_likelihood, *covariances)  # fmt: skip
    return new_state, outputs


def _init(params: KalmanParams) -> KalmanState:
    return KalmanState(params.x0, params.P0, jnp.zeros((), bool), jnp.zeros((), jnp.int32))


def _step(params: KalmanParams, state: KalmanState, inputs: EstimatorInputs):
    params = _at_step(params, inputs)
    y, u_prev = _inputs(params, inputs)
    return _filter_step(params, state, y, u_prev, params.gain)


def _linear(params: KalmanParams) -> LinearObserver:
    if params.gain is None:
        raise ValueError(
            "params: the linear form needs a fixed gain; use with_steady_state_gain (or steady_state=True)"
        )
    return LinearObserver(params.Phi, params.Gamma, params.C, params.gain)


kalman_filter = Estimator(_init, _step, _linear)
"""The Kalman filter as an :class:`~jaxobs.observers.base.Estimator` over :class:`KalmanParams`.

Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (p,) and (m,) (``u_prev=None`` without inputs); each step
checks them against the params while tracing and casts them to the params' dtype. Outputs:
:class:`KalmanOutputs`."""


def filter_shared_model(params: KalmanParams, inputs: EstimatorInputs):
    """Filter a batch of sequences with one model: the Riccati recursion runs once
    (:func:`jaxobs.kalman_steps.covariance_sequence`) and only the means are batched, the fast path for Monte-Carlo
    runs over noise seeds.

    Args:
      params: a time-varying-gain filter (``params.gain`` ``None``); with a fixed gain use ``vmap(run)``.
      inputs: ``EstimatorInputs`` with ``y`` of shape (B, T, p) and ``u_prev`` (B, T, m) or ``None``.

    The gain schedule assumes every measurement is present: a non-finite component has its innovation zeroed
    (the scheduled gain is used for the others) and is counted in ``state.missing``. Where missing data are
    common, ``vmap`` :func:`~jaxobs.observers.base.run` with :data:`kalman_filter` instead (exact, one
    covariance per sequence). ``S`` and ``log_likelihood`` are the schedule's (exact without missing data, through
    ``S = (I - C K_k)^{-1} R``). Returns ``(final_states, outputs)`` with the batch axis first; every final
    state carries the schedule's last covariance.
    """
    if params.gain is not None:
        raise ValueError("params has a fixed gain: filter_shared_model computes the time-varying one; use vmap(run)")
    if params.schedule is not None or inputs.model is not None:
        raise ValueError("inputs.model, params.schedule: filter_shared_model shares one constant model's covariance "
                         "schedule; for a time-varying model use vmap(run)")  # fmt: skip
    if params.output_covariance:
        raise ValueError("params.output_covariance: filter_shared_model shares one covariance schedule over the batch "
                         "and outputs none; use vmap(run) for the covariances of every sequence")  # fmt: skip
    y = jnp.asarray(inputs.y)
    p, m = params.C.shape[-2], params.Gamma.shape[-1]
    _checks.shape("inputs.y", y, (None, None, p), "(batch, time, outputs) measurements")
    if y.shape[1] == 0:
        raise ValueError("inputs.y has no samples: give at least one (its shape is (batch, time, outputs))")
    u_prev = inputs.u_prev
    if u_prev is not None:
        u_prev = jnp.asarray(u_prev)
        _checks.shape("inputs.u_prev", u_prev, (y.shape[0], y.shape[1], m), "(batch, time, inputs) like inputs.y")
    # the schedule of the time-varying filter: P_prior_0 = P0, then P_prior_k = Phi P_{k-1} Phi' + Q
    first_P, first_K = update_covariance(params.P0, params.C, params.R)
    later = covariance_sequence(first_P, params.Phi, params.C, params.Q, params.R, y.shape[1] - 1)
    gains = jnp.concatenate([first_K[None], later.K])
    last_P = later.P[-1] if y.shape[1] > 1 else first_P

    def one(y_seq, u_seq):
        def body(state, step_inputs):
            y_k, u_k, K_k = step_inputs
            y_k, u_k = _inputs(params, EstimatorInputs(y_k, u_k))
            return _filter_step(params, state, y_k, u_k, K_k)

        state, out = jax.lax.scan(body, _init(params), (y_seq, u_seq, gains))
        return state._replace(P=last_P), out

    return jax.vmap(one)(y, u_prev)


# --------------------------------------------------------------------------------------------
# Square-root form


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SquareRootKalmanParams:
    """The Kalman filter of :class:`KalmanParams` with its covariances given by factors (``M = M_sqrt M_sqrt'``,
    any factor, e.g. a Cholesky factor or the noise input matrix ``G`` of ``Q = G G'``), for
    :data:`square_root_kalman_filter`. Differentiate with respect to the factors: singular covariances are then
    no special case.

    Attributes:
      Phi: (n, n).  Gamma: (n, m).  C: (p, n).  x0: (n,) prior mean of ``x_0``.
      Q_sqrt: (n, r) factor of the process noise covariance.  R_sqrt: (p, s) factor of the (positive definite)
        measurement noise covariance.  P0_sqrt: (n, n) factor of the prior covariance of ``x_0``.
      output_covariance: static; outputs ``P = P_sqrt P_sqrt'`` and ``P_prior`` at every step (see
        :class:`KalmanParams`).
      joseph: static; the covariance update in Joseph form (see :class:`KalmanParams`).
      schedule: ``None`` or a time-varying model as in :class:`KalmanParams`, with factors: its dict holds values
        of ``Phi``, ``Gamma``, ``C``, ``Q_sqrt``, ``R_sqrt`` (:func:`step_model`).
    """

    model_fields: ClassVar[tuple[str, ...]] = ("Phi", "Gamma", "C", "Q_sqrt", "R_sqrt")

    Phi: jax.Array
    Gamma: jax.Array
    C: jax.Array
    Q_sqrt: jax.Array
    R_sqrt: jax.Array
    x0: jax.Array
    P0_sqrt: jax.Array
    output_covariance: bool = dataclasses.field(default=False, metadata=dict(static=True))
    joseph: bool = dataclasses.field(default=True, metadata=dict(static=True))
    schedule: Callable | None = None


class SquareRootKalmanState(NamedTuple):
    """State of :data:`square_root_kalman_filter` between steps.

    Attributes:
      x: (n,) a-posteriori estimate x_hat_{k-1|k-1} (the prior mean before the first step)
      P_sqrt: (n, n) lower-triangular factor of its covariance
      started: () bool: a measurement has been processed (the next step predicts)
      missing: () int32, measurement components skipped so far
    """

    x: jax.Array
    P_sqrt: jax.Array
    started: jax.Array
    missing: jax.Array


def _factor(M):
    """A lower-triangular factor of a symmetric positive semidefinite ``M``: an eigendecomposition with the
    rounding-level negative eigenvalues clipped, triangularised (:func:`jaxobs.kalman_steps.tria`)."""
    w, V = jnp.linalg.eigh(symmetrize(M))
    return tria(V * jnp.sqrt(jnp.clip(w, 0.0)))


def square_root_form(params: KalmanParams) -> SquareRootKalmanParams:
    """The same time-varying filter with factors of ``Q``, ``R`` and ``P0`` (lower triangular; semidefinite
    ``Q`` and ``P0`` allowed): the params of :data:`square_root_kalman_filter`, whose outputs equal those of
    :data:`kalman_filter` on ``params`` to rounding.

    Example:
      >>> from jaxobs.observers import kalman, EstimatorInputs, run
      >>> params = kalman.make_kalman(Phi=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]])
      >>> _, out = run(kalman.square_root_kalman_filter, kalman.square_root_form(params),
      ...              EstimatorInputs(y=jnp.ones((50, 1))))
      >>> bool(jnp.allclose(out.x, run(kalman.kalman_filter, params, EstimatorInputs(y=jnp.ones((50, 1))))[1].x))
      True
    """
    if params.gain is not None:
        raise ValueError("params has a fixed gain: the square-root form propagates the time-varying covariance")
    if params.schedule is not None:
        raise ValueError("params.schedule returns covariances: give the square-root filter a schedule of factors "
                         "(SquareRootKalmanParams(..., schedule=...) returning Q_sqrt, R_sqrt)")  # fmt: skip
    Q_sqrt, R_sqrt, P0_sqrt = (_factor(M) for M in (params.Q, params.R, params.P0))
    return SquareRootKalmanParams(params.Phi, params.Gamma, params.C, Q_sqrt, R_sqrt, params.x0, P0_sqrt,
                                  output_covariance=params.output_covariance)  # fmt: skip


def _square_root_init(params: SquareRootKalmanParams) -> SquareRootKalmanState:
    return SquareRootKalmanState(params.x0, params.P0_sqrt, jnp.zeros((), bool), jnp.zeros((), jnp.int32))


def _square_root_step(params: SquareRootKalmanParams, state: SquareRootKalmanState, inputs: EstimatorInputs):
    params = _at_step(params, inputs)
    n, p = params.Phi.shape[-1], params.C.shape[-2]
    _checks.shape("params.Q_sqrt", params.Q_sqrt, (n, None), "a factor of Q: one row per state")
    _checks.shape("params.R_sqrt", params.R_sqrt, (p, None), "a factor of R: one row per row of C")
    _checks.shape("params.P0_sqrt", params.P0_sqrt, (n, n), "a square factor of P0")
    y, u_prev = _inputs(params, inputs)
    x_prior, P_prior = square_root_predict(state.x, state.P_sqrt, params.Phi, params.Q_sqrt, params.Gamma, u_prev,
                                           skip=~state.started)  # fmt: skip
    result = square_root_update(x_prior, P_prior, params.C, params.R_sqrt, y)
    missing = state.missing + result.n_missing.astype(jnp.int32)
    new_state = SquareRootKalmanState(result.x, result.P_sqrt, jnp.ones((), bool), missing)
    gram = lambda M: M @ M.T
    covariances = (gram(result.P_sqrt), gram(P_prior)) if params.output_covariance else ()
    outputs = KalmanOutputs(result.x, x_prior, result.innovation, result.K, jnp.asarray(True), gram(result.S_sqrt),
                            result.log_likelihood, *covariances)  # fmt: skip
    return new_state, outputs


square_root_kalman_filter = Estimator(_square_root_init, _square_root_step)
"""The Kalman filter in square-root form (Bierman 1977) as an :class:`~jaxobs.observers.base.Estimator` over
:class:`SquareRootKalmanParams` (from :func:`square_root_form`, or built from factors): it carries a
lower-triangular factor of the covariance (:class:`SquareRootKalmanState`), predicts with the triangularisation of
``[Phi P_sqrt, Q_sqrt]`` and updates with that of the pre-array of :func:`jaxobs.kalman_steps.square_root_update`,
so covariances stay positive semidefinite in any precision. Outputs: :class:`KalmanOutputs` (the covariances
``S``, ``P``, ``P_prior`` as products of the factors). Costs more per step than the covariance form
(``benchmarks/parallel_in_time.py``)."""
