"""Tyre forces of jaxobs.vehicle: the Magic Formula's slope, peak and friction-dependent shape, the friction
ellipse under combined slip, the Burckhardt curve, gradients at zero slip, batching, bad parameters."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.vehicle import BurckhardtTyre, TyreParams, pure_force, tyre_forces

FZ = 4000.0


def test_magic_formula_slope_is_friction_independent_and_peak_scales_with_mu():
    """Slope at zero slip c F_z for every mu; peak mu F_z, reached at a slip proportional to mu."""
    s = jnp.linspace(0.0, 0.6, 6001)
    peaks = []
    for mu in (1.0, 0.5, 0.25):
        tyre = TyreParams(mu=mu)
        slope = jax.grad(lambda a, t=tyre: pure_force(t, a, FZ))(0.0)
        np.testing.assert_allclose(slope, tyre.cornering_stiffness * FZ, rtol=1e-12)
        f = pure_force(tyre, s, FZ)
        np.testing.assert_allclose(jnp.max(f), mu * FZ, rtol=1e-6)
        peaks.append(float(s[jnp.argmax(f)]))
    np.testing.assert_allclose(np.array(peaks) / peaks[0], [1.0, 0.5, 0.25], atol=2e-3)
    # past the peak the curve falls to D sin(C pi / 2)
    far = pure_force(TyreParams(), 1e4, FZ)
    np.testing.assert_allclose(far, FZ * np.sin(1.3 * np.pi / 2), rtol=1e-3)


@pytest.mark.parametrize("tyre", [TyreParams(mu=0.8), BurckhardtTyre.surface("wet_asphalt")], ids=["mf", "burckhardt"])
def test_combined_slip_stays_in_the_friction_ellipse_and_reduces_to_pure_slip(tyre):
    kappa, tan_alpha = jnp.meshgrid(jnp.linspace(-0.5, 1.0, 31), jnp.linspace(-1.0, 1.0, 41))
    fx, fy = tyre_forces(tyre, kappa, tan_alpha, FZ)
    s = jnp.linspace(0.0, 2.0, 20001)
    dx, dy = jnp.max(pure_force(tyre, s, FZ, direction="x")), jnp.max(pure_force(tyre, s, FZ))
    assert float(jnp.max((fx / dx) ** 2 + (fy / dy) ** 2)) <= 1.0 + 1e-9
    # pure slip: the pure curves of the theoretical slips
    t = jnp.linspace(-0.5, 0.5, 11)
    np.testing.assert_allclose(tyre_forces(tyre, 0.0, t, FZ)[1], pure_force(tyre, t, FZ), rtol=1e-12)
    np.testing.assert_allclose(tyre_forces(tyre, t, 0.0, FZ)[0], pure_force(tyre, t / (1 + t), FZ, direction="x"))
    # braking at a fixed slip angle lowers the lateral force
    assert abs(float(tyre_forces(tyre, -0.2, 0.05, FZ)[1])) < abs(float(tyre_forces(tyre, 0.0, 0.05, FZ)[1]))


def test_burckhardt_curve_matches_its_formula():
    tyre = BurckhardtTyre.surface("snow")
    s = jnp.linspace(0.01, 1.0, 50)
    c1, c2, c3 = 0.1946, 94.129, 0.0646
    np.testing.assert_allclose(pure_force(tyre, s, FZ, direction="x"), FZ * (c1 * (1 - np.exp(-c2 * s)) - c3 * s))


@pytest.mark.parametrize("tyre", [TyreParams(), BurckhardtTyre()], ids=["mf", "burckhardt"])
def test_gradients_finite_at_zero_slip_and_equal_to_the_stiffness(tyre):
    jac = jax.jacfwd(lambda z: jnp.stack(tyre_forces(tyre, z[0], z[1], FZ)))(jnp.zeros(2))
    rev = jax.jacrev(lambda z: jnp.stack(tyre_forces(tyre, z[0], z[1], FZ)))(jnp.zeros(2))
    assert np.all(np.isfinite(jac)) and np.all(np.isfinite(rev))
    np.testing.assert_allclose(jnp.diag(jac), jnp.diag(rev))
    slope_x = jax.grad(lambda a: pure_force(tyre, a, FZ, direction="x"))(0.0)
    np.testing.assert_allclose(jac, jnp.diag(jnp.array([slope_x, jax.grad(lambda a: pure_force(tyre, a, FZ))(0.0)])))


def test_batched_tyre_params_under_vmap_equal_single_calls():
    mus = jnp.array([1.0, 0.6, 0.25])
    batch = jax.tree_util.tree_map(lambda leaf: jnp.broadcast_to(leaf, mus.shape), TyreParams(mu=mus))
    f = jax.jit(jax.vmap(lambda t: tyre_forces(t, 0.05, 0.08, FZ)))(batch)
    for i, mu in enumerate(mus):
        single = tyre_forces(dataclasses.replace(TyreParams(), mu=float(mu)), 0.05, 0.08, FZ)
        np.testing.assert_allclose(f[0][i], single[0], rtol=1e-12)
        np.testing.assert_allclose(f[1][i], single[1], rtol=1e-12)


@pytest.mark.parametrize(
    "make, name",
    [
        (lambda: TyreParams(mu=0.0), "mu"),
        (lambda: TyreParams(mu=jnp.array([1.0, -0.2])), "mu"),
        (lambda: TyreParams(cornering_stiffness=-1.0), "cornering_stiffness"),
        (lambda: TyreParams(slip_stiffness=0.0), "slip_stiffness"),
        (lambda: TyreParams(shape_y=2.5), "shape_y"),
        (lambda: TyreParams(curvature_x=1.5), "curvature_x"),
        (lambda: BurckhardtTyre(c1=0.0), "c1"),
        (lambda: BurckhardtTyre(c3=-0.1), "c3"),
    ],
)
def test_bad_tyre_parameters_raise(make, name):
    with pytest.raises(ValueError, match=name):
        make().validate()


def test_unknown_surface_lists_the_valid_ones():
    with pytest.raises(ValueError, match="dry_asphalt"):
        BurckhardtTyre.surface("gravel")
