"""Special coordinate basis (SCB) of a linear multivariable system (Grip 2010, ch. 7; Sannuti & Saberi 1987).

A design-time module on NumPy and sympy, not JAX (rank decisions fix the dimensions of the result), and the only
one that imports sympy. :func:`scb` transforms ``x' = A x + B u``, ``y = C x + D u`` to the form (7.4)-(7.6) by
the modified Silverman algorithm (section 7.4), exactly by default (integers, fractions, sympy expressions) or in
floating point with ``numeric=True``; :func:`scb_residuals` checks the identities (7.6). The construction and
its arithmetic: docs/theory/analysis.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Integral, Rational, Real
from typing import Any

import numpy as np

from jaxobs import _checks

__all__ = [
    "SCB",
    "scb",
    "scb_residuals",
    "invariant_zeros",
    "infinite_zero_structure",
    "is_left_invertible",
    "is_right_invertible",
    "is_minimum_phase",
    "scb_arrays",
]


@dataclass(frozen=True)
class SCB:
    """Result of :func:`scb`.

    Attributes:
      A, B, C, D: the SCB matrices (7.6), shapes (n, n), (n, m), (p, n), (p, m).
      state_transform, output_transform, input_transform: the state (n, n), output (p, p) and input (m, m)
        transformations, ``x = state_transform x_scb``, ``y = output_transform y_scb``, ``u = input_transform
        u_scb``, of the pre-transformed system ``(A, B U, Y^-1 C, Y^-1 D U)``.
      U, Y: the pre-transformation (m, m), (p, p) of section 7.2.4 (identities for D = 0).
      dims: ``(n_a, n_b, n_c, n_d)``, the dimensions of x_a, x_b, x_c and x_d.
      chain_lengths: tuple of ints, the lengths q_i of the integrator chains of x_d, in their order in x_d
        (nondecreasing).
      m0: int, the rank of D (the dimension of y_0 and u_0).
      exact: bool, sympy matrices (True) or NumPy arrays (False).
      symbols: tuple of the free symbols of the input matrices, sorted by name.
    """

    A: Any
    B: Any
    C: Any
    D: Any
    state_transform: Any
    output_transform: Any
    input_transform: Any
    U: Any
    Y: Any
    dims: tuple[int, int, int, int]
    chain_lengths: tuple[int, ...]
    m0: int
    exact: bool
    symbols: tuple = ()

    def block(self, name: str):
        """The block of ``A`` named ``"aa"``, ``"bb"``, ``"cc"``, ``"dd"``, ``"ab"``, ... (rows, columns)."""
        offsets = np.concatenate([[0], np.cumsum(self.dims)])
        index = {"a": 0, "b": 1, "c": 2, "d": 3}
        if len(name) != 2 or any(k not in index for k in name):
            raise ValueError(f"name must be two letters from 'abcd', got {name!r}")
        r, c = (index[k] for k in name)
        return self.A[offsets[r] : offsets[r + 1], offsets[c] : offsets[c + 1]]


# --------------------------------------------------------------------------------------------------------------
# Linear algebra back ends: exact (sympy DomainMatrix over QQ or a field of rational functions) and floating point.


class _Exact:
    exact = True

    def __init__(self, entries):
        from sympy.polys.constructor import construct_domain

        self.domain, _ = construct_domain(list(entries) or [0], field=True)

    def matrix(self, rows: list, shape: tuple[int, int]):
        from sympy.polys.matrices import DomainMatrix

        if 0 in shape:
            return DomainMatrix.zeros(shape, self.domain).to_dense()
        return DomainMatrix.from_list_sympy(*shape, rows).convert_to(self.domain).to_dense()

    def eye(self, n):
        from sympy.polys.matrices import DomainMatrix

        return (DomainMatrix.eye(n, self.domain) if n else DomainMatrix.zeros((0, 0), self.domain)).to_dense()

    def zeros(self, r, c):
        from sympy.polys.matrices import DomainMatrix

        return DomainMatrix.zeros((r, c), self.domain).to_dense()

    @staticmethod
    def vstack(mats):
        first, *rest = (m.to_dense() for m in mats)
        return first.vstack(*rest) if rest else first

    @staticmethod
    def hstack(mats):
        first, *rest = (m.to_dense() for m in mats)
        return first.hstack(*rest) if rest else first

    def mul(self, x, y):
        if x.shape[1] == 0:
            return self.zeros(x.shape[0], y.shape[1])
        return x.to_dense().matmul(y.to_dense())

    @staticmethod
    def inv(x):
        return x if x.shape[0] == 0 else x.to_dense().inv()

    @staticmethod
    def rank(x):
        return 0 if 0 in x.shape else x.rank()

    @staticmethod
    def rref(x):
        if 0 in x.shape:
            return x, ()
        r, pivots = x.to_dense().rref()
        return r[: len(pivots), :].to_dense(), tuple(pivots)

    def left_null(self, x):
        """Rows v (k, rows(x)) with v x = 0, a basis in reduced row echelon form."""
        r, c = x.shape
        if c == 0:
            return self.eye(r)
        if r == 0:
            return self.zeros(0, 0)
        basis = x.to_dense().transpose().nullspace()
        if basis.shape[0] == 0:
            return self.zeros(0, r)
        return self.rref(basis)[0]

    def dependencies(self, source, M, y):
        """Rows [dep, dep_y] with dep (source M) + dep_y y = 0 (y of full row rank), dep in reduced row echelon
        form."""
        x = self.mul(source, M)
        return self.left_null(self.vstack([x, y]) if y.shape[0] else x)

    @staticmethod
    def is_zero(x):
        return x.is_zero_matrix

    def output(self, x):
        import sympy as sp

        return sp.Matrix(x.shape[0], x.shape[1], [sp.factor(e) for e in x.to_Matrix()])


class _Float:
    exact = False

    def __init__(self, tol):
        self.tol = tol

    @staticmethod
    def matrix(rows, shape):
        return np.asarray(rows, dtype=float).reshape(shape)

    @staticmethod
    def eye(n):
        return np.eye(n)

    @staticmethod
    def zeros(r, c):
        return np.zeros((r, c))

    @staticmethod
    def vstack(mats):
        return np.vstack(mats)

    @staticmethod
    def hstack(mats):
        return np.hstack(mats)

    @staticmethod
    def mul(x, y):
        return x @ y

    @staticmethod
    def inv(x):
        return np.linalg.inv(x) if x.size else x

    def _cut(self, scale):
        return self.tol * max(scale, 1.0)

    def rank(self, x):
        if 0 in x.shape:
            return 0
        s = np.linalg.svd(x, compute_uv=False)
        return int(np.sum(s > self._cut(s[0])))

    def rref(self, x):
        """Gauss-Jordan elimination of a matrix of full row rank (every use in the algorithm): the pivot of each
        row is the leftmost column whose largest remaining entry reaches ``tol`` times the largest remaining entry
        of all columns, so there is one pivot per row."""
        r = np.array(x, dtype=float)
        if 0 in r.shape:
            return r, ()
        pivots = []
        for row in range(r.shape[0]):
            rest = np.abs(r[row:, :])
            best = rest.max()
            col = int(np.argmax(rest.max(axis=0) >= self.tol * best)) if best > 0 else -1
            if col < 0 or col in pivots:
                raise np.linalg.LinAlgError("scb: rank deficiency where full rank is required (numeric=True)")
            k = row + int(np.argmax(rest[:, col]))
            r[[row, k]] = r[[k, row]]
            r[row] /= r[row, col]
            others = np.arange(r.shape[0]) != row
            r[others] -= np.outer(r[others, col], r[row])
            pivots.append(col)
        return r, tuple(pivots)

    def left_null(self, x):
        r, c = x.shape
        if c == 0:
            return np.eye(r)
        if r == 0:
            return np.zeros((0, 0))
        u, s, _ = np.linalg.svd(x)
        k = int(np.sum(s > self._cut(s[0] if s.size else 0.0)))
        basis = u[:, k:].T
        return self.rref(basis)[0] if basis.shape[0] else np.zeros((0, r))

    def dependencies(self, source, M, y):
        """As the exact one. The rows of x = source M are expressed in an orthonormal basis of the complement of
        the rows of y (so at most ``columns - rows(y)`` of them can be independent), scaled by ``|source_i| |M|``
        (a row that is small on that scale is numerically zero) and get their rank decided by singular values;
        dep_y comes from least squares."""
        x = source @ M
        if x.shape[1] == 0:
            return self.left_null(x)
        scale = np.linalg.norm(source, axis=1) * max(np.linalg.norm(M, 2), np.finfo(float).tiny)
        scale[scale == 0] = 1.0
        complement = np.linalg.svd(y)[2][y.shape[0] :].T if y.shape[0] else np.eye(x.shape[1])
        dep = self.left_null((x @ complement) / scale[:, None]) if complement.shape[1] else np.eye(x.shape[0])
        if dep.shape[0] == 0:
            return np.zeros((0, x.shape[0] + y.shape[0]))
        dep = self.rref(dep / scale[None, :])[0]
        coeffs = np.linalg.lstsq(y.T, x.T, rcond=None)[0].T if y.shape[0] else np.zeros((x.shape[0], 0))
        return np.hstack([dep, -dep @ coeffs])

    def is_zero(self, x):
        return not x.size or float(np.max(np.abs(x))) <= self.tol

    @staticmethod
    def output(x):
        return np.asarray(x, dtype=float)


# --------------------------------------------------------------------------------------------------------------
# The modified Silverman algorithm (section 7.4) for a strictly proper system with B of full column rank and C of
# full row rank. Functionals of the state are rows (1, n); a "sequence" is a list of rows r_1, ..., r_k whose
# derivatives satisfy r_j' = r_{j+1} (mod the outputs y_d, and for x_b also y_b) with r_1 an output.


def _complement(bk, rows, n):
    """Identity rows completing ``rows`` (full row rank) to a nonsingular matrix: the rows at the non-pivot
    columns of rref(rows) (section 7.4.1, construction of S_i1)."""
    pivots = set(bk.rref(rows)[1]) if rows.shape[0] else set()
    eye = bk.eye(n)
    keep = [eye[i : i + 1, :] for i in range(n) if i not in pivots]
    return bk.vstack(keep) if keep else bk.zeros(0, n)


def _row(m, i):
    return m[i : i + 1, :]


def _combine(bk, coeffs, rows, n):
    """sum_k coeffs[k] * rows[k] for a coefficient row (1, K) and K rows (1, n); zero row if K = 0."""
    if not rows:
        return bk.zeros(1, n)
    return bk.mul(coeffs, bk.vstack(rows))


def _structure(bk, A, B, C):
    """x_b sequences and x_d chains (section 7.4.1): returns (chains, chain input rows, x_b sequences)."""
    n = A.shape[0]
    chains, inputs, xb = [], [], []
    active = [[_row(C, k)] for k in range(C.shape[0])]
    depth = 1
    while active:
        # S_i: split the level-`depth` rows into new chain bottoms and input-free combinations (aligned with the
        # bottoms of the shorter chains whose input rows they repeat).
        level = bk.vstack([seq[-1] for seq in active])
        null = bk.dependencies(level, B, bk.vstack(inputs) if inputs else bk.zeros(0, B.shape[1]))
        p_i = len(active)
        pivots = bk.rref(null[:, :p_i])[1] if null.shape[0] else ()
        old_chains = list(chains)
        combos = []
        for k in range(null.shape[0]):
            sigma, sigma_b = null[k : k + 1, :p_i], null[k : k + 1, p_i:]
            seq = []
            for lev in range(depth):
                r = _combine(bk, sigma, [s[lev] for s in active], n)
                for j, chain in enumerate(old_chains):
                    idx = len(chain) - depth + lev
                    if idx >= 0:
                        r = r + bk.mul(sigma_b[:, j : j + 1], chain[idx])
                seq.append(r)
            combos.append(seq)
        for k in range(p_i):
            if k not in pivots:
                chains.append(active[k])
                inputs.append(bk.mul(active[k][-1], B))
        if not combos:
            break
        # phi_i: combinations whose next derivative depends on the states found so far end as x_b sequences;
        # their terms in non-output states of chains and of the other sequences are removed by aligned shifts.
        last = bk.vstack([seq[-1] for seq in combos])
        following = [_row(bk.mul(last, A), k) for k in range(len(combos))]
        tagged = [(ch, lev) for ch in chains for lev in range(len(ch))]
        tagged += [(seq, lev) for seq in combos for lev in range(depth)]
        old = [seq[lev] for seq, lev in tagged] + [r for seq in xb for r in seq]
        null = bk.dependencies(last, A, bk.vstack(old) if old else bk.zeros(0, n))
        q = len(following)
        pivots = bk.rref(null[:, :q])[1] if null.shape[0] else ()
        if null.shape[0] and len(pivots) != null.shape[0]:
            # exact arithmetic cannot get here (the states found are independent by construction); in floating
            # point it means the rank decisions at this tolerance contradict each other
            raise np.linalg.LinAlgError(
                "scb: inconsistent rank decisions (ill-conditioned for numeric=True at this tol; use exact arithmetic)"
            )
        for k in range(null.shape[0]):
            dep, dep_b = null[k : k + 1, :q], null[k : k + 1, q:]
            seq = [_combine(bk, dep, [s[lev] for s in combos], n) for lev in range(depth)]
            for t, (other, lev) in enumerate(tagged):
                coeff = dep_b[:, t : t + 1]  # the derivative has the term -coeff * other[lev]
                if lev == 0 or bk.is_zero(coeff):
                    continue
                for s_lev in range(depth):
                    idx = lev - depth + s_lev
                    if idx >= 0:
                        seq[s_lev] = seq[s_lev] + bk.mul(coeff, other[idx])
            xb.append(seq)
        active = [combos[k] + [following[k]] for k in range(q) if k not in pivots]
        depth += 1
    return chains, inputs, xb


def _eliminate(bk, A, Ts, sequences, bottoms):
    """Make the derivative of the states ``Ts`` free of every non-output row of ``sequences`` (section 7.4.2):
    u_d through the chain ``bottoms`` (pairs (bottom row, input coefficient column)), then the levels from the
    deepest up, each term r_{j,L} removed by subtracting its coefficient times r_{j,L-1}."""
    n_s = Ts.shape[0]
    flat = [r for seq in sequences for r in seq]
    index, k = [], n_s
    for seq in sequences:
        index.append(list(range(k, k + len(seq))))
        k += len(seq)

    def coefficients(ts):
        basis = bk.vstack([ts] + flat) if flat else ts
        return bk.mul(bk.mul(ts, A), bk.inv(basis))

    for bottom_row, coeff in bottoms:
        Ts = Ts - bk.mul(coeff, bottom_row)
    depth = max((len(s) for s in sequences), default=0)
    for lev in range(depth - 1, 0, -1):
        F = coefficients(Ts)
        for seq, idx in zip(sequences, index, strict=True):
            if len(seq) > lev:
                Ts = Ts - bk.mul(F[:, idx[lev] : idx[lev] + 1], seq[lev - 1])
    return Ts, coefficients(Ts)


def _scb_sp(bk, A, B, C):
    """SCB of a strictly proper system: (T = state_transform^-1, output_transform^-1 rows, input_transform, dims,
    chain lengths)."""
    n, m = B.shape
    chains, inputs, xb = _structure(bk, A, B, C)
    m_d = len(chains)
    Tb = [r for seq in xb for r in seq]
    Td = [r for ch in chains for r in ch]
    Tbd = bk.vstack(Tb + Td) if Tb + Td else bk.zeros(0, n)
    Dbar = bk.vstack(inputs) if inputs else bk.zeros(0, m)
    G3p = bk.inv(bk.vstack([Dbar, _complement(bk, Dbar, m)]))  # u = G3p col(u_d, u_c')
    Ts = _complement(bk, Tbd, n)
    n_s = Ts.shape[0]
    Bs = bk.mul(bk.mul(Ts, B), G3p)
    bottoms = [(ch[-1], Bs[:, j : j + 1]) for j, ch in enumerate(chains)]
    Ts, F = _eliminate(bk, A, Ts, xb + chains, bottoms)
    Bsc = bk.mul(bk.mul(Ts, B), G3p)[:, m_d:]
    G3 = G3p
    if m - m_d and n_s:
        # split x_s into x_a, x_c by the same construction on the transposed pair (A_ss^T, output B_sc^T)
        Ass = F[:, :n_s]
        At, Ct = Ass.transpose(), Bsc.transpose()
        _, _, xb_t = _structure(bk, At, bk.zeros(n_s, 0), Ct)
        Tb_t = [r for seq in xb_t for r in seq]
        Ta_t = _complement(bk, bk.vstack(Tb_t), n_s)
        Ta_t, _ = _eliminate(bk, At, Ta_t, xb_t, [])
        Tstar = bk.vstack([Ta_t] + Tb_t)
        tops_t = bk.vstack([seq[0] for seq in xb_t])
        G2star_inv = _output_rows(bk, tops_t, Ct)
        Ts = bk.mul(bk.inv(Tstar).transpose(), Ts)
        n_a = Ta_t.shape[0]
        G3 = bk.mul(G3p, _blockdiag(bk, bk.eye(m_d), G2star_inv.transpose()))
    else:
        n_a = n_s
    T = bk.vstack([Ts[:n_a, :], *Tb, Ts[n_a:, :], *Td]) if n else bk.zeros(0, 0)
    tops = [ch[0] for ch in chains] + [seq[0] for seq in xb]
    G2inv = _output_rows(bk, bk.vstack(tops), C) if tops else bk.zeros(0, 0)
    dims = (n_a, len(Tb), n_s - n_a, len(Td))
    return T, G2inv, G3, dims, tuple(len(ch) for ch in chains)


def _output_rows(bk, tops, C):
    """G with G C = tops (C of full row rank): the rows of output_transform^-1."""
    right = bk.mul(C.transpose(), bk.inv(bk.mul(C, C.transpose())))
    return bk.mul(tops, right)


def _blockdiag(bk, a, b):
    top = bk.hstack([a, bk.zeros(a.shape[0], b.shape[1])])
    bottom = bk.hstack([bk.zeros(b.shape[0], a.shape[1]), b])
    return bk.vstack([top, bottom])


# --------------------------------------------------------------------------------------------------------------
# Input conversion and the general (non-strictly proper) case.


def _exact_entry(value, name):
    import sympy as sp

    if isinstance(value, sp.Basic):
        if value.has(sp.nan, sp.oo, -sp.oo, sp.zoo):
            raise ValueError(f"{name} must be finite, got the entry {value}")
        floats = value.atoms(sp.Float)
        return value.xreplace({f: _exact_entry(float(f), name) for f in floats}) if floats else value
    if isinstance(value, bool | np.bool_):
        return sp.Integer(int(value))
    if isinstance(value, Integral):
        return sp.Integer(int(value))
    if isinstance(value, Rational):
        return sp.Rational(int(value.numerator), int(value.denominator))
    if isinstance(value, Real):
        if not np.isfinite(float(value)):
            raise ValueError(f"{name} must be finite, got the entry {value}")
        return sp.Rational(repr(float(value)))
    raise ValueError(f"{name} must hold numbers or sympy expressions, got the entry {value!r} ({type(value).__name__})")


def _as_rows(value, name, shape=None):
    """A nested list of entries with a 2-D shape; 1-D input is a column (B) or a row (C) by ``shape``."""
    try:
        import sympy as sp

        if isinstance(value, sp.MatrixBase):
            rows = value.tolist()
            return rows, (value.rows, value.cols)
    except ImportError:  # pragma: no cover - sympy is a dependency
        pass
    array = np.asarray(value, dtype=object)
    if array.ndim == 0:
        array = array.reshape(1, 1)
    elif array.ndim == 1:
        array = array.reshape(shape if shape is not None else (1, -1))
    if array.ndim != 2:
        raise ValueError(f"{name} must be a matrix (2-D), got shape {array.shape}")
    return array.tolist(), array.shape


def _validate(A, B, C, D):
    a_rows, a_shape = _as_rows(A, "A")
    if a_shape[0] != a_shape[1]:
        raise ValueError(f"A must be square, got shape {a_shape}")
    n = a_shape[0]
    b_rows, b_shape = _as_rows(B, "B", (n, -1) if n else None)
    c_rows, c_shape = _as_rows(C, "C", (-1, n) if n else None)
    if b_shape[0] != n:
        raise ValueError(f"B must have {n} rows (A is {n}x{n}), got shape {b_shape}")
    if c_shape[1] != n:
        raise ValueError(f"C must have {n} columns (A is {n}x{n}), got shape {c_shape}")
    m, p = b_shape[1], c_shape[0]
    if D is None:
        d_rows, d_shape = [[0] * m for _ in range(p)], (p, m)
    else:
        d_rows, d_shape = _as_rows(D, "D", (p, m))
    if d_shape != (p, m):
        raise ValueError(f"D must have shape {(p, m)} (C has {p} rows, B {m} columns), got {d_shape}")
    return {"A": (a_rows, a_shape), "B": (b_rows, b_shape), "C": (c_rows, c_shape), "D": (d_rows, d_shape)}


@_checks.design_time()
def scb(A, B, C, D=None, *, numeric: bool = False, tol: float = 1e-9) -> SCB:
    """Special coordinate basis (7.4)-(7.6) of ``x' = A x + B u``, ``y = C x + D u`` (Grip 2010, section 7.4).

    Args:
      A: (n, n) state matrix; entries numbers or sympy expressions (docs/theory/analysis.md, "Arithmetic").
      B: (n, m) input matrix; ``[B; D]`` must have full column rank.
      C: (p, n) output matrix; ``[C, D]`` must have full row rank.
      D: (p, m) feedthrough, zero if None.
      numeric: floating-point arithmetic with rank decisions by singular values (less exact) instead of exact fractions
        / rational functions. The x_b, x_c and x_d coordinates are successive derivatives (rows r, r A, r A^2, ...), so
        long sequences give ill-conditioned transformations (the numbers in docs/theory/measurements.md): the
        structure (dims, chains) is then reliable only through its rank decisions and the matrices are not; use the
        exact variant for them.
      tol: relative rank tolerance of the numeric variant, in (0, 1).

    Returns:
      :class:`SCB`. With ``Ah = A - B_0 C_0`` of the pre-transformed system (section 7.2.4), ``SCB.A =
      state_transform^-1 Ah state_transform``, ``SCB.B = state_transform^-1 (B U) input_transform``, ``SCB.C =
      output_transform^-1 (Y^-1 C) state_transform``, ``SCB.D = output_transform^-1 (Y^-1 D U) input_transform =
      diag(I_m0, 0)`` hold exactly in the exact variant.

    Example:
      >>> from jaxobs.scb import scb
      >>> s = scb([[0, 1], [0, 0]], [[0], [1]], [[1, 0]])
      >>> s.dims, s.chain_lengths
      ((0, 0, 0, 2), (2,))
    """
    given = _validate(A, B, C, D)
    if _checks.boolean("numeric", numeric):
        if not (isinstance(tol, Real) and np.isfinite(tol) and 0 < tol < 1):
            raise ValueError(f"tol must be a number in (0, 1), got {tol!r}")
        bk = _Float(float(tol))
        mats = {}
        for k, (rows, shape) in given.items():
            try:
                arr = np.asarray(rows, dtype=float).reshape(shape)
            except (TypeError, ValueError) as err:
                raise ValueError(f"{k} must hold numbers for numeric=True ({err})") from None
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{k} must be finite, got non-finite entries")
            mats[k] = arr
        symbols = ()
    else:
        exact = {k: [[_exact_entry(v, k) for v in row] for row in rows] for k, (rows, _) in given.items()}
        entries = [v for rows in exact.values() for row in rows for v in row]
        bk = _Exact(entries)
        mats = {k: bk.matrix(exact[k], given[k][1]) for k in exact}
        symbols = tuple(sorted(set().union(*(getattr(v, "free_symbols", set()) for v in entries)), key=str))
    A_, B_, C_, D_ = mats["A"], mats["B"], mats["C"], mats["D"]
    m, p = B_.shape[1], C_.shape[0]
    if bk.rank(bk.vstack([B_, D_])) < m:
        raise ValueError(f"B: [B; D] must have full column rank {m} (remove dependent inputs first)")
    if bk.rank(bk.hstack([C_, D_])) < p:
        raise ValueError(f"C: [C, D] must have full row rank {p} (remove dependent outputs first)")
    # section 7.2.4 / 7.4.3: U, Y with Y^-1 D U = diag(I_m0, 0)
    Y2 = bk.left_null(D_) if p else bk.zeros(0, 0)
    m0 = p - Y2.shape[0]
    Y1 = _complement(bk, Y2, p)
    Yinv = bk.vstack([Y1, Y2]) if p else bk.zeros(0, 0)
    U1 = bk.mul(Y1, D_)
    Uinv = bk.vstack([U1, _complement(bk, U1, m)]) if m else bk.zeros(0, 0)
    U, Y = bk.inv(Uinv), bk.inv(Yinv)
    Bh, Ch = bk.mul(B_, U), bk.mul(Yinv, C_)
    Ah = A_ - bk.mul(Bh[:, :m0], Ch[:m0, :])
    T, G2inv, G3bar, dims, chains = _scb_sp(bk, Ah, Bh[:, m0:], Ch[m0:, :])
    G1 = bk.inv(T)
    G2 = bk.inv(_blockdiag(bk, bk.eye(m0), G2inv))
    G3 = _blockdiag(bk, bk.eye(m0), G3bar)
    Dh = bk.mul(bk.mul(Yinv, D_), U)
    out = bk.output
    return SCB(
        A=out(bk.mul(bk.mul(T, Ah), G1)),
        B=out(bk.mul(bk.mul(T, Bh), G3)),
        C=out(bk.mul(bk.mul(bk.inv(G2), Ch), G1)),
        D=out(bk.mul(bk.mul(bk.inv(G2), Dh), G3)),
        state_transform=out(G1),
        output_transform=out(G2),
        input_transform=out(G3),
        U=out(U),
        Y=out(Y),
        dims=dims,
        chain_lengths=chains,
        m0=m0,
        exact=bk.exact,
        symbols=symbols,
    )


# --------------------------------------------------------------------------------------------------------------
# Checks and queries (section 7.3).


def _system(system) -> SCB:
    if isinstance(system, SCB):
        return system
    if isinstance(system, tuple | list) and len(system) in (3, 4):
        return scb(*system)
    raise ValueError(f"system must be an SCB or a tuple (A, B, C) or (A, B, C, D), got {type(system).__name__}")


@_checks.design_time()
def scb_residuals(system: SCB, A, B, C, D=None) -> dict:
    """Residuals of the identities relating ``system`` to the original ``(A, B, C, D)`` (section 7.2.3), in the
    inverse-free form ``state_transform A_scb - Ah state_transform``, ``state_transform B_scb - (B U) input_transform``,
    ``output_transform C_scb - (Y^-1 C) state_transform``, ``output_transform D_scb - (Y^-1 D U) input_transform`` with
    ``Ah = A - (B U)_0 (Y^-1 C)_0``.

    Args:
      system: an :class:`SCB` (from :func:`scb`, or built from printed matrices to check them).
      A, B, C, D: the original matrices (D zero if None), as given to :func:`scb`.

    Returns:
      dict ``{"A", "B", "C", "D"}`` of residual matrices: sympy matrices with canceled entries (exactly zero for an
      exact decomposition) when ``system.exact``, else float arrays.
    """
    given = _validate(A, B, C, D)
    if system.exact:
        import sympy as sp

        M = {
            k: sp.Matrix(*shape, [_exact_entry(v, k) for row in rows for v in row])
            for k, (rows, shape) in given.items()
        }
        simplify = lambda x: x.applyfunc(sp.cancel)  # noqa: E731
    else:
        M = {k: np.asarray(rows, dtype=float).reshape(shape) for k, (rows, shape) in given.items()}
        simplify = lambda x: np.asarray(x, dtype=float)  # noqa: E731
    s, m0 = system, system.m0
    Yinv = s.Y.inv() if system.exact else np.linalg.inv(s.Y)
    Bh, Ch, Dh = M["B"] @ s.U, Yinv @ M["C"], Yinv @ M["D"] @ s.U
    Ah = M["A"] - Bh[:, :m0] @ Ch[:m0, :]
    return {
        "A": simplify(s.state_transform @ s.A - Ah @ s.state_transform),
        "B": simplify(s.state_transform @ s.B - Bh @ s.input_transform),
        "C": simplify(s.output_transform @ s.C - Ch @ s.state_transform),
        "D": simplify(s.output_transform @ s.D - Dh @ s.input_transform),
    }


@_checks.design_time()
def invariant_zeros(system) -> list:
    """Invariant zeros: the eigenvalues of A_aa, with multiplicity (section 7.3).

    Args:
      system: an :class:`SCB` or a tuple ``(A, B, C)`` / ``(A, B, C, D)`` decomposed exactly by :func:`scb`.

    Returns:
      list of sympy numbers/expressions (exact; irrational roots as ``CRootOf``) or of complex floats (numeric).
      Raises ValueError when the roots of a symbolic characteristic polynomial cannot be expressed.

    Example:
      >>> import jaxobs as jo
      >>> jo.invariant_zeros(([[0, 1], [-2, -3]], [[0], [1]], [[1, 1]]))  # (s + 1)/((s + 1)(s + 2))
      [-1]
    """
    s = _system(system)
    Aaa = s.block("aa")
    if not s.exact:
        return list(np.linalg.eigvals(np.asarray(Aaa, dtype=float))) if s.dims[0] else []
    import sympy as sp

    if not s.dims[0]:
        return []
    charpoly = Aaa.charpoly()
    lam = charpoly.gen
    poly = sp.Poly(charpoly.as_expr(), lam)
    if not poly.free_symbols - {lam}:
        return list(poly.all_roots())
    roots = sp.roots(poly)
    if sum(roots.values()) != poly.degree():
        raise ValueError(f"system: the roots of det(s I - A_aa) = {poly.as_expr()} have no closed form")
    return [r for r, k in sorted(roots.items(), key=lambda rk: sp.default_sort_key(rk[0])) for _ in range(k)]


@_checks.design_time()
def infinite_zero_structure(system) -> dict[int, int]:
    """Infinite zeros ``{order: count}``: m0 of order 0 and, for each i, the number of chains of length i
    (section 7.3).

    Args:
      system: an :class:`SCB` or a tuple ``(A, B, C)`` / ``(A, B, C, D)``.
    """
    s = _system(system)
    counts = {0: s.m0} if s.m0 else {}
    for q in s.chain_lengths:
        counts[q] = counts.get(q, 0) + 1
    return dict(sorted(counts.items()))


@_checks.design_time()
def is_left_invertible(system) -> bool:
    """True iff there is no x_c subsystem (section 7.3).

    Args:
      system: an :class:`SCB` or a tuple ``(A, B, C)`` / ``(A, B, C, D)``.
    """
    return _system(system).dims[2] == 0


@_checks.design_time()
def is_right_invertible(system) -> bool:
    """True iff there is no x_b subsystem (section 7.3).

    Args:
      system: an :class:`SCB` or a tuple ``(A, B, C)`` / ``(A, B, C, D)``.
    """
    return _system(system).dims[1] == 0


@_checks.design_time()
def is_minimum_phase(system) -> bool:
    """True iff every invariant zero has a negative real part (A_aa Hurwitz, section 7.3).

    Args:
      system: an :class:`SCB` or a tuple ``(A, B, C)`` / ``(A, B, C, D)``. For symbolic zeros whose sign the
        symbols' assumptions do not decide, a ValueError asks for values (see :func:`scb_arrays`).
    """
    zeros = invariant_zeros(system)
    s = _system(system)
    if not s.exact:
        return bool(all(np.real(z) < 0 for z in zeros))
    import sympy as sp

    signs = [sp.re(z).is_negative for z in zeros]
    if None in signs:
        undecided = [z for z, k in zip(zeros, signs, strict=True) if k is None]
        raise ValueError(f"system: the sign of the real part of the zeros {undecided} depends on the parameters")
    return all(signs)


@_checks.design_time()
def scb_arrays(system: SCB, values: dict | None = None) -> SCB:
    """The SCB with every matrix a float array, the symbols replaced by ``values``.

    Args:
      system: an exact :class:`SCB`.
      values: ``{symbol or its name: number}`` for every symbol in ``system.symbols``.

    Returns:
      :class:`SCB` with NumPy arrays and ``exact=False``. Raises ValueError for a missing symbol or values at which
      an entry is singular (a structure valid only generically, e.g. sigma_1 = 0 in Grip 2010, section 7.5.2).
    """
    import sympy as sp

    if not system.exact:
        return system
    values = dict(values or {})
    by_name = {str(k): v for k, v in values.items()}
    missing = [str(x) for x in system.symbols if str(x) not in by_name]
    if missing:
        raise ValueError(f"values must give every symbol, missing {missing}")
    subs = {x: _exact_entry(by_name[str(x)], f"values[{x}]") for x in system.symbols}
    fields = {}
    for name in ("A", "B", "C", "D", "state_transform", "output_transform", "input_transform", "U", "Y"):
        M = getattr(system, name).xreplace(subs).applyfunc(sp.cancel)
        if any(e.has(sp.zoo, sp.nan, sp.oo) for e in M):
            raise ValueError(f"values: {name} is singular at {by_name}")
        fields[name] = np.array(M.tolist(), dtype=float).reshape(M.shape)
    return SCB(**fields, dims=system.dims, chain_lengths=system.chain_lengths, m0=system.m0, exact=False)
