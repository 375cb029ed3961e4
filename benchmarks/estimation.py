"""Estimation from data against dynamax and cuthbert: filter, filter + smoother, log-likelihood gradient, EKF, UKF.

What is measured (float64, the default JAX device), for every ``B`` (sequences), ``n`` (states) and ``T``
(samples) of the grid and every workload:

* ``filter``: the Kalman filter over ``B`` independent random stable models (each its own ``Phi, C, Q, R``;
  ``p = 2`` outputs, no inputs) and their simulated records: ``jaxobs.run(kalman_filter, ...)`` (with the
  per-step covariances, as the peers return them), dynamax ``lgssm_filter``, cuthbert's square-root
  ``gaussian.kalman`` filter (``cuthbert.filter``);
* ``smooth``: filter + Rauch-Tung-Striebel smoother: ``jaxobs.smooth``, dynamax ``lgssm_smoother``, cuthbert
  ``filter`` + ``smoother``;
* ``grad``: the gradient of the summed log-likelihood with respect to ``(Phi, C, Q, R)``: ``jax.grad`` of
  ``jaxobs.log_likelihood``, of dynamax's ``marginal_loglik``, of cuthbert's final ``log_normalizing_constant``;
* ``ekf``: one nonlinear model (``f(x) = Phi x + 0.1 sin(x)``, ``h(x) = C x + 0.5 sin(C x)``) and ``B``
  simulated records: ``make_ekf``, dynamax ``extended_kalman_filter``, cuthbert's moment-linearised filter
  (``gaussian.moments``, linearised at the filtered / predicted mean: the EKF);
* ``ukf``: the same model: ``make_ukf``, dynamax ``unscented_kalman_filter``, both with dynamax's default
  ``(alpha, beta, kappa) = (sqrt 3, 2, 1)``. cuthbert 0.1 has no sigma-point filter (only quadrature rules in
  cuthbertlib): listed as skipped.

jaxobs runs twice: with the standard covariance update ``P1 - K S K'`` (``joseph=False``), the update dynamax
computes, which is the ``jaxobs`` entry the ratios and targets refer to, and with its default Joseph form
(``jaxobs_joseph``, positive semidefinite by construction), reported as the cost ``Joseph / standard``.

``floor`` (filter, smoother, gradient, EKF): only the operations every Kalman filter (RTS smoother, likelihood
gradient, EKF) runs, by the fastest implementation measured here: the covariance prediction products and, for the
smoother, the gain's factor and solves and the smoothed covariance's products, with their outputs; for the
gradient, the prediction and its reverse-mode adjoint (:func:`floor_linear`); for the EKF its Jacobians,
prediction and standard-form update without missing data or symmetrisation (:func:`floor_nonlinear`).
``peer / floor`` therefore bounds the ratio to that peer any implementation on these kernels can reach.

Every entry is ``jit(vmap(...))`` over the ``B`` sequences. Same prior on every side: cuthbert takes the prior of
``x_{-1}`` (mean 0, covariance I) and predicts before its first update; jaxobs and dynamax take the prior of
``x_0`` (no prediction first), computed inside the timed function as that one (EKF) prediction, so the three
filters, likelihoods and gradients are the same numbers. Agreement (max relative difference to jaxobs of the
filtered means, smoothed means, gradients) is computed on the benchmark data and must be below ``AGREE_RTOL``
(dynamax adds 1e-9 I to the matrices it inverts, so about 1e-9 is expected from it).

Timing (``benchmarks/_timing.py``): each function is compiled first (every entry once, then, after clearing
JAX's caches, again: that compile time is reported, so the entry compiled first does not pay the process's
one-time costs), then ``--rounds`` interleaved rounds; times are the median [min, max] over the rounds and each ratio
``peer time / jaxobs time`` is taken round by round. Targets on every batched cell (``B > 1``): at least 1.5x
dynamax and 10x cuthbert, jaxobs compile time no worse than dynamax's.

The whole grid (B in {1, 64, 1024}, n in {2, 10, 32}, T in {100, 10^4}) is heavy on a small CPU: a cell whose work
``B T n^3`` times the workload's weight (``WEIGHT``) exceeds ``--budget`` is skipped and listed as skipped (the
default, 3e7, runs 45 of the 90 cells, all five workloads at (B, n, T) = (1, any, 100), (64, 2 or 10, 100),
(1024, 2, 100), (1, 2 or 10, 10^4), (64, 2, 10^4)).

Run (``make bench`` does it with ``--out out/bench``)::

    python benchmarks/estimation.py --out DIR [--batches 1 64 1024] [--states 2 10 32] [--lengths 100 10000]
        [--workloads filter smooth grad ekf ukf] [--budget 3e7] [--rounds 5] [--idle-timeout 120]

Each cell runs in a child process watched by the parent (``_timing.run_watched``): XLA's CPU runtime can wedge
with every thread idle and never return (cuthbert's gradient over 1024 sequences of 10 states does, every time
here), so a peer that neither reports progress nor uses CPU time for ``--idle-timeout`` seconds is killed, listed
as ``hung``, and the cell measured again without it.

Writes ``DIR/estimation.json`` and prints the table.
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import itertools  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _models import random_models  # noqa: E402
from _timing import (  # noqa: E402
    Hung,
    Skipped,
    format_range,
    optional_import,
    paired_ratio,
    run_watched,
    time_interleaved,
)

import jaxobs as jo  # noqa: E402
from jaxobs._linalg import cholesky, solve_lower, solve_spd  # noqa: E402
from jaxobs.kalman_steps import predict_covariance  # noqa: E402
from jaxobs.observers.kalman import KalmanParams  # noqa: E402

dynamax_lgssm, DYNAMAX_MISSING = optional_import("dynamax.linear_gaussian_ssm")
dynamax_nlgssm, _ = optional_import("dynamax.nonlinear_gaussian_ssm")
cuthbert, CUTHBERT_MISSING = optional_import("cuthbert")
cuthbert_moments, _ = optional_import("cuthbert.gaussian.moments")

WORKLOADS = ("filter", "smooth", "grad", "ekf", "ukf")
WEIGHT = {"filter": 1, "smooth": 2, "grad": 3, "ekf": 1, "ukf": 3}  # rough cost per B T n^3 (for --budget)
PEERS = ("dynamax", "cuthbert")
REQUIRED = ("jaxobs", "jaxobs_joseph")
TARGETS = {"dynamax": 1.5, "cuthbert": 10.0}  # min peer time / jaxobs time on batched cells
AGREE_RTOL = 1e-6
N_OUTPUTS = 2
UKF = dict(alpha=float(np.sqrt(3.0)), beta=2.0, kappa=1.0)  # dynamax's default UKFHyperParams


# ---------------------------------------------------------------------------------------------
# Models and data


def linear_problem(B: int, n: int, T: int, seed: int = 0):
    """B random stable models (stacked ``Phi, C, Q, R``) and a (B, T, p) record simulated from each,
    started from ``x_{-1} ~ N(0, I)``."""
    rng = np.random.default_rng(seed)
    Phi, C, Q, R = (jnp.asarray(M) for M in random_models(rng, B, n, N_OUTPUTS))
    key = jax.random.PRNGKey(seed)

    def simulate(Phi, C, Q, R, key):
        k0, kw, kv = jax.random.split(key, 3)
        w = jax.random.normal(kw, (T, n)) @ jnp.linalg.cholesky(Q).T
        v = jax.random.normal(kv, (T, N_OUTPUTS)) @ jnp.linalg.cholesky(R).T
        step = lambda x, wv: (Phi @ x + wv[0], C @ (Phi @ x + wv[0]) + wv[1])
        return jax.lax.scan(step, jax.random.normal(k0, (n,)), (w, v))[1]

    Y = jax.jit(jax.vmap(simulate))(Phi, C, Q, R, jax.random.split(key, B))
    return (Phi, C, Q, R), Y


def nonlinear_functions(Phi, C):
    f = lambda x: Phi @ x + 0.1 * jnp.sin(x)
    h = lambda x: C @ x + 0.5 * jnp.sin(C @ x)
    return f, h


def nonlinear_problem(B: int, n: int, T: int, seed: int = 0):
    """One random nonlinear model ``(Phi, C, Q, R)`` (spectral radius of Phi 0.85, so ``f`` is a contraction)
    and (B, T, p) records simulated from it, started from ``x_{-1} ~ N(0, I)``."""
    rng = np.random.default_rng(seed)
    Phi, C, Q, R = (jnp.asarray(M[0]) for M in random_models(rng, 1, n, N_OUTPUTS, spectral_radius=0.85))
    f, h = nonlinear_functions(Phi, C)

    def simulate(key):
        k0, kw, kv = jax.random.split(key, 3)
        w = jax.random.normal(kw, (T, n)) @ jnp.linalg.cholesky(Q).T
        v = jax.random.normal(kv, (T, N_OUTPUTS)) @ jnp.linalg.cholesky(R).T
        step = lambda x, wv: (f(x) + wv[0], h(f(x) + wv[0]) + wv[1])
        return jax.lax.scan(step, jax.random.normal(k0, (n,)), (w, v))[1]

    Y = jax.jit(jax.vmap(simulate))(jax.random.split(jax.random.PRNGKey(seed), B))
    return (Phi, C, Q, R), Y


def prior_of_x0(Phi, Q, f=None):
    """Mean and covariance of ``x_0``: one (EKF) prediction from ``x_{-1} ~ N(0, I)`` (cuthbert's prior)."""
    n = Phi.shape[-1]
    if f is None:
        return jnp.zeros(n), Phi @ Phi.T + Q
    F = jax.jacfwd(f)(jnp.zeros(n))
    return f(jnp.zeros(n)), F @ F.T + Q


def symmetric(Phi, C, Q, R):
    """``(Phi, C, sym Q, sym R)``: the likelihood as a function of the symmetric part of ``Q`` and ``R``, so that
    its gradient is the same symmetric matrix whichever triangle a library reads (cuthbert's Cholesky factor
    reads one, dynamax's solves both)."""
    sym = lambda M: 0.5 * (M + M.T)
    return Phi, C, sym(Q), sym(R)


# ---------------------------------------------------------------------------------------------
# The entries: each ``prepare`` returns ``(fn, args)``; ``fn`` is vmapped over the B sequences.


def jaxobs_linear(workload: str, model, Y, joseph: bool = False):
    def params(Phi, C, Q, R, output_covariance=False):
        x0, P0 = prior_of_x0(Phi, Q)
        return KalmanParams(Phi=Phi, Gamma=jnp.zeros((Phi.shape[0], 0)), C=C, Q=Q, R=R, x0=x0, P0=P0,
                            output_covariance=output_covariance, joseph=joseph)  # fmt: skip

    def one(Phi, C, Q, R, y):
        inputs = jo.EstimatorInputs(y=y)
        if workload == "filter":
            out = jo.run(jo.kalman_filter, params(Phi, C, Q, R, True), inputs)[1]
            return out.x, out.P, jnp.sum(out.log_likelihood)
        if workload == "smooth":
            smoothed = jo.smooth(jo.kalman_filter, params(Phi, C, Q, R), inputs)[1]
            return smoothed.x, smoothed.P
        ll = lambda *M: jo.log_likelihood(jo.kalman_filter, params(*symmetric(*M)), inputs)
        return jax.grad(ll, argnums=(0, 1, 2, 3))(Phi, C, Q, R)

    return jax.vmap(one), (*model, Y)


def dynamax_linear(workload: str, model, Y):
    if dynamax_lgssm is None:
        raise Skipped(DYNAMAX_MISSING)
    lg = dynamax_lgssm

    def params(Phi, C, Q, R):
        n, p = Phi.shape[0], C.shape[0]
        x0, P0 = prior_of_x0(Phi, Q)
        return lg.ParamsLGSSM(
            initial=lg.ParamsLGSSMInitial(mean=x0, cov=P0),
            dynamics=lg.ParamsLGSSMDynamics(weights=Phi, bias=jnp.zeros(n), input_weights=jnp.zeros((n, 0)), cov=Q),
            emissions=lg.ParamsLGSSMEmissions(weights=C, bias=jnp.zeros(p), input_weights=jnp.zeros((p, 0)), cov=R),
        )

    def one(Phi, C, Q, R, y):
        if workload == "filter":
            post = lg.lgssm_filter(params(Phi, C, Q, R), y)
            return post.filtered_means, post.filtered_covariances, post.marginal_loglik
        if workload == "smooth":
            post = lg.lgssm_smoother(params(Phi, C, Q, R), y)
            return post.smoothed_means, post.smoothed_covariances
        ll = lambda *M: lg.lgssm_filter(params(*symmetric(*M)), y).marginal_loglik
        return jax.grad(ll, argnums=(0, 1, 2, 3))(Phi, C, Q, R)

    return jax.vmap(one), (*model, Y)


def cuthbert_linear(workload: str, model, Y):
    if cuthbert is None:
        raise Skipped(CUTHBERT_MISSING)
    kalman = cuthbert.gaussian.kalman

    def filtered(Phi, C, Q, R, y):
        n, p = Phi.shape[0], C.shape[0]
        chol_Q, chol_R = jnp.linalg.cholesky(Q), jnp.linalg.cholesky(R)
        dynamics = lambda _: (Phi, jnp.zeros(n), chol_Q)
        filt = kalman.build_filter(m0=jnp.zeros(n), chol_P0=jnp.eye(n), get_dynamics_params=dynamics,
                                   get_observation_params=lambda y_k: (C, jnp.zeros(p), chol_R, y_k))  # fmt: skip
        return cuthbert.filter(filt, y, filt.init_prepare()), dynamics

    def one(Phi, C, Q, R, y):
        if workload == "filter":
            states = filtered(Phi, C, Q, R, y)[0]
            return states.mean[1:], states.chol_cov[1:], states.log_normalizing_constant[-1]
        if workload == "smooth":
            states, dynamics = filtered(Phi, C, Q, R, y)
            smoothed = cuthbert.smoother(kalman.build_smoother(dynamics), states, y)
            return smoothed.mean[1:], smoothed.chol_cov[1:]
        ll = lambda *M: filtered(*symmetric(*M), y)[0].log_normalizing_constant[-1]
        return jax.grad(ll, argnums=(0, 1, 2, 3))(Phi, C, Q, R)

    return jax.vmap(one), (*model, Y)


def jaxobs_nonlinear(workload: str, model, Y, joseph: bool = False):
    Phi, C, Q, R = model
    f, h = nonlinear_functions(Phi, C)
    x0, P0 = prior_of_x0(Phi, Q, f)
    nl = jo.nonlinear_model(lambda x, u, t: f(x), h, Q, R, x0=x0, P0=P0)
    params = jo.make_ekf(nl, joseph=joseph) if workload == "ekf" else jo.make_ukf(nl, **UKF, joseph=joseph)
    estimator = jo.extended_kalman_filter if workload == "ekf" else jo.unscented_kalman_filter

    def one(y):
        out = jo.run(estimator, params, jo.EstimatorInputs(y=y))[1]
        return out.x, out.P

    return jax.vmap(one), (Y,)


def dynamax_nonlinear(workload: str, model, Y):
    if dynamax_nlgssm is None:
        raise Skipped(DYNAMAX_MISSING)
    nlg = dynamax_nlgssm
    Phi, C, Q, R = model
    f, h = nonlinear_functions(Phi, C)
    x0, P0 = prior_of_x0(Phi, Q, f)
    params = nlg.ParamsNLGSSM(x0, P0, f, Q, h, R)

    def one(y):
        if workload == "ekf":
            post = nlg.extended_kalman_filter(params, y)
        else:
            post = nlg.unscented_kalman_filter(params, y, nlg.UKFHyperParams(**UKF))
        return post.filtered_means, post.filtered_covariances

    return jax.vmap(one), (Y,)


def cuthbert_nonlinear(workload: str, model, Y):
    if cuthbert is None:
        raise Skipped(CUTHBERT_MISSING)
    if workload == "ukf":
        raise Skipped("cuthbert 0.1 has no sigma-point (unscented) filter")
    Phi, C, Q, R = model
    f, h = nonlinear_functions(Phi, C)
    n = Phi.shape[0]
    chol_Q, chol_R = jnp.linalg.cholesky(Q), jnp.linalg.cholesky(R)
    filt = cuthbert_moments.build_filter(
        m0=jnp.zeros(n), chol_P0=jnp.eye(n),
        get_dynamics_params=lambda state, _: (lambda x: (f(x), chol_Q), state.mean),
        get_observation_params=lambda state, y_k: (lambda x: (h(x), chol_R), state.mean, y_k),
    )  # fmt: skip

    def one(y):
        states = cuthbert.filter(filt, y, filt.init_prepare())
        return states.mean[1:], states.chol_cov[1:]

    return jax.vmap(one), (Y,)


def floor_linear(workload: str, model, Y):
    """The kernels no Kalman filter (RTS smoother) can skip, and nothing else, each by the fastest implementation
    measured here (XLA's batched product with row-major operands, as ``jaxobs.kalman_steps.predict_covariance``;
    ``jaxobs._linalg.solve_spd``: the Cholesky factor and solves unrolled up to 8 states, LAPACK above): per
    sample the prediction ``Phi P Phi' + Q`` (two n x n products) written out, and for the smoother, backwards,
    the gain ``P_prior^{-1} Phi P`` and ``E D E'`` (two products) written out; for the gradient, the prediction
    forwards and its adjoint backwards, ``dPhi += 2 G Phi P``, ``dQ += G`` and ``Phi' G Phi`` (three products, by a
    hand-scheduled reverse pass whose operands are all row-major). No measurement update: with p = 2 outputs its
    products are O(n^2 p) against O(n^3). ``dynamax / floor`` bounds the ratio any implementation on these kernels
    reaches against dynamax."""

    def one(Phi, C, Q, R, y):
        if workload == "grad":
            return gradient(Phi, Q, y.shape[0])
        predict = lambda P, _: (predict_covariance(P, Phi, Q),) * 2
        _, P_prior = jax.lax.scan(predict, Q, None, length=y.shape[0])
        if workload == "filter":
            return P_prior

        def backward(P_later, P_prior_k):
            E_t = solve_spd(P_prior_k, Phi @ P_later)
            E = jax.lax.optimization_barrier(E_t.T)  # row-major, as jaxobs' smoother
            return (P_later + (E @ (P_later - P_prior_k)) @ E_t,) * 2

        return jax.lax.scan(backward, P_prior[-1], P_prior, reverse=True)[1]

    def gradient(Phi, Q, T):
        # the gradient of sum_k trace(P_prior_k), P_prior_k = Phi P_prior_{k-1} Phi' + Q from P_prior_{-1} = Q, in
        # reverse mode: forward, Phi P (kept) and its product with Phi'; backward, the cotangent G of P_prior_k
        # gives dPhi += 2 G (Phi P), dQ += G and, plus the identity (the trace's own cotangent, standing for the
        # likelihood's), Phi' G Phi to the step before (G symmetric)
        Phi_t = jax.lax.optimization_barrier(Phi.T)
        forward = lambda P, _: ((Phi_P := Phi @ P) @ Phi_t + Q, Phi_P)
        _, Phi_P = jax.lax.scan(forward, Q, None, length=T)
        unit = jnp.eye(Phi.shape[-1], dtype=Phi.dtype)

        def backward(carry, Phi_P_k):
            G, dPhi, dQ = carry
            return (Phi_t @ G @ Phi + unit, dPhi + 2.0 * G @ Phi_P_k, dQ + G), None

        zero = jnp.zeros_like(Phi)
        G, dPhi, dQ = jax.lax.scan(backward, (unit, zero, zero), Phi_P, reverse=True)[0]
        return dPhi, dQ + G - unit  # G - unit: the cotangent of the initial Q

    return jax.vmap(one), (*model, Y)


def floor_nonlinear(workload: str, model, Y):
    """EKF: the operations no extended Kalman filter can skip, and nothing else (no missing data, no
    symmetrisation, no counters): per sample the two Jacobians by ``jax.jacfwd``, the prediction ``f(x)``,
    ``F P F' + Q``, the standard-form update through one Cholesky factor of ``S`` (``jaxobs._linalg``) and the
    outputs; ``cuthbert / floor`` bounds the ratio any such EKF reaches against cuthbert."""
    if workload != "ekf":
        raise Skipped("no floor for the UKF")
    Phi, C, Q, R = model
    f, h = nonlinear_functions(Phi, C)
    x0, P0 = prior_of_x0(Phi, Q, f)

    def one(y):
        def step(carry, y_k):
            x, P, first = carry
            F = jax.lax.optimization_barrier(jax.jacfwd(f)(x))  # row-major, as jaxobs' EKF
            x_prior = jnp.where(first, x, f(x))
            P_prior = jnp.where(first, P, predict_covariance(P, F, Q))
            H = jax.lax.optimization_barrier(jax.jacfwd(h)(x_prior))
            HP = H @ P_prior
            S_chol = cholesky(HP @ H.T + R)
            W = solve_lower(S_chol, HP)
            K = solve_lower(S_chol, W, transpose=True).T
            x, P = x_prior + K @ (y_k - h(x_prior)), P_prior - W.T @ W
            return (x, P, False), (x, P)

        return jax.lax.scan(step, (x0, P0, True), y)[1]

    return jax.vmap(one), (Y,)


ENTRIES = {
    "jaxobs": (jaxobs_linear, jaxobs_nonlinear),
    "jaxobs_joseph": (partial(jaxobs_linear, joseph=True), partial(jaxobs_nonlinear, joseph=True)),
    "dynamax": (dynamax_linear, dynamax_nonlinear),
    "cuthbert": (cuthbert_linear, cuthbert_nonlinear),
    "floor": (floor_linear, floor_nonlinear),
}


def primary(workload: str, result) -> np.ndarray:
    """The compared output, flattened: filtered / smoothed means, or the four gradients."""
    parts = result if workload == "grad" else result[:1]
    return np.concatenate([np.ravel(np.asarray(a)) for a in parts])


# ---------------------------------------------------------------------------------------------


def cell(workload: str, B: int, n: int, T: int, rounds: int, hung=None, progress=None) -> dict:
    """Time one workload on one (B, n, T): every entry, paired ratios, compile times, agreement. ``hung``:
    ``{entry: reason}`` of peers left out (found hung by :func:`measure`)."""
    hung = hung or {}
    linear = workload in ("filter", "smooth", "grad")
    model, Y = (linear_problem if linear else nonlinear_problem)(B, n, T)
    entries = {name: (lambda make=make[0 if linear else 1]: make(workload, model, Y), True, 1.0)
               for name, make in ENTRIES.items() if name not in hung}  # fmt: skip
    timings, problems = time_interleaved(entries, rounds, required=REQUIRED, progress=progress)
    problems.update({name: {"status": "hung", "reason": reason} for name, reason in hung.items()})
    ours, joseph = timings["jaxobs"], timings["jaxobs_joseph"]
    record = {"jaxobs": ours.record(B * T, "steps/s"), "peers": {},
              "joseph": {**joseph.record(B * T, "steps/s"), "cost": paired_ratio(ours, joseph)}}  # fmt: skip
    reference = primary(workload, ours.result)
    scale = np.max(np.abs(reference))
    for peer in PEERS:
        if peer in problems:
            record["peers"][peer] = problems[peer]
            continue
        theirs = timings[peer]
        difference = float(np.max(np.abs(primary(workload, theirs.result) - reference)) / scale)
        record["peers"][peer] = {
            **theirs.record(B * T, "steps/s"),
            "ratio": paired_ratio(ours, theirs),
            "max_relative_difference": difference,
            "agrees": difference < AGREE_RTOL,
        }
    if "floor" in timings:
        floor = timings["floor"]
        record["floor"] = {**floor.record(B * T, "steps/s"), "jaxobs_over_floor": paired_ratio(floor, ours)}
        for peer in PEERS:
            if peer in timings:
                record["floor"][f"{peer}_over_floor"] = paired_ratio(floor, timings[peer])
    return record


def measure(workload: str, B: int, n: int, T: int, rounds: int, idle_timeout: float) -> dict:
    """:func:`cell` in a watched child process (``_timing.run_watched``); a peer that wedges is killed, listed as
    ``hung`` and the cell measured again without it. ``idle_timeout`` 0: in this process, unwatched."""
    if not idle_timeout:
        return cell(workload, B, n, T, rounds)
    hung = {}
    while True:
        try:
            return run_watched(cell, (workload, B, n, T, rounds, hung), idle_timeout=idle_timeout)
        except Hung as exc:
            if exc.entry is None or exc.entry in REQUIRED:
                raise
            hung[exc.entry] = f"{exc}: killed"
            print(f"{workload} B={B} n={n} T={T}: {hung[exc.entry]}; measuring the cell again without it", flush=True)


def work(workload: str, B: int, n: int, T: int) -> float:
    return WEIGHT[workload] * B * T * n**3


def targets(results: list[dict]) -> dict:
    """Per peer: the batched cells that miss the throughput target, and the cells where jaxobs compiles slower
    than dynamax."""
    out = {}
    for peer, minimum in TARGETS.items():
        cells = [r for r in results if r["B"] > 1 and r["record"]["peers"].get(peer, {}).get("status") == "ok"]
        missed = [r["cell"] for r in cells if r["record"]["peers"][peer]["ratio"]["median"] < minimum]
        hung = [r["cell"] for r in results if r["record"]["peers"].get(peer, {}).get("status") == "hung"]
        out[peer] = {"min_ratio": minimum, "batched_cells": len(cells), "missed": missed, "met": not missed,
                     "hung": hung}  # fmt: skip
    slow = [r["cell"] for r in results if r["record"]["peers"].get("dynamax", {}).get("status") == "ok"
            and r["record"]["jaxobs"]["compile_s"] > r["record"]["peers"]["dynamax"]["compile_s"]]  # fmt: skip
    out["compile_vs_dynamax"] = {"slower_cells": slow, "met": not slow}
    return out


def table(results: list[dict], skipped: list[str]) -> str:
    head = (f"{'cell':<24} {'jaxobs [ms]':<30} " + " ".join(f"{p + ' / jaxobs':<22}" for p in PEERS)
            + f" {'Joseph / standard':<22} {'dynamax, cuthbert / floor':<32} compile j/d/c [s]    "
            + "max rel diff d, c")  # fmt: skip
    lines = [head]
    for r in results:
        rec = r["record"]
        ms = {k: rec["jaxobs"]["seconds"][k] * 1e3 for k in ("median", "min", "max")}
        row = f"{r['cell']:<24} {format_range(ms):<30} "
        compiles, diffs = [f"{rec['jaxobs']['compile_s']:.1f}"], []
        for peer in PEERS:
            p = rec["peers"][peer]
            if p["status"] != "ok":
                row += f"{p['status']:<22} "
                compiles.append("-")
                diffs.append("-")
                continue
            row += f"{format_range(p['ratio'], '.2f', 'x'):<22} "
            compiles.append(f"{p['compile_s']:.1f}")
            diffs.append(f"{p['max_relative_difference']:.0e}" + ("" if p["agrees"] else "!"))
        row += f"{format_range(rec['joseph']['cost'], '.2f', 'x'):<22} "
        ceilings = [rec.get("floor", {}).get(f"{peer}_over_floor") for peer in PEERS]
        ceiling = ", ".join("-" if c is None else f"{c['median']:.2f}x" for c in ceilings)
        row += f"{ceiling:<32} "
        lines.append(row + f"{'/'.join(compiles):<20} {', '.join(diffs)}")
    lines += [f"skipped (over --budget): {', '.join(skipped)}"] if skipped else []
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory for estimation.json")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    parser.add_argument("--states", type=int, nargs="+", default=[2, 10, 32])
    parser.add_argument("--lengths", type=int, nargs="+", default=[100, 10_000])
    parser.add_argument("--workloads", nargs="+", choices=WORKLOADS, default=list(WORKLOADS))
    parser.add_argument(
        "--budget",
        type=float,
        default=3e7,
        help="skip cells whose work WEIGHT * B * T * n^3 exceeds this (listed as skipped)",
    )
    parser.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    parser.add_argument(
        "--idle-timeout",
        type=float,
        default=120.0,
        help="run each cell in a child process and kill a peer that neither progresses nor computes for this many "
        "seconds (listed as hung); 0: every cell in this process, unwatched",
    )
    args = parser.parse_args(argv)
    results, skipped = [], []
    for T, B, n, workload in itertools.product(args.lengths, args.batches, args.states, args.workloads):
        name = f"{workload} B={B} n={n} T={T}"
        if work(workload, B, n, T) > args.budget:
            skipped.append(name)
            continue
        record = measure(workload, B, n, T, args.rounds, args.idle_timeout)
        results.append({"cell": name, "workload": workload, "B": B, "n": n, "T": T, "record": record})
        print(table(results[-1:], []).splitlines()[-1], flush=True)
    summary = targets(results)
    meta = {"device": str(jax.devices()[0]), "platform": platform.platform(), "jax": jax.__version__,
            "rounds": args.rounds, "budget": args.budget, "agree_rtol": AGREE_RTOL}  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "estimation.json").write_text(
        json.dumps({"meta": meta, "results": results, "skipped": skipped, "targets": summary}, indent=1)
    )
    print(f"\nfloat64 on {meta['device']}, {args.rounds} interleaved rounds, median [min, max]; ratio = peer time / "
          "jaxobs time (paired by round); ! = disagrees beyond " + f"{AGREE_RTOL:g}")  # fmt: skip
    print(table(results, skipped))
    for peer, t in summary.items():
        if peer in TARGETS:
            verdict = "met" if t["met"] else f"MISSED on {', '.join(t['missed'])}"
            print(f"target >= {t['min_ratio']:g}x {peer} on {t['batched_cells']} batched cells: "
                  + (verdict if t["batched_cells"] else "no batched cell measured")
                  + (f"; {peer} hung on {', '.join(t['hung'])}" if t["hung"] else ""))  # fmt: skip
    slow = summary["compile_vs_dynamax"]["slower_cells"]
    print("compile time no worse than dynamax: " + ("met" if not slow else f"MISSED on {', '.join(slow)}"))
    print(f"wrote {args.out / 'estimation.json'}")
    return {"results": results, "skipped": skipped, "targets": summary}


if __name__ == "__main__":
    main()
