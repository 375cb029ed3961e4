"""The resampling atoms: unbiased offspring counts, the variance ordering of the schemes, the adaptive rule and the
stop-gradient weights, under jit and vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs import resampling

WEIGHTS = np.array([0.02, 0.31, 0.0, 0.17, 0.05, 0.25, 0.2])  # one zero weight, none a multiple of 1/N
DRAWS = 4000
resample = jax.jit(resampling.resample, static_argnames="scheme")


@pytest.fixture(scope="module")
def counts():
    """Offspring counts (DRAWS, N) of every scheme, N = 7 particles resampled into 7."""
    log_weights = jnp.log(jnp.asarray(WEIGHTS))
    keys = jax.random.split(jax.random.key(0), DRAWS)

    def per_scheme(scheme):
        draw = jax.vmap(lambda key: jnp.bincount(scheme(key, log_weights), length=len(WEIGHTS)))
        return np.asarray(jax.jit(draw)(keys))

    return {name: per_scheme(scheme) for name, scheme in resampling.SCHEMES.items()}


@pytest.mark.parametrize("name", sorted(resampling.SCHEMES))
def test_offspring_counts_are_unbiased(counts, name):
    """E[count_i] = N w_i: the sample mean over 4000 draws within 4 standard errors (its own sampling error);
    a count with no variance (the zero-weight particle, systematic's integer parts) equals N w_i's floor or
    ceiling every time."""
    c = counts[name]
    expected = len(WEIGHTS) * WEIGHTS
    assert np.all(c.sum(axis=1) == len(WEIGHTS))
    assert np.all(c[:, WEIGHTS == 0] == 0)
    error = np.sqrt(c.var(axis=0) / DRAWS)
    varying = error > 0
    assert np.all(np.abs(c.mean(axis=0) - expected)[varying] < 4 * error[varying])
    fixed = ~varying
    assert np.all((c[:, fixed] == np.floor(expected[fixed])) | (c[:, fixed] == np.ceil(expected[fixed])))


def test_systematic_stratified_and_residual_vary_less_than_multinomial(counts):
    """The summed variance of the counts: multinomial's is sum N w_i (1 - w_i) (checked to 10 %), each of the
    other schemes' is below it (Douc, Cappé & Moulines 2005), systematic's the lowest here."""
    total = {name: c.var(axis=0).sum() for name, c in counts.items()}
    theory = np.sum(len(WEIGHTS) * WEIGHTS * (1 - WEIGHTS))
    assert abs(total["multinomial"] / theory - 1) < 0.1
    for name in ("stratified", "systematic", "residual"):
        assert total[name] < 0.6 * total["multinomial"], (name, total)
    assert total["systematic"] == min(total.values())


def test_systematic_gives_floor_or_ceiling_copies(counts):
    expected = len(WEIGHTS) * WEIGHTS
    c = counts["systematic"]
    assert np.all((c >= np.floor(expected)) & (c <= np.ceil(expected)))


def test_more_indices_than_particles():
    indices = resampling.systematic(jax.random.key(1), jnp.log(jnp.asarray(WEIGHTS)), num=700)
    assert indices.shape == (700,) and indices.dtype == jnp.int32
    np.testing.assert_allclose(np.bincount(indices, minlength=7) / 700, WEIGHTS, atol=1 / 700)


def test_effective_sample_size():
    assert float(resampling.effective_sample_size(jnp.zeros(10))) == pytest.approx(10.0)
    assert float(resampling.effective_sample_size(jnp.array([0.0, -jnp.inf, -jnp.inf]))) == pytest.approx(1.0)
    w = jnp.asarray(WEIGHTS)
    assert float(resampling.effective_sample_size(jnp.log(3 * w))) == pytest.approx(1 / float(jnp.sum(w**2)))


def test_adaptive_rule_and_stop_gradient_weights():
    """Below the threshold the particles are resampled and every new log-weight is the total's log share in value
    with its parent's derivative; above it nothing changes; threshold 1 always resamples, 0 never."""
    key, log_w = jax.random.key(2), jnp.log(jnp.asarray(WEIGHTS)) + 1.5  # unnormalised: total e^1.5
    ess = float(resampling.effective_sample_size(log_w))
    for threshold, expected in ((1.0, True), (0.0, False), (ess / 7 + 0.01, True), (ess / 7 - 0.01, False)):
        out = resample(key, log_w, ess_threshold=threshold)
        assert bool(out.resampled) is expected
    out = resample(key, log_w, scheme="residual")
    np.testing.assert_allclose(out.log_weights, 1.5 - np.log(7), rtol=1e-14)
    kept = resample(key, log_w, ess_threshold=0.0)
    np.testing.assert_array_equal(kept.ancestors, np.arange(7))
    np.testing.assert_allclose(kept.log_weights, log_w)

    def scaled(theta):  # log-weights theta * log_w: the derivative of new weight j is log_w[parent_j]
        return resampling.resample(key, theta * log_w, scheme="residual").log_weights

    jacobian = jax.jit(jax.jacfwd(scaled))(1.0)
    np.testing.assert_allclose(jacobian, log_w[out.ancestors], rtol=1e-14)


def test_jit_equals_eager_and_vmap_equals_a_loop(scheme="residual"):
    """Residual resampling (the scheme with the most steps) with the adaptive rule: a vmap over two weight
    vectors and keys equals a loop of eager calls."""
    keys = jax.random.split(jax.random.key(3), 2)
    log_w = jnp.log(jnp.asarray(np.random.default_rng(0).dirichlet(np.ones(9), size=2)))
    call = lambda key, lw: resampling.resample(key, lw, scheme=scheme, ess_threshold=0.7)
    batched = jax.jit(jax.vmap(call))(keys, log_w)
    for i in range(2):
        single = call(keys[i], log_w[i])
        for got, want in zip(batched, single, strict=True):
            np.testing.assert_array_equal(got[i], want)


def test_bad_inputs_raise_naming_the_argument():
    key, log_w = jax.random.key(0), jnp.zeros(4)
    with pytest.raises(ValueError, match="scheme must be one of"):
        resampling.resample(key, log_w, scheme="optimal")
    with pytest.raises(ValueError, match="log_weights must have shape"):
        resampling.systematic(key, jnp.zeros((2, 2)))
    with pytest.raises(ValueError, match="log_weights must be a non-empty floating vector"):
        resampling.multinomial(key, jnp.zeros(0))
    with pytest.raises(ValueError, match="num must be an integer >= 1"):
        resampling.stratified(key, log_w, num=0)
    with pytest.raises(ValueError, match="ess_threshold must have shape"):
        resampling.resample(key, log_w, ess_threshold=jnp.ones(2))
