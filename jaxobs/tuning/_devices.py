"""The tuning jobs' rollouts spread over every device of every process, and their blocking waits watched (shared by
:mod:`jaxobs.tuning.job` and :mod:`jaxobs.tuning.search`)."""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxobs._jit import Compiling
from jaxobs._resources import StallWatch, compile_checked

logger = logging.getLogger("jaxobs.tuning")

AXIS = "plants"

STALL_HINT = (
    "use fewer training plants, starts or screening candidates, or set NPROC=1 in the environment (one XLA "
    "intra-op thread); a checkpoint keeps the accepted steps"
)


def mesh_of(devices: list) -> Mesh | None:
    """A 1-D mesh (axis "plants") over ``devices``; None for a single device."""
    return None if len(devices) == 1 else Mesh(np.array(devices), (AXIS,))


def place(batch, mesh: Mesh | None):
    """``batch`` padded to a multiple of the mesh's size with copies of its last plant, each process placing its
    own devices' rows (``NamedSharding`` over the batch axis); ``batch`` itself without a mesh."""
    if mesh is None:
        return batch
    size = int(jax.tree.leaves(batch)[0].shape[0])
    rows = np.minimum(np.arange(-(-size // mesh.size) * mesh.size), size - 1)
    sharding = NamedSharding(mesh, PartitionSpec(AXIS))

    def put(leaf):
        padded = np.asarray(leaf)[rows]
        return jax.make_array_from_callback(padded.shape, sharding, padded.__getitem__)

    return jax.tree.map(put, batch)


@functools.lru_cache(maxsize=8)  # the same function for the same problem: jax.jit's caches hold across calls
def spread(losses: Callable, mesh: Mesh | None, size: int) -> Callable:
    """``losses`` over a batch of ``size`` plants placed by :func:`place`: each device runs the rollouts of its
    own rows (``jax.shard_map``), and the padding rows' losses are dropped, so that what follows (the objective,
    its gradient) is that of ``losses`` on the batch itself; the gradient's terms are summed across devices.
    ``losses`` itself without a mesh. ``losses`` must treat the plants independently (as a ``vmap`` does)."""
    if mesh is None:
        return losses
    spec = PartitionSpec(AXIS)  # check_vma=False: rollouts may scan from constant carries
    per_device = jax.shard_map(losses, mesh=mesh, in_specs=(PartitionSpec(), spec), out_specs=spec, check_vma=False)
    return lambda theta, batch: jax.tree.map(lambda x: x[:size], per_device(theta, batch))


def jit_over(fn: Callable, mesh: Mesh | None, rows: tuple[bool, ...]) -> Callable:
    """``jax.jit(fn)``; over a mesh, the arguments flagged in ``rows`` are batches placed by :func:`place`, the
    others (and the outputs) replicated, so every process gets the whole result."""
    if mesh is None:
        return jax.jit(fn)
    replicated, placed = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec(AXIS))
    return jax.jit(fn, in_shardings=tuple(placed if r else replicated for r in rows), out_shardings=replicated)


def host(tree):
    """``tree``'s leaves as NumPy arrays (a replicated result of every process, or the arguments of a call)."""
    return jax.tree.map(np.asarray, tree)


def compile_over(build: Callable, batch, first, what: str, hint: str, alone=None):
    """``(compiled, placed batch, mesh)``: ``build(mesh) -> fn(first, batch)`` compiled over every device of every
    process (:func:`jit_over`, memory checked by :func:`jaxobs._resources.compile_checked`), not logged. ``alone``:
    the program already lowered for a single device, used when there is one."""
    mesh = mesh_of(jax.devices())
    placed = place(batch, mesh)
    if mesh is None and alone is not None:
        lowered = alone
    else:
        lowered = jit_over(build(mesh), mesh, (False, True)).lower(host(first), placed)
    return compile_checked(lowered, what, hint=hint), placed, mesh


def compile_spread(build: Callable, batch, first, what: str, hint: str):
    """:func:`compile_over`, logged at INFO level (:class:`jaxobs._jit.Compiling`): ``(compiled, placed batch, mesh,
    seconds)``."""
    with Compiling(logger, what) as timer:
        compiled, placed, mesh = compile_over(build, batch, first, what, hint)
    return compiled, placed, mesh, timer.seconds


def stall_watch(what: str) -> StallWatch:
    """The :class:`jaxobs._resources.StallWatch` of a tuning job's computations."""
    return StallWatch(what, STALL_HINT, cpu=jax.devices()[0].platform == "cpu")


def watched(stall: StallWatch, label: str, fn: Callable, *args):
    """``fn(*args)`` (a computation, compiled or compiled on its first call) brought to the host under ``stall``'s
    watch."""
    with stall.waiting(label, program=id(fn)) as wait:
        wait["pending"] = fn(*args)
        return host(wait["pending"])
