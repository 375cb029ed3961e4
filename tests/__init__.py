"""The test suite; it mirrors the package (tests/observers/ for jaxobs/observers/, ...)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root directory."""
