# checked by: tests/mjx/test_floating_base.py (slow: it asserts on the consistency and the errors this script measures)
"""Estimate the pose of a free-flying robot from its IMU, a position fix, a star tracker and its joint encoders with
the EKF and the UKF, over Monte-Carlo runs: are the filters consistent (NEES), and how much better than dead
reckoning from the IMU are they?

The robot is jaxobs' shipped free flyer (``jaxobs/mjx/assets/free_flyer.xml``): a 10 kg cube floating in zero
gravity with a two-link arm, six thruster axes and two arm motors. Its state ``x = (qpos, qvel)`` holds a quaternion,
so the filters work on the tangent space (16 directions for 17 entries: :func:`jaxobs.mjx.estimation.filter_model`);
the accelerometer reads the thrust being applied (an acceleration-stage sensor); the star tracker's quaternion
residual is a rotation vector. Each run draws the true initial state from the filters' prior, a known command
(thrusters and arm), the process noise (on the tangent space, the filters' ``Q``) and the sensor noise (the MJCF's
``noise`` attributes, the filters' ``R``).

Dead reckoning integrates the IMU from the prior mean: the orientation by the gyro, the velocity by the
accelerometer turned to the world frame, the position by the velocity (the IMU site's; gravity is zero).

Run ``python examples/floating_base_estimation.py [--runs N] [--seconds S]``: prints the NEES test of each filter
(its average over the runs and samples against the 95 % band of the per-sample average) and the RMS errors of the
IMU's position and orientation, filters against dead reckoning.
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxobs as jo
from jaxobs.mjx import estimation, manifold
from jaxobs.mjx.robot import load_mjcf

SUBSTEPS = 4  # physics steps of 5 ms per 20 ms sample
SENSORS = ["accelerometer", "gyro", "position_fix", "star_tracker", "shoulder_angle", "elbow_angle"]
PRIOR_STD = np.r_[[0.05] * 3, [0.05] * 3, [0.05] * 2, [0.02] * 3, [0.02] * 3, [0.05] * 2]  # tangent: pos, rot, vel
PROCESS_STD = np.r_[[1e-4] * 8, [2e-3] * 3, [2e-3] * 3, [5e-3] * 2]  # per 20 ms sample, on the tangent space


def setup():
    """``(mj_model, model, x0, P0, Q)``: the free flyer at rest, the prior and the process noise."""
    mj_model = load_mjcf("free_flyer.xml")
    model = estimation.put(mj_model)
    x0 = jnp.concatenate([jnp.asarray(mj_model.qpos0), jnp.zeros(mj_model.nv)])
    return mj_model, model, x0, jnp.diag(jnp.asarray(PRIOR_STD) ** 2), jnp.diag(jnp.asarray(PROCESS_STD) ** 2)


def command(T: int) -> jax.Array:
    """(T, 8) the known command: thrusts and torques (N, N m) and the arm's torques, smooth and non-zero."""
    t = 0.02 * jnp.arange(T)[:, None]
    amplitude = jnp.array([2.0, 1.5, 1.0, 0.3, 0.2, 0.4, 0.5, 0.3])
    return amplitude * jnp.sin(2 * jnp.pi * jnp.array([0.4, 0.3, 0.5, 0.7, 0.6, 0.5, 0.8, 1.1]) * t + jnp.arange(8))


@functools.partial(jax.jit, static_argnames="T")
def simulate(model, x0, P0, Q, R, T: int, key):
    """One run: ``(x_true (T, n), y (T, r-sized points), u_prev (T, nu))``; ``y_k = h(x_k, u_{k-1}) + v_k`` with the
    noise retracted onto the readings (the star tracker's stays a unit quaternion)."""
    space, readings = manifold.state_manifold(model), manifold.sensor_manifold(model, SENSORS)
    f, h = estimation.transition(model, substeps=SUBSTEPS), estimation.measurement(model, SENSORS)
    u = command(T)
    u_prev = jnp.concatenate([jnp.zeros((1, u.shape[1])), u[:-1]])
    k0, kw, kv = jax.random.split(key, 3)
    start = space.retract(x0, jnp.linalg.cholesky(P0) @ jax.random.normal(k0, (space.dim,)))
    w = jax.random.normal(kw, (T, space.dim)) @ jnp.linalg.cholesky(Q).T

    def advance(x, inputs):
        u_k, w_next = inputs
        return space.retract(f(x, u_k, 0.0), w_next), x

    _, x_true = jax.lax.scan(advance, start, (u, w))
    v = jax.random.normal(kv, (T, readings.dim)) @ jnp.linalg.cholesky(R).T
    y = jax.vmap(lambda x, u, v: readings.retract(h(x, u), v))(x_true, u_prev, v)
    return x_true, y, u_prev


def dead_reckoning(model, x0, y, h_period: float):
    """(T, 3) position and (T, 4) orientation of the IMU from its gyro and accelerometer only, from the prior mean."""
    h0 = estimation.measurement(model, ["position_fix", "star_tracker"])(x0, jnp.zeros(model.nu))
    p0, q0 = h0[:3], h0[3:]

    def integrate(carry, reading):
        p, v, q = carry
        acc, gyro = reading[:3], reading[3:6]
        world = manifold.quat_multiply(manifold.quat_multiply(q, jnp.concatenate([jnp.zeros(1), acc])),
                                       q * jnp.array([1.0, -1.0, -1.0, -1.0]))[1:]  # fmt: skip
        return (p + h_period * v, v + h_period * world, manifold.quat_integrate(q, h_period * gyro)), (p, q)

    _, (p, q) = jax.lax.scan(integrate, (p0, jnp.zeros(3), q0), y)
    return p, q


def pose_errors(model, x_true, p, q):
    """RMS over time of the IMU's position error (m) and orientation error (rad) of estimates ``p``, ``q``."""
    fix = estimation.measurement(model, ["position_fix", "star_tracker"])
    truth = jax.vmap(fix)(x_true, jnp.zeros((len(p), model.nu)))
    position = jnp.linalg.norm(p - truth[:, :3], axis=-1)
    angle = jnp.linalg.norm(manifold.quat_difference(q, truth[:, 3:]), axis=-1)
    return jnp.sqrt(jnp.mean(position**2)), jnp.sqrt(jnp.mean(angle**2))


def monte_carlo(runs: int = 20, seconds: float = 3.0, seed: int = 0) -> dict:
    """Every filter on ``runs`` simulated records: the NEES test and the pose errors, with dead reckoning's."""
    mj_model, model, x0, P0, Q = setup()
    nonlinear = estimation.filter_model(mj_model, Q, x0=x0, P0=P0, sensors=SENSORS, substeps=SUBSTEPS)
    T = int(round(seconds / float(nonlinear.dt)))
    keys = jax.random.split(jax.random.key(seed), runs)
    x_true, y, u_prev = jax.vmap(lambda key: simulate(model, x0, P0, Q, nonlinear.R, T, key))(keys)
    results = {"runs": runs, "samples": T, "dof": int(P0.shape[0])}
    pose = jax.jit(jax.vmap(lambda x, p, q: pose_errors(model, x, p, q)))
    p, q = jax.vmap(lambda y: dead_reckoning(model, x0, y, float(nonlinear.dt)))(y)
    results["dead reckoning"] = {"rms": np.asarray(jnp.mean(jnp.stack(pose(x_true, p, q)), axis=1)).tolist()}
    for name, estimator, params in (("EKF", jo.extended_kalman_filter, jo.make_ekf(nonlinear)),
                                    ("UKF", jo.unscented_kalman_filter, jo.make_ukf(nonlinear))):  # fmt: skip
        start = time.perf_counter()
        one = lambda y, u, e=estimator, p=params: jo.run(e, p, jo.EstimatorInputs(y=y, u_prev=u))[1]  # noqa: E731
        run = jax.jit(jax.vmap(one))
        out = jax.block_until_ready(run(y, u_prev))
        test = jo.nees(out, x_true, manifold=nonlinear.manifold)
        h = jax.vmap(jax.vmap(estimation.measurement(model, ["position_fix", "star_tracker"])))(out.x, u_prev)
        results[name] = {
            "nees": float(test.time_average),
            "band": [float(jnp.mean(test.lower)), float(jnp.mean(test.upper))],
            "fraction_inside": float(test.fraction_inside),
            "rms": np.asarray(jnp.mean(jnp.stack(pose(x_true, h[..., :3], h[..., 3:])), axis=1)).tolist(),
            "seconds": time.perf_counter() - start,
        }
    return results


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=3.0, help="length of each run [s]")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    results = monte_carlo(args.runs, args.seconds, args.seed)
    print(f"{results['runs']} runs of {results['samples']} samples, {results['dof']} tangent directions")
    print(
        f"  {'':<16}{'average NEES':>14}{'95 % band':>18}{'inside':>8}{'position RMS [m]':>18}{'angle RMS [rad]':>17}"
    )
    for name in ("EKF", "UKF", "dead reckoning"):
        r = results[name]
        nees = " " * 40
        if "nees" in r:
            band = f"[{r['band'][0]:.2f}, {r['band'][1]:.2f}]"
            nees = f"{r['nees']:>14.2f}{band:>18}{r['fraction_inside']:>8.0%}"
        print(f"  {name:<16}{nees}{r['rms'][0]:>18.4f}{r['rms'][1]:>17.4f}")
    return results


if __name__ == "__main__":
    jax.config.update("jax_enable_x64", True)
    main()
