"""Every public function keeps its promises: one parametrised test over the whole API.

For each function and estimator in ``jaxobs.__all__`` and in the ``__all__`` of every public module (papers and cli
aside), its entry in tests/api_registry/ gives one small valid call; the test checks eager = ``jit``, ``vmap`` over
perturbed inputs = a Python loop, reverse-mode gradients = central differences along a random direction, float32 in
gives float32 out (or a ``ValueError``), Python lists and scalars accepted where an array is, and an undocumented
leading batch axis refused with a ``ValueError`` naming the argument. Design-time functions run eagerly and say so
under ``jit``; the exempt names (jobs, validators, loaders, transformations) are listed on docs/capabilities.md. A
public name with neither an entry nor an exemption fails, saying what to add; a name not audited yet (``PENDING`` of
its registry file, empty today) is an expected failure, listed on the capabilities page.

Budget: the default suite runs the whole test in ~60 s of CPU on one core. It shares compiled programs (the
central differences and the loop of the vmap check run on the jit check's program; nested lists are traced, not
run), uses small inputs, one vmap batch of 3 and one random direction for the central differences. The entries
that still cost more than ~0.65 s of CPU each on a warm compilation cache run only in the slow suite, each with its
reason (``slow(...)`` in its registry file): the Riccati-based designs (lqe, dlqe, lqr, care, the steady-state gains
and the designs built on them), the estimators over a record whose scans are the largest programs (particle,
ensemble, H-infinity, unscented, modular, Gramian, high-gain, the AOB and its controller, the smoother and the
parallel filter, EM, sampling, NEES/whiteness, resampling), the closed loop and the stability margins, c2d,
force_plant and the Bierman update, the saturation chapter's designs, simulations and window tests, the vehicle
observers, simulator and sensors, and the MJX physics (steps, solves, rollouts of a loaded model).
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxobs
from jaxobs.observers.base import Controller, Estimator
from tests import ROOT
from tests.api_registry import EXEMPT, EXEMPTIONS, PENDING, REGISTRY, Design, Example, file_of

# --------------------------------------------------------------------------------------------
# The public names


def _public_modules() -> list[str]:
    names = ["jaxobs"]
    for info in pkgutil.walk_packages(jaxobs.__path__, "jaxobs."):
        parts = info.name.split(".")
        if parts[1] in ("papers", "cli") or any(p.startswith("_") for p in parts):
            continue
        names.append(info.name)
    return names


def _computes(obj) -> bool:
    """A function (or jitted, custom-derivative callable) or an estimator/controller: what needs an entry."""
    if isinstance(obj, (Estimator, Controller)):
        return True
    return callable(obj) and not inspect.isclass(obj) and not inspect.ismodule(obj)


def public_functions() -> dict[str, list[str]]:
    """``home key -> the names it is exported as`` for every public function and estimator; the home is the
    deepest public module that exports the object (``jaxobs.dare`` -> ``jaxobs.matrix_equations.dare``)."""
    exported: dict[int, list[tuple[str, str]]] = {}
    for module_name in _public_modules():
        module = importlib.import_module(module_name)
        for name in getattr(module, "__all__", ()):
            obj = getattr(module, name)
            if _computes(obj):
                exported.setdefault(id(obj), []).append((module_name, name))
    homes = {}
    for places in exported.values():
        module_name, name = max(places, key=lambda place: (place[0].count("."), place[0]))
        homes[f"{module_name}.{name}"] = sorted(f"{m}.{n}" for m, n in places)
    return dict(sorted(homes.items()))


PUBLIC = public_functions()


def _params():
    for key in PUBLIC:
        entry = REGISTRY.get(key)
        marks = [pytest.mark.slow] if entry is not None and entry.slow else []
        if key in PENDING:
            marks.append(pytest.mark.xfail(strict=True, reason=PENDING[key]))
        yield pytest.param(key, id=key, marks=marks)


def _resolve(key: str):
    module_name, name = key.rsplit(".", 1)
    return getattr(importlib.import_module(module_name), name)


def _missing_message(key: str) -> str:
    short = key.rsplit(".", 1)[1]
    return (
        f"{key} (exported as {', '.join(PUBLIC[key])}) has no entry in the registry. Add to ENTRIES in "
        f"{file_of(key)}:\n"
        f'    "{key}": Example(lambda: dict({short}_args...), diff="<argument to differentiate>"),\n'
        f"(Example's skip={{check: reason}} for promises it does not make; Design(...) for a design-time NumPy "
        f"function), or exempt it in EXEMPT of that file with a reason starting with one of {sorted(EXEMPTIONS)} "
        f"and list it under 'Transformation promises' in docs/capabilities.md."
    )


# --------------------------------------------------------------------------------------------
# Arrays, perturbations and comparisons


def _is_array(x) -> bool:
    return isinstance(x, (np.ndarray, np.generic, jax.Array))


def _dynamic(value) -> bool:
    """An argument that is traced: an array or a pytree holding arrays (not a Python scalar, string, function)."""
    if _is_array(value):
        return True
    if value is None or isinstance(value, (str, bool, int, float, complex, Estimator, Controller)):
        return False
    return any(_is_array(leaf) for leaf in jax.tree_util.tree_leaves(value))


def _is_key(x) -> bool:
    return isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key)


def _floating(x) -> bool:
    return _is_array(x) and jnp.issubdtype(jnp.result_type(x), jnp.floating)


def _rng(*labels) -> np.random.Generator:
    return np.random.default_rng(zlib.crc32("/".join(map(str, labels)).encode()))


def _direction(x, kind: str, rng):
    """A perturbation direction of the floating leaf ``x``: of its size, symmetric for a symmetric matrix (on the
    support of its diagonal, so a semidefinite covariance stays one), ``x`` itself for ``"scale"``."""
    x = np.asarray(x)
    if kind == "scale":
        return np.where(np.isfinite(x), x, 0.0)  # infinite bounds stay where they are
    scale = max(float(np.max(np.abs(x))) if x.size else 1.0, 1e-3)
    d = rng.standard_normal(x.shape) * scale
    if x.ndim >= 2 and x.shape[-1] == x.shape[-2] and np.allclose(x, np.swapaxes(x, -1, -2)):
        support = np.diagonal(x, axis1=-2, axis2=-1) != 0
        d = 0.5 * (d + np.swapaxes(d, -1, -2)) * (support[..., :, None] & support[..., None, :])
    return d


def _directions(value, kind: str, label: str):
    rng = _rng(label)
    return jax.tree_util.tree_map(lambda x: _direction(x, kind, rng) if _floating(x) else None, value)


def _moved(value, directions, t):
    """``value + t * direction`` on the floating leaves."""
    return jax.tree_util.tree_map(
        lambda x, d: x if d is None else (np.asarray(x) + t * d).astype(np.asarray(x).dtype),
        value,
        directions,
        is_leaf=lambda x: x is None,
    )


def _members(value, kind: str, label: str, count: int = 3) -> list:
    """``count`` perturbed copies of ``value`` (other PRNG keys for ``"key"``)."""
    if kind == "key":
        return [jax.random.fold_in(value, i + 1) for i in range(count)]
    directions = _directions(value, kind, label)
    return [_moved(value, directions, t) for t in (-1e-3, 1e-3, 2e-3)[:count]]


def _stack(members):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *members)


def _assert_close(got, want, rtol: float, what: str):
    got_leaves, want_leaves = jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(want), f"{what}: other structure"
    for i, (g, w) in enumerate(zip(got_leaves, want_leaves, strict=True)):
        g, w = (np.asarray(jax.random.key_data(a) if _is_key(a) else a) for a in (g, w))
        assert g.shape == w.shape, f"{what}: output leaf {i} has shape {g.shape}, expected {w.shape}"
        if w.dtype == object:  # a design's non-array part (e.g. a symbolic structure): equal as printed
            assert repr(g) == repr(w), f"{what}: output leaf {i} differs"
        elif np.issubdtype(w.dtype, np.inexact):
            scale = max(float(np.max(np.abs(w[np.isfinite(w)]), initial=0.0)), 1e-300)
            np.testing.assert_allclose(g, w, rtol=0, atol=rtol * scale, err_msg=f"{what}: output leaf {i}")
        else:
            np.testing.assert_array_equal(g, w, err_msg=f"{what}: output leaf {i}")


# --------------------------------------------------------------------------------------------
# The call of an entry


class Call:
    """The entry's call split into traced arrays (``dynamic``) and static settings."""

    def __init__(self, key: str, entry):
        self.key, self.entry, self.fn = key, entry, _resolve(key)
        args = entry.args()
        self.static = {k: v for k, v in args.items() if not _dynamic(v)}
        self.dynamic = {k: v for k, v in args.items() if _dynamic(v)}
        assert self.dynamic, f"{key}: the example has no array argument"
        names = list(self.dynamic)
        self.diff = getattr(entry, "diff", None) or getattr(entry, "traced", None) or names[0]
        assert self.diff in self.dynamic, f"{key}: {self.diff!r} is not an array argument of the example"

    def __call__(self, dynamic: dict):
        args = {**self.static, **dynamic}
        call = getattr(self.entry, "call", None)
        return call(self.fn, **args) if call is not None else self.fn(**args)

    def of(self, x):
        """The call as a function of the ``diff`` argument."""
        return self({**self.dynamic, self.diff: x})


def _float_outputs(out) -> list:
    return [leaf for leaf in jax.tree_util.tree_leaves(out) if _floating(leaf)]


def _loss(call: Call, weights):
    select = call.entry.out or (lambda out: out)

    def loss(x):
        leaves = _float_outputs(select(call.of(x)))
        return sum(jnp.sum(w * leaf) for w, leaf in zip(weights, leaves, strict=True))

    return loss


# --------------------------------------------------------------------------------------------
# The checks


def _check_jit(call: Call, eager):
    _assert_close(jax.jit(call)(call.dynamic), eager, call.entry.rtol, f"{call.key}: jit vs eager")


def _check_vmap(call: Call):
    members = _members(call.dynamic[call.diff], call.entry.tangent, call.key)
    single = jax.jit(call)  # the program of the jit check: the loop compiles nothing new
    looped = _stack([single({**call.dynamic, call.diff: m}) for m in members])
    batched = jax.jit(jax.vmap(call.of))(_stack(members))
    _assert_close(batched, looped, call.entry.rtol, f"{call.key}: vmap over {call.diff} vs a loop")


def _weighted(leaves, weights) -> float:
    return sum(float(np.sum(w * np.asarray(leaf))) for w, leaf in zip(weights, leaves, strict=True))


def _check_grad(call: Call, eager):
    """Reverse mode against central differences along a random direction (the differences on the program of
    the jit check, so only the gradient compiles)."""
    select = call.entry.out or (lambda out: out)
    rng = _rng(call.key, "weights")
    weights = [rng.standard_normal(np.shape(leaf)) for leaf in _float_outputs(select(eager))]
    assert weights, f"{call.key}: no floating output to differentiate"
    x = call.dynamic[call.diff]
    directions = _directions(x, call.entry.tangent, call.key + "/grad")
    single, h = jax.jit(call), call.entry.fd_step
    values = [_weighted(_float_outputs(select(single({**call.dynamic, call.diff: _moved(x, directions, t)}))), weights)
              for t in (h, -h)]  # fmt: skip
    central = (values[0] - values[1]) / (2 * h)
    gradient = jax.jit(jax.grad(_loss(call, weights), allow_int=True))(x)
    pairs = zip(jax.tree_util.tree_leaves(gradient), jax.tree_util.tree_structure(x).flatten_up_to(directions),
                strict=True)  # fmt: skip
    reverse = sum(float(np.vdot(np.asarray(g), d)) for g, d in pairs if d is not None)
    size = _weighted([np.abs(leaf) for leaf in _float_outputs(select(eager))], [np.abs(w) for w in weights])
    assert np.isfinite(reverse), f"{call.key}: non-finite gradient in {call.diff}"
    assert abs(reverse - central) <= call.entry.grad_rtol * (abs(central) + 1e-2 * size), (
        f"{call.key}: reverse mode {reverse!r} vs central differences {central!r} (direction in {call.diff})"
    )


def _float32(value):
    return jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32) if _floating(x) else x, value)


def _check_float32(call: Call):
    try:
        out = jax.eval_shape(call, _float32(call.dynamic))
    except ValueError as refusal:  # a clear refusal: it names the precision
        assert re.search(r"float32|float64|precision|dtype", str(refusal)), f"{call.key}: float32: {refusal}"
        return
    wide = [leaf.dtype for leaf in jax.tree_util.tree_leaves(out)
            if jnp.issubdtype(leaf.dtype, jnp.float64) and not leaf.weak_type]  # fmt: skip
    assert not wide, f"{call.key}: float32 inputs gave float64 outputs"


def _as_lists(value):
    if isinstance(value, (np.ndarray, np.generic)) and value.dtype.kind == "f":
        return value.tolist()  # nested lists, or a Python float for a 0-d array
    return value


def _shapes(out) -> list:
    """The shape and dtype of each leaf (the dtype of arrays only: a Python number's is its tracer's)."""
    return [(tuple(np.shape(leaf)), getattr(leaf, "dtype", None) if _is_array(leaf) or hasattr(leaf, "dtype") else None)
            for leaf in jax.tree_util.tree_leaves(out)]  # fmt: skip


def _check_lists(call: Call, eager):
    """Nested lists (and Python floats) where the example has NumPy arrays give the outputs' shapes and dtypes:
    traced, not run (a run would compile the function once more; the values come from the same conversion)."""
    listed = {k: _as_lists(v) for k, v in call.dynamic.items()}
    if all(listed[k] is call.dynamic[k] for k in listed):
        return  # no NumPy array argument
    got = jax.eval_shape(lambda: call(listed))  # concrete lists, as an eager caller passes them
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(eager), f"{call.key}: lists: structure"
    for (shape, dtype), (want_shape, want_dtype) in zip(_shapes(got), _shapes(eager), strict=True):
        assert shape == want_shape and (want_dtype is None or dtype == want_dtype), (
            f"{call.key}: nested lists give {shape} {dtype} where arrays give {want_shape} {want_dtype}"
        )
    lists = {k: v for k, v in listed.items() if isinstance(v, list)}
    if lists:  # traced: lists of tracers, as jit passes a list argument
        jax.eval_shape(lambda a: call({**call.dynamic, **a}), lists)


def _check_batch(call: Call):
    """An undocumented leading batch axis on any array argument is refused, naming it; the documented ones
    (``batched``) together give the loop over their members."""
    for name, value in call.dynamic.items():
        if name in call.entry.batched or (call.entry.tangent == "key" and name == call.diff):
            continue
        batched = jax.tree_util.tree_map(lambda x: jnp.stack([x] * 2), value)
        with pytest.raises(ValueError) as refusal:
            jax.eval_shape(lambda a, name=name: call({**call.dynamic, name: a}), batched)
            pytest.fail(f"{call.key}: a batch axis on {name} was not refused")
        message = str(refusal.value)
        assert re.search(rf"\b{re.escape(name)}\b", message), (
            f"{call.key}: a batch axis on {name} raised a ValueError that does not name it: {message}"
        )
    if call.entry.batched:
        perturbed = {name: _members(call.dynamic[name], call.entry.tangent, f"{call.key}/{name}")
                     for name in call.entry.batched}  # fmt: skip
        members = [{name: values[i] for name, values in perturbed.items()} for i in range(3)]
        looped = _stack([call({**call.dynamic, **member}) for member in members])
        _assert_close(call({**call.dynamic, **_stack(members)}), looped, call.entry.rtol,
                      f"{call.key}: a batch of {call.entry.batched} vs a loop")  # fmt: skip


def _check_example(call: Call):
    entry: Example = call.entry
    eager = call(call.dynamic)
    for i, leaf in enumerate(_float_outputs((entry.out or (lambda out: out))(eager))):
        assert not np.any(np.isnan(np.asarray(leaf))), f"{call.key}: the example's output leaf {i} has NaN entries"
    checks = {
        "jit": lambda: _check_jit(call, eager),
        "vmap": lambda: _check_vmap(call),
        "grad": lambda: _check_grad(call, eager),
        "float32": lambda: _check_float32(call),
        "lists": lambda: _check_lists(call, eager),
        "batch": lambda: _check_batch(call),
    }
    for name, check in checks.items():
        if name not in entry.skip:
            check()


def _check_design(call: Call):
    design: Design = call.entry
    eager = call(call.dynamic)
    listed = {k: _as_lists(v) for k, v in call.dynamic.items()}
    _assert_close(call(listed), eager, 1e-9, f"{call.key}: nested lists vs arrays")
    with pytest.raises(ValueError) as refusal:
        jax.jit(call.of)(call.dynamic[call.diff])
    message = str(refusal.value)
    name = call.key.rsplit(".", 1)[1]
    assert "\n" not in message and name in message and "design-time" in message, f"{call.key}: under jit: {message}"
    assert design.alternative in message, f"{call.key}: the refusal does not name {design.alternative}"


# --------------------------------------------------------------------------------------------
# The test


def _capabilities_exemptions() -> str:
    text = (ROOT / "docs" / "capabilities.md").read_text(encoding="utf-8")
    return text.split("## Transformation promises", 1)[-1].split("\n## ", 1)[0]


@pytest.mark.parametrize("key", list(_params()))
def test_public_function_keeps_its_promises(key):
    entry, exemption = REGISTRY.get(key), EXEMPT.get(key)
    if key in PENDING:
        assert f"`{key}`" in _capabilities_exemptions(), f"{key} is pending but not listed in docs/capabilities.md"
    assert entry is not None or exemption is not None, _missing_message(key)
    assert entry is None or exemption is None, f"{key} has both an entry and an exemption"
    if exemption is not None:
        kind = exemption.split(":", 1)[0]
        assert kind in EXEMPTIONS, f"{key}: the exemption must start with one of {sorted(EXEMPTIONS)}: {exemption}"
        assert f"`{key}`" in _capabilities_exemptions(), (
            f"{key} is exempt ({exemption}) but not listed under 'Transformation promises' in docs/capabilities.md"
        )
        return
    call = Call(key, entry)
    if isinstance(entry, Design):
        _check_design(call)
    else:
        _check_example(call)


def test_every_entry_and_exemption_is_a_public_name():
    """No stale entry: each registered key is a public function's home (renamed or removed names fail here)."""
    stale = sorted((set(REGISTRY) | set(EXEMPT) | set(PENDING)) - set(PUBLIC))
    assert not stale, f"registry entries or exemptions for names that are not public (or not their home): {stale}"
