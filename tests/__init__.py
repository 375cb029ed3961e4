"""The test suite; it mirrors the package (tests/observers/ for jaxobs/observers/, ...)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root directory."""

FAST_COMPILE_FLAGS = (
    "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0 "
    "--xla_llvm_disable_expensive_passes=true --xla_cpu_parallel_codegen_split_count=1 --xla_cpu_max_isa=AVX"
)
"""XLA's cheapest compilation (legacy loop emitters, no LLVM optimisation, no FMA), which tests/conftest.py sets for
the suite: most of its programs run once, so compiling them costs more than running them."""


def run_cli(args: list[str], timeout: float = 1200) -> None:
    """``jaxobs *args`` in a subprocess whose XLA compiles with its default (optimising) settings, for the long runs
    of the published layer, whose run time outweighs their compilation; fails the test on a non-zero exit."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, XLA_FLAGS=os.environ.get("XLA_FLAGS", "").replace(FAST_COMPILE_FLAGS, "").strip())
    done = subprocess.run([sys.executable, "-m", "jaxobs.cli", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)  # fmt: skip
    assert done.returncode == 0, f"jaxobs {' '.join(args)} exited with {done.returncode}:\n{done.stderr[-3000:]}"
