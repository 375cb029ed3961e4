"""Parts the MJX plants share: putting a model on this process's device, the initial data in a dtype, the physics
step (MJX's own constraint solver with implicit derivatives, or a fixed iteration count), the dead-time FIFO of a
command, per-step input series and the checks of integer timing arguments.

Every rollout of the plants steps through :func:`step`, so how a rollout is differentiated is decided here once:
the constraint solve is MJX's at the model's settings, differentiated implicitly (:func:`solve`).

:mod:`jaxobs.mjx.force_1dof`, :mod:`jaxobs.mjx.compliant_6dof`, :mod:`jaxobs.mjx.estimation` and
:mod:`jaxobs.mjx.robot` build on them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import solver as mjx_solver  # its cost (Context): the gradient whose root is qacc

from jaxobs import _checks, _linalg

__all__ = [
    "put_model",
    "initial_data",
    "solve",
    "forward",
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


def check_solver_iterations(solver_iterations) -> int | None:
    """``solver_iterations`` normalised: None for None or 0 (MJX's own solver at the model's settings), the int
    for an int >= 1 (a fixed count); ``ValueError`` otherwise."""
    if solver_iterations is None or (is_int_at_least(solver_iterations, 0) and solver_iterations == 0):
        return None
    if not is_int_at_least(solver_iterations, 1):
        raise ValueError(
            "solver_iterations must be None or 0 (MJX's solver at the model's settings) or a Python int >= 1 "
            f"(a fixed count), got {solver_iterations!r}"
        )
    return int(solver_iterations)


def _constraint_context(model: mjx.Model, data: mjx.Data, qacc: jax.Array):
    """MJX's solver context at ``qacc``: the constraint forces and the gradient's terms of its cost there."""
    return mjx_solver.Context.create(model, data.replace(qacc=qacc), grad=False)


def _cost_gradient(model: mjx.Model, data: mjx.Data):
    """``qacc -> M qacc - qfrc_smooth - J' f(qacc)``: the gradient of the solver's convex cost (Gauss term plus
    the constraints' piecewise quadratic), whose root is the solve's ``qacc``."""

    def gradient(qacc):
        ctx = _constraint_context(model, data, qacc)
        return ctx.Ma - data.qfrc_smooth - ctx.qfrc_constraint

    return gradient


def _hessian_solve(linear, rhs):
    """``H^{-1} rhs`` for the linear map ``linear`` (the cost gradient's derivative at the solution, ``H = M + J' D
    J`` on the active rows plus the cone's curvature: symmetric positive definite), by a Cholesky factor."""
    basis = jnp.eye(rhs.shape[-1], dtype=rhs.dtype)
    hessian = _linalg.symmetrize(jax.vmap(linear)(basis))
    return _linalg.cho_solve(_linalg.cholesky(hessian), rhs)


def solve(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """``mjx.solve`` (MJX's constraint solver: its ``while_loop`` at the model's ``opt.iterations`` and
    ``opt.tolerance``, warm-started from ``qacc_warmstart``) with implicit derivatives.

    The solve minimises a convex cost in ``qacc`` whose gradient ``g(qacc) = M qacc - qfrc_smooth - J' f(qacc)``
    vanishes at the solution; by the implicit function theorem ``d qacc = -H^{-1} dg``, where ``dg`` is the
    gradient's change with the inputs at fixed ``qacc`` and ``H = dg/dqacc = M + J' D J`` over the active rows
    (plus the elliptic cone's curvature), MuJoCo's Newton Hessian. Tangents and cotangents therefore cost one
    linear solve with ``H`` at the solution (``jax.lax.custom_root``: forward and reverse mode); the iterations
    and the warm start are not differentiated. The constraint forces ``efc_force`` and ``qfrc_constraint`` are the
    solver's, with the derivatives of ``f`` at the solution.
    """
    gradient = _cost_gradient(model, data)

    def run(_, guess):
        solved = mjx.solve(model, data)
        return solved.qacc, (solved._impl.efc_force, solved.qfrc_constraint)

    qacc, (efc_force, qfrc_constraint) = jax.lax.custom_root(gradient, data.qacc_smooth, run, _hessian_solve,
                                                             has_aux=True)  # fmt: skip
    at = _constraint_context(model, data, qacc)  # values: the solver's; derivatives: those of f at the solution
    efc_force = efc_force + (at.efc_force - jax.lax.stop_gradient(at.efc_force))
    qfrc_constraint = qfrc_constraint + (at.qfrc_constraint - jax.lax.stop_gradient(at.qfrc_constraint))
    return data.tree_replace({"qacc": qacc, "qfrc_constraint": qfrc_constraint, "_impl.efc_force": efc_force})


def _fixed_solve(model: mjx.Model, data: mjx.Data, iterations: int) -> mjx.Data:
    """``iterations`` calls of ``mjx.solve`` at ``opt.iterations = 1``, each warm-started from the last ``qacc``."""
    one = model.replace(opt=model.opt.replace(iterations=1))
    data = mjx.solve(one, data)
    return jax.lax.fori_loop(0, iterations - 1, lambda _, d: mjx.solve(one, d.replace(qacc_warmstart=d.qacc)), data)


def forward(model: mjx.Model, data: mjx.Data, solver_iterations: int | None = None) -> mjx.Data:
    """``mjx.forward`` with the constraint solve of :func:`step`."""
    solver_iterations = check_solver_iterations(solver_iterations)
    data = mjx.fwd_position(model, data)
    data = mjx.sensor_pos(model, data)
    data = mjx.fwd_velocity(model, data)
    data = mjx.sensor_vel(model, data)
    data = mjx.fwd_actuation(model, data)
    data = mjx.fwd_acceleration(model, data)
    if not constraint_rows(data):
        return data.replace(qacc=data.qacc_smooth)
    data = solve(model, data) if solver_iterations is None else _fixed_solve(model, data, solver_iterations)
    return mjx.sensor_acc(model, data)


def step(model: mjx.Model, data: mjx.Data, solver_iterations: int | None = None) -> mjx.Data:
    """One physics step: ``mjx.step`` with a constraint solve that reverse mode differentiates.

    ``solver_iterations`` None or 0: MJX's own solver at the model's settings (``opt.iterations``,
    ``opt.tolerance``), differentiated implicitly (:func:`solve`), so the step equals ``mjx.step`` and its
    derivatives are those of the exact solution. ``K >= 1``: the solver runs exactly ``K`` Newton iterations (``K``
    calls of ``mjx.solve`` at ``opt.iterations = 1``, each warm-started from the last ``qacc``), differentiated
    through every iteration. A model without constraint rows takes the plain step either way. Euler and
    implicit-fast integrators; RK4 too, whose later stages run ``mjx.forward`` (a model with constraint rows: forward
    mode only, or a fixed ``K``).
    """
    solver_iterations = check_solver_iterations(solver_iterations)
    integrator = mujoco.mjtIntegrator(int(model.opt.integrator))
    if integrator == mujoco.mjtIntegrator.mjINT_RK4:
        stages = model if solver_iterations is None else model.replace(opt=model.opt.replace(iterations=1))
        return mjx.rungekutta4(stages, forward(model, data, solver_iterations))
    data = forward(model, data, solver_iterations)
    if integrator == mujoco.mjtIntegrator.mjINT_EULER:
        return mjx.euler(model, data)
    if integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return mjx.implicit(model, data)
    raise ValueError(f"model: integrator {integrator.name} is not supported by MJX (Euler, RK4, implicitfast)")


def dead_time_step(fifo: jax.Array, u_k: jax.Array, d: int):
    """The command FIFO of a ``d``-sample dead time (oldest first): push ``u_k``, pop ``u_{k-d}``.
    Returns ``(applied, fifo)``; ``fifo`` (d, ...) with the shape of ``u_k`` after its first axis."""
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
