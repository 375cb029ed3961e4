"""The friction-adaptive sideslip observers of Grip 2010 ch. 3 (Grip, Imsland, Johansen, Fossen, Kalkkuhl & Suissa
2008, Automatica).

The lateral observer (3.4) (:data:`lateral_observer`) and the full observer (3.14) (:data:`full_observer`) scale a
nominal tyre-force model (:func:`vehicle_model`) by the adapted friction ``theta``, with the practical
``xi``/``Lambda`` rule, excitation monitor and high-pass of §3.7; build their parameters with
:func:`make_adaptive_lateral`. :func:`lyapunov_3_1` and :func:`lemma_3_1_check` check Lemma 3.1. The sideslip
output uses ch. 2's sign, ``beta = arctan(v_y / v_x)``. The equations and the rules: docs/theory/vehicle.md.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.observers.base import Estimator, EstimatorInputs, run
from jaxobs.observers.pe_monitor import PEMonitorParams, PEMonitorState, pe_monitor
from jaxobs.vehicle.model import GRAVITY, VehicleParams, check_vehicle, friction_model
from jaxobs.vehicle.sensors import AX, AY, N_SENSORS, SENSOR_RATE, STEERING_WHEEL, VX_REF, WHEEL_SPEED, YAW_RATE

__all__ = [
    "AdaptiveLateralParams",
    "AdaptiveLateralState",
    "AdaptiveLateralOutputs",
    "vehicle_model",
    "make_adaptive_lateral",
    "lateral_observer",
    "full_observer",
    "lyapunov_3_1",
    "Lemma31Check",
    "lemma_3_1_check",
]


def _vehicle_forces(vehicle: VehicleParams, v, y):
    ay = y[AY] / (1.0 + vehicle.roll_gradient * GRAVITY)
    f = friction_model(vehicle, v[0], v[1], v[2], y[STEERING_WHEEL], y[WHEEL_SPEED], y[AX], ay)
    return jnp.stack([vehicle.mass * f.ay, f.yaw_moment])


def vehicle_model(vehicle: VehicleParams) -> jax.tree_util.Partial:
    """The nominal model ``(v, y) -> (f_y*, f_r*)`` of ``vehicle``: its friction model (:func:`jaxobs.vehicle.
    friction_model`, tyres at their own friction, loads from the measured accelerations) as lateral force (N) and
    yaw moment (N m)."""
    return jax.tree_util.Partial(_vehicle_forces, vehicle)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class AdaptiveLateralParams:
    """Parameters of :data:`lateral_observer` and :data:`full_observer` (docs/theory/vehicle.md); build with
    :func:`make_adaptive_lateral`.

    Attributes:
      model: the nominal ``model(v, y) -> (f_y*, f_r*)`` (a ``Partial``).  mass: ``m`` (kg).  yaw_inertia: ``J``.
      ay_scale: factor on the measured ``a_y`` (``1 / (1 + p_phi g)``, the roll correction of Grip 2010 §2.2; 1
        for a model without roll).
      K_vy: lateral gain (1/kg).  adaptation_gain: the adaptation gain ``Gamma`` of (3.4), ``Gamma_1`` of (3.14).
      yaw_adaptation_gain: ``Gamma_2`` of (3.14), the adaptation gain on the yaw-rate residual.
      K_r: yaw-rate gain (1/s).  K_vx: longitudinal gain (1/s).  K_c: attraction to ``theta_default`` (1/s).
      theta_default: ``theta*``.  theta_min, theta_max: the clip.  Lambda_min, Lambda_max: the clip of ``Lambda``.
      high_pass_corner: of ``s / (s + c)`` (rad/s).  monitor_time: time constant of the monitor's high-pass (s).
      dt: sample period (s).  vx0: initial ``v_x`` (m/s).
      monitor: :class:`~jaxobs.observers.pe_monitor.PEMonitorParams` for one regressor, or ``None`` (no monitor).
      xi_rule: static, ``"grip"`` or ``"tangent"``.  high_pass: static, filter ``e`` in the update laws.
    """

    model: jax.tree_util.Partial
    mass: jax.Array
    yaw_inertia: jax.Array
    ay_scale: jax.Array
    K_vy: jax.Array
    adaptation_gain: jax.Array
    yaw_adaptation_gain: jax.Array
    K_r: jax.Array
    K_vx: jax.Array
    K_c: jax.Array
    theta_default: jax.Array
    theta_min: jax.Array
    theta_max: jax.Array
    Lambda_min: jax.Array
    Lambda_max: jax.Array
    high_pass_corner: jax.Array
    monitor_time: jax.Array
    dt: jax.Array
    vx0: jax.Array
    monitor: PEMonitorParams | None = None
    xi_rule: str = dataclasses.field(default="grip", metadata=dict(static=True))
    high_pass: bool = dataclasses.field(default=True, metadata=dict(static=True))


_DEFAULTS = dict(
    adaptation_gain=4.0, yaw_adaptation_gain=None, K_r=40.0, K_vx=1.0, K_c=0.5, theta_default=1.0, theta_min=0.1,
    theta_max=1.0, Lambda_min=1e-6, Lambda_max=1e6, high_pass_corner=0.25, monitor_time=1.0, dt=1.0 / SENSOR_RATE,
    vx0=20.0,
)  # fmt: skip


_NUMERIC = tuple(f.name for f in dataclasses.fields(AdaptiveLateralParams))[1:-3]
"""The numeric (scalar) fields of :class:`AdaptiveLateralParams`: all but the model, the monitor and the rules."""


def make_adaptive_lateral(
    vehicle: VehicleParams | None = None, *, model=None, monitor=None, xi_rule="grip", high_pass=True, **settings
) -> AdaptiveLateralParams:
    """Params for ``vehicle`` (default :class:`~jaxobs.vehicle.VehicleParams`) with Vehicle A's gains of Grip 2010
    §3.8 (``K_vy = 1/m``, ``K_r = 40``, ``Gamma_1 = 4``, ``Gamma_2 = 0.1/J``), the settings of §3.7 (``theta`` in
    [0.1, 1], ``Lambda`` in [1e-6, 1e6], high-pass corner 0.25 rad/s) and assumed ``K_vx = 1``, ``K_c = 0.5``,
    ``monitor_time = 1`` (the thesis does not give them), overridden by ``settings``.

    Args:
      vehicle: gives ``mass``, ``yaw_inertia``, the default ``model`` (:func:`vehicle_model`) and with it
        ``ay_scale`` (1 for a user ``model``).
      model: the nominal model ``(v, y) -> (f_y*, f_r*)`` (a function or a ``Partial``), default the vehicle's.
      monitor: :class:`~jaxobs.observers.pe_monitor.PEMonitorParams` with ``n_regressors = 1``
        (:func:`~jaxobs.observers.pe_monitor.make_pe_monitor`), or ``None`` for no monitor.
      xi_rule: ``"grip"`` or ``"tangent"``.  high_pass: filter the residual in the update laws.
      settings: any numeric field of :class:`AdaptiveLateralParams` (``mass``, ``K_vy``, ``adaptation_gain``...);
        concrete values must be positive (``ValueError`` naming the field), ``theta_min < theta_max``.

    Example:
      >>> from jaxobs.vehicle.lateral import make_adaptive_lateral
      >>> params = make_adaptive_lateral(adaptation_gain=5.0)
      >>> float(params.adaptation_gain), float(params.K_vy * params.mass)
      (5.0, 1.0)
    """
    vehicle = check_vehicle(vehicle)
    fields = list(_NUMERIC)
    unknown = sorted(set(settings) - set(fields))
    if unknown:
        raise ValueError(f"unknown settings {unknown}; the fields are {fields}")
    if xi_rule not in ("grip", "tangent"):
        raise ValueError(f"xi_rule must be 'grip' or 'tangent', got {xi_rule!r}")
    if monitor is not None and (not isinstance(monitor, PEMonitorParams) or monitor.n_regressors != 1):
        raise ValueError("monitor must be None or PEMonitorParams with n_regressors = 1 (make_pe_monitor(1, ...))")
    scale = 1.0 / (1.0 + vehicle.roll_gradient * GRAVITY) if model is None else 1.0
    values = dict(_DEFAULTS, mass=vehicle.mass, yaw_inertia=vehicle.yaw_inertia, ay_scale=scale)
    values.update(settings)
    values.setdefault("K_vy", 1.0 / values["mass"])
    if values["yaw_adaptation_gain"] is None:
        values["yaw_adaptation_gain"] = 0.1 / values["yaw_inertia"]
    for name, value in values.items():
        _checks.positive(name, value, allow_zero=name in ("yaw_adaptation_gain", "K_c", "theta_min", "vx0"))
    if _checks.is_concrete(values["theta_min"], values["theta_max"]) and not values["theta_min"] < values["theta_max"]:
        raise ValueError(f"theta_min must be below theta_max, got {values['theta_min']} >= {values['theta_max']}")
    dtype = _checks.float_dtype(**values)
    model = vehicle_model(vehicle) if model is None else _checks.function("model", model)
    arrays = {k: jnp.asarray(v, dtype) for k, v in values.items()}
    return AdaptiveLateralParams(model=model, monitor=monitor, xi_rule=xi_rule, high_pass=high_pass, **arrays)


class AdaptiveLateralState(NamedTuple):
    """State of :data:`lateral_observer` and :data:`full_observer` between samples.

    Attributes:
      x: (4,) the estimate ``(v_x, v_y, r, theta)`` at ``t_{k-1}`` (``v_x``, ``r`` are the measured ones for (3.4)).
      filters: (2,) the low-pass parts of the residual's and the monitor signal's high-pass filters.
      monitor: the excitation monitor's :class:`~jaxobs.observers.pe_monitor.PEMonitorState`, or None.
      y: (N_SENSORS,) the last finite measurement.
      started: () bool, whether a sample has been taken (the first one sets the measured states).
      missing: () int32, non-finite measurement components skipped.
    """

    x: jax.Array
    filters: jax.Array
    monitor: PEMonitorState | None
    y: jax.Array
    started: jax.Array
    missing: jax.Array


class AdaptiveLateralOutputs(NamedTuple):
    """Per-sample outputs of :data:`lateral_observer` and :data:`full_observer`.

    Attributes:
      x: (4,) ``(v_x, v_y, r, theta)`` at ``t_k``.
      beta: () the sideslip ``arctan(v_y / v_x)`` (rad).
      innovation: (2,) ``(m a_y - theta f_y^*, r - r^)`` that drove the interval.
      xi: () the ``xi`` used.
      Lambda: () the ``Lambda`` used.
      excited: () bool, the monitor's verdict (True without a monitor).
    """

    x: jax.Array
    beta: jax.Array
    innovation: jax.Array
    xi: jax.Array
    Lambda: jax.Array
    excited: jax.Array


def _init(params: AdaptiveLateralParams) -> AdaptiveLateralState:
    _checks.fields("params", params, ", ".join(f"{name} ()" for name in _NUMERIC))  # one observer: vmap for a batch
    dtype = params.dt.dtype
    vx0 = params.vx0
    y = jnp.zeros((N_SENSORS,), dtype).at[VX_REF].set(vx0)
    x = jnp.stack([vx0, jnp.zeros((), dtype), jnp.zeros((), dtype), params.theta_default])
    monitor = None if params.monitor is None else pe_monitor.init(params.monitor)
    zero = jnp.zeros((), jnp.int32)
    return AdaptiveLateralState(x, jnp.zeros(2, dtype), monitor, y, jnp.zeros((), bool), zero)


def _step(params: AdaptiveLateralParams, state: AdaptiveLateralState, inputs: EstimatorInputs, *, full: bool):
    dt = params.dt
    y = _checks.vector("inputs.y", inputs.y, N_SENSORS, dt.dtype, what="the ESC sensors", check_finite=False)
    finite = jnp.isfinite(y)
    y_now = jnp.where(finite, y, state.y)
    missing = state.missing + jnp.sum(~finite).astype(jnp.int32)

    m = state.y  # held over [t_{k-1}, t_k]
    ax, r, vref = m[AX], m[YAW_RATE], m[VX_REF]
    _, vy, r_hat, theta = state.x
    vx = state.x[0] if full else vref
    r_model = r_hat if full else r
    forces = lambda vy: params.model(jnp.stack([vx, vy, r_model]), m)
    (f_y, f_r), (slope, zeta) = jax.jvp(forces, (vy,), (jnp.ones_like(vy),))
    ay = m[AY] * params.ay_scale
    may = params.mass * ay

    tiny = 1.0 / params.Lambda_max  # keeps 1 / norm and its derivative finite where f_y* and xi vanish
    norm = jnp.maximum(jnp.sqrt(slope**2 + f_y**2 + tiny**2), tiny)
    if params.xi_rule == "grip":
        exception = (jnp.abs(may) < jnp.abs(theta * f_y)) & (slope > -jnp.abs(f_y))
        xi = jnp.where(exception, -jnp.abs(f_y), slope)
        lam = jnp.where(exception, 0.5 / jnp.maximum(jnp.abs(f_y), tiny), 1.0 / norm)
    else:
        xi, lam = slope, 1.0 / norm
    lam = jnp.clip(lam, params.Lambda_min, params.Lambda_max)

    e = may - theta * f_y
    e_r = (r - r_hat) if full else jnp.zeros_like(r)
    lp_e, lp_s = state.filters
    e_adapt = e - lp_e if params.high_pass else e
    signal = f_y / jnp.maximum(jnp.sqrt(xi**2 + f_y**2 + tiny**2), tiny)
    signal_hp = signal - lp_s
    filters = jnp.stack([lp_e + dt * params.high_pass_corner * (e - lp_e), lp_s + dt / params.monitor_time * signal_hp])
    if params.monitor is None:
        monitor, excited = None, jnp.ones((), bool)
    else:
        monitor, mon = pe_monitor.step(params.monitor, state.monitor, EstimatorInputs(y=jnp.stack([signal_hp, 0 * e])))
        excited = mon.excited

    adapt = params.adaptation_gain * params.K_vy * lam * f_y * e_adapt + params.yaw_adaptation_gain * f_r * e_r
    d_theta = jnp.where(excited, adapt, params.K_c * (params.theta_default - theta))
    d_vy = ay - r * vx + params.K_vy * lam * xi * e
    if full:
        d_vy = d_vy + params.yaw_adaptation_gain / params.adaptation_gain * zeta * e_r
        d_vx = ax + r * vy + params.K_vx * (vref - vx)
        d_r = theta * f_r / params.yaw_inertia + params.K_r * e_r
    else:
        d_vx = d_r = jnp.zeros_like(vy)
    x = state.x + dt * jnp.stack([d_vx, d_vy, d_r, d_theta])
    x = x.at[3].set(jnp.clip(x[3], params.theta_min, params.theta_max))
    if not full:
        x = x.at[0].set(y_now[VX_REF]).at[2].set(y_now[YAW_RATE])

    first = ~state.started
    start = state.x.at[0].set(y_now[VX_REF]).at[2].set(y_now[YAW_RATE])
    x = jnp.where(first, start, x)
    filters = jnp.where(first, jnp.zeros_like(filters), filters)
    beta = jnp.arctan2(x[1], x[0])
    outputs = AdaptiveLateralOutputs(x, beta, jnp.stack([e, e_r]), xi, lam, excited)
    return AdaptiveLateralState(x, filters, monitor, y_now, jnp.ones((), bool), missing), outputs


lateral_observer = Estimator(_init, functools.partial(_step, full=False))
"""The lateral observer (3.4) of Grip 2010 ch. 3 (docs/theory/vehicle.md) over :class:`AdaptiveLateralParams`:
state ``(v_y, theta)`` with ``v_x = v_x,ref`` and ``r`` measured (reported in ``out.x[0]``, ``out.x[2]``). Inputs:
``EstimatorInputs(y)`` with ``y`` (:data:`~jaxobs.vehicle.N_SENSORS`,) (:func:`~jaxobs.vehicle.sensor_inputs`)."""

full_observer = Estimator(_init, functools.partial(_step, full=True))
"""The full observer (3.14) of Grip 2010 ch. 3 (docs/theory/vehicle.md): state ``(v_x, v_y, r, theta)``; as
:data:`lateral_observer` otherwise."""


def lyapunov_3_1(params: AdaptiveLateralParams, vy, theta, vy_hat, theta_hat):
    """Lemma 3.1's ``V = (theta Gamma (v_y - v_y^)^2 + (theta - theta^)^2) / (2 m^2)`` (any shapes that
    broadcast)."""
    return (theta * params.adaptation_gain * (vy - vy_hat) ** 2 + (theta - theta_hat) ** 2) / (2 * params.mass**2)


class Lemma31Check(NamedTuple):
    """Result of :func:`lemma_3_1_check` over a run of ``K`` samples.

    Attributes:
      max_relative_V_increase: () the max over steps of ``(V_{k+1} - V_k) / V_k`` (negative: ``V`` always
        decreases).
      final_V_ratio: () ``V`` at the end over ``V(0)``.
      V: (K,) ``V`` along the run.
      decrease_ratio: (K - 1,) ``(V_k - V_{k+1}) / (dt Gamma K_vy Lambda a_y~^2)``: 1 in continuous time.
    """

    max_relative_V_increase: jax.Array
    final_V_ratio: jax.Array
    V: jax.Array
    decrease_ratio: jax.Array


_C_Y, _D_Y = 3.0e4, 2.0e4  # the check plant's cornering stiffness (N s/m) and steering gain (N/rad)


def _check_model(v, y):
    return jnp.stack([-_C_Y * v[1] + _D_Y * y[STEERING_WHEEL], jnp.zeros_like(v[1])])


def lemma_3_1_check(n_steps: int = 3000, dt: float = 0.01, theta: float = 0.6, vy0: float = 0.5) -> Lemma31Check:
    """Lemma 3.1 along a run of (3.4) on a plant that meets its assumptions: ``m a_y = theta f_y*(v_y, delta)`` with
    ``f_y* = -C v_y + D delta`` (``C = 3e4`` N s/m, ``D = 2e4`` N/rad, ``m = 1600`` kg; its tangent is the exact
    secant of (3.3)), ``v_y' = a_y - r v_x``, ``v_x = 20`` m/s, ``r = 0.2 sin(0.5 t)``, ``delta = 0.3 sin(0.7 t) +
    0.2 sin(1.9 t)``, Euler on the observer's grid. The observer: Vehicle A's gains, ``xi_rule="tangent"``, no
    high-pass, monitor or active projection, from ``v_y = 0``, ``theta = 1``.

    Args:
      n_steps: samples (static).  dt: sample period (s).  theta: the plant's friction scale.  vy0: its initial
        ``v_y`` (m/s).

    Example:
      >>> from jaxobs.vehicle.lateral import lemma_3_1_check
      >>> check = lemma_3_1_check(500)         # float64 (jax_enable_x64) resolves V's per-step decrease
      >>> bool(check.final_V_ratio < 0.5)
      True
    """
    n = _checks.count("n_steps", n_steps, minimum=2)
    _checks.positive_scalar("dt", dt)
    _checks.positive_scalar("theta", theta)
    mass = 1600.0
    params = make_adaptive_lateral(
        model=_check_model, mass=mass, xi_rule="tangent", high_pass=False, theta_min=1e-3, theta_max=10.0,
        vx0=20.0, dt=dt,
    )  # fmt: skip
    dtype = params.dt.dtype
    t = jnp.asarray(dt, dtype) * jnp.arange(n, dtype=dtype)
    y = jnp.zeros((n, N_SENSORS), dtype)
    y = y.at[:, YAW_RATE].set(0.2 * jnp.sin(0.5 * t)).at[:, VX_REF].set(20.0)
    y = y.at[:, STEERING_WHEEL].set(0.3 * jnp.sin(0.7 * t) + 0.2 * jnp.sin(1.9 * t))
    ay = lambda vy, yk: theta * _check_model(jnp.stack([yk[VX_REF], vy, yk[YAW_RATE]]), yk)[0] / mass

    def plant(vy, yk):
        return vy + dt * (ay(vy, yk) - yk[YAW_RATE] * yk[VX_REF]), vy

    _, vy = jax.lax.scan(plant, jnp.asarray(vy0, dtype), y)
    y = y.at[:, AY].set(jax.vmap(ay)(vy, y))
    _, out = run(lateral_observer, params, EstimatorInputs(y=y))
    V = lyapunov_3_1(params, vy, theta, out.x[:, 1], out.x[:, 3])
    predicted = dt * params.adaptation_gain * params.K_vy * out.Lambda[1:] * (out.innovation[1:, 0] / mass) ** 2
    return Lemma31Check(jnp.max(jnp.diff(V) / V[:-1]), V[-1] / V[0], V, -jnp.diff(V) / predicted)
