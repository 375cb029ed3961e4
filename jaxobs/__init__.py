"""jaxobs."""
