"""The six per-DOF controllers and the peg-on-hole alignment scenario of Cortesão's MRAC chapter §7 (eq. 62-68,
§7.4; jaxobs.papers.cortesao.mrac) on the 6-DOF MJX plant (jaxobs.mjx.compliant_6dof, tested in
tests/mjx/test_compliant_6dof.py)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxobs.closed_loop import ideal_response, rms
from jaxobs.design import critically_damped_gain
from jaxobs.mjx import compliant_6dof as c6
from jaxobs.observers.active import active_observer_controller as AOB
from jaxobs.observers.active import classify_strategy, set_active
from jaxobs.papers.cortesao import mrac
from jaxobs.papers.cortesao.example1 import PRINTED_L_R
from jaxobs.plants import force_plant

H = c6.CONTROL_PERIOD
T = 250  # 2 s
DEAD_TIME = 5
X, Z, RX, RY, RZ = c6.X, c6.Z, c6.RX, c6.RY, c6.RZ


@pytest.fixture(scope="module")
def controllers():
    return mrac.design()


def test_design_is_eq62_68(controllers):
    """Per DOF an AOB-1 (8 observer states: force, its derivative, 5 delay slots, the active state) with
    ``L = [L_r, 1]``, ``L_r`` critically damped at tau_c = 10 Tp (eq. 68: on x the printed Cortesão 2006 eq. 83 to
    4 decimals); z is the CKF with the sensor-based gain ``K = [1, 0, ..., 0]'`` (active state off, SBA), the other
    five hybrid (HBA). With Q and P0 scaled by R_i / R(f_x) (eq. 65-66) DOF of equal Ks and Tp share one gain
    (x and y; the three moments, to rounding), and Ks = 100 enters the active state's input column, so the moments'
    force-state gains are larger than the forces'. The reference is ``r = L_1 f_d`` per DOF."""
    aob, L = controllers.estimator, controllers.L
    assert aob.Phi.shape == (6, 8, 8) and L.shape == (6, 1, 8) and controllers.N is None
    np.testing.assert_array_equal(aob.active, [1.0, 1.0, 0.0, 1.0, 1.0, 1.0])
    np.testing.assert_array_equal(aob.gain[Z, :, 0], np.eye(8)[0])
    strategies = [classify_strategy(aob.gain[i], aob.C[i]) for i in range(6)]
    assert strategies == ["HBA", "HBA", "SBA", "HBA", "HBA", "HBA"]
    np.testing.assert_allclose(aob.gain[c6.Y], aob.gain[X], rtol=1e-12)
    for i in (RY, RZ):
        np.testing.assert_allclose(aob.gain[i], aob.gain[RX], rtol=1e-12)
    assert np.all(aob.gain[RX, :2, 0] > aob.gain[X, :2, 0])
    for i, ks in enumerate(mrac.TABLE1_STIFFNESS):
        L_r = critically_damped_gain(force_plant(ks, 0.032, H, DEAD_TIME * H), tau_c=0.32)
        np.testing.assert_allclose(L[i, :, :7], L_r, rtol=1e-12)
    np.testing.assert_array_equal(L[:, 0, 7], 1.0)
    np.testing.assert_array_equal(np.round(np.asarray(L[X, 0, :7]), 4), PRINTED_L_R)
    f_d = jnp.arange(12.0).reshape(2, 6)
    np.testing.assert_array_equal(mrac.force_reference(controllers, f_d), f_d * L[:, 0, 0])


@pytest.mark.slow
def test_aob_partly_cancels_the_alignment_load(controllers):
    """§7.4 alignment phase (f_x -> -5 N, f_z -> 10 N, w_y aligning the 0.04 rad tilt over 1.25 s, v_z bias
    0.05 mm/s, sensor noise of variance R; m_y feedback off): the peg ends upright, and the rotation's load on
    the contact is an equivalent disturbance that the AOB-1 (HBA, eq. 62) on x partly cancels: RMS deviation of
    f_x from the desired closed-loop response 1.19 N against 2.09 N with the same filter as a CKF (active state
    off); required < 0.75x."""
    scenario = mrac.peg_on_hole_scenario(duration=T * H, alignment=(0.5, 1.75))
    np.testing.assert_array_equal(scenario.controllers.L[RY], 0.0)
    np.testing.assert_array_equal(scenario.plant.stiffness[RY], 0.0)
    model = c6.with_params(c6.load_model()[1], scenario.plant)
    v = jax.random.normal(jax.random.PRNGKey(0), (T, 6)) * jnp.sqrt(jnp.asarray(mrac.SENSOR_NOISE_VARIANCE))
    ctrl, r = scenario.controllers, scenario.reference

    @jax.jit
    def loop(params):
        return c6.closed_loop_rollout(model, AOB, params, r, feedforward=scenario.feedforward, noise=v)

    aob = loop(ctrl)
    assert float(aob.position[-1, RY]) == pytest.approx(-float(scenario.plant.tilt), rel=0.02)  # aligned
    on = jnp.ones(6).at[X].set(0.0) * ctrl.estimator.active
    ckf = loop(dataclasses.replace(ctrl, estimator=set_active(ctrl.estimator, on)))
    desired = ideal_response(force_plant(3.0, 0.032, H, DEAD_TIME * H), ctrl.L[X, :, :7], r[:, X])[:, 0]
    err_aob, err_ckf = (float(rms(t.wrench_true[:, X] - desired)) for t in (aob, ckf))
    assert err_aob < 0.75 * err_ckf


def test_full_process_noise_replaces_eq62():
    """``process_noise`` given as eq. 62's own covariances designs the same controllers; a coupled Q changes the
    gains; a Q that is not PSD, of the wrong shape, or given with q_active is refused naming it."""
    hand_set = mrac.design()
    same = mrac.design(process_noise=hand_set.estimator.Q)
    np.testing.assert_array_equal(same.estimator.gain, hand_set.estimator.gain)
    Q = hand_set.estimator.Q
    cross = 0.5 * jnp.sqrt(Q[:, 0, 0] * Q[:, 7, 7])  # a correlation of 0.5 between the force and the active state
    coupled = Q.at[:, 0, 7].set(cross).at[:, 7, 0].set(cross)
    assert not np.allclose(mrac.design(process_noise=coupled).estimator.gain[X], hand_set.estimator.gain[X])
    with pytest.raises(ValueError, match="process_noise must be positive semidefinite"):
        mrac.design(process_noise=-hand_set.estimator.Q)
    with pytest.raises(ValueError, match=r"process_noise must have shape \(6, 8, 8\)"):
        mrac.design(process_noise=hand_set.estimator.Q[:, :7, :7])
    with pytest.raises(ValueError, match="q_active or process_noise, not both"):
        mrac.design(q_active=1e-5, process_noise=hand_set.estimator.Q)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match=r"^stiffness must be > 0"):
        mrac.design(mrac.peg_on_hole_scenario().plant)  # K_ry = 0: nothing to design a moment loop on
    with jax.enable_x64(False), pytest.raises(ValueError, match="float64"):
        mrac.design()  # float32 would give near-zero gains for the 1e-12 Q entries
    with pytest.raises(ValueError, match=r"^sba must list DOF indices"):
        mrac.design(sba=(6,))
    with pytest.raises(ValueError, match=r"^steady_state=False needs sba=\(\)"):
        mrac.design(steady_state=False)
    with pytest.raises(ValueError, match=r"^alignment must be a window"):
        mrac.peg_on_hole_scenario(alignment=(2.0, 1.0))
