"""Estimators and controllers in one protocol (:mod:`jaxobs.observers.base`), one module per family.

Families: ``kalman`` (Kalman filter), ``active`` (Kalman Active Observer AOB-N), ``hinf`` (discrete-time
a-posteriori H-infinity filter), ``inverse_dynamics`` (Liu & Peng's inverse-dynamics state and disturbance
observers), ``linear`` (fixed-gain linear observer), ``ekf`` (extended Kalman filter), ``ukf`` (unscented Kalman
filter), ``continuous`` (continuous-time observers run as sampled estimators). ``feedback.observer_controller``
turns any of them into an observer-based controller.
"""

from jaxobs.observers import active, continuous, ekf, feedback, hinf, inverse_dynamics, kalman, linear, ukf
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
    "feedback",
    "ekf",
    "ukf",
    "continuous",
]
