"""Estimation and control through saturations (Grip 2010, ch. 8 and 9): the interval map against the simulated loop,
the §8.5 example, the masked Gramian, the chapter 9 detectors (Theorem 9.1) on a sandwich instance, the low-gain ARE
family and the three-stage closed loop."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from jaxobs import saturation as sat

# Grip (2010) §8.5
A8 = np.array([[0.0, 1, 1], [0, 0, 0], [0, 0, 0]])
B8 = np.array([[0.0, 0], [1, 0], [0, 1]])
C8 = np.array([[1.0, 0, 0], [1, 1, 0]])
X0 = np.array([2.0, -4.0, 1.0])
SIM8 = jax.jit(sat.simulate_saturated_outputs, static_argnums=2, static_argnames="substeps")

# the sandwich instance of grip2010-sandwich: L1 a double integrator, L2 a first-order lag
SW = dict(A=[[0.0, 1], [0, 0]], B=[[0.0], [1]], C=[[1.0, 0]], M=[[-1.0]], N=[[1.0]], G=[[1.0]])
F_SW = [[-1.0, -2.0]]
H9 = 1e-3  # inner step: 50 per window


@pytest.fixture(scope="module")
def design8():
    """The §8.5 design (T = 0.5, rho = 1.1)."""
    return sat.saturated_output_design(A8, B8, C8, T=0.5, rho=1.1)


@pytest.fixture(scope="module")
def design9():
    """The sandwich instance's design (T = 0.05, Tbar = 4 T, eps = 1e-3)."""
    return sat.sandwich_design(**SW, T=0.05, Tbar_intervals=4, rho=1.1, F=F_SW, eps=1e-3)


@pytest.fixture(scope="module")
def detect(design9):
    """The chapter 9 detectors of ``design9`` on one window, jitted: ``detect(y, u)``."""
    hypotheses = sat.sandwich_hypotheses(design9, H9)
    return jax.jit(lambda y, u: sat.sandwich_detectors(design9, y, u, H9, hypotheses=hypotheses))


@pytest.fixture(scope="module")
def example(design8):
    return SIM8(design8, X0, 10, substeps=500, cond_max=1e12)


def test_interval_map_matches_the_simulated_loop(example, design8):
    """(8.7) x(kT + T) = exp(AT) x(kT) - Bbar U_k against RK4 with 500 steps per interval, to 1e-8."""
    mapped = jax.vmap(lambda x, U: sat.interval_map(design8, x, U))(example.x_start, example.U)
    np.testing.assert_allclose(example.x_end, mapped, atol=1e-8)
    np.testing.assert_allclose(example.x_start[1:], example.x_end[:-1], atol=0)
    assert np.max(np.abs(np.asarray(example.x_end))) > 1  # the comparison is not on a trivial trajectory


def test_section_8_5_pattern_and_rest_after_deadbeat(example):
    """y1 unsaturated in interval 1, y2 first in interval 5 (y1 saturated again there), deadbeat in interval 6, and
    x = 0 from t = 6T = 3 s on."""
    unsat = np.asarray(example.unsaturated)
    first = [int(np.argmax(unsat[:, i])) + 1 for i in range(2)]
    assert first == [1, 5]
    assert not unsat[4, 0]
    mode = np.asarray(example.mode)
    assert int(np.argmax(mode)) + 1 == 6 and np.all(mode[5:] == 1) and np.all(mode[:5] == 0)
    assert np.max(np.abs(np.asarray(example.x_end)[5:])) < 1e-8
    np.testing.assert_allclose(example.x_hat[5], example.x_start[5], atol=1e-8)
    # the printed magnitudes are figure-only; the digest's independent re-check prints ||U_k|| 28.3, 6.41, 9.97, 15.5,
    # 24.1, 23.1 with the spectral norm in alpha
    np.testing.assert_allclose(np.linalg.norm(np.asarray(example.U)[:6], axis=1), [28.3, 6.41, 9.97, 15.5, 24.1, 23.1],
                               rtol=5e-3)  # fmt: skip


def test_xi_equals_D_x0_and_D_is_nonsingular_exactly_when_every_output_was_unsaturated(example):
    xi, D = np.asarray(example.xi), np.asarray(example.D)
    np.testing.assert_allclose(xi, D @ X0, atol=1e-8 * max(1.0, np.abs(xi).max()))
    every = np.all(np.asarray(example.sigma) > 0, axis=1)
    lowest = np.array([np.linalg.eigvalsh(Dk)[0] / np.linalg.eigvalsh(Dk)[-1] for Dk in D])
    assert np.all(lowest[~every] < 1e-12) and np.all(lowest[every] > 1e-9), (every, lowest)
    np.testing.assert_allclose(example.x0_hat[every.argmax() + 1], X0, atol=1e-7)


def test_vmap_over_initial_states_matches_single_runs(design8):
    x0s = np.array([X0, [-3.0, 1.0, 0.5], [0.2, 0.1, -0.1]])
    batched = jax.vmap(lambda x: SIM8(design8, x, 10, substeps=500, cond_max=1e12))(x0s)
    for i, x0 in enumerate(x0s):
        single = SIM8(design8, x0, 10, substeps=500, cond_max=1e12)
        np.testing.assert_allclose(batched.x_end[i], single.x_end, rtol=1e-12, atol=1e-12)
        assert np.max(np.abs(np.asarray(single.x_end[-1]))) < 1e-7


def test_ill_conditioned_gramian_is_flagged_and_desaturation_continues(design8):
    """Traced cond_max below any condition number: the deadbeat branch is never taken, the flag is raised, the
    state stays finite (never NaN)."""
    trace = SIM8(design8, jnp.asarray(X0), 10, substeps=500, cond_max=0.5)
    assert np.all(np.asarray(trace.mode) == 0)
    every = np.all(np.asarray(trace.sigma) > 0, axis=1)
    assert every.any()
    np.testing.assert_array_equal(np.asarray(trace.ill_conditioned)[1:], every[:-1])
    assert np.all(np.isfinite(np.asarray(trace.x_end))) and np.all(np.isfinite(np.asarray(trace.U)))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(A=A8, B=np.array([[0.0], [1], [0]]), C=C8), r"\(A, B\) must be controllable: .* rank 2 < n = 3"),
        (dict(A=A8, B=B8, C=np.array([[1.0, 0, 0]])), r"\(C, A\) must be observable: .* rank 2 < n = 3"),
        (dict(A=A8, B=B8, C=C8, T=0.0), "T must be a finite positive"),
        (dict(A=A8, B=B8, C=C8, rho=1.0), "rho must be > 1"),
        (dict(A=A8, B=B8, C=C8, H=np.array([[1.0, 0, 0], [-1, 0, 0]])), r"H: C_i h_i must be > 0 .* i = 1"),
        (dict(A=A8, B=B8, C=C8, alpha_norm="max"), "alpha_norm must be one of"),
        (dict(A=A8, B=B8[:2], C=C8), "B has shape"),
    ],
)
def test_bad_design_inputs(kwargs, match):
    args = dict(T=0.5, rho=1.1) | kwargs
    with pytest.raises(ValueError, match=match):
        sat.saturated_output_design(args.pop("A"), args.pop("B"), args.pop("C"), **args)


def _window(chi0, u=0.0, T=0.05, steps=50):
    """A window of the sandwich instance, solved independently (SciPy, tight tolerances); returns y, u, z."""
    f = lambda t, c: [c[1], u, -c[2] + np.clip(c[0], -1, 1)]
    t = np.linspace(0, T, steps + 1)
    sol = solve_ivp(f, (0, T), chi0, t_eval=t, rtol=1e-12, atol=1e-13, max_step=T / steps)
    return sol.y[2][:, None], np.full(steps + 1, u), sol.y[0]


@pytest.mark.parametrize(
    "chi0, u, expected",
    [
        ([3.0, 1.0, 0.2], 0.0, "positive"),  # z >= 1
        ([-3.0, 1.0, 0.5], 0.0, "negative"),  # z <= -1
        ([0.5, -1.0, 0.2], 0.0, "linear"),  # |z| < 1
        ([1.2, -8.0, 0.2], 0.0, "mixed"),  # z crosses 1 mid-window
        ([0.2, 4.0, -0.3], -30.0, "linear"),  # |z| < 1 under a nonzero input
        ([1.05, -4.0, 0.2], 0.0, "mixed"),  # z leaves saturation late in the window
    ],
)
def test_theorem_9_1_classifies_each_window(detect, chi0, u, expected):
    y, u_samples, z = _window(chi0, u)
    truth = (
        "positive" if z.min() >= 1 else "negative" if z.max() <= -1 else "linear" if np.abs(z).max() <= 1 else "mixed"
    )
    assert truth == expected  # the window is what its label says
    result = detect(jnp.asarray(y), jnp.asarray(u_samples))
    assert sat.CLASSES[int(result.cls)] == expected, np.asarray([result.e_plus, result.e_minus, result.e_zero])
    e = {"positive": result.e_plus, "negative": result.e_minus}
    if expected in e:  # a true saturation hypothesis is at rounding level, a false one is not
        assert float(e[expected]) < 1e-12 * max(float(result.e_plus), float(result.e_minus))
    if expected == "linear":
        chi_end = solve_ivp(lambda t, c: [c[1], u, -c[2] + np.clip(c[0], -1, 1)], (0, 0.05), chi0, rtol=1e-12,
                            atol=1e-13).y[:, -1]  # fmt: skip
        np.testing.assert_allclose(result.chi_end, chi_end, atol=1e-6)  # the deadbeat reconstruction (9.11b)


def test_low_gain_are_vanishes_linearly_and_stays_positive_definite():
    eps = np.array([1e-1, 1e-2, 1e-3, 1e-4])
    sols = [sat.low_gain_are(**{k: SW[k] for k in "ABCMN"}, F=F_SW, eps=e) for e in eps]
    assert all(bool(s.converged) for s in sols)
    P = np.array([np.asarray(s.X) for s in sols])
    norms = np.linalg.norm(P, 2, axis=(1, 2))
    assert np.all(np.linalg.eigvalsh(P)[:, 0] > 0)
    slope = norms / eps
    np.testing.assert_allclose(slope[1:], slope[-1], rtol=0.03)  # P_eps / eps -> the Lyapunov solution
    assert norms[-1] < 2e-3 * norms[0]  # four decades of eps, about three of P (it is not linear yet at 0.1)
    with pytest.raises(ValueError, match="eps must be a finite positive"):
        sat.low_gain_are(**{k: SW[k] for k in "ABCMN"}, F=F_SW, eps=0.0)


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(eps=-1e-3), "eps must be a finite positive"),
        (dict(T=0.0), "T must be a finite positive"),
        (dict(rho=0.9), "rho must be > 1"),
        (dict(h=[-1.0, 0.0]), "C h must be > 0"),
        (dict(F=[[1.0, 0.0]]), "A \\+ B F must be Hurwitz"),
        (dict(N=[[0.0]]), r"\(AA, BB\) of \(9.2\) must be controllable"),
        (dict(G=[[0.0]]), r"\(CC, AA\) of \(9.2\) must be observable"),
    ],
)
def test_bad_sandwich_inputs(change, match):
    args = dict(SW, T=0.05, Tbar_intervals=4, rho=1.1, F=F_SW, eps=1e-3) | change
    with pytest.raises(ValueError, match=match):
        sat.sandwich_design(**args)


@pytest.mark.slow
def test_three_stage_closed_loop_converges_from_every_grid_point(design9):
    """Grip (2010) Theorem 9.2 on the instance: 5 x 5 x 5 initial states on the box |x1|, |x2| <= 5, |w| <= 1,
    T = 0.05, Tbar = 0.2, eps = 1e-3, 40 s; one jit, vmapped."""
    g, gw = np.linspace(-5, 5, 5), np.linspace(-1, 1, 5)
    chi0 = np.array(np.meshgrid(g, g, gw, indexing="ij")).reshape(3, -1).T
    run = jax.jit(jax.vmap(lambda c: sat.simulate_sandwich(design9, c, 800, substeps=50)))
    trace = run(jnp.asarray(chi0))
    stage = np.asarray(trace.stage)
    assert np.all(stage[:, -1] == 3)
    in3 = stage == 3
    error = np.linalg.norm(np.asarray(trace.chi_end) - np.asarray(trace.chi_hat_end), axis=2)
    assert np.max(error[in3]) < 1e-6  # the deadbeat reconstruction (9.11b) and Lemma 9.2
    assert np.max(np.linalg.norm(np.asarray(trace.chi_end)[:, -1], axis=1)) < 1e-3


# ---------------------------------------------------------------------------------------------------------------
# the input contract (issue 28)

NON_FINITE = [np.nan, np.inf, -np.inf]
ONE = dict(A=[[1.0]], B=[[1.0]], C=[[1.0]])


@pytest.mark.parametrize(
    "call, name",
    [
        pytest.param(lambda: sat.saturated_output_design(**ONE, T=1e4, rho=1.1), "T", id="design-T-overflows"),
        pytest.param(lambda: sat.saturated_output_design(A8, B8, C8, T=1e100, rho=1.1), "T", id="design-T-8.5"),
        pytest.param(lambda: sat.sandwich_design(**SW, T=500.0, Tbar_intervals=4, rho=1.1, F=F_SW, eps=1e-3), "T",
                     id="sandwich-Tbar-overflows"),
        pytest.param(lambda: sat.window_model([[1.0]], [[1.0]], [[1.0]], 1e4), "h", id="window-h-overflows"),
        *[pytest.param(lambda v=v: sat.saturated_output_design(**ONE, T=v, rho=1.1), "T", id=f"design-T-{v}")
          for v in (*NON_FINITE, -1.0)],
        *[pytest.param(lambda v=v: sat.saturated_output_design(**ONE, T=0.5, rho=v), "rho", id=f"design-rho-{v}")
          for v in (*NON_FINITE, 0.5)],
        *[pytest.param(lambda v=v: sat.window_model([[0.0]], [[1.0]], [[1.0]], v), "h", id=f"window-h-{v}")
          for v in (*NON_FINITE, -1.0, 0.0)],
        pytest.param(lambda: sat.window_model([[np.nan]], [[1.0]], [[1.0]], 0.1), "F", id="window-F-nan"),
        pytest.param(lambda: sat.window_model([[0.0]], [[1.0], [1.0]], [[1.0]], 0.1), "Bf", id="window-Bf-rows"),
        pytest.param(lambda: sat.hypothesis([[0.0]], [[1.0]], "H", 0.1), "H", id="hypothesis-H-str"),
    ],
)  # fmt: skip
def test_design_values_are_checked_naming_the_argument(call, name):
    """Times and steps must be finite and positive, rho > 1, and T (h) small enough that the matrix exponentials stay
    finite: before, saturated_output_design([[1]], [[1]], [[1]], T=1e4, rho=1.1) returned alpha = NaN, exp(AT) = inf
    and Bbar = NaN, and window_model(F, Bf, H, -1 or nan) matrices with negative or NaN entries."""
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        call()


def test_traced_overflows_and_steps_are_non_finite_not_wrong():
    """Under jit nothing raises: a T whose exp(A T) overflows gives non-finite design constants, and a step h <= 0 a
    NaN window model (before: matrices with negative entries at h = -1)."""
    alpha = jax.jit(lambda T: sat.saturated_output_design(**ONE, T=T, rho=1.1).alpha)
    assert not np.isfinite(alpha(1e4)) and np.isfinite(alpha(0.5))
    model = jax.jit(lambda h: sat.window_model([[0.0]], [[1.0]], [[1.0]], h))
    for h in (-1.0, 0.0):
        assert all(np.all(np.isnan(M)) for M in model(h)[1:])
    assert all(np.all(np.isfinite(M)) for M in model(0.1))


@pytest.mark.parametrize(
    "kwargs, name",
    [
        *[(dict(cond_max=v), "cond_max") for v in (*NON_FINITE, -1.0, 0.0, 0.5)],
        (dict(x0=[2.0, np.nan, 1.0]), "x0"),
        (dict(x0=[2.0, 1.0]), "x0"),
        (dict(num_intervals=0), "num_intervals"),
        (dict(substeps=2.5), "substeps"),
        (dict(design="design"), "design"),
    ],
)
def test_simulate_saturated_outputs_bad_inputs(design8, kwargs, name):
    """cond_max must be a finite number >= 1 (before: NaN or -1 ran and never reached deadbeat, unflagged)."""
    args = dict(design=design8, x0=X0, num_intervals=3) | kwargs
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        sat.simulate_saturated_outputs(args.pop("design"), args.pop("x0"), args.pop("num_intervals"), **args)


def _two_output_hypothesis():
    return sat.hypothesis(np.zeros((2, 2)), np.ones((2, 1)), np.eye(2), 0.1)


@pytest.mark.parametrize(
    "y, u, kwargs, name",
    [
        (np.zeros((11, 1)), np.zeros((11, 1)), {}, "y"),  # one output for two: was broadcast, statistic 0
        (np.zeros((11, 3)), np.zeros((11, 1)), {}, "y"),
        (np.zeros(11), np.zeros((11, 1)), {}, "y"),
        (np.full((11, 2), np.nan), np.zeros((11, 1)), {}, "y"),
        (np.zeros((11, 2)), np.zeros((9, 1)), {}, "u"),
        (np.zeros((11, 2)), np.zeros((11, 2)), {}, "u"),
        (np.zeros((11, 2)), np.full((11, 1), np.inf), {}, "u"),
        (np.zeros((10, 2)), np.zeros((10, 1)), {}, "y"),  # N odd
        ("y", np.zeros((11, 1)), {}, "y"),
        (np.zeros((11, 2)), np.zeros((11, 1)), dict(ratio=1.0), "ratio"),
        (np.zeros((11, 2)), np.zeros((11, 1)), dict(rtol=-1.0), "rtol"),
        (np.zeros((11, 2)), np.zeros((11, 1)), dict(rounding=np.nan), "rounding"),
    ],
)
def test_explains_checks_its_records(y, u, kwargs, name):
    """Records must have one column per output of the hypothesis (no broadcast) and per input, finite values, and
    an odd number of samples; the acceptance constants their ranges."""
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        sat.explains(_two_output_hypothesis(), y, u, **kwargs)


def test_explains_takes_nested_lists_as_arrays():
    """A nested list is read as an array (before: AttributeError)."""
    hyp, y, u = _two_output_hypothesis(), np.ones((11, 2)), np.zeros((11, 1))
    listed = sat.explains(hyp, y.tolist(), u.tolist())
    arrays = sat.explains(hyp, y, u)
    assert bool(listed[0]) and bool(arrays[0])
    np.testing.assert_array_equal(listed[1], arrays[1])


def test_interval_map_and_residual_check_their_arguments(design8):
    with pytest.raises(ValueError, match=r"^x\b"):
        sat.interval_map(design8, np.zeros(2), np.zeros(3))
    with pytest.raises(ValueError, match=r"^U\b"):
        sat.interval_map(design8, np.zeros(3), [0.0, np.nan, 0.0])
    with pytest.raises(ValueError, match=r"^y\b"):
        sat.hypothesis_residual(_two_output_hypothesis().fine, np.zeros((5, 1)), np.zeros((5, 1)))
