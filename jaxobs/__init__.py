"""jaxobs: differentiable, batched state and disturbance observers in JAX.

``import jaxobs as jo`` gives the main entry points; the modules hold the rest: models and design
(:func:`ss`, :func:`c2d`, :func:`dare`, :func:`dlqr`, :func:`place`, ...), estimators and controllers in one
protocol (:mod:`jaxobs.observers`: :data:`kalman_filter`, :data:`active_observer`, :data:`hinf_filter`, the
combinator :func:`observer_controller`, :func:`run`), nonlinear filters (:mod:`jaxobs.nonlinear`), estimation over
a record (:mod:`jaxobs.smoothing`), learning from data (:mod:`jaxobs.learning`), closed loops and robustness
(:func:`simulate`, :func:`stability_margins`), and the jobs :func:`run_sweep` and :func:`tune`.

Names and submodules load on first use (``import jaxobs`` imports neither JAX nor the modules: each costs its
import when first named; ``jaxobs.mjx`` imports ``mujoco.mjx``). The library never enables float64 itself: do it
in your entry point (``jax.config.update("jax_enable_x64", True)``). A map of the API by task:
docs/theory/api-map.md.
"""

import functools
import importlib
import importlib.util
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what static tools see (IDEs, type checkers, the docs); at run time __getattr__ loads on first use
    from jaxobs._checks import checked
    from jaxobs.batching import safe_lapack, safe_vmap
    from jaxobs.closed_loop import ClosedLoopTrace, measurement_noise, rms, simulate
    from jaxobs.consistency import nees, nis, whiteness
    from jaxobs.design import acker, critically_damped_gain, dlqe, dlqr, lqe, lqr, place, reference_gain
    from jaxobs.learning import FitSettings, als, covariance_model, em, fit, sample
    from jaxobs.lti import StateSpace, c2d, ctrb, dcgain, is_spr, obsv, ss, tf2ss
    from jaxobs.matrix_equations import care, dare
    from jaxobs.nonlinear import Manifold, NonlinearModel, nonlinear_model
    from jaxobs.observers import (
        Controller,
        ControllerInputs,
        Estimator,
        EstimatorInputs,
        FeedbackParams,
        LinearObserver,
        observer_controller,
        run,
    )
    from jaxobs.observers.active import active_observer, active_observer_controller, feedback_gain, make_aob, make_ckf
    from jaxobs.observers.continuous import continuous_observer, make_continuous_observer
    from jaxobs.observers.ekf import extended_kalman_filter, make_ekf
    from jaxobs.observers.ensemble import ensemble_kalman_filter, ensemble_smoother, make_enkf
    from jaxobs.observers.gramian import gramian_estimator, make_gramian
    from jaxobs.observers.hgo import hgo_gains, hgo_observer, make_hgo
    from jaxobs.observers.hinf import hinf_filter, make_hinf
    from jaxobs.observers.imm import imm, make_imm
    from jaxobs.observers.inverse_dynamics import inverse_dynamics_observer, make_inverse_dynamics
    from jaxobs.observers.kalman import kalman_filter, make_kalman, square_root_form, square_root_kalman_filter
    from jaxobs.observers.linear import linear_observer
    from jaxobs.observers.modular import make_modular, modular_estimator
    from jaxobs.observers.particle import make_particle_filter, particle_filter, particle_smoother
    from jaxobs.observers.pe_monitor import make_pe_monitor, pe_monitor
    from jaxobs.observers.ukf import make_ukf, unscented_kalman_filter
    from jaxobs.plants import force_plant
    from jaxobs.scb import (
        SCB,
        infinite_zero_structure,
        invariant_zeros,
        is_left_invertible,
        is_minimum_phase,
        is_right_invertible,
    )
    from jaxobs.smoothing import Smoothed, log_likelihood, parallel_filter, rts_smoother, smooth
    from jaxobs.stability import closed_loop_matrix, loop_transfer, spectral_radius, stability_margins
    from jaxobs.sweep import load_results, run_sweep
    from jaxobs.tuning import TuneSettings, TuningProblem, make_tuner, random_search, tune

__all__ = [
    "__version__",
    # models and design
    "StateSpace",
    "ss",
    "c2d",
    "tf2ss",
    "ctrb",
    "obsv",
    "dcgain",
    "is_spr",
    "dare",
    "dlqr",
    "dlqe",
    "care",
    "lqr",
    "lqe",
    "acker",
    "place",
    "reference_gain",
    "critically_damped_gain",
    "force_plant",
    # estimators and controllers
    "Estimator",
    "Controller",
    "EstimatorInputs",
    "ControllerInputs",
    "LinearObserver",
    "FeedbackParams",
    "observer_controller",
    "run",
    "kalman_filter",
    "make_kalman",
    "square_root_kalman_filter",
    "square_root_form",
    "active_observer",
    "active_observer_controller",
    "make_aob",
    "make_ckf",
    "feedback_gain",
    "hinf_filter",
    "make_hinf",
    "inverse_dynamics_observer",
    "make_inverse_dynamics",
    "pe_monitor",
    "make_pe_monitor",
    "gramian_estimator",
    "make_gramian",
    "linear_observer",
    "NonlinearModel",
    "nonlinear_model",
    "Manifold",
    "extended_kalman_filter",
    "make_ekf",
    "unscented_kalman_filter",
    "make_ukf",
    "particle_filter",
    "make_particle_filter",
    "particle_smoother",
    "ensemble_kalman_filter",
    "make_enkf",
    "ensemble_smoother",
    "continuous_observer",
    "make_continuous_observer",
    "hgo_gains",
    "hgo_observer",
    "make_hgo",
    "modular_estimator",
    "make_modular",
    "imm",
    "make_imm",
    # estimation over a record
    "log_likelihood",
    "smooth",
    "rts_smoother",
    "parallel_filter",
    "Smoothed",
    # learning from data
    "sample",
    "fit",
    "FitSettings",
    "covariance_model",
    "em",
    "als",
    # consistency of a filter
    "nees",
    "nis",
    "whiteness",
    # closed loops and robustness
    "simulate",
    "ClosedLoopTrace",
    "measurement_noise",
    "rms",
    "stability_margins",
    "loop_transfer",
    "closed_loop_matrix",
    "spectral_radius",
    # jobs
    "run_sweep",
    "safe_vmap",
    "safe_lapack",
    "checked",
    "load_results",
    "tune",
    "make_tuner",
    "TuningProblem",
    "TuneSettings",
    "random_search",
    # structure (design time, NumPy/sympy; the decomposition itself is jaxobs.scb.scb)
    "SCB",
    "invariant_zeros",
    "infinite_zero_structure",
    "is_left_invertible",
    "is_right_invertible",
    "is_minimum_phase",
]


@functools.cache
def _module_of() -> dict[str, str]:
    """Exported name -> its module, read from the ``TYPE_CHECKING`` imports above (the one list of them)."""
    import ast

    tree = ast.parse(open(__file__, encoding="utf-8").read())
    block = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING")
    return {alias.name: node.module for node in block.body for alias in node.names}


def __getattr__(name: str):
    """An exported name, ``__version__`` or a submodule (``jaxobs.mjx``), imported on first use and kept."""
    if name in __all__ and name != "__version__":
        value = getattr(importlib.import_module(_module_of()[name]), name)
    elif name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            value = version("jaxobs")
        except PackageNotFoundError:  # running from a source tree that is not installed
            value = "0+unknown"
    elif not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
