"""Registry entries: models."""

ENTRIES = {}
EXEMPT = {}
