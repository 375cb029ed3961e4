"""Bad inputs to the public API: a ``ValueError`` whose message starts with the name of the argument at fault
(shapes, dtypes and counts are static, so they are checked before computing, under ``jit`` and ``vmap`` too),
or a correct answer (integer and mixed-precision inputs are promoted to one floating dtype)."""

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from jaxobs import closed_loop, design, lti, scb, stability
from jaxobs.observers import active, feedback, hinf, kalman, linear
from jaxobs.observers import inverse_dynamics as ido
from jaxobs.observers.base import Controller, ControllerInputs, EstimatorInputs, LinearObserver, run

H = 0.01
NAN = float("nan")
EYE2 = np.eye(2)


# ------------------------------------------------------------------------- small models, built once


def built_once(build):
    """Cache a model builder and build eagerly even when first called inside a ``jit`` case (no leaked tracer)."""

    @functools.cache
    def cached():
        with jax.ensure_compile_time_eval():
            return build()

    return cached


@built_once
def cont():
    return lti.ss([[0.0, 1.0], [0.0, -2.0]], [[0.0], [1.0]], [[1.0, 0.0]])


@built_once
def plant():
    return lti.c2d(cont(), H)


@built_once
def gain():
    return design.acker(plant().A, plant().B, [0.9, 0.9])


@built_once
def aob():
    return active.make_aob(plant(), 1, 0.01)


@built_once
def aob_ctrl():
    """The AOB-1 with the state feedback gain(): params of active.active_observer_controller."""
    return feedback.FeedbackParams(aob(), active.feedback_gain(aob(), gain()))


@built_once
def kf():
    return kalman.make_kalman(plant().A, plant().C, EYE2, 1.0, Gamma=plant().B)


@built_once
def kf2():
    """Two outputs."""
    return kalman.make_kalman(plant().A, EYE2, EYE2, EYE2, Gamma=plant().B)


@built_once
def kf_plain():
    """No inputs (no Gamma)."""
    return kalman.make_kalman(plant().A, plant().C, EYE2, 1.0)


@built_once
def hf():
    return hinf.make_hinf(plant().A, plant().C, EYE2, 1.0, gamma=10.0, Gamma=plant().B)


# Liu & Peng 2002, §4.1 plant (eq. 28) with the §4.2 gains
LP_A = np.array([[-9.754, -14.03], [0.5901, -12.622]])
LP_B, LP_C, LP_K = np.array([[1.0], [0.0]]), np.array([[0.0, 1.0]]), np.array([[47.0], [10.0]])


def make_id(**kwargs):
    return ido.make_inverse_dynamics(LP_A, LP_B, LP_C, LP_K, -10.0, 1.0, h=H, case=2, **kwargs)


@built_once
def idp():
    return make_id()


@built_once
def idp_gamma():
    """With the known term Gamma(u, y) given by its value (Bu = I)."""
    return make_id(Bu=EYE2)


def zeros(*shape):
    return jnp.zeros(shape)


def jit(f, *args):
    """``f(*args)`` traced under ``jit``: a static-shape check must raise while tracing."""
    return jax.jit(f)(*args)


def kalman_run(params, u_prev, y):
    return run(kalman.kalman_filter, params, EstimatorInputs(y=y, u_prev=u_prev))


def aob_run(y, u_prev):
    """The AOB as an estimator."""
    return run(active.active_observer, aob(), EstimatorInputs(y=y, u_prev=u_prev))


def aob_ctrl_run(y, r):
    """The AOB with state feedback as a controller."""
    return run(active.active_observer_controller, aob_ctrl(), ControllerInputs(y=y, r=r))


def simulate_aob(reference, **kwargs):
    return closed_loop.simulate(plant(), active.active_observer_controller, aob_ctrl(), reference, **kwargs)


def wide_command(params, state, inputs):
    """A controller step that returns two commands whatever the plant (for the command-size checks)."""
    return state, feedback.FeedbackOutputs(jnp.zeros((2,)), jnp.zeros((2,)), None)


WIDE = Controller(lambda params: jnp.zeros(()), wide_command)


def mjx_1dof_wide_command():
    from jaxobs.mjx import force_1dof

    model = force_1dof.load_model()[1]
    return force_1dof.closed_loop_rollout(model, WIDE, jnp.zeros(()), jnp.ones(3), substeps=1)


def mjx_6dof_wide_command():
    from jaxobs.mjx import compliant_6dof

    model = compliant_6dof.load_model()[1]
    return compliant_6dof.closed_loop_rollout(model, WIDE, jnp.zeros((6,)), jnp.ones((3, 6)), substeps=1)


def mjx_1dof_jit_noise():
    from jaxobs.mjx import force_1dof

    model = force_1dof.load_model()[1]
    return jit(lambda v: force_1dof.rollout(model, jnp.ones(3), noise=v, substeps=1).force, jnp.ones(4))


# ------------------------------------------------------------------------------- the table of cases

# fmt: off
CASES = [
    # lti: models and discretisation
    ("ss-A-not-square", lambda: lti.ss(np.ones((2, 3)), np.ones((2, 1)), np.ones((1, 2))), "A"),
    ("ss-B-rows", lambda: lti.ss(EYE2, np.ones((3, 1)), np.ones((1, 2))), "B"),
    ("ss-C-columns", lambda: lti.ss(EYE2, np.ones((2, 1)), np.ones((1, 3))), "C"),
    ("ss-D-shape", lambda: lti.ss(EYE2, np.ones((2, 1)), np.ones((1, 2)), np.ones((2, 2))), "D"),
    ("ss-A-nan", lambda: lti.ss([[NAN]], [[1.0]], [[1.0]]), "A"),
    ("ss-A-complex", lambda: lti.ss(1j * EYE2, np.ones((2, 1)), np.ones((1, 2))), "A"),
    ("ss-dt-zero", lambda: lti.ss(EYE2, np.ones((2, 1)), np.ones((1, 2)), dt=0.0), "dt"),
    ("ss-dt-bool", lambda: lti.ss(EYE2, np.ones((2, 1)), np.ones((1, 2)), dt=True), "dt"),
    ("ss-jit-B-rows", lambda: jit(lambda B: lti.ss(EYE2, B, np.ones((1, 2))).A, zeros(3, 1)), "B"),
    ("c2d-n_delay-half", lambda: lti.c2d(cont(), H, 0.0, n_delay=0.5), "n_delay"),
    ("c2d-n_delay-bool", lambda: lti.c2d(cont(), H, 0.0, n_delay=True), "n_delay"),
    ("c2d-n_delay-negative", lambda: lti.c2d(cont(), H, 0.0, n_delay=-1), "n_delay"),
    ("c2d-n_delay-above-limit", lambda: lti.c2d(cont(), H, 0.0, n_delay=lti.MAX_DELAY_SLOTS + 1), "n_delay"),
    ("c2d-delay-1e6", lambda: lti.c2d(cont(), H, 1e6), "delay"),
    ("c2d-delay-nan", lambda: lti.c2d(cont(), H, NAN), "delay"),
    ("c2d-h-1e300", lambda: lti.c2d(cont(), 1e300), "h"),
    ("c2d-A-1e300", lambda: lti.c2d(lti.ss([[0.0, 1.0], [0.0, -1e300]], [[0.0], [1.0]], [[1.0, 0.0]]), H), "h"),
    ("c2d-overflowing-mode", lambda: lti.c2d(lti.ss([[1e5, 0.0], [0.0, -2.0]], [[0.0], [1.0]], [[1.0, 0.0]]), H), "h"),
    ("c2d-h-bool", lambda: lti.c2d(cont(), True), "h"),
    ("c2d-vmap-n_delay-float", lambda: jax.vmap(lambda t: lti.c2d(cont(), H, t, n_delay=1.5).A)(zeros(2)), "n_delay"),
    ("ctrb-B-rows", lambda: lti.ctrb(EYE2, np.ones((3, 1))), "B"),
    ("obsv-C-columns", lambda: lti.obsv(EYE2, np.ones((1, 3))), "C"),
    # design
    ("acker-poles-2d", lambda: design.acker(plant().A, plant().B, [[0.5, 0.5]]), "poles"),
    ("acker-poles-count", lambda: design.acker(plant().A, plant().B, [0.5, 0.5, 0.5]), "poles"),
    ("acker-poles-nan", lambda: design.acker(plant().A, plant().B, [NAN, 0.5]), "poles"),
    ("acker-jit-poles-count", lambda: jit(lambda p: design.acker(plant().A, plant().B, p), zeros(3)), "poles"),
    ("acker-Gamma-two-inputs", lambda: design.acker(plant().A, EYE2, [0.5, 0.5]), "Gamma"),
    ("place-zero_input_columns-float", lambda: design.place(EYE2, EYE2, [0.1, 0.2], zero_input_columns=(0.5,)),
     "zero_input_columns"),
    ("place-poles-2d", lambda: design.place(EYE2, EYE2, [[0.1, 0.2]]), "poles"),
    ("critically_damped-n_fast-float", lambda: design.critically_damped_poles(H, 0.1, 1.5), "n_fast"),
    ("critically_damped-n_fast-negative", lambda: design.critically_damped_poles(H, 0.1, -1), "n_fast"),
    ("critically_damped-tau_c-zero", lambda: design.critically_damped_poles(H, 0.0, 1), "tau_c"),
    ("critically_damped-h-negative", lambda: design.critically_damped_poles(-H, 0.1, 1), "h"),
    ("dc_compensation-target-rows", lambda: design.dc_compensation(np.ones((2, 1)), np.eye(3)), "dc_target"),
    ("dc_compensation-target-nan", lambda: design.dc_compensation(NAN, 2.0), "dc_target"),
    # stability
    ("margins-num_points-1", lambda: stability.stability_margins(plant_loop(), num_points=1), "num_points"),
    ("margins-num_points-float", lambda: stability.stability_margins(plant_loop(), num_points=64.0), "num_points"),
    ("margins-max_crossings-0", lambda: stability.stability_margins(plant_loop(), max_crossings=0), "max_crossings"),
    ("margins-bisection_steps-negative", lambda: stability.stability_margins(plant_loop(), bisection_steps=-1),
     "bisection_steps"),
    ("margins-continuous", lambda: stability.stability_margins(cont()), "sys"),
    ("loop_transfer-continuous-plant", lambda: stability.loop_transfer(cont(), linear.linear_controller, linear_ctrl()),
     "plant"),
    ("spectral_radius-not-square", lambda: stability.spectral_radius(np.ones((2, 3))), "A"),
    ("unstructured_mismatch-negative-norm",
     lambda: stability.unstructured_mismatch(jax.random.key(0), EYE2, np.ones((2, 1)), -1.0, 0.1), "phi_norm"),
    # Kalman filter
    ("make_kalman-x0-length", lambda: kalman.make_kalman(plant().A, plant().C, EYE2, 1.0, x0=zeros(3)), "x0"),
    ("make_kalman-x0-nan", lambda: kalman.make_kalman(plant().A, plant().C, EYE2, 1.0, x0=[NAN, 0.0]), "x0"),
    ("make_kalman-jit-x0-length",
     lambda: jit(lambda x0: kalman.make_kalman(plant().A, plant().C, EYE2, 1.0, x0=x0).x0, zeros(3)), "x0"),
    ("make_kalman-C-columns", lambda: kalman.make_kalman(plant().A, np.ones((1, 3)), EYE2, 1.0), "C"),
    ("make_kalman-Gamma-rows", lambda: kalman.make_kalman(plant().A, plant().C, EYE2, 1.0, Gamma=np.ones((3, 1))),
     "Gamma"),
    ("kalman-y-3-outputs-for-1", lambda: kalman_run(kf(), zeros(5, 1), zeros(5, 3)), "inputs.y"),
    ("kalman-jit-y-3-outputs-for-1", lambda: jit(lambda y: kalman_run(kf(), zeros(5, 1), y), zeros(5, 3)), "inputs.y"),
    ("kalman-jit-y-1-output-for-2", lambda: jit(lambda y: kalman_run(kf2(), zeros(5, 1), y), zeros(5, 1)), "inputs.y"),
    ("kalman-jit-u_prev-2-for-1", lambda: jit(lambda u: kalman_run(kf(), u, zeros(5, 1)), zeros(5, 2)),
     "inputs.u_prev"),
    ("kalman-jit-u_prev-for-a-model-without-inputs", lambda: jit(lambda u: kalman_run(kf_plain(), u, zeros(5, 1)),
                                                                 zeros(5, 1)), "inputs.u_prev"),
    ("run-y-and-u_prev-lengths", lambda: kalman_run(kf(), zeros(4, 1), zeros(5, 1)), "inputs"),
    ("filter_shared_model-y-without-batch",
     lambda: kalman.filter_shared_model(kf(), EstimatorInputs(y=zeros(5, 1), u_prev=zeros(5, 1))), "inputs.y"),
    ("filter_shared_model-u_prev-length",
     lambda: kalman.filter_shared_model(kf(), EstimatorInputs(y=zeros(2, 5, 1), u_prev=zeros(2, 4, 1))),
     "inputs.u_prev"),
    # active observer
    ("make_aob-order-1.5", lambda: active.make_aob(plant(), 1.5, 0.01), "order"),
    ("make_aob-order-2.0", lambda: active.make_aob(plant(), 2.0, 0.01), "order"),
    ("make_aob-order-bool", lambda: active.make_aob(plant(), True, 0.01), "order"),
    ("make_aob-order-0", lambda: active.make_aob(plant(), 0, 0.01), "order"),
    ("make_aob-order-str", lambda: active.make_aob(plant(), "1", 0.01), "order"),
    ("make_aob-x0-length", lambda: active.make_aob(plant(), 1, 0.01, x0=zeros(2)), "x0"),
    ("make_aob-x0-nan", lambda: active.make_aob(plant(), 1, 0.01, x0=[0.0, NAN, 0.0]), "x0"),
    ("make_aob-q_plant-length", lambda: active.make_aob(plant(), 1, 0.01, q_plant=np.ones(3)), "q_plant"),
    ("make_aob-q_active-length", lambda: active.make_aob(plant(), 1, 0.01, q_active=np.ones(2)), "q_active"),
    ("make_aob-alpha-length", lambda: active.make_aob(plant(), 1, 0.01, alpha=[0.1, 0.2]), "alpha"),
    ("make_aob-alpha-nan", lambda: active.make_aob(plant(), 1, 0.01, alpha=NAN), "alpha"),
    ("make_aob-active-vector", lambda: active.make_aob(plant(), 1, 0.01, active=[1.0, 0.0]), "active"),
    ("make_aob-active-nan", lambda: active.make_aob(plant(), 1, 0.01, active=NAN), "active"),
    ("feedback_gain-jit-L_r-columns", lambda: jit(lambda L: active.feedback_gain(aob(), L), zeros(1, 3)), "L_r"),
    ("active_state_model-order-float", lambda: active.active_state_model(1.5), "order"),
    ("active_state_model-jit-order-traced", lambda: jit(active.active_state_model, 2), "order"),
    ("augment-order-negative", lambda: active.augment(plant(), -1), "order"),
    ("evolution_variance-order-float", lambda: active.evolution_variance(1e-3, 2.5), "order"),
    ("aob_noise_covariance-n_plant-float", lambda: active.aob_noise_covariance(1.5, 1, 1, 1.0, 1.0), "n_plant"),
    ("set_active-vector", lambda: active.set_active(aob(), [1.0, 0.0]), "on"),
    ("set_active-nan", lambda: active.set_active(aob(), NAN), "on"),
    ("aob-jit-y-3-outputs-for-1", lambda: jit(lambda y: aob_run(y, zeros(5, 1)), zeros(5, 3)), "inputs.y"),
    ("aob-jit-u_prev-2-for-1-input", lambda: jit(lambda u: aob_run(zeros(5, 1), u), zeros(5, 2)), "inputs.u_prev"),
    ("aob-controller-jit-y-3-outputs-for-1", lambda: jit(lambda y: aob_ctrl_run(y, zeros(5, 1)), zeros(5, 3)),
     "inputs.y"),
    ("aob-controller-jit-r-2-for-1-input", lambda: jit(lambda r: aob_ctrl_run(zeros(5, 1), r), zeros(5, 2)),
     "inputs.r"),
    ("classify_strategy-gain-shape", lambda: active.classify_strategy(np.ones((3, 1)), np.ones((1, 2))), "gain"),
    # H-infinity filter
    ("make_hinf-x0-length", lambda: hinf.make_hinf(plant().A, plant().C, EYE2, 1.0, gamma=10.0, x0=zeros(3)), "x0"),
    ("make_hinf-gamma-str", lambda: hinf.make_hinf(plant().A, plant().C, EYE2, 1.0, gamma="10"), "gamma"),
    ("make_hinf-Cd-columns", lambda: hinf.make_hinf(plant().A, plant().C, EYE2, 1.0, gamma=10.0, Cd=np.ones((1, 3))),
     "Cd"),
    ("hinf-jit-y-3-outputs-for-1",
     lambda: jit(lambda y: run(hinf.hinf_filter, hf(), EstimatorInputs(y=y, u_prev=zeros(5, 1))), zeros(5, 3)),
     "inputs.y"),
    ("hinf_riccati_sequence-num_steps-float",
     lambda: hinf.hinf_riccati_sequence(EYE2, plant().A, plant().C, None, EYE2, 1.0, 10.0, 2.5), "num_steps"),
    ("gamma_bisection-max_iters-0", lambda: hinf.gamma_bisection(plant().A, plant().C, EYE2, 1.0, max_iters=0),
     "max_iters"),
    # inverse-dynamics observer
    ("make_inverse_dynamics-x0-length", lambda: make_id(x0=zeros(3)), "x0"),
    ("make_inverse_dynamics-lowpass_order-float", lambda: make_id(lowpass_order=1.5), "lowpass_order"),
    ("make_inverse_dynamics-lowpass_pole-vector", lambda: make_id(lowpass_pole=[0.5, 0.5]), "lowpass_pole"),
    ("make_inverse_dynamics-case-float", lambda: ido.make_inverse_dynamics(LP_A, LP_B, LP_C, LP_K, -10.0, 1.0, h=H,
                                                                           case=2.0), "case"),
    ("make_inverse_dynamics-case-3", lambda: ido.make_inverse_dynamics(LP_A, LP_B, LP_C, LP_K, -10.0, 1.0, h=H,
                                                                       case=3), "case"),
    ("make_inverse_dynamics-Bu-rows", lambda: make_id(Bu=np.ones((3, 1))), "Bu"),
    ("inverse_dynamics-jit-u_prev-length",
     lambda: jit(lambda u: run(ido.inverse_dynamics_observer, idp_gamma(), EstimatorInputs(y=zeros(5, 1), u_prev=u)),
                 zeros(5, 3)), "inputs.u_prev"),
    ("inverse_dynamics-jit-y-2-for-1",
     lambda: jit(lambda y: run(ido.inverse_dynamics_observer, idp(), EstimatorInputs(y=y)), zeros(5, 2)),
     "inputs.y"),
    ("left_inverse-rho-shape", lambda: ido.left_inverse(LP_B, np.ones((3, 3))), "rho"),
    ("fact35-rank-above-size", lambda: ido.fact35(EYE2, -EYE2, rank=5), "rank"),
    # closed loop
    ("simulate-disturbance-length", lambda: simulate_aob(zeros(10, 1), disturbance=zeros(7)), "disturbance"),
    ("simulate-noise-length", lambda: simulate_aob(zeros(10, 1), noise=zeros(7)), "noise"),
    ("simulate-reference-2-for-1-input", lambda: simulate_aob(zeros(10, 2)), "reference"),
    ("simulate-x0-length", lambda: simulate_aob(zeros(10, 1), x0=zeros(3)), "x0"),
    ("simulate-reference-nan", lambda: simulate_aob(jnp.full((10, 1), NAN)), "reference"),
    ("simulate-jit-reference-2-for-1-input", lambda: jit(lambda r: simulate_aob(r).y, zeros(10, 2)), "reference"),
    ("simulate-jit-disturbance-length", lambda: jit(lambda d: simulate_aob(zeros(10, 1), disturbance=d).y,
                                                    zeros(9, 1)), "disturbance"),
    ("simulate-plant-2-outputs-for-1",
     lambda: closed_loop.simulate(lti.StateSpace(plant().A, plant().B, EYE2, zeros(2, 1), H),
                                  active.active_observer_controller, aob_ctrl(), zeros(10, 1)), "plant"),
    ("simulate-controller-command-size", lambda: closed_loop.simulate(plant(), WIDE, None, zeros(5, 1)), "params"),
    ("ideal_response-reference-2-for-1-input", lambda: closed_loop.ideal_response(plant(), gain(), zeros(10, 2)),
     "reference"),
    ("ideal_response-L-columns", lambda: closed_loop.ideal_response(plant(), np.ones((1, 3)), zeros(10)), "L"),
    ("ideal_response-jit-reference", lambda: jit(lambda r: closed_loop.ideal_response(plant(), gain(), r),
                                                 zeros(10, 3)), "reference"),
    ("measurement_noise-num_steps-float", lambda: closed_loop.measurement_noise(jax.random.key(0), 2.5, 1.0),
     "num_steps"),
    ("measurement_noise-R-negative", lambda: closed_loop.measurement_noise(jax.random.key(0), 3, -1.0), "R"),
    ("padded-n-float", lambda: linear_ctrl().padded(4.5), "n"),
    ("linear_controller-jit-y-3-for-1",
     lambda: jit(lambda y: run(linear.linear_controller, linear_ctrl(), ControllerInputs(y=y, r=zeros(5))),
                 zeros(5, 3)), "inputs.y"),
    ("linear_controller-jit-L-columns",
     lambda: jit(lambda L: run(linear.linear_controller, feedback.FeedbackParams(linear_ctrl().estimator, L),
                               ControllerInputs(y=zeros(5), r=zeros(5))), zeros(1, 3)), "L"),
    # MJX rollouts
    ("mjx-1dof-controller-command-size", mjx_1dof_wide_command, "params"),
    ("mjx-6dof-controller-command-size", mjx_6dof_wide_command, "params"),
    ("mjx-1dof-jit-noise-length", mjx_1dof_jit_noise, "noise"),
]
# fmt: on


def plant_loop():
    """A stable discrete SISO loop transfer function."""
    return lti.ss(0.5, 1.0, 0.3, dt=H)


@built_once
def linear_ctrl():
    """A fixed-gain observer with state feedback: params of linear.linear_controller."""
    return feedback.FeedbackParams(LinearObserver(plant().A, plant().B, plant().C, jnp.zeros((2, 1))), gain())


@pytest.mark.parametrize("call, name", [pytest.param(call, name, id=case_id) for case_id, call, name in CASES])
def test_bad_input_raises_value_error_naming_the_argument(call, name):
    with pytest.raises(ValueError, match=rf"^{re.escape(name)}\b"):
        call()


def test_case_table_is_large_and_unique():
    ids = [case[0] for case in CASES]
    assert len(ids) >= 60 and len(set(ids)) == len(ids)


# ----------------------------------------------------------------------------------- correct answers


def test_acker_with_integer_arrays_equals_the_float_result():
    """Integer Phi, Gamma (and poles): the characteristic polynomial is no longer truncated to integers."""
    L_int = design.acker(np.array([[1, 1], [0, 1]]), np.array([[0], [1]]), [0.5, 0.5])
    L_float = design.acker(np.array([[1.0, 1.0], [0.0, 1.0]]), np.array([[0.0], [1.0]]), [0.5, 0.5])
    np.testing.assert_allclose(L_int, [[0.25, 1.0]], rtol=1e-14)
    np.testing.assert_array_equal(L_int, L_float)
    assert L_int.dtype == jnp.float64
    np.testing.assert_allclose(design.acker(np.array([[1, 1], [0, 1]]), np.array([0, 1]), np.array([0, 0])), [[1, 2]])


def test_integer_and_mixed_precision_models_are_promoted_to_one_float_dtype():
    """ss/c2d and the observer constructors cast integer and float32/float64 mixes to float64, and the filters
    run (before: scan carry errors) with the results of the same model given in float64."""
    A32 = np.asarray(plant().A, np.float32)
    A = A32.astype(np.float64)
    sys_int = lti.ss([[0, 1], [0, -2]], [[0], [1]], [[1, 0]])
    assert {M.dtype for M in (sys_int.A, sys_int.B, sys_int.C, sys_int.D)} == {jnp.dtype("float64")}
    np.testing.assert_array_equal(lti.c2d(sys_int, H).A, plant().A)

    y = jnp.sin(jnp.arange(8.0))[:, None]
    u = jnp.zeros((8, 1))
    mixed = kalman.make_kalman(A32, plant().C, EYE2, 1.0, Gamma=plant().B, x0=np.zeros(2, np.float32))
    assert {leaf.dtype for leaf in jax.tree_util.tree_leaves(mixed)} == {jnp.dtype("float64")}
    reference = kalman.make_kalman(A, plant().C, EYE2, 1.0, Gamma=plant().B)
    np.testing.assert_array_equal(kalman_run(mixed, u, y)[1].x, kalman_run(reference, u, y)[1].x)

    plant32 = lti.StateSpace(*(jnp.asarray(M, jnp.float32) for M in (plant().A, plant().B, plant().C, plant().D)), H)
    params = active.make_aob(plant32, 1, np.array([[0.01]]))  # float32 plant, float64 R
    assert params.Phi.dtype == jnp.float64 and params.x0.dtype == jnp.float64
    out = run(active.active_observer, params, EstimatorInputs(y=y, u_prev=u))[1]
    assert out.x.dtype == jnp.float64 and np.all(np.isfinite(out.x))

    h_mixed = hinf.make_hinf(A32, plant().C, EYE2, 1, gamma=10, Gamma=plant().B)
    h_ref = hinf.make_hinf(A, plant().C, EYE2, 1.0, gamma=10.0, Gamma=plant().B)
    run_h = lambda p: run(hinf.hinf_filter, p, EstimatorInputs(y=y, u_prev=u))[1].x
    np.testing.assert_array_equal(run_h(h_mixed), run_h(h_ref))

    id_int = ido.make_inverse_dynamics([[-10, -14], [1, -13]], [[1], [0]], [[0, 1]], [[47], [10]], -10, 1, h=1, case=2)
    assert {leaf.dtype for leaf in jax.tree_util.tree_leaves(id_int)} == {jnp.dtype("float64")}


def test_c2d_of_a_stiff_model_matches_scipy():
    """h ||A|| = 1e7, beyond the 16 squarings of jax.scipy.linalg.expm's default (NaN before), is discretised."""
    sys = lti.ss([[0.0, 1.0], [0.0, -1e9]], [[0.0], [1e9]], [[1.0, 0.0]])
    d = lti.c2d(sys, H)
    block = np.zeros((3, 3))
    block[:2, :2], block[:2, 2:] = np.asarray(sys.A), np.asarray(sys.B)
    E = scipy.linalg.expm(block * H)
    np.testing.assert_allclose(d.A, E[:2, :2], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(d.B, E[:2, 2:], rtol=1e-9, atol=1e-15)


def test_the_documented_shorthands_still_work():
    """A (T,) series for a single input/output and a scalar measurement for one output are the documented
    shorthands (no other broadcast is): same results as the (T, 1) forms. A concrete 0-d integer array is a count."""
    np.testing.assert_array_equal(lti.c2d(cont(), H, n_delay=jnp.int32(2)).A, lti.c2d(cont(), H, n_delay=2).A)
    r = jnp.linspace(0.0, 1.0, 6)
    full = simulate_aob(r[:, None], noise=0.01 * r[:, None])
    short = simulate_aob(r, noise=0.01 * r)
    np.testing.assert_array_equal(full.y, short.y)
    ideal = closed_loop.ideal_response(plant(), gain(), r)
    np.testing.assert_array_equal(ideal, closed_loop.ideal_response(plant(), gain(), r[:, None]))
    state = kalman.kalman_filter.init(kf())
    a = kalman.kalman_filter.step(kf(), state, EstimatorInputs(y=1.0, u_prev=0.0))[1].x
    b = kalman.kalman_filter.step(kf(), state, EstimatorInputs(y=jnp.ones(1), u_prev=jnp.zeros(1)))[1].x
    np.testing.assert_array_equal(a, b)


# ------------------------------------------------------------------ wrong types (issue 28): every class, every array

WRONG_TYPES = {
    "str": "abc",
    "dict": {"a": 1.0},
    "object": object(),
    "ragged": [[1.0], [1.0, 2.0]],
    "strings": [["a", "b"], ["c", "d"]],
    "complex": 1j * EYE2,
}


def _nonlinear(**kwargs):
    from jaxobs.nonlinear import nonlinear_model

    args = dict(Q=EYE2, R=[[1.0]], x0=np.zeros(2)) | kwargs
    return nonlinear_model(lambda x, u, t: x, lambda x: x[:1], args.pop("Q"), args.pop("R"), **args)


# (case, call with the wrong value, argument named, required: None is wrong too)
TYPE_TARGETS = [
    ("make_kalman-Phi", lambda v: kalman.make_kalman(v, plant().C, EYE2, 1.0), "Phi", True),
    ("make_kalman-C", lambda v: kalman.make_kalman(plant().A, v, EYE2, 1.0), "C", True),
    ("make_kalman-Q", lambda v: kalman.make_kalman(plant().A, plant().C, v, 1.0), "Q", True),
    ("make_kalman-R", lambda v: kalman.make_kalman(plant().A, plant().C, EYE2, v), "R", True),
    ("make_kalman-P0", lambda v: kalman.make_kalman(plant().A, plant().C, EYE2, 1.0, P0=v), "P0", False),
    ("make_aob-R", lambda v: active.make_aob(plant(), 1, v), "R", True),
    ("make_ckf-Q", lambda v: active.make_ckf(plant(), 1.0, Q=v), "Q", False),
    ("nonlinear_model-Q", lambda v: _nonlinear(Q=v), "Q", True),
    ("nonlinear_model-R", lambda v: _nonlinear(R=v), "R", True),
    ("nonlinear_model-x0", lambda v: _nonlinear(x0=v), "x0", True),
    ("nonlinear_model-P0", lambda v: _nonlinear(P0=v), "P0", False),
]
TYPE_CASES = [
    pytest.param(call, name, value, id=f"{case}-{kind}")
    for case, call, name, required in TYPE_TARGETS
    for kind, value in [*WRONG_TYPES.items(), *([("None", None)] if required else [])]
]


@pytest.mark.parametrize("call, name, value", TYPE_CASES)
def test_wrong_types_raise_value_error_naming_the_argument(call, name, value):
    """Strings, dicts, objects, ragged or string sequences and complex arrays (and None where the argument is
    required) give a ValueError naming the argument (before: JAX's TypeError, e.g. make_kalman(Phi, C, "abc", R))."""
    with pytest.raises(ValueError, match=rf"^{re.escape(name)}\b"):
        call(value)


@pytest.mark.parametrize("value", ["no", "False", 0, 1, 1.0, None, np.array([True])])
@pytest.mark.parametrize(
    "call, name",
    [
        pytest.param(lambda v: _nonlinear(continuous=v), "continuous", id="nonlinear_model-continuous"),
        pytest.param(lambda v: kalman.make_kalman(plant().A, plant().C, EYE2, 1.0, steady_state=v), "steady_state",
                     id="make_kalman-steady_state"),
        pytest.param(lambda v: kalman.make_kalman(plant().A, plant().C, EYE2, 1.0, joseph=v), "joseph",
                     id="make_kalman-joseph"),
        pytest.param(lambda v: active.make_aob(plant(), 1, 1.0, steady_state=v), "steady_state",
                     id="make_aob-steady_state"),
    ],
)  # fmt: skip
def test_switches_must_be_bools(call, name, value):
    """A switch takes True or False only: nonlinear_model(..., continuous="no") was taken as True."""
    with pytest.raises(ValueError, match=rf"^{re.escape(name)} must be a bool"):
        call(value)


# ------------------------------------------------- the vehicle package and Grip's design-time modules (issue 28)


def _v(module: str):
    """A module of the vehicle package (imported on first use: ``import jaxobs`` does not import it)."""
    import importlib

    return importlib.import_module(f"jaxobs.vehicle.{module}")


def _car():
    return _v("model").VehicleParams()


# fmt: off
VEHICLE_CASES = [
    ("low_pass-cutoff-negative", lambda: _v("sensors").low_pass(np.ones(5), -1.0, 0.01), "cutoff"),
    ("low_pass-cutoff-nan", lambda: _v("sensors").low_pass(np.ones(5), NAN, 0.01), "cutoff"),
    ("low_pass-period-zero", lambda: _v("sensors").low_pass(np.ones(5), 1.0, 0.0), "period"),
    ("low_pass-x-str", lambda: _v("sensors").low_pass("abc", 1.0, 0.01), "x"),
    ("low_pass-x-empty", lambda: _v("sensors").low_pass(np.ones(0), 1.0, 0.01), "x"),
    ("inclination_gain_bound-a-nan", lambda: _v("road_angles").inclination_gain_bound(NAN), "a"),
    ("inclination_gain_bound-a-negative", lambda: _v("road_angles").inclination_gain_bound(-1.0), "a"),
    ("bank_gain_bound-delta_min-nan", lambda: _v("road_angles").bank_gain_bound(1.0, NAN), "delta_min"),
    ("bank_gain_bound-K_vy-negative", lambda: _v("road_angles").bank_gain_bound(-1.0, 0.1), "K_vy"),
    ("final_angles-outputs", lambda: _v("road_angles").final_angles(None, np.zeros(3), np.zeros(3)), "outputs"),
    ("simulate-params", lambda: _v("simulate").simulate("sine_steer", "car", duration=0.1), "params"),
    ("simulate-manoeuvre", lambda: _v("simulate").simulate(3, _car(), duration=0.1), "manoeuvre"),
    ("simulate-duration-beyond-int32", lambda: _v("simulate").simulate("sine_steer", _car(), duration=1e12),
     "duration"),
    ("understeer_gradient-vehicle", lambda: _v("model").understeer_gradient("car"), "vehicle"),
    ("make_nvso-vehicle-invalid", lambda: _v("nvso").make_nvso(_v("model").VehicleParams(mass=-1.0)), "mass"),
    ("steady_state-vx-nan", lambda: _v("model").steady_state(_car(), NAN), "vx"),
    ("steady_state-r-inf", lambda: _v("model").steady_state(_car(), 20.0, r=np.inf), "r"),
    ("scb-numeric-str", lambda: scb.scb([[0.0]], [[1.0]], [[1.0]], numeric="no"), "numeric"),
]
# fmt: on


@pytest.mark.parametrize("call, name", [pytest.param(call, name, id=case_id) for case_id, call, name in VEHICLE_CASES])
def test_vehicle_and_scb_bad_inputs_raise_naming_the_argument(call, name):
    """Filter constants, gain bounds, simulated time and the types of the vehicle package's public functions (before:
    low_pass(x, -1, 0.01) returned x unfiltered, the gain bounds returned NaN or negative bounds, simulate with
    duration = 1e12 tried to allocate 8 PB, a string for the vehicle gave an AttributeError)."""
    with pytest.raises(ValueError, match=rf"^{re.escape(name)}\b"):
        call()


def test_checked_raises_in_compiled_code_what_eager_calls_raise():
    """``jaxobs.checked``: a negative R under jit(vmap(...)) raises the eager call's ValueError naming R; a NaN
    Q and a non-positive sample time are refused the same way; good values pass and give the unchecked result."""
    import jaxobs as jo

    def design(r):
        return jo.make_kalman([[1.0]], [[1.0]], [[0.1]], r[None, None]).x0

    with pytest.raises(ValueError, match=r"^R must be positive definite \(smallest eigenvalue -1"):
        jo.checked(jax.jit(jax.vmap(design)))(jnp.array([1.0, -1.0]))
    good = jnp.array([1.0, 2.0])
    np.testing.assert_array_equal(jo.checked(jax.jit(jax.vmap(design)))(good), jax.vmap(design)(good))

    def with_q(q):
        return jo.make_kalman([[1.0]], [[1.0]], q[None, None], [[1.0]]).x0

    with pytest.raises(ValueError, match="^Q contains NaN or infinite entries"):
        jo.checked(jax.jit(with_q))(jnp.array(jnp.nan))

    def discretised(h):
        return jo.c2d(jo.ss([[0.0]], [[1.0]], [[1.0]]), 0.1, delay=h, n_delay=1).A

    with pytest.raises(ValueError, match="^delay must be a finite non-negative number"):
        jo.checked(jax.jit(discretised))(jnp.array(-0.05))
    with pytest.raises(ValueError, match="must be the outermost call"):
        jax.jit(jo.checked(design))(jnp.array(1.0))
