"""Test configuration: float64 everywhere, JAX's persistent compilation cache, one JAX configuration for every
test, a modest hypothesis profile.

x64 is switched on here (the entry point of the test run), never on import of the library.
The compiled programs are kept in ``.jax_cache/`` at the repository root (or in ``$JAXOBS_TEST_CACHE``), for this
process and, through the environment, for every subprocess a test starts: a second run reads them back instead of
compiling. XLA compiles the suite's programs with its cheapest settings (``tests.FAST_COMPILE_FLAGS``, prepended
to ``$XLA_FLAGS``): most programs run once, so compiling them costs more than running them.
``HYPOTHESIS_PROFILE=thorough`` runs the property tests with more examples.
"""

import gc
import os
import signal
import threading
import warnings

from tests import FAST_COMPILE_FLAGS, ROOT

# before JAX starts its CPU backend, and inherited by every subprocess (tests.run_cli undoes it for the long runs)
os.environ["XLA_FLAGS"] = f"{FAST_COMPILE_FLAGS} {os.environ.get('XLA_FLAGS', '')}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

jax.config.update("jax_enable_x64", True)

CACHE_DIR = os.environ.get("JAXOBS_TEST_CACHE") or str(ROOT / ".jax_cache")
CACHE_MIN_COMPILE_SECONDS = 0.05  # every program but the tiniest (single eager operations): the suite's are small
os.environ["JAX_COMPILATION_CACHE_DIR"] = CACHE_DIR  # read by JAX on import in the subprocesses
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(CACHE_MIN_COMPILE_SECONDS)
jax.config.update("jax_compilation_cache_dir", CACHE_DIR)
jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_SECONDS)


def _jax_config() -> dict:
    return {name: getattr(jax.config, name) for name in dir(jax.config) if name.startswith("jax_")}


_SESSION_CONFIG = _jax_config()


@pytest.fixture(autouse=True)
def _restore_jax_config():
    """Undo any change of JAX's global configuration a test (or a peer imported by it) made: dynamax, for one,
    sets ``jax_default_matmul_precision`` when imported, which would change every later test's programs."""
    yield
    for name, value in _jax_config().items():
        if name in _SESSION_CONFIG and value != _SESSION_CONFIG[name]:
            jax.config.update(name, _SESSION_CONFIG[name])


MAX_MAPPINGS = 35_000  # before the next test file; one file adds at most ~8 000, the limit is 65 530


def _mappings() -> int:
    try:
        with open("/proc/self/maps") as maps:
            return sum(1 for _ in maps)
    except OSError:  # not Linux: no count, always free
        return MAX_MAPPINGS


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop JAX's caches of compiled programs after a test file once the process holds ``MAX_MAPPINGS`` memory
    mappings. A worker runs hundreds of tests; kept alive, their XLA executables grew one process past 60 000
    mappings (Linux's default ``vm.max_map_count`` is 65 530) and XLA's compiler then crashed (SIGSEGV) late in
    the run. Below the threshold the files keep sharing their compiled programs."""
    yield
    if _mappings() >= MAX_MAPPINGS:
        jax.clear_caches()
        gc.collect()


@pytest.fixture(autouse=True)
def _python_handles_ctrl_c(request):
    """Every test starts with Python's own Ctrl-C handler, which the interrupt and stall watches build on
    (jaxobs._resources): a test (or a library it loads) that leaves another one has it put back, with a warning
    naming the handler and the test, so that the tests after it do not fail for it."""
    yield
    handler = signal.getsignal(signal.SIGINT)
    if handler is not signal.default_int_handler and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.default_int_handler)
        warnings.warn(f"{request.node.nodeid} left the SIGINT handler {handler!r}; Python's was put back", stacklevel=1)


settings.register_profile(
    "jaxobs",
    max_examples=12,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("thorough", max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "jaxobs"))
