"""Observers in the (init, step) protocol: one module per family."""

from jaxobs.observers import active, kalman
from jaxobs.observers.base import Observer, run

__all__ = ["Observer", "run", "kalman", "active"]
