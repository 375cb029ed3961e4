"""Registry entries: systems."""

ENTRIES = {}
EXEMPT = {}
