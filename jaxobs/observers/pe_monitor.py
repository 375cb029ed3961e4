"""The persistency-of-excitation monitor as an estimator: the Gram matrix of the regressors over a sliding window,
its smallest eigenvalue, and the least-squares estimate of the window.

A regressor ``omega`` (n_theta,) is persistently exciting when ``int_t^{t+T} omega omega' dtau >= epsilon I`` for all
``t`` (Grip 2010 §1.3.1, Example 1.1 continued; the same condition on ``S`` in Prop. 5.4): parameter estimates converge
only then. The monitor evaluates it on the last ``N`` samples (``T = N dt``, rectangle rule,
:func:`jaxobs.adaptive.excitation`), so it can gate adaptation (freeze or pull back an update law when the excitation is
low) or report it. Its measurement is the regressor with the target of the regression ``z = omega' theta``: ``inputs.y =
[omega; z]`` (n_theta + 1,), and its estimate ``out.x`` is the least-squares ``theta`` of the window, held at its last
value while the window is not exciting. A sample with a non-finite entry is missing: it contributes nothing to the
window and is counted in ``state.missing``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs.adaptive import excitation
from jaxobs.observers.base import Estimator, EstimatorInputs

__all__ = ["PEMonitorParams", "PEMonitorState", "PEMonitorOutputs", "pe_monitor", "make_pe_monitor"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PEMonitorParams:
    """Parameters of the persistency-of-excitation monitor.

    Attributes:
      dt: () sample period.  threshold: () ``epsilon`` of the condition ``gram >= epsilon I``.
      window: static number ``N`` of samples in the window (``T = N dt``).
      n_regressors: static size ``n_theta`` of the regressor.
    """

    dt: jax.Array
    threshold: jax.Array
    window: int = dataclasses.field(metadata=dict(static=True))
    n_regressors: int = dataclasses.field(metadata=dict(static=True))


class PEMonitorState(NamedTuple):
    """State of :data:`pe_monitor` between samples (``N`` samples in the window, ``n_theta`` regressors).

    Attributes:
      regressors: (N, n_theta) the last N regressors (a ring buffer; zero rows before the window fills)
      targets: (N,) their targets
      count: () int32 samples seen (the next one goes to row count mod N)
      theta: (n_theta,) the last least-squares estimate of an exciting window (zero before)
      missing: () int32 samples skipped for non-finite entries
    """

    regressors: jax.Array
    targets: jax.Array
    count: jax.Array
    theta: jax.Array
    missing: jax.Array


class PEMonitorOutputs(NamedTuple):
    """Outputs of one sample of :data:`pe_monitor`.

    Attributes:
      x: (n_theta,) least-squares theta of the window (held while it is not exciting)
      innovation: (1,) z - omega' theta_previous (0 for a missing sample)
      gram: (n_theta, n_theta) dt sum of omega omega' over the window
      lambda_min: () its smallest eigenvalue
      excited: () bool: the window is full and lambda_min >= threshold
    """

    x: jax.Array
    innovation: jax.Array
    gram: jax.Array
    lambda_min: jax.Array
    excited: jax.Array


def make_pe_monitor(n_regressors, window, dt, threshold) -> PEMonitorParams:
    """Params of :data:`pe_monitor` for a (``n_regressors``,) regressor, a window of ``window`` samples of period
    ``dt`` and the excitation level ``threshold`` (``epsilon``), with the checks (``ValueError`` naming the argument).

    Example:
      >>> import numpy as np
      >>> from jaxobs.observers.base import EstimatorInputs, run
      >>> t = 0.01 * np.arange(700)
      >>> y = np.stack([np.sin(t), np.cos(t), 2 * np.sin(t) - np.cos(t)], axis=1)  # [omega; z], theta = (2, -1)
      >>> _, out = run(pe_monitor, make_pe_monitor(2, 629, 0.01, 1.0), EstimatorInputs(y=y))
      >>> bool(out.excited[-1]), np.round(out.x[-1], 6).tolist()
      (True, [2.0, -1.0])
    """
    n_theta = _checks.count("n_regressors", n_regressors, minimum=1)
    N = _checks.count("window", window, minimum=1)
    _checks.positive_scalar("dt", dt)
    _checks.positive_scalar("threshold", threshold)
    dtype = _checks.float_dtype(dt=dt, threshold=threshold)
    return PEMonitorParams(jnp.asarray(dt, dtype), jnp.asarray(threshold, dtype), N, n_theta)


def _init(params: PEMonitorParams) -> PEMonitorState:
    _checks.fields("params", params, "dt (), threshold ()")
    N, n_theta, dtype = params.window, params.n_regressors, params.dt.dtype
    zero = jnp.zeros((), jnp.int32)
    return PEMonitorState(jnp.zeros((N, n_theta), dtype), jnp.zeros(N, dtype), zero, jnp.zeros(n_theta, dtype), zero)


def _step(params: PEMonitorParams, state: PEMonitorState, inputs: EstimatorInputs):
    _checks.fields("params", params, "dt (), threshold ()")
    n_theta, dtype = params.n_regressors, params.dt.dtype
    what = "the regressor omega and the target z"
    y = _checks.vector("inputs.y", inputs.y, n_theta + 1, dtype, what=what, check_finite=False)
    seen = jnp.all(jnp.isfinite(y))
    y = jnp.where(seen, y, 0)
    omega, z = y[:n_theta], y[n_theta]
    row = state.count % params.window
    regressors = state.regressors.at[row].set(omega)
    targets = state.targets.at[row].set(z)
    gram, lowest = excitation(regressors, params.dt)
    excited = (state.count + 1 >= params.window) & (lowest >= params.threshold)
    moment = params.dt * regressors.T @ targets
    solved = jnp.linalg.solve(jnp.where(excited, gram, jnp.eye(n_theta, dtype=dtype)), moment)
    theta = jnp.where(excited, solved, state.theta)
    innovation = jnp.where(seen, z - omega @ state.theta, 0)[None]
    new_state = PEMonitorState(regressors, targets, state.count + 1, theta, state.missing + (~seen).astype(jnp.int32))
    return new_state, PEMonitorOutputs(theta, innovation, gram, lowest, excited)


pe_monitor = Estimator(_init, _step)
"""The persistency-of-excitation monitor; params: :class:`PEMonitorParams` (:func:`make_pe_monitor`); measurement
``inputs.y = [omega; z]`` (n_theta + 1,); outputs :class:`PEMonitorOutputs`."""
