"""Gains of the modified high-gain observer (Grip 2010, section 6.3): the DC motor of section 6.8, Remark 6.2 on
an SCB-form MIMO system with chains of different lengths (the corrigendum's K_qjq), and the input checks."""

import jax
import numpy as np
import pytest

from jaxobs.observers.hgo import hgo_gains

J, S0, S1, A2 = 0.0023, 260.0, 0.6, 0.176
H1 = [-1 + 0.2j, -1 - 0.2j, -2 + 0.2j, -2 - 0.2j]


def _motor(sigma1):
    """x = (Omega, omega, eta), phi the LuGre term (Grip 2010, section 6.8)."""
    A = [[0, 1, 0], [0, -(A2 + sigma1) / J, -S0 / J], [0, 1, 0]]
    return A, [[0], [sigma1 / J], [-1]], [[1, 0, 0]]


def _close(a, b, tol):
    """Multisets of complex numbers equal within ``tol`` (greedy matching)."""
    a, b = list(np.asarray(a, complex)), list(np.asarray(b, complex))
    assert len(a) == len(b)
    for x in a:
        i = int(np.argmin([abs(x - y) for y in b]))
        if abs(x - b[i]) > tol:
            return False
        b.pop(i)
    return True


def test_dc_motor_gains_and_poles():
    """Section 6.8: K ~ [6, 13, 0, 13] and [4, 5, 0]; the gains map the characteristic coefficients of H through
    the SCB of the sigma_1 = 0 design system; designed on it, they are applied to the true system."""
    design = _motor(0.0)
    obs1 = hgo_gains(*_motor(S1), H1, design=design)
    np.testing.assert_allclose(obs1.K[:2, 0], [6.0, 13.08], rtol=1e-12)
    np.testing.assert_allclose(obs1.K[2:, 0], [-0.00896243, 13.0883227], rtol=1e-6)
    assert obs1.dims == (0, 0, 4) and obs1.chain_lengths == (4,)
    assert _close(obs1.poles, [-3.0 + 2.02j, -3.0 - 2.02j, -168.7 + 290.8j, -168.7 - 290.8j], 0.1)
    obs2 = hgo_gains(*design, [-1 + 0.2j, -1 - 0.2j, -2], extended=False)
    np.testing.assert_allclose(obs2.K[:, 0], [4.0, 5.04, -0.00343009], rtol=1e-5)
    # the true error system (sigma_1 != 0) has one zero at -sigma_0 / sigma_1 and a 3-chain
    true = hgo_gains(*_motor(S1), H1[:3][:2] + [-2.0])
    assert true.dims == (1, 0, 3)
    np.testing.assert_allclose(true.zeros, [-S0 / S1], rtol=1e-12)


def _scb_form_system():
    """An SCB-form (C, A, E), x = (x_a, q1, q2_1, q2_2, q2_3), chains of lengths 1 and 3, zero at -1, with
    output injections and last-row couplings, in scrambled coordinates (integer unimodular T, S)."""
    A = np.array(
        [
            [-1.0, 0.5, 0.3, 0, 0],  # x_a' = -x_a + 0.5 y1 + 0.3 y2
            [0.4, 0.2, 0.2, 0.1, 0],  # q1' = u1 + couplings (the chain's last row)
            [0, 0.7, 0, 1, 0],  # q2_1' = q2_2 + 0.7 y1
            [0, -0.6, 0, 0, 1],  # q2_2' = q2_3 - 0.6 y1
            [0.5, 0.2, -0.3, 0, 0.1],  # q2_3' = u2 + couplings
        ]
    )
    B = np.array([[0, 0], [1, 0], [0, 0], [0, 0], [0, 1.0]])
    C = np.array([[0, 1.0, 0, 0, 0], [0, 0, 1, 0, 0]])
    T = np.array([[1, 1, 0, 0, 0], [0, 1, 0, 1, 0], [0, 0, 1, 0, 0], [1, 0, 0, 1, 1], [0, 0, 1, 0, 1.0]])
    S = np.array([[1, 1], [0, 1.0]])
    Ti = np.linalg.inv(T)
    return T @ A @ Ti, T @ B, S @ C @ Ti


def test_remark_6_2_mimo_chains_of_different_lengths():
    """With the corrected K_qjq, eps times the n_q fast poles tend to eig(H_1) and eig(H_2) as eps -> 0 and one
    pole stays at the invariant zero -1 for every eps; the gains printed in section 6.3.2 do not do that."""
    A, E, C = _scb_form_system()
    poles = [-2.0, -1 + 1j, -1 - 1j, -3.0]  # chain lengths (1, 3): H_1 = {-2}, H_2 = {-1 +- 1j, -3}
    for eps in (1.0, 0.1, 1e-3):
        g = hgo_gains(A, E, C, poles, eps, extended=False)
        assert g.chain_lengths == (1, 3) and g.dims == (1, 0, 4)
        assert np.min(np.abs(g.poles + 1.0)) < 1e-9
    fast = sorted(g.poles, key=abs)[1:]
    assert _close(1e-3 * np.asarray(fast), poles, 0.02)
    printed = hgo_gains(A, E, C, poles, 1e-3, extended=False, corrected=False)
    assert np.min(np.abs(printed.poles + 1.0)) < 1e-5  # roundoff of gains ~ 2e9 (chain 1: Kbar / eps^3)
    assert not _close(1e-3 * np.asarray(sorted(printed.poles, key=abs)[1:]), poles, 0.5)
    # the error shrinks with eps (O(eps)): the fast poles scale as 1 / eps
    g2 = hgo_gains(A, E, C, poles, 1e-4, extended=False)
    err = lambda g, e: max(min(abs(e * p - q) for p in g.poles) for q in poles)  # noqa: E731
    assert err(g2, 1e-4) < 0.3 * err(g, 1e-3)


def test_uncoupled_chain_poles_scale_exactly_as_one_over_eps():
    """Without couplings (a pure chain behind a stable zero), the poles are exactly eig(H) / eps and the zero."""
    A = [[-2.0, 1.0, 0], [0, 0, 1], [0, 0, 0]]  # x_a' = -2 x_a + y, then a 2-chain driven by phi
    E, C = [[0], [0], [1.0]], [[0, 1.0, 0]]
    for eps in (1.0, 0.5, 0.2):
        g = hgo_gains(A, E, C, [-1.0, -3.0], eps, extended=False)
        assert _close(g.poles, [-2.0, -1.0 / eps, -3.0 / eps], 1e-8)
        assert _close(hgo_gains(A, E, C, [-1.0, -3.0, -4.0], eps).poles, [-2, -1 / eps, -3 / eps, -4 / eps], 1e-7)


def test_x_b_subsystem_takes_poles_b():
    """x3' = -x3 + y1 is observable from y2 and unaffected by phi (an x_b subsystem); its pole is poles_b."""
    A = [[0, 1.0, 0], [0, 0, 0], [1.0, 0, -1.0]]
    E, C = [[0], [1.0], [0]], [[1.0, 0, 0], [0, 0, 1.0]]
    g = hgo_gains(A, E, C, [-1.0, -2.0], 0.5, poles_b=[-5.0], extended=False)
    assert g.dims == (0, 1, 2)
    assert _close(g.poles, [-5.0, -2.0, -4.0], 1e-8)
    with pytest.raises(ValueError, match="poles_b is required"):
        hgo_gains(A, E, C, [-1.0, -2.0], extended=False)


def test_gain_is_a_polynomial_in_one_over_eps_under_jit_and_grad():
    g = hgo_gains(*_motor(0.0), H1, 0.5)
    np.testing.assert_allclose(jax.jit(g.at)(0.5), g.K, rtol=1e-12)
    dK = jax.grad(lambda e: g.at(e)[1, 0])(0.5)
    np.testing.assert_allclose(dK, -2 * 13.08 / 0.5**3, rtol=1e-12)  # K_2 = Kbar_2 / eps^2


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(A=[[0, 1.0], [-2, -3]], E=[[0], [1.0]], C=[[-1.0, 1]]), r"minimum-phase.*\[\(1"),
        (dict(A=np.zeros((2, 2)), E=np.eye(2), C=[[1.0, 0]]), "left-invertible"),
        (dict(eps=0.0), r"eps must be a number in \(0, 1\]"),
        (dict(eps=1.5), "eps"),
        (dict(eps=float("nan")), "eps"),
        (dict(eps=True), "eps"),
        (dict(eps=0.5j), "eps"),
        (dict(eps=-1.0), "eps"),
        (dict(eps=float("inf")), "eps"),
        (dict(eps="0.5"), "eps"),
        (dict(eps=[0.5]), "eps"),
        (dict(extended="no"), "extended must be a bool"),
        (dict(corrected=1), "corrected must be a bool"),
        (dict(numeric=None), "numeric must be a bool"),
        (dict(poles=[-1.0, -2.0, -3.0]), "poles must have 4 entries"),
        (dict(poles=[-1 + 1j, -1 - 2j, -2.0, -3.0]), "conjugate pairs"),
        (dict(poles=[-1.0, -2.0, -3.0, np.nan]), "poles must be finite"),
        (dict(E=[[0], [1.0]]), "E has shape"),
        (dict(C=[[1.0, 0]]), "C has shape"),
        (dict(A=[[0, 1.0, 0], [0, 0, 1]]), "A must be square"),
        (dict(A=[[0, 1.0, 0], [0, np.inf, 1], [0, 0, 0]]), "A contains NaN"),
        (dict(design=(np.eye(2), [[0], [1.0]], [[1.0, 0]])), "design"),
        (dict(poles_b=[-1.0]), "poles_b must be empty"),
    ],
)
def test_bad_inputs(kwargs, match):
    args = dict(A=[[0, 1.0, 0], [0, 0, 1], [0, 0, 0]], E=[[0], [0], [1.0]], C=[[1.0, 0, 0]], poles=[-1.0, -2, -3, -4])
    args.update(kwargs)
    if "A" in kwargs and len(np.asarray(kwargs["A"])) == 2 and "poles" not in kwargs:
        args["poles"] = [-1.0, -2.0, -3.0]
    with pytest.raises(ValueError, match=match):
        hgo_gains(**args)


def test_numeric_scb_gives_the_same_gains():
    """The floating-point SCB (rank decisions by SVD) designs the same gains as the exact one on the DC motor."""
    exact = hgo_gains(*_motor(S1), H1, design=_motor(0.0))
    numeric = hgo_gains(*_motor(S1), H1, design=_motor(0.0), numeric=True)
    np.testing.assert_allclose(numeric.K, exact.K, rtol=1e-8)


BAD_EPS = {"zero": 0.0, "negative": -1.0, "above-one": 2.0, "nan": float("nan"), "inf": float("inf")}


@pytest.mark.parametrize("eps", BAD_EPS.values(), ids=BAD_EPS)
def test_gains_at_eps_outside_the_range(eps):
    """HGOGains.at(eps) for eps outside (0, 1]: ValueError naming eps eagerly (before: NaN gains at 0, sign-flipped
    gains at -1, accepted 2 and NaN); NaN gains under jit, never a finite gain that looks valid."""
    g = hgo_gains(*_motor(0.0), H1, 0.5)
    with pytest.raises(ValueError, match=r"^eps must be a number in \(0, 1\]"):
        g.at(eps)
    assert np.all(np.isnan(jax.jit(g.at)(eps)))
    assert np.all(np.isfinite(jax.jit(g.at)(1.0)))


@pytest.mark.parametrize("eps", [True, "0.5", [0.5, 0.5], None])
def test_gains_at_eps_of_the_wrong_type(eps):
    with pytest.raises(ValueError, match=r"^eps\b"):
        hgo_gains(*_motor(0.0), H1, 0.5).at(eps)
