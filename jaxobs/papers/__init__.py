"""Reproductions of the source documents: one module per paper, each returning data and drawing
figures. ``REPRODUCTIONS`` maps the names used by ``jaxobs reproduce`` to their entry points."""

from jaxobs.papers import (
    cortesao2006,
    cortesao_stochastic,
    grip2010_adaptive,
    grip2010_dc_motor,
    grip2010_sandwich,
    grip2010_saturated_outputs,
    grip2010_scb,
    grip2010_sideslip,
    liu_peng,
    steer_by_wire,
)

REPRODUCTIONS = {
    cortesao2006.NAME: cortesao2006.reproduce,
    cortesao_stochastic.NAME: cortesao_stochastic.reproduce,
    steer_by_wire.NAME: steer_by_wire.reproduce,
    liu_peng.NAME: liu_peng.reproduce,
    grip2010_scb.NAME: grip2010_scb.reproduce,
    grip2010_adaptive.NAME_EXAMPLE_1_1: grip2010_adaptive.reproduce_example_1_1,
    grip2010_adaptive.NAME_EXAMPLE_5_6: grip2010_adaptive.reproduce_example_5_6,
    grip2010_adaptive.NAME_DRILLING: grip2010_adaptive.reproduce_drilling,
    grip2010_dc_motor.NAME: grip2010_dc_motor.reproduce,
    grip2010_saturated_outputs.NAME: grip2010_saturated_outputs.reproduce,
    grip2010_sandwich.NAME: grip2010_sandwich.reproduce,
    grip2010_sideslip.NAME: grip2010_sideslip.reproduce,
}

__all__ = ["REPRODUCTIONS"]
