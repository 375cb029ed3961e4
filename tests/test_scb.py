"""Special coordinate basis (Grip 2010, ch. 7): exact identities, the zero pattern of (7.6), the structural
invariants against independent computations (Rosenbrock pencil, Markov-parameter Toeplitz ranks), determinism,
the numeric variant and bad input."""

import numpy as np
import pytest
import scipy.linalg
from sympy.polys.matrices import DomainMatrix

sp = pytest.importorskip("sympy")

from jaxobs import scb as scbmod  # noqa: E402
from jaxobs.papers.grip2010 import scb as grip_scb  # noqa: E402
from jaxobs.scb import (  # noqa: E402
    infinite_zero_structure,
    invariant_zeros,
    is_left_invertible,
    is_minimum_phase,
    is_right_invertible,
    scb,
    scb_arrays,
    scb_residuals,
)


def _zero(M):
    return all(sp.cancel(e) == 0 for e in M)


def _slices(s):
    o = np.concatenate([[0], np.cumsum(s.dims)]).astype(int)
    return [slice(o[k], o[k + 1]) for k in range(4)]


def _check_form(s):
    """The zero pattern of (7.6), checked entry by entry (independently of the library), plus the observability
    of (C_b, A_bb) and the controllability of (A_cc, B_c)."""
    A, B, C, D = (M.applyfunc(sp.cancel) for M in (s.A, s.B, s.C, s.D))
    a, b, c, d = _slices(s)
    n, m0 = A.rows, s.m0
    md = len(s.chain_lengths)
    mc = B.cols - m0 - md
    starts = np.concatenate([[0], np.cumsum(s.chain_lengths)]).astype(int)[:-1]
    tops = [d.start + k for k in starts]
    bottoms = [d.start + k + q - 1 for k, q in zip(starts, s.chain_lengths, strict=True)]
    ud, uc = slice(m0, m0 + md), slice(m0 + md, m0 + md + mc)
    yd, yb = slice(m0, m0 + md), slice(m0 + md, C.rows)
    # D = diag(I_m0, 0); C rows y_d select the chain tops, rows y_b live on x_b
    assert D == sp.diag(sp.eye(m0), sp.zeros(D.rows - m0, D.cols - m0))
    Cd = sp.zeros(md, n)
    for i, t in enumerate(tops):
        Cd[i, t] = 1
    assert C[yd, :] == Cd
    Cb = C[yb, b]
    assert _zero(C[yb, a]) and _zero(C[yb, c]) and _zero(C[yb, d])
    # B: x_a, x_b have no u_d, u_c; x_c no u_d; x_d only at the bottoms, u_d = identity there
    assert _zero(B[a, m0:]) and _zero(B[b, m0:]) and _zero(B[c, ud])
    Bd = sp.zeros(s.dims[3], md)
    for i, r in enumerate(bottoms):
        Bd[r - d.start, i] = 1
    assert B[d, ud] == Bd and _zero(B[d, uc])
    Bc = B[c, uc]

    def in_rowspace(M, basis):  # rows of M in the row space of basis
        return M.rows == 0 or sp.Matrix.vstack(basis, M).rank(simplify=True) == basis.rank(simplify=True)

    def in_colspace(M, basis):
        return in_rowspace(M.T, basis.T)

    def only_tops(M):
        return all(_zero(M[:, k]) for k in range(s.dims[3]) if d.start + k not in tops)

    # A rows x_a: [A_aa, L_ab C_b, 0, L_ad C_d]
    assert _zero(A[a, c]) and only_tops(A[a, d]) and in_rowspace(A[a, b], Cb)
    # rows x_b: [0, A_bb, 0, L_bd C_d]
    assert _zero(A[b, a]) and _zero(A[b, c]) and only_tops(A[b, d])
    # rows x_c: [B_c E_ca, L_cb C_b, A_cc, L_cd C_d]
    assert in_colspace(A[c, a], Bc) and in_rowspace(A[c, b], Cb) and only_tops(A[c, d])
    # rows x_d above the bottoms: shift to the next level plus y_d injection, nothing else
    for r in range(d.start, d.stop):
        if r in bottoms:
            continue
        row = A[r, :]
        assert _zero(row[:, : d.start]) and row[0, r + 1] == 1
        assert all(sp.cancel(row[0, k]) == 0 for k in range(d.start, d.stop) if k not in tops and k != r + 1)
    Abb, Acc = A[b, b], A[c, c]
    nb, nc = s.dims[1], s.dims[2]
    if nb:
        obs = sp.Matrix.vstack(*[Cb * Abb**k for k in range(nb)])
        assert obs.rank(simplify=True) == nb
    if nc:
        ctr = sp.Matrix.hstack(*[Acc**k * Bc for k in range(nc)])
        assert ctr.rank(simplify=True) == nc


def _check_residuals(s, A, B, C, D=None):
    res = scb_residuals(s, A, B, C, D)
    assert all(_zero(M) for M in res.values()), res


# ---------------------------------------------------------------------------------------------------- printed cases

SYSTEMS = grip_scb.systems()
PRINTED = grip_scb.printed()
T_A, T_B, T_C = (np.array(M.tolist(), dtype=int) for M in SYSTEMS["tenth_order"])


@pytest.fixture(scope="module")
def printed():
    return {name: scb(*system) for name, system in SYSTEMS.items()}


@pytest.mark.parametrize("name", list(PRINTED))
def test_printed_cases_structure_and_exact_identities(printed, name):
    """dims, chains and zeros as printed in Grip 2010, section 7.5; the identities hold exactly; (7.6) form."""
    s, expected = printed[name], PRINTED[name]
    assert s.dims == expected["dims"] and s.chain_lengths == expected["chain_lengths"]
    assert [sp.simplify(z) for z in invariant_zeros(s)] == expected["invariant_zeros"]
    _check_residuals(s, *SYSTEMS[name])
    _check_form(s)


def test_printed_queries(printed):
    s = printed
    assert not is_right_invertible(s["single_track"]) and is_left_invertible(s["single_track"])
    assert is_right_invertible(s["single_track_rear"]) and is_left_invertible(s["single_track_rear"])
    assert not is_right_invertible(s["tenth_order"]) and not is_left_invertible(s["tenth_order"])
    assert infinite_zero_structure(s["tenth_order"]) == {1: 1, 2: 1, 3: 1}
    assert infinite_zero_structure(s["single_track_rear"]) == {1: 1, 2: 1}
    assert not is_minimum_phase(s["tenth_order"]) and not is_minimum_phase(s["single_track_rear"])
    assert is_minimum_phase(s["dc_motor"])  # -sigma_0/sigma_1 with positive symbols
    free = scb(*(M.subs(sp.Symbol("sigma_1", positive=True), sp.Symbol("sigma_1")) for M in SYSTEMS["dc_motor"]))
    with pytest.raises(ValueError, match="system"):
        is_minimum_phase(free)  # the sign of -sigma_0/sigma_1 depends on sigma_1 without assumptions


def test_scb_arrays_dc_motor_matches_the_printed_numeric_scb(printed):
    values = {"J": 0.0023, "sigma_0": 260.0, "sigma_1": 0.6, "alpha_2": 0.176}
    num = scb_arrays(printed["dc_motor"], values)
    assert not num.exact and num.A.dtype == float
    # Grip 2010, section 7.5.2, Linear Systems Toolkit: A ~ [[-433.3, -592.7, 0], [0, 0, 1], [-1.1e5, -1.5e5, 95.9]]
    np.testing.assert_allclose(num.A[0, :2], [-433.3, -592.7], atol=0.05)
    np.testing.assert_allclose(num.A[2], [-1.1e5, -1.5e5, 95.9], rtol=0.05)
    with pytest.raises(ValueError, match="values"):
        scb_arrays(printed["dc_motor"], {**values, "sigma_1": 0})
    with pytest.raises(ValueError, match="missing"):
        scb_arrays(printed["dc_motor"], {"J": 1})


# ---------------------------------------------------------------------------------------------------- random systems


def _random_system(seed):
    """Sparse small-integer systems (the kind of Grip 2010, section 7.6) of order 1-6, 1-3 inputs and outputs,
    every fourth with a rank-one or rank-two feedthrough; redrawn until [B; D] and [C, D] have full rank."""
    rng = np.random.default_rng(seed)
    while True:
        n, mm, pp = int(rng.integers(1, 7)), int(rng.integers(1, 4)), int(rng.integers(1, 4))
        draw = lambda *shape: rng.integers(-2, 3, shape) * (rng.random(shape) < 0.45)  # noqa: E731
        A, B, C = draw(n, n), draw(n, mm), draw(pp, n)
        D = np.zeros((pp, mm), dtype=int)
        if seed % 4 == 3:
            k = int(rng.integers(1, min(mm, pp) + 1))
            D = rng.integers(-1, 2, (pp, k)) @ rng.integers(-1, 2, (k, mm))
        if np.linalg.matrix_rank(np.vstack([B, D])) == mm and np.linalg.matrix_rank(np.hstack([C, D])) == pp:
            return A, B, C, D


def _rosenbrock(A, B, C, D, s):
    n = A.shape[0]
    const = np.block([[-A, -B], [C, D]]).astype(int)
    return sp.Matrix(const.tolist()) + sp.diag(s * sp.eye(n), sp.zeros(*D.shape))


def _toeplitz_ranks(A, B, C, D, k_max):
    """rank of the block lower-triangular Toeplitz matrix of the Markov parameters D, CB, CAB, ... (k+1 blocks)."""
    markov = [sp.Matrix(D)] + [sp.Matrix(C) * sp.Matrix(A) ** j * sp.Matrix(B) for j in range(k_max)]
    p, mm = D.shape
    ranks = []
    for k in range(k_max + 1):
        T = sp.zeros(p * (k + 1), mm * (k + 1))
        for i in range(k + 1):
            for j in range(i + 1):
                T[i * p : (i + 1) * p, j * mm : (j + 1) * mm] = markov[i - j]
        ranks.append(T.rank())
    return ranks


RANDOM_SEEDS = list(range(50))


@pytest.fixture(scope="module")
def random_scbs():
    return {seed: (_random_system(seed), scb(*_random_system(seed))) for seed in RANDOM_SEEDS}


def test_random_systems_exact_identities_and_form(random_scbs):
    kinds = set()
    for (A, B, C, D), s in random_scbs.values():
        _check_residuals(s, A, B, C, D)
        _check_form(s)
        kinds.add((s.m0 > 0, *(k > 0 for k in s.dims)))
    # the draw covers feedthrough and every subsystem
    assert any(k[0] for k in kinds) and all(any(k[i] for k in kinds) for i in range(1, 5))


def test_random_systems_invariant_zeros_are_the_rosenbrock_zeros(random_scbs):
    """det(s I - A_aa) equals the zero polynomial of the Rosenbrock pencil: the monic gcd of two random
    compressions L P(s) R to its normal rank (by Cauchy-Binet each is a combination of the maximal minors)."""
    s_ = sp.Symbol("s")
    rng = np.random.default_rng(0)
    for (A, B, C, D), s in random_scbs.values():
        P = DomainMatrix.from_Matrix(_rosenbrock(A, B, C, D, s_))
        ring = P.domain
        r = P.to_field().rank()
        zero_poly = None
        for _ in range(2):
            L = DomainMatrix.from_Matrix(sp.Matrix(rng.integers(-9, 10, (r, P.shape[0])))).convert_to(ring)
            R = DomainMatrix.from_Matrix(sp.Matrix(rng.integers(-9, 10, (P.shape[1], r)))).convert_to(ring)
            det = L.matmul(P).matmul(R).det()
            zero_poly = det if zero_poly is None else ring.gcd(zero_poly, det)
        aa = s.block("aa")
        expected = aa.charpoly(s_).as_expr() if aa.rows else sp.Integer(1)
        got = sp.Poly(ring.to_sympy(zero_poly), s_).monic().as_expr()
        assert sp.expand(got - expected) == 0, (A, B, C, D)


def test_square_invertible_zeros_match_scipy_generalized_eigenvalues(random_scbs):
    checked = 0
    for (A, B, C, D), s in random_scbs.values():
        if s.dims[1] or s.dims[2] or B.shape[1] != C.shape[0]:
            continue
        n = A.shape[0]
        P = np.block([[A, B], [C, D]]).astype(float)
        E = scipy.linalg.block_diag(np.eye(n), np.zeros_like(D, dtype=float))
        w = scipy.linalg.eigvals(P, E)
        finite = w[np.isfinite(w)]
        zeros = np.linalg.eigvals(np.array(s.block("aa"), dtype=float)) if s.dims[0] else np.zeros(0)
        assert len(finite) == len(zeros)
        for z in zeros:  # a matching of the two multisets (no sorting of conjugate pairs)
            assert np.min(np.abs(finite - z)) < 1e-6 * (1 + abs(z))
        checked += 1
    assert checked >= 5


def test_chain_lengths_match_markov_toeplitz_ranks(random_scbs):
    """Infinite zeros of order <= k = rank T_k - rank T_(k-1) (T_k: Toeplitz of D, CB, ..., C A^(k-1) B)."""
    for (A, B, C, D), s in random_scbs.values():
        n = A.shape[0]
        ranks = [0] + _toeplitz_ranks(A, B, C, D, n + 1)
        orders = [0] * s.m0 + list(s.chain_lengths)
        for k in range(n + 2):
            assert ranks[k + 1] - ranks[k] == sum(q <= k for q in orders), (k, A, B, C, D)


def test_deterministic(printed):
    again = scb(*SYSTEMS["tenth_order"])
    first = printed["tenth_order"]
    for name in ("A", "B", "C", "D", "state_transform", "output_transform", "input_transform", "U", "Y"):
        assert getattr(again, name) == getattr(first, name)


# ---------------------------------------------------------------------------------------------------- numeric variant


def test_numeric_variant_agrees_with_exact_on_float_models(random_scbs):
    for (A, B, C, D), s in list(random_scbs.values())[:20]:
        f = scb(A.astype(float), B.astype(float), C.astype(float), D.astype(float), numeric=True)
        assert (f.dims, f.chain_lengths, f.m0) == (s.dims, s.chain_lengths, s.m0)
        res = scb_residuals(f, A, B, C, D)
        scale = 1 + max(np.abs(M).max(initial=0) for M in (f.state_transform, f.A))
        assert max(np.abs(M).max(initial=0) for M in res.values()) < 1e-8 * scale**2
    f = scb(T_A.astype(float), T_B.astype(float), T_C.astype(float), numeric=True)
    assert f.dims == (1, 2, 1, 6) and f.chain_lengths == (1, 2, 3)
    np.testing.assert_allclose(invariant_zeros(f), [1.0], atol=1e-9)


def test_floats_become_exact_decimal_fractions():
    s = scb([[0.0, 1.0], [-0.1, -0.3]], [[0.0], [0.0023]], [[1.0, 0.0]])
    assert s.input_transform[0, 0] == sp.Rational(10000, 23)


# ---------------------------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("args", "kwargs", "name"),
    [
        (([[0, 1]], [[1]], [[1]]), {}, "A"),
        (([[0, 1], [0, 0]], [[0], [1], [2]], [[1, 0]]), {}, "B"),
        (([[0, 1], [0, 0]], [[0], [1]], [[1, 0, 0]]), {}, "C"),
        (([[0, 1], [0, 0]], [[0], [1]], [[1, 0]], [[1, 1]]), {}, "D"),
        (([[0, np.nan], [0, 0]], [[0], [1]], [[1, 0]]), {}, "A"),
        (([[0, 1], [0, 0]], [[0], [np.inf]], [[1, 0]]), {}, "B"),
        (([[0, 1], [0, 0]], [[0], [1]], [[1, np.nan]]), {"numeric": True}, "C"),
        (([[0, 1], [0, 0]], [[0, 0], [1, 1]], [[1, 0]]), {}, "B"),
        (([[0, 1], [0, 0]], [[0], [1]], [[1, 0], [2, 0]]), {}, "C"),
        (([[0, 1], [0, 0]], [[0], [1]], [[1, 0]], [[sp.oo]]), {}, "D"),
        (([[0, 1], [0, 0]], [[0], [1]], [[1, 0]]), {"numeric": True, "tol": 0.0}, "tol"),
        (([[0, 1], [0, 0]], [[0], [1]], [[sp.Symbol("a"), 0]]), {"numeric": True}, "C"),
    ],
)
def test_bad_input_names_the_argument(args, kwargs, name):
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        scb(*args, **kwargs)


def test_queries_reject_other_objects():
    with pytest.raises(ValueError, match="system"):
        invariant_zeros("ABC")
    assert scbmod.SCB is type(scb([[0]], [[1]], [[1]]))


@pytest.mark.parametrize("numeric", [False, True], ids=["exact", "numeric"])
def test_zeros_on_the_imaginary_axis_are_not_minimum_phase(numeric):
    """The boundary belongs to the non-minimum-phase side (section 7.3: A_aa Hurwitz): a zero at s = 0
    (-s / ((s + 1)(s + 2))) and a pair at s = +-j ((s^2 + 1) / ((s + 1)(s + 2)(s + 3)), by partial fractions)."""
    for A, B, C, want in [
        (np.diag([-1, -2]), np.ones((2, 1), int), np.array([[1, -2]]), [0]),
        (np.diag([-1, -2, -3]), np.ones((3, 1), int), np.array([[1, -5, 5]]), [1j, -1j]),
    ]:
        s = scb(*(M.astype(float) for M in (A, B, C)), numeric=True) if numeric else scb(A, B, C)
        zeros = np.array(invariant_zeros(s), dtype=complex)
        np.testing.assert_allclose(sorted(zeros, key=np.imag), sorted(want, key=np.imag), atol=1e-9)
        assert not is_minimum_phase(s)
