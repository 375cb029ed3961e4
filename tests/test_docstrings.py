"""Docstrings that serve a reader: every module says briefly what it is for (theory and measurements live in
docs/), every exported class and function has a docstring, and an exported NamedTuple or dataclass names each of
its fields (with its shape) in its class docstring."""

import dataclasses
import importlib
import inspect
import pkgutil
import re

import pytest

import jaxobs

MAX_MODULE_DOCSTRING_LINES = 15

MODULES = sorted(
    [jaxobs.__name__] + [info.name for info in pkgutil.walk_packages(jaxobs.__path__, prefix=f"{jaxobs.__name__}.")]
)


def _exported(module):
    """The classes and functions a module exports: its ``__all__``, else the public ones it defines itself."""
    if hasattr(module, "__all__"):
        names = module.__all__
    else:
        names = [name for name, obj in vars(module).items() if getattr(obj, "__module__", None) == module.__name__]
    objects = {name: getattr(module, name) for name in names if not name.startswith("_")}
    return {name: obj for name, obj in objects.items() if inspect.isclass(obj) or inspect.isfunction(obj)}


def _fields(cls) -> tuple[str, ...]:
    if dataclasses.is_dataclass(cls):
        return tuple(field.name for field in dataclasses.fields(cls))
    return getattr(cls, "_fields", ())


def _own_docstring(obj) -> str:
    """The docstring the object was written with (not inherited, not the one NamedTuple or dataclass generates)."""
    doc = obj.__dict__.get("__doc__") if inspect.isclass(obj) else obj.__doc__
    if not doc or (inspect.isclass(obj) and doc.startswith(f"{obj.__name__}(")):
        return ""
    return doc


@pytest.mark.parametrize("name", MODULES)
def test_module_docstring_is_short(name):
    doc = importlib.import_module(name).__doc__
    assert doc and doc.strip(), f"{name} has no module docstring"
    lines = len(doc.strip().splitlines())
    assert lines <= MAX_MODULE_DOCSTRING_LINES, (
        f"{name}: module docstring of {lines} lines (at most {MAX_MODULE_DOCSTRING_LINES}; theory goes to docs/)"
    )


@pytest.mark.parametrize("name", MODULES)
def test_exported_names_have_docstrings(name):
    missing = [export for export, obj in _exported(importlib.import_module(name)).items() if not _own_docstring(obj)]
    assert not missing, f"{name}: exported without a docstring: {missing}"


@pytest.mark.parametrize("name", MODULES)
def test_exported_records_document_their_fields(name):
    undocumented = {}
    for export, obj in _exported(importlib.import_module(name)).items():
        if inspect.isclass(obj) and (doc := _own_docstring(obj)):
            absent = [field for field in _fields(obj) if not re.search(rf"\b{re.escape(field)}\b", doc)]
            if absent:
                undocumented[export] = absent
    assert not undocumented, f"{name}: fields missing from the class docstring: {undocumented}"
