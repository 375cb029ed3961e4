"""Continuous-time linear observers (Grip 2010 §1.1-1.2): the Luenberger observer, the Kalman-Bucy filter (Riccati
differential equation or stationary gain), the observer with linear error dynamics for systems in the
output-injection canonical form (eq. 1.9), and the disturbance/exosystem augmentation (eq. 1.8).

Each observer is a pure right-hand side ``rate(params, x_hat, u, y, t)`` of its continuous-time dynamics (``x_hat``
a pytree: the estimate, and its covariance for the Kalman-Bucy filter) with an output map ``output(params, x_hat,
u)``, so it can be integrated inside any ODE solver together with the plant. :func:`as_continuous` binds them into
the :class:`~jaxobs.observers.continuous.ContinuousObserverParams` that
:data:`~jaxobs.observers.continuous.continuous_observer` runs on sampled data (``out.x`` is the estimate at the
sample ``t_k``; ``x0`` is the estimate at the first sample, which only stores ``y_0``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs._linalg import symmetrize
from jaxobs.design import characteristic_polynomial, is_detectable, lqe
from jaxobs.lti import unobservable_modes
from jaxobs.observers.continuous import ContinuousObserverParams, make_continuous_observer

__all__ = [
    "LuenbergerParams",
    "KalmanBucyParams",
    "OutputInjectionParams",
    "make_luenberger",
    "make_kalman_bucy",
    "make_output_injection",
    "luenberger_rate",
    "kalman_bucy_rate",
    "output_injection_rate",
    "augment",
    "sinusoid_exosystem",
    "luenberger_output",
    "kalman_bucy_output",
    "output_injection_output",
    "as_continuous",
    "KalmanBucyEstimate",
]


# --------------------------------------------------------------------------------------------
# Luenberger observer


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LuenbergerParams:
    """``x_hat' = A x_hat + B u + K (y - C x_hat - D u)`` (Grip 2010 eq. 1.3; error dynamics ``A - K C``, eq. 1.4).

    Attributes:
      A: (n, n).  B: (n, m).  C: (p, n).  D: (p, m).  K: (n, p) observer gain.  x0: (n,) estimate at the first sample.
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    D: jax.Array
    K: jax.Array
    x0: jax.Array


def make_luenberger(A, B, C, K, *, D=None, x0=None) -> LuenbergerParams:
    """Params of the continuous-time Luenberger observer (Grip 2010 eq. 1.3), with the checks: shapes, and, when
    concrete, the PBH detectability of ``(C, A)`` (a ``ValueError`` naming the undetectable mode: no gain can
    stabilise it) and a Hurwitz error matrix ``A - K C`` (``ValueError`` naming ``K`` otherwise). For a
    stationary Kalman-Bucy gain pass ``K`` from :func:`jaxobs.design.lqe`; for placed poles,
    ``jaxobs.design.place(A.T, C.T, poles).T``.

    Example:
      >>> params = make_luenberger([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[3.0], [2.0]])
      >>> params.K.shape
      (2, 1)
    """
    A, B, C, K, D = (None if M is None else jnp.atleast_2d(M) for M in _checks.float_arrays(A=A, B=B, C=C, K=K, D=D))
    n = A.shape[-1]
    _checks.matrix("A", A, shape=(n, n), square=True)
    _checks.matrix("B", B, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    p, m = C.shape[0], B.shape[1]
    _checks.matrix("K", K, shape=(n, p))
    dtype = A.dtype
    D = jnp.zeros((p, m), dtype) if D is None else D
    _checks.matrix("D", D, shape=(p, m))
    x0 = jnp.zeros(n, dtype) if x0 is None else _checks.vector("x0", x0, n, dtype)
    _require_detectable(A, C)
    if _checks.is_concrete(A, C, K):
        poles = np.linalg.eigvals(np.asarray(A - K @ C, float))
        if np.max(poles.real) >= 0:
            raise ValueError(f"K must make A - K C Hurwitz, got eigenvalues {np.round(poles, 6).tolist()}")
    return LuenbergerParams(*(M.astype(dtype) for M in (A, B, C, D, K)), x0)


def _require_detectable(A, C) -> None:
    """Eager PBH check of ``(C, A)`` (Grip 2010 §1.1.1): ``ValueError`` naming the unobservable unstable mode."""
    if _checks.is_concrete(A, C) and not is_detectable(A, C):
        modes = unobservable_modes(A, C, lambda lam: lam.real >= 0)
        raise ValueError(
            f"(C, A) is not detectable (PBH): the mode at eigenvalue {modes[0]:.6g} has real part >= 0 and is not "
            "seen by C, so no observer gain stabilises the error"
        )


def _check(params, *values):
    """``params`` (one observer of this module, not a batch) and ``values`` (``x_hat``/``z_hat``, ``u``, ``y``:
    those given) checked at trace time, naming the field or argument; the values as arrays of the params' dtype."""
    spec, x_name = _SHAPES[type(params)]
    sizes = _checks.fields("params", params, spec)
    names = (x_name, "u", "y")[: len(values)]
    dims = {"u": "(m,)" if "m" in sizes else "(*,)", "y": "(p,)" if "p" in sizes else "(*,)", x_name: "(n,)"}
    values = _checks.float_arrays(**dict(zip(names, values, strict=True)))
    _checks.shapes(", ".join(f"{name} {dims[name]}" for name in names), *values)
    return tuple(v.astype(params.x0.dtype) for v in values)


def luenberger_rate(params: LuenbergerParams, x_hat, u, y, t):
    """Right-hand side of Grip 2010 eq. 1.3: ``A x_hat + B u + K (y - y_hat)``, ``y_hat = C x_hat + D u``; ``x_hat``
    (n,), ``u`` (m,), ``y`` (p,), ``t`` unused."""
    _checks.shapes("t ()", t)  # unused: the observer is time invariant
    x_hat, u, y = _check(params, x_hat, u, y)
    return params.A @ x_hat + params.B @ u + params.K @ (y - luenberger_output(params, x_hat, u))


def luenberger_output(params: LuenbergerParams, x_hat, u):
    """``y_hat = C x_hat + D u`` (p,)."""
    x_hat, u = _check(params, x_hat, u)
    return params.C @ x_hat + params.D @ u


# --------------------------------------------------------------------------------------------
# Kalman-Bucy filter


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class KalmanBucyParams:
    """The Kalman-Bucy filter of ``x' = A x + B u + w``, ``y = C x + v``, ``E[w w'] = Q delta``,
    ``E[v v'] = R delta`` (Grip 2010 eq. 1.7).

    The estimate and its error covariance follow::

        x_hat' = A x_hat + B u + K(t) (y - C x_hat),   K = P C' R^{-1},
        P'     = A P + P A' + Q - P C' R^{-1} C P

    Attributes:
      A: (n, n).  B: (n, m).  C: (p, n).  Q: (n, n) process-noise intensity.  R: (p, p) measurement-noise
      intensity.  x0: (n,) estimate and  P0: (n, n) error covariance at the first sample.
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    Q: jax.Array
    R: jax.Array
    x0: jax.Array
    P0: jax.Array


def make_kalman_bucy(A, B, C, Q, R, *, x0=None, P0=None, stationary: bool = False):
    """Params of the Kalman-Bucy filter (Grip 2010 eq. 1.7), with the checks (shapes, ``Q >= 0``, ``R > 0``, PBH
    detectability of ``(C, A)``). ``P0`` defaults to the stationary covariance (the filter CARE's solution).

    With ``stationary=True`` returns the :class:`LuenbergerParams` of the stationary filter instead: the gain
    ``K = P C' R^{-1}`` of :func:`jaxobs.design.lqe` (H2-optimal, Grip 2010 §1.1.2).

    Example:
      >>> import numpy as np
      >>> params = make_kalman_bucy([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], np.eye(2), np.eye(1))
      >>> bool(np.allclose(params.P0, [[np.sqrt(3), 1.0], [1.0, np.sqrt(3)]]))
      True
    """
    A, B, C, Q, R = (jnp.atleast_2d(M) for M in _checks.float_arrays(A=A, B=B, C=C, Q=Q, R=R))
    n = A.shape[-1]
    _checks.matrix("A", A, shape=(n, n), square=True)
    _checks.matrix("B", B, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    _checks.covariance("Q", Q, definite=False, size=n)
    _checks.covariance("R", R, definite=True, size=C.shape[0])
    _require_detectable(A, C)
    K, P, _ = lqe(A, jnp.eye(n), C, Q, R)
    if stationary:
        return make_luenberger(A, B, C, K, x0=x0)
    dtype = _checks.float_dtype(A=A, B=B, C=C, Q=Q, R=R)
    x0 = jnp.zeros(n, dtype) if x0 is None else _checks.vector("x0", x0, n, dtype)
    if P0 is None:
        P0 = P
    _checks.covariance("P0", P0, definite=False, size=n)
    return KalmanBucyParams(*(jnp.asarray(M, dtype) for M in (A, B, C, Q, R)), x0, jnp.asarray(P0, dtype))


class KalmanBucyEstimate(NamedTuple):
    """State and output of the Kalman-Bucy filter.

    Attributes:
      x: (n,) estimate
      P: (n, n) error covariance
    """

    x: jax.Array
    P: jax.Array


def kalman_bucy_rate(params: KalmanBucyParams, estimate: KalmanBucyEstimate, u, y, t) -> KalmanBucyEstimate:
    """Right-hand side of the Kalman-Bucy filter (Grip 2010 eq. 1.7 with the Riccati differential equation);
    ``u`` (m,), ``y`` (p,), ``t`` unused."""
    _checks.shapes("t ()", t)  # unused: the observer is time invariant
    x, P = estimate = _checks.arrays("estimate.x (n,), estimate.P (n, n)", *estimate)
    u, y = _check(params, x, u, y)[1:]
    gain_t = jnp.linalg.solve(params.R, params.C @ P)  # K' = R^{-1} C P
    x_dot = params.A @ x + params.B @ u + gain_t.T @ (y - params.C @ x)
    AP = params.A @ P
    P_dot = AP + AP.T + params.Q - P @ params.C.T @ gain_t
    return KalmanBucyEstimate(x_dot, symmetrize(P_dot))


def kalman_bucy_output(params: KalmanBucyParams, estimate: KalmanBucyEstimate, u):
    """``y_hat = C x_hat`` (p,)."""
    x, _ = _checks.arrays("estimate.x (n,), estimate.P (n, n)", *estimate)
    _check(params, x, u)
    return params.C @ x


# --------------------------------------------------------------------------------------------
# output-injection canonical form


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class OutputInjectionParams:
    """The observer of Grip 2010 eq. 1.9 for ``z_i' = z_{i+1} + gamma_i(y, u)`` (i < n), ``z_n' = gamma_n(y, u)``,
    ``y = z_1``.

    The estimate follows::

        z_hat_i' = z_hat_{i+1} + gamma_i(y, u) + l_i (y - z_hat_1)

    whose error ``z - z_hat`` has the linear dynamics of the companion matrix of ``s^n + l_1 s^{n-1} + ... + l_n``.

    Attributes:
      l: (n,) injection gains.  x0: (n,) estimate at the first sample.
      gamma: static callable ``(y (), u (m,)) -> (n,)``, the output-injection terms (hashable, e.g. a module-level
        function).
    """

    l: jax.Array
    x0: jax.Array
    gamma: Callable = dataclasses.field(metadata=dict(static=True))


def make_output_injection(gamma: Callable, n, *, l=None, poles=None, x0=None) -> OutputInjectionParams:
    """Params of the output-injection observer (Grip 2010 eq. 1.9) with ``n`` states: the gains ``l`` directly, or
    from the desired error ``poles`` (``l`` = the coefficients of ``prod (s - pole)``, complex poles in conjugate
    pairs; the error dynamics are then exactly those poles).

    Example:
      >>> import jax.numpy as jnp
      >>> pendulum = lambda y, u: jnp.stack([0.0 * y, -jnp.sin(y) + u[0]])  # z1' = z2, z2' = -sin(y) + u
      >>> make_output_injection(pendulum, 2, poles=[-2.0, -3.0]).l.tolist()
      [5.0, 6.0]
    """
    n = _checks.count("n", n, minimum=1)
    if (l is None) == (poles is None):
        raise ValueError("l or poles: give exactly one of the injection gains l and the error poles")
    if l is None:
        poles = jnp.atleast_1d(jnp.asarray(poles))
        _checks.shape("poles", poles, (n,), "one error pole per state")
        _checks.finite("poles", poles)
        if _checks.is_concrete(poles) and np.max(np.real(np.asarray(poles))) >= 0:
            raise ValueError(f"poles must have negative real parts, got {np.asarray(poles).tolist()}")
        l = characteristic_polynomial(poles, _checks.float_dtype(poles=jnp.real(poles)))[1:]
    dtype = _checks.float_dtype(l=l)
    l = _checks.vector("l", l, n, dtype)
    x0 = jnp.zeros(n, dtype) if x0 is None else _checks.vector("x0", x0, n, dtype)
    if not callable(gamma):
        raise ValueError(f"gamma must be a callable (y, u) -> (n,), got {type(gamma).__name__}")
    return OutputInjectionParams(l, x0, gamma)


def output_injection_rate(params: OutputInjectionParams, z_hat, u, y, t):
    """Right-hand side of Grip 2010 eq. 1.9's observer; ``z_hat`` (n,), ``y`` () or (1,), ``u`` (m,), ``t`` unused."""
    _checks.shapes("t ()", t)  # unused: the observer is time invariant
    (y,) = _checks.float_arrays(y=y)
    if y.shape not in ((), (1,)):
        raise ValueError(f"y must be a scalar or have shape (1,) (the one output z_1), got {y.shape}")
    z_hat, u = _check(params, z_hat, u)
    y = jnp.reshape(y, ()).astype(z_hat.dtype)
    shifted = jnp.concatenate([z_hat[1:], jnp.zeros((1,), z_hat.dtype)])
    return shifted + params.gamma(y, u) + params.l * (y - z_hat[0])


def output_injection_output(params: OutputInjectionParams, z_hat, u):
    """``y_hat = z_hat_1`` (1,)."""
    z_hat, _ = _check(params, z_hat, u)
    return z_hat[:1]


# --------------------------------------------------------------------------------------------
# disturbance / exosystem augmentation


_SHAPES = {
    LuenbergerParams: ("A (n, n), B (n, m), C (p, n), D (p, m), K (n, p), x0 (n,)", "x_hat"),
    KalmanBucyParams: ("A (n, n), B (n, m), C (p, n), Q (n, n), R (p, p), x0 (n,), P0 (n, n)", "x_hat"),
    OutputInjectionParams: ("l (n,), x0 (n,)", "z_hat"),
}
"""Each params class: the shapes of its fields and the name of the estimate its functions take."""


def sinusoid_exosystem(frequencies):
    """The marginally stable exosystem of sinusoids of known ``frequencies`` (rad/s, (k,) positive): block-diagonal
    ``A_w`` with blocks ``[[0, w], [-w, 0]]`` and ``C_w`` (1, 2k) summing the first state of each (Grip 2010 §1.2.3).
    Returns ``(A_w (2k, 2k), C_w (1, 2k))``."""
    w = jnp.atleast_1d(jnp.asarray(frequencies))
    _checks.shape("frequencies", w, (None,))
    if _checks.is_concrete(w) and not np.all(np.asarray(w) > 0):
        raise ValueError(f"frequencies must be positive, got {np.asarray(w).tolist()}")
    dtype = _checks.float_dtype(frequencies=w)
    k = w.shape[0]
    blocks = jnp.zeros((k, 2, 2), dtype).at[:, 0, 1].set(w).at[:, 1, 0].set(-w)
    A_w = jax.scipy.linalg.block_diag(*blocks) if k > 1 else blocks[0]
    C_w = jnp.tile(jnp.array([[1.0, 0.0]], dtype), (1, k))
    return A_w, C_w


def augment(A, B, C, E, A_w, C_w=None, B_w=None):
    """The plant with a disturbance ``d = C_w w`` generated by the exosystem ``w' = A_w w (+ B_w omega)`` (Grip 2010
    §1.2.3, eq. 1.8: coloured noise as filtered white noise ``omega``, or constant and sinusoidal disturbances of a
    marginally stable ``A_w``), entering as ``x' = A x + B u + E d``.

    Valid in continuous and discrete time alike::

        [x; w]' = [[A, E C_w], [0, A_w]] [x; w] + [B; 0] u + [0; B_w] omega,     y = [C, 0] [x; w]

    Args:
      A: (n, n).  B: (n, m).  C: (p, n).  E: (n, r) disturbance input.  A_w: (k, k) exosystem.
      C_w: (r, k) disturbance output (default: identity, ``r = k``).  B_w: (k, q) noise input (default identity).

    Returns:
      ``(A_a, B_a, C_a, G_a)``: (n + k, n + k), (n + k, m), (p, n + k), and the noise input (n + k, q). An observer
      of the augmented pair estimates the disturbance as ``C_w w_hat``; it exists when the pair is detectable.

    Example:
      >>> A_w, C_w = sinusoid_exosystem([2.0])
      >>> A_a, B_a, C_a, G_a = augment([[-1.0]], [[1.0]], [[1.0]], [[1.0]], A_w, C_w)
      >>> A_a.shape, C_a.tolist()
      ((3, 3), [[1.0, 0.0, 0.0]])
    """
    A, B, C, E, A_w, C_w, B_w = (
        None if M is None else jnp.atleast_2d(M)
        for M in _checks.float_arrays(A=A, B=B, C=C, E=E, A_w=A_w, C_w=C_w, B_w=B_w)
    )
    n, k, dtype = A.shape[-1], A_w.shape[-1], A.dtype
    _checks.matrix("A", A, shape=(n, n), square=True)
    _checks.matrix("B", B, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    _checks.matrix("E", E, shape=(n, None))
    _checks.matrix("A_w", A_w, shape=(k, k), square=True)
    C_w = jnp.eye(k, dtype=dtype) if C_w is None else C_w
    _checks.matrix("C_w", C_w, shape=(E.shape[1], k))
    B_w = jnp.eye(k, dtype=dtype) if B_w is None else B_w
    _checks.matrix("B_w", B_w, shape=(k, None))
    A_a = jnp.block([[A, E @ C_w], [jnp.zeros((k, n), dtype), A_w]])
    B_a = jnp.concatenate([B, jnp.zeros((k, B.shape[1]), dtype)])
    C_a = jnp.concatenate([C, jnp.zeros((C.shape[0], k), dtype)], axis=1)
    G_a = jnp.concatenate([jnp.zeros((n, B_w.shape[1]), dtype), B_w])
    return A_a, B_a, C_a, G_a


# --------------------------------------------------------------------------------------------
# sampled data


def as_continuous(params, dt, *, n_inputs: int | None = None, t0=0.0, substeps: int = 4, method: str = "rk4",
                  measurement: str = "linear") -> ContinuousObserverParams:  # fmt: skip
    """The observer of ``params`` (:class:`LuenbergerParams`, :class:`KalmanBucyParams` or
    :class:`OutputInjectionParams`) as :class:`~jaxobs.observers.continuous.ContinuousObserverParams`, run on
    sampled data by :data:`~jaxobs.observers.continuous.continuous_observer`: ``u_{k-1}`` held over each interval
    of length ``dt``, the measurement interpolated linearly between the samples by default, ``substeps`` fixed
    steps of ``method`` per interval. ``n_inputs`` is ``B``'s column count for the linear observers and must be
    given for an output-injection observer whose ``gamma`` reads ``u`` (default 0). The estimate is ``x_hat``
    (``KalmanBucyEstimate(x, P)`` for the Kalman-Bucy filter).

    Example:
      >>> import numpy as np
      >>> from jaxobs.observers import EstimatorInputs, run
      >>> from jaxobs.observers.continuous import continuous_observer
      >>> params = make_luenberger([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[3.0], [2.0]])
      >>> t = 0.01 * np.arange(1000)  # the unit-acceleration double integrator: position t^2/2, velocity t
      >>> inputs = EstimatorInputs(y=(t**2 / 2)[:, None], u_prev=np.ones((1000, 1)))
      >>> _, out = run(continuous_observer, as_continuous(params, dt=0.01), inputs)
      >>> error = np.asarray(out.x[-1]) - [t[-1] ** 2 / 2, t[-1]]  # 8e-6 in position (linear interpolation of y)
      >>> bool(np.all(np.abs(error) < 1e-4))  # holding y instead (measurement="hold") gives 0.05
      True
    """
    if type(params) in _SHAPES:
        _checks.fields("params", params, _SHAPES[type(params)][0])
    if isinstance(params, LuenbergerParams):
        rate, output, x0, m = luenberger_rate, luenberger_output, params.x0, params.B.shape[1]
    elif isinstance(params, KalmanBucyParams):
        rate, output, m = kalman_bucy_rate, kalman_bucy_output, params.B.shape[1]
        x0 = KalmanBucyEstimate(params.x0, params.P0)
    elif isinstance(params, OutputInjectionParams):
        rate, output, x0, m = output_injection_rate, output_injection_output, params.x0, 0
    else:
        raise ValueError(
            f"params must be LuenbergerParams, KalmanBucyParams or OutputInjectionParams, got {type(params).__name__}"
        )
    if n_inputs is not None and n_inputs != m and not isinstance(params, OutputInjectionParams):
        raise ValueError(f"n_inputs must be {m}, the column count of B, got {n_inputs}")
    bind = jax.tree_util.Partial
    return make_continuous_observer(bind(rate, params), bind(output, params), x0=x0, dt=dt, t0=t0,
                                    n_inputs=m if n_inputs is None else n_inputs, substeps=substeps, method=method,
                                    measurement=measurement)  # fmt: skip
