"""Liu & Peng 2002 §4.2: vehicle lateral speed and disturbance from yaw rate (eq. 31, Figs. 3-5).

The bicycle model of eq. 31 (state ``[v_y, r]``, steering ``u``, lateral disturbance ``d``, yaw rate measured at
100 Hz), with the a_i from the printed parameters or as printed (see docs/reproductions.md), and four estimators
on the nominal model (:data:`METHODS`): the inverse-dynamics observer, an H-infinity filter, the AOB-1 as an
estimator and a Kalman filter without a disturbance state. Values the paper does not print are in
:data:`ASSUMED`. The models, estimators and scenario: docs/theory/papers.md.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from jaxobs.lti import c2d, ss
from jaxobs.observers import active
from jaxobs.observers.base import EstimatorInputs, run
from jaxobs.observers.hinf import gamma_bisection, hinf_filter, make_hinf
from jaxobs.observers.inverse_dynamics import inverse_dynamics_observer, make_inverse_dynamics
from jaxobs.observers.kalman import kalman_filter, make_kalman
from jaxobs.papers._output import pyplot, save_figure, write_reproduction
from jaxobs.papers.scenarios import Reproduction

NAME = "liu-peng2002-vehicle"

G = 9.81
H = 0.01  # 100 Hz (§4.2)
K_GAIN = [[47.0], [10.0]]  # §4.2
F1, F2 = -10.0, 1.0
PRINTED_A = (-9.754, -14.03, 0.5901, -12.622)  # §4.2 text
PARAMETER_A = (-7.686, -14.362, 0.3388, -6.655)  # conventions note, from the printed parameters
METHODS = ("inverse_dynamics", "hinf", "aob", "kalman")
MODELS = ("parameters", "printed_a")
CASES = ("ideal", "robustness")


@dataclasses.dataclass(frozen=True)
class Vehicle:
    """Printed §4.2 parameters (SI units, per-tyre cornering stiffness, eq. 31 uses 2 C).

    Attributes:
      Cf, Cr: front and rear cornering stiffness (N/rad).  m: mass (kg).
      a, b: distances of the front and rear axles from the centre of mass (m).
      Iz: yaw moment of inertia (kg m^2).  vx: longitudinal speed (m/s).
    """

    Cf: float = 51000.0
    Cr: float = 47000.0
    m: float = 1700.0
    a: float = 1.14
    b: float = 1.41
    Iz: float = 3200.0
    vx: float = 15.0


NOMINAL = Vehicle()
STIFFNESS_FACTOR, INERTIA_FACTOR = 0.7, 1.2  # robustness case: C -30 %, m and I_z +20 %
PERTURBED = dataclasses.replace(
    NOMINAL,
    Cf=STIFFNESS_FACTOR * NOMINAL.Cf,
    Cr=STIFFNESS_FACTOR * NOMINAL.Cr,
    m=INERTIA_FACTOR * NOMINAL.m,
    Iz=INERTIA_FACTOR * NOMINAL.Iz,
)

ASSUMED = {
    "superelevation": "d_bank = g sin(5 deg) = 0.855 m/s^2 (positive sign), trapezoid: 0 before 1 s, linear ramps "
    "1-1.5 s and 3.5-4 s, flat between, 0 after 4 s",
    "wind_gusts": "d_wind = 0.1 (sin 3t + sin 10t + sin 35t) m/s^2 (amplitudes and phases not printed)",
    "duration_s": 6.0,
    "truth_simulation": "exact ZOH of eq. 31 at 1 kHz (d and u held over 1 ms), yaw rate sampled every 10th step",
    "initial_state": "true vehicle in the steady turn for its own steering; every estimator starts at v_y = 0, "
    "r = first yaw-rate sample, d = 0",
    "rms_window": "RMS errors over t >= 0.5 s (after the start-up transient); full-run RMS also given",
    "steering_offset": "true road-wheel angle 0.34 deg, measured (and used by every estimator) 0.33 deg",
    "noise": "white N(0, 0.001^2) rad/s, seed 0, plus 0.001 sin(2 pi t) rad/s",
    "perturbed_printed_a": "for the printed-a_i model every term of eq. 31 except -v_x in a2 scales with C/m or C/I_z, "
    "so the perturbed truth is a_i -> s a_i (a2 + v_x -> s (a2 + v_x)), B_u -> s B_u with s = 0.7/1.2",
    "lowpass": "5 identical first-order sections on y, corner 3 Hz each (pole exp(-2 pi 3 h) = 0.828), "
    "inverse-dynamics observer only (filter type and corner are not printed). Chosen as the best d RMS of the corners "
    "2, 3, 5, 8, 10, 15 Hz: the Case 2 observer differentiates y twice (d -> y has relative degree 2), so with a "
    "20 Hz corner the noise gives RMS(d error) ~ 4 m/s^2 and without the filter ~ 80 m/s^2",
    "kalman_design": "R = 1e-6 (0.001 rad/s noise), Q_x = 1e-10 I; AOB/H-infinity random-walk variance "
    "q_d = 1e-3 (m/s^2)^2 per step; CKF: d as white noise with s_d = 0.5 m/s^2; "
    "P0 = diag(0.25, 1e-6, 1) (CKF: diag(0.25, 1e-6))",
    "hinf_gamma": "1.2 x the optimal a-posteriori level over the run (gamma_bisection on the nominal model)",
}
AMPLITUDE_BANK = G * np.sin(np.deg2rad(5.0))
WIND_AMPLITUDE = 0.1
WIND_FREQUENCIES = (3.0, 10.0, 35.0)
STEER = np.deg2rad(0.33)
STEER_OFFSET = np.deg2rad(0.01)
DURATION = 6.0
FINE = 10  # truth steps per sample
RMS_START = 0.5
NOISE_STD = 1e-3
NOISE_SINE = 1e-3
LOWPASS_ORDER = 5
LOWPASS_CORNER_HZ = 3.0
LOWPASS_POLE = float(np.exp(-2 * np.pi * LOWPASS_CORNER_HZ * H))
R_MEAS = NOISE_STD**2
Q_X = 1e-10
Q_D = 1e-3
SIGMA_D_CKF = 0.5
P0_AUG = (0.25, 1e-6, 1.0)
HINF_GAMMA_FACTOR = 1.2
NOISE_SEED = 0


# ----------------------------------------------------------------------------------------------- model


def bicycle(v: Vehicle = NOMINAL):
    """``(A, B_u)`` of eq. 31 from the vehicle parameters (a4 with the bicycle-model sign, see module doc)."""
    cf, cr = 2 * v.Cf, 2 * v.Cr
    A = np.array(
        [
            [-(cf + cr) / (v.m * v.vx), -v.vx + (-v.a * cf + v.b * cr) / (v.m * v.vx)],
            [(-v.a * cf + v.b * cr) / (v.Iz * v.vx), -(v.a**2 * cf + v.b**2 * cr) / (v.Iz * v.vx)],
        ]
    )
    return A, np.array([[cf / v.m], [v.a * cf / v.Iz]])


def printed_eq31_a4(v: Vehicle = NOMINAL) -> float:
    """``a4`` exactly as eq. 31 prints it, ``(-2 a^2 C_f + 2 b^2 C_r) / (I_z v_x)`` (positive: a sign slip)."""
    return (-2 * v.a**2 * v.Cf + 2 * v.b**2 * v.Cr) / (v.Iz * v.vx)


def plant(model: str, truth_perturbed: bool = False):
    """``(A, B_u, B_d, C)`` of eq. 31 for ``model`` in :data:`MODELS`; ``truth_perturbed`` gives the robustness
    case's true vehicle (m, I_z +20 %, C -30 %)."""
    Bd, C = np.array([[1.0], [0.0]]), np.array([[0.0, 1.0]])
    if model == "parameters":
        A, Bu = bicycle(PERTURBED if truth_perturbed else NOMINAL)
    elif model == "printed_a":
        A, Bu = np.array(PRINTED_A, float).reshape(2, 2), bicycle(NOMINAL)[1]
        if truth_perturbed:
            s = STIFFNESS_FACTOR / INERTIA_FACTOR  # every term but -v_x scales with C/m or C/I_z
            shift = np.array([[0.0, NOMINAL.vx], [0.0, 0.0]])
            A, Bu = s * (A + shift) - shift, s * Bu
    else:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    return A, Bu, Bd, C


# ---------------------------------------------------------------------------------------------- scenario


def disturbance(t):
    """Superelevation trapezoid plus wind gusts (m/s^2) at times ``t`` (see :data:`ASSUMED`)."""
    t = np.asarray(t, float)
    ramp = np.clip((t - 1.0) / 0.5, 0, 1) * np.clip((4.0 - t) / 0.5, 0, 1)
    wind = WIND_AMPLITUDE * sum(np.sin(w * t) for w in WIND_FREQUENCIES)
    return AMPLITUDE_BANK * ramp + wind


def simulate_truth(model: str, case: str):
    """True vehicle over :data:`DURATION`: returns ``t`` (samples), true ``x`` and ``d`` at the samples, the
    measured yaw rate ``y`` and the measured steering ``u`` (both at the samples)."""
    robust = case == "robustness"
    A, Bu, Bd, C = plant(model, truth_perturbed=robust)
    steer_true = STEER + (STEER_OFFSET if robust else 0.0)
    hf = H / FINE
    E = scipy.linalg.expm(np.block([[A, np.hstack([Bu, Bd])], [np.zeros((2, 4))]]) * hf)
    Phi, Gam = E[:2, :2], E[:2, 2:]
    n = int(round(DURATION / H))
    tf = np.arange(n * FINE) * hf
    df = disturbance(tf)
    x = -np.linalg.solve(A, Bu[:, 0] * steer_true)  # steady turn
    xs = np.empty((n * FINE, 2))
    for k in range(n * FINE):
        xs[k] = x
        x = Phi @ x + Gam @ np.array([steer_true, df[k]])
    t, x_s, d_s = tf[::FINE], xs[::FINE], df[::FINE]
    y = x_s @ C[0]
    if robust:
        rng = np.random.default_rng(NOISE_SEED)
        y = y + NOISE_STD * rng.standard_normal(n) + NOISE_SINE * np.sin(2 * np.pi * t)
    return t, x_s, d_s, y, np.full(n, STEER)


# ---------------------------------------------------------------------------------------------- estimators


def _discrete(A, Bu, Bd, C):
    sysd = c2d(ss(A, np.hstack([Bu, Bd]), C), H)
    Phi, Gam = np.asarray(sysd.A), np.asarray(sysd.B)
    return Phi, Gam[:, :1], Gam[:, 1:]


def _augmented(A, Bu, Bd, C):
    """AOB-1 augmentation with the disturbance channel as the active-state input: ``[v_y, r, d]``."""
    Phi, Gu, Gd = _discrete(A, Bu, Bd, C)
    Phi_a, Gu_a, C_a = active.augment(ss(Phi, Gu, C, dt=H), 1, disturbance_input=Gd)
    return np.asarray(Phi_a), np.asarray(Gu_a), np.asarray(C_a)


def _advanced(Phi, Q, P):
    """The estimators start from ``x_{-1}`` (the sample before the first measurement) with covariance ``P``; the
    library's prior is that of ``x_0``: ``Phi P Phi' + Q`` (the mean is advanced in :func:`run_estimators`)."""
    return Phi @ P @ Phi.T + Q


class Estimators(NamedTuple):
    """The four estimators designed on the nominal model (a pytree; :func:`run_estimators` is traceable).

    Attributes:
      inverse_dynamics, aob, hinf, kalman: each estimator's parameters.
      G_d_pinv: the Kalman filter's least-squares disturbance from its state correction.
      hinf_gamma: the H-infinity filter's attenuation level (from the bisection).
    """

    inverse_dynamics: Any
    aob: Any
    hinf: Any
    kalman: Any
    G_d_pinv: jax.Array
    hinf_gamma: float


def design_estimators(model: str, lowpass: bool, num_steps: int) -> Estimators:
    """Design-time part of :func:`estimate` (gamma bisection over ``num_steps`` samples, gains, checks), on the
    nominal ``model``; ``lowpass`` switches the inverse-dynamics observer's low-pass on (robustness case).
    Initial states are placeholders: :func:`run_estimators` sets them from the first yaw-rate sample."""
    A, Bu, Bd, C = plant(model)
    ido = make_inverse_dynamics(
        A, Bd, C, K_GAIN, F1, F2, h=H, Bu=Bu, case=2, x0=np.zeros(2),
        lowpass_pole=LOWPASS_POLE if lowpass else 0.0, lowpass_order=LOWPASS_ORDER if lowpass else 0,
    )  # fmt: skip
    Phi, Gu, Gd = _discrete(A, Bu, Bd, C)
    Phi_a, Gu_a, C_a = _augmented(A, Bu, Bd, C)
    Q_a = np.asarray(active.aob_noise_covariance(2, 1, 1, Q_X, Q_D))
    P0_a = _advanced(Phi_a, Q_a, np.diag(P0_AUG))
    aob = active.make_aob(ss(Phi, Gu, C, dt=H), 1, R_MEAS, q_plant=Q_X, q_active=Q_D, disturbance_input=Gd,
                          P0=P0_a)  # fmt: skip
    Cz = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    level = gamma_bisection(Phi_a, C_a, Q_a, R_MEAS, Cz=Cz, P0=P0_a, num_steps=num_steps, rtol=1e-4)
    gamma = HINF_GAMMA_FACTOR * float(level.gamma)
    hinf = make_hinf(Phi_a, C_a, Q_a, R_MEAS, gamma=gamma, Gamma=Gu_a, Cz=Cz, Cd=Cz[1:], P0=P0_a)
    Q_c = SIGMA_D_CKF**2 * Gd @ Gd.T + Q_X * np.eye(2)
    ckf = make_kalman(Phi, C, Q_c, R_MEAS, Gamma=Gu, P0=_advanced(Phi, Q_c, np.diag(P0_AUG[:2])))
    return Estimators(ido, aob, hinf, ckf, jnp.asarray(np.linalg.pinv(Gd)), gamma)


def run_estimators(est: Estimators, y, u) -> dict:
    """Run the designed estimators on the measured ``y`` and ``u`` (traceable, ``vmap``-able); returns
    ``{method: (v_y_hat, d_hat)}`` and ``"_hinf_feasible"`` (every step).

    The inverse-dynamics observer evaluates its known term ``B_u u`` at ``t_k`` (backward Euler, §4.2), so it gets
    the steering of sample ``k`` as its input; the three Kalman-type filters get ``u_{k-1}``, held over the
    interval, and start from ``x_{-1} = [0, y_0, 0]`` advanced one sample.
    """
    y, u = jnp.asarray(y), jnp.asarray(u)
    x0 = jnp.stack([jnp.zeros_like(y[0]), y[0]])
    xa0 = jnp.stack([jnp.zeros_like(y[0]), y[0], jnp.zeros_like(y[0])])
    out = {}
    ido = dataclasses.replace(est.inverse_dynamics, x0=x0.astype(est.inverse_dynamics.x0.dtype))
    o = run(inverse_dynamics_observer, ido, EstimatorInputs(y[:, None], u[:, None]))[1]
    out["inverse_dynamics"] = (o.x[:, 0], o.d[:, 0])

    u_prev = jnp.concatenate([u[:1], u[:-1]])[:, None]
    inputs = EstimatorInputs(y[:, None], u_prev)
    aob, hinf, kf = est.aob, est.hinf, est.kalman
    o = run(active.active_observer, dataclasses.replace(aob, x0=aob.Phi @ xa0 + aob.Gamma @ u_prev[0]), inputs)[1]
    out["aob"] = (o.x[:, 0], o.d[:, 0])

    o = run(hinf_filter, dataclasses.replace(hinf, x0=hinf.Phi @ xa0 + hinf.Gamma @ u_prev[0]), inputs)[1]
    out["hinf"] = (o.z[:, 0], o.d[:, 0])
    out["_hinf_feasible"] = jnp.all(o.feasible)

    o = run(kalman_filter, dataclasses.replace(kf, x0=kf.Phi @ x0 + kf.Gamma @ u_prev[0]), inputs)[1]
    d_ckf = (o.x - o.x_prior) @ est.G_d_pinv.T
    out["kalman"] = (o.x[:, 0], d_ckf[:, 0])
    return out


def estimate(model: str, case: str, t, y, u) -> dict:
    """Run the four estimators on the measured ``y`` and ``u``; returns ``{method: (v_y_hat, d_hat)}``."""
    est = design_estimators(model, case == "robustness", len(t))
    res = jax.jit(run_estimators)(est._replace(hinf_gamma=None), y, u)
    out = {m: (np.asarray(res[m][0]), np.asarray(res[m][1])) for m in METHODS}
    out["_hinf_gamma"] = float(est.hinf.gamma)
    out["_hinf_feasible"] = bool(res["_hinf_feasible"])
    return out


def _rms(e, mask=None):
    e = np.asarray(e) if mask is None else np.asarray(e)[mask]
    return float(np.sqrt(np.mean(e**2)))


def run_case(model: str, case: str) -> dict:
    """Truth, estimates and RMS errors (v_y in m/s, d in m/s^2) of every method for one model and case."""
    t, x, d, y, u = simulate_truth(model, case)
    est = estimate(model, case, t, y, u)
    after = t >= RMS_START
    rms = {}
    for m in METHODS:
        vy_hat, d_hat = est[m]
        rms[m] = {
            "v_y": _rms(vy_hat - x[:, 0], after),
            "d": _rms(d_hat - d, after),
            "v_y_full": _rms(vy_hat - x[:, 0]),
            "d_full": _rms(d_hat - d),
        }
    return dict(
        t=t, v_y=x[:, 0], r=x[:, 1], d=d, y=y,
        estimates={m: est[m] for m in METHODS}, rms=rms,
        hinf_gamma=est["_hinf_gamma"], hinf_feasible=est["_hinf_feasible"],
    )  # fmt: skip


def vehicle_example() -> dict:
    """Every model x case, plus the model checks (a_i from the parameters vs printed, eq. 31's a4 slip)."""
    runs = {m: {c: run_case(m, c) for c in CASES} for m in MODELS}
    A, Bu = bicycle()
    return dict(
        a_from_parameters=A.ravel(),
        a_printed=np.array(PRINTED_A),
        a4_as_printed_in_eq31=printed_eq31_a4(),
        B_u=Bu[:, 0],
        m_over_Iz=NOMINAL.m / NOMINAL.Iz,
        a3_over_a2_plus_vx={
            "parameters": A[1, 0] / (A[0, 1] + NOMINAL.vx),
            "printed_a": PRINTED_A[2] / (PRINTED_A[1] + NOMINAL.vx),
        },
        error_pole_printed=-(K_GAIN[0][0] + F1) / F2,
        runs=runs,
    )


# ------------------------------------------------------------------------------------------------ output

LABELS = {
    "inverse_dynamics": "inverse dynamics",
    "hinf": "H-infinity",
    "aob": "AOB-1 (estimator)",
    "kalman": "Kalman (no d state)",
}
STYLES = {  # the H-infinity and AOB-1 estimates nearly coincide: H-infinity dashed, on top
    "inverse_dynamics": dict(color="C0", lw=1.0, zorder=3),
    "hinf": dict(color="C1", lw=1.4, ls=(0, (4, 3)), zorder=4),
    "aob": dict(color="C2", lw=1.0, zorder=2),
    "kalman": dict(color="C3", lw=1.0, zorder=2),
}


def _fig_pair(run_: dict, methods, title: str):
    plt = pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(9.5, 5.5), sharex=True, layout="constrained")  # no clipped label
    t = run_["t"]
    axes[0].plot(t, run_["d"], "k", lw=2, label="true")
    axes[1].plot(t, run_["v_y"], "k", lw=2, label="true")
    for m in methods:
        vy, d = run_["estimates"][m]
        rms = run_["rms"][m]
        axes[0].plot(t, d, label=f"{LABELS[m]}, RMS {float(rms['d']):.3g}", **STYLES[m])
        axes[1].plot(t, vy, label=f"{LABELS[m]}, RMS {float(rms['v_y']):.3g}", **STYLES[m])
    axes[0].set_ylabel("d (m/s$^2$)")
    axes[1].set_ylabel("$v_y$ (m/s)")
    axes[1].set_xlabel(f"t (s); RMS errors from t = {RMS_START:g} s")
    axes[0].set_title(title)
    shown = t >= 0.2  # y-limits from after the start-up spike (it stays visible, clipped)
    for ax, key, i in ((axes[0], "d", 1), (axes[1], "v_y", 0)):
        values = np.concatenate([run_[key][shown]] + [run_["estimates"][m][i][shown] for m in methods])
        pad = 0.1 * (values.max() - values.min())
        ax.set_ylim(values.min() - pad, values.max() + pad)
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the traces
    return fig


def plot(results: dict, out_dir: Path) -> list[str]:
    """Figs. 3-5 (parameter model) and an all-method comparison per case; returns the PNG names."""
    p = results["runs"]["parameters"]
    figs = [
        (_fig_pair(p["ideal"], ["inverse_dynamics"], "Fig. 3: inverse dynamics, ideal"), f"{NAME}-fig3"),
        (_fig_pair(p["ideal"], ["hinf"], "Fig. 4: H-infinity filter, ideal"), f"{NAME}-fig4"),
        (_fig_pair(p["robustness"], ["inverse_dynamics"], "Fig. 5: inverse dynamics, combined uncertainties"),
         f"{NAME}-fig5"),
    ]  # fmt: skip
    for case in CASES:
        figs.append((_fig_pair(p[case], METHODS, f"all estimators, {case} (parameter model)"), f"{NAME}-{case}-all"))
    return [save_figure(fig, out_dir, name) for fig, name in figs]


def reproduce(out_dir: Path) -> dict:
    """Compute §4.2, write ``liu-peng2002-vehicle.json`` and the figures, return the summary."""
    results = vehicle_example()
    figures = plot(results, Path(out_dir))
    summary = {k: v for k, v in results.items() if k != "runs"}
    summary["rms"] = {m: {c: results["runs"][m][c]["rms"] for c in CASES} for m in MODELS}
    summary["hinf_gamma"] = {m: {c: results["runs"][m][c]["hinf_gamma"] for c in CASES} for m in MODELS}
    summary["units"] = {"v_y": "m/s", "d": "m/s^2"}
    summary["assumed"] = ASSUMED
    return write_reproduction(Path(out_dir), NAME, summary, figures)


REPRODUCTION = Reproduction(name=NAME, summary=__doc__, reproduce=reproduce)
