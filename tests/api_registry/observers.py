"""Registry entries: observers."""

ENTRIES = {}
EXEMPT = {}
