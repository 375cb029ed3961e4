"""Controller design: Ackermann pole placement, MIMO pole placement, discrete and continuous LQR and LQE, the PBH
detectability test, DC-gain compensation.

``acker``, ``dlqr``, ``dlqe``, ``lqr`` and ``lqe`` are JAX functions (``jit``/``vmap``/``grad``); ``place`` and
``is_detectable`` are design-time helpers on concrete arrays (SciPy, NumPy), as MIMO placement has no unique, smooth
answer.
"""

from __future__ import annotations

from functools import partial

import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs._jit import jit
from jaxobs._linalg import solve_spd, symmetrize
from jaxobs.lti import StateSpace, ctrb, dcgain, unobservable_modes
from jaxobs.matrix_equations import care, dare, filter_dare, require_care_converged, require_converged

__all__ = [
    "characteristic_polynomial",
    "acker",
    "place",
    "dlqr",
    "dlqe",
    "lqr",
    "lqe",
    "is_detectable",
    "dc_compensation",
    "reference_gain",
    "critically_damped_poles",
    "critically_damped_gain",
]


def characteristic_polynomial(poles, dtype):
    """The monic polynomial with roots ``poles`` (n,): real coefficients ``[1, a_1, ..., a_n]`` of
    ``prod (z - p_i)`` in ``dtype`` (complex poles in conjugate pairs; the product is formed in the complex type of
    ``poles`` and ``dtype``)."""
    poles = jnp.asarray(poles)
    _checks.shapes("poles (n,)", poles)
    coeffs = jnp.ones((1,), jnp.result_type(poles, dtype, jnp.complex64))
    for i in range(poles.shape[-1]):
        coeffs = jnp.concatenate([coeffs, jnp.zeros((1,), coeffs.dtype)]) - poles[i] * jnp.concatenate(
            [jnp.zeros((1,), coeffs.dtype), coeffs]
        )
    return jnp.real(coeffs).astype(dtype)


def acker(Phi, Gamma, poles):
    """Single-input pole placement by Ackermann's formula (Cortesão 2006, eq. 45-46).

    ``L = [0 ... 0 1] W_c^{-1} P(Phi)`` with ``W_c = [Gamma, Phi Gamma, ..., Phi^{n-1} Gamma]`` and
    ``P`` the desired characteristic polynomial, so that ``eig(Phi - Gamma L) = poles``.
    Works under ``jit``/``vmap``/``grad``; complex poles must come in conjugate pairs. Integer or mixed
    float32/float64 matrices are computed in their common floating dtype.

    Args:
      Phi: (n, n) state matrix.  Gamma: (n, 1) input matrix.  poles: (n,) desired poles.

    Returns:
      (1, n) gain ``L``.
    """
    Phi, Gamma = jnp.asarray(Phi), jnp.asarray(Gamma)
    if Gamma.ndim == 1:
        Gamma = Gamma[:, None]
    dtype = _checks.float_dtype(Phi=Phi, Gamma=Gamma)
    _checks.matrix("Phi", Phi, square=True)
    n = Phi.shape[-1]
    _checks.matrix("Gamma", Gamma, shape=(n, 1))
    poles = jnp.atleast_1d(jnp.asarray(poles))
    _checks.shape("poles", poles, (n,), f"one pole per state of Phi, which has {n}")
    _checks.finite("poles", poles)
    if _checks.is_concrete(poles):
        p = np.sort_complex(np.asarray(poles, dtype=complex))
        if not np.allclose(p, np.sort_complex(p.conj()), atol=1e-12):
            raise ValueError("poles: complex poles must come in conjugate pairs")
    L, Wc = _ackermann(Phi.astype(dtype), Gamma.astype(dtype), poles)
    if _checks.is_concrete(Wc):
        Wc_np = np.asarray(Wc)
        if np.linalg.matrix_rank(Wc_np, tol=1e-12 * np.linalg.norm(Wc_np)) < n:
            raise ValueError("(Phi, Gamma) is not controllable: no gain places all poles (Wc is singular)")
    return L


@partial(jit, what="acker")
def _ackermann(Phi, Gamma, poles):
    """``(L, W_c)`` of :func:`acker` (compiled once per shape: eager calls cost one dispatch)."""
    n = Phi.shape[-1]
    Wc = ctrb(Phi, Gamma)
    a = characteristic_polynomial(poles, Phi.dtype)
    P_Phi = jnp.zeros_like(Phi)
    for coefficient in a:  # Horner: P(Phi) = Phi^n + a_1 Phi^{n-1} + ... + a_n I
        P_Phi = P_Phi @ Phi + coefficient * jnp.eye(n, dtype=Phi.dtype)
    e_n = jnp.zeros((n,), Phi.dtype).at[-1].set(1.0)
    row = jnp.linalg.solve(Wc.T, e_n)  # [0 ... 0 1] Wc^{-1}
    return (row @ P_Phi)[None, :], Wc


@_checks.design_time(alternative="jaxobs.design.acker (single input) or jaxobs.design.dlqr")
def place(Phi, Gamma, poles, *, zero_input_columns=(), method: str = "YT") -> np.ndarray:
    """MIMO pole placement (design time; SciPy's ``place_poles``).

    Args:
      Phi: (n, n) state matrix.  Gamma: (n, m) input matrix.
      poles: (n,) desired closed-loop poles (complex ones in conjugate pairs).
      zero_input_columns: inputs that cannot be actuated; their columns of ``Gamma`` are zeroed
        for the design only and their rows of the returned gain are zero (Cortesão 2006 §8.4: "the first
        and third columns of Gamma_r should be set to zero").
      method: "YT" (Tits-Yang, robust) or "KNV0", as in SciPy.

    Returns:
      (m, n) gain ``L`` with ``eig(Phi - Gamma L) = poles``.

    Example:
      >>> L = place([[1.0, 0.1], [0.0, 1.0]], [[0.0, 1.0], [0.1, 0.0]], [0.5, 0.6])
      >>> L.shape
      (2, 2)
    """
    Phi = np.asarray(Phi, dtype=float)
    Gamma = np.atleast_2d(np.asarray(Gamma, dtype=float))
    n = Phi.shape[0]
    _checks.matrix("Phi", Phi, shape=(n, n), square=True)
    _checks.matrix("Gamma", Gamma, shape=(n, None))
    poles = np.atleast_1d(np.asarray(poles))
    _checks.shape("poles", poles, (n,), f"one pole per state of Phi, which has {n}")
    _checks.finite("poles", poles)
    m = Gamma.shape[1]
    zero = {_checks.count("zero_input_columns", j, maximum=m - 1) for j in zero_input_columns}
    keep = [j for j in range(m) if j not in zero]
    G = Gamma[:, keep]
    Wc = np.asarray(ctrb(Phi, G))
    if np.linalg.matrix_rank(Wc, tol=1e-12 * max(np.linalg.norm(Wc), 1e-300)) < n:
        raise ValueError("(Phi, Gamma) restricted to the actuated inputs is not controllable: poles cannot be placed")
    if len(keep) == 1:
        L_keep = np.asarray(acker(Phi, G, poles))
    else:
        import scipy.signal  # 1-2 s to import: only here, for MIMO placement

        L_keep = scipy.signal.place_poles(Phi, G, poles, method=method).gain_matrix
    L = np.zeros((m, n))
    L[keep] = L_keep
    return L


def dlqr(A, B, Q, R):
    """Discrete linear-quadratic regulator, as python-control's ``dlqr``: the state feedback ``u = -K x`` that
    minimises ``sum_k x_k' Q x_k + u_k' R u_k`` for ``x_{k+1} = A x_k + B u_k``.

    Args:
      A: (n, n).  B: (n, m).  Q: (n, n) positive semidefinite.  R: (m, m) positive definite.

    Returns:
      ``(K, S, E)``: the (m, n) gain ``K = (R + B'SB)^{-1} B'SA`` (a state feedback, ``L`` in jaxobs' own
      notation), the solution ``S`` of :func:`jaxobs.matrix_equations.dare` ``(A, B, Q, R)`` and the (n,) closed-loop
      eigenvalues ``E`` of ``A - B K``.

    Differentiable (implicit-function rule through the DARE). Eagerly, a DARE without a stabilising solution
    raises ``ValueError`` with the reason (e.g. ``(A, B)`` not stabilisable); under ``jit`` the gain and ``S``
    are NaN then (the flag itself is ``jaxobs.dare(A, B, Q, R).converged``).

    Example:
      >>> import numpy as np
      >>> K, S, E = dlqr(np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]]), np.eye(2), np.eye(1))
      >>> K.shape, bool(np.all(np.abs(E) < 1))
      ((1, 2), True)
    """
    A, B, Q, R = _checks.float_arrays(A=A, B=B, Q=Q, R=R)
    sol = dare(A, B, Q, R)
    require_converged(sol, A, B, Q, R, what="dlqr's DARE")
    R = jnp.asarray(R, sol.X.dtype)
    K = solve_spd(symmetrize(B.T @ sol.X @ B + R), B.T @ sol.X @ A)
    K, S = (jnp.where(sol.converged, M, jnp.nan) for M in (K, sol.X))
    return K, S, jnp.linalg.eigvals(A - B @ K)


def _estimation_model(A, G, C, QN, RN):
    """``(A, G, C, QN, RN)`` as 2-D arrays of one floating dtype, their shapes checked (``ValueError`` naming the
    argument)."""
    A, G, C, QN, RN = (jnp.atleast_2d(M) for M in _checks.float_arrays(A=A, G=G, C=C, QN=QN, RN=RN))
    n = A.shape[-1]
    _checks.matrix("A", A, shape=(n, n), square=True)
    _checks.matrix("G", G, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    _checks.covariance("QN", QN, definite=False, size=G.shape[-1])
    _checks.covariance("RN", RN, definite=True, size=C.shape[-2])
    return A, G, C, QN, RN


def dlqe(A, G, C, QN, RN):
    """Steady-state Kalman estimator (linear-quadratic estimator), as python-control's ``dlqe``, for
    ``x_{k+1} = A x_k + B u_k + G w_k``, ``y_k = C x_k + v_k``, ``E[w w'] = QN``, ``E[v v'] = RN``.

    Args:
      A: (n, n).  G: (n, q) process-noise input.  C: (p, n).  QN: (q, q) positive semidefinite.
      RN: (p, p) positive definite.

    Returns:
      ``(K, P, E)``: the (n, p) gain of the one-step predictor ``x_{k+1|k} = A x_{k|k-1} + B u_k + K (y_k -
      C x_{k|k-1})`` (python-control names it ``L``), ``K = A P C' (C P C' + RN)^{-1}``; the a-priori covariance
      ``P`` (the filter DARE, :func:`jaxobs.matrix_equations.filter_dare`); the (n,) eigenvalues ``E`` of ``A - K C``.
      The gain of the filtered (a-posteriori) form that jaxobs' Kalman filter uses is
      ``jaxobs.kalman_steps.kalman_gain(P, C, RN)``.

    Eagerly, raises ``ValueError`` with the reason when the DARE has no stabilising solution; under ``jit`` the
    gain and ``P`` are NaN then.

    Example:
      >>> import numpy as np
      >>> K, P, E = dlqe(np.array([[1.0, 0.1], [0.0, 1.0]]), np.eye(2), np.array([[1.0, 0.0]]), 0.01 * np.eye(2),
      ...                np.eye(1))
      >>> K.shape, bool(np.all(np.abs(E) < 1))
      ((2, 1), True)
    """
    A, G, C, QN, RN = _estimation_model(A, G, C, QN, RN)
    sol = filter_dare(A, C, G @ QN @ G.T, RN, what="dlqe's DARE")
    CP = C @ sol.X
    K = solve_spd(symmetrize(CP @ C.T + RN), CP @ A.T).T
    K, P = (jnp.where(sol.converged, M, jnp.nan) for M in (K, sol.X))
    return K, P, jnp.linalg.eigvals(A - K @ C)


def lqr(A, B, Q, R):
    """Continuous linear-quadratic regulator, as python-control's ``lqr``: the state feedback ``u = -K x`` that
    minimises ``int x' Q x + u' R u dt`` for ``x' = A x + B u``.

    Args:
      A: (n, n).  B: (n, m).  Q: (n, n) positive semidefinite.  R: (m, m) positive definite.

    Returns:
      ``(K, S, E)``: the (m, n) gain ``K = R^{-1} B' S`` (a state feedback, ``L`` in jaxobs' own notation), the
      solution ``S`` of :func:`jaxobs.matrix_equations.care` ``(A, B, Q, R)`` and the (n,) closed-loop eigenvalues
      ``E`` of ``A - B K``.

    Differentiable (implicit-function rule through the CARE). Eagerly, a CARE without a stabilising solution raises
    ``ValueError`` with the reason (e.g. ``(A, B)`` not stabilisable); under ``jit`` the gain and ``S`` are NaN then
    (the flag itself is ``jaxobs.matrix_equations.care(A, B, Q, R).converged``).

    Example:
      >>> import numpy as np
      >>> K, S, E = lqr(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0]]), np.eye(2), np.eye(1))
      >>> [round(float(k), 4) for k in K[0]], bool(np.all(E.real < 0))
      ([1.0, 1.7321], True)
    """
    A, B, Q, R = _checks.float_arrays(A=A, B=B, Q=Q, R=R)
    sol = care(A, B, Q, R)
    require_care_converged(sol, A, B, Q, what="lqr's CARE")
    K = solve_spd(symmetrize(R), B.T @ sol.X)
    K, S = (jnp.where(sol.converged, M, jnp.nan) for M in (K, sol.X))
    return K, S, jnp.linalg.eigvals(A - B @ K)


def lqe(A, G, C, QN, RN):
    """Steady-state Kalman-Bucy filter (linear-quadratic estimator), as python-control's ``lqe``, for
    ``x' = A x + B u + G w``, ``y = C x + v`` with white noises of intensities ``E[w w'] = QN``, ``E[v v'] = RN``
    (Grip 2010 eq. 1.7 with its stationary gain).

    Args:
      A: (n, n).  G: (n, q) process-noise input.  C: (p, n).  QN: (q, q) positive semidefinite.
      RN: (p, p) positive definite.

    Returns:
      ``(K, P, E)``: the (n, p) observer gain ``K = P C' RN^{-1}`` of ``x_hat' = A x_hat + B u + K (y - C x_hat)``
      (python-control names it ``L``), the steady-state error covariance ``P``, the solution of the filter CARE
      ``A P + P A' - P C' RN^{-1} C P + G QN G' = 0`` (:func:`jaxobs.matrix_equations.care` of ``(A', C')``), and
      the (n,) eigenvalues ``E`` of ``A - K C``.

    Eagerly, raises ``ValueError`` with the reason when the CARE has no stabilising solution (e.g. ``(A, C)`` not
    detectable); under ``jit`` the gain and ``P`` are NaN then.

    Example:
      >>> import numpy as np
      >>> K, P, E = lqe(np.array([[0.0, 1.0], [0.0, 0.0]]), np.eye(2), np.array([[1.0, 0.0]]), np.eye(2), np.eye(1))
      >>> K.shape, bool(np.all(E.real < 0))
      ((2, 1), True)
    """
    A, G, C, QN, RN = _estimation_model(A, G, C, QN, RN)
    W = symmetrize(G @ QN @ G.T)
    sol = care(A.T, C.T, W, RN)
    require_care_converged(sol, A.T, C.T, W, what="lqe's CARE", estimation=True)
    K = solve_spd(symmetrize(RN), C @ sol.X).T
    K, P = (jnp.where(sol.converged, M, jnp.nan) for M in (K, sol.X))
    return K, P, jnp.linalg.eigvals(A - K @ C)


@_checks.design_time()
def is_detectable(A, C, *, discrete: bool = False) -> bool:
    """Whether ``(C, A)`` is detectable, by the PBH test (Grip 2010 §1.1.1): every eigenvalue ``lam`` of ``A`` with
    ``rank [A - lam I; C] < n`` (an unobservable mode) is stable, ``Re lam < 0`` (``|lam| < 1`` when ``discrete``).
    Exactly then an observer gain ``K`` with ``A - K C`` stable exists. Design time (NumPy, concrete arrays).

    Args:
      A: (n, n) state matrix.  C: (p, n) output matrix.
      discrete: test against the unit circle instead of the imaginary axis.

    Example:
      >>> is_detectable([[1.0, 0.0], [0.0, -1.0]], [[1.0, 0.0]]), is_detectable([[1.0, 0.0], [0.0, -1.0]], [[0.0, 1.0]])
      (True, False)
    """
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    _checks.matrix("A", A, square=True)
    _checks.matrix("C", C, shape=(None, A.shape[-1]))
    unstable = (lambda lam: abs(lam) >= 1) if discrete else (lambda lam: lam.real >= 0)
    return not unobservable_modes(A, C, unstable)


def critically_damped_poles(h: float, tau_c, n_fast: int):
    """A double pole at ``exp(-h / tau_c)`` plus ``n_fast`` poles at ``z = 0`` (Cortesão 2006, §7.2: critically
    damped response with time constant ``tau_c``, dead-time poles at the origin). Returns ``(2 + n_fast,)``."""
    _checks.positive_scalar("h", h)
    _checks.positive_scalar("tau_c", tau_c)
    n_fast = _checks.count("n_fast", n_fast)
    tau_c = jnp.asarray(tau_c)
    _checks.shape("tau_c", tau_c, (), "one time constant")
    z = jnp.exp(-h / tau_c.astype(_checks.float_dtype(tau_c=tau_c)))
    return jnp.concatenate([jnp.stack([z, z]), jnp.zeros((n_fast,), z.dtype)])


def critically_damped_gain(plant: StateSpace, tau_c):
    """State feedback ``L_r`` (1, n) for a discrete single-input ``plant`` whose first two states are the slow
    dynamics and the others dead-time slots: a critically damped double pole with time constant ``tau_c`` and
    the remaining poles at ``z = 0`` (Cortesão 2006 §7.2, eq. 83), by :func:`acker`.

    Example:
      >>> from jaxobs.plants import force_plant
      >>> L_r = critically_damped_gain(force_plant(3.0, 0.032, 0.008, 0.040), tau_c=0.32)
      >>> [round(float(v), 4) for v in L_r[0, :3]]
      [0.1148, -0.0717, -0.0615]
    """
    plant = StateSpace.check(plant, "plant")
    if not plant.is_discrete:
        raise ValueError("plant must be discrete (use jaxobs.lti.c2d first)")
    if plant.n_states < 2:
        raise ValueError(f"plant must have at least the two slow states, got {plant.n_states} states")
    return acker(plant.A, plant.B, critically_damped_poles(plant.dt, tau_c, plant.n_states - 2))


def reference_gain(plant: StateSpace, L):
    """Reference pre-gain ``N`` (m, p) of a discrete ``plant`` for unit DC gain from the reference (in output units)
    to the output under the state feedback ``u = N r - L x`` (``L`` (m, n)):
    ``N = [C (I - Phi + Gamma L)^{-1} Gamma]^{-1}`` (needs as many inputs as outputs and an invertible closed-loop
    DC gain). Use it as :class:`~jaxobs.observers.feedback.FeedbackParams` ``N``.

    Example:
      >>> from jaxobs.plants import force_plant
      >>> plant = force_plant(3.0, 0.032, 0.008, 0.040)
      >>> L_r = critically_damped_gain(plant, tau_c=0.32)
      >>> bool(jnp.allclose(reference_gain(plant, L_r), L_r[0, 0]))   # the integrating plant: N = L_1
      True
    """
    plant = StateSpace.check(plant, "plant")
    if not plant.is_discrete:
        raise ValueError("plant must be discrete (use jaxobs.lti.c2d first)")
    (L,) = _checks.float_arrays(L=L)
    L = jnp.atleast_2d(L)
    _checks.matrix("L", L, shape=(plant.n_inputs, plant.n_states))
    closed = StateSpace(plant.A - plant.B @ L, plant.B, plant.C, plant.D, plant.dt)
    return dc_compensation(jnp.eye(plant.n_outputs, dtype=L.dtype), dcgain(closed))


def dc_compensation(dc_target, dc_closed_loop):
    """Reference pre-amplification ``L_c = DC_closed^{-1} DC_target`` (Cortesão 2006, eq. 102-104):
    ``dc_closed_loop`` (m, m), ``dc_target`` (m, k) (scalars for one channel)."""
    T, M = (jnp.atleast_2d(X) for X in _checks.float_arrays(dc_target=dc_target, dc_closed_loop=dc_closed_loop))
    _checks.matrix("dc_closed_loop", M, square=True)
    _checks.matrix("dc_target", T, shape=(M.shape[0], None))
    if _checks.is_concrete(M) and np.linalg.cond(np.asarray(M)) > 1e12:
        raise ValueError("dc_closed_loop is singular: the closed loop has no invertible DC gain to compensate")
    return jnp.linalg.solve(M, T)
