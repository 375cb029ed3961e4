"""Registry entries: jobs."""

ENTRIES = {}
EXEMPT = {}
