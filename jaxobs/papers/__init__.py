"""Reproductions of the source documents: one module per paper, each returning data and drawing
figures. ``REPRODUCTIONS`` maps the names used by ``jaxobs reproduce`` to their entry points."""

from jaxobs.papers.cortesao import example1, steer_by_wire, stochastic
from jaxobs.papers.grip2010 import adaptive, dc_motor, sandwich, saturated_outputs, scb, sideslip
from jaxobs.papers.liu_peng import vehicle_lateral

REPRODUCTIONS = {
    example1.NAME: example1.reproduce,
    stochastic.NAME: stochastic.reproduce,
    steer_by_wire.NAME: steer_by_wire.reproduce,
    vehicle_lateral.NAME: vehicle_lateral.reproduce,
    scb.NAME: scb.reproduce,
    adaptive.NAME_EXAMPLE_1_1: adaptive.reproduce_example_1_1,
    adaptive.NAME_EXAMPLE_5_6: adaptive.reproduce_example_5_6,
    adaptive.NAME_DRILLING: adaptive.reproduce_drilling,
    dc_motor.NAME: dc_motor.reproduce,
    saturated_outputs.NAME: saturated_outputs.reproduce,
    sandwich.NAME: sandwich.reproduce,
    sideslip.NAME: sideslip.reproduce,
}

__all__ = ["REPRODUCTIONS"]
