"""Registry entries: vehicle."""

ENTRIES = {}
EXEMPT = {}
