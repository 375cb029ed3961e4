"""Registry entries: estimation over a record, learning, consistency tests and resampling (jaxobs.smoothing,
jaxobs.learning, jaxobs.consistency, jaxobs.resampling)."""

import numpy as np

from tests.api_registry import Example, slow
from tests.api_registry.models import _inputs, _key
from tests.api_registry.observers import U_SEQ, Y_SEQ, _kalman, _kalman_filter

RUNS_AXIS = {"batch": "a leading runs axis is documented: the statistics pool the runs"}
LOG_WEIGHTS = np.log(np.array([0.5, 0.2, 0.2, 0.1]))


def _outputs():
    """A Kalman filter's outputs with covariances over ``Y_SEQ`` (what smoothers and consistency tests read)."""
    import dataclasses

    from jaxobs.observers.base import run

    params = dataclasses.replace(_kalman(), output_covariance=True)
    return run(_kalman_filter(), params, _inputs(Y_SEQ, U_SEQ))[1]


SMOOTHING = {
    "jaxobs.smoothing.log_likelihood": Example(
        lambda: dict(estimator=_kalman_filter(), params=_kalman(), inputs=_inputs(Y_SEQ, U_SEQ)),
        diff="params",
        tangent="scale",
    ),
    "jaxobs.smoothing.smooth": Example(
        lambda: dict(estimator=_kalman_filter(), params=_kalman(), inputs=_inputs(Y_SEQ, U_SEQ)),
        diff="params",
        tangent="scale",
    ),
    "jaxobs.smoothing.rts_smoother": Example(
        lambda: dict(Phi=np.asarray(_kalman().Phi), filtered=_outputs()),
        diff="filtered",
        tangent="scale",
        skip={
            "batch": "Phi may have a leading time axis (T, n, n): a batch "
            "axis of the length of the record is a time-varying model"
        },
    ),
    "jaxobs.smoothing.parallel_filter": Example(
        lambda: dict(params=_kalman(), inputs=_inputs(Y_SEQ, U_SEQ)), diff="params", tangent="scale"
    ),
}

LEARNING = {
    "jaxobs.learning.sample": Example(
        lambda: dict(params=_kalman(), key=_key(3), num_steps=6, u_prev=U_SEQ[:6]), diff="params", tangent="scale"
    ),
    "jaxobs.learning.negative_log_likelihood": Example(
        lambda: dict(estimator=_kalman_filter(), params=_kalman(), inputs=_inputs(Y_SEQ, U_SEQ)),
        diff="params",
        tangent="scale",
        skip={"batch": "inputs may carry a leading batch of records (B, T, p): the likelihood pools them"},
    ),
    "jaxobs.learning.em": Example(
        lambda: dict(params=_kalman(), inputs=_inputs(Y_SEQ[None], U_SEQ[None]), iterations=3),
        diff="inputs",
        skip={
            "batch": "inputs has a documented leading batch of records (B, T, p)",
            "grad": "an iterative fit (a while loop to a tolerance): differentiate the log-likelihood instead",
        },
    ),
    "jaxobs.learning.als": Example(
        lambda: dict(params=_steady(), innovation=np.sin(0.7 * np.arange(60.0))[:, None], lags=4),
        diff="innovation",
        skip={"batch": "innovation may have a leading runs axis"},
    ),
}


def _steady():
    from jaxobs.observers.kalman import with_steady_state_gain

    return with_steady_state_gain(_kalman())


def _x_true():
    return np.asarray(_outputs().x) + 0.1 * np.cos(np.arange(Y_SEQ.shape[0]))[:, None]


CONSISTENCY = {
    "jaxobs.consistency.nees": Example(
        lambda: dict(outputs=_outputs(), x_true=_x_true()), diff="x_true", skip=RUNS_AXIS
    ),
    "jaxobs.consistency.nis": Example(lambda: dict(outputs=_outputs()), tangent="scale", skip=RUNS_AXIS),
    "jaxobs.consistency.chi2_quantile": Example(
        lambda: dict(q=np.float64(0.975), dof=np.float64(3.0)), diff="dof", batched=("q", "dof")
    ),
    "jaxobs.consistency.autocovariance": Example(
        lambda: dict(innovation=np.asarray(_outputs().innovation), lags=3), skip=RUNS_AXIS
    ),
    "jaxobs.consistency.whiteness": Example(
        lambda: dict(innovation=np.asarray(_outputs().innovation), lags=3), skip=RUNS_AXIS
    ),
}

DRAWS = {"grad": "indices drawn from the weights: piecewise constant"}

RESAMPLING = {
    "jaxobs.resampling.effective_sample_size": Example(lambda: dict(log_weights=LOG_WEIGHTS)),
    "jaxobs.resampling.multinomial": Example(
        lambda: dict(key=_key(4), log_weights=LOG_WEIGHTS, num=6), diff="log_weights", skip=DRAWS
    ),
    "jaxobs.resampling.stratified": Example(
        lambda: dict(key=_key(4), log_weights=LOG_WEIGHTS, num=6), diff="log_weights", skip=DRAWS
    ),
    "jaxobs.resampling.systematic": Example(
        lambda: dict(key=_key(4), log_weights=LOG_WEIGHTS, num=6), diff="log_weights", skip=DRAWS
    ),
    "jaxobs.resampling.residual": Example(
        lambda: dict(key=_key(4), log_weights=LOG_WEIGHTS, num=6), diff="log_weights", skip=DRAWS
    ),
    "jaxobs.resampling.resample": Example(
        lambda: dict(key=_key(4), log_weights=LOG_WEIGHTS, ess_threshold=np.float64(0.9)),
        diff="log_weights",
        skip={
            "grad": "stop-gradient resampling (Scibior & Wood 2021): the "
            "weights' gradient is that estimator's by design"
        },
    ),
}

ENTRIES = {**SMOOTHING, **LEARNING, **CONSISTENCY, **RESAMPLING}
ENTRIES = slow(
    ENTRIES,
    "an estimator over a record: a scan compiled for eager, jit, vmap and grad (~0.65-2 s of CPU)",
    "jaxobs.consistency.nees",
    "jaxobs.resampling.residual",
    "jaxobs.learning.sample",
    "jaxobs.smoothing.smooth",
    "jaxobs.consistency.whiteness",
    "jaxobs.learning.em",
    "jaxobs.smoothing.parallel_filter",
)

EXEMPT = {
    "jaxobs.learning.covariance_model": "transformation: returns the parametrisation build_params (a function) with "
    "its start theta0",
    "jaxobs.learning.fit": "job: an optimisation run (optax steps with progress and a stopping rule); its "
    "objective, negative_log_likelihood, has an entry",
}
