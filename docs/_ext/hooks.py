"""MkDocs hooks: the API reference generated from the package.

* API reference: one page per public module of ``jaxobs`` (a module without a leading underscore in its path),
  written in memory (``api/<module>.md``, rendered by mkdocstrings) and put under the ``API reference`` section
  of the nav, grouped by subpackage. A new module appears without editing mkdocs.yml. A package's page shows its
  docstring, what it defines itself and the table of what it exports (linked to their modules' pages).
* The command output the pages show (help texts, ``--list``, ``--print-config``) is in the pages themselves,
  written there by ``docs/_ext/cli_output.py`` and checked by tests/test_docs.py; the site shows it as it is.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).parents[2]
PACKAGE = "jaxobs"
API_SECTION = "API reference"
API_INDEX = "api/index.md"


def public_modules() -> list[str]:
    """Dotted names of the public modules, packages first within each package, sorted."""
    names = []
    for path in sorted((ROOT / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        if not any(p.startswith("_") for p in parts):
            names.append(".".join(parts))
    return sorted(names, key=lambda name: (name.split("."), name))


def _is_package(name: str) -> bool:
    return (ROOT / Path(*name.split(".")) / "__init__.py").is_file()


def _page(name: str) -> str:
    return API_INDEX if name == PACKAGE else f"api/{name}.md"


def _nav(names: list[str], parent: str) -> list:
    """Nav entries of the modules directly under ``parent`` (subpackages as sections headed by their page)."""
    entries = []
    for name in names:
        if name.rpartition(".")[0] != parent:
            continue
        if _is_package(name):
            entries.append({name: [_page(name), *_nav(names, name)]})
        else:
            entries.append({name: _page(name)})
    return entries


def _exports(name: str) -> list[tuple[str, str]]:
    """``(exported name, canonical path)`` for each name of the package ``name``'s ``__all__`` defined in jaxobs."""
    import griffe

    package = griffe.load(name, search_paths=[str(ROOT)], resolve_aliases=True, resolve_external=False)
    rows = []
    for export in package.exports or []:
        if export.startswith("__") or export not in package.members:
            continue
        member = package.members[export]
        try:
            path = member.final_target.path if member.is_alias else member.path
        except (griffe.AliasResolutionError, griffe.CyclicAliasError):
            continue
        if path.startswith(PACKAGE + "."):
            rows.append((export, path))
    return rows


def _documented_at(name: str, export: str, path: str) -> str:
    """Where the page of package ``name`` documents ``export`` (defined at ``path``): its home module's page, or the
    package's own page when the home is private (``jaxobs.checked``, defined in ``jaxobs._checks``)."""
    return f"{name}.{export}" if any(p.startswith("_") for p in path.split(".")) else path


def _markdown(name: str) -> str:
    header = f"::: {name}\n    options:\n      heading_level: 1\n"
    if not _is_package(name):
        return header
    exports = [(export, _documented_at(name, export, path)) for export, path in _exports(name)]
    own = [export for export, path in exports if path == f"{name}.{export}"]  # documented on the package's page
    rows = "".join(f"| [`{export}`][{path}] | `{path.rpartition('.')[0]}` |\n" for export, path in exports)
    table = f"\n| name | defined in |\n| --- | --- |\n{rows}" if rows else ""
    return header + f"      members: {own or 'false'}\n" + table


def on_config(config):
    sys.path.insert(0, str(ROOT))  # run this checkout's command, wherever the environment's jaxobs points
    names = public_modules()
    nav = config["nav"]
    for i, entry in enumerate(nav):
        if isinstance(entry, dict) and entry.get(API_SECTION) == API_INDEX:
            nav[i] = {API_SECTION: [API_INDEX, *_nav(names, PACKAGE)]}
            break
    else:
        raise ValueError(f"mkdocs.yml: the nav needs the entry '{API_SECTION}: {API_INDEX}'")
    return config


def on_files(files, config):
    for name in public_modules():
        files.append(File.generated(config, _page(name), content=_markdown(name)))
    return files
