"""The modified high-gain observer of Grip 2010, ch. 6: an extended-state observer with a model-based perturbation.

For ``x' = A x + B u + E phi``, ``y = C x`` with the perturbation ``phi = g(v, x, theta)``, ``v = col(u, y)``, the
observer (6.3) estimates ``x``, ``phi`` and, with an update law of :mod:`jaxobs.adaptive`, ``theta``.
:func:`hgo_gains` designs the gains ``K(eps)`` (section 6.3, through :mod:`jaxobs.scb`; design time, NumPy, its
result traceable in ``eps``); :func:`make_hgo` builds the parameters and :data:`hgo_observer` runs it on samples
through :mod:`jaxobs.observers.continuous`. The equations: docs/theory/adaptive.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks, adaptive
from jaxobs import scb as _scb
from jaxobs.design import place
from jaxobs.observers.base import Estimator, EstimatorInputs
from jaxobs.observers.continuous import ContinuousObserverParams, continuous_observer

__all__ = [
    "HGOGains",
    "hgo_gains",
    "smooth_abs",
    "HGOParams",
    "HGOOutputs",
    "make_hgo",
    "hgo_observer",
]


# --------------------------------------------------------------------------------------------------------------
# Gain design (section 6.3)


@dataclasses.dataclass(frozen=True)
class HGOGains:
    """Result of :func:`hgo_gains`.

    Attributes:
      K: (n + k, p) the gain ``[K_x; K_phi]`` at ``eps`` ((n, p) ``K_x`` alone when ``extended=False``).
      terms: (q + 1, n + k, p) with ``K(eps) = sum_i terms[i] eps^-i`` (``q`` the longest chain); see :meth:`at`.
      eps: float, the ``eps`` of ``K``.
      poles: (n + k,) complex, the eigenvalues of the error dynamics ``A_e - K C_e`` of the (true) system given to
        :func:`hgo_gains`.
      zeros: (n_a,) complex, the invariant zeros of the design error system (where ``n_a`` of the poles sit when
        the design and the true system agree, Remark 6.2).
      dims: ``(n_a, n_b, n_q)``, the dimensions of the zero dynamics, the x_b subsystem and the chains.
      chain_lengths: tuple of ints, the lengths of the integrator chains, in the order ``poles`` were assigned to
        them.
      system: the :class:`jaxobs.scb.SCB` of the design error system, as float arrays.
    """

    K: np.ndarray
    terms: np.ndarray
    eps: float
    poles: np.ndarray
    zeros: np.ndarray
    dims: tuple[int, int, int]
    chain_lengths: tuple[int, ...]
    system: _scb.SCB

    def at(self, eps) -> jax.Array:
        """``K(eps)`` (the shape of :attr:`K`) for a scalar ``0 < eps <= 1``, traced or not (``jit``/``grad`` in
        ``eps``). A concrete ``eps`` outside ``(0, 1]`` (or NaN) raises ``ValueError``; a traced one gives NaN
        gains."""
        _check_eps(eps, hint="")
        terms = jnp.asarray(self.terms, jnp.result_type(eps, float))
        eps = jnp.asarray(eps, terms.dtype)
        powers = eps ** -jnp.arange(terms.shape[0], dtype=terms.dtype)
        return jnp.where((eps > 0) & (eps <= 1), jnp.tensordot(powers, terms, axes=1), jnp.nan)


def _check_eps(eps, hint: str) -> None:
    """``eps`` must be a real scalar in ``(0, 1]`` (a bool is refused); its value is checked where concrete."""
    if eps is None or isinstance(eps, (bool, np.bool_)) or np.ndim(eps) != 0:
        raise ValueError(f"eps must be a number in (0, 1], got {eps!r}{hint}")
    dtype = _checks.float_dtype(eps=eps)
    if _checks.is_concrete(eps) and not 0 < float(jnp.asarray(eps, dtype)) <= 1:
        raise ValueError(f"eps must be a number in (0, 1], got {eps!r}{hint}")


def _real_matrix(name, value, shape):
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real numeric matrix, got {type(value).__name__}") from None
    _checks.matrix(name, a, shape=shape)
    return a


def _triple(A, E, C, prefix=""):
    A = _real_matrix(f"{prefix}A", A, (None, None))
    if A.shape[0] != A.shape[1]:
        raise ValueError(f"{prefix}A must be square, got shape {A.shape}")
    n = A.shape[0]
    E = _real_matrix(f"{prefix}E", E, (n, None))
    C = _real_matrix(f"{prefix}C", C, (None, n))
    if np.linalg.matrix_rank(E) < E.shape[1]:
        raise ValueError(f"{prefix}E must have full column rank {E.shape[1]} (remove dependent perturbations first)")
    if np.linalg.matrix_rank(C) < C.shape[0]:
        raise ValueError(f"{prefix}C must have full row rank {C.shape[0]} (remove dependent outputs first)")
    return A, E, C


def _error_system(A, E, C, extended):
    """(A_e, B_e, C_e) of the error dynamics (6.4) with K = 0 (input d, output y), or of x' = A x + E g."""
    if not extended:
        return A, E, C
    n, k = E.shape
    Ae = np.block([[A, E], [np.zeros((k, n)), np.zeros((k, k))]])
    return Ae, np.vstack([np.zeros((n, k)), np.eye(k)]), np.hstack([C, np.zeros((C.shape[0], k))])


def _pole_groups(name, poles, sizes):
    """``poles`` split into conjugation-closed groups of ``sizes`` (ValueError naming ``name`` otherwise)."""
    total = int(sum(sizes))
    try:
        p = np.atleast_1d(np.asarray(poles, dtype=complex))
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a vector of numbers, got {type(poles).__name__}") from None
    if p.ndim != 1 or p.size != total:
        raise ValueError(f"{name} must have {total} entries (groups of {tuple(sizes)}), got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be finite, got {p.tolist()}")
    groups, start = [], 0
    for size in sizes:
        group = p[start : start + size]
        start += size
        scale = max(1.0, float(np.max(np.abs(group)))) if size else 1.0
        if size and not np.allclose(np.sort_complex(group), np.sort_complex(np.conj(group)), rtol=0, atol=1e-9 * scale):
            raise ValueError(
                f"{name}: complex poles must come in conjugate pairs within each group {tuple(sizes)}, got "
                f"{group.tolist()}"
            )
        groups.append(group)
    return groups


@_checks.design_time(alternative="the gains K as arrays (make_hgo takes them)")
def hgo_gains(A, E, C, poles, eps=1.0, *, poles_b=None, extended: bool = True, design=None,
              corrected: bool = True, numeric: bool = False) -> HGOGains:  # fmt: skip
    """Gains ``K(eps) = [K_x(eps); K_phi(eps)]`` of the modified high-gain observer (6.3) (Grip 2010, section 6.3).

    The error dynamics (6.4) with input ``d`` and output ``y`` (``A_e = [[A, E], [0, 0]]``, ``B_e = [0; I_k]``,
    ``C_e = [C, 0]``) are put in the special coordinate basis (:func:`jaxobs.scb.scb`, exact arithmetic by default)
    ``chi = col(chi_a, chi_b, chi_q1, ..., chi_qk)``, ``gamma = col(gamma_q, gamma_b)``, and (sections 6.3.1-6.3.2)::

        K_aq = L_aq,  K_ab = L_ab,  K_bq = L_bq,  eig(A_b - K_bb C_b) = poles_b,  K_qjb = 0,
        K_qjq(eps) = [0, col(Kbar_qj1 / eps, ..., Kbar_qjn / eps^n), 0] + L_qjq     (author's corrigendum)

    where ``Kbar_qj`` places the poles of ``H_j = A_qj - Kbar_qj C_qj`` (an integrator chain of length ``n =
    n_qj``) and ``L_qjq`` is the output injection of the chain's upper rows (the entries of a chain's last row are
    the ``D_qj`` couplings, matched with the input, and are not cancelled). Then ``K = Lambda_1 K_scb Lambda_2^-1``
    (6.8). As ``eps -> 0``, ``n_a`` poles sit at the invariant zeros, ``n_b`` at ``poles_b`` and ``eps`` times the
    ``n_q`` others tend to ``eig(H_j)`` (Remark 6.2).

    Args:
      A: (n, n), E: (n, k), C: (p, n): the plant ``x' = A x + B u + E phi``, ``y = C x`` (finite floats);
        ``(C, A, E)`` must be left-invertible and minimum-phase (Assumption 6.1), else ``ValueError`` naming which
        (with the offending zeros).
      poles: (n_q,) the poles of the ``H_j``, the first ``n_q1`` for the first chain of ``chain_lengths`` and so
        on (each group closed under conjugation); ``n_q = sum(chain_lengths)``.
      eps: the high-gain parameter, ``0 < eps <= 1``.
      poles_b: (n_b,) the eigenvalues of ``A_b - K_bb C_b``; required iff the error system has an x_b subsystem.
      extended: design the extended observer (6.3) (True) or the state observer of the cascade redesign, section
        6.6 (False: the SCB of ``x' = A x + E g``, input ``g``, and ``K`` is (n, p)).
      design: ``(A0, E0, C0)``: design on these (unperturbed) matrices instead, section 6.7.1 (e.g. a small
        parameter set to zero); ``poles`` of the result are still those of ``(A, E, C)``.
      corrected: the corrigendum's ``K_qjq`` (True) or the one printed in section 6.3.2, with powers
        ``eps^(nbar - n_qj + i)`` (False; wrong for chains of different lengths, kept to show it).
      numeric: floating-point SCB (rank decisions by SVD, :func:`jaxobs.scb.scb`) instead of exact fractions.

    Returns:
      :class:`HGOGains`.

    Example: the DC motor with LuGre friction of Grip 2010, section 6.8 (design system sigma_1 = 0).

      >>> import numpy as np
      >>> J, s0, a2 = 0.0023, 260.0, 0.176
      >>> A = [[0, 1, 0], [0, -a2 / J, -s0 / J], [0, 1, 0]]
      >>> gains = hgo_gains(A, [[0], [0], [-1]], [[1, 0, 0]], [-1 + 0.2j, -1 - 0.2j, -2 + 0.2j, -2 - 0.2j])
      >>> np.round(gains.K[:, 0], 2).tolist()
      [6.0, 13.08, -0.01, 13.09]
    """
    A, E, C = _triple(A, E, C)
    A0, E0, C0 = (A, E, C) if design is None else _design_triple(design, (A.shape, E.shape, C.shape))
    hint = " (for a traced eps use HGOGains.at)"
    if not _checks.is_concrete(eps):
        raise ValueError(f"eps must be a concrete number in (0, 1]{hint}, got a traced value")
    _check_eps(eps, hint)
    eps = float(eps)
    extended, corrected = _checks.boolean("extended", extended), _checks.boolean("corrected", corrected)
    numeric = _checks.boolean("numeric", numeric)
    triple = "(C, A, E)" if design is None else "the design triple (C0, A0, E0)"
    s, zeros = _assumption_6_1(_scb.scb(*_error_system(A0, E0, C0, extended), numeric=numeric), triple)
    f = _scb.scb_arrays(s)
    n_a, n_b, _, n_q = f.dims
    chains = f.chain_lengths
    terms = _scb_gain_terms(f, _pole_groups("poles", poles, chains), poles_b, corrected)
    K_terms = np.einsum("ij,qjk,kl->qil", f.state_transform, terms, np.linalg.inv(f.output_transform))
    K = np.tensordot(eps ** -np.arange(K_terms.shape[0], dtype=float), K_terms, axes=1)
    Ae, _, Ce = _error_system(A, E, C, extended)
    return HGOGains(
        K=K,
        terms=K_terms,
        eps=eps,
        poles=np.linalg.eigvals(Ae - K @ Ce),
        zeros=zeros,
        dims=(n_a, n_b, n_q),
        chain_lengths=chains,
        system=f,
    )


def _design_triple(design, shapes: tuple) -> tuple:
    """``(A0, E0, C0)`` of ``design`` (section 6.7.1), checked: three matrices of the plant's ``shapes``."""
    if not (isinstance(design, tuple | list) and len(design) == 3):
        raise ValueError(f"design must be a triple (A0, E0, C0), got {type(design).__name__}")
    A0, E0, C0 = _triple(*design, prefix="design ")
    if (A0.shape, E0.shape, C0.shape) != shapes:
        raise ValueError(
            f"design: the shapes {(A0.shape, E0.shape, C0.shape)} of (A0, E0, C0) must equal those of (A, E, C), "
            f"{shapes}"
        )
    return A0, E0, C0


def _assumption_6_1(s, triple: str) -> tuple:
    """``(s, invariant zeros)`` of the error system's SCB ``s``; ``ValueError`` naming ``triple`` unless it is
    left-invertible and minimum-phase (Assumption 6.1)."""
    if not _scb.is_left_invertible(s):
        raise ValueError(f"{triple} must be left-invertible (Assumption 6.1), but its SCB has n_c = {s.dims[2]}")
    zeros = np.asarray([complex(z) for z in _scb.invariant_zeros(s)], dtype=complex)
    unstable = zeros[np.real(zeros) >= 0]
    if unstable.size:
        raise ValueError(
            f"{triple} must be minimum-phase (Assumption 6.1), but has the invariant zeros {unstable.tolist()} in the "
            "closed right half-plane"
        )
    return s, zeros


def _scb_gain_terms(f: _scb.SCB, groups, poles_b, corrected: bool) -> np.ndarray:
    """``K_scb(eps) = sum_i terms[i] eps^-i`` in SCB coordinates (sections 6.3.1-6.3.2)."""
    n_a, n_b, _, n_q = f.dims
    chains = f.chain_lengths
    k = len(chains)
    n_e, p = f.A.shape[0], f.C.shape[0]
    a, b, d = slice(0, n_a), slice(n_a, n_a + n_b), slice(n_a + n_b, n_e)
    C_d = f.C[:k, d]  # y_scb = col(y_d, y_b): y_d the first states of the chains
    tops = np.concatenate([[0], np.cumsum(chains)[:-1]]).astype(int)
    lasts = tops + np.asarray(chains, dtype=int) - 1
    shift = np.zeros((n_q, n_q))
    for top, q in zip(tops, chains, strict=True):
        shift[top : top + q - 1, top + 1 : top + q] = np.eye(q - 1)
    qbar = max(chains, default=0)
    terms = np.zeros((qbar + 1, n_e, p))
    # output injections L: they cancel the output terms of x_a, x_b and the upper rows of each chain
    bd = slice(n_a, n_e)
    terms[0, a, :] = f.A[a, bd] @ np.linalg.pinv(f.C[:, bd])
    terms[0, b, :k] = f.A[b, d] @ np.linalg.pinv(C_d)
    upper = np.setdiff1d(np.arange(n_q), lasts)
    terms[0, n_a + n_b + upper, :k] = (f.A[d, d] - shift)[upper] @ np.linalg.pinv(C_d)
    if n_b:
        if poles_b is None:
            raise ValueError(f"poles_b is required: the error system has an x_b subsystem of dimension {n_b}")
        (pb,) = _pole_groups("poles_b", poles_b, (n_b,))
        terms[0, b, k:] = place(f.A[b, b].T, f.C[k:, b].T, pb).T
    elif poles_b is not None and np.size(poles_b):
        raise ValueError(f"poles_b must be empty: the error system has no x_b subsystem, got {np.size(poles_b)} poles")
    for j, (top, q, group) in enumerate(zip(tops, chains, groups, strict=True)):
        coeffs = np.real(np.poly(group))[1:]  # Kbar_qj: H_j = A_qj - Kbar_qj C_qj has the poles ``group``
        offset = 0 if corrected else qbar - q
        for i in range(q):
            terms[i + 1 + offset, n_a + n_b + top + i, j] += coeffs[i]
    return terms


# --------------------------------------------------------------------------------------------------------------
# The smooth absolute value of section 6.8


def smooth_abs(w, kappa):
    """The C^1 absolute value of Grip 2010, section 6.8: ``w^2 / (2 kappa) + kappa / 2`` on ``[-kappa, kappa]``,
    ``|w|`` outside (value and slope continuous at ``+-kappa``; ``>= kappa / 2 > 0``).

    Args:
      w: array.  kappa: positive half-width of the quadratic piece.

    Example:
      >>> round(float(smooth_abs(0.0, 0.1)), 6), round(float(smooth_abs(-0.3, 0.1)), 6)
      (0.05, 0.3)
    """
    w = jnp.asarray(w, _checks.float_dtype(w=w, kappa=kappa))
    _checks.positive_scalar("kappa", kappa)
    inside = jnp.abs(w) <= kappa
    return jnp.where(inside, w**2 / (2 * kappa) + kappa / 2, jnp.abs(jnp.where(inside, kappa, w)))


# --------------------------------------------------------------------------------------------------------------
# The observer (6.3) as a sampled estimator


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class HGOParams:
    """The modified high-gain observer (6.3); build it with :func:`make_hgo`.

    Attributes:
      A: (n, n).  B: (n, m).  E: (n, k).  C: (p, n): the plant matrices.
      K: (n + k, p) the gain ``[K_x; K_phi]`` (:func:`hgo_gains`).
      g: ``g(v, x, theta) -> (k,)`` with ``v = col(u, y)``, a ``Partial``.
      law: the update law, called as ``law(g, (v, x_hat), phi_hat, theta_hat) -> (n_theta,)``
        (:class:`~jaxobs.adaptive.InversionLaw`, :class:`~jaxobs.adaptive.PerturbationGradientLaw`,
        :class:`~jaxobs.adaptive.CustomLaw`), or None: ``theta_hat`` stays at ``theta0``.
      x0: (n,).  z0: (k,).  theta0: (n_theta,): the initial ``x_hat``, ``z`` and ``theta_hat``.
      K2: (n, p) the gain of the cascaded state observer of section 6.6 (``hgo_gains(..., extended=False)``),
        or an (n, 0) array for none.
      g2: the perturbation model of the cascaded observer, a ``Partial`` (``g`` unless another was given).
      dt: () sample period.  t0: () time of the first sample.
      substeps: static RK4 (or Euler) steps per sample.  method: static ``"rk4"`` or ``"euler"``.
    """

    A: jax.Array
    B: jax.Array
    E: jax.Array
    C: jax.Array
    K: jax.Array
    g: Callable
    law: Callable | None
    x0: jax.Array
    z0: jax.Array
    theta0: jax.Array
    K2: jax.Array
    g2: Callable
    dt: jax.Array
    t0: jax.Array
    substeps: int = dataclasses.field(default=1, metadata=dict(static=True))
    method: str = dataclasses.field(default="rk4", metadata=dict(static=True))


class HGOOutputs(NamedTuple):
    """Per-sample outputs of :data:`hgo_observer`.

    Attributes:
      x: (n,) ``x_hat(t_k)``.
      phi: (k,) ``phi_hat(t_k) = g(v, x_hat, theta_hat) + z``, ``v`` the ``(u, y)`` held over the last interval.
      theta: (n_theta,) ``theta_hat(t_k)``.
      x2: (n,) the cascaded state observer of section 6.6 (``x_hat`` when there is none).
      innovation: (p,) ``y_k - C x_hat(t_k)`` (0 for missing components).
    """

    x: jax.Array
    phi: jax.Array
    theta: jax.Array
    x2: jax.Array
    innovation: jax.Array


def _split(params: HGOParams, xi):
    """``(x_hat, z, theta_hat, x2)`` from the stacked state (``x2`` empty without a cascade)."""
    n, k = params.E.shape
    n_theta = params.theta0.shape[0]
    return xi[:n], xi[n : n + k], xi[n + k : n + k + n_theta], xi[n + k + n_theta :]


def _cascade(params: HGOParams) -> bool:
    return params.K2.shape[1] > 0


def _rhs(params: HGOParams, xi, u, y, t):
    """d/dt col(x_hat, z, theta_hat, x2), (6.3a)-(6.3b), (6.9) and the cascade of section 6.6."""
    n = params.A.shape[0]
    x_hat, z, theta_hat, x2 = _split(params, xi)
    v = jnp.concatenate([u, y])
    innovation = y - params.C @ x_hat
    phi_hat = params.g(v, x_hat, theta_hat) + z
    if params.law is None:
        theta_dot = jnp.zeros_like(theta_hat)
    else:
        theta_dot = params.law(params.g, (v, x_hat), phi_hat, theta_hat)
    Kx_innov, Kphi_innov = params.K[:n] @ innovation, params.K[n:] @ innovation
    # dg/dx K_x innovation + dg/dtheta theta_dot in one forward-mode product
    _, along = jax.jvp(lambda x, th: params.g(v, x, th), (x_hat, theta_hat), (Kx_innov, theta_dot))
    x_dot = params.A @ x_hat + params.B @ u + params.E @ phi_hat + Kx_innov
    if _cascade(params):  # x2' = A x2 + B u + E g2(v, x2, theta_hat) + K2 (y - C x2)
        x2 = params.A @ x2 + params.B @ u + params.E @ params.g2(v, x2, theta_hat) + params.K2 @ (y - params.C @ x2)
    return jnp.concatenate([x_dot, Kphi_innov - along, theta_dot, x2])


def _output(C, n, xi, u):
    del u  # y = C x: no feedthrough
    return C @ xi[:n]


def _continuous(params: HGOParams) -> ContinuousObserverParams:
    x0 = jnp.concatenate([params.x0, params.z0, params.theta0] + ([params.x0] if _cascade(params) else []))
    F = jax.tree_util.Partial(_rhs, params)
    h = jax.tree_util.Partial(_output, params.C, params.A.shape[0])
    return ContinuousObserverParams(F, h, x0, params.dt, params.t0, params.B.shape[1], params.substeps, params.method)


def _check_models(g, g2, law, v, x0, z0, theta0):
    """``(g, g2)`` (``g2`` defaulting to ``g``) checked to return ``phi`` (k,) at ``(v, x0, theta0)``, and ``law``
    (if any) to return one rate per entry of ``theta0``; ``ValueError`` naming the function otherwise."""
    k = z0.shape[0]
    g = _checks.function("g", g)
    _checks.returns("g(v, x, theta)", g, (v, x0, theta0), (k,), f"phi, one entry per column of E ({k})")
    if law is not None:
        adaptive.check_law(law, theta0)
        _checks.returns(
            "law(g, (v, x_hat), phi_hat, theta_hat)", lambda *a: law(g, a[:2], *a[2:]), (v, x0, z0, theta0),
            theta0.shape, "theta_hat_dot, one entry per entry of theta0",
        )  # fmt: skip
    g2 = g if g2 is None else _checks.function("g2", g2)
    _checks.returns("g2(v, x, theta)", g2, (v, x0, theta0), (k,), f"phi, one entry per column of E ({k})")
    return g, g2


def make_hgo(A, B, E, C, K, g, *, law=None, x0=None, z0=None, theta0=(), K2=None, g2=None, dt, t0=0.0,
             substeps: int = 1, method: str = "rk4") -> HGOParams:  # fmt: skip
    """Build and check :class:`HGOParams` of the modified high-gain observer (6.3) (Grip 2010, ch. 6).

    Args:
      A: (n, n), B: (n, m), E: (n, k), C: (p, n): ``x' = A x + B u + E phi``, ``y = C x`` (B may be (n, 0)).
      K: (n + k, p) the gain ``[K_x(eps); K_phi(eps)]`` (:func:`hgo_gains`, ``HGOGains.K`` or ``.at(eps)``).
      g: the perturbation model ``g(v, x, theta) -> (k,)``, ``v = col(u, y)`` (m + p,), differentiable.
      law: the parameter update law, a law object of :mod:`jaxobs.adaptive` called as ``law(g, (v, x_hat),
        phi_hat, theta_hat) -> (n_theta,)`` (:class:`~jaxobs.adaptive.InversionLaw` for Props. 6.1-6.2,
        :class:`~jaxobs.adaptive.PerturbationGradientLaw` for Props. 6.3-6.4); None keeps ``theta_hat = theta0``
        (a known theta).
      x0: (n,) initial ``x_hat`` (zeros if None).  z0: (k,) initial ``z`` (zeros if None).
      theta0: (n_theta,) initial ``theta_hat`` (inside the projection set of ``law``, if any).
      K2: (n, p) gain of the cascaded state observer of section 6.6, ``x2' = A x2 + B u + E g(v, x2, theta_hat)
        + K2 (y - C x2)`` with ``theta_hat`` from (6.3) (``hgo_gains(..., extended=False)``; output ``x2``, started at
        ``x0``); None for none (``x2`` then repeats ``x_hat``).
      g2: the cascaded observer's perturbation model, ``g`` if None (section 6.8 gives it the exact ``|omega|``,
        as it needs only g, not its derivative, to be Lipschitz).
      dt: finite sample period (> 0).  t0: finite time of the first sample.
      substeps: fixed steps per sample (>= 1).  method: ``"rk4"`` or ``"euler"``.

    Shapes are checked at trace time; values (finite matrices and initial values, ``dt > 0``, the law's gain,
    ``epsilon`` and projection set) where concrete, ``ValueError`` naming the argument.

    Example: the extended-state observer of a double integrator with an unknown constant force (g = 0).

      >>> import jax.numpy as jnp
      >>> import jaxobs as jo
      >>> from jaxobs.observers import hgo
      >>> A, E, C = [[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]]
      >>> gains = hgo.hgo_gains(A, E, C, [-2.0, -2.0, -2.0], 0.5)
      >>> params = hgo.make_hgo(A, [[0.0], [1.0]], E, C, gains.K, lambda v, x, th: jnp.zeros(1), dt=0.01)
      >>> t = 0.01 * jnp.arange(600)
      >>> y = (0.5 * 0.3 * t**2)[:, None]  # x'' = 0.3
      >>> _, out = jo.run(hgo.hgo_observer, params, jo.EstimatorInputs(y=y, u_prev=jnp.zeros((600, 1))))
      >>> bool(jnp.abs(out.phi[-1, 0] - 0.3) < 1e-2)
      True
    """
    theta = theta0 if jnp.size(jnp.asarray(theta0)) else None
    dtype = _checks.float_dtype(A=A, B=B, E=E, C=C, K=K, x0=x0, z0=z0, theta0=theta, dt=dt, t0=t0)
    A, E, C = (jnp.asarray(M, dtype) for M in (A, E, C))
    _checks.matrix("A", A, square=True)
    n = A.shape[0]
    _checks.matrix("E", E, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    k, p = E.shape[1], C.shape[0]
    B = jnp.asarray(B, dtype)
    B = B.reshape((n, -1)) if B.size == 0 else B
    _checks.matrix("B", B, shape=(n, None))
    K = jnp.asarray(K, dtype)
    _checks.matrix("K", K, shape=(n + k, p))
    m = B.shape[1]
    K2 = jnp.zeros((n, 0), dtype) if K2 is None else jnp.asarray(K2, dtype)
    if K2.shape[1]:
        _checks.matrix("K2", K2, shape=(n, p))
    x0 = jnp.zeros((n,), dtype) if x0 is None else _checks.vector("x0", x0, n, dtype, what="one entry per state")
    z0 = jnp.zeros((k,), dtype) if z0 is None else _checks.vector("z0", z0, k, dtype, what="one per perturbation")
    theta0 = jnp.asarray(theta0, dtype)
    theta0 = jnp.atleast_1d(theta0) if theta0.size else jnp.zeros((0,), dtype)
    _checks.shape("theta0", theta0, (None,), "the initial parameter estimate, a vector")
    _checks.finite("theta0", theta0)
    _checks.positive_scalar("dt", dt)
    _checks.finite("t0", t0)
    g, g2 = _check_models(g, g2, law, jnp.zeros((m + p,), dtype), x0, z0, theta0)
    substeps = _checks.count("substeps", substeps, minimum=1, hint="fixed integration steps per sample")
    if method not in ("rk4", "euler"):
        raise ValueError(f"method must be 'rk4' or 'euler', got {method!r}")
    t0 = jnp.asarray(t0, dtype)
    _checks.shape("t0", t0, (), "a scalar time")
    dt = jnp.asarray(dt, dtype)
    return HGOParams(A, B, E, C, K, g, law, x0, z0, theta0, K2, g2, dt, t0, substeps, method)


_SHAPES = "A (n, n), B (n, m), E (n, k), C (p, n), K (j, p), x0 (n,), z0 (k,), theta0 (t,), K2 (n, r), dt (), t0 ()"


def _init(params: HGOParams):
    _checks.fields("params", params, _SHAPES)
    return continuous_observer.init(_continuous(params))


def _step(params: HGOParams, state, inputs: EstimatorInputs):
    _checks.fields("params", params, _SHAPES)
    m = params.B.shape[1]
    before = state.y  # y_{k-1}, held over the interval now integrated (NaN where missing)
    state, out = continuous_observer.step(_continuous(params), state, inputs)
    x_hat, z, theta_hat, x2 = _split(params, state.x)
    u = jnp.zeros((0,), x_hat.dtype) if inputs.u_prev is None else jnp.reshape(inputs.u_prev, (m,))
    y = jnp.where(jnp.isfinite(before), before, params.C @ x_hat)
    phi_hat = params.g(jnp.concatenate([u, y]), x_hat, theta_hat) + z
    x2 = x2 if _cascade(params) else x_hat
    return state, HGOOutputs(x_hat, phi_hat, theta_hat, x2, out.innovation)


hgo_observer = Estimator(_init, _step)
"""The modified high-gain observer (6.3) as a sampled :class:`~jaxobs.observers.base.Estimator` over
:class:`HGOParams` (run by :mod:`jaxobs.observers.continuous`: ``u_{k-1}``, ``y_{k-1}`` held over ``[t_{k-1},
t_k]``). Inputs: ``EstimatorInputs(y, u_prev)`` of shapes (p,) and (m,). Outputs: :class:`HGOOutputs`."""
