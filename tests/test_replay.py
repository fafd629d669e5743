"""Offline replay of observers over recorded data, from Python and the command line."""

import json
import math

import equinox as eqx
import jax
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.__main__ import main


DRIVE = pj.preset("zhang750")
M = DRIVE.motor
WR = float(DRIVE.w_rated)
THETA_HAT0 = -math.radians(20.0)


def _observers(drive):
    return {"eso": pj.ESOObserver.from_drive(drive), "leso": pj.LESOObserver.from_drive(drive),
            "afo": pj.AFOObserver.from_drive(drive, w2=2 * math.pi * 80)}


def _run(observer, drive=DRIVE, observer_scale=None):
    sc = pj.Scenario(t_end=0.4, w_m_ref=pj.Profile.ramp(0.0, 0.15, 0.0, 0.3 * WR),
                     tau_L=pj.Profile.constant(0.2 * float(drive.tau_rated)),
                     observer_scale=observer_scale)
    return pj.simulate(drive, pj.FOC.from_drive(drive), observer, sc, theta_hat0=THETA_HAT0,
                       w_hat0=0.0, sensing=pj.Sensing(noise_std=0.02),
                       key=jax.random.PRNGKey(3))


@pytest.fixture(scope="module")
def traces():
    return {k: _run(obs) for k, obs in _observers(DRIVE).items()}


@pytest.mark.parametrize("kind", ["eso", "leso", "afo"])
def test_replay_reproduces_the_in_loop_estimates(traces, kind):
    """The observer in the loop and the replay see the same (i_ab[k], u_ab[k-1]) and do
    the same arithmetic: the estimates agree to 1e-12 (in practice bitwise, apart from
    the AFO's speed output, whose fused arithmetic may differ in the last bit)."""
    traj = traces[kind]
    obs = _observers(DRIVE)[kind]
    assert bool(traj.ok)
    th, w = pj.replay(obs, traj, theta0=THETA_HAT0, w0=0.0)
    np.testing.assert_allclose(th, traj.theta_hat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w, traj.w_hat, rtol=1e-13, atol=1e-12)
    # through the recorded-data format (NPZ and CSV round trips are exact)
    data = pj.RecordedData.from_trajectory(traj)
    th2, w2 = pj.replay(obs, data, theta0=THETA_HAT0)
    np.testing.assert_allclose(th2, traj.theta_hat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w2, traj.w_hat, rtol=1e-13, atol=1e-12)
    # a different initial angle gives a different result: the comparison can fail
    th3, _ = pj.replay(obs, data, theta0=0.0)
    assert np.max(np.abs(np.asarray(th3) - np.asarray(traj.theta_hat))) > 1e-3


def test_replay_reproduces_a_run_with_delay_and_a_mismatch_step():
    drive = eqx.tree_at(lambda d: d.inverter, DRIVE, pj.Inverter(u_dc=311.0, delay=True))
    obs = pj.ESOObserver.from_drive(drive)
    prof = pj.Profile.steps([0.2], [0.7], 1.0)
    traj = _run(obs, drive, observer_scale={"L_q": prof, "R_s": prof})
    scale = np.asarray(prof(traj.t))
    th, w = pj.replay(obs, traj, theta0=THETA_HAT0, observer_scale={"L_q": scale,
                                                                      "R_s": scale})
    np.testing.assert_allclose(th, traj.theta_hat, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w, traj.w_hat, rtol=1e-13, atol=1e-12)
    th_no, _ = pj.replay(obs, traj, theta0=THETA_HAT0)
    assert np.max(np.abs(np.asarray(th_no) - np.asarray(traj.theta_hat))) > 1e-3


def test_replay_vmaps_over_recordings(traces):
    """A batch of recordings (here: the same run with shifted noise) in one call."""
    traj = traces["eso"]
    obs = _observers(DRIVE)["eso"]
    key = jax.random.PRNGKey(0)
    noise = 0.05 * jax.random.normal(key, (4,) + traj.i_meas_ab.shape)
    i_batch = traj.i_meas_ab[None] + noise
    th, w = jax.vmap(lambda i: pj.replay(obs, traj.t, traj.u_ab, i, theta0=THETA_HAT0))(
        i_batch)
    assert th.shape == (4, traj.t.shape[0])
    for b in range(4):
        th_b, w_b = pj.replay(obs, traj.t, traj.u_ab, i_batch[b], theta0=THETA_HAT0)
        np.testing.assert_allclose(th[b], th_b, atol=1e-12)
        np.testing.assert_allclose(w[b], w_b, rtol=1e-12, atol=1e-9)


def test_replay_stats_numbers():
    t = np.arange(1000) * 1e-3
    theta = np.zeros(1000)
    err = np.where(t < 0.3, 0.5, 0.01 * np.sin(2 * np.pi * 10 * t) + 0.002)
    stats = pj.replay_stats(t, theta - err, np.full(1000, 9.0), theta, np.full(1000, 10.0),
                            t_settle=0.5, tol_deg=2.0)
    e = np.degrees(err[t >= 0.5])
    assert stats["n_samples"] == 500
    assert stats["theta_err_mean_deg"] == pytest.approx(np.mean(e))
    assert stats["theta_err_std_deg"] == pytest.approx(np.std(e))
    assert stats["theta_err_max_deg"] == pytest.approx(np.max(np.abs(e)))
    assert stats["t_converge_s"] == pytest.approx(0.3)
    assert stats["w_err_mean"] == pytest.approx(1.0) and stats["w_err_std"] == 0.0
    # wrapped errors: an estimate 2 pi + 0.1 rad away is 0.1 rad away
    s2 = pj.replay_stats(t, theta - 0.1 - 2 * np.pi, np.zeros(1000), theta)
    assert s2["theta_err_mean_deg"] == pytest.approx(math.degrees(0.1))
    with pytest.raises(ValueError, match="t_settle"):
        pj.replay_stats(t, theta, theta, theta, t_settle=5.0)
    assert math.isnan(float(pj.settling_time(t, np.ones(1000), 0.5)))


def test_replay_input_errors():
    obs = pj.ESOObserver.from_drive(DRIVE)
    t = np.arange(10) * 1e-4
    with pytest.raises(ValueError, match="u_ab"):
        pj.replay(obs, t, np.zeros((9, 2)), np.zeros((10, 2)))
    with pytest.raises(ValueError, match="AbstractObserver"):
        pj.replay(DRIVE, t, np.zeros((10, 2)), np.zeros((10, 2)))
    with pytest.raises(ValueError, match="T_s"):
        pj.replay(obs, None, np.zeros((10, 2)), np.zeros((10, 2)))
    with pytest.raises(ValueError, match="i_ab"):
        pj.replay(obs, pj.RecordedData(t=t, u_ab=np.zeros((10, 2))))


# ---------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def recording(tmp_path_factory, traces):
    d = tmp_path_factory.mktemp("rec")
    data = pj.RecordedData.from_trajectory(traces["eso"])
    pj.save_recording(d / "run.npz", data)
    pj.save_recording(d / "run.csv", data)
    return d, data


@pytest.mark.parametrize("kind,ext", [("eso", "npz"), ("leso", "csv"), ("afo", "npz")])
def test_cli_replay_end_to_end(recording, tmp_path, kind, ext, capsys):
    d, data = recording
    out = tmp_path / "out"
    argv = ["replay", "--motor", "zhang750", "--observer", kind, "--data",
            str(d / f"run.{ext}"), "--out", str(out), "--t-settle", "0.3"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "angle error after 0.3 s" in printed
    for name in ("replay.npz", "stats.json", "replay.png"):
        assert (out / name).stat().st_size > 0
    res = pj.load_recording(out / "replay.npz", require=("t", "theta_hat", "w_hat"))
    obs = pj.observers.make_observer(kind, DRIVE)
    th, w = pj.replay(obs, data)  # zero initial angle and speed, default gains
    np.testing.assert_allclose(res.theta_hat, th, atol=1e-12)
    np.testing.assert_allclose(res.w_hat, w, rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(res.theta, data.theta)
    stats = json.loads((out / "stats.json").read_text())
    want = pj.replay_stats(data.t, th, w, data.theta, data.w_m, t_settle=0.3)
    for key in ("theta_err_mean_deg", "theta_err_std_deg", "theta_err_max_deg",
                "w_err_mean", "w_err_std", "w_err_max"):
        assert stats[key] == pytest.approx(want[key], rel=1e-9, abs=1e-12)
    assert stats["observer"] == kind and stats["motor"] == "zhang750"
    # the observer started from 0 while the drive's estimate started at -20 deg
    assert abs(stats["theta_err_mean_deg"]) < 0.5


def test_cli_replay_gain_overrides(recording, tmp_path):
    d, data = recording
    out = tmp_path / "o"
    assert main(["replay", "--observer", "eso", "--data", str(d / "run.npz"), "--out",
                 str(out), "--bandwidth", "120", "--a", "0.7", "--eta", "0.004",
                 "--theta0", "-20", "--no-plot"]) == 0
    assert not (out / "replay.png").exists()
    obs = pj.ESOObserver(M, pj.ESODesign.zhang38(WR, 2 * math.pi * 120), a=0.7, eta=0.004)
    th, _ = pj.replay(obs, data, theta0=math.radians(-20))
    res = pj.load_recording(out / "replay.npz", require=("theta_hat",))
    np.testing.assert_allclose(res.theta_hat, th, atol=1e-12)
    # --fixed-at freezes the gains; --set changes the observer's model
    out2 = tmp_path / "o2"
    assert main(["replay", "--observer", "leso", "--data", str(d / "run.npz"), "--out",
                 str(out2), "--fixed-at", "0.2", "--set", "L_q=2.0e-3", "--no-plot"]) == 0
    m2 = eqx.tree_at(lambda p: p.L_q, M, 2.0e-3)
    obs2 = pj.LESOObserver(m2, pj.FixedGains.at(pj.ESODesign.zhang38(WR), m2, 0.2 * WR))
    th2, _ = pj.replay(obs2, data)
    res2 = pj.load_recording(out2 / "replay.npz", require=("theta_hat",))
    np.testing.assert_allclose(res2.theta_hat, th2, atol=1e-12)


@pytest.mark.parametrize("extra,fragment", [
    (["--observer", "kalman"], "invalid choice"),
    (["--zeta2", "-1"], "zeta2"),
    (["--bandwidth", "0"], "--bandwidth: '0' must be a finite number > 0"),
    (["--a", "1.5"], "`a`|a="),
    (["--eta", "-0.1"], "eta"),
    (["--schedule", "fixed_ratio"], "zeta1"),
])
def test_cli_replay_bad_arguments(recording, tmp_path, capsys, extra, fragment):
    d, _ = recording
    argv = ["replay", "--data", str(d / "run.npz"), "--out", str(tmp_path / "x"), *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    import re

    assert re.search(fragment, err), err


def test_cli_replay_needs_currents(tmp_path, capsys):
    path = tmp_path / "u_only.npz"
    np.savez(path, t=np.arange(10) * 1e-4, u_ab=np.zeros((10, 2)))
    assert main(["replay", "--data", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "i_ab" in capsys.readouterr().err
