"""The numbers README.md prints, for the tests that pin each one where it is computed.

``pin(value, pattern)`` finds the number captured by ``pattern`` (a regular expression over the README with its
line breaks read as spaces; it must match exactly once) and asserts that ``value`` shows as that number at the
printed precision: within half a unit of its last printed digit, plus an explicit ``noise`` allowance where the
value depends on the machine (e.g. Monte-Carlo fractions near a rounding boundary). Editing a number in the
README without the code, or the code without the README, fails the pinning test.
"""

from __future__ import annotations

import re
from decimal import Decimal

from tests import ROOT

README = ROOT / "README.md"


def _text() -> str:
    return " ".join(README.read_text().split())


def printed(pattern: str, group: int = 1) -> str:
    """The text of capture ``group`` of the single match of ``pattern`` in the README."""
    matches = list(re.finditer(pattern, _text()))
    assert len(matches) == 1, f"README: {len(matches)} matches of {pattern!r} (need exactly one)"
    return matches[0].group(group)


def half_unit(number: str) -> float:
    """Half a unit of the last printed digit of ``number`` ("0.0413" -> 5e-5, "7e-14" -> 5e-15)."""
    return 0.5 * 10.0 ** Decimal(number.replace("−", "-")).as_tuple().exponent


def pin(value, pattern: str, group: int = 1, *, noise: float = 0.0) -> float:
    """Assert that ``value`` rounds to the README number captured by ``pattern``; returns that number."""
    text = printed(pattern, group)
    number = float(text.replace("−", "-"))
    tolerance = half_unit(text) * (1 + 1e-9) + noise
    assert abs(float(value) - number) <= tolerance, (
        f"README prints {text} ({pattern!r}); the code gives {float(value):.6g} (allowed +-{tolerance:.2g})"
    )
    return number
