"""The layers point down only, checked on the source of every module of jaxobs (imports inside functions included):

* the library never imports the paper layer (``jaxobs.papers``) or the command line (``jaxobs.cli``);
* no module imports another module's private name (``_x``); ``_``-prefixed modules (``jaxobs._checks``,
  ``jaxobs._linalg``, ``jaxobs.papers.tuning_config``) are shared private modules of their package;
* the module import graph has no cycle;
* no estimator family imports another family (they share the protocol, :mod:`jaxobs.kalman_steps`, the atoms,
  the feedback wrapper and the sampled runner of continuous-time observers, :mod:`jaxobs.observers.continuous`).

Each rule has a test on a small synthetic module graph that proves the checker catches a violation.
"""

from __future__ import annotations

import ast
import functools
from typing import NamedTuple

import pytest

from tests import ROOT

PACKAGE = ROOT / "jaxobs"
UPPER_LAYERS = ("jaxobs.papers", "jaxobs.cli")
OBSERVERS = "jaxobs.observers"
SHARED_OBSERVER_MODULES = {"__init__", "base", "feedback", "continuous"}


@functools.cache
def package_imports() -> dict[str, ModuleImports]:
    """:func:`scan` of every module of jaxobs (a package under its own name)."""
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = ast.parse(path.read_text(), str(path))
    return scan(modules)


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _is_package(name: str, modules: dict[str, ast.Module]) -> bool:
    return any(other.startswith(name + ".") for other in modules)


def _base(module: str, node: ast.ImportFrom, modules: dict[str, ast.Module]) -> str:
    """The absolute module a ``from ... import`` reads from (relative imports resolved against ``module``)."""
    if not node.level:
        return node.module or ""
    package = module if _is_package(module, modules) else module.rpartition(".")[0]
    for _ in range(node.level - 1):
        package = package.rpartition(".")[0]
    return f"{package}.{node.module}" if node.module else package


class ModuleImports(NamedTuple):
    """What one module takes from jaxobs, found in one pass over its syntax tree."""

    imports: list[tuple[str, str | None, int]]  # (target module, name read from it or None for the module, line)
    attribute_reads: list[tuple[str, str, int]]  # (module, private attribute, line) for ``alias._x``


def scan(modules: dict[str, ast.Module]) -> dict[str, ModuleImports]:
    """:class:`ModuleImports` of every module (imports inside functions included)."""
    return {module: _scan_module(module, modules) for module in modules}


def _scan_module(module: str, modules: dict[str, ast.Module]) -> ModuleImports:
    found, aliases, attributes = [], {}, []
    for node in ast.walk(modules[module]):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in modules:
                    found.append((alias.name, None, node.lineno))
                    aliases[alias.asname or alias.name] = alias.name
        elif isinstance(node, ast.ImportFrom):
            base = _base(module, node, modules)
            for alias in node.names:
                if f"{base}.{alias.name}" in modules:
                    found.append((f"{base}.{alias.name}", None, node.lineno))
                    aliases[alias.asname or alias.name] = f"{base}.{alias.name}"
                elif base in modules:
                    found.append((base, alias.name, node.lineno))
        elif isinstance(node, ast.Attribute) and _is_private(node.attr):
            attributes.append(node)
    reads = []
    for node in attributes:
        dotted = _dotted(node.value)
        head, _, rest = (dotted or "").partition(".")
        if head in aliases:
            target = f"{aliases[head]}.{rest}" if rest else aliases[head]
            if target in modules and f"{target}.{node.attr}" not in modules:
                reads.append((target, node.attr, node.lineno))
    return ModuleImports(found, reads)


def _dotted(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        inner = _dotted(node.value)
        return None if inner is None else f"{inner}.{node.attr}"
    return None


def upper_layer_imports(scanned: dict[str, ModuleImports]) -> list[str]:
    """Rule (a): imports of the paper layer or the command line from outside them."""
    found = []
    for module, info in scanned.items():
        if any(module == top or module.startswith(top + ".") for top in UPPER_LAYERS):
            continue
        for target, _, line in info.imports:
            if any(target == top or target.startswith(top + ".") for top in UPPER_LAYERS):
                found.append(f"{module}:{line} imports {target}")
    return found


def _private_module_allowed(importer: str, target: str) -> bool:
    """A ``_``-prefixed module serves the package it sits in (and that package's subpackages)."""
    parts = target.split(".")
    for i, part in enumerate(parts):
        if _is_private(part):
            package = ".".join(parts[:i])
            if not (importer == package or importer.startswith(package + ".")):
                return False
    return True


def private_imports(scanned: dict[str, ModuleImports]) -> list[str]:
    """Rule (b): another module's private name, imported (``from m import _x``) or read (``m._x``); private
    modules outside the package they serve."""
    found = []
    for module, info in scanned.items():
        for target, name, line in info.imports:
            if target == module:
                continue
            if name is not None and _is_private(name):
                found.append(f"{module}:{line} imports {target}.{name}")
            elif not _private_module_allowed(module, target):
                found.append(f"{module}:{line} imports the private module {target}")
        reads = info.attribute_reads
        found += [f"{module}:{line} reads {target}.{name}" for target, name, line in reads if target != module]
    return found


def import_cycle(scanned: dict[str, ModuleImports]) -> list[str] | None:
    """Rule (c): one cycle of the module import graph as its path ``[a, b, ..., a]``, or ``None``."""
    graph = {module: sorted({target for target, _, _ in info.imports} - {module}) for module, info in scanned.items()}
    state = dict.fromkeys(graph, 0)  # 0 unvisited, 1 on the current path, 2 done
    path: list[str] = []

    def visit(module):
        state[module] = 1
        path.append(module)
        for target in graph[module]:
            if state[target] == 1:
                return path[path.index(target) :] + [target]
            if state[target] == 0 and (cycle := visit(target)):
                return cycle
        path.pop()
        state[module] = 2
        return None

    for module in graph:
        if state[module] == 0 and (cycle := visit(module)):
            return cycle
    return None


def family_imports(scanned: dict[str, ModuleImports]) -> list[str]:
    """Rule (d): an estimator family of ``jaxobs.observers`` importing another family."""
    families = {
        module
        for module in scanned
        if module.rpartition(".")[0] == OBSERVERS and module.rpartition(".")[2] not in SHARED_OBSERVER_MODULES
    }
    return [
        f"{module}:{line} imports {target}"
        for module in sorted(families)
        for target, _, line in scanned[module].imports
        if target in families - {module}
    ]


# --------------------------------------------------------------------------------------------------------------
# the rules on jaxobs


def test_library_does_not_import_the_paper_layer_or_the_cli():
    found = upper_layer_imports(package_imports())
    assert not found, f"the library must not depend on jaxobs.papers or jaxobs.cli: {found}"


def test_no_module_imports_another_modules_private_names():
    found = private_imports(package_imports())
    assert not found, f"make the helper public in its own home instead: {found}"


def test_module_import_graph_has_no_cycle():
    cycle = import_cycle(package_imports())
    assert cycle is None, f"import cycle: {' -> '.join(cycle)}"


def test_no_estimator_family_imports_another():
    found = family_imports(package_imports())
    assert not found, f"families share base, kalman_steps and the atoms only: {found}"


# --------------------------------------------------------------------------------------------------------------
# the checker catches each violation (the tests above are not vacuous)


def _parsed(sources: dict[str, str]) -> dict[str, ModuleImports]:
    return scan({name: ast.parse(source) for name, source in sources.items()})


def test_checker_sees_an_upper_layer_import():
    modules = _parsed({
        "jaxobs": "",
        "jaxobs.lti": "def f():\n    import jaxobs.papers.grip2010.sideslip as s\n",
        "jaxobs.design": "from jaxobs.cli import main\n",
        "jaxobs.papers": "",
        "jaxobs.papers.grip2010": "",
        "jaxobs.papers.grip2010.sideslip": "from jaxobs import lti\n",
        "jaxobs.cli": "from jaxobs.papers import grip2010\n",
    })  # fmt: skip
    assert upper_layer_imports(modules) == [
        "jaxobs.lti:2 imports jaxobs.papers.grip2010.sideslip",
        "jaxobs.design:1 imports jaxobs.cli",
    ]


def test_checker_sees_a_private_import():
    modules = _parsed({
        "jaxobs": "",
        "jaxobs._checks": "",
        "jaxobs.lti": "from jaxobs import _checks\ndef _rank(A):\n    return 0\n",
        "jaxobs.design": "from jaxobs.lti import _rank\n",
        "jaxobs.stability": "import jaxobs.lti as lti\nlti._rank(1)\n",
        "jaxobs.vehicle": "",
        "jaxobs.vehicle._layout": "",
        "jaxobs.vehicle.nvso": "from jaxobs.vehicle import _layout\n",
        "jaxobs.mjx": "",
        "jaxobs.mjx.robot": "from jaxobs.vehicle._layout import AX\n",
    })  # fmt: skip
    assert private_imports(modules) == [
        "jaxobs.design:1 imports jaxobs.lti._rank",
        "jaxobs.stability:2 reads jaxobs.lti._rank",
        "jaxobs.mjx.robot:1 imports the private module jaxobs.vehicle._layout",
    ]


def test_checker_sees_an_import_cycle_inside_a_function():
    modules = _parsed({
        "jaxobs": "",
        "jaxobs.a": "from jaxobs import b\n",
        "jaxobs.b": "from jaxobs.c import f\n",
        "jaxobs.c": "def f():\n    from jaxobs.a import g\n",
    })  # fmt: skip
    assert import_cycle(modules) == ["jaxobs.a", "jaxobs.b", "jaxobs.c", "jaxobs.a"]
    modules["jaxobs.c"] = modules["jaxobs.c"]._replace(imports=[])
    assert import_cycle(modules) is None


@pytest.mark.parametrize("statement", ["from jaxobs.observers.kalman import kalman", "from . import kalman"])
def test_checker_sees_a_family_importing_another(statement):
    modules = _parsed({
        "jaxobs": "",
        "jaxobs.observers": "",
        "jaxobs.observers.base": "",
        "jaxobs.observers.kalman": "from jaxobs.observers.base import Estimator\n",
        "jaxobs.observers.hinf": statement + "\n",
    })  # fmt: skip
    assert family_imports(modules) == ["jaxobs.observers.hinf:1 imports jaxobs.observers.kalman"]
