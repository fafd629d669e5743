"""`pmsmjax.FlyingCatch`: a drive switched on while its rotor turns, the observer's angle
and speed unknown (2 rad off, zero speed). In the closed loop every registered observer,
wrapped, acquires the lock within the catch window's time and keeps it at the static error
its analysis predicts, at either sign of speed; zhang2022's ESO, LESO and AFO without it
do not (they slip or sit in the false lock at 180 deg). The caught estimate is the flying
start's (an independent route: a circular mean over the window against the wrapper's
running sums), and a rotor at rest is left alone."""

import math

import jax
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.__main__ import main
from pmsmjax.observers import make_observer, observer_names


DRIVE = pj.preset("zhang750")
W = float(DRIVE.w_rated)
TAU = float(DRIVE.tau_rated)
# rotor turning from the first sample at the set-point, a half-load step at 0.15 s
LOAD = pj.Profile([0.0, 0.15, 0.16, 0.3], [0.0, 0.0, 0.5 * TAU, 0.5 * TAU])
# largest |angle error - the static error| at the end (deg), measured at either sign of
# speed: ripple and what is left of the load step's transient. The test allows three
# times it, at most 2 deg.
MEASURED_DEG = {"eso": 0.24, "leso": 0.24, "afo": 0.26, "parallel-model": 1.81,
                "rotor-flux": 0.022, "c-leso": 0.24, "gi-leso": 0.19, "fa-leso": 0.16,
                "reduced-order": 0.35, "nonlinear-flux": 0.222}


def _closed_loop(obs, speed_pu):
    sc = pj.Scenario(t_end=0.3, w_m_ref=pj.Profile.constant(speed_pu * W), tau_L=LOAD)
    return pj.simulate(DRIVE, pj.FOC.from_drive(DRIVE), obs, sc, theta0=0.0,
                       w_m0=speed_pu * W, theta_hat0=2.0, w_hat0=0.0, throw=False)


@pytest.mark.parametrize("name", observer_names())
def test_every_observer_is_caught_on_a_turning_rotor_in_the_closed_loop(name):
    inner = make_observer(name, DRIVE)
    for speed_pu in (0.5, -0.3):
        tr = _closed_loop(pj.FlyingCatch(inner), speed_pu)
        assert bool(tr.ok)
        t, err = np.asarray(tr.t), np.asarray(tr.theta_err)
        st = pj.lock_status(t, err)
        assert bool(st["acquired"]) and not bool(st["lost"]), (speed_pu, st)
        # at once: within the catch window (64 samples, 8 ms; measured: 5 ms or less)
        assert float(st["t_acquired"]) < 64 * 125e-6
        end = t > 0.25
        op = analysis.OperatingPoint(speed_pu * W, np.asarray(tr.i_dq)[end].mean(0))
        design = float(inner.designed_error(op, DRIVE.three_phase_motor)[
            inner.coordinates.angle])
        dev = np.abs(np.asarray(pj.wrap_angle(err[end] - design)))
        tol = math.radians(min(3 * MEASURED_DEG[name], 2.0))
        assert dev.max() < tol, (speed_pu, math.degrees(dev.max()))
        # the speed loop's set-point after the load step (measured: within 1.6 %)
        assert abs(float(tr.w_m[-1]) / (speed_pu * W) - 1.0) < 0.02


@pytest.mark.parametrize("name", ["leso", "afo"])
def test_without_the_catch_the_flux_observers_never_lock(name):
    """The same start without the wrapper: the estimate slips or sits in the false lock,
    and the drive does not reach its set-point."""
    tr = _closed_loop(make_observer(name, DRIVE), 0.5)
    late = np.asarray(tr.t) > 0.2
    assert np.degrees(np.abs(np.asarray(tr.theta_err)[late])).mean() > 45.0
    assert abs(float(tr.w_m[-1]) / (0.5 * W) - 1.0) > 0.2


def _recording(speed_pu, t_end=0.05):
    sc = pj.Scenario(t_end=t_end, w_m_ref=pj.Profile.constant(speed_pu * W))
    return pj.simulate(DRIVE, pj.FOC.from_drive(DRIVE), pj.SensoredObserver(), sc,
                       theta0=1.0, w_m0=speed_pu * W, sensing=pj.Sensing(noise_std=0.01),
                       key=jax.random.PRNGKey(0))


def test_the_caught_estimate_is_the_flying_starts():
    n = 64
    tr = _recording(0.4)
    obs = make_observer("eso", DRIVE)
    est = pj.replay_estimates(pj.FlyingCatch(obs, n=n), tr, theta0=0.0, w0=0.0)
    fs = pj.flying_start(DRIVE.three_phase_motor, tr.u_ab, tr.i_meas_ab, 125e-6, n=n)
    # the flying start's angle at t_0, advanced to t_n at its speed
    want = float(pj.wrap_angle(float(fs.theta0) + n * 125e-6 * float(fs.w0)))
    # measured: 0.49 deg (the angle the estimate moved in its step after the window),
    # the speeds equal, the flying start's speed within 0.26 % of the rotor's
    assert abs(float(pj.wrap_angle(float(est.theta_hat[n]) - want))) < math.radians(1.0)
    assert float(est.w_hat[n]) == pytest.approx(float(fs.w0), rel=1e-9)
    assert float(fs.w0) == pytest.approx(0.4 * W, rel=8e-3)


def test_a_rotor_at_rest_is_left_alone():
    sc = pj.Scenario(t_end=0.03, i_d_ref=pj.Profile.constant(0.0),
                     i_q_ref=pj.Profile.constant(2.0), w_m_imposed=pj.Profile.constant(0.0))
    tr = pj.simulate(DRIVE, pj.FOC.from_drive(DRIVE), pj.SensoredObserver(), sc, theta0=1.0)
    obs = make_observer("leso", DRIVE)
    a = pj.replay_estimates(pj.FlyingCatch(obs), tr, theta0=0.3, w0=0.0)
    b = pj.replay_estimates(obs, tr, theta0=0.3, w0=0.0)
    np.testing.assert_array_equal(np.asarray(a.theta_hat), np.asarray(b.theta_hat))
    np.testing.assert_array_equal(np.asarray(a.w_hat), np.asarray(b.w_hat))


def test_bad_arguments():
    obs = make_observer("eso", DRIVE)
    with pytest.raises(ValueError, match="n=.*int >= 3"):
        pj.FlyingCatch(obs, n=2)
    with pytest.raises(ValueError, match="must be an observer"):
        pj.FlyingCatch(DRIVE)
    with pytest.raises(ValueError, match="must be an observer"):
        pj.FlyingCatch(pj.FlyingCatch(obs))


def test_cli_simulate_catches_a_turning_rotor_by_default(tmp_path, capsys):
    import json

    for startup, status in (("auto", "successful"), ("none", "never locked")):
        out = tmp_path / startup
        assert main(["simulate", "--observer", "leso", "--scenario", "load-step",
                     "--theta-hat0", "115", "--speed-hat0", "0", "--t-end", "0.2",
                     "--startup", startup, "--no-plot", "--out", str(out)]) == 0
        summary = json.loads((out / "summary.json").read_text())
        assert summary["status"] == status, summary["status"]
    assert "start-up: catch" in capsys.readouterr().out
