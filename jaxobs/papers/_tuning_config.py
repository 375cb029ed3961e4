"""The config tables every ``jaxobs tune`` problem shares: ``[optimizer]`` (:class:`jaxobs.tune.TuneSettings`),
``[baseline]`` (the random search) and the seed, with their checks; plus the run's tag."""

from __future__ import annotations

import dataclasses
import hashlib
import json

from jaxobs._config import check_at_least, fail
from jaxobs.tune import TuneSettings

__all__ = ["optimizer_defaults", "BASELINE_DEFAULTS", "check_common", "settings", "config_tag"]

BASELINE_DEFAULTS = {"random_search": True, "spread": 2.0}  # candidates theta0 + U(-spread, spread)


def optimizer_defaults(**overrides) -> dict:
    """The ``[optimizer]`` table: :class:`jaxobs.tune.TuneSettings`'s fields, with a problem's ``overrides``."""
    table = dataclasses.asdict(TuneSettings())
    unknown = set(overrides) - set(table)
    if unknown:
        raise KeyError(f"not TuneSettings fields: {sorted(unknown)}")
    return {**table, **overrides}


def check_common(config: dict, source: str) -> None:
    """Check ``seed``, ``[optimizer]`` and ``[baseline]``; a :class:`jaxobs._config.ConfigError` names the key."""
    check_at_least(config, source, "seed", 0)
    check_at_least(config, source, "baseline.spread", 0, strict=True)
    try:
        settings(config).validate()
    except ValueError as exc:
        fail(source, "optimizer", str(exc))


def settings(config: dict) -> TuneSettings:
    return TuneSettings(**config["optimizer"])


def config_tag(config: dict) -> str:
    """A short hash of everything but the optimiser settings (a resumed run must match it)."""
    text = json.dumps({k: v for k, v in config.items() if k != "optimizer"}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]
