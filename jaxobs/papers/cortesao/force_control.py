"""Example 1 of Cortesão 2006 (§7): the settings and the design of the 1-DOF robot force-control plant shared by
Cortesão 2006, the stochastic AOB paper and the MRAC chapter (the plant itself: :func:`jaxobs.plants.force_plant`).

Per Cartesian DOF (the MRAC chapter eq. 56-61; Cortesão 2006 eq. 80) the position-controlled robot
``1 / (1 + Tp s) e^{-s Td}`` pushes on an environment of stiffness ``Ks``:
``G(s) = k1 / (s (s + p1)) e^{-s Td}`` with ``k1 = Ks / Tp``, ``p1 = 1 / Tp``; states
``[force (N), force derivative (N/s)]``, input velocity in mm/s, so ``Ks`` is in N/mm
(``Ks = 3`` reproduces the printed numbers; SI units do not).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from jaxobs.design import critically_damped_gain
from jaxobs.observers.active import ActiveObserverParams, feedback_gain
from jaxobs.observers.feedback import FeedbackParams
from jaxobs.plants import force_plant

__all__ = [
    "ForceControlSetup",
    "EXAMPLE1",
    "nominal_design",
    "with_feedback",
    "example1_disturbance",
    "chirp",
]


@dataclasses.dataclass(frozen=True)
class ForceControlSetup:
    """Nominal parameters (Cortesão 2006 §7.2, the MRAC chapter Table 1).

    Attributes:
      Ks: environment stiffness (N/mm).
      Tp: position response time constant (s).
      h: sample time (s).
      dead_time_samples: dead time in samples (Td = 5 h).
      tau_c_over_Tp: closed-loop time constant over ``Tp`` (tau_c = 10 Tp, the MRAC chapter eq. 68).
      R: force sensor noise variance (N^2; Cortesão 2006 §7.2, the MRAC chapter eq. 64).
      q_plant: process noise of each plant state, ``Q_xr(i, i)``.
      sigma2_active: variance of the active-state noise ``xi_p``.
      c: the factor of eq. 55.
      duration: length of a run (s).
    """

    Ks: float = 3.0
    Tp: float = 0.032
    h: float = 0.008
    dead_time_samples: int = 5
    tau_c_over_Tp: float = 10.0
    R: float = 2.1e-2
    q_plant: float = 1e-12
    sigma2_active: float = 1e-3
    c: float = 1.0 / 500.0
    duration: float = 20.0

    @property
    def num_steps(self) -> int:
        """Samples in ``duration``."""
        return int(round(self.duration / self.h))


EXAMPLE1 = ForceControlSetup()


def nominal_design(setup: ForceControlSetup = EXAMPLE1):
    """The nominal delay-augmented plant and its ``L_r`` (tau_c = 10 Tp, Cortesão 2006 eq. 83)."""
    plant = force_plant(setup.Ks, setup.Tp, setup.h, setup.dead_time_samples * setup.h)
    return plant, critically_damped_gain(plant, setup.tau_c_over_Tp * setup.Tp)


def with_feedback(aob: ActiveObserverParams, L_r) -> FeedbackParams:
    """The AOB (or CKF) ``aob`` with the state feedback ``u = r - L_r x_hat_r - p_hat`` (eq. 49-50), the params of
    :data:`jaxobs.observers.active.active_observer_controller`."""
    return FeedbackParams(aob, feedback_gain(aob, L_r))


def chirp(t, f0: float, f1: float, t1: float):
    """Linear chirp ``sin(2 pi (f0 t + (f1 - f0) t^2 / (2 t1)))``: frequency f0 at 0, f1 at t1."""
    return jnp.sin(2.0 * jnp.pi * (f0 * t + (f1 - f0) * t**2 / (2.0 * t1)))


def example1_disturbance(t):
    """Cortesão 2006 eq. 81-82: ``D = u^3 + u^2 - u``, ``u = 2 chirp(0.01 Hz -> 0.1 Hz, 20 s) - 0.5 step(t - 8)``,
    added to the plant input (mm/s)."""
    u = 2.0 * chirp(t, 0.01, 0.1, 20.0) - 0.5 * (t >= 8.0)
    return u**3 + u**2 - u


def reference_gain(L_r) -> float:
    """Reference scaling for unit DC gain from desired force to force: the integrating plant makes
    the closed-loop DC gain ``1 / L_1``, so ``r_k = L_1 F_d`` (Cortesão 2006: "the system input L_1 r_k")."""
    return float(np.asarray(L_r)[0, 0])
