"""Input validation shared by the public API.

Shapes, dtypes and counts are static, so the checks of them (:func:`matrix`'s shapes, :func:`count`,
:func:`vector`, :func:`float_dtype`) run on tracers too, at trace time, under ``jit``/``vmap``/``grad``.
Checks of values (NaN, sign, definiteness) run on concrete arrays; on tracers they are skipped (traced code
reports problems through flags and NaNs instead, never by raising), except while :func:`checked` traces a
function, when they become ``checkify`` checks with the same messages. Each check raises ``ValueError`` naming
the argument, the expected and the given value.
"""

from __future__ import annotations

import contextvars
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import checkify

MAX_INDEX = 2**31 - 1
"""The largest count or index the library and its jobs take: JAX's default integers (indices, seeds, loop
counters, scan lengths) are int32."""


def is_concrete(*values) -> bool:
    """True when none of ``values`` is a JAX tracer (so they can be inspected with NumPy)."""
    return not any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(values))


_CHECKING = contextvars.ContextVar("jaxobs_checked", default=False)


def checked(fn):
    """``fn`` with the library's value checks in compiled code: the ``ValueError`` that an eager call raises for a
    bad value (non-finite or indefinite ``Q``/``R``, a non-positive variance, ...) is raised under ``jit`` and
    ``vmap`` too.

    Wrap the outermost function: ``checked(jax.jit(jax.vmap(f)))(...)``. While it traces ``fn``, the checks that
    are skipped on traced values become ``jax.experimental.checkify`` checks with the same messages; after the
    run, the first that failed is raised as ``ValueError`` (``checkify`` tells where). It costs what the checks
    compute (an eigenvalue decomposition per covariance) and is meant for debugging, not for sweeps.

    Example::

        >>> import jax, jax.numpy as jnp
        >>> import jaxobs as jo
        >>> design = lambda r: jo.make_kalman([[1.0]], [[1.0]], [[0.1]], r[None, None]).x0
        >>> jax.jit(jax.vmap(design))(jnp.array([1.0, -1.0])).shape  # unchecked: a negative R passes
        (2, 1)
        >>> jo.checked(jax.jit(jax.vmap(design)))(jnp.array([1.0, -1.0]))
        Traceback (most recent call last):
        ...
        ValueError: R must be positive definite (smallest eigenvalue -1.0); a singular R cannot be inverted ...
    """

    @functools.wraps(fn)
    def run(*args, **kwargs):
        if not is_concrete(args, kwargs):
            raise ValueError("checked(fn) must be the outermost call: checked(jax.jit(jax.vmap(fn)))(...)")

        def flagged(*a, **k):
            token = _CHECKING.set(True)
            try:
                return fn(*a, **k)
            finally:
                _CHECKING.reset(token)

        error, out = checkify.checkify(flagged, errors=checkify.user_checks)(*args, **kwargs)
        message = error.get()
        if message is not None:
            raise ValueError(message)
        return out

    return run


def _check_traced(ok, message: str, **values) -> None:
    """Under :func:`checked`, a ``checkify`` check that ``ok`` holds (``message`` formatted with ``values``)."""
    if _CHECKING.get():
        checkify.check(jnp.all(ok), message, **values)


def finite(name: str, value) -> None:
    """Raise when a concrete ``value`` has NaN or infinite entries (skipped on tracers, unless :func:`checked`)."""
    if not is_concrete(value):
        _check_traced(jnp.isfinite(value), f"{name} contains NaN or infinite entries")
    elif not np.all(np.isfinite(np.asarray(value))):
        raise ValueError(f"{name} contains NaN or infinite entries")


def count(name: str, value, *, minimum: int = 0, maximum: int | None = None, hint: str = "") -> int:
    """A static count (a size, an order, a number of steps): a Python or NumPy integer or a concrete 0-d integer
    array, not a bool, a float or a traced value, in ``[minimum, maximum]``. Returns it as a Python ``int``;
    ``hint`` ends the message."""
    bound = f">= {minimum}" if maximum is None else f"in [{minimum}, {maximum}]"
    hint = f"; {hint}" if hint else ""
    if not is_concrete(value):
        raise ValueError(f"{name} must be a concrete integer {bound} (it fixes a shape), got a traced value{hint}")
    integer = np.ndim(value) == 0 and np.issubdtype(np.asarray(value).dtype, np.integer)
    if isinstance(value, (bool, np.bool_)) or not integer:
        raise ValueError(f"{name} must be an integer {bound}, got {value!r} ({type(value).__name__}){hint}")
    value = int(value)
    if value < minimum or (maximum is not None and value > maximum):
        raise ValueError(f"{name} must be an integer {bound}, got {value}{hint}")
    return value


def _real(name: str, value):
    """``value`` checked to be real numbers: a Python scalar (kept weakly typed), an array, or a sequence (read as an
    array); ``ValueError`` naming ``name`` for anything else (None, a string, a complex or object array, a ragged
    sequence)."""
    try:
        if any(isinstance(leaf, (str, bytes)) for leaf in jax.tree_util.tree_leaves(value)):
            raise TypeError("text")  # before jnp.asarray, which reads a string in a list as a dtype
        value = value if isinstance(value, (jax.Array, np.ndarray, np.generic, int, float)) else jnp.asarray(value)
        dtype = jnp.result_type(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real numeric array, got {type(value).__name__}") from exc
    if jnp.issubdtype(dtype, jnp.complexfloating) or not (
        jnp.issubdtype(dtype, jnp.number) or jnp.issubdtype(dtype, jnp.bool_)
    ):
        raise ValueError(f"{name} must be real (a float, integer or bool array), got dtype {dtype}")
    return value


def real_array(name: str, value) -> jax.Array:
    """``value`` as a JAX array of real numbers (float, integer or bool dtype, cast by the caller); ``ValueError``
    naming ``name`` for None, a string, a complex or object array or a ragged sequence (where ``jnp.asarray`` raises
    a ``TypeError`` that names nothing)."""
    return jnp.asarray(_real(name, value))


def boolean(name: str, value) -> bool:
    """``value`` as a Python ``bool``: ``True``/``False`` (or a NumPy bool) only, so that a string such as ``"no"``
    or a number is not taken for true; ``ValueError`` naming ``name`` otherwise."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be a bool (True or False), got {value!r} ({type(value).__name__})")
    return bool(value)


def float_dtype(**values):
    """The common floating dtype of the named arrays (``result_type`` of them and ``float``): integer and
    bool inputs become float, float32 mixed with float64 becomes float64 (where x64 is enabled).
    ``None`` entries are ignored; a complex or non-numeric argument raises ``ValueError`` naming it."""
    arrays = [_real(name, value) for name, value in values.items() if value is not None]
    return jnp.result_type(*arrays, float)


def _shape_text(shape) -> str:
    dims = ["*" if d is None else str(d) for d in shape]
    return "(" + ", ".join(dims) + ("," if len(dims) == 1 else "") + ")"


def shape(name: str, value, expected: tuple, what: str = "") -> None:
    """Static check that ``value`` has shape ``expected`` (``None`` entries: any size); works on tracers."""
    got = np.shape(value)
    if len(got) != len(expected) or any(e is not None and e != g for e, g in zip(expected, got, strict=False)):
        hint = f" ({what})" if what else ""
        raise ValueError(f"{name} must have shape {_shape_text(expected)}{hint}, got {tuple(got)}")


def vector(name: str, value, size: int, dtype, *, what: str = "", check_finite: bool = True) -> jax.Array:
    """``value`` as a ``(size,)`` vector in ``dtype``: the shape must be ``(size,)``, or ``()`` when ``size``
    is 1 (never another broadcast). Shape checked at trace time; finiteness on concrete values when
    ``check_finite`` (measurements, where NaN means missing, pass False)."""
    value = jnp.asarray(value)
    if not (value.shape == (size,) or (size == 1 and value.shape == ())):
        shape(name, value, (size,), what)
    if check_finite:
        finite(name, value)
    return jnp.reshape(value, (size,)).astype(dtype)


def per_entry(name: str, value, size: int, dtype, what: str = "") -> jax.Array:
    """A scalar (the same for every entry) or a ``(size,)`` vector, broadcast to ``(size,)`` in ``dtype``.
    Shape checked at trace time (no other broadcast); finite where concrete."""
    value = jnp.asarray(value)
    if value.shape not in ((), (size,)):
        hint = f" ({what})" if what else ""
        raise ValueError(f"{name} must be a scalar or have shape ({size},){hint}, got {value.shape}")
    finite(name, value)
    return jnp.broadcast_to(value.astype(dtype), (size,))


def matrix(name: str, value, *, shape: tuple | None = None, square: bool = False, batch: bool = False):
    """Check that ``value`` is a 2-D matrix (or a stack of them when ``batch``) of the given ``shape``
    (entries ``None``: any size), and finite when concrete. Shapes are checked on tracers too.
    Returns nothing; raises ``ValueError``."""
    dims = np.shape(value)
    if len(dims) != 2 and not (batch and len(dims) > 2):
        raise ValueError(f"{name} must be a 2-D matrix, got an array of shape {tuple(dims)}")
    rows, cols = dims[-2:]
    if square and rows != cols:
        raise ValueError(f"{name} must be square, got shape {tuple(dims)}")
    if shape is not None:
        for axis, (want, got) in enumerate(zip(shape, (rows, cols), strict=True)):
            if want is not None and want != got:
                raise ValueError(
                    f"{name} has shape {tuple(dims[-2:])}, but dimension {axis} must be {want} to match the other "
                    "arguments"
                )
    finite(name, value)


def covariance(name: str, value, *, definite: bool, size: int | None = None):
    """Check that ``value`` is a finite symmetric positive (semi)definite matrix of the given size."""
    matrix(name, value, shape=(size, size), square=True, batch=True)
    if not is_concrete(value):
        if _CHECKING.get():
            _traced_covariance(name, jnp.asarray(value), definite)
        return
    a = np.asarray(value, dtype=float)
    scale = max(float(np.max(np.abs(a))), np.finfo(float).tiny) if a.size else 1.0
    if not np.allclose(a, np.swapaxes(a, -1, -2), rtol=1e-10, atol=1e-12 * scale):
        raise ValueError(f"{name} must be symmetric; symmetrise it with (M + M.T) / 2")
    if a.size == 0:
        return
    lowest = float(np.min(np.linalg.eigvalsh((a + np.swapaxes(a, -1, -2)) / 2)))
    if definite and lowest <= 1e-14 * scale:
        raise ValueError(
            f"{name} must be positive definite (smallest eigenvalue {lowest:.3g}); a singular {name} cannot be inverted"
        )
    if not definite and lowest < -1e-10 * scale:
        raise ValueError(f"{name} must be positive semidefinite (smallest eigenvalue {lowest:.3g})")


def _traced_covariance(name: str, a, definite: bool) -> None:
    """:func:`covariance`'s value checks as ``checkify`` checks (:func:`checked`), with its tolerances."""
    scale = jnp.maximum(jnp.max(jnp.abs(a)), jnp.finfo(a.dtype).tiny)
    _check_traced(jnp.abs(a - jnp.swapaxes(a, -1, -2)) <= 1e-10 * jnp.abs(a) + 1e-12 * scale,
                  f"{name} must be symmetric; symmetrise it with (M + M.T) / 2")  # fmt: skip
    lowest = jnp.min(jnp.linalg.eigvalsh((a + jnp.swapaxes(a, -1, -2)) / 2))
    if definite:
        _check_traced(lowest > 1e-14 * scale, f"{name} must be positive definite (smallest eigenvalue {{lowest}}); "
                      f"a singular {name} cannot be inverted", lowest=lowest)  # fmt: skip
    else:
        _check_traced(lowest >= -1e-10 * scale, f"{name} must be positive semidefinite (smallest eigenvalue "
                      "{lowest})", lowest=lowest)  # fmt: skip


def positive_scalar(name: str, value, *, allow_zero: bool = False):
    """Check a finite positive (or non-negative) real scalar (a bool is refused); skipped on tracers (unless
    :func:`checked`)."""
    if not is_concrete(value):
        bound = "non-negative" if allow_zero else "positive"
        ok = jnp.isfinite(value) & ((value >= 0) if allow_zero else (value > 0))
        _check_traced(ok, f"{name} must be a finite {bound} number, got {{value}}", value=value)
        return
    a = np.asarray(value)
    if a.dtype == bool or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    if a.ndim != 0:
        raise ValueError(f"{name} must be a scalar, got shape {a.shape}")
    a = a.astype(float)
    ok = np.isfinite(a) and (a >= 0 if allow_zero else a > 0)
    if not ok:
        bound = "non-negative" if allow_zero else "positive"
        raise ValueError(f"{name} must be a finite {bound} number, got {float(a)}")


def positive(name: str, value, *, allow_zero: bool = False, what: str = "") -> None:
    """Check that every entry of a concrete real array (any shape, e.g. a batch of parameters) is finite and
    positive (or non-negative); skipped on tracers (unless :func:`checked`). ``what`` ends the message."""
    if not is_concrete(value):
        bound, hint = ("non-negative" if allow_zero else "positive"), (f" ({what})" if what else "")
        ok = jnp.isfinite(value) & ((value >= 0) if allow_zero else (value > 0))
        _check_traced(ok, f"{name} must be finite and {bound}{hint}")
        return
    a = np.asarray(value)
    if a.dtype == bool or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise ValueError(f"{name} must be real, got {value!r}")
    bad = ~np.isfinite(a) | ((a < 0) if allow_zero else (a <= 0))
    if np.any(bad):
        bound = "non-negative" if allow_zero else "positive"
        hint = f" ({what})" if what else ""
        raise ValueError(f"{name} must be finite and {bound}{hint}, got {a[bad].ravel()[0]!r}")


def gain(name: str, value, size: int, dtype) -> jax.Array:
    """A gain as a (size, size) matrix: a positive scalar (times the identity) or a symmetric positive-definite
    matrix; ``ValueError`` naming ``name`` otherwise (values checked when concrete)."""
    value = jnp.asarray(value)
    if value.ndim == 0:
        positive_scalar(name, value)
        return value.astype(dtype) * jnp.eye(size, dtype=dtype)
    if value.ndim != 2:
        raise ValueError(f"{name} must be a positive scalar or a ({size}, {size}) matrix, got shape {value.shape}")
    covariance(name, value, definite=True, size=size)
    return value.astype(dtype)


def optimizer(name: str, value, example: str) -> None:
    """``ValueError`` unless ``value`` is an ``optax.GradientTransformation`` (``example``: one to suggest)."""
    import optax

    if not isinstance(value, optax.GradientTransformation):
        raise ValueError(f"{name} must be an optax.GradientTransformation (e.g. {example}), got {value!r}")


def function(name: str, fn) -> jax.tree_util.Partial:
    """``fn`` as a ``jax.tree_util.Partial``: a pytree whose bound arguments are leaves (so ``jit``, ``vmap`` and
    ``grad`` reach the parameters a user binds) and whose function is static. A ``Partial`` is returned as is."""
    if isinstance(fn, jax.tree_util.Partial):
        return fn
    if not callable(fn):
        raise ValueError(f"{name} must be a function, got {type(fn).__name__}")
    return jax.tree_util.Partial(fn)


def returns(call: str, fn, args: tuple, shape: tuple, what: str) -> None:
    """Check abstractly (``jax.eval_shape``, nothing runs) that ``fn(*args)`` returns a floating array of
    ``shape`` (``None`` entries: any size); ``call`` names the call in the message, e.g. ``"f(x, u, t)"``."""
    try:
        out = jax.eval_shape(fn, *args)
    except Exception as exc:  # the user's function failed on arrays of the expected shapes
        given = ", ".join(str(jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a))) for a in args)
        raise ValueError(f"{call} failed on arguments {given}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(out, jax.ShapeDtypeStruct):
        raise ValueError(f"{call} must return {what}, an array of shape {_shape_text(shape)}, got {type(out).__name__}")
    shape_ok = len(out.shape) == len(shape) and all(e is None or e == g for e, g in zip(shape, out.shape, strict=True))
    if not shape_ok:
        raise ValueError(f"{call} must return {what}, shape {_shape_text(shape)}, got {out.shape}")
    if not jnp.issubdtype(out.dtype, jnp.floating):
        raise ValueError(f"{call} must return a floating array, got dtype {out.dtype}")


def key(name: str, value) -> jax.Array:
    """``value`` checked to be a PRNG key: a typed key (``jax.random.key``, shape ``()``) or a raw one
    (``jax.random.PRNGKey``, uint32 of shape (2,)); static, so it runs under ``jit`` and ``vmap`` too."""
    value = value if isinstance(value, jax.Array) else jnp.asarray(value)
    typed = jnp.issubdtype(value.dtype, jax.dtypes.prng_key) and value.shape == ()
    if not (typed or (value.dtype == jnp.uint32 and value.shape == (2,))):
        raise ValueError(f"{name} must be a PRNG key (jax.random.key(seed) or jax.random.PRNGKey(seed)), got "
                         f"{value.dtype}{tuple(value.shape)}")  # fmt: skip
    return value
