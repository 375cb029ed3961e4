"""Throughput of the jaxobs Kalman filter and DARE solver against dynamax, simdkalman, filterpy, NumPy and SciPy.

What is measured (float64; n = 10 states, m = 1 output; defaults B = 1024 sequences of T = 1000 steps):

1. ``independent``: B models, each with its own Phi, C, Q, R (time-varying gain). jaxobs and dynamax
   ``lgssm_filter`` are both ``jit(vmap(...))`` over params and measurements; simdkalman runs with
   stacked (B, n, n) matrices (NumPy batched over the models); filterpy has no batched form and filters one
   sequence at a time. Every peer does the same work: B covariance recursions.
2. ``shared``: one model, B measurement sequences. jaxobs ``filter_shared_model`` runs the covariance recursion
   once; so do dynamax (``vmap`` over the measurements only leaves its covariance recursion unbatched) and
   ``numpy_schedule`` (NumPy, batched over the B sequences, the same gain schedule computed once per call).
   simdkalman and filterpy have no shared-covariance form: they run B recursions, an algorithmic difference
   (labelled so in the JSON, the table and the figure), not the same work.
3. ``steady_state``: the shared model with the fixed steady-state (DARE) gain, computed before the timing:
   jaxobs ``with_steady_state_gain`` and ``numpy_schedule`` with SciPy's DARE gain do the same work (no
   covariance propagation); dynamax (one time-varying recursion), simdkalman and filterpy (B recursions) do
   more: an algorithmic difference, labelled so.
4. ``dare``: B filter DAREs, ``jit(vmap(jaxobs.matrix_equations.dare))`` against a Python loop of
   ``scipy.linalg.solve_discrete_are`` (SciPy has no batched DARE).

Scenarios 1-3 also time ``write_floor``, a function that only writes an array of the filtered means'
shape: no filter can beat it, so ``floor / peer`` is the largest ratio over that peer attainable on
this machine (reported as ``attainable_ratio`` next to each target).

Models are random and stable (spectral radius 0.95) with random positive definite Q and R, and the
measurements are simulated from them. Every filter gets the same prior of ``x_0`` (the state at the first
measurement): mean 0 and the covariance ``Phi Q Phi' + Q`` (one prediction from ``P_{-1} = Q``). A small case
checks that all filters return the same filtered means (max abs difference, stored in the JSON).

Timing (``benchmarks/_timing.py``): each JAX function is lowered and compiled first (compile time reported
separately); then ``--rounds`` interleaved rounds run every entry once each, ending in ``block_until_ready``.
Times and throughputs are reported as the median and [min, max] over the rounds, and each ratio ours / peer is
taken round by round (paired, same round) and summarised the same way. filterpy is timed on a few sequences
and extrapolated to B. Throughput is plant-steps/s (B * T / seconds; DAREs/s for scenario 4). A peer that
cannot be imported is reported as skipped.

Run (``make bench`` does the first with ``--out out/bench``)::

    python benchmarks/kalman_throughput.py --out DIR [--batch 1024] [--steps 1000] [--rounds 7] [--quick]
    python benchmarks/kalman_throughput.py --out DIR --device-sweep   # GPU only: B = 1e3, 1e4, 1e5

Writes ``DIR/kalman_throughput.json`` (every number, platform, targets) and
``DIR/kalman_throughput.png`` (speedup ratios, median and range, log scale, with the target lines).
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
from _models import random_models  # noqa: E402
from _timing import Skipped, format_range, optional_import, paired_ratio, time_interleaved  # noqa: E402

from jaxobs.matrix_equations import dare  # noqa: E402
from jaxobs.observers import EstimatorInputs, run  # noqa: E402
from jaxobs.observers.kalman import (  # noqa: E402
    KalmanParams,
    filter_shared_model,
    kalman_filter,
    make_kalman,
    with_steady_state_gain,
)

N_STATES, N_OUTPUTS = 10, 1
SPECTRAL_RADIUS = 0.95
OURS = "jaxobs"
FLOOR = "write_floor"  # pseudo-peer: the memory-write lower bound on any filter (see prepare_write_floor)
SCHEDULE = "numpy_schedule"  # NumPy batched over the sequences of one shared model, with its gain schedule
# scenario -> (peer the target is measured against, minimum ours/peer ratio)
TARGETS = {
    "independent": ("dynamax", 1.5),
    "shared": ("dynamax", 10.0),
    "steady_state": ("dynamax", 20.0),
    "dare": ("scipy", 20.0),
}
SWEEP_BATCHES = (1_000, 10_000, 100_000)


dynamax_lgssm, DYNAMAX_MISSING = optional_import("dynamax.linear_gaussian_ssm")
simdkalman, SIMDKALMAN_MISSING = optional_import("simdkalman")
filterpy_kalman, FILTERPY_MISSING = optional_import("filterpy.kalman")


# ---------------------------------------------------------------------------------------------
# Workload


@dataclasses.dataclass(frozen=True)
class Workload:
    """NumPy float64 models and data. Model arrays have a leading batch axis, or none when shared."""

    Phi: np.ndarray  # (B, n, n) or (n, n)
    C: np.ndarray  # (B, m, n) or (m, n)
    Q: np.ndarray
    R: np.ndarray
    Y: np.ndarray  # (B, T, m) simulated measurements

    @property
    def shared(self) -> bool:
        return self.Phi.ndim == 2

    @property
    def batch(self) -> int:
        return self.Y.shape[0]

    @property
    def steps(self) -> int:
        return self.Y.shape[1]

    def model(self, i: int) -> tuple[np.ndarray, ...]:
        """``(Phi, C, Q, R)`` of sequence ``i``."""
        pick = (lambda M: M) if self.shared else (lambda M: M[i])
        return tuple(pick(M) for M in (self.Phi, self.C, self.Q, self.R))

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of x_0 before the first update: one predict from x_{-1} = 0, P_{-1} = Q."""
        mean = np.zeros(self.Phi.shape[:-1])
        cov = self.Phi @ self.Q @ np.swapaxes(self.Phi, -1, -2) + self.Q
        return mean, 0.5 * (cov + np.swapaxes(cov, -1, -2))


def make_workload(seed: int, batch: int, steps: int, shared: bool) -> Workload:
    """Random models (one shared, or one per sequence) and ``batch`` simulated measurement sequences."""
    rng = np.random.default_rng(seed)
    Phi, C, Q, R = random_models(rng, 1 if shared else batch, N_STATES, N_OUTPUTS, SPECTRAL_RADIUS)
    chol_Q, chol_R = np.linalg.cholesky(Q), np.linalg.cholesky(R)
    x = np.zeros((batch, N_STATES))
    Y = np.empty((batch, steps, N_OUTPUTS))
    for k in range(steps):
        w = (chol_Q @ rng.standard_normal((batch, N_STATES, 1)))[..., 0]
        v = (chol_R @ rng.standard_normal((batch, N_OUTPUTS, 1)))[..., 0]
        x = np.einsum("bij,bj->bi", np.broadcast_to(Phi, (batch, N_STATES, N_STATES)), x) + w
        Y[:, k] = np.einsum("bij,bj->bi", np.broadcast_to(C, (batch, N_OUTPUTS, N_STATES)), x) + v
    models = (M[0] for M in (Phi, C, Q, R)) if shared else (Phi, C, Q, R)
    return Workload(*models, Y=Y)


# ---------------------------------------------------------------------------------------------
# The filters under test: each ``prepare_*`` turns a Workload into ``(fn, args)`` where ``fn(*args)``
# returns the filtered means, shape (B, T, n). JAX entries are jit-compiled by ``measure``.


def kalman_params(work: Workload, steady_state: bool = False) -> KalmanParams:
    """jaxobs params (stacked over the batch unless shared; a model without inputs); validated by ``make_kalman``
    for one model."""
    n = N_STATES
    Phi, C, Q, R = work.model(0)
    make_kalman(Phi, C, Q, R)  # eager validation of a representative model
    lead = work.Phi.shape[:-2]
    mean, cov = work.prior()
    params = KalmanParams(
        Phi=jnp.asarray(work.Phi),
        Gamma=jnp.zeros(lead + (n, 0)),
        C=jnp.asarray(work.C),
        Q=jnp.asarray(work.Q),
        R=jnp.asarray(work.R),
        x0=jnp.asarray(mean),
        P0=jnp.asarray(cov),
    )
    return with_steady_state_gain(params) if steady_state else params


def prepare_jaxobs(work: Workload, steady_state: bool = False):
    """Independent models: ``vmap(run)`` over params and data. One shared time-varying model:
    ``filter_shared_model`` (Riccati recursion once, means batched). Steady state: fixed gain."""
    params = kalman_params(work, steady_state)
    Y = jnp.asarray(work.Y)

    if work.shared and not steady_state:

        def shared_means(p, y):
            return filter_shared_model(p, EstimatorInputs(y=y))[1].x

        return shared_means, (params, Y)

    def filtered_means(p, y):
        return run(kalman_filter, p, EstimatorInputs(y=y))[1].x

    fn = jax.vmap(filtered_means, in_axes=(None if work.shared else 0, 0))
    return fn, (params, Y)


def prepare_dynamax(work: Workload):
    if dynamax_lgssm is None:
        raise Skipped(DYNAMAX_MISSING)
    lg = dynamax_lgssm
    mean, cov = work.prior()
    lead = work.Phi.shape[:-2]
    params = lg.ParamsLGSSM(
        initial=lg.ParamsLGSSMInitial(mean=mean, cov=cov),
        dynamics=lg.ParamsLGSSMDynamics(
            weights=work.Phi,
            bias=np.zeros(lead + (N_STATES,)),
            input_weights=np.zeros(lead + (N_STATES, 0)),
            cov=work.Q,
        ),
        emissions=lg.ParamsLGSSMEmissions(
            weights=work.C,
            bias=np.zeros(lead + (N_OUTPUTS,)),
            input_weights=np.zeros(lead + (N_OUTPUTS, 0)),
            cov=work.R,
        ),
    )
    params = jax.tree.map(jnp.asarray, params)

    def filtered_means(p, y):
        return lg.lgssm_filter(p, y).filtered_means

    fn = jax.vmap(filtered_means, in_axes=(None if work.shared else 0, 0))
    return fn, (params, jnp.asarray(work.Y))


def prepare_simdkalman(work: Workload):
    """simdkalman's vectorised update / predict over all B series (stacked matrices when not shared).

    ``KalmanFilter.compute`` reads the state size from ``state_transition.shape[0]`` and so cannot
    take per-series (B, n, n) transitions; this is its inner loop, without storing covariances.
    """
    if simdkalman is None:
        raise Skipped(SIMDKALMAN_MISSING)
    kf = simdkalman.KalmanFilter(work.Phi, work.Q, work.C, work.R)
    B, T, n = work.batch, work.steps, N_STATES
    mean, cov = work.prior()

    def filtered_means(Y):
        m = np.broadcast_to(mean, (B, n))[..., None].copy()
        P = np.broadcast_to(cov, (B, n, n)).copy()
        out = np.empty((B, T, n))
        for k in range(T):
            m, P, _ = kf.update(m, P, Y[:, k, :, None])
            out[:, k] = m[..., 0]
            m, P = kf.predict_next(m, P)
        return out

    return filtered_means, (work.Y,)


def prepare_filterpy(work: Workload, sequences: int):
    """filterpy, one ``KalmanFilter.batch_filter`` per sequence, for the first ``sequences`` sequences."""
    if filterpy_kalman is None:
        raise Skipped(FILTERPY_MISSING)
    mean, cov = work.prior()

    def filtered_means(Y):
        out = []
        for i in range(sequences):
            Phi, C, Q, R = work.model(i)
            kf = filterpy_kalman.KalmanFilter(dim_x=N_STATES, dim_z=N_OUTPUTS)
            kf.F, kf.H, kf.Q, kf.R = Phi, C, Q, R
            m0 = mean if work.shared else mean[i]
            P0 = cov if work.shared else cov[i]
            kf.x, kf.P = m0.copy(), P0.copy()
            means = kf.batch_filter(Y[i], update_first=True)[0]
            out.append(means.reshape(work.steps, N_STATES))
        return np.stack(out)

    return filtered_means, (work.Y[:sequences],)


def prepare_numpy_schedule(work: Workload, steady_state: bool = False):
    """NumPy batched over the B sequences of one shared model, with the gain schedule they all share: the
    covariance recursion (eq. 27-29, Joseph form, from the same prior) runs once per call, or not at
    all with the steady-state gain of ``scipy.linalg.solve_discrete_are`` (computed here, before the timing,
    as jaxobs's). Then one (B, n) update per step: the same work as jaxobs on scenarios 2 and 3."""
    if not work.shared:
        raise Skipped("needs one shared model")
    Phi, C, Q, R = work.model(0)
    n = N_STATES
    mean, cov = work.prior()
    fixed = None
    if steady_state:
        P1 = scipy.linalg.solve_discrete_are(Phi.T, C.T, Q, R)
        fixed = np.linalg.solve(C @ P1 @ C.T + R, C @ P1).T

    def gain_schedule(T):
        if fixed is not None:
            return [fixed] * T
        P1, gains = cov, []
        for _ in range(T):
            K = np.linalg.solve(C @ P1 @ C.T + R, C @ P1).T
            IKC = np.eye(n) - K @ C
            P = IKC @ P1 @ IKC.T + K @ R @ K.T
            P1 = Phi @ P @ Phi.T + Q
            gains.append(K)
        return gains

    def filtered_means(Y):
        B, T = Y.shape[:2]
        out = np.empty((B, T, n))
        x1 = np.broadcast_to(mean, (B, n))
        for k, K in enumerate(gain_schedule(T)):
            x = x1 + (Y[:, k] - x1 @ C.T) @ K.T
            out[:, k] = x
            x1 = x @ Phi.T
        return out

    return filtered_means, (work.Y,)


def prepare_write_floor(work: Workload):
    """Not a filter: the cheapest ``jit`` function that reads the measurements and writes the
    (B, T, n) filtered-means array every filter must return. Its time bounds every filter from
    below, so ``floor / peer`` is the largest speedup over that peer any implementation can reach."""

    def write_means_shaped(Y):
        return jnp.broadcast_to(Y[..., :1], Y.shape[:2] + (N_STATES,)) * 2.0

    return write_means_shaped, (jnp.asarray(work.Y),)


def prepare_dare_jaxobs(work: Workload):
    fn = jax.vmap(lambda Phi, C, Q, R: dare(Phi.T, C.T, Q, R).X)
    return fn, tuple(jnp.asarray(M) for M in (work.Phi, work.C, work.Q, work.R))


def prepare_dare_scipy(work: Workload):
    def solve_all(Phi, C, Q, R):
        return np.stack(
            [scipy.linalg.solve_discrete_are(A.T, H.T, W, V) for A, H, W, V in zip(Phi, C, Q, R, strict=True)]
        )

    return solve_all, (work.Phi, work.C, work.Q, work.R)


# ---------------------------------------------------------------------------------------------
# Ratios and targets


def add_ratios(scenario: dict, name: str, timings: dict) -> dict:
    """Ours / peer ratios (paired round by round) and the target verdict of ``scenario`` (in place)."""
    ours = timings[OURS]
    scenario["ratios"] = {peer: paired_ratio(ours, t) for peer, t in timings.items() if peer != OURS}
    if name in TARGETS:
        peer, minimum = TARGETS[name]
        ratio = scenario["ratios"].get(peer)
        median = None if ratio is None else ratio["median"]
        scenario["target"] = {
            "peer": peer,
            "min_ratio": minimum,
            "ratio_median": median,
            "met": None if median is None else bool(median >= minimum),
        }
        if FLOOR in timings and peer in timings:
            scenario["target"]["attainable_ratio"] = paired_ratio(timings[FLOOR], timings[peer])
    return scenario


# ---------------------------------------------------------------------------------------------
# Scenarios


SAME_WORK = "same work"


def work_labels(shared: bool, steady_state: bool) -> dict:
    """``{peer: what it computes relative to jaxobs}`` for a filtering scenario."""
    if not shared:
        return {"dynamax": SAME_WORK, "simdkalman": SAME_WORK, "filterpy": SAME_WORK + " (one sequence at a time)"}
    ours = "none" if steady_state else "one"
    many = f"algorithmic difference: B covariance recursions (jaxobs: {ours})"
    dynamax = f"algorithmic difference: one covariance recursion (jaxobs: {ours})" if steady_state else SAME_WORK
    return {"dynamax": dynamax, SCHEDULE: SAME_WORK, "simdkalman": many, "filterpy": many}


def filter_peers(work: Workload, filterpy_sequences: int, steady_state: bool = False, peers=None):
    """``{peer: (prepare, jit, scale)}`` for the filtering scenarios; ``peers`` restricts the set."""
    table = {
        OURS: (lambda: prepare_jaxobs(work, steady_state), True, 1.0),
        "dynamax": (lambda: prepare_dynamax(work), True, 1.0),
        SCHEDULE: (lambda: prepare_numpy_schedule(work, steady_state), False, 1.0),
        "simdkalman": (lambda: prepare_simdkalman(work), False, 1.0),
        "filterpy": (
            lambda: prepare_filterpy(work, filterpy_sequences),
            False,
            work.batch / filterpy_sequences,
        ),
        FLOOR: (lambda: prepare_write_floor(work), True, 1.0),
    }
    if not work.shared:
        del table[SCHEDULE]
    return {k: v for k, v in table.items() if peers is None or k in peers}


def _records(table: dict, timings: dict, problems: dict, work_items: float, unit: str) -> dict:
    return {name: timings[name].record(work_items, unit) if name in timings else problems[name] for name in table}


def filter_scenario(
    name: str,
    description: str,
    work: Workload,
    *,
    rounds: int,
    filterpy_sequences: int,
    steady_state: bool = False,
    peers=None,
) -> dict:
    table = filter_peers(work, filterpy_sequences, steady_state, peers)
    timings, problems = time_interleaved(table, rounds, required=(OURS,))
    records = _records(table, timings, problems, work.batch * work.steps, "plant-steps/s")
    labels = work_labels(work.shared, steady_state)
    for peer, (_, _, scale) in table.items():
        if peer in labels:
            records[peer]["work"] = labels[peer]
        if scale != 1.0 and records[peer]["status"] == "ok":
            records[peer]["extrapolated_from_sequences"] = filterpy_sequences
    scenario = {
        "description": description,
        "unit": "plant-steps/s",
        "batch": work.batch,
        "steps": work.steps,
        "peers": records,
    }
    return add_ratios(scenario, name, timings)


DARE_TOLERANCE = 1e-12  # max relative difference from SciPy accepted as "the same answer"


def dare_scenario(work: Workload, *, rounds: int) -> dict:
    table = {
        OURS: (lambda: prepare_dare_jaxobs(work), True, 1.0),
        "scipy": (lambda: prepare_dare_scipy(work), False, 1.0),
    }
    timings, problems = time_interleaved(table, rounds, required=(OURS, "scipy"))
    records = _records(table, timings, problems, work.batch, "DAREs/s")
    records["scipy"]["work"] = SAME_WORK + " (one DARE at a time: SciPy has no batched DARE)"
    P, P_ref = np.asarray(timings[OURS].result), timings["scipy"].result
    rel = np.abs(P - P_ref).max(axis=(-2, -1)) / np.abs(P_ref).max(axis=(-2, -1))
    scenario = {
        "description": f"{work.batch} filter DAREs (n={N_STATES}, m={N_OUTPUTS}): "
        "jit(vmap(jaxobs.matrix_equations.dare)) vs a loop of scipy.linalg.solve_discrete_are",
        "unit": "DAREs/s",
        "batch": work.batch,
        "peers": records,
        "max_relative_error": float(rel.max()),
        "relative_error_definition": "max over the batch of max|P - P_scipy| / max|P_scipy|",
        "relative_error_tolerance": DARE_TOLERANCE,
        "answers_agree": bool(rel.max() <= DARE_TOLERANCE),
    }
    return add_ratios(scenario, "dare", timings)


def agreement_check(seed: int, batch: int = 4, steps: int = 200) -> dict:
    """Max abs difference of every peer's filtered means from jaxobs's on a small case (same prior); on the
    shared model also the steady-state NumPy peer against jaxobs's steady-state filter."""
    out = {
        "batch": batch,
        "steps": steps,
        "note": "dynamax's psd_solve adds 1e-9 to the innovation covariance, hence its ~1e-9 difference; "
        "jaxobs_steady_state_last_half compares jaxobs's fixed-gain and time-varying filters over t >= T/2",
    }
    for label, shared in (("independent", False), ("shared", True)):
        work = make_workload(seed, batch, steps, shared)
        fn, args = prepare_jaxobs(work)
        ref = np.asarray(jax.jit(fn)(*args))
        diffs = {}
        for peer, (prepare, _, _) in filter_peers(work, filterpy_sequences=batch).items():
            if peer in (OURS, FLOOR):
                continue
            try:
                peer_fn, peer_args = prepare()
            except Skipped as exc:
                diffs[peer] = f"skipped: {exc}"
                continue
            diffs[peer] = float(np.abs(np.asarray(peer_fn(*peer_args)) - ref).max())
        if shared:  # the steady-state filter approaches the time-varying one as P settles
            ss_fn, ss_args = prepare_jaxobs(work, steady_state=True)
            ss = np.asarray(jax.jit(ss_fn)(*ss_args))
            diffs["jaxobs_steady_state_last_half"] = float(np.abs(ss - ref)[:, steps // 2 :].max())
            np_fn, np_args = prepare_numpy_schedule(work, steady_state=True)
            diffs[f"{SCHEDULE}_steady_state_vs_jaxobs_steady_state"] = float(np.abs(np_fn(*np_args) - ss).max())
        out[label] = diffs
        out[f"{label}_max_abs_mean"] = float(np.abs(ref).max())
    return out


# ---------------------------------------------------------------------------------------------
# Device sweep (GPU only)


def missing_gpu() -> str | None:
    """Why the device sweep cannot run, or None when JAX has a GPU."""
    kinds = {d.platform for d in jax.devices()}
    return None if kinds & {"gpu", "cuda", "rocm"} else f"no GPU: jax sees only {sorted(kinds)} devices"


def device_sweep(seed: int, steps: int, rounds: int) -> dict:
    """Scenarios 1-3 (jaxobs and dynamax only) for B in ``SWEEP_BATCHES`` on a GPU."""
    reason = missing_gpu()
    if reason:
        print(f"\ndevice sweep skipped ({reason})")
        return {"skipped": reason}
    sweep = {}
    for batch in SWEEP_BATCHES:
        for name, (description, shared, steady) in FILTER_SCENARIOS.items():
            work = make_workload(seed, batch, steps, shared)
            sweep[f"{name}@B={batch}"] = filter_scenario(
                name,
                description,
                work,
                rounds=rounds,
                filterpy_sequences=1,
                steady_state=steady,
                peers=(OURS, "dynamax", FLOOR),
            )
            print(format_scenario(f"{name} (B={batch})", sweep[f"{name}@B={batch}"]))
    return sweep


# ---------------------------------------------------------------------------------------------
# Report


# scenario -> (description, shared model, steady-state gain)
FILTER_SCENARIOS = {
    "independent": ("B independent models (own Phi, C, Q, R), time-varying gain", False, False),
    "shared": ("one shared model, B measurement sequences, time-varying gain", True, False),
    "steady_state": (
        "one shared model, B sequences; jaxobs with the steady-state gain, peers time-varying",
        True,
        True,
    ),
}


def environment() -> dict:
    device = jax.devices()[0]
    return {
        "machine": platform.machine(),
        "processor": platform.processor(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "jax_backend": jax.default_backend(),
        "device_kind": device.device_kind,
        "x64": bool(jax.config.jax_enable_x64),
        "peers": {
            name: getattr(module, "__version__", "installed") if module is not None else f"missing ({why})"
            for name, module, why in (
                ("dynamax", importlib.import_module("dynamax") if dynamax_lgssm else None, DYNAMAX_MISSING),
                ("simdkalman", simdkalman, SIMDKALMAN_MISSING),
                ("filterpy", importlib.import_module("filterpy") if filterpy_kalman else None, FILTERPY_MISSING),
            )
        },
    }


def verdict(target: dict) -> str:
    return "n/a (peer unavailable)" if target["met"] is None else ("MET" if target["met"] else "MISSED")


def format_scenario(title: str, scenario: dict) -> str:
    unit = scenario["unit"]
    lines = [
        f"\n== {title}: {scenario['description']}",
        f"   {'peer':<15}{'seconds, median [min, max]':>34}{'compile s':>11}   {'ours/peer, median [min, max]':<30}",
    ]
    for peer, rec in scenario["peers"].items():
        if rec["status"] != "ok":
            lines.append(f"   {peer:<15}{rec['status']}: {rec['reason']}")
            continue
        compile_s = "" if rec["compile_s"] is None else f"{rec['compile_s']:.2f}"
        ratio = scenario["ratios"].get(peer)
        ratio_s = "" if ratio is None else format_range(ratio, ".3g", "x")
        notes = [rec["work"]] if "work" in rec else []
        if "extrapolated_from_sequences" in rec:
            notes.append(f"extrapolated from {rec['extrapolated_from_sequences']} seq")
        lines.append(
            f"   {peer:<15}{format_range(rec['seconds'], '.4f'):>34}{compile_s:>11}   {ratio_s:<30}"
            + (f"  ({'; '.join(notes)})" if notes else "")
        )
    lines.append(f"   throughput of jaxobs: {format_range(scenario['peers'][OURS]['throughput'], '.4g')} {unit}")
    target = scenario.get("target")
    if target:
        got = "" if target["ratio_median"] is None else f", median {target['ratio_median']:.2f}x"
        lines.append(f"   target: >= {target['min_ratio']:g}x {target['peer']}{got} -> {verdict(target)}")
        if "attainable_ratio" in target:
            bound = format_range(target["attainable_ratio"], ".3g", "x")
            lines.append(f"   attainable by any filter (memory-write floor / {target['peer']}): {bound}")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    from jaxobs.papers._output import pyplot, save_figure

    fig, ax = pyplot().subplots(figsize=(14, 5.5))
    x, ticks, labels = 0.0, [], []
    for name, scenario in results["scenarios"].items():
        start = x
        target = scenario.get("target")
        for peer, ratio in scenario["ratios"].items():
            work = scenario["peers"][peer].get("work", SAME_WORK)
            color = "tab:blue"  # same work, not the target's peer
            if peer == FLOOR:
                color = "lightgrey"  # below 1: how close jaxobs is to the memory-write lower bound
            elif not work.startswith(SAME_WORK):
                color = "tab:orange"  # the peer computes more (an algorithmic difference, not the same work)
            elif target and peer == target["peer"]:
                color = "tab:green" if target["met"] else "tab:red"
            med = ratio["median"]
            ax.bar(x, med, color=color, width=0.8)
            ax.errorbar(x, med, yerr=[[med - ratio["min"]], [ratio["max"] - med]], color="k", capsize=3, lw=0.8)
            ax.text(x, ratio["max"], f"{med:.2g}x", ha="center", va="bottom", fontsize=8)
            ticks.append(x)
            labels.append(peer.replace("_", "\n"))
            if target and peer == target["peer"]:  # the target: a line across its peer's bar, named below it
                ax.hlines(target["min_ratio"], x - 0.45, x + 0.45, colors="k", linestyles="--")
                labels[-1] += f"\n(target {target['min_ratio']:g}x)"
            x += 1
        ax.annotate(
            name,
            xy=((start + x - 1) / 2, 0),
            xycoords=("data", "axes fraction"),
            xytext=(0, -30),
            textcoords="offset points",
            ha="center",
            va="top",
            fontweight="bold",
        )
        x += 0.7
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_yscale("log")
    ax.set_xticks(ticks, labels, fontsize=7)
    ax.set_ylabel("speedup: jaxobs / peer throughput\n(median of paired rounds, bar: [min, max])")
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    ax.legend(  # beside the axes: no bar hidden
        handles=[
            Patch(color="tab:green", label="same work, target met"),
            Patch(color="tab:red", label="same work, target missed"),
            Patch(color="tab:blue", label="same work"),
            Patch(color="tab:orange", label="peer does more work (algorithmic difference)"),
            Patch(color="lightgrey", label="memory-write floor (bound on any filter)"),
            Line2D([], [], color="k", ls="--", label="target: the least speedup asked"),
        ],
        fontsize=7,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
    )
    cfg = results["config"]
    ax.set_title(
        f"jaxobs Kalman throughput, B={cfg['batch']}, T={cfg['steps']}, n={N_STATES}, float64, "
        f"{results['environment']['device_kind']}, {cfg['rounds']} interleaved rounds"
    )
    save_figure(fig, path.parent, path.stem, dpi=130)


# ---------------------------------------------------------------------------------------------


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--batch", type=int, default=1024, help="B: sequences / models / DAREs")
    parser.add_argument("--steps", type=int, default=1000, help="T: time steps per sequence")
    parser.add_argument("--rounds", type=int, default=7, help="interleaved timed rounds (median and range reported)")
    parser.add_argument(
        "--filterpy-sequences", type=int, default=8, help="sequences filterpy is timed on (extrapolated to B)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="small sizes for a smoke run")
    parser.add_argument(
        "--device-sweep", action="store_true", help=f"on a GPU, also time scenarios 1-3 for B in {SWEEP_BATCHES}"
    )
    args = parser.parse_args(argv)
    if args.quick:
        args.batch, args.steps = min(args.batch, 64), min(args.steps, 100)
        args.filterpy_sequences = min(args.filterpy_sequences, 2)
    args.filterpy_sequences = min(args.filterpy_sequences, args.batch)

    results = {
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "environment": environment(),
        "targets": {name: {"peer": peer, "min_ratio": ratio} for name, (peer, ratio) in TARGETS.items()},
        "scenarios": {},
    }
    print(
        f"jax {jax.__version__} on {results['environment']['device_kind']} "
        f"({results['environment']['jax_backend']}), float64, n={N_STATES}, m={N_OUTPUTS}, "
        f"B={args.batch}, T={args.steps}, {args.rounds} interleaved rounds (median [min, max])"
    )

    agreement = results["agreement"] = agreement_check(args.seed)
    print(
        f"\nagreement: max |peer - jaxobs| of the filtered means (B={agreement['batch']}, "
        f"T={agreement['steps']}; the means reach about {agreement['independent_max_abs_mean']:.2g})"
    )
    for label in ("independent", "shared"):
        print(
            f"   {label:<12}"
            + ", ".join(
                f"{peer} {d:.2g}" if isinstance(d, float) else f"{peer} {d}" for peer, d in agreement[label].items()
            )
        )

    for index, (name, (description, shared, steady)) in enumerate(FILTER_SCENARIOS.items(), start=1):
        work = make_workload(args.seed, args.batch, args.steps, shared)
        scenario = filter_scenario(
            name,
            description,
            work,
            rounds=args.rounds,
            filterpy_sequences=args.filterpy_sequences,
            steady_state=steady,
        )
        results["scenarios"][name] = scenario
        print(format_scenario(f"{index}. {name}", scenario))

    dare_work = make_workload(args.seed, args.batch, 1, shared=False)
    results["scenarios"]["dare"] = dare_scenario(dare_work, rounds=args.rounds)
    print(format_scenario("4. dare", results["scenarios"]["dare"]))
    print(f"   max relative error vs scipy: {results['scenarios']['dare']['max_relative_error']:.3g}")

    if args.device_sweep:
        results["device_sweep"] = device_sweep(args.seed, args.steps, args.rounds)

    results["targets_met"] = {name: sc["target"]["met"] for name, sc in results["scenarios"].items()}
    print("\nsummary (ours/peer, median of paired rounds; * = the peer does more work):")
    for name, scenario in results["scenarios"].items():
        target = scenario["target"]
        ratios = ", ".join(
            f"{peer}{'' if scenario['peers'][peer].get('work', SAME_WORK).startswith(SAME_WORK) else '*'} "
            f"{r['median']:.2f}x"
            for peer, r in scenario["ratios"].items()
        )
        print(f"   {name:<13} {ratios:<80} target >= {target['min_ratio']:g}x {target['peer']}: {verdict(target)}")

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "kalman_throughput.json").write_text(json.dumps(results, indent=2))
    plot(results, args.out / "kalman_throughput.png")
    print(f"\nwrote {args.out / 'kalman_throughput.json'} and {args.out / 'kalman_throughput.png'}")
    return results


if __name__ == "__main__":
    main()
