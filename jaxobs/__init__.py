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

import importlib
import importlib.util

_EXPORTS = {  # module -> the names ``jaxobs`` exports from it, loaded on first use (PEP 562)
    # models and design
    "jaxobs.lti": ("StateSpace", "ss", "c2d", "tf2ss", "ctrb", "obsv", "dcgain", "is_spr"),
    "jaxobs.matrix_equations": ("dare", "care"),
    "jaxobs.design": ("dlqr", "dlqe", "lqr", "lqe", "acker", "place", "reference_gain", "critically_damped_gain"),
    "jaxobs.plants": ("force_plant",),
    # estimators and controllers
    "jaxobs.observers": ("Estimator", "Controller", "EstimatorInputs", "ControllerInputs", "LinearObserver",
                         "FeedbackParams", "observer_controller", "run"),
    "jaxobs.observers.kalman": ("kalman_filter", "make_kalman", "square_root_kalman_filter", "square_root_form"),
    "jaxobs.observers.active": ("active_observer", "active_observer_controller", "make_aob", "make_ckf",
                                "feedback_gain"),
    "jaxobs.observers.hinf": ("hinf_filter", "make_hinf"),
    "jaxobs.observers.inverse_dynamics": ("inverse_dynamics_observer", "make_inverse_dynamics"),
    "jaxobs.observers.pe_monitor": ("pe_monitor", "make_pe_monitor"),
    "jaxobs.observers.gramian": ("gramian_estimator", "make_gramian"),
    "jaxobs.observers.linear": ("linear_observer",),
    "jaxobs.nonlinear": ("NonlinearModel", "nonlinear_model"),
    "jaxobs.observers.ekf": ("extended_kalman_filter", "make_ekf"),
    "jaxobs.observers.ukf": ("unscented_kalman_filter", "make_ukf"),
    "jaxobs.observers.continuous": ("continuous_observer", "make_continuous_observer"),
    "jaxobs.observers.hgo": ("hgo_gains", "hgo_observer", "make_hgo"),
    "jaxobs.observers.modular": ("modular_estimator", "make_modular"),
    # estimation over a record
    "jaxobs.smoothing": ("log_likelihood", "smooth", "rts_smoother", "parallel_filter", "Smoothed"),
    # learning from data
    "jaxobs.learning": ("sample", "fit", "FitSettings", "covariance_model", "em"),
    # closed loops and robustness
    "jaxobs.closed_loop": ("simulate", "ClosedLoopTrace", "measurement_noise", "rms"),
    "jaxobs.stability": ("stability_margins", "loop_transfer", "closed_loop_matrix", "spectral_radius"),
    # jobs
    "jaxobs.sweep": ("run_sweep", "load_results"),
    "jaxobs.tuning": ("tune", "TuningProblem", "TuneSettings", "random_search"),
    # structure (design time, NumPy/sympy; the decomposition itself is jaxobs.scb.scb)
    "jaxobs.scb": ("SCB", "invariant_zeros", "infinite_zero_structure", "is_left_invertible", "is_right_invertible",
                   "is_minimum_phase"),
}  # fmt: skip
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = ["__version__", *_MODULE_OF]


def __getattr__(name: str):
    """An exported name, ``__version__`` or a submodule (``jaxobs.mjx``), imported on first use and kept."""
    if name in _MODULE_OF:
        value = getattr(importlib.import_module(_MODULE_OF[name]), name)
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
