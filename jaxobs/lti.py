"""Linear time-invariant models: the state-space pytree, exact ZOH discretisation with dead time,
transfer functions to state space, and the controllability/observability/DC-gain helpers.

The delay-augmented discretisation follows Cortesão 2006 (Cortesão 2006), eq. 11-18: a continuous plant
``x' = A x + B u(t - tau)`` sampled with period ``h`` under a zero-order hold, with dead time
``tau = (d - 1) h + tau'`` and ``0 < tau' <= h``, becomes

    x_{r,k} = Phi_r x_{r,k-1} + Gamma_r u_{k-1},   x_{r,k} = [x'_k, u_{k-d}, ..., u_{k-1}]

with ``Phi_1 = e^{Ah}`` (eq. 15), ``Gamma_0 = int_0^{h-tau'} e^{As} ds B`` (eq. 16) and
``Gamma_1 = e^{A(h-tau')} int_0^{tau'} e^{As} ds B`` (eq. 17).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from jaxobs import _checks
from jaxobs._jit import jit

__all__ = [
    "StateSpace",
    "ss",
    "c2d",
    "tf2ss",
    "ctrb",
    "obsv",
    "controllability_rank",
    "observability_rank",
    "unobservable_modes",
    "dcgain",
    "is_spr",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class StateSpace:
    """``x' = A x + B u, y = C x + D u`` (continuous, ``dt is None``) or
    ``x_{k+1} = A x_k + B u_k, y_k = C x_k + D u_k`` (discrete with sample time ``dt``).

    Attributes:
      A: (n, n) state matrix.  B: (n, m) input matrix.  C: (p, n) output matrix.  D: (p, m) feedthrough.
      dt: sample time in seconds (static metadata), ``None`` for continuous time.

    A pytree: ``A, B, C, D`` are leaves (they may carry leading batch axes under ``vmap``). Build it with
    :func:`ss`, which checks and casts. A discrete model's ``A`` and ``B`` are also ``Phi`` and ``Gamma``, their
    names in the estimator designs (``make_kalman(Phi, C, Q, R, Gamma=...)``) and in Cortesão 2006.
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    D: jax.Array
    dt: float | None = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def Phi(self) -> jax.Array:
        """The discrete state matrix ``A`` (``x_{k+1} = Phi x_k + Gamma u_k``); discrete models only."""
        return self._discrete("Phi", self.A)

    @property
    def Gamma(self) -> jax.Array:
        """The discrete input matrix ``B``; discrete models only."""
        return self._discrete("Gamma", self.B)

    def _discrete(self, name: str, value: jax.Array) -> jax.Array:
        if self.dt is None:
            raise AttributeError(f"{name} is the matrix of a discrete model; this one is continuous (dt=None): use "
                                 "A and B, or discretise it with c2d")  # fmt: skip
        return value

    @property
    def n_states(self) -> int:
        """Number of states ``n``."""
        return self.A.shape[-1]

    @property
    def n_inputs(self) -> int:
        """Number of inputs ``m``."""
        return self.B.shape[-1]

    @property
    def n_outputs(self) -> int:
        """Number of outputs ``p``."""
        return self.C.shape[-2]

    @property
    def is_discrete(self) -> bool:
        """Whether the model is discrete-time (it has a sample time ``dt``)."""
        return self.dt is not None

    def check(self, name: str = "sys") -> StateSpace:
        """``self``, checked at trace time to be one model: ``A`` (n, n), ``B`` (n, m), ``C`` (p, n), ``D`` (p, m),
        no leading batch axis (``vmap`` over a batch of models); a ``ValueError`` naming ``name.A`` ... otherwise
        (``name``: the argument that holds it)."""
        if not isinstance(self, StateSpace):
            raise ValueError(f"{name} must be a StateSpace (jaxobs.lti.ss), got {type(self).__name__}")
        _checks.shapes(f"{name}.A (n, n), {name}.B (n, m), {name}.C (p, n), {name}.D (p, m)",
                       self.A, self.B, self.C, self.D)  # fmt: skip
        return self


def ss(A, B, C, D=None, dt: float | None = None) -> StateSpace:
    """Build a :class:`StateSpace`, checking shapes (also under ``jit``) and finiteness (eagerly).

    Args:
      A: (n, n).  B: (n, m).  C: (p, n).  D: (p, m), default zeros.
      dt: sample time in seconds for a discrete model; ``None`` (default) for continuous time.

    The four matrices are cast to their common floating dtype (integers and bools become float; float32 mixed
    with float64 becomes float64), so a model never mixes precisions.

    Example:
      >>> sys = ss([[0.0, 1.0], [0.0, -2.0]], [[0.0], [1.0]], [[1.0, 0.0]])
      >>> sys.n_states, sys.n_inputs, sys.n_outputs, sys.is_discrete
      (2, 1, 1, False)
    """
    A, B, C = (jnp.atleast_2d(jnp.asarray(M)) for M in (A, B, C))
    D = None if D is None else jnp.atleast_2d(jnp.asarray(D))
    dtype = _checks.float_dtype(A=A, B=B, C=C, D=D)
    n = A.shape[-1]
    _checks.matrix("A", A, shape=(n, n), square=True)
    _checks.matrix("B", B, shape=(n, None))
    _checks.matrix("C", C, shape=(None, n))
    D = jnp.zeros((C.shape[-2], B.shape[-1]), dtype) if D is None else D
    _checks.matrix("D", D, shape=(C.shape[-2], B.shape[-1]))
    if dt is not None:
        _checks.positive_scalar("dt", dt)
        dt = float(dt)
    return StateSpace(*(M.astype(dtype) for M in (A, B, C, D)), dt)


MAX_DELAY_SLOTS = 1000
"""Largest number of delayed-input slots :func:`c2d` builds (state dimension ``n + slots * m``); a longer dead
time is refused with the number of slots it would need (hold it in a FIFO outside the model instead)."""

MAX_EXPM_NORM = 1e9
"""Largest ``h ||[A B]||_1`` :func:`c2d` accepts: beyond it the zero-order-hold matrix exponential would need
more scaling-and-squaring steps than it is given (:data:`_EXPM_SQUARINGS`), so it is refused."""

_EXPM_SQUARINGS = 32  # expm handles 1-norms up to about 5.4 * 2**32 = 2.3e10 > MAX_EXPM_NORM


def _zoh_integral(A, B, t):
    """``(e^{At}, int_0^t e^{As} ds B)`` from one block matrix exponential (Van Loan)."""
    n, m = B.shape
    block = jnp.zeros((n + m, n + m), A.dtype).at[:n, :n].set(A).at[:n, n:].set(B)
    E = jax.scipy.linalg.expm(block * t, max_squarings=_EXPM_SQUARINGS)
    return E[:n, :n], E[:n, n:]


def n_delay_slots(delay: float, h: float) -> int:
    """Number of delayed-input slots ``d`` for a concrete dead time (``tau = (d-1)h + tau'``)."""
    return max(0, math.ceil(float(delay) / float(h) - 1e-9))


def c2d(sys: StateSpace, h: float, delay=0.0, *, n_delay: int | None = None) -> StateSpace:
    """Exact zero-order-hold discretisation with dead time (Cortesão 2006, eq. 11-18).

    Args:
      sys: continuous-time model (``sys.dt is None``).
      h: sample time (a Python number: it fixes the model's ``dt``). ``h ||[A B]||_1`` must not exceed
        :data:`MAX_EXPM_NORM`, and a model whose unstable modes overflow over one sample is refused.
      delay: dead time ``tau >= 0`` in seconds; may be a traced value (differentiable almost
        everywhere: the gradient is one-sided at whole multiples of ``h``).
      n_delay: number of delayed-input slots in the state (an integer, at most :data:`MAX_DELAY_SLOTS`).
        Defaults to ``ceil(tau / h)`` for a concrete ``delay``; must be given when ``delay`` is traced
        (e.g. ``vmap`` over dead times), and then any ``tau`` in ``[0, n_delay * h]`` is represented
        exactly by placing ``Gamma_0, Gamma_1`` in the right slots. A traced ``tau`` outside that range
        gives NaN matrices.

    Returns:
      The delay-augmented discrete model with state ``[x', u_{k-d}, ..., u_{k-1}]`` (oldest slot
      first, eq. 18). For ``d >= 1`` the new input enters only the newest slot
      (``Gamma_r = [0 ... 0 I]``, eq. 22) unless ``tau < h``, when ``Gamma_0`` acts at once.
      ``C`` reads ``x'`` and ``D u(t - tau)`` is routed to the slot holding that input.

    Example:
      >>> sys = ss([[0.0, 1.0], [0.0, -31.25]], [[0.0], [93.75]], [[1.0, 0.0]])   # 3 / (s (0.032 s + 1))
      >>> plant = c2d(sys, 0.008, delay=0.040)                                     # five samples of dead time
      >>> plant.A.shape, plant.dt
      ((7, 7), 0.008)
    """
    sys = StateSpace.check(sys, "sys")
    if sys.is_discrete:
        raise ValueError("sys is already discrete; c2d needs a continuous-time model (dt=None)")
    _checks.positive_scalar("h", h)
    _checks.positive_scalar("delay", delay, allow_zero=True)
    _checks.shapes("delay ()", delay)
    h = float(h)
    if n_delay is None:
        if not _checks.is_concrete(delay):
            raise ValueError(
                "n_delay must be given when delay is traced (e.g. under vmap); "
                "pass the largest number of delay samples you need"
            )
        n_delay = n_delay_slots(delay, h)
        if n_delay > MAX_DELAY_SLOTS:
            raise ValueError(
                f"delay={float(delay)} needs n_delay={n_delay} slots of h={h} (a state of dimension "
                f"{sys.n_states + n_delay * sys.n_inputs}), above MAX_DELAY_SLOTS={MAX_DELAY_SLOTS}; "
                "hold such a dead time in a FIFO outside the model"
            )
    n_delay = _checks.count("n_delay", n_delay, maximum=MAX_DELAY_SLOTS)
    if _checks.is_concrete(delay) and float(delay) > n_delay * h * (1 + 1e-9):
        raise ValueError(f"delay={float(delay)} needs more than n_delay={n_delay} slots of h={h}")

    dtype = _checks.float_dtype(A=sys.A, B=sys.B, C=sys.C, D=sys.D)
    A, B, C, D = (jnp.asarray(M, dtype) for M in (sys.A, sys.B, sys.C, sys.D))
    concrete = _checks.is_concrete(A, B)
    if concrete:
        with np.errstate(over="ignore", invalid="ignore"):
            scale = h * float(np.max(np.abs(np.concatenate([np.asarray(A), np.asarray(B)], axis=1)).sum(axis=0)))
        if not scale <= MAX_EXPM_NORM:
            raise ValueError(
                f"h * ||[sys.A, sys.B]||_1 = {scale:.3g} exceeds MAX_EXPM_NORM={MAX_EXPM_NORM:.0e}: the sample "
                f"period h={h} is too long for the model's time scales to discretise; lower h or rescale sys"
            )
    matrices = _c2d_matrices(A, B, C, D, jnp.asarray(delay, dtype), h=h, n_delay=n_delay)
    if _checks.is_concrete(matrices[:2]) and not all(np.isfinite(np.asarray(M)).all() for M in matrices[:2]):
        raise ValueError(
            f"h={h} is too long for sys: e^(A h) overflows {jnp.dtype(dtype).name} (an unstable mode of sys.A grows "
            "beyond the float range over one sample); lower h"
        )
    return StateSpace(*matrices, h)


@functools.partial(jit, static_argnames=("h", "n_delay"), what="c2d")
def _c2d_matrices(A, B, C, D, tau, *, h: float, n_delay: int):
    """The numerical part of :func:`c2d` (compiled once per shape: eager calls cost one dispatch)."""
    dtype = A.dtype
    n, m = B.shape
    p = C.shape[0]

    # tau = (d - 1) h + tau' with 0 < tau' <= h; d = 0 only for tau = 0 (then tau' = h).
    d = jnp.maximum(jnp.ceil(tau / h - 1e-9), 0.0)
    tau_p = jnp.clip(tau - (d - 1.0) * h, 0.0, h)
    Phi1, F_h = _zoh_integral(A, B, h)
    _, F_rest = _zoh_integral(A, B, h - tau_p)
    Gamma0 = F_rest  # eq. 16: acts on u_{k-d}
    Gamma1 = F_h - F_rest  # eq. 17: e^{A(h-tau')} int_0^tau' e^{As} ds B, acts on u_{k-d-1}

    def lag_input_matrices(lags):
        """Input matrices multiplying u_{k-lag} in x'_k, one (n, m) block per lag."""
        lags = lags[:, None, None]
        return jnp.where(lags == d + 1, Gamma1, 0.0) + jnp.where(lags == d, Gamma0, 0.0)

    # slot i of x_{r,k-1} holds u_{k-1-(n_delay-i)}; slot i of x_{r,k} holds u_{k-(n_delay-i)}
    slots = jnp.arange(n_delay, dtype=dtype)
    from_slots = lag_input_matrices(n_delay + 1.0 - slots).transpose(1, 0, 2).reshape(n, n_delay * m)
    shift = jnp.eye(n_delay * m, k=m, dtype=dtype)  # each slot takes the next newer one
    Phi = jnp.concatenate(
        [jnp.concatenate([Phi1, from_slots], axis=1),
         jnp.concatenate([jnp.zeros((n_delay * m, n), dtype), shift], axis=1)], axis=0
    )  # fmt: skip
    newest = jnp.eye(m, dtype=dtype) if n_delay else jnp.zeros((0, m), dtype)
    Gamma = jnp.concatenate(
        [lag_input_matrices(jnp.ones((1,), dtype))[0], jnp.zeros((max(n_delay - 1, 0) * m, m), dtype), newest]
    )
    # the output sees u(kh - tau) = u_{k-d}, held in slot n_delay - d
    at_output = (d == n_delay - slots)[:, None, None]
    Cr = jnp.concatenate([C, jnp.where(at_output, D, 0.0).transpose(1, 0, 2).reshape(p, n_delay * m)], axis=1)
    Dr = jnp.where(d == 0, D, 0.0)

    out_of_range = tau > n_delay * h * (1 + 1e-9)
    return tuple(jnp.where(out_of_range, jnp.nan, M) for M in (Phi, Gamma, Cr, Dr))


def _poly(coeffs, name) -> np.ndarray:
    c = np.trim_zeros(np.atleast_1d(np.asarray(coeffs, dtype=float)), "f")
    if c.size == 0:
        c = np.zeros(1)
    if c.ndim != 1 or not np.all(np.isfinite(c)):
        raise ValueError(f"{name} must be a finite 1-D coefficient list (highest power first)")
    return c


def _siso_ss(num, den):
    """Controllable canonical realisation of one transfer function num(s)/den(s)."""
    num, den = _poly(num, "num"), _poly(den, "den")
    if not np.any(den):
        raise ValueError("den must not be identically zero")
    if num.size > den.size:
        raise ValueError(
            f"improper transfer function: numerator degree {num.size - 1} exceeds denominator degree {den.size - 1}"
        )
    num, den = num / den[0], den / den[0]
    n = den.size - 1
    num = np.concatenate([np.zeros(n + 1 - num.size), num])
    D = num[0]
    rest = num[1:] - D * den[1:]  # strictly proper remainder, coefficients s^{n-1} .. s^0
    A = np.zeros((n, n))
    if n:
        A[0, :] = -den[1:]
        A[1:, :-1] = np.eye(n - 1)
    B = np.zeros((n, 1))
    if n:
        B[0, 0] = 1.0
    C = rest.reshape(1, n)
    return A, B, C, np.array([[D]])


@_checks.design_time()
def tf2ss(num, den, dt: float | None = None) -> StateSpace:
    """Transfer function (matrix) to state space (design time, NumPy).

    SISO: ``num``, ``den`` are coefficient lists, highest power first.
    MIMO: ``num[i][j]``, ``den[i][j]`` give entry (output i, input j); every entry is
    realised on its own (controllable canonical form) and the blocks are stacked: the state is
    block diagonal, input j drives the blocks of column j and output i sums the blocks of row i.
    The order is the sum of the entry orders, so the realisation is in general not minimal (entries
    sharing poles give uncontrollable or unobservable copies); build a minimal model from your
    knowledge of the shared poles where the design needs one.

    ``dt``: sample time of a discrete transfer function (``None``: continuous).

    Example:
      >>> tf2ss([1.0], [1.0, 3.0, 2.0]).A.shape            # 1 / (s^2 + 3 s + 2)
      (2, 2)
    """
    if not (_is_matrix_of_polys(num) or _is_matrix_of_polys(den)):
        A, B, C, D = _siso_ss(num, den)
        return ss(A, B, C, D, dt)
    if not (_is_matrix_of_polys(num) and _is_matrix_of_polys(den)):
        raise ValueError("for a MIMO transfer function give num and den as nested lists [output][input]")
    rows = len(num)
    if rows == 0 or len(den) != rows:
        raise ValueError(f"num has {len(num)} rows but den has {len(den)}; they must match")
    cols = len(num[0])
    for i in range(rows):
        if len(num[i]) != cols or len(den[i]) != cols:
            raise ValueError(f"row {i} of num/den has {len(num[i])}/{len(den[i])} entries; every row needs {cols}")
    blocks = [[_siso_ss(num[i][j], den[i][j]) for j in range(cols)] for i in range(rows)]
    sizes = [blocks[i][j][0].shape[0] for j in range(cols) for i in range(rows)]
    n = sum(sizes)
    A = np.zeros((n, n))
    B = np.zeros((n, cols))
    C = np.zeros((rows, n))
    D = np.zeros((rows, cols))
    k = 0
    for j in range(cols):
        for i in range(rows):
            a, b, c, dd = blocks[i][j]
            s = a.shape[0]
            A[k : k + s, k : k + s] = a
            B[k : k + s, j] = b[:, 0]
            C[i, k : k + s] = c[0]
            D[i, j] = dd[0, 0]
            k += s
    return ss(A, B, C, D, dt)


def _is_matrix_of_polys(x) -> bool:
    """True for ``x[i][j] = coefficient list`` (a transfer-function matrix), False for one polynomial."""
    return (
        isinstance(x, Sequence)
        and len(x) > 0
        and isinstance(x[0], Sequence)
        and len(x[0]) > 0
        and np.ndim(x[0][0]) == 1
    )


def ctrb(A, B) -> jax.Array:
    """Controllability (reachability) matrix ``[B, A B, ..., A^{n-1} B]`` (Cortesão 2006, eq. 46); ``A`` (n, n),
    ``B`` (n, m), optionally with the same leading batch axes. Integer inputs are computed in float."""
    A, B = _checks.float_arrays(A=A, B=B)
    _checks.matrix("A", A, square=True, batch=True)
    n = A.shape[-1]
    _checks.matrix("B", B, shape=(n, None), batch=True)
    if A.shape[:-2] != B.shape[:-2]:
        raise ValueError(f"B must have the leading batch axes of A, {A.shape[:-2]}, got shape {B.shape}")
    blocks = [B]
    for _ in range(n - 1):
        blocks.append(A @ blocks[-1])
    return jnp.concatenate(blocks, axis=-1)


def obsv(A, C) -> jax.Array:
    """Observability matrix ``[C; C A; ...; C A^{n-1}]``; ``A`` (n, n), ``C`` (p, n), optionally with the same
    leading batch axes."""
    A, C = _checks.float_arrays(A=A, C=C)
    _checks.matrix("A", A, square=True, batch=True)
    _checks.matrix("C", C, shape=(None, A.shape[-1]), batch=True)
    if A.shape[:-2] != C.shape[:-2]:
        raise ValueError(f"C must have the leading batch axes of A, {A.shape[:-2]}, got shape {C.shape}")
    return jnp.swapaxes(ctrb(jnp.swapaxes(A, -1, -2), jnp.swapaxes(C, -1, -2)), -1, -2)


@_checks.design_time()
def controllability_rank(A, B, *, rtol: float = 1e-10) -> int:
    """Rank of the controllability matrix ``[B, A B, ..., A^{n-1} B]`` of ``A`` (n, n), ``B`` (n, m): its singular
    values above ``rtol`` times the largest (eager, NumPy in float64)."""
    A, B = np.asarray(A, np.float64), np.asarray(B, np.float64)
    blocks, block = [], B
    for _ in range(A.shape[0]):
        blocks.append(block)
        block = A @ block
    s = np.linalg.svd(np.hstack(blocks), compute_uv=False)
    return int(np.sum(s > rtol * max(s[0], np.finfo(float).tiny))) if s.size else 0


@_checks.design_time()
def observability_rank(A, C, *, rtol: float = 1e-10) -> int:
    """Rank of the observability matrix ``[C; C A; ...; C A^{n-1}]`` of ``A`` (n, n), ``C`` (p, n) (eager, NumPy):
    :func:`controllability_rank` of ``(A', C')``."""
    return controllability_rank(np.transpose(A), np.transpose(C), rtol=rtol)


@_checks.design_time()
def unobservable_modes(A, C, region, tol: float = 1e-9) -> list[complex]:
    """Eigenvalues ``lam`` of ``A`` (n, n) in ``region`` (a predicate on a NumPy eigenvalue) whose PBH matrix
    ``[lam I - A; C]`` loses rank (smallest singular value below ``tol`` times ``max(|A|, 1)``, ``C`` (p, n) scaled
    to ``A``): the unobservable modes of ``(C, A)`` there (Hautus test; eager, NumPy). For the uncontrollable
    modes of ``(A, B)`` pass ``(A', B')``."""
    A, C = np.asarray(A, np.float64), np.asarray(C, np.float64)
    n = A.shape[-1]
    scale = max(float(np.max(np.abs(A))) if A.size else 0.0, 1.0)
    C_scaled = C / max(float(np.max(np.abs(C))) if C.size else 0.0, np.finfo(float).tiny) * scale
    deficient = []
    for lam in np.linalg.eigvals(A):
        if region(lam):
            pbh = np.vstack([lam * np.eye(n) - A, C_scaled])
            if np.linalg.svd(pbh, compute_uv=False)[-1] <= tol * scale:
                deficient.append(complex(lam))
    return deficient


def dcgain(sys: StateSpace) -> jax.Array:
    """Steady-state gain (p, m) of ``sys``: ``C (I - A)^{-1} B + D`` (discrete) or ``-C A^{-1} B + D``
    (continuous).

    Infinite/NaN entries come back for systems with a pole at 1 (discrete) or 0 (continuous).
    """
    sys = StateSpace.check(sys, "sys")
    n = sys.A.shape[-1]
    M = jnp.eye(n, dtype=sys.A.dtype) - sys.A if sys.is_discrete else -sys.A
    return sys.C @ jnp.linalg.solve(M, sys.B) + sys.D


@_checks.design_time()
def is_spr(A, B, C, D=None, *, rtol: float = 1e-10) -> bool:
    """Whether ``G(s) = C (sI - A)^{-1} B + D`` (square, continuous time) is strictly positive real (design time,
    NumPy; concrete arrays only).

    The frequency-domain characterisation (Khalil 2002, Lemma 6.1): ``A`` Hurwitz, ``G(jw) + G(jw)^* > 0`` for
    every real ``w``, and at infinity either ``R = D + D^T > 0`` or, on the null space ``M`` of ``R``,
    ``lim_{w -> inf} w^2 M^T (G(jw) + G(jw)^*) M > 0``. No frequency grid: ``G(jw) + G(jw)^*`` is the value on the
    imaginary axis of ``Phi(s) = G(s) + G^T(-s)``, realised by ``(diag(A, -A^T), [B; -C^T], [C, B^T], R)``; it is
    positive at ``w = 0`` and has no zero ``s = jw`` (a finite generalised eigenvalue of the Rosenbrock pencil of
    that realisation on the imaginary axis) exactly when it is positive for every ``w`` (the Hamiltonian test,
    which the pencil reduces to when ``R`` is invertible). At infinity, ``w^2 M^T (G + G^*) M`` tends to
    ``-M^T (C A B + (C A B)^T) M`` when ``M^T (C B - (C B)^T) M = 0`` and diverges otherwise.

    Args:
      A: (n, n).  B: (n, m).  C: (m, n).  D: (m, m), or a scalar ``d`` for ``d I``; default zeros.
      rtol: relative tolerance of the strict inequalities (scaled by the norms of the matrices); a zero ``z`` of
        ``Phi`` counts as on the imaginary axis when ``|Re z| <= sqrt(rtol) max(1, |z|)`` (the eigensolver does not
        keep the zeros' symmetry about the axis, so the axis test is looser than the inequalities).

    Returns:
      a Python ``bool``.

    Example:
      >>> is_spr([[-1.0]], [[1.0]], [[1.0]])                      # 1 / (s + 1)
      True
      >>> is_spr([[0.0, 1.0], [-1.0, -1.0]], [[0.0], [1.0]], [[1.0, 0.0]])  # 1 / (s^2 + s + 1)
      False
    """
    A, B, C = (np.asarray(M, dtype=float) for M in (A, B, C))
    _checks.matrix("A", A, square=True)
    n = A.shape[0]
    _checks.matrix("B", B, shape=(n, None))
    m = B.shape[1]
    _checks.matrix("C", C, shape=(m, n))
    D = np.zeros((m, m)) if D is None else np.asarray(D, dtype=float)
    D = D * np.eye(m) if D.ndim == 0 else D
    _checks.matrix("D", D, shape=(m, m))
    for name, M in (("A", A), ("B", B), ("C", C), ("D", D)):
        _checks.finite(name, M)
    norm = lambda M: np.linalg.norm(M, 2) if M.size else 0.0
    if n and np.max(np.linalg.eigvals(A).real) >= -rtol * norm(A):
        return False
    R = D + D.T

    def hermitian_part(w):
        G = C @ np.linalg.solve(1j * w * np.eye(n) - A, B) + D if n else D.astype(complex)
        return G + G.conj().T

    phi0 = hermitian_part(0.0)
    if np.min(np.linalg.eigvalsh(phi0)) <= rtol * norm(phi0):
        return False
    r_eig, r_vec = np.linalg.eigh(R)
    M = r_vec[:, r_eig <= rtol * norm(R)]  # directions in which G + G^* vanishes at infinity
    if M.shape[1]:
        CB, CAB = C @ B, C @ A @ B
        if np.linalg.norm(M.T @ (CB - CB.T) @ M) > rtol * norm(C) * norm(B) or np.min(
            np.linalg.eigvalsh(-M.T @ (CAB + CAB.T) @ M)
        ) <= rtol * norm(C) * norm(A) * norm(B):
            return False
    if not n:
        return True
    # zeros of Phi(s): finite generalised eigenvalues of [[Ah - s I, Bh], [Ch, R]]
    Ah = scipy.linalg.block_diag(A, -A.T)
    Bh = np.vstack([B, -C.T])
    Ch = np.hstack([C, B.T])
    pencil = np.block([[Ah, Bh], [Ch, R]])
    E = scipy.linalg.block_diag(np.eye(2 * n), np.zeros((m, m)))
    alpha, beta = scipy.linalg.eigvals(pencil, E, homogeneous_eigvals=True)
    finite = np.abs(beta) > 1e3 * np.finfo(float).eps * np.abs(alpha)
    zeros = alpha[finite] / beta[finite]
    return not bool(np.any(np.abs(zeros.real) <= np.sqrt(rtol) * np.maximum(1.0, np.abs(zeros))))
