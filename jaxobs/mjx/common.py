"""Parts the MJX plants share: putting a model on this process's device, the initial data in a dtype, the physics
step (with a fixed-count constraint solver that reverse mode differentiates), the dead-time FIFO of a command,
per-step input series and the checks of integer timing arguments.

:mod:`jaxobs.mjx.force_1dof`, :mod:`jaxobs.mjx.compliant_6dof`, :mod:`jaxobs.mjx.estimation` and
:mod:`jaxobs.mjx.robot` build on them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxobs import _checks

__all__ = [
    "put_model",
    "initial_data",
    "step",
    "constraint_rows",
    "check_solver_iterations",
    "dead_time_step",
    "input_series",
    "is_int_at_least",
    "check_timing",
]


def put_model(m: mujoco.MjModel) -> mjx.Model:
    """``mjx.put_model`` on this process's first device (its default, ``jax.devices()[0]``, is process 0's in a
    multi-process run, which the other processes cannot use)."""
    return mjx.put_model(m, device=jax.local_devices()[0])


def initial_data(model: mjx.Model, dtype) -> mjx.Data:
    """``mjx.make_data`` (the model's initial state) with its state arrays in ``dtype``."""
    data = mjx.make_data(model)
    return data.replace(
        qpos=data.qpos.astype(dtype),
        qvel=data.qvel.astype(dtype),
        ctrl=data.ctrl.astype(dtype),
        act=data.act.astype(dtype),
        time=jnp.asarray(data.time, dtype),
    )


def constraint_rows(data: mjx.Data) -> int:
    """The number of constraint rows (contacts, joint limits, equalities, friction loss) of ``data`` for the
    solver: static, MJX sizes them when the data is made."""
    return int(data._impl.nefc)  # MJX keeps the static row count in its backend-specific part


def check_solver_iterations(solver_iterations) -> None:
    """``ValueError`` unless ``solver_iterations`` is None or an int >= 1."""
    if solver_iterations is not None and not is_int_at_least(solver_iterations, 1):
        raise ValueError(f"solver_iterations must be None or a Python int >= 1, got {solver_iterations!r}")


def step(model: mjx.Model, data: mjx.Data, solver_iterations: int | None = None) -> mjx.Data:
    """One physics step: ``mjx.step``, or with ``solver_iterations = K`` a step whose constraint solver runs exactly
    ``K`` iterations.

    MJX's solver iterates in a ``lax.while_loop`` until ``opt.tolerance`` (at most ``opt.iterations``), which
    reverse mode cannot differentiate. With ``K``, the solver runs as ``K`` calls of ``mjx.solve`` at
    ``opt.iterations = 1``, each warm-started from the last ``qacc``: a loop of fixed length (reverse mode goes
    through it) that, for MuJoCo's default Newton solver, is ``K`` Newton iterations of the same problem. A model
    without constraint rows takes the plain step either way. Euler, RK4 and implicit-fast integrators.
    """
    if solver_iterations is None:
        return mjx.step(model, data)
    check_solver_iterations(solver_iterations)
    one = model.replace(opt=model.opt.replace(iterations=1))
    data = mjx.forward(one, data)
    if constraint_rows(data) and solver_iterations > 1:

        def iterate(_, data):
            return mjx.solve(one, data.replace(qacc_warmstart=data.qacc))

        data = jax.lax.fori_loop(0, solver_iterations - 1, iterate, data)
        data = mjx.sensor_acc(one, data)
    integrator = mujoco.mjtIntegrator(int(model.opt.integrator))
    if integrator == mujoco.mjtIntegrator.mjINT_EULER:
        return mjx.euler(one, data)
    if integrator == mujoco.mjtIntegrator.mjINT_RK4:
        return mjx.rungekutta4(one, data)
    if integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return mjx.implicit(one, data)
    raise ValueError(f"model: integrator {integrator.name} is not supported by MJX (Euler, RK4, implicitfast)")


def dead_time_step(fifo: jax.Array, u_k: jax.Array, d: int):
    """The command FIFO of a ``d``-sample dead time (oldest first): push ``u_k``, pop ``u_{k-d}``.
    Returns ``(applied, fifo)``; ``fifo`` (d, ...) with the shape of ``u_k`` after its first axis."""
    fifo, u_k = _checks.float_arrays(fifo=fifo, u_k=u_k)
    if d == 0:
        return u_k, fifo
    return fifo[0], jnp.concatenate([fifo[1:], u_k[None]])


def input_series(name: str, value, shape, dtype, like: str) -> jax.Array:
    """A per-step input of shape ``shape`` (an int: ``(shape,)``), zeros for None; finite where concrete.
    ``like`` names what fixes the shape in the error message."""
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    if value is None:
        return jnp.zeros(shape, dtype)
    value = jnp.asarray(value, dtype)
    if value.shape != shape:
        raise ValueError(f"{name} must have the shape of {like} {shape}, got {value.shape}")
    if _checks.is_concrete(value) and not np.all(np.isfinite(np.asarray(value))):
        raise ValueError(f"{name} contains NaN or infinite entries")
    return value


def is_int_at_least(value, minimum: int) -> bool:
    """``value`` is a Python or NumPy integer (not a bool) of at least ``minimum``."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= minimum


def check_timing(dead_time_samples, substeps) -> None:
    """``ValueError`` unless ``dead_time_samples`` is an int >= 0 and ``substeps`` an int >= 1 (static shapes)."""
    if not is_int_at_least(dead_time_samples, 0):
        raise ValueError(f"dead_time_samples must be a Python int >= 0, got {dead_time_samples!r}")
    if not is_int_at_least(substeps, 1):
        raise ValueError(f"substeps must be a Python int >= 1, got {substeps!r}")
