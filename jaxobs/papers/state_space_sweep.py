"""Your own linear plant from a TOML block: its model, an LQG or AOB design on the nominal plant, and mismatch.

The ``[model]`` block gives continuous or discrete ``A``, ``B``, ``C``, ``D`` (entries numbers or expressions of the
``[parameters]``, so that a stiffness can appear in several entries), the sample time and the dead time; the
``[design]`` block the controller family (``lqg``: LQR and a steady-state Kalman filter; ``aob``: an AOB-N with the
same LQR on its plant states) designed on the nominal plant; each parameter its nominal value, unit and mismatch
range (uniform or log-uniform, relative or absolute); ``[noise]`` the sensor noise. Per configuration: validity,
stability and margins (:func:`jaxobs.stability.robustness_metrics`) and a closed-loop step response with sensor
noise; the generic report (:func:`jaxobs.sweep_report.write_report`). The default is a two-mass spring.
"""

from __future__ import annotations

import ast
import dataclasses
import itertools
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxobs._config import Expression, check_at_least, check_choice, check_range, expression, fail
from jaxobs.closed_loop import simulate
from jaxobs.design import dlqr, reference_gain
from jaxobs.lti import MAX_DELAY_SLOTS, StateSpace, c2d, n_delay_slots
from jaxobs.observers import FeedbackParams, observer_controller
from jaxobs.observers.active import active_observer_controller, feedback_gain, make_aob
from jaxobs.observers.kalman import kalman_filter, make_kalman
from jaxobs.papers.scenarios import Sweep, SweepScenario
from jaxobs.stability import check_nominal, robustness_metrics
from jaxobs.sweep_report import write_report

__all__ = [
    "NAME",
    "DEFAULT_CONFIG",
    "CONFIG_NOTES",
    "PARAMETER",
    "SCENARIO",
    "Model",
    "parse",
    "nominal_values",
    "design",
    "make_sweep",
    "report",
]

NAME = "state-space"

PARAMETER = {"nominal": 0.0, "unit": "", "range": [1.0, 1.0], "scale": "relative", "distribution": "uniform"}
"""The keys of one ``[parameters.NAME]`` table and their defaults (a parameter without ``range`` is not
mismatched)."""

DEFAULT_CONFIG = {
    "scenario": NAME,
    "seed": 0,
    "chunk_size": 2048,
    "configs": 10_000,
    "model": {
        "time": "continuous",
        "sample_time": 0.002,
        "dead_time": Expression("tau"),
        # a motor (q_m, v_m) driving a load (q_l, v_l) through a spring k with damping c; the load's position read
        "A": [[0, 1, 0, 0], ["-k/J_m", "-c/J_m", "k/J_m", "c/J_m"],
              [0, 0, 0, 1], ["k/J_l", "c/J_l", "-k/J_l", "-c/J_l"]],
        "B": [[0], ["1/J_m"], [0], [0]],
        "C": [[0, 0, 1, 0]],
        "D": [[0]],
        "output_unit": "rad",
        "input_unit": "N m",
    },
    "parameters": {
        "k": {**PARAMETER, "nominal": 100.0, "unit": "N m/rad", "range": [0.7, 1.3]},
        "J_m": {**PARAMETER, "nominal": 0.01, "unit": "kg m^2", "range": [0.7, 1.3]},
        "J_l": {**PARAMETER, "nominal": 0.02, "unit": "kg m^2", "range": [0.7, 1.3]},
        "c": {**PARAMETER, "nominal": 0.05, "unit": "N m s/rad"},
        "tau": {**PARAMETER, "nominal": 0.0015, "unit": "s", "range": [0.0005, 0.0035], "scale": "absolute"},
    },
    "design": {
        "family": "lqg",
        "dead_time": Expression("model"),
        "Q": [0.0, 0.0, 100.0, 0.0],
        "R": [1.0],
        "process_noise": [0.0, 1e-2, 0.0, 1e-2],
        "measurement_noise": [1e-6],
        "order": 1,
        "q_active": 1e-4,
    },
    "noise": {"sensor_std": [1e-4]},
    "simulation": {"duration": 0.5, "reference": [0.01]},
    "margins": {"num_points": 512},
}  # fmt: skip
"""The embedded default: a two-mass spring (4 states, 1.5 ms dead time at h = 2 ms) under LQG, stiffness and
inertias +-30 %, dead time 0.5-3.5 ms, 10 000 configurations."""

CONFIG_NOTES = {
    "configs": "number of configurations (true plants); a larger value extends a sweep in the same directory",
    "model": "the plant: x' = A x + B u(t - dead_time), y = C x + D u (time = 'continuous'), or x_{k+1} = A x_k + "
    "B u_{k-d}, y_k = C x_k with d = dead_time / sample_time rounded (time = 'discrete'); matrix entries are "
    "numbers or expressions (strings) of the parameters, with + - * / **, parentheses, pi, sqrt, exp, log, sin, "
    "cos, tan, abs",
    "model.time": "'continuous' (discretised exactly with the dead time, zero-order hold) or 'discrete'",
    "model.sample_time": "h (s): the controller's sample time (that of A, B for a discrete model)",
    "model.dead_time": "input dead time (s): a number or an expression of the parameters; the model holds the "
    "largest over the parameters' ranges",
    "model.A": "(n, n)",
    "model.B": "(n, m)",
    "model.C": "(p, n)",
    "model.D": "(p, m), zero: the loop needs a strictly proper plant",
    "model.output_unit": "the outputs' unit, for the report (the RMS error)",
    "model.input_unit": "the inputs' unit, for the report (the peak command)",
    "parameters": "[parameters.NAME]: nominal (the design's value), unit (for the report), range [low, high] of "
    "the true value (a factor on nominal with scale = 'relative', values with 'absolute'; [1, 1] relative: not "
    "mismatched), distribution 'uniform' or 'log-uniform'",
    "design": "the controller, designed on the nominal plant (nominal parameters and dead time)",
    "design.family": "'lqg' (LQR + steady-state Kalman filter) or 'aob' (an AOB-N, Cortesão 2006, with the LQR "
    "gain on its plant states and the active-state compensation)",
    "design.dead_time": "the dead time of the design's model (s): 'model' (the model's at the nominal parameters), "
    "or a number (0: a design that ignores the dead time) or an expression of the parameters",
    "design.Q": "LQR state weights (diagonal, one per state of A; the dead-time states weigh 0)",
    "design.R": "LQR input weights (diagonal, one per input)",
    "design.process_noise": "lqg: the Kalman filter's process noise variances (diagonal, one per state of A)",
    "design.measurement_noise": "the filter's measurement noise variances (diagonal, one per output)",
    "design.order": "aob: the order N of the active state (at least 1)",
    "design.q_active": "aob: the variance of the active state's last derivative (per input)",
    "noise": "the true sensor",
    "noise.sensor_std": "standard deviation of the sensor noise, one per output (in the outputs' units)",
    "simulation": "a closed-loop step response per configuration (with the sensor noise)",
    "simulation.duration": "simulated time (s); 0: no simulation",
    "simulation.reference": "the step on each output (a reference pre-gain for unit DC gain on the nominal "
    "plant: as many outputs as inputs)",
    "margins": "the margins of the loop cut at the plant input (jaxobs.stability.loop_transfer)",
    "margins.num_points": "frequency points of the margin search (at least 16)",
}

PARAMETER_NOTES = {
    "nominal": "the design's value",
    "unit": "its unit, for the report",
    "range": "[low, high] of the true value: a factor on nominal (scale 'relative'; [1, 1]: not mismatched) or "
    "values (scale 'absolute')",
    "scale": "'relative' or 'absolute'",
    "distribution": "'uniform' or 'log-uniform'",
}
CONFIG_NOTES |= {
    f"parameters.{name}.{field}": note
    for name in DEFAULT_CONFIG["parameters"]
    for field, note in PARAMETER_NOTES.items()
}

MATRICES = ("A", "B", "C", "D")


@dataclasses.dataclass(frozen=True)
class Model:
    """A parsed ``[model]``/``[parameters]`` block.

    Attributes:
      matrices: ``{"A": f, "B": f, "C": f, "D": f}``, ``f(values)`` the matrix at parameter values
        ``{name: value}`` (traceable).
      dead_time: ``dead_time(values)``, seconds.
      continuous: whether A, B are continuous-time (discretised with the dead time by :func:`jaxobs.lti.c2d`).
      h: the sample time (s).  n_delay: the dead-time slots for the largest dead time over the ranges.
      names: the parameters' names.
    """

    matrices: dict
    dead_time: object
    continuous: bool
    h: float
    n_delay: int
    names: tuple[str, ...]

    def plant(self, values: dict, n_delay: int | None = None, dead_time=None) -> StateSpace:
        """The discrete plant at ``values`` with its dead time (or ``dead_time``, seconds), in ``n_delay`` slots
        (default :attr:`n_delay`); its matrices are NaN for a dead time beyond them, and non-finite where a
        parameter makes them so."""
        n_delay = self.n_delay if n_delay is None else n_delay
        A, B, C, D = (self.matrices[name](values) for name in MATRICES)
        tau = jnp.asarray(self.dead_time(values) if dead_time is None else dead_time, A.dtype)
        if self.continuous:
            return c2d(StateSpace(A, B, C, D, None), self.h, tau, n_delay=n_delay)
        return _discrete_delay(A, B, C, tau / self.h, n_delay, self.h)


def _discrete_delay(A, B, C, samples, n_delay: int, h: float) -> StateSpace:
    """``x_{k+1} = A x_k + B u_{k-d}`` with ``d = round(samples)`` in state ``[x, u_{k-n_delay}, ..., u_{k-1}]``
    (oldest first, as :func:`jaxobs.lti.c2d`); NaN matrices for ``d`` beyond ``n_delay`` or below 0."""
    n, m = B.shape
    d = jnp.round(samples)
    lags = n_delay - jnp.arange(n_delay)  # slot i holds u_{k - (n_delay - i)}
    from_slots = jnp.concatenate([jnp.where(lag == d, B, 0.0) for lag in lags], axis=1) if n_delay else B[:, :0]
    Phi = jnp.block([[A, from_slots], [jnp.zeros((n_delay * m, n)), jnp.eye(n_delay * m, k=m)]])
    newest = jnp.eye(m) if n_delay else jnp.zeros((0, m))
    Gamma = jnp.concatenate([jnp.where(d == 0, B, 0.0), jnp.zeros((max(n_delay - 1, 0) * m, m)), newest])
    Cr = jnp.concatenate([C, jnp.zeros((C.shape[0], n_delay * m))], axis=1)
    out = (d < 0) | (d > n_delay)
    Phi, Gamma, Cr = (jnp.where(out, jnp.nan, M) for M in (Phi, Gamma, Cr))
    return StateSpace(Phi, Gamma, Cr, jnp.zeros((C.shape[0], m), Phi.dtype), h)


def _matrix(config: dict, source: str, name: str, names) -> tuple:
    """``(function values -> matrix, shape)`` of ``[model] name``."""
    rows = config["model"][name]
    cells = [[expression(source, f"model.{name}[{i}][{j}]", v, names) for j, v in enumerate(row)]
             for i, row in enumerate(rows)]  # fmt: skip
    return (lambda values: jnp.stack([jnp.stack([jnp.asarray(f(values), float) for f in r]) for r in cells])), (
        len(rows), len(rows[0]))  # fmt: skip


def _names_in(text: str) -> set:
    return {node.id for node in ast.walk(ast.parse(text.strip(), mode="eval")) if isinstance(node, ast.Name)}


def nominal_values(config: dict) -> dict:
    """``{parameter: nominal value}``."""
    return {name: p["nominal"] for name, p in config["parameters"].items()}


def _sample_ranges(config: dict) -> dict:
    """``{name: (low, high)}`` of each parameter's true value."""
    out = {}
    for name, p in config["parameters"].items():
        low, high = p["range"]
        out[name] = (low * p["nominal"], high * p["nominal"]) if p["scale"] == "relative" else (low, high)
    return out


def parse(config: dict, source: str) -> Model:
    """The :class:`Model` of ``config``'s ``[model]`` and ``[parameters]``; a :class:`jaxobs._config.ConfigError`
    names the key of a bad shape, name or value."""
    names = tuple(config["parameters"])
    for name in names:
        if not name.isidentifier() or name == "pi":
            fail(source, f"parameters.{name}", "a parameter's name must be a Python identifier other than pi")
    built = {name: _matrix(config, source, name, names) for name in MATRICES}
    (n, n2), (nb, m), (p, nc), (pd, md) = (built[name][1] for name in MATRICES)
    sizes = f"(A {n}x{n2}, B {nb}x{m}, C {p}x{nc}, D {pd}x{md})"
    for key, bad, want in (("A", n2 != n, "square"), ("B", nb != n, f"{n} rows, one per state"),
                           ("C", nc != n, f"{n} columns, one per state"),
                           ("D", (pd, md) != (p, m), f"{p}x{m}: a row per output, a column per input")):  # fmt: skip
        if bad:
            fail(source, f"model.{key}", f"must be {want} {sizes}")
    h = config["model"]["sample_time"]
    text = config["model"]["dead_time"]
    dead_time = expression(source, "model.dead_time", text, names)
    ranges, nominal = _sample_ranges(config), nominal_values(config)
    used = [k for k in names if isinstance(text, str) and k in _names_in(text)]  # the corners of what it reads
    corners = [nominal | dict(zip(used, c, strict=True)) for c in itertools.product(*(ranges[k] for k in used))]
    largest = max(float(dead_time(v)) for v in [nominal, *corners])
    if not math.isfinite(largest) or n_delay_slots(largest, h) > MAX_DELAY_SLOTS:
        fail(source, "model.dead_time", f"the largest dead time over the ranges, {largest:.4g} s, needs more than "
                                        f"{MAX_DELAY_SLOTS} samples of {h} s")  # fmt: skip
    continuous = config["model"]["time"] == "continuous"
    n_delay = n_delay_slots(largest, h) if continuous else max(0, round(largest / h))
    return Model({k: built[k][0] for k in MATRICES}, dead_time, continuous, h, n_delay, names)


def _check_parameters(config: dict, source: str) -> None:
    if not config["parameters"]:
        fail(source, "parameters", "name at least one parameter ([parameters.NAME] with nominal = ...)")
    for name, p in config["parameters"].items():
        key = f"parameters.{name}"
        check_choice(config, source, f"{key}.scale", ("relative", "absolute"))
        check_choice(config, source, f"{key}.distribution", ("uniform", "log-uniform"))
        check_range(config, source, f"{key}.range", allow_point=True)
        low, high = _sample_ranges(config)[name]
        if p["distribution"] == "log-uniform" and not 0 < low:
            fail(source, f"{key}.range", f"a log-uniform range must be positive, got true values {low:g} to {high:g}")
        if p["scale"] == "relative" and p["nominal"] == 0 and p["range"][0] != p["range"][1]:
            fail(source, f"{key}.range", "a relative range of a zero nominal value is a point; use scale = 'absolute'")


def _check_sizes(config: dict, source: str, n: int, m: int, p: int) -> None:
    """The design, noise and simulation lists against the model's ``n`` states, ``m`` inputs, ``p`` outputs."""
    for key, size, positive in (("design.Q", n, False), ("design.R", m, True), ("design.process_noise", n, False),
                                ("design.measurement_noise", p, True), ("noise.sensor_std", p, False),
                                ("simulation.reference", p, False)):  # fmt: skip
        *table, last = key.split(".")
        value = config[table[0]][last]
        if len(value) != size:
            fail(source, key, f"needs {size} entries (one per {'state input output'.split()[(n, m, p).index(size)]}"
                              f" of the model), got {value!r}")  # fmt: skip
        if any(v < 0 or (positive and v == 0) for v in value) and key != "simulation.reference":
            fail(source, key, f"entries must be {'positive' if positive else 'non-negative'}, got {value!r}")
    if config["simulation"]["duration"] > 0 and p != m:
        fail(source, "simulation.reference", f"the step's pre-gain needs as many outputs as inputs ({p} and {m}); "
                                             "set simulation.duration = 0 to run no simulation")  # fmt: skip


def _check(config: dict, source: str) -> None:
    """Raise a :class:`jaxobs._config.ConfigError` naming the key of a bad value of the merged ``config``."""
    check_choice(config, source, "model.time", ("continuous", "discrete"))
    check_choice(config, source, "design.family", ("lqg", "aob"))
    for key, low in (("seed", 0), ("chunk_size", 1), ("configs", 1), ("design.order", 1), ("margins.num_points", 16),
                     ("simulation.duration", 0)):  # fmt: skip
        check_at_least(config, source, key, low)
    for key in ("model.sample_time", "design.q_active"):
        check_at_least(config, source, key, 0, strict=True)
    _check_parameters(config, source)
    model = parse(config, source)
    nominal = nominal_values(config)
    A, B, C, D = (np.asarray(model.matrices[name](nominal)) for name in MATRICES)
    for name, M in zip(MATRICES, (A, B, C, D), strict=True):
        if not np.isfinite(M).all():
            fail(source, f"model.{name}", "is not finite at the nominal parameters")
    if np.any(D != 0):
        fail(source, "model.D", "must be zero: a feedthrough closes an algebraic loop through the command")
    if not float(model.dead_time(nominal)) >= 0:
        fail(source, "model.dead_time", "must be at least 0 at the nominal parameters")
    if config["design"]["dead_time"] != "model":
        expression(source, "design.dead_time", config["design"]["dead_time"], model.names)
    _check_sizes(config, source, A.shape[0], B.shape[1], C.shape[0])


def design(config: dict, model: Model):
    """``(controller, params)`` of ``[design]`` on the nominal plant (nominal parameters, the nominal dead time's
    slots); a design that fails (no stabilising LQR or filter) is a :class:`jaxobs._config.ConfigError`."""
    nominal, d = nominal_values(config), config["design"]
    source = "the nominal design"
    assumed = "model" if d["dead_time"] == "model" else expression(source, "design.dead_time", d["dead_time"], nominal)
    tau = float((model.dead_time if assumed == "model" else assumed)(nominal))
    if not 0 <= tau <= MAX_DELAY_SLOTS * model.h:
        fail(source, "design.dead_time", f"must be between 0 and {MAX_DELAY_SLOTS} samples, got {tau:g} s")
    plant = model.plant(nominal, n_delay=_slots(model, tau), dead_time=tau)
    n_plant = len(d["Q"])
    pad = lambda diagonal: jnp.diag(jnp.pad(jnp.asarray(diagonal, float), (0, plant.n_states - n_plant)))
    try:
        L = dlqr(plant.A, plant.B, pad(d["Q"]), jnp.diag(jnp.asarray(d["R"], float)))[0]
    except ValueError as exc:
        fail(source, "design.Q", f"the LQR design failed: {exc}")
    N = reference_gain(plant, L) if config["simulation"]["duration"] > 0 else None
    V = jnp.diag(jnp.asarray(d["measurement_noise"], float))
    try:
        if d["family"] == "lqg":
            kf = make_kalman(plant.A, plant.C, pad(d["process_noise"]), V, Gamma=plant.B, steady_state=True)
            return observer_controller(kalman_filter), FeedbackParams(kf, L, N)
        aob = make_aob(plant, d["order"], V, q_active=d["q_active"], steady_state=True)
    except ValueError as exc:
        fail(source, "design.process_noise" if d["family"] == "lqg" else "design.q_active", f"the filter failed: {exc}")
    return active_observer_controller, FeedbackParams(aob, feedback_gain(aob, L), N)


def _slots(model: Model, dead_time: float) -> int:
    return n_delay_slots(dead_time, model.h) if model.continuous else max(0, round(dead_time / model.h))


def _sampler(config: dict):
    """``sampler(key, index)``: each mismatched parameter from its range, and the sensor noise's key."""
    ranges = _sample_ranges(config)
    swept = {name: ranges[name] for name, p in config["parameters"].items() if ranges[name][0] != ranges[name][1]}
    log = {name: config["parameters"][name]["distribution"] == "log-uniform" for name in swept}

    def sampler(key, index):
        keys = jax.random.split(key, len(swept) + 1)
        values = {}
        for k, (name, (low, high)) in zip(keys, swept.items(), strict=False):
            if log[name]:
                values[name] = jnp.exp(jax.random.uniform(k, minval=math.log(low), maxval=math.log(high)))
            else:
                values[name] = jax.random.uniform(k, minval=low, maxval=high)
        return values | {"noise_key": keys[-1]}  # a key: it reaches evaluate, not the rows

    return sampler


def make_sweep(config: dict) -> Sweep:
    """The sweep of ``config``: the design on the nominal plant (with a warning where it is not stable there) and
    per configuration the true plant's :func:`jaxobs.stability.robustness_metrics`, then the RMS error and the
    peak command of a step response with sensor noise (NaN where invalid, inf where it diverges)."""
    model = parse(config, "the config")
    controller, params = design(config, model)
    nominal = nominal_values(config)
    check_nominal(model.plant(nominal), controller, params, what=f"the {config['design']['family']} design",
                  num_points=config["margins"]["num_points"])  # fmt: skip
    steps = int(round(config["simulation"]["duration"] / model.h))
    reference = jnp.asarray(config["simulation"]["reference"], float)
    std = jnp.asarray(config["noise"]["sensor_std"], float)

    def evaluate(p):
        values = nominal | {k: v for k, v in p.items() if k != "noise_key"}
        true = model.plant(values)
        row = robustness_metrics(true, controller, params, valid=model.dead_time(values) >= 0,
                                 num_points=config["margins"]["num_points"])  # fmt: skip
        if not steps:
            return row
        noise = std * jax.random.normal(p["noise_key"], (steps, std.size))
        trace = simulate(true, controller, params, jnp.broadcast_to(reference, (steps, reference.size)), noise=noise)
        error, peak = jnp.sqrt(jnp.mean((trace.y_true - reference) ** 2)), jnp.max(jnp.abs(trace.u))
        finite = lambda v: jnp.where(row["valid"], jnp.where(jnp.isfinite(v), v, jnp.inf), jnp.nan)
        return row | {"rms_error": finite(error), "peak_command": finite(peak)}

    return Sweep(_sampler(config), evaluate, config["configs"])


def report(config: dict, out_dir: Path, result=None, context=None) -> dict:
    """The generic report (:func:`jaxobs.sweep_report.write_report`) with the parameters' units."""
    units = {name: p["unit"] for name, p in config["parameters"].items() if p["unit"]}
    units |= {"rms_error": config["model"]["output_unit"], "peak_command": config["model"]["input_unit"]}
    title = f"Robustness sweep: {config['design']['family'].upper()} on the nominal state-space plant"
    return write_report(out_dir, title=title, units=units, result=result)


SCENARIO = SweepScenario(
    name=NAME,
    summary=__doc__,
    defaults=DEFAULT_CONFIG,
    notes=CONFIG_NOTES,
    check=_check,
    build=make_sweep,
    report=report,
    open_tables={"parameters": PARAMETER},
    size_key="configs",
    size_keys=("configs", "simulation.duration", "margins.num_points"),
)
