"""Observers in the (init, step) protocol: one module per family.

``kalman`` (classical Kalman filter), ``active`` (Kalman Active Observer AOB-N), ``inverse_dynamics``
(Liu & Peng's inverse-dynamics state and disturbance observers, Cases 1 and 2), ``hinf`` (discrete-time
suboptimal H-infinity filter).
"""

from jaxobs.observers import active, hinf, inverse_dynamics, kalman
from jaxobs.observers.base import Observer, run

__all__ = ["Observer", "run", "kalman", "active", "inverse_dynamics", "hinf"]
