"""jaxobs: differentiable, batched state and disturbance observers in JAX.

``import jaxobs as jo`` gives the main entry points; the modules hold the rest:

* models and design: :func:`ss`, :func:`c2d` (zero-order hold with dead time), :func:`dare`, :func:`dlqr`,
  :func:`dlqe`, :func:`acker`, :func:`place`, :func:`reference_gain`, :func:`critically_damped_gain`,
  :func:`force_plant`;
* estimators and controllers (one protocol, :mod:`jaxobs.observers`): :data:`kalman_filter`,
  :data:`active_observer` (the Kalman Active Observer), :data:`hinf_filter`, :data:`inverse_dynamics_observer`,
  :data:`linear_observer`, the combinator :func:`observer_controller`, and :func:`run`;
* estimation over a record (:mod:`jaxobs.smoothing`): :func:`log_likelihood`, :func:`smooth` (Rauch-Tung-Striebel,
  for the Kalman filter and the active observer), :func:`rts_smoother`, :func:`parallel_filter` (parallel in time),
  and the square-root Kalman filter :data:`square_root_kalman_filter` (:func:`square_root_form`);
* closed loops and robustness: :func:`simulate`, :func:`measurement_noise`, :func:`stability_margins`,
  :func:`closed_loop_matrix`, :func:`spectral_radius`;
* jobs: :func:`run_sweep` (Monte-Carlo sweeps), :func:`tune` (optax tuning).

MuJoCo MJX plants live in :mod:`jaxobs.mjx` (not imported here: it imports ``mujoco.mjx``). The library never
enables float64 itself: do it in your entry point (``jax.config.update("jax_enable_x64", True)``).
"""

from importlib.metadata import PackageNotFoundError, version

from jaxobs.closed_loop import ClosedLoopTrace, measurement_noise, rms, simulate
from jaxobs.design import acker, critically_damped_gain, dlqe, dlqr, place, reference_gain
from jaxobs.lti import StateSpace, c2d, ctrb, dcgain, obsv, ss, tf2ss
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
from jaxobs.observers.hinf import hinf_filter, make_hinf
from jaxobs.observers.inverse_dynamics import inverse_dynamics_observer, make_inverse_dynamics
from jaxobs.observers.kalman import kalman_filter, make_kalman, square_root_form, square_root_kalman_filter
from jaxobs.observers.linear import linear_observer
from jaxobs.plants import force_plant
from jaxobs.riccati import dare
from jaxobs.smoothing import Smoothed, log_likelihood, parallel_filter, rts_smoother, smooth
from jaxobs.stability import closed_loop_matrix, loop_transfer, spectral_radius, stability_margins
from jaxobs.sweep import load_results, run_sweep
from jaxobs.tuning import TuneSettings, TuningProblem, random_search, tune

try:
    __version__ = version("jaxobs")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"

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
    "dare",
    "dlqr",
    "dlqe",
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
    "linear_observer",
    # estimation over a record
    "log_likelihood",
    "smooth",
    "rts_smoother",
    "parallel_filter",
    "Smoothed",
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
    "load_results",
    "tune",
    "TuningProblem",
    "TuneSettings",
    "random_search",
]
