"""Registry entries: mjx."""

ENTRIES = {}
EXEMPT = {}
