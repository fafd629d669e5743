"""Lock acquisition: the back-EMF PLL (li-fa-leso's C-LESO, GI-LESO, FA-LESO): its
acquisition assist leaves the designed lock's linearisation unchanged, its phase detector
matches its closed form (the old one near the designed lock, the back-EMF axis below
w_min where the signs disagree); it acquires from a zero or wrong-signed speed estimate
on a turning rotor at either sign of speed; `analysis.lock_basin` / `lock_time` measure
it."""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import make_observer


DTP = pj.preset("li_dtp")
W = float(DTP.w_rated)
BEMF = ("c-leso", "gi-leso", "fa-leso")


def test_lock_time_is_the_first_sample_after_which_the_error_stays_inside():
    t = np.arange(10) * 0.1
    tol = 0.1
    err = np.array([3.0, 2.0, 0.05, 0.5, 0.02, -0.01, 0.03, 0.0, -0.05, 0.01])
    locked, t_l = analysis.lock_time(jnp.asarray(t), jnp.asarray(err), tol)
    assert bool(locked) and float(t_l) == pytest.approx(0.4)  # the 0.5 at index 3
    # a lock only in the last 20 % of the run is not a kept lock; NaN counts as outside
    err2 = np.array([1.0] * 8 + [0.0, 0.0])
    assert not bool(analysis.lock_time(jnp.asarray(t), jnp.asarray(err2), tol)[0])
    err3 = err.copy()
    err3[6] = np.nan
    locked3, t3 = analysis.lock_time(jnp.asarray(t), jnp.asarray(err3), tol)
    assert bool(locked3) and float(t3) == pytest.approx(0.7)


@pytest.mark.parametrize("name", BEMF)
def test_acquisition_assist_does_not_change_the_discrete_linearisation(name):
    """The assist's term is third order at the designed lock: the Jacobian of one real
    step (with a mismatched model, so that the designed angle error is not zero) is the
    same with and without it."""
    obs = make_observer(name, DTP)
    off = eqx.tree_at(lambda o: o.pll.fll, obs, 0.0)
    plant = pj.replace_params(DTP, R_s=1.3 * DTP.three_phase_motor.R_s).three_phase_motor
    op = analysis.OperatingPoint(0.6 * W, (0.0, 2.0))
    x0 = obs.designed_error(op, plant)
    T_s = 1e-4
    jac = [np.asarray(analysis.discrete_jacobian(o, plant, op.w_m, op.i_dq, T_s, x=x0))
           for o in (obs, off)]
    # the map is evaluated at the equilibrium: the assist is active (g != 0 elsewhere)
    assert np.all(np.isfinite(jac[0]))
    np.testing.assert_allclose(jac[0], jac[1], rtol=1e-9, atol=1e-9 * np.abs(jac[1]).max())


def _starts(w_m):
    # initial angle errors over the whole circle, speed estimates zero and wrong-signed
    return np.array([-2.5, -1.0, 1.5, 3.0]), np.array([0.0, -0.6 * w_m])


@pytest.mark.parametrize("name", BEMF)
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_back_emf_observers_acquire_a_turning_rotor_from_zero_speed(name, sign):
    """Replay of a recording that turns from the first sample, the observer started at
    zero (or the opposite) speed and a wrong angle: locks onto the designed steady-state
    angle error (the analysis' `designed_error`, e.g. the C-LESO's lag) at the right
    sign of speed and keeps it."""
    obs = make_observer(name, DTP)
    w_m = sign * 0.5 * W
    th0, wh0 = _starts(w_m)
    b = analysis.lock_basin(obs, DTP, w_m=w_m, theta_err0=th0, w_hat0=wh0, t_end=0.25,
                            tol=math.radians(3.0), batch=8, progress=False)
    assert b.locked.all(), (b.locked, b.final_err)
    # at constant speed the discrete observer has exactly the continuous steady state:
    # the final error is the designed one, far inside the lock tolerance (not yet for the
    # GI-LESO: its generalised integrator's transient decays at w_c = pi rad/s, Table II,
    # and is still ~1 deg after 0.25 s; the lock tolerance holds)
    if name != "gi-leso":
        assert np.abs(b.final_err).max() < math.radians(0.5)
    assert np.all(b.t_lock < 0.15)


@pytest.mark.parametrize("w, w_hat", [(150.0, 0.0), (-150.0, 0.0), (30.0, 20.0),
                                       (-30.0, 25.0), (30.0, -5.0), (400.0, 300.0),
                                       (-400.0, 300.0)])
def test_phase_detector_against_its_closed_form(w, w_hat):
    """The detector on an exact back-EMF $e = \\omega\\psi[-\\sin\\theta, \\cos\\theta]$,
    over the whole circle of angle errors: $(\\omega/\\hat\\omega)\\sin\\tilde\\theta$
    above w_min; below it the old $\\omega\\hat\\omega\\sin\\tilde\\theta/w_{min}^2$
    where sign(e_q) = sign(w_hat), and the back-EMF axis' sign otherwise, including at
    w_hat = 0, where the bare PI loop (the factor w_hat) had no gain at all."""
    pll = pj.observers.QuadraturePLL(w_pll=100.0, zeta_pll=1.0, w_min=50.0)
    psi, theta = 0.2, 0.7
    th_err = np.linspace(-3.1, 3.1, 41)
    th_hat = theta - th_err
    e = w * psi * np.array([-np.sin(theta), np.cos(theta)])
    eps = np.asarray(pll.error(jnp.asarray(np.broadcast_to(e, (41, 2))),
                               jnp.asarray(th_hat), w_hat, psi))
    r = abs(w_hat) / pll.w_min
    s_q = np.sign(w * np.cos(th_err))
    if r >= 1:
        want = (w / w_hat) * np.sin(th_err)
    else:
        bracket = w_hat / pll.w_min + (1 - r) * (s_q - np.sign(w_hat))
        want = w * np.sin(th_err) / pll.w_min * bracket
    np.testing.assert_allclose(eps, want, rtol=1e-12, atol=1e-12)
    # near the designed lock (sign(e_q) = sign(w) = sign(w_hat)) it is the old detector
    if np.sign(w) == np.sign(w_hat):
        near = np.abs(th_err) < 1.0
        old = w * w_hat * np.sin(th_err) / max(w_hat ** 2, pll.w_min ** 2)
        np.testing.assert_allclose(eps[near], old[near], rtol=1e-12, atol=1e-15)


def test_closed_loop_flying_start_locks():
    """The observer in the current loop from the first sample (wrong frame, wrong currents
    until it locks), rotor turning: the FA-LESO locks from zero speed."""
    obs = make_observer("fa-leso", DTP)
    b = analysis.lock_basin(obs, DTP, mode="closed_loop", theta_err0=[2.0],
                            w_hat0=[0.0], t_end=0.25, progress=False)
    assert b.locked.all() and b.mode == "closed_loop"
    assert 0.0 < float(b.t_lock[0, 0]) < 0.15


def test_lock_basin_rejects_bad_arguments():
    obs = make_observer("fa-leso", DTP)
    with pytest.raises(ValueError, match="w_m"):
        analysis.lock_basin(obs, DTP, w_m=0.0)
    with pytest.raises(ValueError, match="mode"):
        analysis.lock_basin(obs, DTP, mode="flying")
    with pytest.raises(ValueError, match="sensorless"):
        analysis.lock_basin(pj.observers.SensoredObserver(), DTP)


def test_plot_lock_basin_marks_the_starts_that_did_not_lock():
    import matplotlib

    matplotlib.use("Agg")
    from pmsmjax.plotting import plot_lock_basin

    locked = np.array([[True, False], [True, True], [False, True]])
    b = analysis.LockBasin(
        theta_err0=np.array([-1.0, 0.0, 1.0]), w_hat0=np.array([0.0, 100.0]), w_m=100.0,
        i_q=1.0, locked=locked, t_lock=np.where(locked, 0.05, np.nan),
        final_err=np.zeros((3, 2)), theta_design=0.0, tol=0.1, t_end=0.2, mode="replay")
    ax = plot_lock_basin(b)
    crosses = ax.collections[-1].get_offsets()
    # the two starts without a lock, at (w_hat0 / w_m, theta_err0 in deg)
    np.testing.assert_allclose(sorted(map(tuple, np.asarray(crosses))),
                               sorted([(1.0, np.degrees(-1.0)), (0.0, np.degrees(1.0))]))
    assert "67 % locked" in ax.get_title()
