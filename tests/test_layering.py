"""The layers point down only: the library never imports the paper layer, and no estimator family imports
another family (they share the protocol, :mod:`jaxobs.kalman_steps`, the atoms, the feedback wrapper and the
sampled runner of continuous-time observers, :mod:`jaxobs.observers.continuous`)."""

import ast
from pathlib import Path

import pytest

from tests import ROOT

PACKAGE = ROOT / "jaxobs"
FAMILIES = {p.stem for p in (PACKAGE / "observers").glob("*.py")} - {"__init__", "base", "feedback", "continuous"}


def _imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports (absolute names; ``from jaxobs import x`` counts as ``jaxobs.x``)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _library_modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE)
        if relative.parts[0] == "papers" or relative == Path("cli.py"):
            continue
        yield path


@pytest.mark.parametrize("path", list(_library_modules()), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_library_module_does_not_import_the_paper_layer(path):
    imported = _imported_modules(path)
    arrows = sorted(name for name in imported if name == "jaxobs.papers" or name.startswith("jaxobs.papers."))
    assert not arrows, f"{path.relative_to(PACKAGE)} imports {arrows}: the library must not depend on jaxobs.papers"


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_no_estimator_family_imports_another(family):
    imported = _imported_modules(PACKAGE / "observers" / f"{family}.py")
    others = sorted(f"jaxobs.observers.{f}" for f in FAMILIES - {family} if f"jaxobs.observers.{f}" in imported)
    assert not others, f"observers/{family}.py imports {others}: families share base, kalman_steps and the atoms only"


def test_the_checker_sees_an_arrow(tmp_path):
    """The parser catches both spellings of an import of the paper layer (the test is not vacuous)."""
    module = tmp_path / "m.py"
    module.write_text("from jaxobs.papers import force_control\nimport jaxobs.papers.liu_peng.vehicle_lateral as lp\n")
    assert {"jaxobs.papers", "jaxobs.papers.liu_peng.vehicle_lateral"} <= _imported_modules(module)
