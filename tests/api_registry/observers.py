"""Registry entries: the estimators and controllers (jaxobs.observers and its modules) and their building blocks.

An estimator's entry runs it over a short record with ``run``; ``diff="params"`` with ``tangent="scale"`` scales
every floating leaf of its params (covariances stay definite, gains stay gains), ``diff="inputs"`` perturbs the
measurements (and inputs)."""

import functools

import numpy as np

from tests.api_registry import Design, Example, slow
from tests.api_registry.models import (
    A2,
    B2,
    C2,
    P2,
    Q2,
    QUAT_A,
    QUAT_B,
    R1,
    U1,
    X2,
    Y1,
    _inputs,
    _pendulum,
    _rotation,
    _ss_discrete,
)

T = 12
Y_SEQ = np.sin(0.4 * np.arange(T))[:, None]
U_SEQ = np.cos(0.3 * np.arange(T))[:, None]


def _run(estimator, params, inputs):
    from jaxobs.observers.base import run

    return run(estimator, params, inputs)


def estimator(params, inputs=None, *, diff="params", tangent=None, **options):
    """The entry of an estimator: ``run`` over ``inputs`` (default: ``Y_SEQ`` and ``U_SEQ``)."""
    build = lambda: dict(params=params(), inputs=inputs() if inputs else _inputs(Y_SEQ, U_SEQ))
    tangent = tangent or ("scale" if diff == "params" else "random")
    return Example(build, diff=diff, tangent=tangent, call=_run, **options)


@functools.cache
def _kalman():
    from jaxobs.observers.kalman import make_kalman

    with __import__("jax").ensure_compile_time_eval():
        return make_kalman(A2, C2, Q2, R1, Gamma=B2, P0=P2)


def _steady_kalman():
    from jaxobs.observers.kalman import with_steady_state_gain

    return with_steady_state_gain(_kalman())


def _aob():
    from jaxobs.observers.active import make_aob

    return make_aob(_ss_discrete(), 1, R1, q_active=1e-3, P0=np.eye(3))


def _hinf():
    from jaxobs.observers.hinf import make_hinf

    return make_hinf(A2, C2, Q2, R1, gamma=5.0, Gamma=B2, P0=P2)


LP_A = np.array([[-9.754, -14.03], [0.5901, -12.622]])
LP_B, LP_C, LP_K = np.array([[1.0], [0.0]]), np.array([[0.0, 1.0]]), np.array([[47.0], [10.0]])


def _inverse_dynamics():
    from jaxobs.observers.inverse_dynamics import make_inverse_dynamics

    return make_inverse_dynamics(LP_A, LP_B, LP_C, LP_K, -10.0, 1.0, h=0.01, case=2)


KALMAN = {
    "jaxobs.observers.base.run": Example(
        lambda: dict(params=_kalman(), inputs=_inputs(Y_SEQ, U_SEQ)),
        call=lambda fn, params, inputs: fn(_kalman_filter(), params, inputs),
        diff="params",
        tangent="scale",
    ),
    "jaxobs.observers.kalman.make_kalman": Example(lambda: dict(Phi=A2, C=C2, Q=Q2, R=R1, Gamma=B2, P0=P2), diff="Q"),
    "jaxobs.observers.kalman.with_steady_state_gain": Example(lambda: dict(params=_kalman()), tangent="scale"),
    "jaxobs.observers.kalman.kalman_filter": estimator(_kalman),
    "jaxobs.observers.kalman.square_root_form": Example(
        lambda: dict(params=_kalman()), tangent="scale", out=lambda p: (p.Q_sqrt @ p.Q_sqrt.T, p.P0_sqrt @ p.P0_sqrt.T)
    ),
    "jaxobs.observers.kalman.square_root_kalman_filter": estimator(
        lambda: __import__("jaxobs.observers.kalman").observers.kalman.square_root_form(_kalman())
    ),
    "jaxobs.observers.kalman.filter_shared_model": Example(
        lambda: dict(params=_kalman(), inputs=_inputs(np.stack([Y_SEQ, -Y_SEQ]), np.stack([U_SEQ, U_SEQ]))),
        diff="inputs",
        skip={"batch": "inputs has a documented leading batch axis of sequences"},
    ),
    "jaxobs.observers.kalman.step_model": Example(lambda: dict(params=_kalman(), model={"Q": 2 * Q2}), diff="model"),
}


def _kalman_filter():
    from jaxobs.observers.kalman import kalman_filter

    return kalman_filter


def _key(seed=0):
    import jax

    return jax.random.key(seed)


AOB_Y = np.sin(0.4 * np.arange(T))[:, None]


def _aob_steady():
    from jaxobs.observers.active import with_steady_state_gains

    return with_steady_state_gains(_aob())


def _aob_controller():
    from jaxobs.observers.active import feedback_gain
    from jaxobs.observers.feedback import FeedbackParams

    return FeedbackParams(_aob(), feedback_gain(_aob(), np.array([[2.0, 0.5]])))


def _controller_inputs():
    from jaxobs.observers.base import ControllerInputs

    return ControllerInputs(y=Y_SEQ, r=np.ones((T, 1)))


ACTIVE = {
    "jaxobs.observers.active.make_aob": Example(
        lambda: dict(plant=_ss_discrete(), order=1, R=R1, q_active=np.float64(1e-3)), diff="R"
    ),
    "jaxobs.observers.active.make_ckf": Example(lambda: dict(plant=_ss_discrete(), R=R1, Q=Q2), diff="Q"),
    "jaxobs.observers.active.active_observer": estimator(_aob),
    "jaxobs.observers.active.active_observer_controller": estimator(_aob_controller, _controller_inputs),
    "jaxobs.observers.active.with_steady_state_gains": Example(lambda: dict(params=_aob()), tangent="scale"),
    "jaxobs.observers.active.feedback_gain": Example(
        lambda: dict(params=_aob(), L_r=np.array([[2.0, 0.5]])), diff="L_r"
    ),
    "jaxobs.observers.active.disturbance": Example(
        lambda: dict(params=_aob(), x=np.array([0.1, 0.2, 0.3])), diff="x", batched=("x",)
    ),
    "jaxobs.observers.active.augment": Example(lambda: dict(plant=_ss_discrete(), order=2), diff="plant"),
    "jaxobs.observers.active.evolution_variance": Example(
        lambda: dict(sigma2=np.float64(1e-3), order=2, c=np.float64(0.5))
    ),
    "jaxobs.observers.active.aob_noise_covariance": Example(
        lambda: dict(n_plant=3, order=1, n_channels=1, q_plant=np.float64(1e-6), q_active=np.float64(1e-3)),
        diff="q_active",
    ),
    "jaxobs.observers.active.set_active": Example(
        lambda: dict(params=_aob(), on=np.float64(0.0)),
        diff="params",
        tangent="scale",
        skip={"batch": "params may be stacked per DOF (documented: one switch per DOF of stacked controllers)"},
    ),
    "jaxobs.observers.active.adaptive_variance": Example(
        lambda: dict(evolution=np.array([0.3]), alpha=np.array([0.2]), sigma_floor=np.array([0.01])),
        batched=("evolution", "alpha", "sigma_floor"),
    ),
    "jaxobs.observers.active.alpha_for_floor": Example(
        lambda: dict(evolution=np.array([0.003]), sigma_floor=np.array([0.01])), batched=("evolution", "sigma_floor")
    ),
    "jaxobs.observers.active.strategy_alpha": Example(
        lambda: dict(evolution=np.array([0.3]), q=np.array([0.2])), batched=("evolution", "q")
    ),
    "jaxobs.observers.active.constant_strategy_variance": Example(
        lambda: dict(evolution=np.array([0.3]), c=np.array([2.0])), batched=("evolution", "c")
    ),
    "jaxobs.observers.active.deviation_variance": Example(lambda: dict(gamma=np.float64(0.3)), batched=("gamma",)),
    "jaxobs.observers.active.sensor_based_gain": Example(lambda: dict(C=np.array([[1.0, 0.0, 0.5]]))),
    "jaxobs.observers.active.classify_strategy": Design(
        lambda: dict(gain=np.array([[0.5], [0.1], [0.0]]), C=np.array([[1.0, 0.0, 0.0]]))
    ),
}


def _luenberger():
    from jaxobs.observers.ct_linear import make_luenberger

    return make_luenberger([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[3.0], [2.0]])


def _kalman_bucy():
    from jaxobs.observers.ct_linear import make_kalman_bucy

    return make_kalman_bucy([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], np.eye(2), np.eye(1))


def _pendulum_injection(y, u):
    import jax.numpy as jnp

    return jnp.stack([0.0 * y, -jnp.sin(y) + u[0]])


def _output_injection():
    from jaxobs.observers.ct_linear import make_output_injection

    return make_output_injection(_pendulum_injection, 2, poles=[-2.0, -3.0])


def _kalman_bucy_estimate():
    from jaxobs.observers.ct_linear import KalmanBucyEstimate

    return KalmanBucyEstimate(x=X2, P=P2)


CT_LINEAR = {
    "jaxobs.observers.ct_linear.make_luenberger": Example(
        lambda: dict(A=AC2, B=np.array([[0.0], [1.0]]), C=C2, K=np.array([[3.0], [2.0]])), diff="K"
    ),
    "jaxobs.observers.ct_linear.make_kalman_bucy": Example(
        lambda: dict(A=AC2, B=np.array([[0.0], [1.0]]), C=C2, Q=Q2, R=R1), diff="Q"
    ),
    "jaxobs.observers.ct_linear.make_output_injection": Example(
        lambda: dict(gamma=_pendulum_injection, n=2, poles=np.array([-2.0, -3.0])), diff="poles"
    ),
    "jaxobs.observers.ct_linear.luenberger_rate": Example(
        lambda: dict(params=_luenberger(), x_hat=X2, u=U1, y=Y1, t=np.float64(0.1)), diff="x_hat"
    ),
    "jaxobs.observers.ct_linear.kalman_bucy_rate": Example(
        lambda: dict(params=_kalman_bucy(), estimate=_kalman_bucy_estimate(), u=U1, y=Y1, t=np.float64(0.1)), diff="y"
    ),
    "jaxobs.observers.ct_linear.output_injection_rate": Example(
        lambda: dict(params=_output_injection(), z_hat=X2, u=U1, y=np.float64(0.3), t=np.float64(0.1)), diff="z_hat"
    ),
    "jaxobs.observers.ct_linear.luenberger_output": Example(
        lambda: dict(params=_luenberger(), x_hat=X2, u=U1), diff="x_hat"
    ),
    "jaxobs.observers.ct_linear.kalman_bucy_output": Example(
        lambda: dict(params=_kalman_bucy(), estimate=_kalman_bucy_estimate(), u=U1), diff="estimate"
    ),
    "jaxobs.observers.ct_linear.output_injection_output": Example(
        lambda: dict(params=_output_injection(), z_hat=X2, u=U1), diff="z_hat"
    ),
    "jaxobs.observers.ct_linear.augment": Example(
        lambda: dict(
            A=np.array([[-1.0]]),
            B=np.array([[1.0]]),
            C=np.array([[1.0]]),
            E=np.array([[1.0]]),
            A_w=np.array([[0.0, 2.0], [-2.0, 0.0]]),
            C_w=np.array([[1.0, 0.0]]),
        ),
        diff="A_w",
    ),
    "jaxobs.observers.ct_linear.sinusoid_exosystem": Example(lambda: dict(frequencies=np.array([2.0, 5.0]))),
    "jaxobs.observers.ct_linear.as_continuous": Example(
        lambda: dict(params=_luenberger(), dt=np.float64(0.01)), diff="params", tangent="scale"
    ),
}

AC2 = np.array([[0.0, 1.0], [-2.0, -3.0]])


def _continuous():
    import jax.numpy as jnp

    from jaxobs.observers.continuous import make_continuous_observer

    F = lambda x, u, y, t: jnp.array([x[1], 0.0]) + jnp.array([4.0, 4.0]) * (y[0] - x[0])
    return make_continuous_observer(F, lambda x, u: x[:1], x0=np.zeros(2), dt=0.01)


def _ekf():
    from jaxobs.observers.ekf import make_ekf

    return make_ekf(_pendulum())


def _ukf():
    from jaxobs.observers.ukf import make_ukf

    return make_ukf(_pendulum())


def _particle():
    from jaxobs.observers.particle import make_particle_filter

    return make_particle_filter(_pendulum(), 32, key=_key())


def _enkf():
    from jaxobs.observers.ensemble import make_enkf

    return make_enkf(_pendulum(), 16, key=_key())


MONTE_CARLO = {
    "grad": "resampling and perturbed draws: the likelihood's gradient is a stop-gradient estimator "
    "(tests/observers/test_particle.py checks it statistically), not the derivative of one draw"
}

NONLINEAR = {
    "jaxobs.observers.continuous.make_continuous_observer": Example(
        lambda: dict(F=lambda x, u, y, t: -x, h=lambda x, u: x[:1], x0=X2, dt=np.float64(0.01)), diff="x0"
    ),
    "jaxobs.observers.continuous.continuous_observer": estimator(_continuous, lambda: _inputs(Y_SEQ)),
    "jaxobs.observers.ekf.make_ekf": Example(lambda: dict(model=_pendulum()), tangent="scale"),
    "jaxobs.observers.ekf.extended_kalman_filter": estimator(_ekf),
    "jaxobs.observers.ekf.taylor": Example(lambda: dict(g=lambda x: 0.8 * x**2, m=X2, P=P2), diff="m"),
    "jaxobs.observers.ukf.make_ukf": Example(lambda: dict(model=_pendulum()), tangent="scale"),
    "jaxobs.observers.ukf.unscented_kalman_filter": estimator(_ukf),
    "jaxobs.observers.ukf.sigma_points": Example(lambda: dict(m=X2, P=P2, alpha=np.float64(0.5))),
    "jaxobs.observers.ukf.unscented": Example(lambda: dict(g=lambda x: x**2, m=X2, P=P2), diff="m"),
    "jaxobs.observers.ukf.manifold_mean": Example(
        lambda: dict(
            manifold=_rotation(), Y=np.stack([QUAT_A, QUAT_B, QUAT_A]), w=np.array([0.5, 0.25, 0.25]), reference=QUAT_B
        ),  # fmt: skip
        diff="Y",
        skip={"batch": "Y is a set of points (N, k): its leading axis is the documented one"},
    ),
    "jaxobs.observers.particle.make_particle_filter": Example(
        lambda: dict(model=_pendulum(), num_particles=8, key=_key()), tangent="scale"
    ),
    "jaxobs.observers.particle.particle_filter": estimator(_particle, diff="inputs", skip=MONTE_CARLO),
    "jaxobs.observers.particle.particle_smoother": Example(
        lambda: dict(params=_particle(), inputs=_inputs(Y_SEQ, U_SEQ), key=_key(1), num_paths=8),
        diff="inputs",
        skip=MONTE_CARLO,
    ),
    "jaxobs.observers.ensemble.make_enkf": Example(
        lambda: dict(model=_pendulum(), num_members=8, key=_key()), tangent="scale"
    ),
    "jaxobs.observers.ensemble.ensemble_kalman_filter": estimator(_enkf, diff="inputs", skip=MONTE_CARLO),
    "jaxobs.observers.ensemble.ensemble_smoother": Example(
        lambda: dict(params=_enkf(), inputs=_inputs(Y_SEQ, U_SEQ)), diff="inputs", skip=MONTE_CARLO
    ),
    "jaxobs.observers.ensemble.stochastic_update": Example(
        lambda: dict(
            forecast=np.array([[0.1, 0.2], [0.3, -0.1], [-0.2, 0.05], [0.0, 0.3]]),
            predicted=np.array([[0.1], [0.3], [-0.2], [0.0]]),
            R=R1,
            y=Y1,
            perturbations=np.array([[0.1], [-0.2], [0.05], [0.3]]),
        ),
        diff="forecast",
    ),
    "jaxobs.observers.ensemble.transform_update": Example(
        lambda: dict(
            forecast=np.array([[0.1, 0.2], [0.3, -0.1], [-0.2, 0.05], [0.0, 0.3]]),
            predicted=np.array([[0.1], [0.3], [-0.2], [0.0]]),
            R=R1,
            y=Y1,
        ),
        diff="forecast",
    ),
    "jaxobs.observers.ensemble.perturbations": Example(
        lambda: dict(params=_enkf(), key=_key(2)), diff="key", tangent="key", skip={"grad": "random draws of a key"}
    ),
}


def _imm_params():
    from jaxobs.observers.imm import make_imm
    from jaxobs.observers.kalman import make_kalman

    modes = [make_kalman(A2, C2, q * Q2, R1, P0=P2) for q in (0.1, 10.0)]
    return make_imm(modes, np.array([[0.9, 0.1], [0.2, 0.8]]))


def _imm_kalman():
    from jaxobs.observers.imm import imm

    return imm(_kalman_filter(), _kalman_filter())


def _linear_observer():
    from jaxobs.observers.base import LinearObserver

    return LinearObserver(A2, B2, C2, np.array([[0.5], [0.2]]))


def _linear_controller_params():
    from jaxobs.observers.feedback import FeedbackParams

    return FeedbackParams(_linear_observer(), np.array([[2.0, 0.5]]))


def _hgo_gains():
    from jaxobs.observers.hgo import hgo_gains

    return hgo_gains([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], [-2.0, -2.0, -2.0], 0.5)


def _hgo():
    import jax.numpy as jnp

    from jaxobs.observers.hgo import make_hgo

    return make_hgo([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[0.0], [1.0]], [[1.0, 0.0]], _hgo_gains().K,
                    lambda v, x, th: jnp.zeros(1), dt=0.01)  # fmt: skip


def _unit_input(t, x):
    import jax.numpy as jnp

    return jnp.eye(1, dtype=x.dtype)


def _modular_law():
    from jaxobs.adaptive import InversionLaw

    return InversionLaw(lambda t, x, phi: phi, adaptation_gain=5.0)


def _modular():
    from jaxobs.observers.modular import make_modular

    return make_modular(lambda t, x: -x, _unit_input, lambda t, x, th: th * x, theta0=[0.5], K_phi=10.0,
                        law=_modular_law(), dt=0.01, n=1)  # fmt: skip


def _modular_state():
    from jaxobs.observers.modular import ModularState

    return ModularState(z=np.array([0.1]), theta_hat=np.array([0.3]))


def _gramian():
    from jaxobs.observers.gramian import make_gramian

    return make_gramian([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], dt=0.1)


def _pe_monitor():
    from jaxobs.observers.pe_monitor import make_pe_monitor

    return make_pe_monitor(2, 8, 0.01, 0.1)


PE_Y = np.stack([np.sin(0.3 * np.arange(T)), np.cos(0.3 * np.arange(T)), np.sin(0.5 * np.arange(T))], axis=1)

OTHERS = {
    "jaxobs.observers.imm.make_imm": Example(
        lambda: dict(modes=[_kalman(), _kalman()], transition=np.array([[0.9, 0.1], [0.2, 0.8]])),
        diff="transition",
        skip={"batch": "modes: the params of any estimators, which their own steps check when the IMM runs"},
    ),
    "jaxobs.observers.imm.mix": Example(
        lambda: dict(
            weights=np.array([[0.7, 0.4], [0.3, 0.6]]), x=np.array([[0.1, 0.2], [0.3, -0.1]]), P=np.stack([P2, Q2])
        ),
        diff="x",
    ),
    "jaxobs.observers.linear.linear_observer": estimator(_linear_observer),
    "jaxobs.observers.linear.linear_controller": estimator(_linear_controller_params, _controller_inputs),
    "jaxobs.observers.hinf.make_hinf": Example(
        lambda: dict(Phi=A2, C=C2, Q=Q2, R=R1, gamma=np.float64(5.0), Gamma=B2, P0=P2), diff="Q"
    ),
    "jaxobs.observers.hinf.hinf_filter": estimator(_hinf, out=lambda run: run[1][:6]),
    "jaxobs.observers.hinf.with_steady_state_gain": Example(
        lambda: dict(params=_hinf(), num_iters=200), tangent="scale"
    ),
    "jaxobs.observers.hinf.hinf_correction": Example(
        lambda: dict(P=P2, Cz=np.eye(2), gamma=np.float64(5.0)), out=lambda r: r[0]
    ),
    "jaxobs.observers.hinf.hinf_riccati_step": Example(
        lambda: dict(Pb_prev=P2, Phi=A2, C=C2, Cz=np.eye(2), Q=Q2, R=R1, gamma=np.float64(5.0)), out=lambda r: r[:3]
    ),
    "jaxobs.observers.hinf.hinf_riccati_sequence": Example(
        lambda: dict(P0=P2, Phi=A2, C=C2, Cz=np.eye(2), Q=Q2, R=R1, gamma=np.float64(5.0), num_steps=4),
        out=lambda r: r[:3],
    ),
    "jaxobs.observers.hinf.hinf_steady_state": Example(
        lambda: dict(Phi=A2, C=C2, Cz=np.eye(2), Q=Q2, R=R1, gamma=np.float64(5.0), num_iters=200),
        diff="Q",
        out=lambda r: r[:3],
    ),
    "jaxobs.observers.hinf.gamma_bisection": Example(
        lambda: dict(Phi=A2, C=C2, Q=Q2, R=R1, num_steps=50, max_iters=60),
        diff="Q",
        skip={"grad": "a bisection: piecewise constant in its data"},
    ),
    "jaxobs.observers.feedback.observer_controller": Example(
        lambda: dict(params=_aob_controller(), inputs=_controller_inputs()),
        call=lambda fn, params, inputs: _run(
            fn(__import__("jaxobs.observers.active").observers.active.active_observer), params, inputs
        ),
        diff="params",
        tangent="scale",
    ),
    "jaxobs.observers.hgo.hgo_gains": Design(
        lambda: dict(
            A=np.array([[0.0, 1.0], [0.0, 0.0]]),
            E=np.array([[0.0], [1.0]]),
            C=np.array([[1.0, 0.0]]),
            poles=np.array([-2.0, -2.0, -2.0]),
            eps=np.float64(0.5),
        )
    ),
    "jaxobs.observers.hgo.hgo_observer": estimator(_hgo),
    "jaxobs.observers.hgo.make_hgo": Example(
        lambda: dict(
            A=np.array([[0.0, 1.0], [0.0, 0.0]]),
            B=np.array([[0.0], [1.0]]),
            E=np.array([[0.0], [1.0]]),
            C=np.array([[1.0, 0.0]]),
            K=_hgo_gains().K,
            g=lambda v, x, th: 0.0 * x[:1],
            dt=np.float64(0.01),
        ),
        diff="K",
    ),
    "jaxobs.observers.hgo.smooth_abs": Example(
        lambda: dict(w=np.array([-0.3, 0.05, 0.4]), kappa=np.float64(0.1)), batched=("w",)
    ),
    "jaxobs.observers.modular.make_modular": Example(
        lambda: dict(
            f=lambda t, x: -x,
            B=_unit_input,
            g=lambda t, x, th: th * x,
            theta0=np.array([0.5]),
            K_phi=np.float64(10.0),
            law=_modular_law(),
            dt=np.float64(0.01),
            n=1,
        ),
        diff="K_phi",
        out=lambda p: (p.model.K_phi, p.sampled.x0),
    ),
    "jaxobs.observers.modular.modular_estimator": estimator(_modular, lambda: _inputs(Y_SEQ)),
    "jaxobs.observers.modular.modular_rate": Example(
        lambda: dict(
            model=_modular().model, state=_modular_state(), u=np.zeros(0), x=np.array([0.2]), t=np.float64(0.1)
        ),
        diff="x",
    ),
    "jaxobs.observers.modular.parameter_rate": Example(
        lambda: dict(
            model=_modular().model,
            t=np.float64(0.1),
            x=np.array([0.2]),
            phi_hat=np.array([0.5]),
            theta_hat=np.array([0.3]),
        ),
        diff="phi_hat",
    ),
    "jaxobs.observers.modular.perturbation_estimate": Example(
        lambda: dict(model=_modular().model, state=_modular_state(), t=np.float64(0.1), x=np.array([0.2])), diff="x"
    ),
    "jaxobs.observers.modular.perturbation_error_rate": Example(
        lambda: dict(
            model=_modular().model,
            t=np.float64(0.1),
            x=np.array([0.2]),
            x_dot=np.array([0.1]),
            theta=np.array([0.5]),
            theta_hat=np.array([0.3]),
        ),
        diff="x",
    ),
    "jaxobs.observers.modular.compensation": Example(
        lambda: dict(model=_modular().model, theta_hat=np.array([0.3]), t=np.float64(0.1), x=np.array([0.2])),
        diff="theta_hat",
    ),
    "jaxobs.observers.gramian.make_gramian": Example(
        lambda: dict(
            A=np.array([[0.0, 1.0], [0.0, 0.0]]),
            B=np.array([[0.0], [1.0]]),
            C=np.array([[1.0, 0.0]]),
            dt=np.float64(0.1),
        ),
        diff="A",
    ),
    "jaxobs.observers.gramian.gramian_estimator": estimator(_gramian, out=lambda run: run[1][:2]),
    "jaxobs.observers.pe_monitor.make_pe_monitor": Example(
        lambda: dict(n_regressors=2, window=8, dt=np.float64(0.01), threshold=np.float64(0.1)), diff="dt"
    ),
    "jaxobs.observers.pe_monitor.pe_monitor": estimator(_pe_monitor, lambda: _inputs(PE_Y)),
    "jaxobs.observers.inverse_dynamics.make_inverse_dynamics": Example(
        lambda: dict(A=LP_A, B=LP_B, C=LP_C, K=LP_K, F1=np.float64(-10.0), F2=np.float64(1.0), h=0.01, case=2), diff="K"
    ),
    "jaxobs.observers.inverse_dynamics.inverse_dynamics_observer": estimator(
        _inverse_dynamics, lambda: _inputs(Y_SEQ), fd_step=1e-7
    ),
    "jaxobs.observers.inverse_dynamics.case1_f2": Design(lambda: dict(B=LP_B, C=np.array([[1.0, 0.0]]))),
    "jaxobs.observers.inverse_dynamics.plant_zeros": Design(lambda: dict(A=LP_A, B=LP_B, C=LP_C)),
    "jaxobs.observers.inverse_dynamics.left_inverse": Example(
        lambda: dict(B=np.array([[1.0], [0.5]]), rho=np.array([[0.2, 0.1]]))
    ),
    "jaxobs.observers.inverse_dynamics.case1_gains": Example(
        lambda: dict(A=LP_A, B=LP_B, C=np.array([[1.0, 0.0]]), F1=np.array([[-10.0]]), F2=np.array([[1.0]])), diff="F1"
    ),
    "jaxobs.observers.inverse_dynamics.case2_gains": Example(
        lambda: dict(A=LP_A, B=LP_B, C=LP_C, F1=np.array([[-10.0]]), F2=np.array([[1.0]])), diff="F1"
    ),
    "jaxobs.observers.inverse_dynamics.error_dynamics": Example(
        lambda: dict(A=LP_A, B=LP_B, C=LP_C, K=LP_K, G1=np.array([[0.5, 0.2]]), G2=np.array([[0.1, 0.3]])), diff="K"
    ),
    "jaxobs.observers.inverse_dynamics.fact35": Example(
        lambda: dict(M_e=np.array([[1.0, 0.0], [0.0, 0.0]]), A_e=np.array([[-1.0, 0.5], [0.2, -2.0]]), rank=1),
        diff="A_e",
        skip={"grad": "stability flags and eigenvalues"},
    ),
}

ENTRIES = {**KALMAN, **ACTIVE, **CT_LINEAR, **NONLINEAR, **OTHERS}
ENTRIES = slow(
    ENTRIES,
    "a Riccati solve with its implicit derivative, compiled for eager, jit, vmap and grad (~0.7-3 s of CPU)",
    "jaxobs.observers.active.with_steady_state_gains",
    "jaxobs.observers.gramian.make_gramian",
    "jaxobs.observers.hinf.hinf_steady_state",
    "jaxobs.observers.kalman.with_steady_state_gain",
    "jaxobs.observers.ct_linear.make_kalman_bucy",
    "jaxobs.observers.gramian.make_gramian",
    "jaxobs.observers.ensemble.make_enkf",
)
ENTRIES = slow(
    ENTRIES,
    "an estimator over a record: a scan compiled for eager, jit, vmap and grad (~0.65-2 s of CPU)",
    "jaxobs.observers.active.active_observer",
    "jaxobs.observers.gramian.gramian_estimator",
    "jaxobs.observers.hgo.hgo_observer",
    "jaxobs.observers.ensemble.stochastic_update",
    "jaxobs.observers.active.active_observer_controller",
    "jaxobs.observers.ensemble.ensemble_kalman_filter",
    "jaxobs.observers.ensemble.ensemble_smoother",
    "jaxobs.observers.feedback.observer_controller",
    "jaxobs.observers.hinf.hinf_filter",
    "jaxobs.observers.kalman.filter_shared_model",
    "jaxobs.observers.modular.modular_estimator",
    "jaxobs.observers.particle.particle_filter",
    "jaxobs.observers.particle.particle_smoother",
    "jaxobs.observers.ukf.unscented_kalman_filter",
)

EXEMPT = {
    "jaxobs.observers.active.active_state_model": "static: the companion matrix of an order and a channel count",
    "jaxobs.observers.ukf.unit_points": "static: the points and weights of a rule as NumPy constants",
    "jaxobs.observers.inverse_dynamics.design_gains": "job: an optimisation run (optax steps in a Python loop) that "
    "returns a design; its objective's pieces (error_dynamics, fact35) have entries",
    "jaxobs.observers.imm.imm": "transformation: combines estimators into an estimator (its entry: the IMM of two "
    "Kalman filters run over a record, below as make_imm's)",
}
