"""The road-angle estimators of jaxobs.vehicle.road_angles (Grip 2010 ch. 4): the SPR gain bounds of Lemmas 4.1 and
4.2 against jaxobs.lti.is_spr."""

import jax
import numpy as np
import pytest

from jaxobs.lti import is_spr
from jaxobs.vehicle import GRAVITY
from jaxobs.vehicle.road_angles import (
    bank_error_system,
    bank_gain_bound,
    inclination_error_system,
    inclination_gain_bound,
    lemma_check,
)


@pytest.mark.parametrize("a", [0.1, 0.5, 3.0])
@pytest.mark.parametrize("rel", [1e-6, 1e-2])
def test_lemma_4_1_is_spr_flips_at_the_bound(a, rel):
    """``G(s) = (s + g K) / (s^2 + a s + g K a)`` is SPR just below ``a / g`` and not just above."""
    check = lemma_check("4.1", a=a, rel=rel)
    assert check.bound == pytest.approx(a / GRAVITY)
    assert check.spr_below and not check.spr_above


@pytest.mark.parametrize("K_vy, delta_min", [(1.0, 0.5), (3.0, 2.0), (0.2, 8.0)])
@pytest.mark.parametrize("rel", [1e-6, 1e-2])
def test_lemma_4_2_is_spr_flips_at_the_bound(K_vy, delta_min, rel):
    check = lemma_check("4.2", K_vy=K_vy, delta_min=delta_min, rel=rel)
    assert check.bound == pytest.approx(K_vy**2 * delta_min / GRAVITY)
    assert check.spr_below and not check.spr_above


def test_error_systems_have_the_lemmas_transfer_functions():
    """The realisations give the printed ``G(s)`` (compared at a few complex points) and ``Re G(jw)`` of Lemma
    4.1's proof."""
    a, K, Kvy, d, g = 0.7, 0.03, 1.5, 2.0, GRAVITY
    incl, bank = inclination_error_system(a, K), bank_error_system(Kvy, d, K)

    def G(sys, s):
        return (np.asarray(sys.C) @ np.linalg.solve(s * np.eye(2) - np.asarray(sys.A), np.asarray(sys.B)))[0, 0]

    for s in (0.3 + 1j, 2j, -0.1 + 5j):
        assert G(incl, s) == pytest.approx((s + g * K) / (s**2 + a * s + g * K * a))
        assert G(bank, s) == pytest.approx((Kvy * s + g * K) / (s**2 + Kvy * d * s + g * K * d))
    w = 3.0
    re = ((a - g * K) * w**2 + g**2 * K**2 * a) / ((g * K * a - w**2) ** 2 + a**2 * w**2)
    assert G(incl, 1j * w).real == pytest.approx(re)


def test_bounds_and_systems_are_traceable():
    """The bounds and error systems under jit/vmap/grad (the SPR verdict itself is a design-time check)."""
    a = np.array([0.2, 0.4])
    np.testing.assert_allclose(jax.jit(jax.vmap(inclination_gain_bound))(a), a / GRAVITY)
    assert jax.grad(bank_gain_bound)(2.0, 0.5) == pytest.approx(2 * 2.0 * 0.5 / GRAVITY)
    A = jax.jit(jax.vmap(lambda K: inclination_error_system(0.5, K).A))(np.array([0.01, 0.02]))
    assert A.shape == (2, 2, 2)
    assert is_spr(*(np.asarray(M) for M in (A[0], inclination_error_system(0.5, 0.01).B, [[1.0, 0.0]])))


def test_lemma_check_rejects_bad_arguments():
    with pytest.raises(ValueError, match="lemma"):
        lemma_check("4.3", a=1.0)
    with pytest.raises(ValueError, match="delta_min"):
        lemma_check("4.2", K_vy=1.0, delta_min=-1.0)
