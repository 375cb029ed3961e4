"""jaxobs.batching (blocks that keep jaxlib's CPU LAPACK kernels sequential) and the jobs' stall watch."""

import math
import subprocess
import sys
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxobs as jo
from jaxobs._resources import Stalled, StallWatch
from jaxobs.batching import MIN_WORK_PER_TASK, lapack_calls, safe_vmap
from tests import ROOT

CASE = ROOT / "tests" / "sweep_scripts" / "lapack_case.py"


def two_expm(a):
    return jax.scipy.linalg.expm(a) @ jax.scipy.linalg.expm(2 * a)


def test_bounds_are_jaxlibs_sequential_batches():
    """ceil(200000 / cost) matrices per call: LU of 5 x 5 (cost 125) 1600, its triangular solves too; the 6 x 6
    nonsymmetric eigenproblem costs 10 n^3; a complex LU 3 m n min(m, n); a 60 x 60 LU is one per call."""
    calls = lapack_calls(jax.vmap(two_expm), jnp.zeros((4096, 5, 5)))
    assert {(name, bound) for name, _, bound in calls} == {("lu", 1600), ("triangular_solve", 1600)}
    assert lapack_calls(jnp.linalg.eigvals, jnp.eye(6)) == [("eig", (6, 6), -(-MIN_WORK_PER_TASK // 2160))]
    assert lapack_calls(jnp.linalg.det, jnp.eye(4, dtype=complex))[0][2] == -(-MIN_WORK_PER_TASK // (3 * 64))
    assert lapack_calls(jnp.linalg.det, jnp.eye(60))[0][2] == 1
    assert lapack_calls(lambda x: x @ x, jnp.eye(5)) == []


def test_lapack_calls_read_loop_bodies_and_solves():
    def f(a):
        return jax.lax.fori_loop(0, 3, lambda i, x: jnp.linalg.solve(a, x), jnp.ones(4))

    names = [(name, shape) for name, shape, _ in lapack_calls(f, jnp.eye(4))]
    assert ("lu", (4, 4)) in names and ("triangular_solve", (4, 1)) in names


def _within_bounds(fn, *args) -> bool:
    """Whether every LAPACK call in the program of ``fn`` takes at most its bound's matrices."""
    return all(math.prod(shape[:-2]) <= bound for _, shape, bound in lapack_calls(fn, *args))


def test_safe_vmap_equals_vmap_with_every_call_within_its_bound():
    a = 0.1 * jax.random.normal(jax.random.key(0), (3300, 5, 5))
    want = jax.vmap(two_expm)(a)
    np.testing.assert_array_equal(safe_vmap(two_expm)(a), want)  # blocks of 1600, 1600, 100
    np.testing.assert_array_equal(jax.jit(safe_vmap(two_expm))(a), want)
    assert not _within_bounds(jax.vmap(two_expm), a) and _within_bounds(safe_vmap(two_expm), a)


def test_calls_in_loop_bodies_and_large_elements_are_blocked():
    """A scan body's LU of 60 x 60 matrices and an element holding ten of them (past the bound alone): one matrix
    per call."""

    def f(a):
        x, _ = jax.lax.scan(lambda x, _: (jnp.linalg.solve(a[0], x), None), jnp.ones(60), None, length=2)
        return x + jnp.sum(jax.vmap(jnp.linalg.det)(a))

    a = jnp.stack([jnp.eye(60) * (1 + 0.01 * i) for i in range(10)])
    batch = jnp.stack([a, 2 * a, 3 * a])
    np.testing.assert_allclose(jax.jit(safe_vmap(f))(batch), jax.vmap(f)(batch), rtol=1e-12)
    assert not _within_bounds(jax.vmap(f), batch) and _within_bounds(safe_vmap(f), batch)
    assert {shape for name, shape, _ in lapack_calls(safe_vmap(f), batch) if name == "lu"} == {(1, 60, 60)}


def test_safe_vmap_shared_arguments_and_gradient():
    a = 0.1 * jax.random.normal(jax.random.key(1), (1700, 5, 5))

    def solve(m, scale):
        return jnp.linalg.solve(jnp.eye(5) + scale * m, jnp.ones(5))

    def loss(scale, a):
        return jnp.sum(safe_vmap(solve, (0, None))(a, scale))

    def unblocked(scale, a):
        return jnp.sum(jax.vmap(solve, (0, None))(a, scale))

    np.testing.assert_allclose(jax.grad(loss)(0.5, a), jax.grad(unblocked)(0.5, a), rtol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.grad(loss))(0.5, a), jax.grad(unblocked)(0.5, a), rtol=1e-12)


def test_safe_lapack_keeps_pytrees_and_keywords():
    def f(tree, *, shift):
        return {"det": jax.vmap(jnp.linalg.det)(tree["m"] + shift), "m": tree["m"]}

    m = jnp.stack([jnp.eye(5)] * 2000)
    out = jo.safe_lapack(f)({"m": m}, shift=1.0)
    np.testing.assert_allclose(out["det"], 6.0)  # det(I + ones(5, 5)) = 1 + 5
    assert out["m"].shape == m.shape


def _run_case(case: str, size: int, out):
    done = subprocess.run([sys.executable, str(CASE), case, str(size), str(out)], capture_output=True, text=True,
                          timeout=240)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[:2] == ["ok", str(size)]


def test_two_exponentials_sweep_at_chunk_16384(tmp_path):
    """The reduced case of the deadlock (two batched LU factorisations in one program), which hung jit(vmap(...))
    at 4096 and above on a 2-core CPU, as a sweep with chunk_size 16384: it finishes (a hang times out)."""
    _run_case("two-expm", 16384, tmp_path / "sweep")


@pytest.mark.slow
@pytest.mark.parametrize("case", ["dead-time", "safe-vmap"])
def test_traced_dead_time_sweep_and_safe_vmap_at_16384(tmp_path, case):
    _run_case(case, 16384, tmp_path / "sweep")


@pytest.fixture
def quick_watch(monkeypatch):
    monkeypatch.setattr(StallWatch, "POLL_SECONDS", 0.1)
    monkeypatch.setattr(StallWatch, "IDLE_SECONDS", 1.0)
    monkeypatch.setattr(StallWatch, "MIN_SECONDS", 0.5)
    monkeypatch.setattr(StallWatch, "FACTOR", 5.0)


def test_an_idle_wait_on_cpu_is_reported(quick_watch):
    start = time.perf_counter()
    with StallWatch("the job", "do this", cpu=True) as watch, pytest.raises(Stalled, match="the job: step 1 .*idle"):
        with watch.waiting("step 1") as wait:
            wait["pending"] = None
            time.sleep(30)
    assert time.perf_counter() - start < 5


def test_a_wait_far_slower_than_the_slowest_is_reported(quick_watch):
    with StallWatch("the job", "smaller chunks", cpu=False) as watch:
        with watch.waiting("first", program="other"):  # another program: its slow wait sets no bound on "step"
            time.sleep(1.5)
        for _ in range(2):
            with watch.waiting("fast", program="step"):
                time.sleep(0.1)
        start = time.perf_counter()
        with pytest.raises(Stalled, match=r"5x the slowest step so far.*smaller chunks"):
            with watch.waiting("slow", program="step"):
                time.sleep(30)
    assert 0.5 <= time.perf_counter() - start < 5


def test_a_programs_first_wait_has_no_time_bound(quick_watch):
    """A first wait may compile its program: only the idle rule applies to it (here off: cpu=False)."""
    with StallWatch("the job", "", cpu=False) as watch:
        with watch.waiting("fast", program="a"):
            time.sleep(0.1)
        with watch.waiting("compiling", program="b"):
            time.sleep(1.5)


def test_busy_waits_are_not_stalls(quick_watch):
    with StallWatch("the job", "", cpu=True) as watch, watch.waiting("busy"):
        end = time.perf_counter() + 2.5
        while time.perf_counter() < end:
            pass


def test_a_sweep_whose_chunk_blocks_is_stopped_by_the_watch(quick_watch, tmp_path):
    """Chunk 1's evaluation waits in a host callback that nothing releases: the sweep raises Stalled within the
    watch's bounds (shortened here), chunk 0 is kept; releasing the callback afterwards lets the computation (and
    the test) end."""
    release = threading.Event()

    def blocking(i):
        if int(i) >= 4:
            release.wait(60)
        return np.float64(i)

    def evaluate(i):
        shape = jax.ShapeDtypeStruct((), jnp.float64)
        return {"x": jax.pure_callback(blocking, shape, i, vmap_method="sequential")}

    start = time.perf_counter()
    try:
        with pytest.raises(Stalled, match=r"chunk\(s\) 1 made no progress .*finished chunks are kept"):
            jo.run_sweep(lambda key, i: i, evaluate, 8, tmp_path, chunk_size=4, progress=False)
    finally:
        release.set()
    assert time.perf_counter() - start < 10
    assert list(jo.sweep.read_manifest(tmp_path)["completed"]) == ["0"]


def test_a_tuning_step_that_blocks_is_stopped_by_the_watch(quick_watch, tmp_path):
    """The second evaluation's rollouts wait in a host callback that nothing releases: tune raises Stalled (and
    says where the checkpoint is) instead of waiting."""
    import optax

    from jaxobs.tuning import TuneSettings, TuningProblem, tune

    release, calls = threading.Event(), []

    def blocking(x):
        calls.append(1)
        if len(calls) > 1:
            release.wait(60)
        return np.asarray(x)

    def losses(theta, t):
        x = jax.lax.stop_gradient(theta["x"])  # the callback's input has no tangent
        wait = jax.pure_callback(blocking, jax.ShapeDtypeStruct((), jnp.float64), x, vmap_method="sequential")
        return (theta["x"] - t) ** 2 + 0 * wait, t < -1e9

    problem = TuningProblem({"x": jnp.array(0.0)}, losses, jnp.array([1.0, 3.0]), jnp.array([2.0]))
    settings = TuneSettings(optax.sgd(0.1), steps=5, gradient="forward")
    try:
        with pytest.raises(Stalled, match=r"evaluation 2 made no progress.*checkpoint saved to"):
            tune(problem, settings, checkpoint=tmp_path / "c.npz", progress=False)
    finally:
        release.set()
