"""Batches that jaxlib 0.10's CPU LAPACK kernels deadlock on a 2-core CPU unless they are split into blocks.

``python lapack_case.py CASE SIZE OUT`` runs one case over ``SIZE`` elements and prints ``ok`` and a checksum:

* ``two-expm``: two matrix exponentials of a 5 x 5 matrix per configuration, a sweep with ``chunk_size = SIZE``
  (the reduced case: two independent batched LU factorisations in one program);
* ``dead-time``: a user's sweep of a two-mass spring (4 states, dead time 0.5-3.5 ms traced at h = 2 ms, 2 delay
  slots) under an LQR, its closed-loop spectral radius per configuration, ``chunk_size = SIZE``;
* ``safe-vmap``: the two exponentials under ``jax.jit(jaxobs.batching.safe_vmap(...))``, no sweep.

Run by tests/test_batching.py in a subprocess with a timeout, so a deadlock fails the test instead of hanging it.
"""

import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxobs as jo  # noqa: E402
from jaxobs.batching import safe_vmap  # noqa: E402


def two_expm(a):
    m = jnp.eye(5) * a + 0.1 * jnp.ones((5, 5))
    return jax.scipy.linalg.expm(m) + jax.scipy.linalg.expm(2 * m)


def two_mass(k):
    """A motor inertia driving a load through a spring of stiffness ``k``: states (q_m, v_m, q_l, v_l)."""
    jm, jl = 0.01, 0.02
    A = jnp.array([[0, 1, 0, 0], [-k / jm, 0, k / jm, 0], [0, 0, 0, 1], [k / jl, 0, -k / jl, 0]], float)
    return jo.ss(A, jnp.array([[0.0], [1 / jm], [0.0], [0.0]]), jnp.eye(4)[:1])


NOMINAL = jo.c2d(two_mass(10.0), 0.002, 0.0015, n_delay=2)
GAIN = jo.dlqr(NOMINAL.A, NOMINAL.B, jnp.eye(NOMINAL.A.shape[0]), jnp.eye(1))[0]


def dead_time(params):
    k, tau = params
    plant = jo.c2d(two_mass(k), 0.002, tau, n_delay=2)
    return {"radius": jnp.max(jnp.abs(jnp.linalg.eigvals(plant.A - plant.B @ GAIN)))}


def sample(key, index):
    k_key, tau_key = jax.random.split(key)
    k = jax.random.uniform(k_key, (), minval=7.0, maxval=13.0)
    return k, jax.random.uniform(tau_key, (), minval=5e-4, maxval=3.5e-3)


def main(case: str, size: int, out: str) -> None:
    if case == "two-expm":
        sample_a = lambda key, index: jax.random.uniform(key, (), minval=0.1, maxval=1.0)
        jo.run_sweep(sample_a, lambda a: {"e": two_expm(a)[0, 0]}, size, out, chunk_size=size, progress=False)
        value = jo.load_results(out)["metric.e"]
    elif case == "dead-time":
        jo.run_sweep(sample, dead_time, size, out, chunk_size=size, progress=False)
        value = jo.load_results(out)["metric.radius"]
    elif case == "safe-vmap":
        value = np.asarray(jax.jit(safe_vmap(two_expm))(jnp.linspace(0.1, 1.0, size)))
    else:
        raise SystemExit(f"unknown case {case!r}")
    print("ok", value.shape[0], float(np.sum(value)))


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), sys.argv[3])
