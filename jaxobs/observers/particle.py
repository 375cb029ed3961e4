"""Particle filters in the estimator protocol: the bootstrap and the auxiliary particle filter and the
backward-simulation particle smoother.

The model is a discrete-time :class:`~jaxobs.nonlinear.NonlinearModel`, ``x_k = f(x_{k-1}, u_{k-1}, t_{k-1}) +
w_k``, ``y_k = h(x_k) + v_k`` with Gaussian noises (``Q`` may be singular), and ``x_0 ~ N(x0, P0)`` at the first
measurement. The state holds the particles, their normalised log-weights and a PRNG key; every step resamples
adaptively through :func:`jaxobs.resampling.resample` (its stop-gradient weights make the log-likelihood estimate
differentiate into the Fisher-identity score estimate, Ścibior & Wood 2021). The bootstrap filter (Gordon, Salmond
& Smith 1993) proposes from the transition; the auxiliary filter (Pitt & Shephard 1999) first reweights by a
Gaussian predictive density of ``y_k`` given ``x_{k-1}``. :func:`make_particle_filter`, :data:`particle_filter`,
:func:`particle_smoother` (Godsill, Doucet & West 2004). The equations: docs/guides/particle-and-ensemble.md.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxobs import _checks
from jaxobs._linalg import cholesky, solve_lower
from jaxobs.kalman_steps import innovation_log_likelihood, observed, observed_model
from jaxobs.nonlinear import NonlinearModel, check_discrete_model, gaussian_factor, model_inputs, sample_gaussian
from jaxobs.observers.base import Estimator, EstimatorInputs, run
from jaxobs.resampling import SCHEMES, effective_sample_size, multinomial, resample

__all__ = [
    "ParticleParams",
    "ParticleState",
    "ParticleOutputs",
    "make_particle_filter",
    "particle_filter",
    "ParticlePaths",
    "particle_smoother",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ParticleParams:
    """Parameters of :data:`particle_filter` (build them with :func:`make_particle_filter`).

    Attributes:
      model: the discrete-time :class:`~jaxobs.nonlinear.NonlinearModel`.
      key: the PRNG key the initial particles and every step's draws descend from.
      ess_threshold: () resample when the effective sample size is below ``ess_threshold * num_particles``
        (1: at every step; 0: never).
      Q_sqrt: (n, n) a factor of ``model.Q`` (``Q_sqrt Q_sqrt' = Q``; :func:`make_particle_filter` computes it
        once with :func:`jaxobs.nonlinear.gaussian_factor`), with which the process noise is drawn.
      num_particles: static number of particles ``N``.
      scheme: static resampling scheme, a name in :data:`jaxobs.resampling.SCHEMES`.
      auxiliary: static; the auxiliary particle filter instead of the bootstrap filter.
      output_particles: static; every step also outputs its particles, log-weights and ancestors (what
        :func:`particle_smoother` needs).
    """

    model: NonlinearModel
    key: jax.Array
    ess_threshold: jax.Array
    Q_sqrt: jax.Array
    num_particles: int = dataclasses.field(metadata=dict(static=True))
    scheme: str = dataclasses.field(default="systematic", metadata=dict(static=True))
    auxiliary: bool = dataclasses.field(default=False, metadata=dict(static=True))
    output_particles: bool = dataclasses.field(default=False, metadata=dict(static=True))


class ParticleState(NamedTuple):
    """State of :data:`particle_filter` between steps (``N`` particles of ``n`` states).

    Attributes:
      particles: (N, n) the particles after sample ``k - 1`` (draws from the prior before the first step).
      log_weights: (N,) their normalised log-weights (``logsumexp`` 0).
      key: the PRNG key of the next step.
      t: () the time of the particles.
      started: () bool: a measurement has been processed (the next step propagates).
      missing: () int32, measurement components skipped so far.
    """

    particles: jax.Array
    log_weights: jax.Array
    key: jax.Array
    t: jax.Array
    started: jax.Array
    missing: jax.Array


class ParticleOutputs(NamedTuple):
    """Outputs of one step of :data:`particle_filter`.

    Attributes:
      x: (n,) weighted mean of the particles, the estimate of ``E[x_k | y_0..y_k]``.
      P: (n, n) their weighted covariance.
      innovation: (p,) ``y_k`` minus the predicted measurement, the weighted mean of ``h`` over the propagated
        particles before the update (0 for missing components).
      log_likelihood: () the estimate of ``log p(y_k | y_0..y_{k-1})``; summed over a record, the log of an
        unbiased estimate of the likelihood ``p(y_0..y_{T-1})``.
      ess: () effective sample size of the updated weights.
      resampled: () bool, the particles were resampled at this step.
      particles: (N, n) the updated particles (with ``output_particles``, else None).
      log_weights: (N,) their normalised log-weights (with ``output_particles``, else None).
      ancestors: (N,) int32 index of each particle's parent at the previous step (with ``output_particles``).
    """

    x: jax.Array
    P: jax.Array
    innovation: jax.Array
    log_likelihood: jax.Array
    ess: jax.Array
    resampled: jax.Array
    particles: jax.Array | None = None
    log_weights: jax.Array | None = None
    ancestors: jax.Array | None = None


def make_particle_filter(model: NonlinearModel, num_particles: int, *, key, scheme: str = "systematic",
                         ess_threshold=0.5, auxiliary: bool = False,
                         output_particles: bool = False) -> ParticleParams:  # fmt: skip
    """The bootstrap (or auxiliary) particle filter of ``model``.

    Args:
      model: a discrete-time :class:`~jaxobs.nonlinear.NonlinearModel` (:func:`jaxobs.nonlinear.nonlinear_model`).
      num_particles: ``N`` (an integer >= 1).
      key: a PRNG key (``jax.random.key(seed)`` or ``jax.random.PRNGKey(seed)``); batch it with ``vmap`` for
        independent runs.
      scheme: ``"systematic"`` (default), ``"stratified"``, ``"residual"`` or ``"multinomial"``.
      ess_threshold: resample when the effective sample size drops below this fraction of ``N`` (in ``[0, 1]``;
        1 resamples at every step).
      auxiliary: the auxiliary particle filter (Pitt & Shephard 1999).
      output_particles: output the particles and weights at every step.

    Example:
      >>> import jax, jax.numpy as jnp
      >>> import jaxobs as jo
      >>> model = jo.nonlinear_model(lambda x, u, t: 0.9 * x, lambda x: x, [[0.1]], [[0.5]], x0=[0.0], P0=[[1.0]])
      >>> params = jo.make_particle_filter(model, 256, key=jax.random.key(0))
      >>> _, out = jo.run(jo.particle_filter, params, jo.EstimatorInputs(y=jnp.ones((20, 1))))
      >>> out.x.shape, out.log_likelihood.shape
      ((20, 1), (20,))
    """
    check_discrete_model(model, "the particle filter")
    num_particles = _checks.count("num_particles", num_particles, minimum=1, hint="the number of particles")
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {sorted(SCHEMES)}, got {scheme!r}")
    threshold = jnp.asarray(ess_threshold, model.x0.dtype)
    _checks.shape("ess_threshold", threshold, (), "a fraction of num_particles")
    if _checks.is_concrete(threshold) and not 0.0 <= float(threshold) <= 1.0:
        raise ValueError(f"ess_threshold must be in [0, 1], got {float(threshold)}")
    return ParticleParams(model, _checks.key("key", key), threshold, gaussian_factor(model.Q), num_particles, scheme,
                          _checks.boolean("auxiliary", auxiliary),
                          _checks.boolean("output_particles", output_particles))  # fmt: skip


def _log_observation(R, y, predicted):
    """``(log N(y; predicted_i, R) over the observed components for each row of predicted (N, p), mask)``."""
    mask, y_observed = observed(y, predicted.dtype)
    _, R = observed_model(jnp.zeros((y.shape[-1], 0), predicted.dtype), R, mask)  # R with unit placeholders
    innovations = (y_observed - predicted) * mask
    log_density = jax.vmap(innovation_log_likelihood, (0, None, None))(innovations, R, jnp.sum(mask))
    return log_density, mask


def _first_stage(model: NonlinearModel, y, means, log_weights):
    """The auxiliary filter's first-stage log-weights: ``log N(y; h(f(x_{k-1})), H Q H' + R)``, ``H`` the Jacobian
    of ``h`` at the weighted mean of ``f(x_{k-1})``: the predictive density ``p(y_k | x_{k-1})`` of a
    linear-Gaussian model exactly, an approximation of it otherwise. With ``R`` alone (Pitt & Shephard's point
    prediction) the first stage is too selective when the process noise is large next to ``R``, and the
    second-stage weights degenerate."""
    H = jax.jacfwd(model.h)(jnp.exp(log_weights) @ means)
    return _log_observation(H @ model.Q @ H.T + model.R, y, jax.vmap(model.h)(means))[0]


def _init(params: ParticleParams) -> ParticleState:
    model, num = params.model, params.num_particles
    key, draw = jax.random.split(params.key)
    particles = sample_gaussian(draw, model.x0, gaussian_factor(model.P0), num)
    log_weights = jnp.full((num,), -math.log(num), model.x0.dtype)
    return ParticleState(particles, log_weights, key, model.t0, jnp.zeros((), bool), jnp.zeros((), jnp.int32))


def _step(params: ParticleParams, state: ParticleState, inputs: EstimatorInputs):
    model, num = params.model, params.num_particles
    y, u = model_inputs(model, inputs)
    key, resample_key, noise_key = jax.random.split(state.key, 3)
    first = ~state.started  # the particles are draws of x_0: no propagation before the first update
    means = jax.vmap(model.f, (0, None, None))(state.particles, u, state.t)
    look_ahead = jnp.zeros((num,), means.dtype)
    if params.auxiliary:
        look_ahead = jnp.where(first, 0.0, _first_stage(model, y, means, state.log_weights))
    chosen = resample(resample_key, state.log_weights + look_ahead, scheme=params.scheme,
                      ess_threshold=params.ess_threshold)  # fmt: skip
    ancestors = jnp.where(first, jnp.arange(num, dtype=jnp.int32), chosen.ancestors)
    noise = sample_gaussian(noise_key, jnp.zeros_like(model.x0), params.Q_sqrt, num)
    particles = jnp.where(first, state.particles, means[ancestors] + noise)
    prior = jnp.where(first, state.log_weights, chosen.log_weights - look_ahead[ancestors])
    predicted = jax.vmap(model.h)(particles)
    log_g, mask = _log_observation(model.R, y, predicted)
    updated = prior + log_g
    increment = jax.nn.logsumexp(updated)  # the weights before the step sum to one
    log_weights = updated - increment
    weights = jnp.exp(log_weights)
    x = weights @ particles
    deviations = particles - x
    innovation = (observed(y, x.dtype)[1] - jax.nn.softmax(prior) @ predicted) * mask
    missing = state.missing + jnp.sum(1 - mask).astype(jnp.int32)
    t = jnp.where(first, state.t, state.t + model.dt)
    new_state = ParticleState(particles, log_weights, key, t, jnp.ones((), bool), missing)
    extra = (particles, log_weights, ancestors) if params.output_particles else ()
    outputs = ParticleOutputs(x, (weights[:, None] * deviations).T @ deviations, innovation, increment,
                              effective_sample_size(log_weights), chosen.resampled & ~first, *extra)  # fmt: skip
    return new_state, outputs


particle_filter = Estimator(_init, _step)
"""The bootstrap or auxiliary particle filter as an :class:`~jaxobs.observers.base.Estimator` over
:class:`ParticleParams`.

Each step (after the first, which only weights the prior draws): resample adaptively
(:func:`jaxobs.resampling.resample`; for the auxiliary filter on the weights times ``N(y_k; h(f(x_{k-1})),
H Q H' + R)``, exact for a linear-Gaussian model), propagate ``x = f(x_parent, u_{k-1}, t) + w``, ``w ~ N(0,
Q)``, and weight by the likelihood of ``y_k`` (divided by the first-stage one for the auxiliary filter); missing
components of ``y_k`` are skipped. The step's likelihood estimate is the sum of the weights before normalising. Inputs:
``EstimatorInputs(y, u_prev)``. State: :class:`ParticleState`. Outputs: :class:`ParticleOutputs`."""


class ParticlePaths(NamedTuple):
    """Result of :func:`particle_smoother`: trajectories drawn from the particle approximation of the smoothing
    distribution ``p(x_0..x_{T-1} | y_0..y_{T-1})``.

    Attributes:
      paths: (T, M, n) the ``M`` trajectories.
      x: (T, n) their mean, the estimate of ``E[x_k | y_0..y_{T-1}]``.
      P: (T, n, n) their covariance (divided by ``M``).
    """

    paths: jax.Array
    x: jax.Array
    P: jax.Array


def _backward_step(model: NonlinearModel, factor):
    """One step of backward simulation: each path's state at ``k`` drawn among the particles of ``k`` with the
    weights ``w_k^i N(x_{k+1}; f(x_k^i, u_k, t_k), Q)`` (Godsill, Doucet & West 2004, Algorithm 1)."""

    def step(carry, inputs):
        later, key = carry
        particles, log_weights, u, t = inputs
        means = jax.vmap(model.f, (0, None, None))(particles, u, t)
        centre = jnp.mean(means, axis=0)  # whitened differences from a common centre: no cancellation far away
        a = solve_lower(factor, (later - centre).T).T
        b = solve_lower(factor, (means - centre).T).T
        squared = jnp.sum(a**2, -1)[:, None] + jnp.sum(b**2, -1)[None, :] - 2 * a @ b.T
        key, draw = jax.random.split(key)
        chosen = jax.random.categorical(draw, log_weights[None, :] - 0.5 * squared, axis=-1)
        earlier = particles[chosen]
        return (earlier, key), earlier

    return step


def particle_smoother(params: ParticleParams, inputs: EstimatorInputs, *, key, num_paths: int):
    """Filter a record with :data:`particle_filter` and draw ``num_paths`` trajectories from the smoothing
    distribution by backward simulation (Godsill, Doucet & West 2004): the last state from the final weights,
    then each earlier one from the particles of its sample reweighted by the transition density to the state
    after it. ``O(num_paths N)`` work per sample; ``model.Q`` must be positive definite.

    Args:
      params: :class:`ParticleParams` (``output_particles`` is switched on here).
      inputs: ``EstimatorInputs`` over ``T`` samples (``u_prev`` of sample ``k + 1`` drives ``x_k -> x_{k+1}``).
      key: a PRNG key for the backward draws.  num_paths: ``M`` (an integer >= 1).

    Returns:
      ``(outputs, paths)``: the filter's :class:`ParticleOutputs` (with particles) and :class:`ParticlePaths`.

    Example:
      >>> import jax, jax.numpy as jnp
      >>> import jaxobs as jo
      >>> model = jo.nonlinear_model(lambda x, u, t: 0.9 * x, lambda x: x, [[0.1]], [[0.5]], x0=[0.0], P0=[[1.0]])
      >>> params = jo.make_particle_filter(model, 128, key=jax.random.key(0))
      >>> _, smoothed = jo.particle_smoother(params, jo.EstimatorInputs(y=jnp.ones((20, 1))),
      ...                                    key=jax.random.key(1), num_paths=64)
      >>> smoothed.paths.shape, smoothed.x.shape
      ((20, 64, 1), (20, 1))
    """
    num_paths = _checks.count("num_paths", num_paths, minimum=1, hint="the number of smoothed trajectories")
    key = _checks.key("key", key)
    model = params.model
    _checks.covariance("params.model.Q", model.Q, definite=True)
    outputs = run(particle_filter, dataclasses.replace(params, output_particles=True), inputs)[1]
    steps = outputs.particles.shape[0]
    u = jnp.zeros((steps, 0), model.x0.dtype) if inputs.u_prev is None else jnp.asarray(inputs.u_prev, model.x0.dtype)
    times = model.t0 + model.dt * jnp.arange(steps, dtype=model.x0.dtype)
    last_key, key = jax.random.split(key)
    last = outputs.particles[-1][multinomial(last_key, outputs.log_weights[-1], num_paths)]
    backward = (outputs.particles[:-1], outputs.log_weights[:-1], u[1:], times[:-1])
    _, earlier = jax.lax.scan(_backward_step(model, cholesky(model.Q)), (last, key), backward, reverse=True)
    paths = jnp.concatenate([earlier, last[None]])
    x = jnp.mean(paths, axis=1)
    deviations = paths - x[:, None]
    return outputs, ParticlePaths(paths, x, jnp.einsum("tmi,tmj->tij", deviations, deviations) / num_paths)
