"""The noise-versus-gain sweep on the DC motor of Grip 2010, section 6.8 (jaxobs.papers.grip2010.dc_motor_sweep)."""

import jax
import numpy as np
import pytest

from jaxobs.papers.grip2010 import dc_motor as dc
from jaxobs.papers.grip2010 import dc_motor_sweep as sweep
from jaxobs.sweep import config_key

pytest.importorskip("sympy")


def test_default_config_file_validates():
    from jaxobs._config import load_toml

    path = "tuning/dc_motor_hgo_sweep.toml"
    assert sweep.SCENARIO.validate(load_toml(path), path) == sweep.DEFAULT_CONFIG


@pytest.mark.parametrize(
    "given, key",
    [
        ({"grid": {"eps": [0.0]}}, "grid.eps"),
        ({"grid": {"eps": [1.5]}}, "grid.eps"),
        ({"grid": {"sigma": [-1e-3]}}, "grid.sigma"),
        ({"grid": {"alpha_0": [2.0]}}, "grid.alpha_0"),
        ({"grid": {"seeds": 1.5}}, "grid.seeds"),
        ({"simulation": {"rms_start": 30.0}}, "simulation.rms_start"),
    ],
)
def test_bad_config_names_the_key(given, key):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        sweep.SCENARIO.validate(given, "test.toml")


def test_one_configuration_matches_the_reproduction():
    """The sweep's row at eps = 1, sigma = 0, alpha_0 = 0.28 equals the reproduction's noise-free simulation over the
    same (short) horizon: the traced K(eps) = HGOGains.at(eps) gives the eager gains."""
    config = sweep.SCENARIO.validate(
        {
            "grid": {"eps": [1.0], "sigma": [0.0], "alpha_0": [0.28], "seeds": 1},
            "simulation": {"duration": 1.0, "rms_start": 0.5},
        }  # fmt: skip
    )
    sampler, evaluate, n, _ = sweep.make_sweep(config)
    assert n == 1
    metrics = jax.jit(evaluate)(sampler(config_key(0, 0), 0))
    _, obs1, obs2 = dc.design()
    sim = dc.simulate(obs1.K, obs2.K, obs1.K[None], 0.0, duration=1.0)
    late = np.asarray(sim["t"]) > 0.5
    omega = np.asarray(sim["x"])[:, 1]
    expected = np.sqrt(np.mean((omega - np.asarray(sim["obs"].x)[:, 1])[late] ** 2))
    np.testing.assert_allclose(metrics["rms_omega"]["observer1"], expected, rtol=1e-10)
    expected_eso = np.sqrt(np.mean((omega - np.asarray(sim["eso_x"])[0, :, 1])[late] ** 2))
    np.testing.assert_allclose(metrics["rms_omega"]["pure_eso"], expected_eso, rtol=1e-10)
    assert bool(metrics["finite"])
