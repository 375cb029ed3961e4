"""Cortesão 2006, "On Kalman Active Observers" (Cortesão 2006), Example 2 (§8): steer-by-wire (SBW) model
matching with a MIMO AOB-1.

The SBW plant (eq. 95-99, four inputs, two actuated) is made to behave like a conventional car (eq. 90-94) by
state feedback ``L_r`` for the poles of eq. 100-101 (decoupled or coupled), the DC-gain compensation ``L_c`` of
eq. 102-105 and an AOB-1 with one active state per input (eq. 108-110). Both signs of the road force ``F_r`` are
run (``road_force_sign``; see docs/reproductions.md). The design: docs/theory/papers.md.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs.design import acker, dc_compensation, place
from jaxobs.lti import StateSpace, c2d, dcgain, ss, tf2ss
from jaxobs.observers.active import active_observer_controller, feedback_gain, make_aob
from jaxobs.observers.base import ControllerInputs
from jaxobs.observers.feedback import FeedbackParams
from jaxobs.papers._output import pyplot, save_figure, write_reproduction
from jaxobs.papers.scenarios import Reproduction

NAME = "cortesao2006-example2"

H = 1.0e-3  # T_s = 1 ms (§8.4)
INPUTS = ("T_h", "tau_m", "F_r", "f_s")
OUTPUTS = ("d delta_h/dt [rad/s]", "d x_r/dt [m/s]")
NON_ACTUATED = (0, 2)  # T_h and F_r: columns of Gamma_r zeroed for the design (eq. 101 text)
ACTUATED = (1, 3)  # tau_m and f_s
STEERING_STATES = slice(0, 5)  # y_h (3) and alpha_h (2) in the realisation of sbw_model
RACK_STATES = slice(5, 7)  # y_r (1) and alpha_r (1)

# Eq. 91-94: target (conventional car at v = 80 km/h, mu = 0.8), entries (output, input), common denominator.
TARGET_DEN = (1.0, 20.71, 7655.0, 45790.0)
T11 = (33.33, 44.87, 93690.0)
T13 = (1.295, 894.6)
T21 = (-1.295, -894.6)
T23 = (-0.001789, -0.01296, -8.543)
# Eq. 95-98: identified SBW transfer functions (numerator, denominator).
Y_H = ((26.67, 568.0, 218300.0), (1.0, 28.1, 16430.0, 120000.0))
Y_R = ((-0.00179,), (1.0, 9.395))
ALPHA_H = ((-13510.0,), (1.0, 21.3, 8188.0))
ALPHA_R = ((1974000.0,), (1.0, 1885.0))

PRINTED_TARGET_POLES = (0.9890 + 0.0859j, 0.9890 - 0.0859j, 0.9940)  # eq. 100
EXTRA_POLES = (0.89, 0.89, -0.89, 0.994)  # eq. 101
RACK_POLES = (0.89, 0.994)  # decoupled design: the rack loop (f_s) gets these two, the steering loop the rest
PRINTED_L_C = ((0.4785, -0.0046), (67.0076, -0.6399))  # eq. 105
PRINTED_EQ114 = (-0.27, 0.61)  # eq. 114: [p_2, p_4] after the road disturbance
Q_PLANT = 1e-12  # eq. 108
Q_ACTIVE = (0.0, 1e-1, 0.0, 1e3)  # eq. 109
R_MEAS = 4.0  # R_k = 4 I
ROAD_DISTURBANCE = 1000.0  # tau_D [N], Fig. 9a
DISTURBANCE_TIME = 1.0  # s


# ------------------------------------------------------------------------------------------------
# Models


def target_model(road_force_sign: float = 1.0) -> StateSpace:
    """Eq. 90-94 as a continuous state space with inputs ``[T_h, tau_m, F_r, f_s]`` (the ``tau_m`` and
    ``f_s`` columns are zero) and outputs ``[d delta_h/dt, d x_r/dt]``.

    Realised entry by entry with :func:`jaxobs.lti.tf2ss` (12 states, not minimal: every entry
    repeats the common denominator; harmless for the DC gain and the simulation).
    ``road_force_sign=-1`` flips the ``F_r`` column (the convention behind the printed eq. 105).
    """
    if road_force_sign not in (1.0, -1.0):
        raise ValueError(f"road_force_sign must be +1 or -1, got {road_force_sign}")
    zero = (0.0,)
    f13 = tuple(road_force_sign * c for c in T13)
    f23 = tuple(road_force_sign * c for c in T23)
    num = [[T11, zero, f13, zero], [T21, zero, f23, zero]]
    den = [[TARGET_DEN] * 4, [TARGET_DEN] * 4]
    return tf2ss(num, den)


def _series_loop(y, alpha) -> tuple[np.ndarray, ...]:
    """``s q = y (u_direct - alpha u_actuator)`` (eq. 86-87) as one realisation with inputs
    ``[u_direct, u_actuator]``: state ``[x_y, x_alpha]``, output ``s q``."""
    Y, A = tf2ss(*y), tf2ss(*alpha)
    if np.any(np.asarray(Y.D)) or np.any(np.asarray(A.D)):
        raise ValueError("y and alpha must be strictly proper for the series realisation")
    Ay, By, Cy = (np.asarray(M) for M in (Y.A, Y.B, Y.C))
    Aa, Ba, Ca = (np.asarray(M) for M in (A.A, A.B, A.C))
    ny, na = Ay.shape[0], Aa.shape[0]
    Am = np.block([[Ay, -By @ Ca], [np.zeros((na, ny)), Aa]])
    Bm = np.block([[By, np.zeros((ny, 1))], [np.zeros((na, 1)), Ba]])
    Cm = np.concatenate([Cy, np.zeros((1, na))], axis=1)
    return Am, Bm, Cm


ACTUATOR_MODELS = ("y_h", "alpha_h", "y_r", "alpha_r")  # eq. 95, 97, 96, 98


def scaled_transfer_function(tf, gain=1.0, pole=1.0):
    """``(num, den)`` with the gain scaled by ``gain`` and every pole by ``pole``: the numerator times
    ``gain``, the monic denominator's ``s^{n-i}`` coefficient times ``pole^i`` (roots ``p -> pole p``)."""
    if gain == 0 or pole <= 0:
        raise ValueError(f"gain must be non-zero and pole > 0, got gain={gain}, pole={pole}")
    num, den = (np.asarray(c, float) for c in tf)
    return gain * num, den * float(pole) ** np.arange(den.size)


def sbw_model(mismatch: dict | None = None) -> StateSpace:
    """Eq. 99 (from eq. 86-89, 95-98) as a 7-state continuous model, inputs ``[T_h, tau_m, F_r, f_s]``,
    outputs ``[d delta_h/dt, d x_r/dt]``. States: ``y_h`` (3), ``alpha_h`` (2), ``y_r`` (1), ``alpha_r`` (1).

    ``mismatch``: optional ``{name: (gain_scale, pole_scale)}`` for names in :data:`ACTUATOR_MODELS`
    (:func:`scaled_transfer_function`), a plant whose identified actuator models are off."""
    mismatch = mismatch or {}
    unknown = set(mismatch) - set(ACTUATOR_MODELS)
    if unknown:
        raise ValueError(f"mismatch keys must be among {ACTUATOR_MODELS}, got {sorted(unknown)}")
    tfs = {
        name: scaled_transfer_function(tf, *mismatch.get(name, (1.0, 1.0)))
        for name, tf in zip(ACTUATOR_MODELS, (Y_H, ALPHA_H, Y_R, ALPHA_R), strict=True)
    }
    As, Bs, Cs = _series_loop(tfs["y_h"], tfs["alpha_h"])
    Ar, Br, Cr = _series_loop(tfs["y_r"], tfs["alpha_r"])
    ns, nr = As.shape[0], Ar.shape[0]
    A = np.block([[As, np.zeros((ns, nr))], [np.zeros((nr, ns)), Ar]])
    B = np.zeros((ns + nr, 4))
    B[:ns, 0:2] = Bs
    B[ns:, 2:4] = Br
    C = np.zeros((2, ns + nr))
    C[0, :ns] = Cs[0]
    C[1, ns:] = Cr[0]
    return ss(A, B, C)


def with_positions(sys: StateSpace) -> StateSpace:
    """Append two integrators ``delta_h, x_r`` of the velocity outputs as states (the outputs stay the
    velocities), so that the discretised model carries the exact positions for the figures."""
    A, B, C = (np.asarray(M) for M in (sys.A, sys.B, sys.C))
    n, m = B.shape
    A2 = np.block([[A, np.zeros((n, 2))], [C, np.zeros((2, 2))]])
    B2 = np.concatenate([B, np.zeros((2, m))])
    C2 = np.concatenate([C, np.zeros((2, 2))], axis=1)
    return ss(A2, B2, C2)


def frequency_response(sys: StateSpace, s) -> np.ndarray:
    """``C (s I - A)^{-1} B + D`` of a continuous model at the complex points ``s``: shape (len(s), p, m)."""
    A, B, C, D = (np.asarray(M) for M in (sys.A, sys.B, sys.C, sys.D))
    eye = np.eye(A.shape[0])
    return np.stack([C @ np.linalg.solve(si * eye - A, B) + D for si in np.atleast_1d(s)])


def printed_transfer_matrices(s, road_force_sign: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The printed eq. 90-94 (target) and eq. 99 (SBW) evaluated at ``s``: two arrays (len(s), 2, 4)."""
    s = np.atleast_1d(s)
    tf = lambda num, den: np.polyval(num, s) / np.polyval(den, s)
    target = np.zeros((s.size, 2, 4), complex)
    target[:, 0, 0] = tf(T11, TARGET_DEN)
    target[:, 0, 2] = road_force_sign * tf(T13, TARGET_DEN)
    target[:, 1, 0] = tf(T21, TARGET_DEN)
    target[:, 1, 2] = road_force_sign * tf(T23, TARGET_DEN)
    yh, yr, ah, ar = (tf(*g) for g in (Y_H, Y_R, ALPHA_H, ALPHA_R))
    sbw = np.zeros((s.size, 2, 4), complex)
    sbw[:, 0, 0], sbw[:, 0, 1] = yh, -ah * yh
    sbw[:, 1, 2], sbw[:, 1, 3] = yr, -ar * yr
    return target, sbw


# ------------------------------------------------------------------------------------------------
# Design


def target_poles() -> np.ndarray:
    """The discrete target poles ``exp(h s_i)`` of eq. 91-94 (unrounded eq. 100), complex pair first."""
    target = np.exp(np.roots(TARGET_DEN) * H)
    return target[np.argsort(-np.abs(target.imag))]


def design_poles(printed: bool = True) -> np.ndarray:
    """The seven closed-loop poles [eq. 100 (3), 0.89, 0.89, -0.89, 0.994] (eq. 101).

    ``printed=True`` uses eq. 100 as printed (4 decimals), which reproduces row 1 of the printed
    ``L_c`` (0.4784 vs 0.4785); ``False`` uses the unrounded target poles (row 1 then 0.4811)."""
    target = np.asarray(PRINTED_TARGET_POLES, complex) if printed else target_poles()
    return np.concatenate([target, np.asarray(EXTRA_POLES, complex)])


def state_feedback(plant: StateSpace, method: str = "decoupled", poles=None) -> np.ndarray:
    """``L_r`` (4 x 7) for the poles of eq. 100-101 with no feedback to ``T_h`` and ``F_r``.

    ``method="decoupled"``: the plant is two separate loops (steering wheel: states 0-4 with input
    ``tau_m``; rack: states 5-6 with input ``f_s``); each gets its own single-input Ackermann design,
    the rack the poles ``{0.89, 0.994}`` and the steering wheel the other five. ``L_r`` is block
    diagonal and independent of the state coordinates.

    ``method="coupled"``: one MIMO :func:`jaxobs.design.place` (SciPy's Tits-Yang) on the whole plant
    with the ``T_h``/``F_r`` columns zeroed (footnote 17's MATLAB ``place``). The eigenvalues are the
    same, but the algorithm also picks the eigenvectors and with them which loop gets which pole; it
    may add cross gains between the loops, and then the closed-loop DC gain, hence row 2 of ``L_c``,
    depends on the algorithm and the state coordinates. With the printed eq. 100 poles SciPy lands
    (not converged to its tolerance) on the decoupled assignment (cross gains below 1e-6); MATLAB's
    ``place`` evidently did not (printed row 2 is 1 % from the decoupled one), and cannot be replicated.
    """
    poles = design_poles() if poles is None else np.asarray(poles, complex)
    Phi, Gamma = np.asarray(plant.A), np.asarray(plant.B)
    if method == "coupled":
        return place(Phi, Gamma, poles, zero_input_columns=NON_ACTUATED)
    if method != "decoupled":
        raise ValueError(f"method must be 'decoupled' or 'coupled', got {method!r}")
    rack = list(RACK_POLES)
    rest = list(poles)
    for p in rack:  # remove one copy of each rack pole from the full set
        i = int(np.argmin(np.abs(np.asarray(rest) - p)))
        if abs(rest[i] - p) > 1e-12:
            raise ValueError(f"poles must contain the rack poles {RACK_POLES} for the decoupled design")
        rest.pop(i)
    L = np.zeros((4, Phi.shape[0]))
    for states, column, sub_poles in ((STEERING_STATES, 1, rest), (RACK_STATES, 3, rack)):
        L[column, states] = np.asarray(acker(Phi[states, states], Gamma[states, column : column + 1], sub_poles))[0]
    return L


def closed_loop(plant: StateSpace, L_r) -> StateSpace:
    """``(Phi - Gamma L_r, Gamma, C)``: the SBW closed loop seen from the reference ``r_k`` (eq. 103)."""
    return dataclasses.replace(plant, A=plant.A - plant.B @ jnp.asarray(L_r))


def reference_gain(target: StateSpace, plant: StateSpace, L_r) -> jax.Array:
    """``L_c = (SBW DC)^{-1} (target DC)`` (eq. 102-104), both DC gains from ``[T_h; F_r]`` to the outputs."""
    cols = list(NON_ACTUATED)
    dc_target = dcgain(target)[:, cols]
    dc_sbw = dcgain(closed_loop(plant, L_r))[:, cols]
    return dc_compensation(dc_target, dc_sbw)


def active_state_limit(L_c, tau_D: float = ROAD_DISTURBANCE) -> np.ndarray:
    """Eq. 113: ``[p_2; p_4] -> -diag(alpha_h, alpha_r)(0)^{-1} L_c [0; tau_D]``."""
    a0 = np.array([ALPHA_H[0][-1] / ALPHA_H[1][-1], ALPHA_R[0][-1] / ALPHA_R[1][-1]])
    return -(np.asarray(L_c) @ np.array([0.0, tau_D])) / a0


def actuation_point_filter(L_c, cutoff: float = 2 * np.pi * 100.0, h: float = H, *, closed_loop=None) -> StateSpace:
    """Eq. 107: the reference pre-amplification moved to the actuators, as a discrete filter from
    ``[T_h; F_r]`` to the feed-forward commands ``[tau_m; f_s]``.

    ``closed_loop=None`` (eq. 107 as printed): from eq. 88, ``s q = y (u_direct - alpha u_actuator)``,
    the actuator command that makes the entry point see ``L_c [T_h; F_r]`` is
    ``-alpha^{-1} (L_c - I) [T_h; F_r]`` (the minus sign of eq. 88 written out). ``alpha_h^{-1}`` and
    ``alpha_r^{-1}`` are improper, so they are multiplied by the low-pass filters ``(w / (s + w))^k``
    (``k`` = 2 and 1, the relative degrees, ``w = cutoff`` [rad/s]), then discretised (ZOH, step ``h``).

    This inverts the *open-loop* actuators. In the loop the command ``r_k`` passes through
    ``Phi - Gamma L_r``, and ``L_r`` feeds back the actuator states themselves: the rack actuator's
    discrete pole moves from 0.152 to about 0.89, so the feed-forward reaches the rack about 8 times
    stronger at DC than eq. 107 assumes, which turns the road feedback into a negative stiffness
    (unstable with the vehicle impedance). ``closed_loop=(Phi - Gamma L_r, Gamma, C)`` (a
    :class:`StateSpace`, see :func:`closed_loop`) instead uses the closed-loop DC gains:
    ``r_act = DC_act^{-1} DC_entry (L_c - I) [T_h; F_r]`` (exact at DC, as ``L_c`` itself), through
    first-order low-pass filters with the same cutoff.
    """
    L_c = np.asarray(L_c, float)
    if L_c.shape != (2, 2):
        raise ValueError(f"L_c must be 2 x 2 (inputs T_h, F_r), got shape {L_c.shape}")
    if not cutoff > 0:
        raise ValueError(f"cutoff must be a positive frequency in rad/s, got {cutoff}")
    M = L_c - np.eye(2)
    if closed_loop is not None:
        dc = np.asarray(dcgain(closed_loop))
        G = np.linalg.solve(dc[:, list(ACTUATED)], dc[:, list(NON_ACTUATED)] @ M)
        return c2d(ss(-cutoff * np.eye(2), cutoff * G, np.eye(2)), h)
    rows = []
    for num, den in (ALPHA_H, ALPHA_R):
        k = len(den) - len(num)  # relative degree of alpha
        lowpass = np.poly(np.full(k, -cutoff))
        rows.append((np.asarray(den) * cutoff**k / -num[-1], lowpass))
    zero, one = (0.0,), (1.0,)
    filt = tf2ss([[rows[0][0], zero], [zero, rows[1][0]]], [[rows[0][1], one], [one, rows[1][1]]])
    cont = ss(filt.A, np.asarray(filt.B) @ M, filt.C, np.asarray(filt.D) @ M)
    return c2d(cont, h)


# ------------------------------------------------------------------------------------------------
# Road feedback and closed-loop simulation

# Eq. 111, Z_v(s) = (a2 s^2 + a1 s + a0) / (s (b2 s^2 + b1 s + b0)): the coefficients come from [2] and are
# not printed. Assumed here: rack stiffness a0/b0 = 2e5 N/m (T_h = 2 Nm then holds the steering wheel at about
# 0.1 rad with the target's 9.5 mm/rad ratio), zeros at 1.5 Hz and poles at 4 Hz (damping 0.7 both): with the
# target the slow road-feedback modes are well damped (-5.6 +- 6.2j, -12.6 +- 40.2j rad/s).
IMPEDANCE_STIFFNESS = 2.0e5
IMPEDANCE_NUM = tuple(IMPEDANCE_STIFFNESS * c for c in (1 / (3 * np.pi) ** 2, 2 * 0.7 / (3 * np.pi), 1.0))
IMPEDANCE_DEN = (1 / (8 * np.pi) ** 2, 2 * 0.7 / (8 * np.pi), 1.0)
TORQUE_AMPLITUDE = 2.0  # Nm, Fig. 8a (not printed): T_h = 2 sin(2 pi 0.5 t) for 4 s
TORQUE_FREQUENCY = 0.5  # Hz
DURATION = 4.0  # s


def vehicle_impedance(h: float = H) -> StateSpace:
    """Eq. 111 as the discrete map from the rack position ``x_r`` to the road feedback ``F_r^* = Z_v s x_r``."""
    return c2d(tf2ss(IMPEDANCE_NUM, IMPEDANCE_DEN), h)


def design(road_force_sign: float = 1.0, method: str = "decoupled", printed_poles: bool = True) -> dict:
    """Discrete target and SBW models, ``L_r`` and ``L_c``. Returns a dict of models and arrays."""
    target = c2d(target_model(road_force_sign), H)
    plant = c2d(sbw_model(), H)
    L_r = state_feedback(plant, method, design_poles(printed_poles))
    L_c = reference_gain(target, plant, L_r)
    return {"target": target, "plant": plant, "L_r": L_r, "L_c": np.asarray(L_c)}


def aob(plant: StateSpace, L_r) -> FeedbackParams:
    """The AOB-1 of eq. 108-110 with its state feedback: ``Q_xr = 1e-12 I``, ``Q_p = diag(0, 1e-1, 0, 1e3)``,
    ``R = 4 I``, ``P_{-1} = Q_0``, time-varying Kalman gain. The zero ``Q_p`` entries lock ``p_1 = p_3 = 0``.
    Params of :data:`jaxobs.observers.active.active_observer_controller`."""
    estimator = make_aob(plant, 1, R_MEAS * np.eye(2), q_plant=Q_PLANT, q_active=jnp.asarray(Q_ACTIVE))
    return FeedbackParams(estimator, feedback_gain(estimator, L_r))


def _lti_step(sys: StateSpace, x, u):
    return sys.A @ x + sys.B @ u, sys.C @ x + sys.D @ u


def simulate_sbw(
    d: dict,
    torque,
    road_disturbance,
    *,
    reference: str = "preamplified",
    cutoff=2 * np.pi * 100.0,
    true_plant: StateSpace | None = None,
    controller=None,
):
    """SBW with the AOB-1 and the road feedback ``F_r^*`` of the vehicle impedance, in one ``lax.scan``.

    The reference depends on the rack position through ``F_r^*``, so this loop is written here rather
    than with :func:`jaxobs.closed_loop.simulate` (which takes a precomputed reference).

    ``reference="preamplified"`` (eq. 106): the entry points receive ``L_c [T_h; F_r]`` with the true
    ``F_r = F_r^* + tau_D``; the AOB knows ``L_c [T_h; F_r^*]``, so the road disturbance acts as the
    input disturbance ``L_c [0; tau_D]`` at the entries ``T_h`` and ``F_r`` (the situation of eq. 113).
    ``reference="actuators"``: ``T_h`` and ``F_r`` act unamplified and the closed-loop consistent
    feed-forward of :func:`actuation_point_filter` drives ``tau_m`` and ``f_s``;
    ``reference="actuators_eq107"``: the same with eq. 107 as printed (open-loop ``alpha^{-1}``).

    ``true_plant``: the discrete plant with positions (``c2d(with_positions(sbw_model(mismatch)), H)``;
    default the nominal one; may be traced, e.g. under ``vmap``); ``controller``: the AOB parameters
    (default :func:`aob` of the design, time-varying gains).

    Returns a dict of time series: ``delta_h``, ``x_r`` (positions), ``velocity`` (outputs), ``p``
    (active states), ``F_r_star``, ``u``.
    """
    if reference not in ("preamplified", "actuators", "actuators_eq107"):
        raise ValueError(f"reference must be 'preamplified', 'actuators' or 'actuators_eq107', got {reference!r}")
    plant = c2d(with_positions(sbw_model()), H) if true_plant is None else true_plant
    params = aob(d["plant"], d["L_r"]) if controller is None else controller
    L_c = jnp.asarray(d["L_c"])
    imp = vehicle_impedance()
    preamp = reference == "preamplified"
    if preamp:  # no feed-forward filter (its design-time NumPy steps must not run under a trace)
        ff = StateSpace(jnp.zeros((0, 0)), jnp.zeros((0, 2)), jnp.zeros((2, 0)), jnp.zeros((2, 2)), H)
    else:
        cl = closed_loop(d["plant"], d["L_r"]) if reference == "actuators" else None
        ff = actuation_point_filter(d["L_c"], cutoff, closed_loop=cl)
    entries = jnp.zeros((4, 2)).at[0, 0].set(1.0).at[2, 1].set(1.0)  # [T_h; F_r] -> input vector
    actuators = jnp.zeros((4, 2)).at[1, 0].set(1.0).at[3, 1].set(1.0)  # [tau_m; f_s] -> input vector

    def body(carry, inp):
        x, ctrl, z, w = carry
        T_h, tau_D = inp
        z, F_star = _lti_step(imp, z, x[-1:])
        known = jnp.stack([T_h, F_star[0]])
        true = known + jnp.stack([0.0, tau_D])
        if preamp:
            r = entries @ (L_c @ known)
            dist = entries @ (L_c @ (true - known))
        else:
            w, u_ff = _lti_step(ff, w, known)
            r = entries @ known + actuators @ u_ff
            dist = entries @ (true - known)
        y = plant.C @ x
        ctrl, out = active_observer_controller.step(params, ctrl, ControllerInputs(y, r))
        x_next = plant.A @ x + plant.B @ (out.u + dist)
        series = {"delta_h": x[-2], "x_r": x[-1], "velocity": y, "p": out.estimator.d, "F_r_star": F_star[0],
                  "u": out.u}  # fmt: skip
        return (x_next, ctrl, z, w), series

    carry = (
        jnp.zeros(plant.n_states),
        active_observer_controller.init(params),
        jnp.zeros(imp.n_states),
        jnp.zeros(ff.n_states),
    )
    inputs = (jnp.asarray(torque, float), jnp.asarray(road_disturbance, float))
    _, series = jax.lax.scan(body, carry, inputs)
    return series


def simulate_target(d: dict, torque, road_disturbance):
    """The conventional car (eq. 90-94) with ``F_r = F_r^* + tau_D`` from the same vehicle impedance."""
    plant = c2d(with_positions(target_model(_sign(d))), H)
    imp = vehicle_impedance()
    entries = jnp.zeros((4, 2)).at[0, 0].set(1.0).at[2, 1].set(1.0)

    def body(carry, inp):
        x, z = carry
        T_h, tau_D = inp
        z, F_star = _lti_step(imp, z, x[-1:])
        u = entries @ jnp.stack([T_h, F_star[0] + tau_D])
        series = {"delta_h": x[-2], "x_r": x[-1], "velocity": plant.C @ x, "F_r_star": F_star[0]}
        return (plant.A @ x + plant.B @ u, z), series

    inputs = (jnp.asarray(torque, float), jnp.asarray(road_disturbance, float))
    _, series = jax.lax.scan(body, (jnp.zeros(plant.n_states), jnp.zeros(imp.n_states)), inputs)
    return series


def _sign(d: dict) -> float:
    """The road-force sign a design was built with (from its target's F_r column DC gain)."""
    return 1.0 if float(dcgain(d["target"])[1, 2]) < 0 else -1.0


# ------------------------------------------------------------------------------------------------
# Reproduction


def scenarios():
    """``(t, torque, road disturbance)`` of the Fig. 8/9 run: a 2 Nm, 0.5 Hz steering torque for 4 s and
    a 1000 N road disturbance from 1 s."""
    T = int(round(DURATION / H))
    t = np.arange(T) * H
    torque = TORQUE_AMPLITUDE * np.sin(2 * np.pi * TORQUE_FREQUENCY * t)
    road = np.where(t >= DISTURBANCE_TIME, ROAD_DISTURBANCE, 0.0)
    return t, torque, road


def _matching_errors(sbw: dict, target: dict) -> dict:
    out = {}
    for key in ("delta_h", "x_r"):
        a, b = np.asarray(sbw[key]), np.asarray(target[key])
        out[key] = {
            "max_abs": float(np.max(np.abs(a - b))),
            "rms": float(np.sqrt(np.mean((a - b) ** 2))),
            "target_peak": float(np.max(np.abs(b))),
        }
    return out


def example2() -> dict:
    """Every number of Example 2 (dict of arrays and floats) plus the time series for the figures."""
    d = design()
    paper = design(road_force_sign=-1.0)
    unrounded = design(printed_poles=False)
    coupled = design(method="coupled")
    s = 1j * np.array([0.1, 1.0, 10.0, 86.7, 300.0, 1000.0])
    target_printed, sbw_printed = printed_transfer_matrices(s)
    realisation = {
        "target_max_rel_error": float(
            np.max(np.abs(frequency_response(target_model(), s) - target_printed)) / np.max(np.abs(target_printed))
        ),
        "sbw_max_rel_error": float(
            np.max(np.abs(frequency_response(sbw_model(), s) - sbw_printed)) / np.max(np.abs(sbw_printed))
        ),
        "omega_rad_s": np.abs(s),
    }
    cl_poles = np.linalg.eigvals(np.asarray(closed_loop(d["plant"], d["L_r"]).A))
    t, torque, road = scenarios()
    zero = np.zeros_like(t)
    fig8 = {"sbw": simulate_sbw(d, torque, zero), "target": simulate_target(d, torque, zero)}
    fig8_act = simulate_sbw(d, torque, zero, reference="actuators")
    fig9 = {"sbw": simulate_sbw(d, zero, road), "target": simulate_target(d, zero, road)}
    p_sim = np.asarray(fig9["sbw"]["p"])[-1]
    fig9_act = simulate_sbw(d, zero, road, reference="actuators")
    eq107 = simulate_sbw(d, torque, zero, reference="actuators_eq107")
    L_c_printed = np.asarray(PRINTED_L_C)
    results = {
        "sign_convention": (
            "transfer functions as printed (road_force_sign=+1): F_r > 0 moves the rack negative in the target "
            "(T23(0) < 0) and in the SBW plant (y_r(0) < 0). The printed L_c and eq. 114 correspond to "
            "road_force_sign=-1 (F_r column of eq. 91-94 flipped)."
        ),
        "L_r": d["L_r"],
        "L_r_coupled": coupled["L_r"],
        "closed_loop_poles": {"real": np.sort_complex(cl_poles).real, "imag": np.sort_complex(cl_poles).imag},
        "L_c": d["L_c"],
        "L_c_paper_sign": paper["L_c"],
        "L_c_printed": L_c_printed,
        "L_c_paper_sign_minus_printed": paper["L_c"] - L_c_printed,
        "L_c_paper_sign_rel_error": np.abs(paper["L_c"] - L_c_printed) / np.abs(L_c_printed),
        "L_c_unrounded_eq100_poles": unrounded["L_c"],
        "L_c_coupled_place": coupled["L_c"],
        "L_c_row_ratio": d["L_c"][:, 1] / d["L_c"][:, 0],
        "target_dc_ratio_T13_T11": float(T13[-1] / T11[-1]),
        "realisation": realisation,
        "eq113_formula": active_state_limit(d["L_c"]),
        "eq113_formula_paper_sign": active_state_limit(paper["L_c"]),
        "eq113_formula_printed_L_c": active_state_limit(L_c_printed),
        "eq114_printed": PRINTED_EQ114,
        "eq113_simulated": p_sim[list(ACTUATED)],
        "eq113_simulated_minus_formula": p_sim[list(ACTUATED)] - active_state_limit(d["L_c"]),
        "locked_active_states_max_abs": float(np.max(np.abs(np.asarray(fig9["sbw"]["p"])[:, list(NON_ACTUATED)]))),
        "model_matching_error": _matching_errors(fig8["sbw"], fig8["target"]),
        "model_matching_error_actuators": _matching_errors(fig8_act, fig8["target"]),
        "eq107_as_printed_diverges": bool(not np.all(np.abs(np.asarray(eq107["x_r"])) < 1.0)),
        "road_disturbance": {
            "tau_D": ROAD_DISTURBANCE,
            "final_x_r_sbw": float(np.asarray(fig9["sbw"]["x_r"])[-1]),
            "final_x_r_target": float(np.asarray(fig9["target"]["x_r"])[-1]),
            "final_delta_h_sbw": float(np.asarray(fig9["sbw"]["delta_h"])[-1]),
            "final_delta_h_target": float(np.asarray(fig9["target"]["delta_h"])[-1]),
            "actuators_p_final": np.asarray(fig9_act["p"])[-1],
            "actuators_final_x_r": float(np.asarray(fig9_act["x_r"])[-1]),
        },
        "assumed": {
            "impedance_num": IMPEDANCE_NUM,
            "impedance_den": IMPEDANCE_DEN,
            "torque": f"{TORQUE_AMPLITUDE} sin(2 pi {TORQUE_FREQUENCY} t) Nm",
            "feedforward_cutoff_rad_s": 2 * np.pi * 100.0,
        },
    }
    results["series"] = {"t": t, "torque": torque, "road": road, "fig8": fig8, "fig9": fig9}
    return results


def plot(results: dict, out_dir: Path) -> list[str]:
    """Fig. 8 (model matching) and Fig. 9 (road disturbance) analogues."""
    plt = pyplot()
    sr = results["series"]
    t = np.asarray(sr["t"])
    names = []
    for fig_name, case, top in (("fig8", sr["fig8"], "torque"), ("fig9", sr["fig9"], "road")):
        fig, ax = plt.subplots(2, 2, figsize=(11, 6.5), sharex=True)
        sbw, tgt = case["sbw"], case["target"]
        if top == "torque":
            ax[0, 0].plot(t, np.asarray(sr["torque"]), lw=1)
            ax[0, 0].set_ylabel("a  T_h [Nm]")
            ax[0, 1].plot(t, np.asarray(sbw["F_r_star"]), lw=1, label="SBW")
            ax[0, 1].plot(t, np.asarray(tgt["F_r_star"]), "k--", lw=1, label="conventional")
            ax[0, 1].set_ylabel("b  F_r = F_r* [N]")
            ax[0, 1].legend(fontsize=8)
        else:
            ax[0, 0].plot(t, np.asarray(sr["road"]), lw=1)
            ax[0, 0].set_ylabel("a  tau_D [N]")
            p = np.asarray(sbw["p"])
            ax[0, 1].plot(t, p[:, 1], lw=1, label="p_2 (tau_m)")
            ax[0, 1].plot(t, p[:, 3], lw=1, label="p_4 (f_s)")
            for value, style in zip(results["eq113_formula"], ("C0:", "C1:"), strict=True):
                ax[0, 1].axhline(value, ls=":", color=style[:2], lw=0.8)
            ax[0, 1].set_ylabel("b  active states")
            ax[0, 1].legend(fontsize=8)
        ax[1, 0].plot(t, np.asarray(sbw["delta_h"]), lw=1, label="SBW + AOB-1")
        ax[1, 0].plot(t, np.asarray(tgt["delta_h"]), "k--", lw=1, label="conventional")
        ax[1, 0].set_ylabel("c  delta_h [rad]")
        ax[1, 0].legend(fontsize=8)
        ax[1, 1].plot(t, 1e3 * np.asarray(sbw["x_r"]), lw=1)
        ax[1, 1].plot(t, 1e3 * np.asarray(tgt["x_r"]), "k--", lw=1)
        ax[1, 1].set_ylabel("d  x_r [mm]")
        for a in ax[1]:
            a.set_xlabel("time [s]")
        title = "model matching" if top == "torque" else "road disturbance tau_D = 1000 N at 1 s"
        fig.suptitle(f"Cortesão 2006 Example 2 ({'Fig. 8' if top == 'torque' else 'Fig. 9'}): {title}")
        names.append(save_figure(fig, out_dir, f"{NAME}-{fig_name}"))
    return names


def reproduce(out_dir: Path) -> dict:
    """Compute Example 2, write ``cortesao2006-example2.json`` and the two figures, return the summary."""
    results = example2()
    figures = plot(results, out_dir)
    summary = {k: v for k, v in results.items() if k != "series"}
    return write_reproduction(out_dir, NAME, summary, figures)


REPRODUCTION = Reproduction(name=NAME, summary=__doc__, reproduce=reproduce)
