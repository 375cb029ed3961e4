"""Stability of observer-based control with model errors (Cortesão 2006 §6): closed-loop matrices,
spectral radius, the loop transfer function at the plant input, and discrete-time margins.

:func:`closed_loop_matrix` (Theorem 2, eq. 59) and :func:`spectral_radius`, the loop transfer function cut at the
plant input (Theorem 3, eq. 65), :func:`stability_margins` in python-control's conventions plus the delay margin and
the lower and upper gain margins of conditionally stable loops, differentiable where the crossover is simple, and
:func:`robustness_metrics`, a sweep's row of them (validity, stability, margins only where they mean something).
The ``[x; x_hat]`` coordinates and how they map to the printed equations: docs/theory/analysis.md.
"""

from __future__ import annotations

import logging
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
    "robustness_metrics",
    "ROBUSTNESS_MARGINS",
    "check_nominal",
    "unstructured_mismatch",
]

_log = logging.getLogger(__name__)


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

    Where the loop is cut: at the plant input only. The plant receives ``u'``, and so does the observer, which
    is fed the command that actually enters the plant (in the closed loop, its own ``-L x_hat``); the reference is
    zero. The margins of this loop are therefore those of a gain, phase or delay inserted between the controller's
    command and the plant's actuator, seen by both; an error that the observer does not see (a gain or delay in
    the actuator after the observer's tap) is a plant mismatch, checked with the true ``plant`` instead.
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

    ``gain_margin``: ``1/|H|`` at the phase crossover closest to 1 in log scale (inf if none), as python-control;
    for a conditionally stable loop it can be below 1: the loop then goes unstable when its gain is *reduced* by
    that factor; ``gain_margin_lower``, ``gain_margin_upper``: the interval of loop gains ``k`` for which
    ``k H`` stays stable, for a closed loop that is stable: ``gain_margin_upper = min 1/|H|`` over the phase
    crossovers with ``|H| < 1`` (inf if none: any gain increase is tolerated), ``gain_margin_lower = max 1/|H|``
    over those with ``|H| > 1`` (0 if none: the loop is not conditionally stable, any reduction is tolerated);
    ``phase_margin``: degrees, ``angle(H) + 180`` wrapped to (-180, 180] at the gain crossover with
    the smallest ``|margin|`` (inf if none); ``delay_margin``: seconds, the smallest extra input delay
    that destabilises a stable loop, ``min_i mod(pm_i, 360) / w_i`` over all gain crossovers (inf if
    none), at most one sample ``dt`` when ``|H(-1)| > 1`` (one sample of delay flips the sign of
    ``H(-1)``); ``stability_margin``: ``min_w |1 + H|``; ``phase_crossover``, ``gain_crossover``,
    ``stability_margin_frequency``: the frequencies of those margins in rad/s (nan if none);
    ``spectral_radius`` of the closed loop (the margins mean something only when it is below 1).
    ``truncated``: more crossings than ``max_crossings`` were seen (margins may be optimistic). Phase crossovers
    with ``|H| >= MAX_LOOP_GAIN`` (an open-loop pole on the unit circle) are not counted.

    Every field is NaN (``truncated`` False) for a loop whose matrices are not finite (e.g. a plant from
    :func:`jaxobs.lti.c2d` with a dead time beyond its slots): such a loop has no margins, not infinite ones.
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
    gain_margin_lower: jax.Array
    gain_margin_upper: jax.Array


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


MAX_LOOP_GAIN = 1e8
"""A phase crossover where ``|H|`` reaches this is an open-loop pole on (or within rounding of) the unit circle,
e.g. a rigid-body mode at z = 1: not counted (a gain reduction by 1e8 is none in practice)."""


def _phase_crossovers(fast, theta, H, max_crossings: int, iters: int):
    """The phase crossovers (``H`` real and negative, z = 1 and z = -1 included) of the response ``fast``:
    ``(frequencies, valid, the indices of the one closest to |H| = 1 in log scale and of the nearest on either
    side of it in gain, truncated)``."""
    dtype = theta.dtype
    pc, valid, truncated = _crossings(lambda t: jnp.imag(fast(t)), theta, jnp.imag(H), max_crossings, iters)
    pc = jnp.concatenate([pc, jnp.zeros((1,), dtype), jnp.full((1,), jnp.pi, dtype)])
    H_pc = fast(pc)
    valid = jnp.concatenate([valid, jnp.ones((2,), bool)]) & (jnp.real(H_pc) <= 0) & (jnp.abs(H_pc) < MAX_LOOP_GAIN)
    log_gain = -jnp.log(jnp.abs(H_pc))  # log of the gain factor that puts this crossing on -1
    inf = jnp.asarray(jnp.inf, dtype)
    nearest = jnp.argmin(jnp.where(valid, jnp.abs(log_gain), inf))
    upper = jnp.argmin(jnp.where(valid & (log_gain > 0), log_gain, inf))  # the smallest gain increase
    lower = jnp.argmax(jnp.where(valid & (log_gain < 0), log_gain, -inf))  # the smallest gain reduction
    has = (jnp.any(valid), jnp.any(valid & (log_gain > 0)), jnp.any(valid & (log_gain < 0)))
    return pc, (nearest, upper, lower), has, truncated


def _gain_crossovers(fast, theta, H, max_crossings: int, iters: int):
    """The gain crossovers (``|H| = 1``) of the response ``fast``: ``(frequencies, the indices of the phase-margin
    crossover and of the one that sets the delay margin, any, truncated)``."""
    inf = jnp.asarray(jnp.inf, theta.dtype)
    gc, valid, truncated = _crossings(lambda t: jnp.log(jnp.abs(fast(t))), theta, jnp.log(jnp.abs(H)), max_crossings,
                                      iters)  # fmt: skip
    lag = jnp.remainder(jnp.degrees(jnp.angle(fast(gc))), 360.0)  # phase margin + 180 in [0, 360)
    i_gc = jnp.argmin(jnp.where(valid, jnp.abs(lag - 180.0), inf))
    # a delay tau multiplies H by exp(-j w tau) (exact for whole samples): the loop first reaches -1
    # at the crossover with the smallest (phase margin mod 360) / w
    i_dm = jnp.argmin(jnp.where(valid, jnp.remainder(lag - 180.0, 360.0) / gc, inf))
    return gc, (i_gc, i_dm), jnp.any(valid), truncated


def _closest_approach(fast, theta, H, iters: int):
    """The frequency of ``min |1 + H|``: on the grid ``theta`` (response ``H``) and DC, refined by golden-section
    search."""
    theta0 = jnp.concatenate([jnp.zeros((1,), theta.dtype), theta])
    distance = jnp.abs(1.0 + jnp.concatenate([fast(theta0[:1]), H]))
    i_sm = jnp.argmin(jnp.where(jnp.isfinite(distance), distance, jnp.inf))
    lo, hi = theta0[jnp.maximum(i_sm - 1, 0)], theta0[jnp.minimum(i_sm + 1, theta.size)]
    return _golden_minimum(lambda t: jnp.abs(1.0 + fast(t)), lo, hi, iters)


def _finite_or_zero(sys: StateSpace):
    """``(whether every matrix of sys is finite, sys with zero matrices if not)``: the zero loop keeps the margin
    search harmless, its margins are replaced by NaN afterwards."""
    finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(M)) for M in (sys.A, sys.B, sys.C, sys.D)]))
    return finite, StateSpace(*(jnp.where(finite, M, 0.0) for M in (sys.A, sys.B, sys.C, sys.D)), sys.dt)


def _delay_margin(fast, theta, H, dt: float):
    """The delay margin (s) set by the gain crossover at ``theta`` (response ``H`` there): its phase margin mod 360
    over its frequency, at most one sample ``dt`` when ``|H(-1)| > 1``."""
    lag = jnp.remainder(jnp.degrees(jnp.angle(H)) - 180.0, 360.0)
    margin = jnp.radians(lag) / (theta / dt)
    # a whole-sample delay multiplies H(-1) by -1: when |H(-1)| > 1 the end of the Nyquist plot jumps across -1
    # between 0 and 1 sample, so one sample destabilises the loop whatever the gain crossovers allow
    nyquist_gain = jnp.abs(fast(jnp.asarray(jnp.pi, theta.dtype)))
    return jnp.where(nyquist_gain > 1.0, jnp.minimum(margin, dt), margin)


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
    crossover when ``H(-1) < 0``. The margins describe the loop whatever its stability; they say how far a stable
    loop is from instability only when ``spectral_radius < 1`` (:func:`robustness_metrics` keeps them there only).

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
    finite, sys = _finite_or_zero(sys)  # a non-finite loop (traced: eagerly it is refused) has NaN margins
    dtype = sys.A.dtype
    d = sys.D[0, 0]
    # one batched eigenvalue call: independent LAPACK calls in one XLA CPU program can run at once,
    # and jaxlib 0.10's batched LAPACK kernels deadlock when they fill its thread pool (see jaxobs.sweep)
    poles, closed = jnp.linalg.eigvals(jnp.stack([sys.A, sys.A - sys.B @ sys.C / (1.0 + d)]))
    fast = _product_response(poles, closed, d)
    theta = _grid(num_points, dtype)
    H = fast(theta)
    inf, nan = jnp.asarray(jnp.inf, dtype), jnp.asarray(jnp.nan, dtype)

    pc, (i_pc, i_up, i_lo), (has_pc, has_up, has_lo), pc_trunc = _phase_crossovers(
        fast, theta, H, max_crossings, bisection_steps
    )
    gc, (i_gc, i_dm), has_gc, gc_trunc = _gain_crossovers(fast, theta, H, max_crossings, bisection_steps)
    theta_sm = _closest_approach(fast, theta, H, bisection_steps)

    # exact values at the selected frequencies, one Newton step each (none needed at the minimum of
    # |1 + H|: a stationary point, so the envelope theorem gives its gradient)
    selected = jnp.stack([pc[i_pc], gc[i_gc], gc[i_dm], theta_sm, pc[i_up], pc[i_lo]])
    H_exact, slope = _exact_with_slope(sys, selected)
    theta_pc, H_pc = _newton_step(selected[0], H_exact[0], slope[0], _phase_residual)
    theta_gc, H_gc = _newton_step(selected[1], H_exact[1], slope[1], _unit_gain_residual)
    theta_dm, H_dm = _newton_step(selected[2], H_exact[2], slope[2], _unit_gain_residual)
    H_up, H_lo = (_newton_step(selected[i], H_exact[i], slope[i], _phase_residual)[1] for i in (4, 5))

    margins = Margins(
        gain_margin=jnp.where(has_pc, 1.0 / jnp.abs(jnp.real(H_pc)), inf),
        phase_margin=jnp.where(has_gc, jnp.remainder(jnp.degrees(jnp.angle(H_gc)), 360.0) - 180.0, inf),
        delay_margin=jnp.where(has_gc, _delay_margin(fast, theta_dm, H_dm, sys.dt), inf),
        stability_margin=jnp.abs(1.0 + H_exact[3]),
        phase_crossover=jnp.where(has_pc, theta_pc / sys.dt, nan),
        gain_crossover=jnp.where(has_gc, theta_gc / sys.dt, nan),
        stability_margin_frequency=jax.lax.stop_gradient(theta_sm) / sys.dt,
        spectral_radius=jnp.max(jnp.abs(closed)),
        truncated=pc_trunc | gc_trunc,
        gain_margin_lower=jnp.where(has_lo, 1.0 / jnp.abs(jnp.real(H_lo)), 0.0),
        gain_margin_upper=jnp.where(has_up, 1.0 / jnp.abs(jnp.real(H_up)), inf),
    )
    return Margins(*(jnp.where(finite, v, False) if v.dtype == bool else jnp.where(finite, v, nan).astype(dtype)
                     for v in margins))  # fmt: skip  # one floating dtype, the loop's


ROBUSTNESS_MARGINS = ("gain_margin", "gain_margin_lower", "gain_margin_upper", "phase_margin", "delay_margin",
                      "stability_margin")  # fmt: skip
"""The :class:`Margins` fields that :func:`robustness_metrics` reports (NaN unless the loop is stable)."""


def robustness_metrics(plant: StateSpace, controller: Controller, params, *, valid=True, num_points: int = 1024,
                       max_crossings: int = 8, bisection_steps: int = 30) -> dict:  # fmt: skip
    """A robustness sweep's row for one true plant: validity and stability as data, margins where they mean
    something (Cortesão 2006 §6: eq. 59's spectral radius, eq. 65's loop).

    Args:
      plant: the true discrete plant (e.g. from :func:`jaxobs.lti.c2d` with a traced dead time).
      controller: a linear fixed-gain controller.  params: its params (see :func:`loop_transfer`).
      valid: a boolean (traced allowed) that the configuration is valid besides its matrices being finite, e.g.
        the ``converged`` flag of a design computed per configuration.
      num_points, max_crossings, bisection_steps: as :func:`stability_margins`.

    Returns a dict of scalars, the columns of a sweep's metrics: ``valid`` (``valid``, and the loop's matrices
    finite: a non-finite plant, e.g. a zero inertia or a dead time beyond ``c2d``'s ``n_delay`` slots, is
    invalid), ``stable`` (valid and the closed loop's spectral radius below 1), ``spectral_radius`` (NaN where
    invalid) and the margins of :data:`ROBUSTNESS_MARGINS`, NaN where the loop is not stable (an unstable loop has
    no margin to lose). On a stable loop an infinite margin means the loop has no crossover of that kind: no gain
    increase (``gain_margin_upper``), phase lag or delay makes it unstable; ``gain_margin_lower`` 0 means no gain
    reduction does, a value above 0 marks a conditionally stable loop.

    Example:
      >>> from jaxobs.lti import ss
      >>> from jaxobs.observers import FeedbackParams, LinearObserver
      >>> from jaxobs.observers.linear import linear_controller
      >>> one = jnp.ones((1, 1))
      >>> ctrl = FeedbackParams(LinearObserver(0.5 * one, one, one, one), 0.4 * one)  # K = 1, L = 0.4
      >>> row = robustness_metrics(ss(0.5 * one, one, one, dt=0.01), linear_controller, ctrl)
      >>> bool(row["stable"]), round(float(row["gain_margin"]), 3)
      (True, 3.75)
      >>> invalid = StateSpace(jnp.nan * one, one, one, 0 * one, dt=0.01)  # e.g. a zero inertia
      >>> {k: bool(v) if v.dtype == bool else float(v) for k, v in robustness_metrics(invalid, linear_controller,
      ...                                                                           ctrl).items()}
      ... # doctest: +NORMALIZE_WHITESPACE
      {'valid': False, 'stable': False, 'spectral_radius': nan, 'gain_margin': nan, 'gain_margin_lower': nan,
       'gain_margin_upper': nan, 'phase_margin': nan, 'delay_margin': nan, 'stability_margin': nan}
    """
    finite, loop = _finite_or_zero(loop_transfer(plant, controller, params))
    margins = stability_margins(loop, num_points=num_points, max_crossings=max_crossings,
                                bisection_steps=bisection_steps)  # fmt: skip
    valid = jnp.asarray(valid, bool) & finite & jnp.isfinite(margins.spectral_radius)
    stable = valid & (margins.spectral_radius < 1.0)
    nan = jnp.asarray(jnp.nan, margins.spectral_radius.dtype)
    row = {"valid": valid, "stable": stable, "spectral_radius": jnp.where(valid, margins.spectral_radius, nan)}
    return row | {name: jnp.where(stable, getattr(margins, name), nan) for name in ROBUSTNESS_MARGINS}


def check_nominal(plant: StateSpace, controller: Controller, params, *, what: str = "the design",
                  num_points: int = 1024) -> dict:  # fmt: skip
    """:func:`robustness_metrics` of the loop on the nominal ``plant`` (compiled once, run eagerly), with a warning
    (logged on ``jaxobs.stability``) when it is not stable there: a sweep of that design would measure only how
    unstable it is. Call it before a sweep.

    Args:
      plant, controller, params: as :func:`robustness_metrics`, the plant the design was made for.
      what: how the warning names the design.  num_points: as :func:`stability_margins`.

    Returns the row (Python scalars).
    """
    metrics = jax.jit(lambda plant, params: robustness_metrics(plant, controller, params, num_points=num_points))
    row = {name: value.item() for name, value in metrics(plant, params).items()}
    if not row["stable"]:
        state = (
            "invalid (non-finite)" if not row["valid"] else f"unstable (spectral radius {row['spectral_radius']:.4g})"
        )
        _log.warning("%s is %s on the nominal plant: a sweep of it measures how unstable it is, not how robust", what,
                     state)  # fmt: skip
    return row


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
