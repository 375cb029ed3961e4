"""The files jaxobs ships for its command: the example configs and the robots, found in the installed package.

The configs are the TOML files of ``jaxobs sweep`` and ``jaxobs tune`` (the repository's ``tuning/`` folder,
installed as ``jaxobs/papers/configs``); the robots are the MJCF files under ``jaxobs/mjx/assets``. Every default
path is resolved here, from the package, never from the working directory.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

__all__ = ["CONFIGS", "ROBOTS", "ShippedConfig", "shipped_configs", "config_path", "resolve_path"]

CONFIGS = Path(__file__).parent / "configs"
"""The folder of the shipped configs (the repository's ``tuning/``)."""

ROBOTS = Path(__file__).parents[1] / "mjx" / "assets"
"""The folder of the shipped MJCF files."""

_KIND = re.compile(r'^(scenario|problem)\s*=\s*"([^"]+)"', re.M)


@dataclasses.dataclass(frozen=True)
class ShippedConfig:
    """One shipped config: its ``name`` (the file's stem, for ``--example NAME``), the ``kind`` of job ("sweep" or
    "tune"), the scenario or problem it picks (``job``), a one-line ``summary`` (its leading comment, less the
    command line) and its ``path``."""

    name: str
    kind: str
    job: str
    summary: str
    path: Path


_SUMMARY_CHARACTERS = 110


def _summary(text: str) -> str:
    """The first sentence of a config's leading comment (after its ``jaxobs ...`` command line), on one line of at
    most :data:`_SUMMARY_CHARACTERS` characters."""
    comment = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        comment.append(line.lstrip("#").strip())
    paragraphs = " ".join(line or "\n" for line in comment if not line.startswith("jaxobs ")).split("\n")
    first = next((" ".join(p.split()) for p in paragraphs if p.strip()), "")
    sentence = re.split(r"(?<=[a-z0-9)])\. (?=[A-Z])", first)[0].rstrip(".") + "."
    return sentence if len(sentence) <= _SUMMARY_CHARACTERS else sentence[: _SUMMARY_CHARACTERS - 3] + "..."


def shipped_configs(kind: str | None = None) -> list[ShippedConfig]:
    """The shipped configs, by name; only those of ``kind`` ("sweep" or "tune") if given."""
    found = []
    for path in sorted(CONFIGS.glob("*.toml")):
        text = path.read_text()
        match = _KIND.search(text)
        if match is None:
            continue
        job_kind = "sweep" if match.group(1) == "scenario" else "tune"
        if kind in (None, job_kind):
            found.append(ShippedConfig(path.stem, job_kind, match.group(2), _summary(text), path))
    return found


def config_path(name: str, kind: str) -> Path:
    """The path of the shipped config ``name`` (with or without ``.toml``) of ``kind``; a ``ValueError`` listing
    the names otherwise."""
    names = {c.name: c.path for c in shipped_configs(kind)}
    stem = name.removesuffix(".toml")
    if stem not in names:
        raise ValueError(f"--example: no shipped {kind} config {name!r}; one of {', '.join(sorted(names))}")
    return names[stem]


def resolve_path(value: str, source: str) -> str:
    """The file a config's path ``value`` names: an absolute path as it is; a relative one from the directory of
    the config file ``source`` (the current directory when the config is not a file); failing that, a shipped
    robot of that name (``cartpole_payload.xml``). Returned as given when none exists (the loader then says so)."""
    path = Path(value)
    if path.is_absolute() or not value:
        return value
    base = Path(source).parent if Path(source).is_file() else Path.cwd()
    for candidate in (base / path, ROBOTS / path):
        if candidate.is_file():
            return str(candidate.resolve())
    return value
