"""Registry entries: models, matrix equations, design, the Kalman building blocks, integration, adaptation laws
and nonlinear models (jaxobs.lti, .matrix_equations, .design, .kalman_steps, .plants, .ct, .adaptive, .nonlinear)."""

import numpy as np

from tests.api_registry import Design, Example, slow

# small valid data shared by the entries: a stable discrete pair, a Hurwitz continuous one, covariances
A2 = np.array([[0.9, 0.1], [-0.05, 0.8]])
B2 = np.array([[0.0], [0.1]])
C2 = np.array([[1.0, 0.0]])
AC = np.array([[0.0, 1.0], [-2.0, -3.0]])
Q2 = np.array([[0.2, 0.05], [0.05, 0.1]])
R1 = np.array([[0.5]])
P2 = np.array([[1.0, 0.2], [0.2, 0.5]])
X2 = np.array([0.3, -0.2])
Y1 = np.array([0.7])
U1 = np.array([0.4])


def _ss_continuous():
    from jaxobs.lti import ss

    return ss(AC, [[0.0], [1.0]], [[1.0, 0.0]])


def _ss_discrete():
    from jaxobs.lti import c2d

    return c2d(_ss_continuous(), 0.1)


def _sign_free(update):
    """The outputs of a square-root update that do not depend on the signs of the triangular factors' diagonals
    (which QR picks, and a perturbation of an entry that is zero in the factor can flip): the factors' grams."""
    return update.x, update.K, update.log_likelihood, update.P_sqrt @ update.P_sqrt.T, update.S_sqrt @ update.S_sqrt.T


NOT_DIFFERENTIABLE = {"grad": "a bool or integer answer"}

LTI = {
    "jaxobs.lti.ss": Example(lambda: dict(A=AC, B=B2, C=C2, D=np.zeros((1, 1)))),
    "jaxobs.lti.c2d": Example(lambda: dict(sys=_ss_continuous(), h=0.1, delay=np.float64(0.05), n_delay=1), diff="sys"),
    "jaxobs.lti.tf2ss": Design(lambda: dict(num=np.array([1.0, 2.0]), den=np.array([1.0, 3.0, 2.0])), alternative=""),
    "jaxobs.lti.ctrb": Example(lambda: dict(A=A2, B=B2), batched=("A", "B")),
    "jaxobs.lti.obsv": Example(lambda: dict(A=A2, C=C2), batched=("A", "C")),
    "jaxobs.lti.controllability_rank": Design(lambda: dict(A=A2, B=B2)),
    "jaxobs.lti.observability_rank": Design(lambda: dict(A=A2, C=C2)),
    "jaxobs.lti.unobservable_modes": Design(
        lambda: dict(A=np.diag([1.2, 0.5]), C=np.array([[0.0, 1.0]]), region=lambda lam: abs(lam) >= 1)
    ),  # fmt: skip
    "jaxobs.lti.dcgain": Example(lambda: dict(sys=_ss_discrete())),
    "jaxobs.lti.is_spr": Design(
        lambda: dict(A=np.array([[-1.0]]), B=np.array([[1.0]]), C=np.array([[1.0]]), D=np.array([[0.1]]))
    ),  # fmt: skip
}

MATRIX_EQUATIONS = {
    "jaxobs.matrix_equations.dare": Example(lambda: dict(A=A2, B=B2, Q=Q2, R=R1), diff="Q", out=lambda s: s.X),
    "jaxobs.matrix_equations.filter_dare": Example(lambda: dict(Phi=A2, C=C2, Q=Q2, R=R1), diff="Q", out=lambda s: s.X),
    "jaxobs.matrix_equations.stein": Example(lambda: dict(A=A2, E=Q2)),
    "jaxobs.matrix_equations.is_stable": Example(lambda: dict(A=A2), skip=NOT_DIFFERENTIABLE),
    "jaxobs.matrix_equations.care": Example(
        lambda: dict(A=AC, B=np.array([[0.0], [1.0]]), Q=Q2, R=R1), diff="Q", out=lambda s: s.X
    ),
    "jaxobs.matrix_equations.lyapunov": Example(lambda: dict(A=AC, E=Q2)),
}

DESIGN = {
    "jaxobs.design.characteristic_polynomial": Example(
        lambda: dict(poles=np.array([0.5, 0.2, -0.3]), dtype=np.float64),
        skip={"float32": "its dtype argument sets the output's"},
    ),
    "jaxobs.design.acker": Example(lambda: dict(Phi=A2, Gamma=B2, poles=np.array([0.5, 0.4])), diff="poles"),
    "jaxobs.design.place": Design(
        lambda: dict(Phi=A2, Gamma=np.array([[0.0, 1.0], [0.1, 0.0]]), poles=np.array([0.5, 0.4])),
        alternative="jaxobs.design.acker",
    ),
    "jaxobs.design.dlqr": Example(lambda: dict(A=A2, B=B2, Q=Q2, R=R1), diff="Q"),
    "jaxobs.design.dlqe": Example(lambda: dict(A=A2, G=np.eye(2), C=C2, QN=Q2, RN=R1), diff="QN"),
    "jaxobs.design.lqr": Example(lambda: dict(A=AC, B=np.array([[0.0], [1.0]]), Q=Q2, R=R1), diff="Q"),
    "jaxobs.design.lqe": Example(lambda: dict(A=AC, G=np.eye(2), C=C2, QN=Q2, RN=R1), diff="QN"),
    "jaxobs.design.is_detectable": Design(lambda: dict(A=A2, C=C2)),
    "jaxobs.design.dc_compensation": Example(
        lambda: dict(dc_target=np.array([[1.0]]), dc_closed_loop=np.array([[0.8]]))
    ),
    "jaxobs.design.reference_gain": Example(lambda: dict(plant=_ss_discrete(), L=np.array([[2.0, 0.5]])), diff="L"),
    "jaxobs.design.critically_damped_poles": Example(lambda: dict(h=0.01, tau_c=np.float64(0.05), n_fast=2)),
    "jaxobs.design.critically_damped_gain": Example(
        lambda: dict(plant=_ss_discrete(), tau_c=np.float64(0.5)), diff="tau_c"
    ),
}

KALMAN_STEPS = {
    "jaxobs.kalman_steps.predict_covariance": Example(lambda: dict(P=P2, Phi=A2, Q=Q2)),
    "jaxobs.kalman_steps.kalman_gain": Example(lambda: dict(P1=P2, C=C2, R=R1)),
    "jaxobs.kalman_steps.update_covariance_factors": Example(lambda: dict(P1=P2, C=C2, R=R1)),
    "jaxobs.kalman_steps.update_covariance_moments": Example(lambda: dict(P1=P2, CP1=C2 @ P2, S=C2 @ P2 @ C2.T + R1)),
    "jaxobs.kalman_steps.update_covariance": Example(lambda: dict(P1=P2, C=C2, R=R1)),
    "jaxobs.kalman_steps.riccati_step": Example(lambda: dict(P_prev=P2, Phi=A2, C=C2, Q=Q2, R=R1)),
    "jaxobs.kalman_steps.covariance_sequence": Example(
        lambda: dict(P_init=P2, Phi=A2, C=C2, Q=Q2, R=R1, num_steps=4), diff="Q"
    ),
    "jaxobs.kalman_steps.predict": Example(lambda: dict(x=X2, P=P2, Phi=A2, Q=Q2, Gamma=B2, u_prev=U1)),
    "jaxobs.kalman_steps.update": Example(lambda: dict(x_prior=X2, P_prior=P2, C=C2, R=R1, y=Y1)),
    "jaxobs.kalman_steps.moment_update": Example(
        lambda: dict(x_prior=X2, P_prior=P2, cross=P2 @ C2.T, cov=C2 @ P2 @ C2.T, R=R1, y=Y1, predicted=C2 @ X2)
    ),  # fmt: skip
    "jaxobs.kalman_steps.innovation_gate": Example(
        lambda: dict(innovation=np.array([0.3]), C=C2, P_prior=P2, R=R1, threshold=np.float64(3.0)),
        skip=NOT_DIFFERENTIABLE,
    ),  # fmt: skip
    "jaxobs.kalman_steps.bierman_update": Example(lambda: dict(x_prior=X2, P_prior=P2, C=C2, R=R1, y=Y1)),
    "jaxobs.kalman_steps.ud_factor": Example(lambda: dict(P=P2)),
    "jaxobs.kalman_steps.observed": Example(
        lambda: dict(y=np.array([0.3, np.nan, 1.0])),
        skip={
            "grad": "a mask and the measurement with zeros: piecewise constant "
            "in the missing pattern, the identity elsewhere"
        },
    ),
    "jaxobs.kalman_steps.observed_model": Example(lambda: dict(C=np.eye(2), R=P2, mask=np.array([1.0, 0.0])), diff="R"),
    "jaxobs.kalman_steps.innovation_log_likelihood": Example(
        lambda: dict(innovation=np.array([0.3, -0.1]), S=P2, n_observed=np.float64(2.0))
    ),
    "jaxobs.kalman_steps.tria": Example(lambda: dict(A=np.array([[1.0, 0.2, 0.3], [0.1, 0.5, -0.2]]))),
    "jaxobs.kalman_steps.psd_factor": Example(lambda: dict(M=P2)),
    "jaxobs.kalman_steps.square_root_predict": Example(
        lambda: dict(x=X2, P_sqrt=np.linalg.cholesky(P2), Phi=A2, Q_sqrt=np.linalg.cholesky(Q2), Gamma=B2, u_prev=U1),
        diff="Q_sqrt",
    ),  # fmt: skip
    "jaxobs.kalman_steps.square_root_update": Example(
        lambda: dict(x_prior=X2, P_sqrt=np.linalg.cholesky(P2), C=C2, R_sqrt=np.sqrt(R1), y=Y1),
        diff="P_sqrt",
        out=_sign_free,
    ),
}

PLANTS = {
    "jaxobs.plants.force_plant": Example(
        lambda: dict(
            stiffness=np.float64(2000.0), time_constant=np.float64(0.05), h=0.01, dead_time=np.float64(0.02), n_delay=2
        ),
        diff="stiffness",
    ),  # fmt: skip
}


def _decay(x, u, t):
    """A small time-varying ODE ``x' = -x + u + sin(t)`` for the integrators (``x`` and ``u`` with leading batch
    axes too)."""
    import jax.numpy as jnp

    return -x + jnp.expand_dims(u, -1) + jnp.sin(t)


PYTREE_STATE = {"lists": "x is a pytree of arrays: a list is a pytree (of scalars), not an array"}

CT = {
    "jaxobs.ct.euler_step": Example(
        lambda: dict(f=_decay, x=X2, u=np.float64(0.5), t=np.float64(0.1), dt=np.float64(0.01)),
        diff="x",
        batched=("x", "u"),
        skip=PYTREE_STATE,
    ),
    "jaxobs.ct.rk4_step": Example(
        lambda: dict(f=_decay, x=X2, u=np.float64(0.5), t=np.float64(0.1), dt=np.float64(0.01)),
        diff="x",
        batched=("x", "u"),
        skip=PYTREE_STATE,
    ),
    "jaxobs.ct.integrate": Example(
        lambda: dict(f=_decay, x=X2, u=np.float64(0.5), t=np.float64(0.1), h=np.float64(0.2), substeps=4),
        diff="x",
        batched=("x", "u"),
        skip=PYTREE_STATE,
    ),
    "jaxobs.ct.trajectory": Example(
        lambda: dict(f=_decay, x0=X2, u=np.array([0.5, -0.2, 0.1]), h=np.float64(0.2), substeps=2),
        diff="x0",
        skip={
            "lists": "x0 and u are pytrees: a list is a pytree (of scalars)",
            "batch": "x0 and u are pytrees of any shapes that f takes",
        },
    ),
}


def _ball():
    from jaxobs.adaptive import Ball

    return Ball(center=np.zeros(2), radius=np.float64(2.0))


THETA = np.array([0.3, -0.4])
OMEGA = np.array([[1.0, 0.5], [0.2, -0.3]])

ADAPTIVE = {
    "jaxobs.adaptive.regression_gradient_law": Example(
        lambda: dict(theta_hat=THETA, omega=OMEGA, z=np.array([0.2, 0.1]), adaptation_gain=np.float64(2.0))
    ),
    "jaxobs.adaptive.lyapunov_law": Example(
        lambda: dict(omega=OMEGA, x=np.array([0.2, 0.1]), adaptation_gain=np.float64(2.0))
    ),
    "jaxobs.adaptive.rls_update": Example(
        lambda: dict(theta_hat=THETA, P=P2, omega=OMEGA, z=np.array([0.2, 0.1]), forgetting=np.float64(0.98))
    ),
    "jaxobs.adaptive.rls_rate": Example(
        lambda: dict(theta_hat=THETA, P=P2, omega=OMEGA, z=np.array([0.2, 0.1]), forgetting=np.float64(0.1))
    ),
    "jaxobs.adaptive.project": Example(
        lambda: dict(
            tau=np.array([1.0, 0.5]),
            theta_hat=np.array([1.9, 0.3]),
            adaptation_gain=np.float64(1.0),
            region=_ball(),
            epsilon=np.float64(0.2),
        ),
        diff="tau",
    ),
    "jaxobs.adaptive.clip_step": Example(
        lambda: dict(
            theta_hat=THETA,
            rate=np.array([1.0, -2.0]),
            dt=np.float64(0.01),
            lower=np.array([-1.0, -1.0]),
            upper=np.array([1.0, 1.0]),
        )
    ),
    "jaxobs.adaptive.excitation": Example(
        lambda: dict(
            regressors=np.stack([np.sin(0.3 * np.arange(20)), np.cos(0.2 * np.arange(20))], axis=1), dt=np.float64(0.01)
        ),
        skip={"batch": "regressors is a window of any length: a batch axis is the (N, n_theta, q) form"},
    ),
}


QUAT_A = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
QUAT_B = np.array([0.8, -0.2, 0.1, 0.4]) / np.linalg.norm([0.8, -0.2, 0.1, 0.4])
_ROTATION_BATCH = "the manifold's maps decide the shapes (the quaternion maps broadcast over leading axes)"


def _rotation():
    """Unit quaternions as a Manifold (tangent: rotation vectors), from MuJoCo's quaternion maps."""
    import jax

    from jaxobs.mjx.manifold import quat_difference, quat_integrate
    from jaxobs.nonlinear import Manifold

    return Manifold(jax.tree_util.Partial(quat_difference), jax.tree_util.Partial(quat_integrate), 3, 4)


def _pendulum():
    import jax.numpy as jnp

    from jaxobs.nonlinear import nonlinear_model

    f = lambda x, u, t: jnp.array([x[0] + 0.05 * x[1], x[1] - 0.05 * jnp.sin(x[0]) + 0.05 * u[0]])
    return nonlinear_model(f, lambda x: jnp.sin(x[:1]), 0.01 * np.eye(2), [[0.1]], x0=[0.5, 0.0], n_inputs=1)


def _inputs(y, u_prev=None):
    from jaxobs.observers.base import EstimatorInputs

    return EstimatorInputs(y=y, u_prev=u_prev)


def _gaussian_step(fn, model, inputs):
    from jaxobs.nonlinear import gaussian_init
    from jaxobs.observers.ekf import taylor

    return fn(taylor, 1, model, gaussian_init(model), inputs)


NONLINEAR = {
    "jaxobs.nonlinear.nonlinear_model": Example(
        lambda: dict(f=lambda x, u, t: -x, h=lambda x: x[:1], Q=Q2, R=R1, x0=X2, dt=np.float64(0.1)), diff="Q"
    ),
    "jaxobs.nonlinear.gaussian_init": Example(lambda: dict(model=_pendulum()), tangent="scale"),
    "jaxobs.nonlinear.difference": Example(
        lambda: dict(manifold=_rotation(), a=QUAT_A, b=QUAT_B), diff="a", skip={"batch": _ROTATION_BATCH}
    ),  # fmt: skip
    "jaxobs.nonlinear.retract": Example(
        lambda: dict(manifold=_rotation(), b=QUAT_A, delta=np.array([0.1, 0.2, -0.1])),
        diff="delta",
        skip={"batch": _ROTATION_BATCH},
    ),  # fmt: skip
    "jaxobs.nonlinear.residual": Example(
        lambda: dict(manifold=_rotation(), y=QUAT_A, y_bar=QUAT_B), diff="y", skip={"batch": _ROTATION_BATCH}
    ),  # fmt: skip
    "jaxobs.nonlinear.gaussian_step": Example(
        lambda: dict(model=_pendulum(), inputs=_inputs(Y1, U1)), diff="inputs", call=_gaussian_step
    ),
    "jaxobs.nonlinear.model_inputs": Example(lambda: dict(model=_pendulum(), inputs=_inputs(Y1, U1)), diff="inputs"),
    "jaxobs.nonlinear.gaussian_factor": Example(lambda: dict(cov=P2)),
    "jaxobs.nonlinear.sample_gaussian": Example(
        lambda: dict(key=_key(), mean=X2, factor=np.linalg.cholesky(P2), num=5), diff="mean"
    ),
}


def _key(seed: int = 0):
    import jax

    return jax.random.key(seed)


ENTRIES = {**LTI, **MATRIX_EQUATIONS, **DESIGN, **KALMAN_STEPS, **PLANTS, **CT, **ADAPTIVE, **NONLINEAR}
ENTRIES = slow(
    ENTRIES,
    "a Riccati solve with its implicit derivative, compiled for eager, jit, vmap and grad (~0.7-3 s of CPU)",
    "jaxobs.design.dlqe",
    "jaxobs.design.lqe",
    "jaxobs.design.lqr",
    "jaxobs.matrix_equations.care",
)
ENTRIES = slow(
    ENTRIES,
    (
        "a matrix exponential of the padded delay model, or a factor update by a loop of rank-one steps, compiled"
        " for eager, jit, vmap and grad (~0.7-1.2 s of CPU)"
    ),
    "jaxobs.lti.c2d",
    "jaxobs.plants.force_plant",
    "jaxobs.kalman_steps.bierman_update",
)

EXEMPT = {
    "jaxobs.ct.discretize": "transformation: returns the sampled model of the user's f (its calls are integrate's)",
    "jaxobs.adaptive.check_law": "validator: checks an update law's fields and the start in its projection set",
    "jaxobs.nonlinear.check_discrete_model": "validator: refuses a model that is not a discrete NonlinearModel",
    "jaxobs.matrix_equations.require_converged": "validator: raises with the reason when a concrete DARE solution "
    "did not converge",
    "jaxobs.matrix_equations.require_care_converged": "validator: raises with the reason when a concrete CARE "
    "solution did not converge",
}
