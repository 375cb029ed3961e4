"""Estimators and controllers in one protocol (:mod:`jaxobs.observers.base`), one module per family.

Families: ``kalman`` (Kalman filter), ``active`` (Kalman Active Observer AOB-N), ``hinf`` (discrete-time
a-posteriori H-infinity filter), ``inverse_dynamics`` (Liu & Peng's inverse-dynamics state and disturbance
observers), ``linear`` (fixed-gain linear observer), ``ekf`` (extended Kalman filter), ``ukf`` (unscented Kalman
filter), ``continuous`` (continuous-time observers run as sampled estimators), ``pe_monitor``
(persistency-of-excitation monitor: the windowed Gram matrix of the regressors), ``ct_linear`` (continuous-time
Luenberger, Kalman-Bucy and output-injection observers), ``modular`` (the modular parameter and perturbation
estimator of Grip 2010 ch. 5), ``hgo`` (the modified high-gain observer of Grip 2010, ch. 6, and its gains),
``gramian`` (the masked observability-Gramian reconstruction of Grip 2010, ch. 8).
``imm.imm`` combines Gaussian estimators into an interacting multiple model estimator.
``particle`` (bootstrap and auxiliary particle filters, backward-simulation smoother).
``ensemble`` (stochastic and transform ensemble Kalman filters, ensemble Kalman smoother).
``feedback.observer_controller`` turns any of them into
an observer-based controller.
"""

from jaxobs.observers import (
    active,
    continuous,
    ct_linear,
    ekf,
    ensemble,
    feedback,
    gramian,
    hgo,
    hinf,
    imm,
    inverse_dynamics,
    kalman,
    linear,
    modular,
    particle,
    pe_monitor,
    ukf,
)
from jaxobs.observers.base import (
    Controller,
    ControllerInputs,
    Estimator,
    EstimatorInputs,
    LinearObserver,
    run,
)
from jaxobs.observers.feedback import FeedbackParams, observer_controller

__all__ = [
    "Estimator",
    "Controller",
    "EstimatorInputs",
    "ControllerInputs",
    "LinearObserver",
    "FeedbackParams",
    "observer_controller",
    "run",
    "kalman",
    "active",
    "hinf",
    "inverse_dynamics",
    "linear",
    "pe_monitor",
    "ct_linear",
    "feedback",
    "ekf",
    "ukf",
    "continuous",
    "modular",
    "hgo",
    "gramian",
    "imm",
    "particle",
    "ensemble",
]
