"""Sensorless closed loop with the zhang2022 observers, and the paper's experiments.

Tolerances are stated per test. The simulated drive has no dead time or other inverter
non-linearity and white current noise of 0.02 A (see `pmsmjax.papers.zhang2022`), so the
steady-state errors are far below the paper's measured ones; the tests bound them at
values the model must meet, not at the paper's numbers (those are compared side by
side in notebooks/02_eso_observers.ipynb).
"""

import math

import equinox as eqx
import jax
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.papers import zhang2022


DRIVE = pj.preset("zhang750")
M = DRIVE.motor
WR = float(DRIVE.w_rated)

OBSERVERS = {
    "eso": lambda: pj.ESOObserver.from_drive(DRIVE),
    "leso": lambda: pj.LESOObserver.from_drive(DRIVE),
    "afo": lambda: pj.AFOObserver.from_drive(DRIVE),
}


def sensored_track_pct(fig):
    """The speed-tracking error (max, % of the set-point) of the same experiment with an
    encoder: the reference the sensorless drive is held to (the paper's printed bands are
    shown next to the simulation in notebooks/02, not used as limits)."""
    if fig not in _SENSORED:
        r = zhang2022.experiment(fig, observer=pj.SensoredObserver()).run()
        _SENSORED[fig] = r.stats["eso"]["w_track_err_max_pct"]
    return _SENSORED[fig]


_SENSORED: dict = {}
# The sensorless drive's speed loop sees the estimate instead of the encoder: its angle
# error (std below 0.2 deg) costs a torque error of 1 - cos(0.2 deg) ~ 6e-6, nothing, but
# its speed-estimate noise enters the speed loop. Measured: 0.097 / 0.543 / 0.009 % against
# 0.125 / 0.619 / 0.007 % sensored (Figs. 2, 3, 4). Allowed: half as much again as
# the sensored drive, plus 0.005 % for the estimate's noise at rated speed.
TRACK_FACTOR, TRACK_PLUS_PCT = 1.5, 0.005


def track_limit_pct(fig):
    return TRACK_FACTOR * sensored_track_pct(fig) + TRACK_PLUS_PCT


def stable_deg(eq):
    """Angles (deg) of the stable equilibria of an `Equilibria`."""
    return np.degrees(np.asarray(eq.theta)[np.asarray(eq.stable)])


@pytest.mark.parametrize("kind", list(OBSERVERS))
def test_converges_from_30_deg_on_a_loaded_ramp(kind):
    """Fig. 2: ramp to 0.05 p.u. against 0.1 p.u. load, theta_err(0) = 30 deg.

    Tolerance: within 2 deg for good after 0.5 s (paper: 0.35 s); after 0.6 s the angle
    error has |mean| < 0.2 deg, std < 0.2 deg and the speed tracks as well as with an
    encoder (`track_limit_pct`; paper: 0.11 deg, 0.69 deg, +-5 %).
    """
    r = zhang2022.experiment("fig2", observer=OBSERVERS[kind]()).run()
    assert bool(r.traj.ok)
    err0 = np.degrees(float(r.traj.theta_err[0]))
    assert err0 == pytest.approx(30.0, abs=1e-9)
    s = r.stats["eso"]
    assert 0.05 < s["t_converge_s"] < 0.5
    assert abs(s["theta_err_mean_deg"]) < 0.2 and s["theta_err_std_deg"] < 0.2
    assert s["w_track_err_max_pct"] < track_limit_pct("fig2")
    # the estimate really was wrong at first: the error decays, it is not just small
    assert s["theta_err_max_all_deg"] > 25.0


def test_steady_state_at_rated_speed_and_load():
    """Fig. 4: 1.0 p.u., rated load. Tolerance |mean| < 0.2 deg, std < 0.2 deg, speed
    tracked as with an encoder (paper: 0.07 deg, 0.08 deg, +-1 %)."""
    r = zhang2022.experiment("fig4").run()
    s = r.stats["eso"]
    assert abs(s["theta_err_mean_deg"]) < 0.2 and s["theta_err_std_deg"] < 0.2
    assert s["w_track_err_max_pct"] < track_limit_pct("fig4")
    # the load is really carried: mean torque equals the rated torque
    tau = np.asarray(r.traj.tau_M)[r.t >= 0.4]
    assert np.mean(tau) == pytest.approx(float(DRIVE.tau_rated), rel=0.02)


def test_low_speed_one_percent():
    """Fig. 3: 0.01 p.u., 0.01 p.u. load. Without inverter non-linearities the simulated
    drive holds |mean| < 0.5 deg, std < 0.2 deg, and tracks the speed as with an encoder
    (paper: 1.45 deg, 0.10 deg, +-15 %)."""
    r = zhang2022.experiment("fig3").run()
    s = r.stats["eso"]
    assert abs(s["theta_err_mean_deg"]) < 0.5 and s["theta_err_std_deg"] < 0.2
    assert s["w_track_err_max_pct"] < track_limit_pct("fig3")


@pytest.mark.parametrize("fig,w_pu", [("fig3", 0.01), ("fig4", 1.0)])
def test_resistance_error_gives_the_static_error_of_11(fig, w_pu):
    """A 20 % resistance error in the observer's model: the simulated static angle error
    equals the stable equilibrium of (11) with that mismatch within 0.1 deg. (It is
    large, 2.4 deg at 0.01 p.u. / 0.01 p.u. load and 9.7 deg at rated speed and load:
    with (17)/(38) the flux gain acts along psi_a only and the q-axis drop R i_q is
    balanced through the angle, about 2 zeta1 w0 / w1 = 4 zeta1^2 / 3 times the
    voltage-model error R i_q / (w0 psi_f).)"""
    exp = zhang2022.experiment(fig, noise_std=0.0)
    obs = eqx.tree_at(lambda o: o.motor.R_s, exp.kwargs["observer"], 1.2 * M.R_s)
    r = zhang2022.experiment(fig, noise_std=0.0, observer=obs).run()
    tr = r.traj
    mask = np.asarray(tr.t) >= exp.t_settle
    i_c = np.asarray(pj.park(tr.i_meas_ab, tr.theta_hat))[mask].mean(0)
    eq = stable_deg(pj.analysis.equilibria(obs, M, w_pu * WR, i_c))
    assert len(eq) == 1
    s = r.stats["eso"]
    assert abs(s["theta_err_mean_deg"]) > 1.0
    assert s["theta_err_mean_deg"] == pytest.approx(eq[0], abs=0.1)


def test_speed_steps():
    """Fig. 5: 0 -> 1 -> 0.5 p.u. without load, from standstill. The drive follows the
    steps (speed within 1 % at the end of each plateau) and the angle error, large
    while accelerating at the torque limit, returns below 0.3 deg."""
    r = zhang2022.experiment("fig5").run()
    tr = r.traj
    t, w = np.asarray(tr.t), np.asarray(tr.w_m)
    assert w[np.searchsorted(t, 0.55)] == pytest.approx(WR, rel=0.01)
    assert w[-1] == pytest.approx(0.5 * WR, rel=0.01)
    err = np.abs(np.degrees(np.asarray(tr.theta_err)))
    assert err[np.searchsorted(t, 0.5):np.searchsorted(t, 0.6)].max() < 0.3
    assert err[-800:].max() < 0.3
    assert 5.0 < err.max() < 90.0


def test_load_steps():
    """Fig. 6: +0.25 / -0.25 p.u. load at 1.0 p.u. The speed dips as with an encoder,
    the angle error stays below 5 deg and the speed estimate follows the dips (error
    below 3 % of rated speed during the steps, 0.1 % before the next step)."""
    r = zhang2022.experiment("fig6").run()
    tr = r.traj
    w, w_hat = np.asarray(tr.w_m), np.asarray(tr.w_hat)
    dip = np.max(np.abs(WR - w)) / WR
    # against the same load steps with an encoder (the speed loop's own dip): the
    # sensorless loop sees the load through the speed estimate, which lags the speed, so
    # its dip is larger, but by less than half (measured 4.66 % against 3.77 %)
    ref = zhang2022.experiment("fig6", observer=pj.SensoredObserver()).run()
    dip_ref = np.max(np.abs(WR - np.asarray(ref.traj.w_m))) / WR
    assert dip_ref < dip < 1.5 * dip_ref
    assert np.max(np.abs(np.degrees(np.asarray(tr.theta_err)))) < 5.0
    assert np.max(np.abs(w - w_hat)) < 0.03 * WR
    t = np.asarray(tr.t)
    for t_end in (2.2, 3.0):
        window = (t > t_end - 0.3) & (t < t_end)
        assert np.max(np.abs(w - w_hat)[window]) < 1e-3 * WR


def test_delay_noise_initial_error_and_mismatch_step():
    """Computational delay, noise, a 30 deg initial error, and a step in the observer's
    R_s (x1.5) and inductances (x0.8) mid-run: before the step the error is below
    0.2 deg; after it, the static error equals the stable equilibrium of the error
    dynamics (11) with that mismatch, within 0.3 deg."""
    drive = eqx.tree_at(lambda d: d.inverter, DRIVE, pj.Inverter(u_dc=311.0, delay=True))
    obs = pj.ESOObserver.from_drive(drive)
    step = lambda v: pj.Profile.steps([0.6], [v], 1.0)  # noqa: E731
    sc = pj.Scenario(t_end=1.2, w_m_ref=pj.Profile.constant(0.5 * WR),
                     tau_L=pj.Profile.constant(0.5 * float(DRIVE.tau_rated)),
                     observer_scale={"R_s": step(1.5), "L_d": step(0.8), "L_q": step(0.8)})
    tr = pj.simulate(drive, pj.FOC.from_drive(drive), obs, sc, w_m0=0.5 * WR,
                     theta_hat0=-math.radians(30), sensing=pj.Sensing(noise_std=0.02),
                     key=jax.random.PRNGKey(1))
    t, e = np.asarray(tr.t), np.degrees(np.asarray(tr.theta_err))
    before = e[(t >= 0.3) & (t < 0.6)]
    after = e[t >= 0.9]
    assert abs(before.mean()) < 0.2 and before.std() < 0.2
    i_c = np.asarray(pj.park(tr.i_meas_ab, tr.theta_hat))[t >= 0.9].mean(0)
    obs_hat = obs.with_motor(pj.scale_motor(M, {"R_s": 1.5, "L_d": 0.8, "L_q": 0.8}))
    eq = stable_deg(pj.analysis.equilibria(obs_hat, M, 0.5 * WR, i_c))
    assert len(eq) == 1
    assert abs(after.mean()) > 3.0
    assert after.mean() == pytest.approx(eq[0], abs=0.3)


def test_infeasible_design_of_fig9():
    """Fig. 9 (zeta1 = 0.5, w1 = 0.5 w0 at 0.5 p.u.). The error dynamics (11) have a
    nonzero equilibrium at theta = 2 atan(w1 / (2 zeta1 w0)) = 53.13 deg for i = 0 (derived
    from (31)), and it is *unstable* with the paper's own gains: the simulated drive
    converges to zero from the paper's -14.53 deg (the paper measures 23.18 deg)."""
    design = pj.ESODesign.fixed_ratio(0.5, 0.5, 2 * math.pi * 50)
    eq = pj.analysis.equilibria(pj.LESOObserver(M, design), M, 0.5 * WR, (0.0, 0.0))
    valid = np.asarray(eq.valid)
    angles = np.degrees(np.asarray(eq.theta)[valid])
    assert angles == pytest.approx([0.0, math.degrees(2 * math.atan(0.5))], abs=1e-3)
    assert list(np.asarray(eq.stable)[valid]) == [True, False]
    r = zhang2022.experiment("fig9").run()
    assert np.degrees(float(r.traj.theta_err[0])) == pytest.approx(-14.53, abs=1e-9)
    s = r.stats["eso"]
    assert abs(s["theta_err_mean_deg"]) < 0.2
    eq = r.theory["equilibria"]
    assert list(np.asarray(eq.stable)[np.asarray(eq.valid)]) == [True, False]


def test_noise_at_equal_bandwidth_fig7():
    """Fig. 7 (sensing mode, 0.25 p.u., both at 250 Hz): the same angle error, but the
    AFO's speed estimate (the PI output of (53)) fluctuates more than 3x as much as the
    ESO's (the integral state of (10c))."""
    r = zhang2022.experiment("fig7").run()
    eso, afo = r.stats["eso"], r.stats["afo"]
    assert eso["theta_err_std_deg"] == pytest.approx(afo["theta_err_std_deg"], rel=0.1)
    assert afo["w_err_std"] > 3 * eso["w_err_std"]
    assert eso["t_w_converge_s"] < 0.02 and afo["t_w_converge_s"] < 0.02


def test_half_inductance_under_load_fig10():
    """Fig. 10 with rated load: L/2 in the observer gives the static error that (11)
    predicts (within 0.2 deg), for the ESO and the AFO alike; at zero load (the
    paper's setting) the inductance hardly matters (< 0.1 deg)."""
    exp = zhang2022.experiment("fig10", load_pu=1.0)
    r = exp.run()
    for name in ("eso_half_L", "afo_half_L"):
        obs = exp.observers[name]
        s = r.stats[name]
        i_est = pj.rotate(np.asarray(pj.park(r.traj.i_meas_ab, r.traj.theta))[800:]
                          .mean(0), math.radians(s["theta_err_mean_deg"]))
        eq = stable_deg(pj.analysis.equilibria(obs, M, 0.1 * WR, i_est))
        assert s["theta_err_mean_deg"] < -5.0
        assert s["theta_err_mean_deg"] == pytest.approx(eq[0], abs=0.2)
    r0 = zhang2022.experiment("fig10").run()
    assert abs(r0.stats["eso_half_L"]["theta_err_mean_deg"]
               - r0.stats["eso"]["theta_err_mean_deg"]) < 0.1


def test_adaptive_and_fixed_gains_fig11():
    """Fig. 11 from zero initial conditions: at 0.2 p.u. both designs converge within
    0.1 s; at 0.6 p.u. both converge with a 250 Hz bandwidth (with the paper's 50 Hz
    default neither pulls in from w_hat = 0: the 754 rad/s offset is beyond the
    speed loop's pull-in range; see the notebook)."""
    for w_pu, bw in ((0.2, 50.0), (0.6, 250.0)):
        r = zhang2022.experiment("fig11", w_pu=w_pu, bandwidth_hz=bw).run()
        for name in ("adaptive", "fixed"):
            s = r.stats[name]
            assert s["t_w_converge_s"] < 0.1, (w_pu, name, s)
            assert abs(s["theta_err_mean_deg"]) < 0.2
