"""Test configuration: float64 everywhere and a modest hypothesis profile.

x64 is switched on here (the entry point of the test run), never on import of the library
(DESIGN.md, "Precision"). ``HYPOTHESIS_PROFILE=thorough`` runs the property tests with more examples.
"""

import os

import jax
from hypothesis import HealthCheck, settings

jax.config.update("jax_enable_x64", True)

settings.register_profile(
    "jaxobs",
    max_examples=12,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("thorough", max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "jaxobs"))
