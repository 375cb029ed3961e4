"""The road inclination and bank estimators of Grip 2010 ch. 4 (Grip, Imsland, Johansen, Kalkkuhl & Suissa 2009,
ACC) and the positive-realness gain bounds of its Lemmas 4.1 and 4.2.

:data:`road_angles` is the known-friction estimator (4.6)-(4.10) (Theorem 4.1), :data:`road_angles_adaptive` the
friction-adaptive one (4.12)-(4.14); both treat ``sin(Theta)`` and ``cos(Theta) sin(Phi)`` as constants estimated
by integral action, discretised as the NVSO. :func:`inclination_error_system`, :func:`bank_error_system`,
:func:`inclination_gain_bound`, :func:`bank_gain_bound` and :func:`lemma_check` give the error systems and the SPR
bounds; :func:`final_angles` reads a run's final estimates. The equations and the source's misprints:
docs/theory/vehicle.md.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs import _checks
from jaxobs.lti import StateSpace, is_spr, ss
from jaxobs.observers.base import Estimator, EstimatorInputs
from jaxobs.vehicle.model import GRAVITY, VehicleParams, check_vehicle, friction_model
from jaxobs.vehicle.sensors import AX, AY, N_SENSORS, SENSOR_RATE, STEERING_WHEEL, VX_REF, WHEEL_SPEED, YAW_RATE

__all__ = [
    "RoadAnglesParams",
    "RoadAnglesState",
    "RoadAnglesOutputs",
    "make_road_angles",
    "road_angles",
    "road_angles_adaptive",
    "inclination_error_system",
    "bank_error_system",
    "inclination_gain_bound",
    "bank_gain_bound",
    "LemmaCheck",
    "lemma_check",
    "FinalAngles",
    "final_angles",
]


def inclination_error_system(a, K_theta_i, g=GRAVITY) -> StateSpace:
    """The linear part of the inclination error system (4.8), state ``(v_x~, theta_i~)``, input ``u`` (the
    sector part ``-(K_vx(t) - a) v_x~``), output ``v_x~``: ``A = [[-a, g], [-K_theta_i a, 0]]``,
    ``B = [1, K_theta_i]'``, ``C = [1, 0]``. Args: ``a`` (1/s, ``0 < a < K_vx,min``), ``K_theta_i``, ``g``
    (m/s^2). Traceable (jit, vmap, grad)."""
    a, K, g = _checks.arrays("a (), K_theta_i (), g ()", a, K_theta_i, g)
    zero, one = jnp.zeros_like(a), jnp.ones_like(a)
    A = jnp.stack([jnp.stack([-a, g]), jnp.stack([-K * a, zero])])
    return ss(A, jnp.stack([one, K])[:, None], jnp.stack([one, zero])[None, :])


def bank_error_system(K_vy, delta_min, K_theta_b, g=GRAVITY) -> StateSpace:
    """The linear part of the bank error system (4.11), state ``(v_y~, theta_b~)``, input ``u = -(delta -
    delta_min) v_y~``, output ``v_y~``: ``A = [[-K_vy delta_min, -g], [K_theta_b delta_min, 0]]``,
    ``B = [K_vy, -K_theta_b]'``, ``C = [1, 0]``. Args: ``K_vy``, ``delta_min`` (1/s, the least slope of
    ``-a_y~`` in ``v_y~``, Assumption 4.1), ``K_theta_b``, ``g``. Traceable."""
    k, d, K, g = _checks.arrays("K_vy (), delta_min (), K_theta_b (), g ()", K_vy, delta_min, K_theta_b, g)
    zero, one = jnp.zeros_like(k), jnp.ones_like(k)
    A = jnp.stack([jnp.stack([-k * d, -g]), jnp.stack([K * d, zero])])
    return ss(A, jnp.stack([k, -K])[:, None], jnp.stack([one, zero])[None, :])


def inclination_gain_bound(a, g=GRAVITY):
    """Lemma 4.1: the inclination estimator is GES for ``0 < K_theta_i < a / g``; returns ``a / g``. ``a`` (1/s) and
    ``g`` (m/s^2) finite and > 0, checked where concrete."""
    a, g = _checks.arrays("a (), g ()", a, g)
    for name, value in (("a", a), ("g", g)):
        _checks.positive(name, value)
    return a / g


def bank_gain_bound(K_vy, delta_min, g=GRAVITY):
    """Lemma 4.2: the bank estimator is GES for ``0 < K_theta_b < K_vy^2 delta_min / g``; returns the bound. ``K_vy``,
    ``delta_min`` (1/s) and ``g`` (m/s^2) finite and > 0, checked where concrete."""
    K_vy, delta_min, g = _checks.arrays("K_vy (), delta_min (), g ()", K_vy, delta_min, g)
    for name, value in (("K_vy", K_vy), ("delta_min", delta_min), ("g", g)):
        _checks.positive(name, value)
    return K_vy**2 * delta_min / g


class LemmaCheck(NamedTuple):
    """:func:`lemma_check`'s result: the ``bound`` and whether the error system is SPR at ``bound (1 - rel)``
    (``spr_below``) and ``bound (1 + rel)`` (``spr_above``)."""

    bound: float
    spr_below: bool
    spr_above: bool


@_checks.design_time()
def lemma_check(lemma: str, *, a=None, K_vy=None, delta_min=None, g=GRAVITY, rel=1e-3) -> LemmaCheck:
    """Evaluate :func:`jaxobs.lti.is_spr` on the error system of Lemma 4.1 (``lemma="4.1"``, needs ``a``) or
    Lemma 4.2 (``"4.2"``, needs ``K_vy`` and ``delta_min``) with the gain a relative ``rel`` below and above the
    bound (design time, concrete values). The lemma holds when ``spr_below`` and not ``spr_above``.

    Example:
      >>> check = lemma_check("4.1", a=0.5)             # bound a / g
      >>> round(check.bound, 6), check.spr_below, check.spr_above
      (0.050968, True, False)
    """
    _checks.positive_scalar("rel", rel)
    if lemma == "4.1":
        _checks.positive_scalar("a", a)
        bound = float(inclination_gain_bound(a, g))
        system = lambda K: inclination_error_system(a, K, g)
    elif lemma == "4.2":
        _checks.positive_scalar("K_vy", K_vy)
        _checks.positive_scalar("delta_min", delta_min)
        bound = float(bank_gain_bound(K_vy, delta_min, g))
        system = lambda K: bank_error_system(K_vy, delta_min, K, g)
    else:
        raise ValueError(f"lemma must be '4.1' or '4.2', got {lemma!r}")
    spr = [is_spr(s.A, s.B, s.C) for s in (system(bound * (1 - rel)), system(bound * (1 + rel)))]
    return LemmaCheck(bound, *spr)


class RoadAnglesParams(NamedTuple):
    """Gains of the chapter 4 estimators (docs/theory/vehicle.md); build with :func:`make_road_angles`. Every field is a
    leaf (batchable, differentiable).

    Attributes:
      vehicle: the :class:`~jaxobs.vehicle.VehicleParams` of the friction model.
      K_vx: longitudinal gain (1/s).  K_vy: lateral gain.  K_theta_i: inclination gain (times ``K_vx``).
      K_theta_b: bank gain (rad / (m/s^2 s)).  K_theta: friction adaptation gain (:data:`road_angles_adaptive`).
      friction: the known road friction (scale of the tyres' peak, :data:`road_angles`) or the initial ``theta``
        (:data:`road_angles_adaptive`).  theta_min, theta_max: the clip of ``theta``.
      dt: sample period (s).  vx0: initial ``v_x`` before the first finite ``v_x,ref`` (m/s).
    """

    vehicle: VehicleParams
    K_vx: jax.Array = 1.0
    K_vy: jax.Array = 1.0
    K_theta_i: jax.Array = 0.02
    K_theta_b: jax.Array = 0.05
    K_theta: jax.Array = 1.0
    friction: jax.Array = 1.0
    theta_min: jax.Array = 0.05
    theta_max: jax.Array = 1.1
    dt: jax.Array = 1.0 / SENSOR_RATE
    vx0: jax.Array = 20.0


def make_road_angles(vehicle: VehicleParams | None = None, **settings) -> RoadAnglesParams:
    """Params of :data:`road_angles` / :data:`road_angles_adaptive` for ``vehicle`` (default
    :class:`~jaxobs.vehicle.VehicleParams`), the defaults of :class:`RoadAnglesParams` (assumed; Grip 2010 ch. 4
    gives no values; they satisfy Lemma 4.1 for ``0.2 <= a < K_vx`` and Lemma 4.2 for ``delta_min >= 0.5``)
    overridden by ``settings``.

    Args:
      vehicle: the vehicle whose friction model the estimator uses.
      settings: any field of :class:`RoadAnglesParams` (``ValueError`` for an unknown one); concrete gains,
        ``friction``, ``theta_max`` and ``dt`` must be positive, ``K_theta_i``, ``K_theta_b``, ``theta_min`` and
        ``vx0`` non-negative, ``theta_min < theta_max`` (``ValueError`` naming the field).

    Example:
      >>> from jaxobs.vehicle.road_angles import make_road_angles
      >>> float(make_road_angles(K_theta_b=0.1).K_theta_b)
      0.1
    """
    vehicle = check_vehicle(vehicle)
    fields = RoadAnglesParams._fields[1:]
    unknown = sorted(set(settings) - set(fields))
    if unknown:
        raise ValueError(f"unknown road-angle settings {unknown}; the fields are {list(fields)}")
    for name, value in settings.items():
        zero_ok = name in ("K_theta_i", "K_theta_b", "theta_min", "vx0")
        _checks.positive(name, value, allow_zero=zero_ok)
    params = RoadAnglesParams(vehicle, **settings)
    lo, hi = params.theta_min, params.theta_max
    if _checks.is_concrete(lo, hi) and not np.all(np.asarray(lo) < np.asarray(hi)):  # NumPy: no tracer under jit
        raise ValueError(f"theta_min must be below theta_max (the bounds of theta), got {lo!r} >= {hi!r}")
    return params


class RoadAnglesState(NamedTuple):
    """State of :data:`road_angles` between samples.

    Attributes:
      x: (5,) estimate (v_x, v_y, theta_i, theta_b, theta) at t_{k-1}
      y: (N_SENSORS,) last finite measurement (held over the next interval)
      started: () bool: a sample has been processed (the first step outputs the initial estimate)
      missing: () int32, non-finite sensor samples skipped so far
    """

    x: jax.Array
    y: jax.Array
    started: jax.Array
    missing: jax.Array


class RoadAnglesOutputs(NamedTuple):
    """Outputs of one sample of :data:`road_angles`.

    Attributes:
      x: (5,) (v_x, v_y, theta_i, theta_b, theta) at t_k
      inclination: () arcsin(theta_i) (rad)
      bank: () arcsin(theta_b / cos(inclination)) (rad)
      beta: () sideslip arctan(v_y / v_x) (rad)
      innovation: (2,) (v_x,ref - v_x, a_y - a_y^) that drove the interval
      xi: () d a_y* / d v_y (1/s) over the interval
    """

    x: jax.Array
    inclination: jax.Array
    bank: jax.Array
    beta: jax.Array
    innovation: jax.Array
    xi: jax.Array


def _init(params: RoadAnglesParams) -> RoadAnglesState:
    check_vehicle(params.vehicle, "params.vehicle")  # one estimator, checked at trace time: vmap for a batch
    _checks.fields("params", params, ", ".join(f"{name} ()" for name in RoadAnglesParams._fields[1:]))
    dtype = jnp.result_type(params.vx0, params.friction, params.vehicle.mass, float)  # the vehicle's precision
    vx0 = jnp.asarray(params.vx0, dtype)
    y = jnp.zeros((N_SENSORS,), dtype).at[WHEEL_SPEED].set(vx0 / params.vehicle.wheel_radius).at[VX_REF].set(vx0)
    zero = jnp.zeros((), dtype)
    x = jnp.stack([vx0, zero, zero, zero, jnp.asarray(params.friction, dtype)])
    return RoadAnglesState(x, y, jnp.zeros((), bool), jnp.zeros((), jnp.int32))


def _step(params: RoadAnglesParams, state: RoadAnglesState, inputs: EstimatorInputs, *, adaptive: bool):
    v, dt, g = params.vehicle, params.dt, GRAVITY
    y = _checks.vector("inputs.y", inputs.y, N_SENSORS, state.x.dtype, what="the ESC sensors", check_finite=False)
    finite = jnp.isfinite(y)
    y_now = jnp.where(finite, y, state.y)
    missing = state.missing + jnp.sum(~finite).astype(jnp.int32)

    m = state.y  # the measurement held over [t_{k-1}, t_k]
    ax, r, sw, omega, vref = m[AX], m[YAW_RATE], m[STEERING_WHEEL], m[WHEEL_SPEED], m[VX_REF]
    ay = m[AY] / (1.0 + v.roll_gradient * g)  # roll correction, Grip 2010 §2.2
    vx, vy, theta_i, theta_b, theta = state.x
    friction = 1.0 if adaptive else params.friction
    ay_model = lambda vy: friction_model(v, vx, vy, r, sw, omega, ax, ay, friction).ay
    ay_star, xi = jax.jvp(ay_model, (vy,), (jnp.ones_like(vy),))

    e_x = vref - vx
    d_vx = ax + r * vy + g * theta_i + params.K_vx * e_x  # (4.6)
    d_theta_i = params.K_theta_i * params.K_vx * e_x  # (4.7)
    kinematic_y = ay - r * vx - g * theta_b
    if adaptive:
        e_y = ay - theta * ay_star
        lam = jax.lax.rsqrt(jnp.maximum(xi**2 + ay_star**2, 1e-12))
        d_vy = kinematic_y + params.K_vy * lam * xi * e_y  # (4.13)
        d_theta = params.K_theta * lam * ay_star * e_y  # (4.12b)
        d_theta_b = -params.K_theta_b * lam * xi * e_y  # (4.14)
    else:
        e_y = ay - ay_star
        d_vy = kinematic_y - params.K_vy * e_y  # (4.9)
        d_theta = jnp.zeros_like(theta)
        d_theta_b = params.K_theta_b * e_y  # (4.10)
    x = state.x + dt * jnp.stack([d_vx, d_vy, d_theta_i, d_theta_b, d_theta])
    if adaptive:
        x = x.at[4].set(jnp.clip(x[4], params.theta_min, params.theta_max))

    first = ~state.started
    x = jnp.where(first, state.x.at[0].set(y_now[VX_REF]), x)
    inclination = jnp.arcsin(jnp.clip(x[2], -1.0, 1.0))
    bank = jnp.arcsin(jnp.clip(x[3] / jnp.cos(inclination), -1.0, 1.0))
    beta = jnp.arctan2(x[1], x[0])
    outputs = RoadAnglesOutputs(x, inclination, bank, beta, jnp.stack([e_x, e_y]), xi)
    return RoadAnglesState(x, y_now, jnp.ones((), bool), missing), outputs


road_angles = Estimator(_init, functools.partial(_step, adaptive=False))
"""The known-friction inclination and bank estimator (4.6), (4.7), (4.9), (4.10) of Grip 2010 ch. 4 (module
docstring) as an :class:`~jaxobs.observers.base.Estimator` over :class:`RoadAnglesParams`. Inputs:
``EstimatorInputs(y)`` with ``y`` (:data:`~jaxobs.vehicle.N_SENSORS`,) (:func:`~jaxobs.vehicle.sensor_inputs`).
State: :class:`RoadAnglesState`. Outputs: :class:`RoadAnglesOutputs` (``theta`` stays at ``friction``)."""

road_angles_adaptive = Estimator(_init, functools.partial(_step, adaptive=True))
"""The friction-adaptive inclination and bank estimator (4.6), (4.7), (4.13), (4.12b), (4.14) of Grip 2010 ch. 4
(docs/theory/vehicle.md); as :data:`road_angles` otherwise."""


class FinalAngles(NamedTuple):
    """:func:`final_angles`' result: the estimated and the true parameters at the last sample and their errors in
    degrees of the angles.

    Attributes:
      theta_i_final: () estimated sin(Theta)
      theta_i_expected: () true sin(Theta)
      theta_b_final: () estimated cos(Theta) sin(Phi)
      theta_b_expected: () true cos(Theta) sin(Phi)
      inclination_error: () estimated minus true inclination (deg)
      bank_error: () estimated minus true bank (deg)
    """

    theta_i_final: jax.Array
    theta_i_expected: jax.Array
    theta_b_final: jax.Array
    theta_b_expected: jax.Array
    inclination_error: jax.Array
    bank_error: jax.Array


def final_angles(outputs: RoadAnglesOutputs, inclination, bank) -> FinalAngles:
    """The final inclination and bank estimates of a run (``outputs`` of :data:`road_angles` or
    :data:`road_angles_adaptive`, stacked over K samples) against the road's true ``inclination`` and ``bank``
    (K,) (rad, e.g. a :class:`~jaxobs.vehicle.Trajectory`'s ``inputs.inclination`` at the sensor samples)."""
    if not isinstance(outputs, RoadAnglesOutputs):
        raise ValueError(f"outputs must be the RoadAnglesOutputs of a run, got {type(outputs).__name__}")
    samples = outputs.x.shape[0]
    inclination, bank = _checks.real_array("inclination", inclination), _checks.real_array("bank", bank)
    _checks.shape("inclination", inclination, (samples,), "one angle per sample of outputs")
    _checks.shape("bank", bank, (samples,), "one angle per sample of outputs")
    Theta, Phi = inclination[-1], bank[-1]
    deg = 180.0 / jnp.pi
    return FinalAngles(
        outputs.x[-1, 2], jnp.sin(Theta), outputs.x[-1, 3], jnp.cos(Theta) * jnp.sin(Phi),
        deg * (outputs.inclination[-1] - Theta), deg * (outputs.bank[-1] - Phi),
    )  # fmt: skip
