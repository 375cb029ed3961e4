"""The registry of examples behind tests/test_api_promises.py: one entry per public function of jaxobs.

Every name in ``jaxobs.__all__`` and in the ``__all__`` of each public module (``jaxobs.papers`` and
``jaxobs.cli`` aside) is either

* a class, a constant or a submodule (exempt by kind: they hold data, they compute nothing), or
* a function or an estimator with an :class:`Example` here: one small valid call, from which the test checks
  the promises of the library (eager = ``jit``, ``vmap`` over perturbed inputs = a Python loop, gradients =
  central differences, float32 in gives float32 out or a clear refusal, Python lists and scalars accepted where
  an array is, an undocumented leading batch axis refused with a ``ValueError`` naming the argument), or
* a design-time function with a :class:`Design` entry (NumPy/SciPy/sympy on concrete arrays: it works eagerly,
  takes lists, and under ``jit`` says in one line that it is design-time), or
* exempt with a reason in the ``EXEMPT`` dict of its file (:data:`EXEMPTIONS`: jobs, validators, loaders,
  function transformations), listed on docs/capabilities.md, or
* pending (``PENDING`` of its file, with the reason): not audited yet. Its test is an expected failure (strict: once
  an entry exists, the name must leave ``PENDING``), and the capabilities page lists it as not yet checked.

The entries live in one file per part of the package (:data:`FILES`), keyed by the name's home (the module that
defines it; a re-export such as ``jaxobs.dare`` is covered by ``jaxobs.matrix_equations.dare``).

Adding a public name (the test's failure message says the same): in the file of :data:`FILES` for its module, add
to ``ENTRIES``::

    "jaxobs.mjx.manifold.retract": Example(
        lambda: dict(manifold=_so3(), x=X0, v=np.array([0.1, -0.2, 0.3])),  # one small valid call, lazily built
        diff="v",  # the argument that vmap perturbs and grad differentiates (default: the first array)
        skip={"batch": "x may carry leading batch axes (documented)"},  # a promise not made, with the reason
    ),

``batched=("x",)`` instead of that skip when a documented batch must equal the loop; ``tangent="scale"`` for a
pytree of parameters (a random direction would break their validity); ``out=`` to differentiate part of the output;
``slow(ENTRIES, why, *keys)`` (:func:`slow`) only for what costs more than ~0.65 s of CPU on a warm compilation
cache. An estimator's entry runs it over a record (``call=``, see ``estimator`` in observers.py). A design-time
NumPy function gets ``Design(lambda: dict(...))`` and the ``@_checks.design_time()`` decorator; a job, validator,
loader, transformation or static helper an ``EXEMPT`` reason starting with its kind (:data:`EXEMPTIONS`), listed
under "Transformation promises" on docs/capabilities.md.
Run ``pytest -n 0 tests/test_api_promises.py -k NAME``: a failing check is a defect of the function to fix (a shape
check naming the argument, lists through ``_checks.float_arrays``, a derivative), not a reason to skip.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

CHECKS = ("jit", "vmap", "grad", "float32", "lists", "batch")
"""The promises checked for an :class:`Example`; ``skip`` names those that do not apply, each with the reason."""


@dataclasses.dataclass(frozen=True)
class Example:
    """One valid call of a public function (or estimator) and what it promises.

    Attributes:
      args: builds the keyword arguments of the call (lazily: designs are built when the test runs, not on
        import). NumPy/JAX arrays (0-d included) and pytrees of them are the call's arrays: traced under ``jit``,
        cast for float32, given as lists and with a batch axis; Python scalars, strings, functions and ``None``
        are static settings.
      diff: the argument that is perturbed for ``vmap`` and differentiated (``None``: the first array argument).
      tangent: how ``diff`` is perturbed: ``"random"`` (a random direction; symmetric for a symmetric matrix,
        kept on the support of its diagonal), ``"scale"`` (every floating leaf scaled: for pytrees of parameters
        such as a filter's, whose validity a random direction would break), ``"key"`` (PRNG keys: other keys).
      call: ``call(fn, **args)`` when the call is not ``fn(**args)`` (an estimator: ``run`` over a record).
      out: the differentiated part of the output (default: every floating leaf).
      batched: arguments documented to take leading batch axes: a batch must equal the loop over its members.
      skip: ``{check: reason}`` for the promises of :data:`CHECKS` that the function does not make.
      slow: why the entry runs only in the slow suite (empty: the default suite); see :func:`slow`.
      rtol: tolerance of the eager/jit/vmap comparisons (relative to each output's largest entry).
      grad_rtol: tolerance of the gradient against central differences.
      fd_step: the step of the central differences, relative to the direction (which has the size of ``diff``).
    """

    args: Callable[[], dict]
    diff: str | None = None
    tangent: str = "random"
    call: Callable | None = None
    out: Callable | None = None
    batched: tuple[str, ...] = ()
    skip: Mapping[str, str] = dataclasses.field(default_factory=dict)
    slow: str = ""
    rtol: float = 1e-9
    grad_rtol: float = 1e-6
    fd_step: float = 1e-5

    def __post_init__(self):
        unknown = set(self.skip) - set(CHECKS)
        if unknown:
            raise ValueError(f"skip names unknown checks {sorted(unknown)}; the checks are {CHECKS}")
        if self.tangent not in ("random", "scale", "key"):
            raise ValueError(f"tangent must be 'random', 'scale' or 'key', got {self.tangent!r}")


@dataclasses.dataclass(frozen=True)
class Design:
    """A design-time function (NumPy/SciPy/sympy on concrete values): it runs eagerly on ``args`` (also given as
    nested lists), and under ``jit`` raises a ``ValueError`` saying it is design-time (one line naming the function;
    ``alternative``, when given, must appear in it: the traceable function to use instead).

    Attributes:
      args: builds the keyword arguments of one valid call.
      traced: the argument traced under ``jit`` for the refusal (default: the first array argument).
      alternative: the traceable alternative that the refusal names, if any.
      slow: why it runs only in the slow suite (empty: the default suite).
    """

    args: Callable[[], dict]
    traced: str | None = None
    alternative: str = ""
    slow: str = ""


def slow(entries: dict, reason: str, *keys: str) -> dict:
    """``entries`` with those of ``keys`` run only in the slow suite, for ``reason``.

    The default suite's budget for the whole test is ~60 s of CPU on one core; an entry whose checks cost more than
    ~0.65 s of CPU on a warm compilation cache (measured per entry: a solver with an implicit derivative, a loop over
    a record or a frequency grid, compiled for eager, ``jit``, ``vmap`` and ``grad``) goes to the slow suite."""
    unknown = set(keys) - set(entries)
    if unknown:
        raise ValueError(f"slow: no such entries {sorted(unknown)}")
    return {key: dataclasses.replace(e, slow=reason) if key in keys else e for key, e in entries.items()}


EXEMPTIONS = {
    "job": "a job: it writes files, prints progress or loops in Python over compiled steps; its pure cores have "
    "entries",
    "validator": "an eager check that raises on concrete values (under tracing it checks shapes or nothing)",
    "loader": "reads a file, a name or a model description (strings and files, nothing to trace)",
    "transformation": "takes or returns functions (a transformation of the user's function, or a factory)",
    "static": "takes only static sizes and settings (Python integers, strings) and returns constants: nothing to trace",
}
"""The kinds of exemption; an exempt name's reason starts with one of them (``"job: ..."``)."""

PARTS = ("models", "observers", "estimation", "systems", "vehicle", "mjx", "jobs")
"""The registry files, each with ``ENTRIES`` and ``EXEMPT`` dicts (and optionally ``PENDING``)."""


def _merged(attribute: str) -> dict:
    import importlib

    merged: dict = {}
    for part in PARTS:
        entries = getattr(importlib.import_module(f"tests.api_registry.{part}"), attribute, {})
        clash = set(merged) & set(entries)
        if clash:
            raise ValueError(f"registered twice: {sorted(clash)}")
        merged.update(entries)
    return merged


FILES = {
    "jaxobs.lti": "models.py",
    "jaxobs.design": "models.py",
    "jaxobs.matrix_equations": "models.py",
    "jaxobs.kalman_steps": "models.py",
    "jaxobs.plants": "models.py",
    "jaxobs.ct": "models.py",
    "jaxobs.adaptive": "models.py",
    "jaxobs.nonlinear": "models.py",
    "jaxobs.batching": "jobs.py",
    "jaxobs._checks": "jobs.py",
    "jaxobs.observers": "observers.py",
    "jaxobs.smoothing": "estimation.py",
    "jaxobs.learning": "estimation.py",
    "jaxobs.consistency": "estimation.py",
    "jaxobs.resampling": "estimation.py",
    "jaxobs.closed_loop": "systems.py",
    "jaxobs.stability": "systems.py",
    "jaxobs.saturation": "systems.py",
    "jaxobs.scb": "systems.py",
    "jaxobs.vehicle": "vehicle.py",
    "jaxobs.mjx": "mjx.py",
    "jaxobs.sweep": "jobs.py",
    "jaxobs.tuning": "jobs.py",
}
"""The registry file of each part of the package (the longest matching module prefix)."""


def file_of(key: str) -> str:
    """The registry file where the entry ``key`` (``module.name``) belongs."""
    module = key.rsplit(".", 1)[0]
    prefixes = [p for p in FILES if module == p or module.startswith(p + ".")]
    return f"tests/api_registry/{FILES[max(prefixes, key=len)] if prefixes else 'models.py'}"


REGISTRY: dict[str, Example | Design] = _merged("ENTRIES")
"""Every entry: ``"module.name"`` (the name's home module) -> its :class:`Example` or :class:`Design`."""

EXEMPT: dict[str, str] = _merged("EXEMPT")
"""``"module.name"`` -> ``"kind: reason"`` (a kind of :data:`EXEMPTIONS`) for the names without an entry."""

PENDING: dict[str, str] = _merged("PENDING")
"""``"module.name"`` -> why it has no entry yet: names not audited yet (an expected failure of the test)."""

__all__ = ["PENDING", "slow", "CHECKS", "Example", "Design", "EXEMPTIONS", "REGISTRY", "EXEMPT", "FILES", "file_of"]
