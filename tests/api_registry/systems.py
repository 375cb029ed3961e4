"""Registry entries: closed loops, stability, saturated systems and the special coordinate basis (jaxobs.closed_loop,
jaxobs.stability, jaxobs.saturation, jaxobs.scb)."""

import functools

import numpy as np

from tests.api_registry import Design, Example, slow
from tests.api_registry.models import NOT_DIFFERENTIABLE, R1, _key, _ss_discrete
from tests.api_registry.observers import T, _aob_controller


def _plant():
    return _ss_discrete()


def _aob_controller_system():
    from jaxobs.observers.active import active_observer_controller

    return active_observer_controller


REFERENCE = np.ones((T, 1))
DISTURBANCE = np.cos(0.9 * np.arange(T))[:, None]  # d_0 != 0: the active state moves from the first innovation on,
# its evolution away from the kink of |w| at 0 (a model equal to the plant with d_0 = 0 leaves it exactly at 0)

CLOSED_LOOP = {
    "jaxobs.closed_loop.simulate": Example(
        lambda: dict(
            plant=_plant(),
            controller=_aob_controller_system(),
            params=_aob_controller(),
            reference=REFERENCE,
            disturbance=DISTURBANCE,
        ),
        diff="params",
        tangent="scale",
    ),
    "jaxobs.closed_loop.ideal_response": Example(
        lambda: dict(plant=_plant(), L=np.array([[2.0, 0.5]]), reference=REFERENCE), diff="L"
    ),
    "jaxobs.closed_loop.measurement_noise": Example(
        lambda: dict(key=_key(5), num_steps=4, R=R1), diff="R", tangent="scale"
    ),
    "jaxobs.closed_loop.rms": Example(
        lambda: dict(error=np.sin(np.arange(8.0))[:, None]), skip={"batch": "error is any array, reduced over axis"}
    ),
}


def _loop():
    from jaxobs.lti import ss

    return ss([[0.5]], [[1.0]], [[0.4]], dt=0.01)


STABILITY_PARAMS = {
    "batch": "a batch axis on params is refused, but by messages naming the linear form's matrices "
    "(Phi_n, K, L), not params: jaxobs.stability is being reworked (issue 45)"
}

STABILITY = {
    "jaxobs.stability.stability_margins": Example(
        lambda: dict(sys=_loop(), num_points=16),
        diff="sys",
        out=lambda m: (m.gain_margin, m.stability_margin, m.spectral_radius),
        skip={"grad": "margins are extrema and crossings over a frequency grid refined by bisection: piecewise smooth"},
    ),
    "jaxobs.stability.loop_transfer": Example(
        lambda: dict(plant=_plant(), controller=_aob_controller_system(), params=_steady_controller()),
        diff="params",
        tangent="scale",
        skip=STABILITY_PARAMS,
    ),
    "jaxobs.stability.closed_loop_matrix": Example(
        lambda: dict(plant=_plant(), controller=_aob_controller_system(), params=_steady_controller()),
        diff="params",
        tangent="scale",
        skip=STABILITY_PARAMS,
    ),
    "jaxobs.stability.robustness_metrics": Example(
        lambda: dict(plant=_plant(), controller=_aob_controller_system(), params=_steady_controller(), num_points=16),
        diff="params",
        tangent="scale",
        skip={**STABILITY_PARAMS, "grad": "margins are extrema and crossings over a frequency grid: piecewise smooth"},
    ),
    "jaxobs.stability.spectral_radius": Example(
        lambda: dict(A=np.array([[0.5, 0.2], [-0.1, 0.3]])),
        skip={"batch": "a stack of matrices is documented: the largest spectral radius over the stack"},
    ),
    "jaxobs.stability.frequency_response": Example(
        lambda: dict(sys=_loop(), omega=np.array([1.0, 10.0])),
        diff="sys",
        batched=("omega",),
        out=lambda H: (H.real, H.imag),
    ),
    "jaxobs.stability.unstructured_mismatch": Example(
        lambda: dict(
            key=_key(6),
            Phi_n=np.array([[0.9, 0.1], [0.0, 0.8]]),
            Gamma_n=np.array([[0.0], [0.1]]),
            phi_norm=np.float64(0.05),
            gamma_norm=np.float64(0.01),
        ),
        diff="Phi_n",
    ),
}


def _steady_controller():
    from jaxobs.observers.active import feedback_gain, make_aob
    from jaxobs.observers.feedback import FeedbackParams

    aob = make_aob(_plant(), 1, R1, q_active=1e-3, steady_state=True)
    return FeedbackParams(aob, feedback_gain(aob, np.array([[2.0, 0.5]])))


A8 = np.array([[0.0, 1, 1], [0, 0, 0], [0, 0, 0]])
B8 = np.array([[0.0, 0], [1, 0], [0, 1]])
C8 = np.array([[1.0, 0, 0], [1, 1, 0]])
SW = dict(A=np.array([[0.0, 1], [0, 0]]), B=np.array([[0.0], [1]]), C=np.array([[1.0, 0]]), M=np.array([[-1.0]]),
          N=np.array([[1.0]]), G=np.array([[1.0]]))  # fmt: skip
F_SW = np.array([[-1.0, -2.0]])


@functools.cache
def _design8():
    from jaxobs.saturation import saturated_output_design

    return saturated_output_design(A8, B8, C8, T=0.5, rho=1.1)


@functools.cache
def _design9():
    from jaxobs.saturation import sandwich_design

    return sandwich_design(**SW, T=0.05, Tbar_intervals=4, rho=1.1, F=F_SW, eps=1e-3)


def _window_model():
    from jaxobs.saturation import window_model

    return window_model(np.zeros((2, 2)), np.ones((2, 1)), np.eye(2), 0.1)


def _hypothesis():
    from jaxobs.saturation import hypothesis

    return hypothesis(np.zeros((2, 2)), np.ones((2, 1)), np.eye(2), 0.1)


WINDOW_Y = np.stack([0.1 * np.arange(11.0), 0.05 * np.arange(11.0) ** 2], axis=1)
WINDOW_U = np.cos(np.arange(11.0))[:, None]

SATURATION = {
    "jaxobs.saturation.sat": Example(lambda: dict(v=np.array([-2.0, 0.3, 1.7])), batched=("v",)),
    "jaxobs.saturation.saturated_output_design": Example(
        lambda: dict(A=A8, B=B8, C=C8, T=np.float64(0.5), rho=np.float64(1.1)), diff="A"
    ),
    "jaxobs.saturation.interval_map": Example(
        lambda: dict(design=_design8(), x=np.array([2.0, -4.0, 1.0]), U=np.array([0.3, -0.2, 0.1])), diff="x"
    ),
    "jaxobs.saturation.simulate_saturated_outputs": Example(
        lambda: dict(design=_design8(), x0=np.array([2.0, -4.0, 1.0]), num_intervals=3, substeps=20),
        diff="x0",
        skip={"grad": "a hybrid controller: saturations and switching on the measured pattern"},
    ),
    "jaxobs.saturation.window_model": Example(
        lambda: dict(F=np.array([[0.0, 1.0], [0.0, 0.0]]), Bf=np.array([[0.0], [1.0]]), H=np.eye(2), h=np.float64(0.1)),
        diff="F",
    ),
    "jaxobs.saturation.forced_response": Example(lambda: dict(model=_window_model(), u=WINDOW_U), diff="u"),
    "jaxobs.saturation.hypothesis_residual": Example(
        lambda: dict(model=_window_model(), y=WINDOW_Y, u=WINDOW_U), diff="y"
    ),
    "jaxobs.saturation.hypothesis": Example(
        lambda: dict(F=np.array([[0.0, 1.0], [0.0, 0.0]]), Bf=np.array([[0.0], [1.0]]), H=np.eye(2), h=np.float64(0.1)),
        diff="F",
    ),
    "jaxobs.saturation.explains": Example(
        lambda: dict(hyp=_hypothesis(), y=WINDOW_Y, u=WINDOW_U), diff="y", skip=NOT_DIFFERENTIABLE
    ),
    "jaxobs.saturation.sandwich_hypotheses": Example(lambda: dict(design=_design9(), h=np.float64(1e-3)), diff="h"),
    "jaxobs.saturation.sandwich_detectors": Example(
        lambda: dict(design=_design9(), y=0.2 + 0.05 * np.arange(11.0)[:, None], u=np.zeros(11), h=np.float64(5e-3)),
        diff="y",
        out=lambda r: r[:3],
        rtol=1e-6,
    ),  # e0 is a rounding-level residual
    "jaxobs.saturation.sandwich_design": Example(
        lambda: dict(**SW, T=np.float64(0.05), Tbar_intervals=4, rho=np.float64(1.1), F=F_SW, eps=np.float64(1e-3)),
        diff="F",
    ),
    "jaxobs.saturation.low_gain_are": Example(
        lambda: dict(**{k: SW[k] for k in "ABCMN"}, F=F_SW, eps=np.float64(1e-3)), diff="eps"
    ),
    "jaxobs.saturation.simulate_sandwich": Example(
        lambda: dict(design=_design9(), chi0=np.array([0.5, -1.0, 0.2]), num_intervals=4, substeps=10),
        diff="chi0",
        skip={"grad": "a three-stage switching controller"},
    ),
}

SCB_SYSTEM = (np.array([[0.0, 1.0], [-2.0, -3.0]]), np.array([[0.0], [1.0]]), np.array([[1.0, 1.0]]))


def _scb():
    from jaxobs.scb import scb

    return scb(*SCB_SYSTEM)


SCB = {
    "jaxobs.scb.scb": Design(lambda: dict(A=SCB_SYSTEM[0], B=SCB_SYSTEM[1], C=SCB_SYSTEM[2], numeric=True)),
    "jaxobs.scb.scb_residuals": Design(
        lambda: dict(system=_scb(), A=SCB_SYSTEM[0], B=SCB_SYSTEM[1], C=SCB_SYSTEM[2]), traced="A"
    ),
    "jaxobs.scb.scb_arrays": Design(lambda: dict(system=_scb(), values={"k": np.float64(1.0)}), traced="values"),
    "jaxobs.scb.invariant_zeros": Design(lambda: dict(system=SCB_SYSTEM)),
    "jaxobs.scb.infinite_zero_structure": Design(lambda: dict(system=SCB_SYSTEM)),
    "jaxobs.scb.is_left_invertible": Design(lambda: dict(system=SCB_SYSTEM)),
    "jaxobs.scb.is_right_invertible": Design(lambda: dict(system=SCB_SYSTEM)),
    "jaxobs.scb.is_minimum_phase": Design(lambda: dict(system=SCB_SYSTEM)),
}

ENTRIES = {**CLOSED_LOOP, **STABILITY, **SATURATION, **SCB}
ENTRIES = slow(
    ENTRIES,
    (
        "a closed loop over a record, or margins over a frequency grid refined by bisection, compiled for eager, "
        "jit, vmap and grad (~0.8-5 s of CPU)"
    ),
    "jaxobs.closed_loop.simulate",
    "jaxobs.stability.closed_loop_matrix",
    "jaxobs.stability.frequency_response",
    "jaxobs.stability.robustness_metrics",
    "jaxobs.stability.stability_margins",
)
ENTRIES = slow(
    ENTRIES,
    (
        "a design by a low-gain Riccati solve, or a simulation or window test of the sandwich/saturated systems "
        "(matrix exponentials and integrals over a window), compiled for eager, jit, vmap and grad (~0.8-6 s of "
        "CPU)"
    ),
    "jaxobs.saturation.explains",
    "jaxobs.saturation.hypothesis",
    "jaxobs.saturation.low_gain_are",
    "jaxobs.saturation.sandwich_design",
    "jaxobs.saturation.sandwich_detectors",
    "jaxobs.saturation.sandwich_hypotheses",
    "jaxobs.saturation.saturated_output_design",
    "jaxobs.saturation.simulate_sandwich",
    "jaxobs.saturation.simulate_saturated_outputs",
)

EXEMPT = {
    "jaxobs.stability.check_nominal": "job: compiles robustness_metrics, runs it eagerly and logs a warning",
    "jaxobs.saturation.require_controllable_observable": "validator: raises naming the pair that is not "
    "controllable or observable",
}
