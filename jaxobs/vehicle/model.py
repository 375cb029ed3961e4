"""Planar two-track vehicle model: body velocities, yaw rate, wheel spin, tyre relaxation, load transfer.

:class:`VehicleState` holds ``vx``, ``vy``, the yaw rate ``r``, the wheel speeds, the relaxed lateral slips and the
lagged accelerations of the load transfer; wheels are ordered FL, FR, RL, RR. :func:`dynamics` is the right-hand
side (road inclination and bank as in Grip 2010 (2.11)-(2.12)), :func:`forces` the tyre forces and their sums,
:func:`friction_model` and :func:`lateral_acceleration` the observers' friction model. Below :data:`MIN_SPEED`
the model is not meant to be used. The equations and the load transfer: docs/theory/vehicle.md.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.vehicle.tyres import TyreParams, pure_force, tyre_forces

__all__ = [
    "GRAVITY",
    "MIN_SPEED",
    "VehicleParams",
    "VehicleState",
    "Inputs",
    "Forces",
    "wheel_kinematics",
    "normal_loads",
    "forces",
    "dynamics",
    "steady_state",
    "friction_model",
    "lateral_acceleration",
    "understeer_gradient",
    "reference_yaw_rate",
    "broadcast",
    "check_vehicle",
]

GRAVITY = 9.81
"""Gravitational acceleration (m/s^2)."""
MIN_SPEED = 3.0
"""Standstill guard (m/s): the wheel speed over ground below which slips and relaxation rates use this value."""
AIR_DENSITY = 1.2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class VehicleParams:
    """A rear-wheel-drive passenger car. The defaults are assumed values of a typical mid-size car (Grip 2010
    used a rear-wheel-drive passenger car whose data are not published); each field says its source.

    Attributes:
      mass: total mass (kg, > 0); 1600 kg assumed.
      yaw_inertia: yaw moment of inertia ``I_z`` (kg m^2, > 0); 2800 assumed (about ``m l_f l_r 1.2``).
      lf, lr: distances from the centre of gravity to the front and rear axles (m, > 0; wheelbase ``lf + lr``);
        1.35 and 1.45 assumed.
      track_front, track_rear: track widths (m, > 0); 1.58 and 1.60 assumed.
      cg_height: height of the centre of gravity (m, >= 0); 0.55 assumed.
      roll_share_front: front share ``chi_f`` of the roll stiffness, hence of the lateral load transfer
        (in [0, 1]); 0.55 assumed (understeering set-up).
      wheel_radius: rolling radius ``R`` (m, > 0); 0.32 assumed (a 225/45 R18 tyre).
      wheel_inertia: spin inertia ``J`` of a wheel with its share of the drive line (kg m^2, > 0); 1.2 assumed.
      steering_ratio: steering-wheel angle over road-wheel angle (> 0); 15.5 assumed.
      relaxation_length: lateral relaxation length ``l_relax`` (m, > 0); 0.5 assumed.
      load_time_constant: lag ``tau`` of the load transfer (s, > 0); 0.05 assumed.
      drag_area: ``c_d A`` (m^2, >= 0); 0.65 assumed (``c_d`` 0.29, frontal area 2.25 m^2).
      roll_gradient: roll angle per lateral acceleration ``p_phi`` (rad per m/s^2, >= 0); 0.0085 assumed (about
        4.8 deg per g); Grip 2010 §2.2 divides the accelerometer's ``a_y`` by ``1 + p_phi g``.
      brake_share_front: front share of a braking torque (in [0, 1]); 0.65 assumed.
      tyre_front, tyre_rear: the tyres of the front and rear axles (:class:`jaxobs.vehicle.TyreParams` or
        ``BurckhardtTyre``, the same family on both). The defaults are :class:`TyreParams` with cornering
        stiffnesses 15 (front) and 22 (rear) per rad per unit load, assumed: the front value is an effective
        one that includes steering compliance, and the pair gives the linear understeer gradient
        ``(1/c_f - 1/c_r) / g`` of 0.0022 rad per m/s^2 (1.2 deg of road-wheel angle per g).
    """

    mass: float = 1600.0
    yaw_inertia: float = 2800.0
    lf: float = 1.35
    lr: float = 1.45
    track_front: float = 1.58
    track_rear: float = 1.60
    cg_height: float = 0.55
    roll_share_front: float = 0.55
    wheel_radius: float = 0.32
    wheel_inertia: float = 1.2
    steering_ratio: float = 15.5
    relaxation_length: float = 0.5
    load_time_constant: float = 0.05
    drag_area: float = 0.65
    roll_gradient: float = 0.0085
    brake_share_front: float = 0.65
    tyre_front: TyreParams = dataclasses.field(default_factory=lambda: TyreParams(cornering_stiffness=15.0))
    tyre_rear: TyreParams = dataclasses.field(default_factory=lambda: TyreParams(cornering_stiffness=22.0))

    def validate(self) -> None:
        """Raise ``ValueError`` naming the bad field (concrete values only; skipped under tracing)."""
        for name in ("mass", "yaw_inertia", "lf", "lr", "track_front", "track_rear", "wheel_radius"):
            _checks.positive(name, getattr(self, name))
        for name in ("wheel_inertia", "steering_ratio", "relaxation_length", "load_time_constant"):
            _checks.positive(name, getattr(self, name))
        for name in ("cg_height", "drag_area", "roll_gradient"):
            _checks.positive(name, getattr(self, name), allow_zero=True)
        for name in ("roll_share_front", "brake_share_front"):
            _checks.positive(name, getattr(self, name), allow_zero=True, what="a share in [0, 1]")
            _checks.positive(name, 1.0 - getattr(self, name), allow_zero=True, what="a share <= 1")
        self.tyre_front.validate()
        self.tyre_rear.validate()

    @property
    def wheelbase(self):
        """Wheelbase ``lf + lr`` (m)."""
        return self.lf + self.lr


class VehicleState(NamedTuple):
    """State of the two-track model (docs/theory/vehicle.md); wheels ordered FL, FR, RL, RR.

    Attributes:
      vx: () longitudinal velocity at the centre of gravity (m/s, body frame)
      vy: () lateral velocity at the centre of gravity (m/s, body frame, positive to the left)
      r: () yaw rate (rad/s, counter-clockwise)
      omega: (4,) wheel angular speeds (rad/s)
      tan_alpha: (4,) relaxed lateral slips tan(alpha)
      ax_lt: () lagged a_x of the load transfer (m/s^2)
      ay_lt: () lagged a_y of the load transfer (m/s^2)
    """

    vx: jax.Array
    vy: jax.Array
    r: jax.Array
    omega: jax.Array
    tan_alpha: jax.Array
    ax_lt: jax.Array
    ay_lt: jax.Array

    def check(self, name: str) -> VehicleState:
        """The state, its fields' shapes checked at trace time (one vehicle: ``vmap`` for a batch), naming
        ``name.field``."""
        _checks.fields(name, self, "vx (), vy (), r (), omega (4,), tan_alpha (4,), ax_lt (), ay_lt ()")
        return self


class Inputs(NamedTuple):
    """Plant inputs at one instant.

    Attributes:
      steering_wheel: () steering-wheel angle (rad)
      torque: (4,) wheel torques (N m, driving > 0)
      bank: () road bank ``Phi`` (rad, sign of Grip 2010 (2.12))
      inclination: () road inclination ``Theta`` (rad, sign of Grip 2010 (2.11))
      friction: () friction scale of the road (1 = the tyre's own ``mu``; it multiplies the tyre's peak friction)
    """

    steering_wheel: jax.Array
    torque: jax.Array
    bank: jax.Array = 0.0
    inclination: jax.Array = 0.0
    friction: jax.Array = 1.0


class Forces(NamedTuple):
    """Per-wheel quantities (4,) and body-frame sums at one instant.

    Attributes:
      fx_wheel: (4,) longitudinal tyre forces in the wheel frames (N)
      fy_wheel: (4,) lateral tyre forces in the wheel frames (N)
      fz: (4,) normal loads (N)
      kappa: (4,) longitudinal slips
      tan_alpha_ss: (4,) steady-state lateral slips
      v_long: (4,) wheel-centre speeds along the wheel planes (m/s)
      ax: () specific force a_x (m/s^2)
      ay: () specific force a_y (m/s^2)
      yaw_moment: () yaw moment of the tyre forces (N m)
    """

    fx_wheel: jax.Array
    fy_wheel: jax.Array
    fz: jax.Array
    kappa: jax.Array
    tan_alpha_ss: jax.Array
    v_long: jax.Array
    ax: jax.Array
    ay: jax.Array
    yaw_moment: jax.Array


def _geometry(p: VehicleParams):
    x = jnp.stack(jnp.broadcast_arrays(p.lf, p.lf, -p.lr, -p.lr))
    y = jnp.stack(jnp.broadcast_arrays(p.track_front / 2, -p.track_front / 2, p.track_rear / 2, -p.track_rear / 2))
    return x, y


def _scaled(tyre, friction):
    """``tyre`` on a road whose friction is ``friction`` times the tyre's own (peak scaled, stiffness kept)."""
    if isinstance(tyre, TyreParams):
        return dataclasses.replace(tyre, mu=tyre.mu * friction)
    return dataclasses.replace(tyre, c1=tyre.c1 * friction, c3=tyre.c3 * friction)


def wheel_kinematics(p: VehicleParams, vx, vy, r, steering_wheel):
    """Wheel-centre velocities in the wheel frames and the road-wheel angles: ``(v_l, v_s, delta)``, each (4,), of
    the scalars ``vx``, ``vy``, ``r`` and ``steering_wheel`` (``vmap`` for a batch)."""
    p = check_vehicle(p, "p")
    vx, vy, r, steering_wheel = _checks.arrays("vx (), vy (), r (), steering_wheel ()", vx, vy, r, steering_wheel)
    x, y = _geometry(p)
    d = steering_wheel / p.steering_ratio
    delta = jnp.stack(jnp.broadcast_arrays(d, d, 0.0 * d, 0.0 * d))
    vwx, vwy = vx - r * y, vy + r * x
    c, s = jnp.cos(delta), jnp.sin(delta)
    return vwx * c + vwy * s, -vwx * s + vwy * c, delta


def normal_loads(p: VehicleParams, ax, ay, bank=0.0, inclination=0.0):
    """Quasi-static normal loads (4,) (N) at the accelerations ``ax``, ``ay`` (m/s^2), clipped at 0 (wheel lift);
    scalars (``vmap`` for a batch)."""
    p = check_vehicle(p, "p")
    ax, ay, bank, inclination = _checks.arrays("ax (), ay (), bank (), inclination ()", ax, ay, bank, inclination)
    L = p.wheelbase
    w = p.mass * GRAVITY * jnp.cos(inclination) * jnp.cos(bank)
    front = (w * p.lr / L - p.mass * ax * p.cg_height / L) / 2
    rear = (w * p.lf / L + p.mass * ax * p.cg_height / L) / 2
    dyf = p.mass * ay * p.cg_height * p.roll_share_front / p.track_front
    dyr = p.mass * ay * p.cg_height * (1 - p.roll_share_front) / p.track_rear
    return jnp.maximum(jnp.stack([front - dyf / 2, front + dyf / 2, rear - dyr / 2, rear + dyr / 2]), 0.0)


def forces(p: VehicleParams, x: VehicleState, u: Inputs) -> Forces:
    """Tyre forces, loads and slips of state ``x`` under inputs ``u`` (the lateral slips are the relaxed states)."""
    VehicleState.check(x, "x")
    _checks.fields("u", u, "steering_wheel (), torque (4,), bank (), inclination (), friction ()")
    v_l, v_s, delta = wheel_kinematics(p, x.vx, x.vy, x.r, u.steering_wheel)
    speed = jnp.maximum(jnp.abs(v_l), MIN_SPEED)
    kappa = (x.omega * p.wheel_radius - v_l) / speed
    fz = normal_loads(p, x.ax_lt, x.ay_lt, u.bank, u.inclination)
    front = tyre_forces(_scaled(p.tyre_front, u.friction), kappa[:2], x.tan_alpha[:2], fz[:2])
    rear = tyre_forces(_scaled(p.tyre_rear, u.friction), kappa[2:], x.tan_alpha[2:], fz[2:])
    fxw, fyw = jnp.concatenate([front[0], rear[0]]), jnp.concatenate([front[1], rear[1]])
    c, s = jnp.cos(delta), jnp.sin(delta)
    fx, fy = fxw * c - fyw * s, fxw * s + fyw * c
    gx, gy = _geometry(p)
    drag = 0.5 * AIR_DENSITY * p.drag_area * x.vx * jnp.abs(x.vx)
    return Forces(
        fx_wheel=fxw,
        fy_wheel=fyw,
        fz=fz,
        kappa=kappa,
        tan_alpha_ss=-v_s / speed,
        v_long=v_l,
        ax=(jnp.sum(fx) - drag) / p.mass,
        ay=jnp.sum(fy) / p.mass,
        yaw_moment=jnp.sum(gx * fy - gy * fx),
    )


def dynamics(p: VehicleParams, x: VehicleState, u: Inputs) -> VehicleState:
    """The time derivative of the state (docs/theory/vehicle.md) under the inputs ``u``."""
    f = forces(p, x, u)
    speed = jnp.maximum(jnp.abs(f.v_long), MIN_SPEED)
    return VehicleState(
        vx=f.ax + x.r * x.vy + GRAVITY * jnp.sin(u.inclination),
        vy=f.ay - x.r * x.vx - GRAVITY * jnp.cos(u.inclination) * jnp.sin(u.bank),
        r=f.yaw_moment / p.yaw_inertia,
        omega=(u.torque - p.wheel_radius * f.fx_wheel) / p.wheel_inertia,
        tan_alpha=speed / p.relaxation_length * (f.tan_alpha_ss - x.tan_alpha),
        ax_lt=(f.ax - x.ax_lt) / p.load_time_constant,
        ay_lt=(f.ay - x.ay_lt) / p.load_time_constant,
    )


def steady_state(p: VehicleParams, vx, vy=0.0, r=0.0, steering_wheel=0.0, ax=0.0, ay=None) -> VehicleState:
    """A state with free-rolling wheels, relaxed slips and the load transfer of ``ax`` and ``ay`` (default
    ``ay = r vx``), e.g. the initial state of a manoeuvre. Scalars (``vmap`` for a batch), finite where concrete."""
    for name, value in (("vx", vx), ("vy", vy), ("r", r), ("steering_wheel", steering_wheel), ("ax", ax), ("ay", ay)):
        if value is not None:
            _checks.finite(name, _checks.real_array(name, value))
    _checks.shapes("vx (), vy (), r (), steering_wheel (), ax (), ay ()", vx, vy, r, steering_wheel, ax, ay)
    dtype = jnp.result_type(vx, vy, r, float)
    vx, vy, r = (jnp.asarray(v, dtype) for v in (vx, vy, r))
    v_l, v_s, _ = wheel_kinematics(p, vx, vy, r, steering_wheel)
    speed = jnp.maximum(jnp.abs(v_l), MIN_SPEED)
    ay = r * vx if ay is None else ay
    return VehicleState(
        vx=vx,
        vy=vy,
        r=r,
        omega=v_l / p.wheel_radius,
        tan_alpha=-v_s / speed,
        ax_lt=jnp.asarray(ax, dtype),
        ay_lt=jnp.asarray(ay, dtype),
    )


def friction_model(p: VehicleParams, vx, vy, r, steering_wheel, omega, ax, ay, friction=1.0) -> Forces:
    """The road-tyre friction model an observer evaluates (Grip 2010 §2.2, §2.8): the :class:`Forces` of the
    velocities ``vx``, ``vy``, yaw rate ``r``, steering-wheel angle and wheel speeds ``omega`` (4,) with
    steady-state (unrelaxed) slips and the normal loads of the given (measured) ``ax``, ``ay``."""
    vx, vy, r, steering_wheel, omega, ax, ay, friction = _checks.arrays(
        "vx (), vy (), r (), steering_wheel (), omega (4,), ax (), ay (), friction ()",
        vx, vy, r, steering_wheel, omega, ax, ay, friction,
    )  # fmt: skip
    v_l, v_s, _ = wheel_kinematics(p, vx, vy, r, steering_wheel)
    x = VehicleState(vx, vy, r, omega, -v_s / jnp.maximum(jnp.abs(v_l), MIN_SPEED), ax, ay)
    return forces(p, x, Inputs(steering_wheel, jnp.zeros(4), friction=friction))


def lateral_acceleration(p: VehicleParams, vx, vy, r, steering_wheel, omega, ax, ay, friction=1.0):
    """The friction model's ``a_y`` (m/s^2, :func:`friction_model`): the ``a_y(v_y)`` of Grip 2010 §2.2 whose
    strict decrease in ``v_y`` the sideslip observer relies on."""
    return friction_model(p, vx, vy, r, steering_wheel, omega, ax, ay, friction).ay


def understeer_gradient(vehicle: VehicleParams):
    """``(1/c_f - 1/c_r) / g`` with ``c`` the slope of each axle's pure lateral force per unit load at zero slip."""
    vehicle = check_vehicle(vehicle)
    fz = vehicle.mass * GRAVITY / 4
    stiffness = lambda tyre: jax.grad(lambda s: pure_force(tyre, s, fz))(jnp.zeros((), jnp.result_type(fz))) / fz
    return (1.0 / stiffness(vehicle.tyre_front) - 1.0 / stiffness(vehicle.tyre_rear)) / GRAVITY


def reference_yaw_rate(vehicle: VehicleParams, vx, steering_wheel):
    """The yaw rate of the linear single track in steady state, ``v_x delta / (L + K_us v_x^2)`` (rad/s) with
    ``delta`` the road-wheel angle and ``K_us`` the :func:`understeer_gradient`: the reference of the friction
    switch (Grip 2010 §2.5) and of the simulated ESC (:func:`jaxobs.vehicle.esc_intervention`). Scalars (``vmap``
    for a batch)."""
    vx, steering_wheel = _checks.arrays("vx (), steering_wheel ()", vx, steering_wheel)
    delta = steering_wheel / vehicle.steering_ratio
    K_us = understeer_gradient(vehicle).astype(vx.dtype)  # the vehicle's Python floats would give float64
    return vx * delta / (vehicle.wheelbase + K_us * vx**2)


def broadcast(params, n: int):
    """``params`` with every leaf broadcast to a leading batch axis of ``n`` (for ``vmap`` over a sweep in which
    only some fields vary: set those fields to ``(n,)`` arrays first)."""
    n = _checks.count("n", n, minimum=1)
    return jax.tree_util.tree_map(lambda leaf: jnp.broadcast_to(leaf, (n, *jnp.shape(leaf)[1:])), params)


def check_vehicle(vehicle, name: str = "vehicle") -> VehicleParams:
    """``vehicle`` checked: a :class:`VehicleParams` (``None``: the default one) whose concrete fields are valid
    (:meth:`VehicleParams.validate`) and scalar (at trace time too: ``vmap`` for a batch of vehicles);
    ``ValueError`` naming ``name`` (or the bad field) otherwise."""
    vehicle = VehicleParams() if vehicle is None else vehicle
    if not isinstance(vehicle, VehicleParams):
        raise ValueError(f"{name} must be a VehicleParams, got {type(vehicle).__name__}")
    for path, leaf in jax.tree_util.tree_flatten_with_path(vehicle)[0]:
        _checks.shapes(f"{name}{jax.tree_util.keystr(path)} ()", leaf)
    vehicle.validate()
    return vehicle
