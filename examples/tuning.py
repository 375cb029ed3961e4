# slow: 1-DOF MJX force plant, 4 training plants x 0.5 s rollouts, 127 screened candidates, 2 starts of at most
# 5 steps (about 30 s of CPU)
"""Tuning guide: the noise covariances of an AOB-1 tuned by gradient descent through MuJoCo MJX rollouts."""

# --8<-- [start:problem]
import jax

import jaxobs as jo
from jaxobs.papers import tuning_config
from jaxobs.papers.cortesao import force_tuning
from jaxobs.tuning import evaluate

jax.config.update("jax_enable_x64", True)

# the packaged 1-DOF problem ('jaxobs tune --list'), made small: any key of 'jaxobs tune --print-config'
small = {"plants": {"train": 4, "heldout": 8}, "scenario": {"duration": 0.5}, "optimizer": {"steps": 5}}
config = force_tuning.PROBLEM.validate(small)
problem = force_tuning.PROBLEM.build(config)  # a jo.TuningProblem: theta0, per-plant losses, train/held-out plants
print(sorted(problem.theta0), problem.batch_size(problem.train), problem.batch_size(problem.heldout))
# prints: ['log_q', 'log_r'] 4 8
# --8<-- [end:problem]

# --8<-- [start:tune]
settings = tuning_config.settings(config)  # the [optimizer] table: screening, 2 starts, L-BFGS on the mean loss
result = jo.tune(problem, settings, progress=False)  # add checkpoint="tune.npz" to resume after Ctrl-C
before, after = (evaluate(problem, theta, settings) for theta in (problem.theta0, result.theta))
print(f"{result.evaluations} evaluations, {result.rollouts} rollouts")
print(f"held-out mean squared force error: {before['mean']:.2f} -> {after['mean']:.2f} N^2")
print({k: f"{v:.1e}" for k, v in problem.describe(result.theta).items() if k in ("q_active", "R")})
# prints: 10 evaluations, 552 rollouts
# prints: held-out mean squared force error: 24.54 -> 3.59 N^2
# prints: {'q_active': '1.6e+00', 'R': '2.6e-08'}
# --8<-- [end:tune]
