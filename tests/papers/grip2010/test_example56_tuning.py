"""The Example 5.6 gain-tuning problem (jaxobs.papers.grip2010.example56_tuning)."""

import json

import jax
import pytest

from jaxobs._config import ConfigError, load_toml
from jaxobs.papers.grip2010 import example56_tuning
from tests import run_cli


def test_default_config_file_validates():
    path = "tuning/grip_example56.toml"
    assert example56_tuning.PROBLEM.validate(load_toml(path), path) == example56_tuning.DEFAULT_CONFIG


@pytest.mark.parametrize(
    "given, key",
    [
        ({"seeds": {"heldout": 0}}, "seeds.heldout"),
        ({"scenario": {"noise_variance": -1.0}}, "scenario.noise_variance"),
        ({"scenario": {"segment_s": 2.0, "window_s": 3.0}}, "scenario.window_s"),
        ({"design": {"adaptation_gain": 0.0}}, "design.adaptation_gain"),
        ({"optimizer": {"learning_rate": 0.0}}, "optimizer"),
    ],
)
def test_bad_config_names_the_key(given, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        example56_tuning.PROBLEM.validate({"problem": example56_tuning.NAME, **given})


def test_gradient_matches_finite_differences():
    """d loss / d (log K_phi, log adaptation_gain) through the 5000 RK4 steps of a 1 s-segment run, forward mode against
    a central difference (step 1e-5: truncation about 1e-10 relative; the loss is smooth away from theta_tilde = 0)."""
    config = example56_tuning.PROBLEM.validate({"seeds": {"train": 1}, "scenario": {"segment_s": 1.0, "window_s": 0.5}})
    problem = example56_tuning.build_problem(config)
    loss = jax.jit(lambda theta: problem.losses(theta, problem.train)[0][0])
    grad = jax.jit(jax.jacfwd(loss))(problem.theta0)
    for name in problem.theta0:
        h = 1e-5
        up = {**problem.theta0, name: problem.theta0[name] + h}
        down = {**problem.theta0, name: problem.theta0[name] - h}
        fd = (float(loss(up)) - float(loss(down))) / (2 * h)
        assert float(grad[name]) == pytest.approx(fd, rel=1e-5)
        assert abs(fd) > 1e-3  # both gains matter


@pytest.mark.slow
@pytest.mark.published
def test_readme_table_row(tmp_path):
    """The README's tuning-table row of ``jaxobs tune --config tuning/grip_example56.toml`` from a fresh run: the
    held-out objectives of the printed gains, the tuned gains and the random search at equal rollouts (seeded,
    so reproducible; the equal-time search depends on the machine's speed, is not pinned, and is left out here)."""
    from tests._published import pin

    out = tmp_path / "grip"
    run_cli(["tune", "--config", "tuning/grip_example56.toml", "--set", "baseline.equal_time=false", "--out", str(out),
             "--no-progress"])  # fmt: skip
    summary = json.loads((out / "tuned.json").read_text())
    row = (
        r"\| Grip 2010 Example 5\.6, [^|]*\\\|theta_tilde\\\|[^|]*\| ([0-9.]+) \(10, 3\) \| ([0-9.]+) \(-([0-9.]+) %\) "
        r"at \(([0-9.]+), ([0-9.]+)\) \| ([0-9.]+) \(-([0-9.]+) %\)"
    )
    held = summary["heldout"]
    pin(held["hand-set"]["objective"], row, 1)
    pin(held["tuned"]["objective"], row, 2)
    pin(100 * held["tuned"]["reduction_vs_hand_set"], row, 3)
    pin(summary["parameters"]["tuned"]["K_phi"], row, 4)
    pin(summary["parameters"]["tuned"]["adaptation_gain"], row, 5)
    pin(held["random search, equal rollouts"]["objective"], row, 6)
    pin(100 * held["random search, equal rollouts"]["reduction_vs_hand_set"], row, 7)
