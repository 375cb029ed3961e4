"""Configuration files of the ``jaxobs`` commands: TOML over an embedded default, checked key by key.

Every command that reads a config (``jaxobs sweep``, ``jaxobs tune``) merges the user's TOML over its
embedded default with :func:`merge` (unknown keys, wrong types, non-finite numbers such as TOML's ``inf``
and ``nan``, and integers beyond int32 are errors) and checks values with :func:`check_range` /
:func:`check_at_least`, and the sizes of what the configuration will allocate with :func:`check_memory`; a
:class:`ConfigError` names the file and the key. The paper layer names the size key of a job that exceeds the
machine's memory or JAX's counts as it is built (:class:`jaxobs.papers.scenarios.SweepScenario`). Each scenario
documents its keys in a ``{dotted key: note}`` dict beside its default, and :func:`to_toml` writes a configuration
back as TOML with every key's note above it (``--print-config``).
"""

from __future__ import annotations

import copy
import json
import math
import re
import textwrap
from pathlib import Path

from jaxobs._resources import MAX_INDEX, JobError
from jaxobs._resources import check_memory as _check_memory

__all__ = [
    "ConfigError",
    "fail",
    "load_toml",
    "load_toml_text",
    "deep_merge",
    "merge",
    "get",
    "check_range",
    "check_at_least",
    "check_choice",
    "check_memory",
    "leaf_keys",
    "to_toml",
]


class ConfigError(JobError):
    """A bad configuration (a ``ValueError``); the message names the file and the key."""


def fail(source: str, key: str, message: str):
    """Raise :class:`ConfigError` for ``key`` of ``source`` (a file name or "defaults")."""
    raise ConfigError(f"{source}: {key}: {message}")


def load_toml(path) -> dict:
    """Parse a TOML file; a missing file or invalid TOML is a :class:`ConfigError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file")
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    return load_toml_text(text, str(path))


def load_toml_text(text: str, source: str) -> dict:
    """Parse TOML ``text``; invalid TOML is a :class:`ConfigError` naming ``source``."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    try:
        return tomllib.loads(text)
    except ValueError as exc:  # tomllib.TOMLDecodeError is a ValueError
        raise ConfigError(f"{source}: not valid TOML: {exc}") from exc


def deep_merge(base: dict, over: dict) -> dict:
    """A copy of ``base`` with ``over``'s keys set, tables merged key by key (no checks: :func:`merge` does them)."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        out[key] = deep_merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _is_names(value) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, str) for v in value)


def _is_numbers(value) -> bool:
    return isinstance(value, list) and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)


def _check_numbers(source: str, name: str, value) -> None:
    """Numbers (alone or in a list) must be finite, and integers at most :data:`jaxobs._resources.MAX_INDEX` in
    magnitude: JAX reads counts, sizes and seeds as int32 (a larger one overflows, or sets an impossible size)."""
    numbers = value if isinstance(value, list) else [value]
    if any(isinstance(v, float) and not math.isfinite(v) for v in numbers):
        fail(source, name, f"must be finite, got {value!r}")
    if any(isinstance(v, int) and not isinstance(v, bool) and abs(v) > MAX_INDEX for v in numbers):
        fail(source, name, f"must be an integer of magnitude at most 2**31 - 1 = {MAX_INDEX} (int32), got {value!r}")


def merge(default: dict, given: dict, source: str, prefix: str = "", *, open_tables: tuple = ()) -> dict:
    """``given`` over ``default``; unknown keys, type mismatches, non-finite numbers and integers beyond int32 are
    errors. A list default of strings takes a list of strings, any other list default a list of numbers. The tables
    named (dotted) in ``open_tables`` take keys of the user's choosing, each a list of numbers: a given one replaces
    the default's."""
    merged = copy.deepcopy(default)
    for key, value in given.items():
        name = f"{prefix}{key}"
        _check_numbers(source, name, value)
        if key not in default:
            fail(source, name, f"unknown key (expected one of: {', '.join(default)})")
        expected = default[key]
        if name in open_tables:
            if not isinstance(value, dict):
                fail(source, name, "must be a table")
            for entry, numbers in value.items():
                if not _is_numbers(numbers):
                    fail(source, f"{name}.{entry}", f"must be a list of finite numbers, got {numbers!r}")
                _check_numbers(source, f"{name}.{entry}", numbers)
            merged[key] = dict(value)
        elif isinstance(expected, dict):
            if not isinstance(value, dict):
                fail(source, name, "must be a table")
            merged[key] = merge(expected, value, source, name + ".", open_tables=open_tables)
        elif _is_names(expected):
            if not _is_names(value):
                fail(source, name, f"must be a non-empty list of strings, got {value!r}")
            merged[key] = value
        elif isinstance(expected, list):
            if not _is_numbers(value):
                fail(source, name, f"must be a list of numbers, got {value!r}")
            merged[key] = value
        elif isinstance(expected, bool) != isinstance(value, bool):
            kind = "true or false" if isinstance(expected, bool) else "a number"
            fail(source, name, f"must be {kind}, got {value!r}")
        elif isinstance(expected, str) and not isinstance(value, str):
            fail(source, name, f"must be a string, got {value!r}")
        elif isinstance(expected, int) and not isinstance(value, int):
            fail(source, name, f"must be an integer, got {value!r}")
        elif isinstance(expected, float) and not isinstance(value, int | float):
            fail(source, name, f"must be a number, got {value!r}")
        else:
            merged[key] = value
    return merged


def get(config: dict, key: str):
    """The value at a dotted ``key`` such as ``"plant.stiffness"``."""
    value = config
    for part in key.split("."):
        value = value[part]
    return value


def check_range(config: dict, source: str, key: str, *, positive: bool = False, minimum=None, maximum=None,
                allow_point: bool = False):  # fmt: skip
    """``key`` must be ``[low, high]`` with ``low < high`` (``<=`` with ``allow_point``) within the bounds."""
    value = get(config, key)
    ordered = len(value) == 2 and (value[0] <= value[1] if allow_point else value[0] < value[1])
    if not ordered:
        fail(source, key, f"must be a range [low, high] with low {'<=' if allow_point else '<'} high, got {value!r}")
    if positive and value[0] <= 0:
        fail(source, key, f"must be positive, got {value!r}")
    if minimum is not None and value[0] < minimum:
        fail(source, key, f"must be >= {minimum}, got {value!r}")
    if maximum is not None and value[1] > maximum:
        fail(source, key, f"must be <= {maximum}, got {value!r}")


def check_at_least(config: dict, source: str, key: str, low, *, strict: bool = False):
    """``key`` must be ``>= low`` (``> low`` with ``strict``)."""
    value = get(config, key)
    if value < low or (strict and value == low):
        fail(source, key, f"must be {'>' if strict else '>='} {low}, got {value!r}")


def check_choice(config: dict, source: str, key: str, choices):
    """The value of ``key`` (dotted) must be one of ``choices``, else a :class:`ConfigError`."""
    value = get(config, key)
    if value not in choices:
        fail(source, key, f"must be one of {', '.join(map(repr, choices))}, got {value!r}")


def check_memory(source: str, key: str, nbytes: int, what: str, hint: str = "") -> None:
    """``what`` (set by ``key``) must fit in the memory available: ``nbytes`` is the configuration's estimate."""
    try:
        _check_memory(nbytes, what, hint=hint or f"lower {key}")
    except JobError as exc:
        fail(source, key, str(exc))


def leaf_keys(config: dict, prefix: str = "") -> list[str]:
    """The dotted names of the values of ``config`` (not of its tables), in order."""
    keys = []
    for key, value in config.items():
        keys += leaf_keys(value, f"{prefix}{key}.") if isinstance(value, dict) else [f"{prefix}{key}"]
    return keys


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, int | float | str):
        return json.dumps(value)  # a TOML float or integer, or a basic string with JSON's escapes
    raise TypeError(f"no TOML form for {value!r}")


def to_toml(config: dict, notes: dict, header: str = "", width: int = 100) -> str:
    """``config`` as TOML, each key preceded by its note (``notes[dotted key]``, a table's note above its header),
    after ``header`` as comment lines. Parses back to ``config``."""

    def comment(text: str) -> list[str]:
        return [f"# {line}" if line else "#" for line in textwrap.wrap(text, width - 2)] if text else []

    def table(values: dict, prefix: str) -> list[str]:
        lines = []
        for key, value in values.items():
            if not isinstance(value, dict):
                bare = re.fullmatch(r"[A-Za-z0-9_-]+", key)
                lines += [
                    *comment(notes.get(prefix + key, "")),
                    f"{key if bare else json.dumps(key)} = {_toml_value(value)}",
                ]
        for key, value in values.items():
            if isinstance(value, dict):
                name = prefix + key
                lines += ["", *comment(notes.get(name, "")), f"[{name}]", *table(value, name + ".")]
        return lines

    head = [line for text in header.splitlines() for line in (comment(text) or ["#"])]
    return "\n".join([*head, *([""] if head else []), *table(config, "")]).strip("\n") + "\n"
