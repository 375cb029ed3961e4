"""Batching that cannot deadlock jaxlib's CPU LAPACK kernels.

jaxlib 0.10's CPU LAPACK kernels (LU, triangular solves, Cholesky, eigenvalues, QR, SVD, Schur, ...) split a
batch of matrices into tasks on XLA's intra-op thread pool and block until those tasks are done, once the batch
holds more than ``ceil(200000 / cost)`` matrices (``cost`` the kernel's flop estimate per matrix, e.g. ``n**3`` for
the LU of an ``n x n`` matrix). XLA runs independent operations of one program at the same time on that pool, so
two such calls (two matrix exponentials, two solves) can occupy every thread of a 2-core pool while their tasks
wait behind them: the program never returns and the CPU is idle. Up to the bound a kernel runs on the thread that
called it and nothing waits. docs/theory/jobs.md has the mechanism and the measurements.

:func:`safe_lapack` rewrites a function so that each of its LAPACK calls over more matrices than its bound runs
as a loop over blocks of at most that many (``jax.lax.map``), everything else unchanged; :func:`safe_vmap` is
``jax.vmap`` with that rewrite, which :func:`jaxobs.run_sweep` and :func:`jaxobs.tune` apply to every program they
compile. :func:`lapack_calls` lists a function's LAPACK calls and their bounds.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import numpy as np
from jax.extend import core as jex_core

__all__ = ["MIN_WORK_PER_TASK", "lapack_calls", "safe_lapack", "safe_vmap"]

MIN_WORK_PER_TASK = 200_000
"""jaxlib's ``kMinWorkPerTask``: a call on ``k`` matrices of cost ``c`` stays on its thread while
``k <= ceil(MIN_WORK_PER_TASK / c)``."""

# cost per matrix (m x n) as jaxlib 0.10.2 estimates it (lapack_kernels.cc): an upper bound where the kernel's own
# formula subtracts lower-order terms; complex kernels count 3x
_COSTS = {
    "lu": lambda m, n: m * n * min(m, n),
    "cholesky": lambda m, n: m**3 // 3,
    "eigh": lambda m, n: 5 * m**3,
    "eig": lambda m, n: 10 * m**3,
    "schur": lambda m, n: 5 * m**3,
    "hessenberg": lambda m, n: 2 * m**3,
    "tridiagonal": lambda m, n: 2 * m**3,
    "svd": lambda m, n: 10 * m * n * min(m, n),
    "qr": lambda m, n: 4 * m * n * min(m, n),
    "geqrf": lambda m, n: 2 * m * n * min(m, n),
    "geqp3": lambda m, n: 2 * m * n * min(m, n),
    "householder_product": lambda m, n: 4 * m * n * min(m, n),
    "ormqr": lambda m, n: 4 * m * n * max(m, n),
}
# the operand whose shape sets the cost: the right-hand side of the solves, the matrix otherwise
_OPERAND = {"triangular_solve": 1, "tridiagonal_solve": 3}


def _bound(eqn) -> tuple[tuple[int, ...], int] | None:
    """``(batch shape, most matrices per call on the calling thread)`` of a LAPACK equation; None for any other."""
    name = eqn.primitive.name
    if name not in _COSTS and name not in _OPERAND:
        return None
    aval = eqn.invars[_OPERAND.get(name, 0)].aval
    *batch, m, n = aval.shape
    if name == "triangular_solve":
        cost = m * n * (m if eqn.params["left_side"] else n)
    elif name == "tridiagonal_solve":
        cost = 5 * m * n
    else:
        cost = _COSTS[name](m, n)
    if np.issubdtype(aval.dtype, np.complexfloating):
        cost *= 3
    return tuple(batch), -(-MIN_WORK_PER_TASK // max(int(cost), 1))


def _subjaxprs(params):
    for value in params.values():
        for item in value if isinstance(value, tuple | list) else (value,):
            if isinstance(item, jex_core.ClosedJaxpr):
                yield item.jaxpr
            elif isinstance(item, jex_core.Jaxpr):
                yield item


def _walk(jaxpr):
    for eqn in jaxpr.eqns:
        yield eqn
        for sub in _subjaxprs(eqn.params):
            yield from _walk(sub)


def lapack_calls(fn: Callable, *args) -> list[tuple[str, tuple[int, ...], int]]:
    """The CPU LAPACK calls of ``fn(*args)``: ``(primitive, operand shape, bound)`` each, in program order, loops'
    and branches' bodies included, where ``bound`` is the most matrices the call takes on its calling thread
    (``ceil(200000 / cost)``; traced with ``jax.make_jaxpr``; ``args`` may be ``jax.ShapeDtypeStruct``).

    Example::

        >>> import jax, jax.numpy as jnp
        >>> lapack_calls(jax.vmap(jnp.linalg.det), jnp.zeros((4096, 5, 5)))  # 4096 LUs, 1600 on one thread
        [('lu', (4096, 5, 5), 1600)]
    """
    calls = []
    for eqn in _walk(jax.make_jaxpr(fn)(*args).jaxpr):
        bound = _bound(eqn)
        if bound is not None:
            calls.append((eqn.primitive.name, eqn.invars[_OPERAND.get(eqn.primitive.name, 0)].aval.shape, bound[1]))
    return calls


def _over(jaxpr) -> bool:
    """Whether any LAPACK call of ``jaxpr`` (or of its bodies) takes more matrices than its bound."""
    return any((b := _bound(eqn)) is not None and math.prod(b[0]) > b[1] for eqn in _walk(jaxpr))


def _blocked(eqn, invals: list):
    """``eqn`` (a LAPACK call past its bound) on ``invals`` as a loop over blocks of at most the bound's matrices:
    the batch dimensions (shared by the batched operands and the outputs) are flattened, mapped, restored."""
    batch, bound = _bound(eqn)
    count, rank = math.prod(batch), len(batch)
    batched = [np.shape(x)[:rank] == batch for x in invals]
    flat = [jax.numpy.reshape(x, (count, *np.shape(x)[rank:])) for x, b in zip(invals, batched, strict=True) if b]

    def one(xs):
        it = iter(xs)
        return eqn.primitive.bind(*(next(it) if b else x for x, b in zip(invals, batched, strict=True)), **eqn.params)

    out = jax.lax.map(one, flat, batch_size=bound)
    restore = lambda y: jax.numpy.reshape(y, batch + y.shape[1:])
    return [restore(y) for y in out] if eqn.primitive.multiple_results else restore(out)


def _rewritten(sub):
    """``sub`` (a ``ClosedJaxpr`` or ``Jaxpr``) with its LAPACK calls blocked; ``sub`` itself when none is over."""
    jaxpr = sub.jaxpr if isinstance(sub, jex_core.ClosedJaxpr) else sub
    if not _over(jaxpr):
        return sub
    consts = sub.consts if isinstance(sub, jex_core.ClosedJaxpr) else []
    avals = [jax.ShapeDtypeStruct(v.aval.shape, v.aval.dtype) for v in (*jaxpr.constvars, *jaxpr.invars)]
    new = jax.make_jaxpr(lambda *a: _evaluate(jaxpr, a[: len(consts)], a[len(consts) :]))(*avals)
    if new.consts:
        raise NotImplementedError(f"safe_lapack cannot rewrite the body of {sub!r}: its rewrite holds constants")
    body = new.jaxpr.replace(constvars=new.jaxpr.invars[: len(consts)], invars=new.jaxpr.invars[len(consts) :])
    return jex_core.ClosedJaxpr(body, consts) if isinstance(sub, jex_core.ClosedJaxpr) else body


def _params(params: dict) -> dict:
    """``params`` with every body (a jaxpr, or a tuple of them) rewritten by :func:`_rewritten`."""
    new = {}
    for key, value in params.items():
        if isinstance(value, jex_core.ClosedJaxpr | jex_core.Jaxpr):
            value = _rewritten(value)
        elif isinstance(value, tuple) and any(isinstance(v, jex_core.ClosedJaxpr | jex_core.Jaxpr) for v in value):
            items = [_rewritten(v) if isinstance(v, jex_core.ClosedJaxpr | jex_core.Jaxpr) else v for v in value]
            value = value._make(items) if hasattr(value, "_make") else tuple(items)
        new[key] = value
    return new


def _evaluate(jaxpr, consts, args) -> list:
    """``jaxpr`` evaluated like ``jax.core.eval_jaxpr``, with LAPACK calls past their bound blocked."""
    env = dict(zip(jaxpr.constvars, consts, strict=True)) | dict(zip(jaxpr.invars, args, strict=True))
    read = lambda v: v.val if isinstance(v, jex_core.Literal) else env[v]
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        bound = _bound(eqn)
        if bound is not None and math.prod(bound[0]) > bound[1]:
            out = _blocked(eqn, invals)
        else:
            params = _params(eqn.params) if any(True for _ in _subjaxprs(eqn.params)) else eqn.params
            out = eqn.primitive.bind(*invals, **eqn.primitive.get_bind_params(params))
        env.update(zip(eqn.outvars, out if eqn.primitive.multiple_results else [out], strict=True))
    return [read(v) for v in jaxpr.outvars]


def safe_lapack(fn: Callable) -> Callable:
    """``fn`` with each CPU LAPACK call over more matrices than jaxlib runs on one thread done in blocks.

    Args:
      fn: any function of arrays (pytrees and keyword arguments included), typically already batched.

    The returned function takes and returns what ``fn`` does. It traces ``fn`` (``jax.make_jaxpr``) and evaluates
    the trace with every LAPACK call past its bound (:func:`lapack_calls`) replaced by ``jax.lax.map`` over blocks
    of at most the bound's matrices, loop and branch bodies included: the same numbers, and no kernel waits on the
    thread pool, so the program cannot deadlock. Other operations are untouched. On a backend other than the CPU,
    ``fn`` itself. Apply it to the whole batched computation (``safe_lapack(jax.vmap(f))``, as :func:`safe_vmap`
    does): a ``vmap`` around it multiplies the batches again. Works eagerly and under ``jit`` and ``grad``.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> expm2 = jax.vmap(lambda a: jax.scipy.linalg.expm(a) @ jax.scipy.linalg.expm(2 * a))
        >>> a = jnp.zeros((8192, 5, 5))  # jax.jit(expm2)(a) can hang on a 2-core CPU
        >>> jax.jit(safe_lapack(expm2))(a).shape
        (8192, 5, 5)
    """

    def safe(*args, **kwargs):
        if jax.default_backend() != "cpu":
            return fn(*args, **kwargs)
        flat, tree = jax.tree.flatten((args, kwargs))
        closed, shape = jax.make_jaxpr(lambda *leaves: fn(*tree.unflatten(leaves)[0], **tree.unflatten(leaves)[1]),
                                       return_shape=True)(*flat)  # fmt: skip
        out = _evaluate(closed.jaxpr, closed.consts, flat)
        return jax.tree.unflatten(jax.tree.structure(shape), out)

    return safe


def safe_vmap(fn: Callable, in_axes=0, out_axes=0) -> Callable:
    """``jax.vmap(fn, in_axes, out_axes)`` whose CPU LAPACK calls cannot deadlock: :func:`safe_lapack` of it.

    Args:
      fn: a function of one element.  in_axes, out_axes: as ``jax.vmap``'s.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> expm2 = lambda a: jax.scipy.linalg.expm(a) @ jax.scipy.linalg.expm(2 * a)
        >>> jax.jit(safe_vmap(expm2))(jnp.zeros((8192, 5, 5))).shape
        (8192, 5, 5)
    """
    return safe_lapack(jax.vmap(fn, in_axes=in_axes, out_axes=out_axes))
