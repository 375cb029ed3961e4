"""Stability of observer-based control with model errors (Cortesão 2006 §6): closed-loop matrices,
spectral radius, the loop transfer function at the plant input, and discrete-time margins.

:func:`closed_loop_matrix` (Theorem 2, eq. 59) and :func:`spectral_radius`, the loop transfer function cut at the
plant input (Theorem 3, eq. 65), and :func:`stability_margins` in python-control's conventions plus the delay
margin, differentiable where the crossover is simple. The ``[x; x_hat]`` coordinates and how they map to the
printed equations: docs/theory/analysis.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.lti import StateSpace
from jaxobs.observers.base import Controller
from jaxobs.observers.feedback import FeedbackParams

__all__ = [
    "loop_transfer",
    "closed_loop_matrix",
    "spectral_radius",
    "frequency_response",
    "Margins",
    "stability_margins",
    "unstructured_mismatch",
]


def _linear_form(controller: Controller, params) -> FeedbackParams:
    if controller.linear is None:
        raise ValueError("controller has no linear form: stability analysis needs a linear fixed-gain controller")
    return controller.linear(params)


def loop_transfer(plant: StateSpace, controller: Controller, params) -> StateSpace:
    """Loop transfer function at the plant input (Cortesão 2006 Theorem 3, eq. 65-69), state ``[x; x_hat]``.

    Args:
      plant: the true discrete plant (any state dimension, ``D = 0``).
      controller: a linear controller with a fixed gain, e.g. an observer-based controller
        (:func:`~jaxobs.observers.feedback.observer_controller`) around a steady-state Kalman filter or AOB
        (its linear form honours the AOB's active-state switch).
      params: the controller's params, built on the nominal model.

    Returns a discrete :class:`StateSpace` from ``u'`` to ``L x_hat``; the loop is closed with ``u' = -L x_hat``
    (negative feedback), so its return ratio is the transfer function itself.
    """
    if not StateSpace.check(plant, "plant").is_discrete:
        raise ValueError("plant must be discrete (dt set; use jaxobs.lti.c2d)")
    lin = _linear_form(controller, params)
    c, L = lin.estimator, lin.L
    Phi, Gamma, C = plant.A, plant.B, plant.C
    n, n_obs = Phi.shape[-1], c.Phi.shape[-1]
    _checks.matrix("Phi_n", c.Phi, shape=(n_obs, n_obs), square=True)
    _checks.matrix("Gamma_n", c.Gamma, shape=(n_obs, Gamma.shape[-1]))
    _checks.matrix("C_n", c.C, shape=(C.shape[-2], n_obs))
    _checks.matrix("K", c.K, shape=(n_obs, C.shape[-2]))
    _checks.matrix("L", L, shape=(Gamma.shape[-1], n_obs))
    observer = (jnp.eye(n_obs, dtype=c.Phi.dtype) - c.K @ c.C) @ (c.Phi - c.Gamma @ L)
    KC = c.K @ C
    A = jnp.block([[Phi, jnp.zeros((n, n_obs), Phi.dtype)], [KC @ Phi, observer]])
    B = jnp.concatenate([Gamma, KC @ Gamma], axis=0)
    C_loop = jnp.concatenate([jnp.zeros((L.shape[0], n), L.dtype), L], axis=1)
    return StateSpace(A, B, C_loop, jnp.zeros((L.shape[0], Gamma.shape[-1]), A.dtype), plant.dt)


def closed_loop_matrix(plant: StateSpace, controller: Controller, params):
    """System matrix of plant plus observer-based feedback (Cortesão 2006 Theorem 2, eq. 59), state
    ``[x; x_hat]``: ``[[Phi, -Gamma L], [K C Phi, (I - K C_n)(Phi_n - Gamma_n L) - K C Gamma L]]``.
    The loop is absolutely stable iff its spectral radius is below 1.

    Args:
      plant: the true discrete plant.  controller: a linear fixed-gain controller.  params: its params (see
        :func:`loop_transfer`).
    """
    loop = loop_transfer(plant, controller, params)
    return loop.A - loop.B @ loop.C


def spectral_radius(A):
    """``max |eig(A)|`` of an (n, n) matrix ``A`` or a stack of them (differentiable where the largest eigenvalue
    is simple)."""
    (A,) = _checks.float_arrays(A=A)
    _checks.matrix("A", A, square=True, batch=True)
    return jnp.max(jnp.abs(jnp.linalg.eigvals(A)))


def frequency_response(sys: StateSpace, omega):
    """``H(e^{j omega dt}) = C (zI - A)^{-1} B + D`` of a discrete SISO system at angular
    frequencies ``omega`` (rad/s), by a linear solve per frequency."""
    sys = _require_discrete_siso(sys)
    theta = jnp.asarray(omega) * sys.dt
    return jnp.vectorize(lambda t: _resolvent_response(sys, t))(theta)


def _require_discrete_siso(sys: StateSpace) -> StateSpace:
    """``sys`` checked (discrete, SISO, consistent shapes) and cast to its common floating dtype."""
    if not sys.is_discrete:
        raise ValueError("sys must be discrete (dt set)")
    if sys.n_inputs != 1 or sys.n_outputs != 1:
        raise ValueError(f"sys must be SISO, got {sys.n_outputs} outputs and {sys.n_inputs} inputs")
    n = sys.n_states
    _checks.matrix("sys.A", sys.A, shape=(n, n))
    _checks.matrix("sys.B", sys.B, shape=(n, 1))
    _checks.matrix("sys.C", sys.C, shape=(1, n))
    _checks.matrix("sys.D", sys.D, shape=(1, 1))
    dtype = _checks.float_dtype(A=sys.A, B=sys.B, C=sys.C, D=sys.D)
    return StateSpace(*(jnp.asarray(M, dtype) for M in (sys.A, sys.B, sys.C, sys.D)), sys.dt)


def _resolvent_response(sys: StateSpace, theta):
    """Exact ``H(e^{j theta})`` (complex solve); smooth in ``theta`` and in the matrices."""
    z = jnp.exp(1j * theta)
    n = sys.A.shape[-1]
    x = jnp.linalg.solve(z * jnp.eye(n) - sys.A, sys.B[:, 0].astype(z.dtype))
    return sys.C[0] @ x + sys.D[0, 0]


class Margins(NamedTuple):
    """Discrete-time stability margins of a loop transfer function ``H`` (negative feedback).

    ``gain_margin``: ``1/|H|`` at the phase crossover closest to 1 in log scale (inf if none);
    ``phase_margin``: degrees, ``angle(H) + 180`` wrapped to (-180, 180] at the gain crossover with
    the smallest ``|margin|`` (inf if none); ``delay_margin``: seconds, the smallest extra input delay
    that destabilises a stable loop, ``min_i mod(pm_i, 360) / w_i`` over all gain crossovers (inf if
    none), at most one sample ``dt`` when ``|H(-1)| > 1`` (one sample of delay flips the sign of
    ``H(-1)``); ``stability_margin``: ``min_w |1 + H|``; ``phase_crossover``, ``gain_crossover``,
    ``stability_margin_frequency``: the frequencies of those margins in rad/s (nan if none);
    ``spectral_radius`` of the closed loop (the margins mean something only when it is below 1).
    ``truncated``: more crossings than ``max_crossings`` were seen (margins may be optimistic).
    """

    gain_margin: jax.Array
    phase_margin: jax.Array
    delay_margin: jax.Array
    stability_margin: jax.Array
    phase_crossover: jax.Array
    gain_crossover: jax.Array
    stability_margin_frequency: jax.Array
    spectral_radius: jax.Array
    truncated: jax.Array


def _product_response(poles, closed, d):
    """A fast ``theta -> H(e^{j theta})`` for many frequencies from the open- and closed-loop
    eigenvalues: ``1 + H(z) = (1 + D) prod(z - closed) / prod(z - poles)`` (O(n) per frequency and
    well conditioned even for the repeated poles of a dead-time chain). Locates crossings only."""
    poles, closed, d = (jax.lax.stop_gradient(v) for v in (poles, closed, d))

    def response(theta):
        z = jnp.exp(1j * theta)[..., None]
        return (1.0 + d) * jnp.prod(z - closed, axis=-1) / jnp.prod(z - poles, axis=-1) - 1.0

    return response


def _grid(num_points: int, dtype):
    """Normalised frequencies ``theta = omega dt`` in (0, pi]: log-spaced from ``1e-5 pi``."""
    return jnp.pi * jnp.logspace(-5.0, 0.0, num_points, dtype=dtype)


def _bisect(f, lo, hi, iters: int):
    """Bisection (in log theta) of a sign change of ``f`` on ``[lo, hi]``, elementwise."""
    f_lo = f(lo)

    def body(_, bracket):
        lo, hi, f_lo = bracket
        mid = jnp.sqrt(lo * hi)
        f_mid = f(mid)
        left = jnp.sign(f_mid) != jnp.sign(f_lo)
        return jnp.where(left, lo, mid), jnp.where(left, mid, hi), jnp.where(left, f_lo, f_mid)

    lo, hi, _ = jax.lax.fori_loop(0, iters, body, (lo, hi, f_lo))
    return jnp.sqrt(lo * hi)


def _crossings(f, theta, values, max_crossings: int, iters: int):
    """Up to ``max_crossings`` refined roots of ``f`` bracketed by sign changes of ``values = f(theta)``
    on the grid. Returns ``(roots, valid, truncated)``."""
    change = (jnp.sign(values[:-1]) * jnp.sign(values[1:]) < 0) & jnp.isfinite(values[:-1] + values[1:])
    (index,) = jnp.nonzero(change, size=max_crossings, fill_value=0)
    valid = jnp.arange(max_crossings) < jnp.sum(change)
    roots = _bisect(f, theta[index], theta[index + 1], iters)
    return roots, valid, jnp.sum(change) > max_crossings


def _exact_with_slope(sys: StateSpace, theta):
    """Exact ``H`` and ``dH/dtheta`` at the (held constant) frequencies ``theta``, in one batched
    solve: Newton steps from them give first-order values whose gradients follow the implicit
    function theorem through the crossover frequencies (one solve call on purpose: see the
    eigenvalue call in :func:`stability_margins`)."""
    theta = jax.lax.stop_gradient(theta)
    one = jax.vmap(lambda t: jax.jvp(lambda s: _resolvent_response(sys, s), (t,), (jnp.ones_like(t),)))
    return one(theta)


def _newton_step(theta, H, dH, residual):
    g, dg = residual(H, dH)
    step = jnp.where(dg != 0, -g / jnp.where(dg != 0, dg, 1.0), 0.0)
    return theta + step, H + dH * step


def _phase_residual(H, dH):
    return jnp.imag(H), jnp.imag(dH)


def _unit_gain_residual(H, dH):
    return jnp.abs(H) ** 2 - 1.0, 2.0 * jnp.real(jnp.conj(H) * dH)


def stability_margins(
    sys: StateSpace, *, num_points: int = 1024, max_crossings: int = 8, bisection_steps: int = 30
) -> Margins:
    """Gain, phase, delay and stability margins of the discrete SISO loop ``sys`` (Cortesão 2006 §6.2),
    and the spectral radius of the closed loop ``A - B C / (1 + D)``.

    Args:
      sys: the discrete SISO loop transfer function (e.g. :func:`loop_transfer`), negative feedback.
      num_points: crossings are bracketed on ``num_points >= 2`` log-spaced frequencies up to Nyquist (two
        crossings closer than one grid step can be missed; increase it).
      max_crossings: at most ``max_crossings >= 1`` crossings of each kind are refined.
      bisection_steps: ``>= 1`` bisection steps refine each bracket; the selected crossings are then polished by
        a Newton step on the exact response.

    Returns :class:`Margins`. ``jit``/``vmap`` compatible; differentiable where the selected crossover and the
    largest closed-loop eigenvalue are simple. Unlike python-control, the Nyquist frequency counts as a phase
    crossover when ``H(-1) < 0``.

    Example:
      >>> from jaxobs.lti import ss
      >>> loop = ss([[0.5]], [[1.0]], [[0.4]], dt=0.01)                 # 0.4 / (z - 0.5)
      >>> m = stability_margins(loop)
      >>> round(float(m.gain_margin), 3), bool(m.spectral_radius < 1)
      (3.75, True)
    """
    sys = _require_discrete_siso(sys)
    num_points = _checks.count("num_points", num_points, minimum=2)
    max_crossings = _checks.count("max_crossings", max_crossings, minimum=1)
    bisection_steps = _checks.count("bisection_steps", bisection_steps, minimum=1)
    dtype = sys.A.dtype
    d = sys.D[0, 0]
    # one batched eigenvalue call: independent LAPACK calls in one XLA CPU program can run at once,
    # and jaxlib 0.10's batched LAPACK kernels deadlock when they fill its thread pool (see jaxobs.sweep)
    poles, closed = jnp.linalg.eigvals(jnp.stack([sys.A, sys.A - sys.B @ sys.C / (1.0 + d)]))
    fast = _product_response(poles, closed, d)
    theta = _grid(num_points, dtype)
    H = fast(theta)
    inf, nan = jnp.asarray(jnp.inf, dtype), jnp.asarray(jnp.nan, dtype)

    # phase crossovers: H real and negative (including z = 1 and z = -1)
    pc, pc_valid, pc_trunc = _crossings(lambda t: jnp.imag(fast(t)), theta, jnp.imag(H), max_crossings, bisection_steps)
    pc = jnp.concatenate([pc, jnp.zeros((1,), dtype), jnp.full((1,), jnp.pi, dtype)])
    H_pc = fast(pc)
    pc_valid = jnp.concatenate([pc_valid, jnp.ones((2,), bool)]) & (jnp.real(H_pc) <= 0) & jnp.isfinite(H_pc)
    i_pc = jnp.argmin(jnp.where(pc_valid, jnp.abs(jnp.log(jnp.abs(H_pc))), inf))
    has_pc = jnp.any(pc_valid)

    # gain crossovers: |H| = 1
    gc, gc_valid, gc_trunc = _crossings(
        lambda t: jnp.log(jnp.abs(fast(t))), theta, jnp.log(jnp.abs(H)), max_crossings, bisection_steps
    )
    lag = jnp.remainder(jnp.degrees(jnp.angle(fast(gc))), 360.0)  # phase margin + 180 in [0, 360)
    has_gc = jnp.any(gc_valid)
    i_gc = jnp.argmin(jnp.where(gc_valid, jnp.abs(lag - 180.0), inf))
    # a delay tau multiplies H by exp(-j w tau) (exact for whole samples): the loop first reaches -1
    # at the crossover with the smallest (phase margin mod 360) / w
    i_dm = jnp.argmin(jnp.where(gc_valid, jnp.remainder(lag - 180.0, 360.0) / gc, inf))

    # stability margin: min |1 + H| on the grid (with DC), refined by golden-section search
    theta0 = jnp.concatenate([jnp.zeros((1,), dtype), theta])
    distance = jnp.abs(1.0 + jnp.concatenate([fast(theta0[:1]), H]))
    i_sm = jnp.argmin(jnp.where(jnp.isfinite(distance), distance, inf))
    lo, hi = theta0[jnp.maximum(i_sm - 1, 0)], theta0[jnp.minimum(i_sm + 1, num_points)]
    theta_sm = _golden_minimum(lambda t: jnp.abs(1.0 + fast(t)), lo, hi, bisection_steps)

    # exact values at the selected frequencies, one Newton step each (none needed at the minimum of
    # |1 + H|: a stationary point, so the envelope theorem gives its gradient)
    selected = jnp.stack([pc[i_pc], gc[i_gc], gc[i_dm], theta_sm])
    H_exact, slope = _exact_with_slope(sys, selected)
    theta_pc, H_pc_star = _newton_step(selected[0], H_exact[0], slope[0], _phase_residual)
    theta_gc, H_gc = _newton_step(selected[1], H_exact[1], slope[1], _unit_gain_residual)
    theta_dm, H_dm = _newton_step(selected[2], H_exact[2], slope[2], _unit_gain_residual)

    gain_margin = jnp.where(has_pc, 1.0 / jnp.abs(jnp.real(H_pc_star)), inf)
    phase_crossover = jnp.where(has_pc, theta_pc / sys.dt, nan)
    phase_margin = jnp.where(has_gc, jnp.remainder(jnp.degrees(jnp.angle(H_gc)), 360.0) - 180.0, inf)
    gain_crossover = jnp.where(has_gc, theta_gc / sys.dt, nan)
    lag_dm = jnp.remainder(jnp.degrees(jnp.angle(H_dm)) - 180.0, 360.0)
    delay_margin = jnp.where(has_gc, jnp.radians(lag_dm) / (theta_dm / sys.dt), inf)
    # a whole-sample delay multiplies H(-1) by -1: when |H(-1)| > 1 the end of the Nyquist plot jumps across -1
    # between 0 and 1 sample, so one sample destabilises the loop whatever the gain crossovers allow
    nyquist_gain = jnp.abs(fast(jnp.asarray(jnp.pi, dtype)))
    delay_margin = jnp.where(nyquist_gain > 1.0, jnp.minimum(delay_margin, sys.dt), delay_margin)
    stability_margin = jnp.abs(1.0 + H_exact[3])

    values = (gain_margin, phase_margin, delay_margin, stability_margin, phase_crossover, gain_crossover,
              jax.lax.stop_gradient(theta_sm) / sys.dt, jnp.max(jnp.abs(closed)))  # fmt: skip
    return Margins(*(v.astype(dtype) for v in values), pc_trunc | gc_trunc)  # one dtype, the loop's


def _golden_minimum(f, lo, hi, iters: int):
    """Golden-section search for a minimum of a unimodal ``f`` on ``[lo, hi]``."""
    ratio = (jnp.sqrt(5.0) - 1.0) / 2.0

    def body(_, bracket):
        lo, hi = bracket
        a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
        left = f(a) < f(b)
        return jnp.where(left, lo, a), jnp.where(left, b, hi)

    lo, hi = jax.lax.fori_loop(0, iters, body, (lo, hi))
    return 0.5 * (lo + hi)


def unstructured_mismatch(key, Phi_n, Gamma_n, phi_norm, gamma_norm):
    """Random true model ``(Phi_n + Delta Phi, Gamma_n + Delta Gamma)`` with Gaussian directions
    scaled to spectral norms ``||Delta Phi||_2 = phi_norm`` and ``||Delta Gamma||_2 = gamma_norm``
    (the unstructured model errors of Cortesão 2006 Theorem 2)."""
    Phi_n, Gamma_n = jnp.asarray(Phi_n), jnp.asarray(Gamma_n)
    _checks.matrix("Phi_n", Phi_n, square=True)
    _checks.matrix("Gamma_n", Gamma_n, shape=(Phi_n.shape[-1], None))
    _checks.positive_scalar("phi_norm", phi_norm, allow_zero=True)
    _checks.positive_scalar("gamma_norm", gamma_norm, allow_zero=True)
    dtype = _checks.float_dtype(Phi_n=Phi_n, Gamma_n=Gamma_n)
    Phi_n, Gamma_n = Phi_n.astype(dtype), Gamma_n.astype(dtype)
    k_phi, k_gamma = jax.random.split(key)
    d_phi = jax.random.normal(k_phi, Phi_n.shape, Phi_n.dtype)
    d_gamma = jax.random.normal(k_gamma, Gamma_n.shape, Gamma_n.dtype)
    d_phi = d_phi * (phi_norm / jnp.linalg.norm(d_phi, 2))
    d_gamma = d_gamma * (gamma_norm / jnp.linalg.norm(d_gamma, 2))
    return Phi_n + d_phi, Gamma_n + d_gamma
