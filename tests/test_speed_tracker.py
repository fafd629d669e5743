"""`SpeedFromAngle`: the speed a drive takes from an observer's angle estimate (its
closed loop on the saturated preset: tests/test_saturated_analysis.py)."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.cli import main as cli_main
from pmsmjax.observers import make_observer


T_S = 125e-6


def _track(observer, theta, w):
    """The wrapper's outputs over an angle sequence `theta` (rad) with speed `w` (rad/s)
    handed to it as measurements (the sensored inner observer passes them through)."""
    def step(state, x):
        th, wm = x
        meas = pj.Measurement(i_ab=jnp.zeros(2), u_ab=jnp.zeros(2), theta=th, w_m=wm)
        state, est = observer.step(state, meas, T_S)
        return state, (est.theta_hat, est.w_hat, est.extras["w_observer"])

    state0 = observer.init(theta0=theta[0], w0=w[0])
    return jax.lax.scan(step, state0, (jnp.asarray(theta), jnp.asarray(w)))[1]


def _numpy_tracker(theta, w0, w_track, zeta):
    """The tracking loop of the module docstring, a plain loop (the reference)."""
    k_p, k_i = 2 * zeta * w_track, w_track ** 2
    th, w, out = theta[0], w0, []
    for x in theta:
        pred = th + T_S * w
        e = math.remainder(x - pred, 2 * math.pi)
        w = w + T_S * k_i * e
        th = math.remainder(pred + T_S * k_p * e, 2 * math.pi)
        out.append(w)
    return np.array(out)


def test_the_tracker_is_its_discrete_loop_and_lags_a_ramp_by_its_closed_form():
    """A speed ramp a = 2000 rad/s^2 from 50 rad/s over 0.2 s, angles wrapped: the
    wrapper's speed equals a plain loop of the module docstring's equations to round-off,
    its angle is the inner observer's unchanged, and the speed lags the ramp by the
    type-2 loop's 2 zeta a / w_track (here 21.2 rad/s; measured 0.59 % under it once the
    start has died out, the loop's discretisation at T_s w_track = 0.024; tested at 3x)."""
    a, w_track, zeta = 2000.0, 188.5, 1.0
    t = np.arange(1600) * T_S
    w = 50.0 + a * t
    theta = np.remainder(50.0 * t + 0.5 * a * t ** 2 + np.pi, 2 * np.pi) - np.pi
    obs = pj.SpeedFromAngle(pj.SensoredObserver(), w_track=w_track, zeta=zeta)
    th_hat, w_hat, w_obs = (np.asarray(x) for x in _track(obs, theta, w))
    np.testing.assert_array_equal(th_hat, theta)
    np.testing.assert_array_equal(w_obs, w)
    np.testing.assert_allclose(w_hat, _numpy_tracker(theta, w[0], w_track, zeta),
                               rtol=0, atol=1e-9)
    lag = (w - w_hat)[t > 0.1]
    np.testing.assert_allclose(lag, 2 * zeta * a / w_track, rtol=0.018)


def test_bad_wrappers_are_named():
    obs = make_observer("rotor-flux", pj.preset("morawiec_ipm3k5"))
    for bad in (dict(w_track=0.0), dict(w_track=-1.0), dict(zeta=0.0),
                dict(w_track=float("nan"))):
        with pytest.raises(ValueError, match="SpeedFromAngle"):
            pj.SpeedFromAngle(obs, **bad)
    with pytest.raises(ValueError, match="must be an observer"):
        pj.SpeedFromAngle(pj.SpeedFromAngle(obs))
    with pytest.raises(ValueError, match="wraps an observer"):
        pj.SpeedFromAngle.from_drive(pj.preset("morawiec_ipm3k5"))
    # the wrapper keeps itself through a new design or model, and a catch wraps it
    tracked = pj.SpeedFromAngle(obs, w_track=100.0)
    assert isinstance(tracked.with_motor(obs.motor), pj.SpeedFromAngle)
    assert tracked.with_design().w_track == 100.0
    assert pj.FlyingCatch(tracked).observer is tracked
    assert cli_main(["simulate", "--speed-from-angle", "--t-end", "0.1", "--no-plot"]) == 2


def test_export_c_generates_the_tracked_speed(tmp_path, capsys):
    """`pmsmjax export-c --speed-from-angle`: the header says that w_hat is the tracked
    speed, with the loop's gains (the C against replay: tests/test_firmware.py,
    "afo-tracked")."""
    out = tmp_path / "fw"
    assert cli_main(["export-c", "--observer", "afo", "--speed-from-angle", "20",
                     "--out", str(out)]) == 0
    assert "speed from its angle (20 Hz tracking loop)" in capsys.readouterr().out
    header = (out / "pmsm_observer.h").read_text()
    w_t = 2 * math.pi * 20.0
    assert "speed from its angle (SpeedFromAngle)" in header
    assert f"k_p = 2 zeta w_track = {2 * w_t!r} rad/s" in header
    assert "trk_w" in header


def test_replay_gives_the_tracked_speed(tmp_path, capsys):
    """`pmsmjax replay --speed-from-angle HZ`: the replayed w_hat is the speed of the
    observer's angle through the tracking loop, as `replay_estimates` of the wrapped
    observer gives it (the same start the command chooses), and the first line and
    stats.json say so; the angle is the observer's own."""
    drive = pj.preset("zhang750")
    w = 0.3 * float(drive.w_rated)
    sc = pj.Scenario(t_end=0.15, w_m_ref=pj.Profile.constant(w))
    traj = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver(), sc, T_s=T_S,
                       theta0=0.4, w_m0=w)
    data = pj.RecordedData.from_trajectory(traj)
    pj.save_recording(tmp_path / "run.npz", data)
    outs = {}
    for name, extra in (("own", []), ("tracked", ["--speed-from-angle", "20"])):
        out = tmp_path / name
        assert cli_main(["replay", "--data", str(tmp_path / "run.npz"), "--observer", "afo",
                         "--theta0", "23", "--speed0", "0.3", *extra, "--no-plot", "--out",
                         str(out)]) == 0
        outs[name] = np.load(out / "replay.npz")
    printed = capsys.readouterr().out
    assert "speed from its angle (20 Hz tracking loop)" in printed
    obs = make_observer("afo", drive)
    ref = pj.replay_estimates(pj.SpeedFromAngle(obs, w_track=2 * math.pi * 20.0), data,
                              theta0=math.radians(23.0), w0=w)
    np.testing.assert_allclose(outs["tracked"]["w_hat"], np.asarray(ref.w_hat), rtol=0,
                               atol=1e-9 * w)
    np.testing.assert_array_equal(outs["tracked"]["theta_hat"], outs["own"]["theta_hat"])
    assert np.max(np.abs(outs["tracked"]["w_hat"] - outs["own"]["w_hat"])) > 1e-3 * w
    stats = json.loads((tmp_path / "tracked" / "stats.json").read_text())
    assert stats["speed_from_angle_Hz"] == 20.0
