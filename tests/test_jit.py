"""jaxobs._jit: a compiled core's first compiling call says so once at INFO level on its module's logger, nothing
is printed unless the caller configures logging, and a job's compilation is logged with its seconds."""

import logging
import os
import subprocess
import sys

import jax.numpy as jnp

from jaxobs._jit import Compiling, jit
from tests import ROOT


def test_the_first_compiling_call_logs_once(caplog):
    core = jit(lambda x: 2 * x, what="double")
    caplog.set_level(logging.INFO, logger=__name__)
    core(jnp.ones(3))
    core(jnp.ones(3))  # the same program: no compilation
    core(jnp.ones(4))  # another shape compiles, but the first compilation was the one to say
    said = [r for r in caplog.records if r.name == __name__]
    assert len(said) == 1 and said[0].levelno == logging.INFO
    assert said[0].getMessage().startswith("double: the first call compiled its program in ")
    assert core.lower(jnp.ones(2)) is not None  # the jitted function's own methods still answer


def test_compiling_logs_what_and_keeps_the_seconds(caplog):
    caplog.set_level(logging.INFO, logger=__name__)
    with Compiling(logging.getLogger(__name__), "the step") as timer:
        pass
    assert [r.getMessage() for r in caplog.records][0] == "compiling the step ..."
    assert caplog.records[1].getMessage() == f"compiled the step in {timer.seconds:.1f} s"


def test_a_design_call_says_it_compiled_only_where_logging_is_configured():
    """``jo.dlqr``'s first call: one INFO line from jaxobs.matrix_equations with ``logging.basicConfig``; without
    it, nothing on stderr."""
    call = "import jax.numpy as jnp, jaxobs as jo; jo.dlqr(0.9 * jnp.eye(2), jnp.ones((2, 1)), jnp.eye(2), jnp.eye(1))"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for configure in ("", "import logging; logging.basicConfig(level=logging.INFO); "):
        done = subprocess.run([sys.executable, "-c", configure + call], env=env, capture_output=True, text=True,
                              timeout=300, check=True)  # fmt: skip
        said = [line for line in done.stderr.splitlines() if line.startswith("INFO:jaxobs")]
        if configure:
            assert len(said) == 1 and said[0].startswith("INFO:jaxobs.matrix_equations:dare (behind dlqr"), said
        else:
            assert done.stderr == "", done.stderr
