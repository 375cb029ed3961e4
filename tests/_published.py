"""The numbers the project publishes (README.md and the pages of docs/), for the tests that pin each one where it
is computed.

``pin(value, pattern)`` finds the number captured by ``pattern`` (a regular expression over each published page
with its line breaks read as spaces; it must match exactly once across all of them) and asserts that ``value``
shows as that number at the printed precision: within half a unit of its last printed digit, plus an explicit
``noise`` allowance where the value depends on the machine (e.g. Monte-Carlo fractions near a rounding boundary).
Editing a published number without the code, or the code without the page, fails the pinning test.
"""

from __future__ import annotations

import re
from decimal import Decimal

from tests import ROOT


def pages() -> list:
    """The published pages: README.md and every Markdown page under docs/."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def printed(pattern: str, group: int = 1) -> str:
    """The text of capture ``group`` of the single match of ``pattern`` across the published pages."""
    matches = {}
    for page in pages():
        found = list(re.finditer(pattern, " ".join(page.read_text().split())))
        if found:
            matches[page.relative_to(ROOT).as_posix()] = found
    count = sum(len(found) for found in matches.values())
    where = ", ".join(f"{name} ({len(found)})" for name, found in matches.items()) or "no page"
    assert count == 1, f"{count} matches of {pattern!r} in {where}; need exactly one across README.md and docs/"
    return next(iter(matches.values()))[0].group(group)


def half_unit(number: str) -> float:
    """Half a unit of the last printed digit of ``number`` ("0.0413" -> 5e-5, "7e-14" -> 5e-15)."""
    return 0.5 * 10.0 ** Decimal(number.replace("−", "-")).as_tuple().exponent


def pin(value, pattern: str, group: int = 1, *, noise: float = 0.0) -> float:
    """Assert that ``value`` rounds to the published number captured by ``pattern``; returns that number."""
    text = printed(pattern, group)
    number = float(text.replace("−", "-"))
    tolerance = half_unit(text) * (1 + 1e-9) + noise
    assert abs(float(value) - number) <= tolerance, (
        f"published {text} ({pattern!r}); the code gives {float(value):.6g} (allowed +-{tolerance:.2g})"
    )
    return number
