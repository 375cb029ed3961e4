"""Parts the MJX plants share: putting a model on this process's device, the initial data in a dtype, the physics
step (MJX's own constraint solver with implicit derivatives, or a fixed iteration count), the dead-time FIFO of a
command, per-step input series and the checks of integer timing arguments.

Every rollout of the plants steps through :func:`step`, so how a rollout is differentiated is decided here once:
the constraint solve is MJX's at the model's settings, differentiated implicitly (:func:`solve`).

:mod:`jaxobs.mjx.force_1dof`, :mod:`jaxobs.mjx.compliant_6dof`, :mod:`jaxobs.mjx.estimation` and
:mod:`jaxobs.mjx.robot` build on them.
"""

from __future__ import annotations

import functools

import jax
import jax.extend
import jax.flatten_util
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from jax.custom_derivatives import SymbolicZero, zero_from_primal
from mujoco import mjx
from mujoco.mjx._src import solver as mjx_solver  # its cost (Context): the gradient whose root is qacc

from jaxobs import _checks, _linalg

__all__ = [
    "put_model",
    "initial_data",
    "solve",
    "STAGES",
    "STATE_FIELDS",
    "PASSED",
    "JACOBIAN_MAX",
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
    _checks.fields("model", model, "qpos0 (q,), body_mass (b,)")  # one model: vmap for a batch
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


def solve(model: mjx.Model, data: mjx.Data, solution=None) -> mjx.Data:
    """``mjx.solve`` (MJX's constraint solver: its ``while_loop`` at the model's ``opt.iterations`` and
    ``opt.tolerance``, warm-started from ``qacc_warmstart``) with implicit derivatives.

    The solve minimises a convex cost in ``qacc`` whose gradient ``g(qacc) = M qacc - qfrc_smooth - J' f(qacc)``
    vanishes at the solution (Todorov 2014); by the implicit function theorem ``d qacc = -H^{-1} dg``, where ``dg``
    is the gradient's change with the inputs at fixed ``qacc`` and ``H = dg/dqacc = M + J' D J`` over the active
    rows (plus the elliptic cone's curvature), MuJoCo's Newton Hessian. Tangents and cotangents therefore cost one
    linear solve with ``H`` at the solution (``jax.lax.custom_root``: forward and reverse mode); the iterations
    and the warm start are not differentiated. The constraint forces ``efc_force`` and ``qfrc_constraint`` are the
    solver's, with the derivatives of ``f`` at the solution; the three carry the ``jax.checkpoint`` name
    ``"constraint_solve"`` (a policy that saves them spares a rematerialised step the solver's loop). ``solution``:
    ``(qacc, efc_force, qfrc_constraint)`` of this very solve, computed before (it is then not run again).
    """
    _checks.fields("data", data, "qpos (q,), qvel (v,), qacc_smooth (v,)")  # one state: vmap for a batch
    gradient = _cost_gradient(model, data)

    def run(_, guess):
        if solution is not None:
            return solution[0], tuple(solution[1:])
        solved = mjx.solve(model, data)
        return solved.qacc, (solved._impl.efc_force, solved.qfrc_constraint)

    qacc, (efc_force, qfrc_constraint) = jax.lax.custom_root(gradient, data.qacc_smooth, run, _hessian_solve,
                                                             has_aux=True)  # fmt: skip
    qacc, efc_force, qfrc_constraint = checkpoint_name((qacc, efc_force, qfrc_constraint), "constraint_solve")
    at = _constraint_context(model, data, qacc)  # values: the solver's; derivatives: those of f at the solution
    efc_force = efc_force + (at.efc_force - jax.lax.stop_gradient(at.efc_force))
    qfrc_constraint = qfrc_constraint + (at.qfrc_constraint - jax.lax.stop_gradient(at.qfrc_constraint))
    return data.tree_replace({"qacc": qacc, "qfrc_constraint": qfrc_constraint, "_impl.efc_force": efc_force})


def _fixed_solve(model: mjx.Model, data: mjx.Data, iterations: int) -> mjx.Data:
    """``iterations`` calls of ``mjx.solve`` at ``opt.iterations = 1``, each warm-started from the last ``qacc``."""
    one = model.replace(opt=model.opt.replace(iterations=1))
    data = mjx.solve(one, data)
    return jax.lax.fori_loop(0, iterations - 1, lambda _, d: mjx.solve(one, d.replace(qacc_warmstart=d.qacc)), data)


STAGES = (
    ("kinematics", mjx.kinematics),
    ("com_pos", mjx.com_pos),
    ("camlight", mjx.camlight),
    ("tendon", mjx.tendon),
    ("crb", mjx.crb),
    ("tendon_armature", mjx.tendon_armature),
    ("factor_m", mjx.factor_m),
    ("collision", mjx.collision),
    ("make_constraint", mjx.make_constraint),
    ("transmission", mjx.transmission),
    ("sensor_pos", mjx.sensor_pos),
    ("fwd_velocity", mjx.fwd_velocity),
    ("sensor_vel", mjx.sensor_vel),
    ("fwd_actuation", mjx.fwd_actuation),
    ("fwd_acceleration", mjx.fwd_acceleration),
)
"""``mjx.forward``'s stages before the constraint solve, in its order: ``(name, fn(model, data) -> data)``. Each runs
under ``jax.named_scope(name)`` (as do ``solve``, ``sensor_acc`` and ``integrator``), so a profile of a compiled
step attributes its operations to them (benchmarks/mjx_stages.py)."""

STATE_FIELDS = ("time", "qpos", "qvel", "act", "history", "qacc_warmstart", "plugin_state", "ctrl", "qfrc_applied",
                "xfrc_applied", "eq_active", "mocap_pos", "mocap_quat", "userdata")  # fmt: skip
"""The fields of ``mjx.Data`` a physics step reads (MuJoCo's full physics state, its controls and applied forces):
it computes every other field."""

PASSED = ("time", "ctrl", "qfrc_applied", "xfrc_applied", "eq_active", "mocap_pos", "mocap_quat", "userdata",
          "plugin_state", "history")  # fmt: skip
"""The :data:`STATE_FIELDS` a physics step leaves as they are (``time`` advances by a constant)."""

JACOBIAN_MAX = 8
"""Largest number of differentiated input entries for which :func:`step`'s reverse mode is one forward-mode
Jacobian of the step (a ``vmap``-ed ``jax.jvp``) instead of JAX's transpose of it."""


def forward(model: mjx.Model, data: mjx.Data, solver_iterations: int | None = None, *, solution=None) -> mjx.Data:
    """``mjx.forward`` with the constraint solve of :func:`step` (``solution``: see :func:`solve`)."""
    solver_iterations = check_solver_iterations(solver_iterations)
    _checks.fields("data", data, "qpos (q,), qvel (v,), act (a,), ctrl (u,)")  # one state: vmap for a batch
    for name, stage in STAGES:
        with jax.named_scope(name):
            data = stage(model, data)
    if not constraint_rows(data):
        return data.replace(qacc=data.qacc_smooth)
    with jax.named_scope("solve"):
        if solver_iterations is None:
            data = solve(model, data, solution)
        else:
            data = _fixed_solve(model, data, solver_iterations)
    with jax.named_scope("sensor_acc"):
        return mjx.sensor_acc(model, data)


def _physics_step(model: mjx.Model, data: mjx.Data, solver_iterations: int | None, solution=None) -> mjx.Data:
    """:func:`forward`, then the model's integrator."""
    integrator = mujoco.mjtIntegrator(int(model.opt.integrator))
    if integrator == mujoco.mjtIntegrator.mjINT_RK4:
        stages = model if solver_iterations is None else model.replace(opt=model.opt.replace(iterations=1))
        data = forward(model, data, solver_iterations, solution=solution)
        with jax.named_scope("integrator"):
            return mjx.rungekutta4(stages, data)
    data = forward(model, data, solver_iterations, solution=solution)
    with jax.named_scope("integrator"):
        if integrator == mujoco.mjtIntegrator.mjINT_EULER:
            return mjx.euler(model, data)
        if integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
            return mjx.implicit(model, data)
    raise ValueError(f"model: integrator {integrator.name} is not supported by MJX (Euler, RK4, implicitfast)")


_traced_step = jax.jit(_physics_step, static_argnums=2)
""":func:`_physics_step` traced once per signature: the Jacobian rule evaluates it several times per trace."""


@functools.partial(jax.checkpoint, policy=jax.checkpoint_policies.save_only_these_names("constraint_solve"))
def _rematerialised_step(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """The step as JAX's transpose differentiates it: reverse mode keeps only its inputs and the solver's output and
    recomputes the rest in the backward pass, cheaper in a rollout than storing every step's residuals
    (docs/performance.md)."""
    return _traced_step(model, data, None)


def step(model: mjx.Model, data: mjx.Data, solver_iterations: int | None = None) -> mjx.Data:
    """One physics step: ``mjx.step`` with a constraint solve that reverse mode differentiates.

    ``solver_iterations`` None or 0: MJX's own solver at the model's settings (``opt.iterations``,
    ``opt.tolerance``), differentiated implicitly (:func:`solve`), so the step equals ``mjx.step`` and its
    derivatives are those of the exact solution. ``K >= 1``: the solver runs exactly ``K`` Newton iterations (``K``
    calls of ``mjx.solve`` at ``opt.iterations = 1``, each warm-started from the last ``qacc``), differentiated
    through every iteration. A model without constraint rows takes the plain step either way. Euler and
    implicit-fast integrators; RK4 too, whose later stages run ``mjx.forward`` (a model with constraint rows: forward
    mode only, or a fixed ``K``).

    Reverse mode (with None): when at most :data:`JACOBIAN_MAX` entries of the step's inputs (:data:`STATE_FIELDS`)
    are differentiated and no model field is, the backward pass is the step's forward-mode Jacobian in those entries
    (one ``vmap``-ed ``jax.jvp`` at the saved inputs and solver output, ``jax.lax.custom_linear_solve`` giving the
    transpose) contracted with the cotangent: on a CPU it costs a fraction of JAX's transpose of the step, whose
    backward program stores and pads hundreds of small arrays per step (benchmarks/mjx_stages.py). Otherwise JAX's
    transpose of the step rematerialised (``jax.checkpoint`` saving only the solver's output). Forward mode is the
    step's own ``jax.jvp`` either way, and second derivatives (reverse mode over ``jax.jacfwd`` of steps, as in the
    gradient of :func:`jaxobs.mjx.robot.linearize`) are JAX's derivatives of it.
    """
    solver_iterations = check_solver_iterations(solver_iterations)
    _checks.fields("data", data, "qpos (q,), qvel (v,), act (a,), ctrl (u,)")  # one state: vmap for a batch
    if solver_iterations is None:
        return _implicit_step(model, data)
    return _physics_step(model, data, solver_iterations)


@jax.custom_jvp
def _implicit_step(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    return _traced_step(model, data, None)


def _implicit_step_jvp(primals, tangents):
    """The step's tangent; for at most :data:`JACOBIAN_MAX` differentiated state entries (the warm start aside: the
    solve's derivative does not depend on it) and a model held fixed, :func:`_jacobian_tangent`. The fields the step
    passes through (:data:`PASSED`) keep their tangents, symbolic zeros included, so that a rollout's later steps see
    as few differentiated inputs as its first."""
    model, data = primals
    d_model, d_data = tangents
    names = [name for name in STATE_FIELDS if name != "qacc_warmstart" and getattr(data, name).size
             and jnp.issubdtype(getattr(data, name).dtype, jnp.floating)
             and not _is_zero(getattr(d_data, name))]  # fmt: skip
    moved = any(not _is_zero(t) for t in jax.tree.leaves(d_model, is_leaf=_is_zero))
    if moved or not names or sum(getattr(data, name).size for name in names) > JACOBIAN_MAX:
        dense = jax.tree.map(lambda t: jnp.zeros(t.shape, t.dtype) if _is_zero(t) else t, tangents, is_leaf=_is_zero)
        out, d_out = jax.jvp(_rematerialised_step, primals, dense)
    else:
        out = _traced_step(model, data, None)
        d_out = _jacobian_tangent(model, data, out, {name: getattr(d_data, name) for name in names})
    return out, d_out.replace(**{name: getattr(d_data, name) for name in PASSED})


def _jacobian_tangent(model: mjx.Model, data: mjx.Data, out: mjx.Data, tangents: dict) -> mjx.Data:
    """The tangent of the step ``data -> out`` for the tangents ``tangents`` of some of its state fields: the step's
    forward-mode Jacobian in those entries applied to them (:func:`_jacobian_product`), the program traced once.
    Output leaves that no differentiated input reaches keep a symbolic zero."""
    template = mjx.make_data(model).replace(**{name: getattr(data, name) for name in STATE_FIELDS})
    solution = (out.qacc, out._impl.efc_force, out.qfrc_constraint) if constraint_rows(data) else None
    paths, tree = jax.tree_util.tree_flatten_with_path(out)
    candidates = [i for i, (path, x) in enumerate(paths)
                  if x.size and jnp.issubdtype(x.dtype, jnp.floating) and path[0].name not in PASSED]  # fmt: skip

    def outputs(inputs):
        leaves = jax.tree.leaves(_traced_step(model, template.replace(**inputs), None, solution))
        return [leaves[i] for i in candidates]

    inputs = {name: getattr(data, name) for name in tangents}
    traced = jax.make_jaxpr(outputs)(inputs)  # traced once: evaluated again by the jvp's, not retraced
    keys = [path[0].key for path, _ in jax.tree_util.tree_flatten_with_path(inputs)[0]]
    moving = [(i, names) for i, names in zip(candidates, _dependence(traced, keys), strict=True) if names]
    picks = [(candidates.index(i), names, paths[i][1]) for i, names in moving]
    d_moving = _jacobian_product(traced.jaxpr, picks)(traced.consts, inputs, tangents)
    d_out = jax.tree.leaves(zero_from_primal(out))
    for (i, _), t in zip(moving, d_moving, strict=True):
        d_out[i] = t
    return jax.tree.unflatten(tree, d_out)


def _jacobian_product(program, picks: list):
    """``(consts, inputs, tangents) -> J tangents``: the Jacobian of the outputs ``picks`` (``(index, names of the
    inputs it depends on, output)``) of the step's jaxpr ``program`` (constants ``consts``) in ``inputs``, applied to
    ``tangents``, as a linear map (``jax.lax.custom_linear_solve``) whose transpose, reverse mode's backward pass, is
    the Jacobian's columns (one ``vmap``-ed ``jax.jvp``) contracted with the cotangent. Its own derivative in
    ``consts`` and ``inputs`` (the step's second derivatives, e.g. the gradient of :func:`jaxobs.mjx.robot.linearize`)
    is JAX's of the plain product: a custom_linear_solve alone would drop it (its rule treats the solve as constant)."""

    def moved(consts, inputs):
        leaves = jax.extend.core.jaxpr_as_fun(jax.extend.core.ClosedJaxpr(program, consts))(*jax.tree.leaves(inputs))
        return [leaves[k] for k, _, _ in picks]

    def plain(consts, inputs, tangents):
        return jax.jvp(lambda x: moved(consts, x), (inputs,), (tangents,))[1]

    @jax.custom_jvp
    def product(consts, inputs, tangents):
        vector, unravel = jax.flatten_util.ravel_pytree(inputs)

        def jvp(e):
            return jax.jvp(lambda v: moved(consts, unravel(v)), (vector,), (e,))[1]

        def apply(_, b):  # (t, 0, ...) -> (0, J t): one jvp
            return jnp.zeros_like(b[0]), jvp(b[0])

        def apply_transpose(_, c):  # (c_0, c_1, ...) -> (J' (c_1, ...), 0, ...): the Jacobian's columns
            columns = jax.vmap(jvp)(jnp.eye(vector.size, dtype=vector.dtype))
            products = [jnp.tensordot(col, ct, axes=ct.ndim) for col, ct in zip(columns, c[1], strict=True)]
            return sum(products), [jnp.zeros_like(ct) for ct in c[1]]

        # zeros linear in the tangents each output depends on (vmap batches them as the output); sorted names, so
        # that the program does not depend on the hash seed (checkpoint fingerprints)
        zeros = [jnp.broadcast_to(sum(0.0 * tangents[n].ravel()[0] for n in sorted(names)), x.shape).astype(x.dtype)
                 for _, names, x in picks]  # fmt: skip
        rhs = (jax.flatten_util.ravel_pytree(tangents)[0], zeros)
        return jax.lax.custom_linear_solve(lambda b: b, rhs, apply, apply_transpose)[1]

    def product_jvp(primals, derivatives):
        consts, inputs, tangents = primals
        d_consts, d_inputs, d_tangents = derivatives
        leaves, shape = jax.tree.flatten((consts, inputs))
        d_leaves = jax.tree.leaves((d_consts, d_inputs), is_leaf=_is_zero)
        varying = [k for k, d in enumerate(d_leaves) if not _is_zero(d)]

        def second(*values):  # the plain product in the varying constants and inputs
            moved_leaves = list(leaves)
            for k, value in zip(varying, values, strict=True):
                moved_leaves[k] = value
            return plain(*jax.tree.unflatten(shape, moved_leaves), tangents)

        out = product(consts, inputs, tangents)
        d_out = [jnp.zeros_like(x) for x in out]
        if varying:
            d_out = jax.jvp(second, [leaves[k] for k in varying], [d_leaves[k] for k in varying])[1]
        if not all(_is_zero(d) for d in d_tangents.values()):
            dense = {n: jnp.zeros_like(tangents[n]) if _is_zero(d) else d for n, d in d_tangents.items()}
            d_out = [a + b for a, b in zip(d_out, product(consts, inputs, dense), strict=True)]
        return out, d_out

    product.defjvp(product_jvp, symbolic_zeros=True)
    return product


def _dependence(traced, names: list) -> list[frozenset]:
    """For each output of the closed jaxpr ``traced``, the ``names`` of its inputs it depends on: data flow through
    the jaxpr and the ``jit`` calls in it (any other operation's outputs depend on all its inputs)."""
    return _flow(traced.jaxpr, [frozenset([name]) for name in names])


def _flow(jaxpr, inputs: list) -> list[frozenset]:
    """The dependence sets of ``jaxpr``'s outputs given those of its inputs (see :func:`_dependence`)."""
    literal = jax.extend.core.Literal
    depends = dict(zip(jaxpr.invars, inputs, strict=True))
    for eqn in jaxpr.eqns:
        used = [frozenset() if isinstance(v, literal) else depends.get(v, frozenset()) for v in eqn.invars]
        if eqn.primitive.name == "jit":
            outs = _flow(eqn.params["jaxpr"].jaxpr, used)
        else:
            outs = [frozenset().union(*used)] * len(eqn.outvars)
        depends.update(zip(eqn.outvars, outs, strict=True))
    return [frozenset() if isinstance(v, literal) else depends.get(v, frozenset()) for v in jaxpr.outvars]


def _is_zero(tangent) -> bool:
    return isinstance(tangent, SymbolicZero)


_implicit_step.defjvp(_implicit_step_jvp, symbolic_zeros=True)


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
