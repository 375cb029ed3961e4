"""Throughput of the jaxobs Kalman filter and DARE solver against dynamax, simdkalman, filterpy and SciPy.

What is measured (float64; n = 10 states, m = 1 output; defaults B = 1024 sequences of T = 1000 steps):

1. ``independent``: B models, each with its own Phi, C, Q, R (time-varying gain). jaxobs and dynamax
   ``lgssm_filter`` are both ``jit(vmap(...))`` over params and measurements; simdkalman runs with
   stacked (B, n, n) matrices; filterpy filters one sequence at a time.
2. ``shared``: one model, B measurement sequences; the JAX filters ``vmap`` over the measurements only.
3. ``steady_state``: jaxobs with ``with_steady_state_gain`` (fixed DARE gain, no covariance
   propagation) on the shared model, against the peers' time-varying filters of scenario 2.
4. ``dare``: B filter DAREs, ``jit(vmap(jaxobs.riccati.dare))`` against a Python loop of
   ``scipy.linalg.solve_discrete_are``.

Scenarios 1-3 also time ``write_floor``, a function that only writes an array of the filtered means'
shape: no filter can beat it, so ``floor / peer`` is the largest ratio over that peer attainable on
this machine (reported as ``attainable_ratio`` next to each target).

Models are random and stable (spectral radius 0.95) with random positive definite Q and R, and the
measurements are simulated from them. Every filter gets the same prior: jaxobs starts from
``x_{-1} = 0, P_{-1} = Q`` and predicts once; the peers start from that predicted prior. A small case
checks that all filters return the same filtered means (max abs difference, stored in the JSON).

Timing: each JAX function is lowered and compiled first (compile time reported separately), then
every peer is timed as the best of ``--repeats`` runs ending in ``block_until_ready``, in interleaved
rounds (each round runs every peer once) so that a slow phase of the machine hits all peers. filterpy is
timed on a few sequences and extrapolated to B. Throughput is plant-steps/s (B * T / seconds;
DAREs/s for scenario 4) and the ratios are ours / peer. A peer that cannot be imported is reported
as skipped.

Run (``make bench`` does the first with ``--out out/bench``)::

    python benchmarks/kalman_throughput.py --out DIR [--batch 1024] [--steps 1000] [--quick]
    python benchmarks/kalman_throughput.py --out DIR --device-sweep   # GPU only: B = 1e3, 1e4, 1e5

Writes ``DIR/kalman_throughput.json`` (every number, platform, targets) and
``DIR/kalman_throughput.png`` (speedup ratios, log scale, with the target lines).
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
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402

from jaxobs.observers import run  # noqa: E402
from jaxobs.observers.kalman import (  # noqa: E402
    KalmanInputs,
    KalmanParams,
    filter_shared_model,
    kalman_filter,
    make_kalman,
    with_steady_state_gain,
)
from jaxobs.riccati import dare  # noqa: E402

N_STATES, N_OUTPUTS = 10, 1
SPECTRAL_RADIUS = 0.95
OURS = "jaxobs"
FLOOR = "write_floor"  # pseudo-peer: the memory-write lower bound on any filter (see prepare_write_floor)
# scenario -> (peer the target is measured against, minimum ours/peer ratio)
TARGETS = {
    "independent": ("dynamax", 1.5),
    "shared": ("dynamax", 10.0),
    "steady_state": ("dynamax", 20.0),
    "dare": ("scipy", 20.0),
}
SWEEP_BATCHES = (1_000, 10_000, 100_000)


def _optional_import(name: str):
    """``(module, None)``, or ``(None, reason)`` when ``name`` cannot be imported."""
    try:
        return importlib.import_module(name), None
    except Exception as exc:  # any import-time failure means "skip this peer"
        return None, f"{type(exc).__name__}: {exc}"


dynamax_lgssm, DYNAMAX_MISSING = _optional_import("dynamax.linear_gaussian_ssm")
simdkalman, SIMDKALMAN_MISSING = _optional_import("simdkalman")
filterpy_kalman, FILTERPY_MISSING = _optional_import("filterpy.kalman")


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


def random_models(rng: np.random.Generator, count: int, n: int = N_STATES, m: int = N_OUTPUTS):
    """``count`` stable random models ``(Phi, C, Q, R)``, each stacked on a leading axis."""
    Phi = rng.standard_normal((count, n, n))
    Phi *= SPECTRAL_RADIUS / np.abs(np.linalg.eigvals(Phi)).max(axis=-1)[:, None, None]
    G = rng.standard_normal((count, n, n))
    Q = 0.1 * G @ np.swapaxes(G, -1, -2) / n + 1e-3 * np.eye(n)
    C = rng.standard_normal((count, m, n))
    H = rng.standard_normal((count, m, m))
    R = 0.5 * H @ np.swapaxes(H, -1, -2) / m + 0.5 * np.eye(m)
    return Phi, C, Q, R


def make_workload(seed: int, batch: int, steps: int, shared: bool) -> Workload:
    """Random models (one shared, or one per sequence) and ``batch`` simulated measurement sequences."""
    rng = np.random.default_rng(seed)
    Phi, C, Q, R = random_models(rng, 1 if shared else batch)
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
    """jaxobs params (stacked over the batch unless shared); validated by ``make_kalman`` for one model."""
    n = N_STATES
    Phi, C, Q, R = work.model(0)
    make_kalman(Phi, np.zeros((n, 1)), C, Q, R)  # eager validation of a representative model
    lead = work.Phi.shape[:-2]
    params = KalmanParams(
        Phi=jnp.asarray(work.Phi),
        Gamma=jnp.zeros(lead + (n, 1)),
        C=jnp.asarray(work.C),
        Q=jnp.asarray(work.Q),
        R=jnp.asarray(work.R),
        x0=jnp.zeros(lead + (n,)),
        P0=jnp.asarray(work.Q),
    )
    return with_steady_state_gain(params) if steady_state else params


def prepare_jaxobs(work: Workload, steady_state: bool = False):
    """Independent models: ``vmap(run)`` over params and data. One shared time-varying model:
    ``filter_shared_model`` (Riccati recursion once, means batched). Steady state: fixed gain."""
    params = kalman_params(work, steady_state)
    Y = jnp.asarray(work.Y)
    U = jnp.zeros(Y.shape[:2] + (1,))  # Gamma = 0: one zero input

    if work.shared and not steady_state:

        def shared_means(p, u, y):
            return filter_shared_model(p, KalmanInputs(u_prev=u, y=y))[1].x

        return shared_means, (params, U, Y)

    def filtered_means(p, u, y):
        return run(kalman_filter, p, KalmanInputs(u_prev=u, y=y))[1].x

    fn = jax.vmap(filtered_means, in_axes=(None if work.shared else 0, 0, 0))
    return fn, (params, U, Y)


def prepare_dynamax(work: Workload):
    if dynamax_lgssm is None:
        raise PeerSkipped(DYNAMAX_MISSING)
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
        raise PeerSkipped(SIMDKALMAN_MISSING)
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
        raise PeerSkipped(FILTERPY_MISSING)
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


def prepare_write_floor(work: Workload):
    """Not a filter: the cheapest ``jit`` function that reads the measurements and writes the
    (B, T, n) filtered-means array every filter must return. Its time bounds every filter from
    below, so ``floor / peer`` is the largest speedup over that peer any implementation can reach."""

    def write_means_shaped(Y):
        return jnp.broadcast_to(Y[..., :1], Y.shape[:2] + (N_STATES,)) * 2.0

    return write_means_shaped, (jnp.asarray(work.Y),)


def prepare_dare_jaxobs(work: Workload):
    fn = jax.vmap(lambda Phi, C, Q, R: dare(Phi, C, Q, R).P)
    return fn, tuple(jnp.asarray(M) for M in (work.Phi, work.C, work.Q, work.R))


def prepare_dare_scipy(work: Workload):
    def solve_all(Phi, C, Q, R):
        return np.stack(
            [scipy.linalg.solve_discrete_are(A.T, H.T, W, V) for A, H, W, V in zip(Phi, C, Q, R, strict=True)]
        )

    return solve_all, (work.Phi, work.C, work.Q, work.R)


# ---------------------------------------------------------------------------------------------
# Timing


class PeerSkipped(Exception):
    """A peer is unavailable (not installed); the message says why."""


@dataclasses.dataclass
class Timing:
    seconds: float  # best of the repeats (extrapolated to the full batch where ``scale`` != 1)
    compile_s: float | None  # jit lowering + compilation, JAX only
    result: object


def time_peers(peers: dict, *, work_items: int, repeats: int) -> tuple[dict, dict]:
    """Time every peer of ``{name: (prepare, jit, scale)}``, interleaved.

    Each peer is prepared (and compiled when ``jit``) first; then ``repeats`` rounds run every peer
    once each, and each peer keeps its best time (times ``scale``). Interleaving spreads the slow
    and fast phases of a shared machine over all peers alike, so their ratios are steadier than
    with back-to-back repeats. Returns ``(records for the JSON, {name: Timing})``; a peer that is
    missing or fails is recorded and skipped (ours failing raises).
    """
    records, ready = {}, {}
    for name, (prepare, jit, scale) in peers.items():
        try:
            fn, args = prepare()
            compile_s = None
            if jit:
                start = time.perf_counter()
                fn = jax.jit(fn).lower(*args).compile()
                compile_s = time.perf_counter() - start
            ready[name] = (fn, args, scale, compile_s)
        except PeerSkipped as exc:
            records[name] = {"status": "skipped", "reason": str(exc)}
        except Exception as exc:  # a broken peer must not abort the other measurements
            if name == OURS:
                raise
            records[name] = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}"}
    best, results = dict.fromkeys(ready, float("inf")), {}
    for _ in range(repeats):
        for name, (fn, args, _, _) in ready.items():
            start = time.perf_counter()
            results[name] = jax.block_until_ready(fn(*args))
            best[name] = min(best[name], time.perf_counter() - start)
    timings = {}
    for name, (_, _, scale, compile_s) in ready.items():
        timings[name] = Timing(best[name] * scale, compile_s, results[name])
        records[name] = {
            "status": "ok",
            "seconds": timings[name].seconds,
            "throughput": work_items / timings[name].seconds,
            "compile_s": compile_s,
        }
    return {name: records[name] for name in peers}, timings


def add_ratios(scenario: dict, name: str) -> dict:
    """Ours / peer throughput ratios and the target verdict of ``scenario`` (in place)."""
    peers = scenario["peers"]
    ours = peers[OURS]["throughput"]
    scenario["ratios"] = {
        peer: ours / rec["throughput"] for peer, rec in peers.items() if peer != OURS and rec["status"] == "ok"
    }
    if name in TARGETS:
        peer, minimum = TARGETS[name]
        ratio = scenario["ratios"].get(peer)
        scenario["target"] = {
            "peer": peer,
            "min_ratio": minimum,
            "ratio": ratio,
            "met": None if ratio is None else bool(ratio >= minimum),
        }
        floor = peers.get(FLOOR, {})
        if floor.get("status") == "ok" and peers[peer]["status"] == "ok":
            scenario["target"]["attainable_ratio"] = floor["throughput"] / peers[peer]["throughput"]
    return scenario


# ---------------------------------------------------------------------------------------------
# Scenarios


def filter_peers(work: Workload, filterpy_sequences: int, steady_state: bool = False, peers=None):
    """``{peer: (prepare, jit, scale)}`` for the filtering scenarios; ``peers`` restricts the set."""
    table = {
        OURS: (lambda: prepare_jaxobs(work, steady_state), True, 1.0),
        "dynamax": (lambda: prepare_dynamax(work), True, 1.0),
        "simdkalman": (lambda: prepare_simdkalman(work), False, 1.0),
        "filterpy": (
            lambda: prepare_filterpy(work, filterpy_sequences),
            False,
            work.batch / filterpy_sequences,
        ),
        FLOOR: (lambda: prepare_write_floor(work), True, 1.0),
    }
    return {k: v for k, v in table.items() if peers is None or k in peers}


def filter_scenario(
    name: str,
    description: str,
    work: Workload,
    *,
    repeats: int,
    filterpy_sequences: int,
    steady_state: bool = False,
    peers=None,
) -> dict:
    table = filter_peers(work, filterpy_sequences, steady_state, peers)
    records, _ = time_peers(table, work_items=work.batch * work.steps, repeats=repeats)
    for peer, (_, _, scale) in table.items():
        if scale != 1.0 and records[peer]["status"] == "ok":
            records[peer]["extrapolated_from_sequences"] = filterpy_sequences
    scenario = {
        "description": description,
        "unit": "plant-steps/s",
        "batch": work.batch,
        "steps": work.steps,
        "peers": records,
    }
    return add_ratios(scenario, name)


def dare_scenario(work: Workload, *, repeats: int) -> dict:
    table = {
        OURS: (lambda: prepare_dare_jaxobs(work), True, 1.0),
        "scipy": (lambda: prepare_dare_scipy(work), False, 1.0),
    }
    records, timings = time_peers(table, work_items=work.batch, repeats=repeats)
    P, P_ref = np.asarray(timings[OURS].result), timings["scipy"].result
    rel = np.abs(P - P_ref).max(axis=(-2, -1)) / np.abs(P_ref).max(axis=(-2, -1))
    scenario = {
        "description": f"{work.batch} filter DAREs (n={N_STATES}, m={N_OUTPUTS}): "
        "jit(vmap(jaxobs.riccati.dare)) vs a loop of scipy.linalg.solve_discrete_are",
        "unit": "DAREs/s",
        "batch": work.batch,
        "peers": records,
        "max_relative_error": float(rel.max()),
        "relative_error_definition": "max over the batch of max|P - P_scipy| / max|P_scipy|",
        "relative_error_tolerance": 1e-9,
        "answers_agree": bool(rel.max() <= 1e-9),
    }
    return add_ratios(scenario, "dare")


def agreement_check(seed: int, batch: int = 4, steps: int = 200) -> dict:
    """Max abs difference of every peer's filtered means from jaxobs's on a small case (same prior)."""
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
            except PeerSkipped as exc:
                diffs[peer] = f"skipped: {exc}"
                continue
            diffs[peer] = float(np.abs(np.asarray(peer_fn(*peer_args)) - ref).max())
        if shared:  # the steady-state filter approaches the time-varying one as P settles
            ss_fn, ss_args = prepare_jaxobs(work, steady_state=True)
            ss = np.asarray(jax.jit(ss_fn)(*ss_args))
            diffs["jaxobs_steady_state_last_half"] = float(np.abs(ss - ref)[:, steps // 2 :].max())
        out[label] = diffs
        out[f"{label}_max_abs_mean"] = float(np.abs(ref).max())
    return out


# ---------------------------------------------------------------------------------------------
# Device sweep (GPU only)


def missing_gpu() -> str | None:
    """Why the device sweep cannot run, or None when JAX has a GPU."""
    kinds = {d.platform for d in jax.devices()}
    return None if kinds & {"gpu", "cuda", "rocm"} else f"no GPU: jax sees only {sorted(kinds)} devices"


def device_sweep(seed: int, steps: int, repeats: int) -> dict:
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
                repeats=repeats,
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
        f"   {'peer':<12}{'seconds':>12}{unit:>18}{'compile s':>12}{'ours/peer':>12}",
    ]
    for peer, rec in scenario["peers"].items():
        if rec["status"] != "ok":
            lines.append(f"   {peer:<12}{rec['status']}: {rec['reason']}")
            continue
        compile_s = "" if rec["compile_s"] is None else f"{rec['compile_s']:.2f}"
        ratio = scenario["ratios"].get(peer)
        ratio_s = "" if ratio is None else f"{ratio:.2f}x"
        note = (
            f"  (extrapolated from {rec['extrapolated_from_sequences']} seq)"
            if "extrapolated_from_sequences" in rec
            else ""
        )
        lines.append(
            f"   {peer:<12}{rec['seconds']:>12.4f}{rec['throughput']:>18.4g}{compile_s:>12}{ratio_s:>12}" + note
        )
    target = scenario.get("target")
    if target:
        got = "" if target["ratio"] is None else f", got {target['ratio']:.2f}x"
        lines.append(f"   target: >= {target['min_ratio']:g}x {target['peer']}{got} -> {verdict(target)}")
        if "attainable_ratio" in target:
            bound = target["attainable_ratio"]
            lines.append(f"   attainable by any filter (memory-write floor / {target['peer']}): {bound:.2f}x")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 5))
    x, ticks, labels = 0.0, [], []
    for name, scenario in results["scenarios"].items():
        start = x
        target = scenario.get("target")
        for peer, ratio in scenario["ratios"].items():
            color = "tab:blue"  # bars the target is not about
            if peer == FLOOR:
                color = "lightgrey"  # below 1: how close jaxobs is to the memory-write lower bound
            elif target and peer == target["peer"]:
                color = "tab:green" if target["met"] else "tab:red"
            ax.bar(x, ratio, color=color, width=0.8)
            ax.text(x, ratio, f"{ratio:.2g}x", ha="center", va="bottom", fontsize=8)
            ticks.append(x)
            labels.append(peer)
            x += 1
        if target:
            ax.hlines(target["min_ratio"], start - 0.45, x - 0.55, colors="k", linestyles="--")
            ax.text(
                start - 0.45,
                target["min_ratio"],
                f"target {target['min_ratio']:g}x vs {target['peer']}",
                fontsize=7,
                va="bottom",
            )
        ax.annotate(
            name,
            xy=((start + x - 1) / 2, 0),
            xycoords=("data", "axes fraction"),
            xytext=(0, -24),
            textcoords="offset points",
            ha="center",
            va="top",
            fontweight="bold",
        )
        x += 0.7
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_yscale("log")
    ax.set_xticks(ticks, labels, fontsize=8)
    ax.set_ylabel("speedup: jaxobs / peer (plant-steps/s)")
    cfg = results["config"]
    ax.set_title(
        f"jaxobs Kalman throughput, B={cfg['batch']}, T={cfg['steps']}, n={N_STATES}, "
        f"float64, {results['environment']['device_kind']}"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--batch", type=int, default=1024, help="B: sequences / models / DAREs")
    parser.add_argument("--steps", type=int, default=1000, help="T: time steps per sequence")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds (the best of each peer is kept)")
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
        f"B={args.batch}, T={args.steps}, best of {args.repeats}"
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
            repeats=args.repeats,
            filterpy_sequences=args.filterpy_sequences,
            steady_state=steady,
        )
        results["scenarios"][name] = scenario
        print(format_scenario(f"{index}. {name}", scenario))

    dare_work = make_workload(args.seed, args.batch, 1, shared=False)
    results["scenarios"]["dare"] = dare_scenario(dare_work, repeats=args.repeats)
    print(format_scenario("4. dare", results["scenarios"]["dare"]))
    print(f"   max relative error vs scipy: {results['scenarios']['dare']['max_relative_error']:.3g}")

    if args.device_sweep:
        results["device_sweep"] = device_sweep(args.seed, args.steps, args.repeats)

    results["targets_met"] = {name: sc["target"]["met"] for name, sc in results["scenarios"].items()}
    print("\nsummary (ours/peer, target):")
    for name, scenario in results["scenarios"].items():
        target = scenario["target"]
        ratios = ", ".join(f"{peer} {r:.2f}x" for peer, r in scenario["ratios"].items())
        print(f"   {name:<13} {ratios:<55} target >= {target['min_ratio']:g}x {target['peer']}: {verdict(target)}")

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "kalman_throughput.json").write_text(json.dumps(results, indent=2))
    plot(results, args.out / "kalman_throughput.png")
    print(f"\nwrote {args.out / 'kalman_throughput.json'} and {args.out / 'kalman_throughput.png'}")
    return results


if __name__ == "__main__":
    main()
