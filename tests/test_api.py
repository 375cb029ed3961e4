"""The public API: every name ``import jaxobs as jo`` exports resolves, is documented (each argument of a function,
each field of a params class named in its docstring), and every example in those docstrings runs (doctest)."""

import ast
import dataclasses
import doctest
import importlib
import inspect
import os
import pkgutil
import re
import subprocess
import sys

import pytest

import jaxobs as jo
import jaxobs.observers
from tests import ROOT

NAMES = [name for name in jo.__all__ if name != "__version__"]


def _attribute_docstring(obj_name: str, module) -> str | None:
    """The string literal that follows ``obj_name = ...`` at module level (how module constants and the estimator
    objects are documented), or None."""
    body = ast.parse(inspect.getsource(module)).body
    for node, following in zip(body, body[1:], strict=False):
        if isinstance(node, ast.Assign):
            targets = node.targets
        else:
            targets = [node.target] if isinstance(node, ast.AnnAssign) else []
        if any(isinstance(t, ast.Name) and t.id == obj_name for t in targets):
            if isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant):
                return following.value.value
    return None


def _documentation(name: str) -> str:
    obj = getattr(jo, name)
    if inspect.isfunction(obj) or inspect.isclass(obj):
        return inspect.getdoc(obj) or ""
    for info in pkgutil.iter_modules(jaxobs.observers.__path__, "jaxobs.observers."):
        module = importlib.import_module(info.name)
        if getattr(module, name, None) is obj:
            return _attribute_docstring(name, module) or ""
    return ""


def _describes(doc: str, name: str) -> bool:
    """``name`` appears as an argument is described: in double backticks, or starting an ``Args`` entry
    (``name:``, ``name (``), or in a list of names sharing an entry (``A, B, C:``)."""
    word = re.escape(name)
    pattern = rf"``{word}``|^\s*{word}\s*[:(]|(?:^|[\s,]){word}\s*,[^\n]*:|[\s,]{word}\s*:"
    return re.search(pattern, doc, re.M) is not None


def test_version():
    assert isinstance(jo.__version__, str) and jo.__version__[0].isdigit()


@pytest.mark.parametrize("name", NAMES)
def test_exported_name_resolves_and_is_documented(name):
    obj = getattr(jo, name)
    doc = _documentation(name)
    assert len(doc) > 40, f"jo.{name} has no real docstring"
    if inspect.isfunction(obj):
        missing = [p for p in inspect.signature(obj).parameters if not _describes(doc, p)]
        assert not missing, f"jo.{name}: arguments {missing} are not described in its docstring"
    elif inspect.isclass(obj) and dataclasses.is_dataclass(obj):
        missing = [f.name for f in dataclasses.fields(obj) if not _describes(doc, f.name)]
        assert not missing, f"jo.{name}: fields {missing} are not described in its docstring"


MAIN_ENTRY_POINTS = ["c2d", "dare", "dlqr", "make_kalman", "make_aob", "run", "simulate", "observer_controller",
                     "stability_margins", "force_plant", "critically_damped_gain", "nonlinear_model", "make_ekf",
                     "make_ukf", "make_continuous_observer", "smooth", "log_likelihood", "fit", "em",
                     "make_modular", "hgo_gains", "make_hgo", "make_gramian"]  # fmt: skip


@pytest.mark.parametrize("name", MAIN_ENTRY_POINTS)
def test_main_entry_points_have_an_example(name):
    assert ">>>" in _documentation(name), f"jo.{name} needs a short runnable example"


@pytest.mark.parametrize("name", NAMES)
def test_docstring_examples_run(name):
    obj = getattr(jo, name)
    if not (inspect.isfunction(obj) or inspect.isclass(obj)):
        return
    finder = doctest.DocTestFinder(recurse=False)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    module = inspect.getmodule(obj)
    for test in finder.find(obj, name, module=module, globs=dict(vars(module))):
        runner.run(test)
    assert runner.failures == 0, f"jo.{name}: {runner.failures} docstring example(s) failed (run pytest -s to see)"


def _fresh(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300,
                          check=True)  # fmt: skip


def test_import_jaxobs_loads_names_on_first_use():
    """``import jaxobs`` imports neither JAX nor a module of jaxobs; a name loads its module (and JAX), never MuJoCo,
    matplotlib or SciPy's signal package (1-2 s of import that only MIMO placement needs)."""
    heavy = ("jax", "jaxobs.lti", "jaxobs.mjx", "mujoco", "matplotlib", "scipy.signal", "optax", "pyarrow")
    code = (f"import sys, jaxobs; print([m for m in {heavy!r} if m in sys.modules]); jaxobs.make_kalman; "
            f"print([m for m in {heavy!r} if m in sys.modules])")  # fmt: skip
    before, after = _fresh(code).stdout.splitlines()
    assert before == "[]"
    assert after == "['jax', 'jaxobs.lti']"
    assert set(jo.__all__) <= set(dir(jo))
    with pytest.raises(AttributeError, match="module 'jaxobs' has no attribute 'no_such_name'"):
        jo.no_such_name  # noqa: B018
    assert jo.observers is jaxobs.observers  # a submodule by attribute, as after an import


def test_import_jaxobs_mjx_prints_nothing():
    """mujoco.mjx's "Failed to import warp: No module named 'warp'" lines (the absent optional backend) are not
    passed on."""
    done = _fresh("import jaxobs.mjx")
    assert (done.stdout, done.stderr) == ("", "")
