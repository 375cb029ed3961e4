"""Griffe extension for the API reference: the docstrings' Sphinx roles become mkdocstrings cross-references.

jaxobs' docstrings are Google style with Sphinx roles (``:func:`dare```, ``:class:`~jaxobs.lti.StateSpace```).
Once the package is loaded, each role is resolved the way Python would resolve the name in the docstring's scope
(the object, its parents, then the module's imports); a target the reference renders (public, in a public module)
becomes a link ``[`dare`][jaxobs.matrix_equations.dare]``, anything else (private helpers, other packages) plain code.
An RST literal-block marker ``::`` at the end of a line becomes ``:`` (the indented block is code in Markdown too),
and an ``Example:`` header Google's ``Examples:`` (so its doctest renders as code).
"""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:func|class|data|mod|attr|meth|obj|exc):`(~?)([\w.]+?)(\(\))?`")
LITERAL_BLOCK = re.compile(r"(?<=\S)::$", flags=re.M)
EXAMPLE_HEADER = re.compile(r"^(\s*)Example:$", flags=re.M)  # Google's section is "Examples:" (doctest as code)


def _lookup(scope: griffe.Object, dotted: str):
    """The object ``dotted`` names from ``scope`` (its members, then its parents'), or ``None``."""
    head, *rest = dotted.split(".")
    while scope is not None:
        if head in scope.members:
            found = scope.members[head]
            try:
                for part in rest:
                    found = found.members[part]
            except (KeyError, griffe.AliasResolutionError, griffe.CyclicAliasError):
                return None
            return found
        scope = scope.parent
    return None


def _rendered_path(obj) -> str | None:
    """The canonical path of ``obj`` if the API reference renders it (public all the way up), else ``None``."""
    try:
        target = obj.final_target if obj.is_alias else obj
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None
    node = target
    while node is not None:
        if node.name.startswith("_") and not node.name.startswith("__"):
            return None
        if node.parent is not None and not node.is_module and not node.is_public:
            return None
        node = node.parent
    return target.path


class SphinxRoles(griffe.Extension):
    def __init__(self) -> None:
        self._loader = None

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs) -> None:
        self._loader = loader
        self._rewrite(pkg, seen=set())

    def _rewrite(self, obj: griffe.Object, seen: set) -> None:
        if obj.path in seen:
            return
        seen.add(obj.path)
        if obj.docstring is not None:
            obj.docstring.value = self._convert(obj, obj.docstring.value)
        for member in obj.members.values():
            if not member.is_alias:
                self._rewrite(member, seen)

    def _convert(self, obj: griffe.Object, text: str) -> str:
        scope = obj if obj.is_module or obj.is_class else obj.parent

        def link(match: re.Match) -> str:
            short, dotted, call = match.group(1), match.group(2), match.group(3) or ""
            shown = (dotted.rsplit(".", 1)[-1] if short else dotted) + call
            found = _lookup(scope, dotted)
            if found is None and dotted.startswith("jaxobs"):
                try:
                    found = self._loader.modules_collection.get_member(dotted)
                except (KeyError, ValueError):
                    found = None
            path = _rendered_path(found) if found is not None else None
            return f"[`{shown}`][{path}]" if path else f"`{shown}`"

        return EXAMPLE_HEADER.sub(r"\1Examples:", LITERAL_BLOCK.sub(":", ROLE.sub(link, text)))
