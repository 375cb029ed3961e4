"""Registry entries: estimation."""

ENTRIES = {}
EXEMPT = {}
