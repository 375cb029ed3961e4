# checked by: tests/mjx/test_estimation.py (slow: it asserts on the RMS errors this script measures)
"""Estimate the state of a MuJoCo MJX cart-pole from noisy sensors with the EKF and the UKF, with the true model
and with a mismatched one (the filter believes the pole is 30 % heavier than it is).

The plant is the cart-pole shipped with jaxobs (``jaxobs/mjx/assets/cartpole_sensors.xml``): a 1 kg cart on a
rail pushed by a motor, a 0.5 m, 0.2 kg pole hanging from it. Its state is ``x = (qpos, qvel)`` = (cart position
[m], pole angle [rad], cart velocity [m/s], pole angular velocity [rad/s]); the filters' transition is
``mjx.step`` (two 10 ms physics steps per 20 ms sample, the motor force held), their measurement the model's
``sensordata``: the cart position and the world position (x, y, z) of the pole tip [m].

The truth starts with the pole swung out by 0.8 rad and is pushed by a known sinusoidal force plus an unknown
random force (std 0.5 N, held over each sample); the filters are told only the known force, and their process
noise ``Q`` is that random force through the input Jacobian of the physics step. Sensor noise: 5 mm on the cart
position, 10 mm on each tip coordinate; 10 % of the tip samples are lost (NaN: the filters skip them).
The filters start at rest with the pole hanging (an error of 0.8 rad) and a wide prior.

Run ``python examples/mjx_state_estimation.py [--out DIR] [--seconds S]``: prints the RMS estimation errors
(after a one-second transient) and writes ``DIR/mjx_state_estimation.png``. The mismatched model is the same
pytree as the nominal one with other values, so each filter compiles once for both.
"""

from __future__ import annotations

import argparse
import functools
import pathlib
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

import jaxobs as jo
from jaxobs.mjx import estimation

SUBSTEPS = 2  # physics steps of 10 ms per sample
FORCE_STD = 0.5  # N, unknown random force on the cart
SENSOR_STD = np.array([0.005, 0.01, 0.01, 0.01])  # m: cart position, tip x, y, z
DROPOUT = 0.1  # fraction of tip-position samples lost
MASS_FACTOR = 1.3  # the mismatched filter's pole mass (and inertia) over the true one
TRANSIENT = 1.0  # s left out of the RMS errors
STATES = ["cart position [m]", "pole angle [rad]", "cart velocity [m/s]", "pole angular velocity [rad/s]"]


def heavier_pole(mj_model: mujoco.MjModel, factor: float) -> mujoco.MjModel:
    """The model with the pole's mass and inertia scaled by ``factor`` (the same shape, uniformly denser)."""
    mismatched = mj_model.__copy__()
    pole = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, "pole")
    mismatched.body_mass[pole] *= factor
    mismatched.body_inertia[pole] *= factor
    return mismatched


def input_jacobian(mj_model: mujoco.MjModel, x) -> np.ndarray:
    """(n, nu): the change of ``x = (qpos, qvel)`` over one sample per unit of held control, at the state ``x``
    at rest, from MuJoCo's finite-difference step derivatives (``mjd_transitionFD``: one physics step
    ``x+ = A x + B u``, chained over the substeps, ``B_sample = (A^(s-1) + ... + A + I) B``)."""
    data = mujoco.MjData(mj_model)
    n = 2 * mj_model.nv
    data.qpos[:], data.qvel[:] = np.asarray(x[: mj_model.nq]), np.asarray(x[mj_model.nq :])
    A, B = np.zeros((n, n)), np.zeros((n, mj_model.nu))
    mujoco.mjd_transitionFD(mj_model, data, 1e-6, True, A, B, None, None)
    B_sample = B
    for _ in range(SUBSTEPS - 1):
        B_sample = A @ B_sample + B
    return B_sample


def filter_model(mj_model: mujoco.MjModel, x0, P0) -> jo.NonlinearModel:
    """The nonlinear model the filters use: ``mjx.step`` and ``sensordata`` of ``mj_model`` on MJX; ``Q`` is the
    random force through the input Jacobian at the prior mean (plus 1e-10 for definiteness), ``R`` the sensor
    noise."""
    model = mjx.put_model(mj_model)
    f, h = estimation.transition(model, substeps=SUBSTEPS), estimation.measurement(model)
    G = jnp.asarray(input_jacobian(mj_model, x0))
    Q = FORCE_STD**2 * G @ G.T + 1e-10 * jnp.eye(x0.shape[0])
    return jo.nonlinear_model(f, h, Q, jnp.diag(jnp.asarray(SENSOR_STD) ** 2), x0=x0, P0=P0, n_inputs=model.nu,
                              dt=estimation.sample_period(model, SUBSTEPS), feedthrough=True)  # fmt: skip


@functools.partial(jax.jit, static_argnames="T")
def simulate(model: mjx.Model, T: int, seed):
    """``T`` samples of the true trajectory, the known force and the sensor readings: ``(t, x_true, u_known, y)``;
    ``x_true[k]`` and ``y[k]`` are at ``t[k]``, ``u_known[k]`` is held over ``[t[k], t[k+1]]``."""
    t = model.opt.timestep * SUBSTEPS * jnp.arange(T)
    keys = jax.random.split(jax.random.key(seed), 3)
    u_known = (2.0 * jnp.sin(2 * jnp.pi * 0.5 * t))[:, None]
    u_true = u_known + FORCE_STD * jax.random.normal(keys[0], (T, 1))
    f, h = estimation.transition(model, substeps=SUBSTEPS), estimation.measurement(model)

    def step(x, inputs):
        u, t = inputs
        return f(x, u, t), x

    _, x_true = jax.lax.scan(step, jnp.array([0.0, 0.8, 0.0, 0.0]), (u_true, t))
    u_prev = jnp.concatenate([jnp.zeros((1, 1)), u_true[:-1]])  # the force acting when each sample is taken
    y = jax.vmap(h)(x_true, u_prev) + jnp.asarray(SENSOR_STD) * jax.random.normal(keys[1], (T, 4))
    lost = jax.random.uniform(keys[2], (T,)) < DROPOUT
    y = y.at[:, 1:].set(jnp.where(lost[:, None], jnp.nan, y[:, 1:]))
    return t, x_true, u_known, y


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/examples", help="folder of the figure")
    parser.add_argument("--seconds", type=float, default=8.0, help="length of the run [s]")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-figure", action="store_true", help="print the numbers only")
    args = parser.parse_args(argv)

    mj_model, model = estimation.load_cartpole()
    T = int(round(args.seconds / estimation.sample_period(model, SUBSTEPS)))
    t, x_true, u_known, y = simulate(model, T, args.seed)
    inputs = jo.EstimatorInputs(y=y, u_prev=jnp.concatenate([jnp.zeros((1, 1)), u_known[:-1]]))
    x0, P0 = jnp.zeros(4), jnp.diag(jnp.array([0.1, 1.0, 0.5, 2.0]) ** 2)
    mismatch = f"pole mass +{round(100 * (MASS_FACTOR - 1))} %"
    models = {"true model": filter_model(mj_model, x0, P0),
              mismatch: filter_model(heavier_pole(mj_model, MASS_FACTOR), x0, P0)}  # fmt: skip
    filters = {"EKF": (jo.extended_kalman_filter, jo.make_ekf), "UKF": (jo.unscented_kalman_filter, jo.make_ukf)}

    settled = t >= TRANSIENT
    results, estimates = {"missing_samples": int(jnp.sum(jnp.isnan(y[:, 1])))}, {}
    print(f"{y.shape[0]} samples of {float(t[1] - t[0]) * 1e3:.0f} ms, {results['missing_samples']} tip samples lost;"
          f" RMS errors after {TRANSIENT:g} s:")  # fmt: skip
    print(f"  {'filter':<30}" + "".join(f"{name:>32}" for name in STATES))
    for filter_name, (estimator, make) in filters.items():
        estimate = jax.jit(lambda params, inputs, estimator=estimator: jo.run(estimator, params, inputs))
        for model_name, nonlinear_model in models.items():
            start = time.perf_counter()
            state, out = jax.block_until_ready(estimate(make(nonlinear_model), inputs))
            seconds = time.perf_counter() - start
            name = f"{filter_name}, {model_name}"
            rms = jnp.sqrt(jnp.mean((out.x - x_true)[settled] ** 2, axis=0))
            results[name] = {"rms": np.asarray(rms).tolist(), "missing": int(state.missing), "seconds": seconds}
            estimates[name] = np.asarray(out.x)
            print(f"  {name:<30}" + "".join(f"{float(e):>32.4f}" for e in rms) + f"   ({seconds:.1f} s incl. compile)")
    if not args.no_figure:
        results["figure"] = str(plot(pathlib.Path(args.out), t, x_true, y, estimates, results))
        print(f"figure: {results['figure']}")
    return results


def plot(out: pathlib.Path, t, x_true, y, estimates, results) -> pathlib.Path:
    """Top: the four states, true and estimated (colour: the filter, line style: the model). Bottom: the RMS
    errors after the transient, one panel per state."""
    from jaxobs.papers._output import pyplot, save_figure

    t, x_true = np.asarray(t), np.asarray(x_true)
    colors = {"EKF": "tab:blue", "UKF": "tab:orange"}
    style = lambda name: dict(color=colors[name.split(",")[0]], ls="-" if "true" in name else "--")
    fig = pyplot().figure(figsize=(13, 9.5), layout="constrained")
    grid = fig.add_gridspec(3, 4, height_ratios=[1, 1, 0.8])
    for i, label in enumerate(STATES):
        ax = fig.add_subplot(grid[i // 2, 2 * (i % 2) : 2 * (i % 2) + 2])
        if i == 0:
            ax.plot(t, np.asarray(y[:, 0]), ".", color="0.6", ms=3, label="cart position sensor")
        ax.plot(t, x_true[:, i], color="black", lw=3, alpha=0.6, label="true state")
        for name, x in estimates.items():
            ax.plot(t, x[:, i], lw=1.1, label=name, **style(name))
        ax.axvline(TRANSIENT, color="0.5", lw=0.8, ls=":")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if i == 0:
            ax.legend(fontsize=8, loc="best")
    for i, label in enumerate(STATES):
        ax = fig.add_subplot(grid[2, i])
        names = list(estimates)
        rms = [results[name]["rms"][i] for name in names]
        bars = ax.bar(range(len(names)), rms, color=[style(n)["color"] for n in names],
                      hatch=["" if "true" in n else "//" for n in names], edgecolor="black")  # fmt: skip
        ax.bar_label(bars, fmt="%.3g", fontsize=7)
        short = [n.replace(", true model", "\ntrue").replace(", pole mass ", "\nmass ") for n in names]
        ax.set_xticks(range(len(names)), short, fontsize=8)
        ax.set_title(f"RMS error, t > {TRANSIENT:g} s", fontsize=9)
        ax.set_ylabel(label.replace(" [", " error ["), fontsize=8)
        ax.margins(y=0.2)
    fig.suptitle("MJX cart-pole: EKF and UKF from noisy sensors (10 % of tip samples lost), "
                 "with the true model and with a 30 % heavier pole")  # fmt: skip
    return out / save_figure(fig, out, "mjx_state_estimation")


if __name__ == "__main__":
    jax.config.update("jax_enable_x64", True)
    main()
