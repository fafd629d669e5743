"""Replays that start as real logs do, for every registered observer with its default
design on zhang750 and the default (unknown) initial estimate: a rotor at rest that then
accelerates, a rotor turning from the first sample, and a reversal through zero speed,
each recorded by a sensored drive with the rotor at 2 rad (the observer does not know
it). Every observer acquires the lock, keeps it (through the reversal it may lose it
only inside its low-speed band around zero speed, and regains it), never produces a
non-finite estimate, and at constant speed after the lock its angle error is the static
error its analysis predicts (`designed_error`: the C-LESO's and GI-LESO's phase lag, zero
for the others)."""

import math

import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import make_observer, observer_names


DRIVE = pj.preset("zhang750")
W = float(DRIVE.w_rated)
T_S = 1e-4
THETA0 = 2.0  # rad: the rotor's angle at the first sample
# (scenario, rotor speed at the first sample, constant-speed window (s) and its speed).
# All three as long as the reversal (0.8 s) and with speed profiles of four breakpoints:
# one compiled simulation for the three recordings and one compiled replay per observer
# for all three (instead of three); the constant-speed windows are those of the shorter
# runs they replaced (the standstill run's 0.6 s, the turning run's 0.4 s)
RECORDINGS = {
    "standstill-then-ramp": (pj.Scenario(t_end=0.8, w_m_ref=pj.Profile(
        [0.0, 0.1, 0.4, 0.6], [0.0, 0.0, 0.5 * W, 0.5 * W])), 0.0, (0.5, 0.6), 0.5 * W),
    "turning": (pj.Scenario(t_end=0.8, w_m_ref=pj.Profile(
        [0.0, 0.2, 0.5, 0.8], [0.3 * W] * 4)), 0.3 * W, (0.3, 0.4), 0.3 * W),
    "reversal": (pj.Scenario(t_end=0.8, w_m_ref=pj.Profile(
        [0.0, 0.2, 0.5, 0.8], [0.5 * W, 0.5 * W, -0.5 * W, -0.5 * W])), 0.5 * W,
        (0.7, 0.8), -0.5 * W),
}
# Where a back-EMF observer may lose the lock in a reversal: |w_m| below this (the band
# where the back-EMF is too small to read; measured on zhang750: 0.05 p.u. for the
# zhang2022 LESO and AFO and the rotor-flux observer, docs/lock-and-startup.md), with the
# lock's 10 ms window and the reversal's rate (2 p.u. in 0.3 s) added
LOW_SPEED = 0.1 * W
# Allowance around the static error at constant speed after the lock (rad): what is left
# of the transients (the GI-LESO's generalised integrator decays at w_c, 4 pi rad/s on
# zhang750) and the current ripple of the recording
TOL = math.radians(1.0)


@pytest.fixture(scope="module")
def recordings():
    out = {}
    for name, (sc, w0, _, _) in RECORDINGS.items():
        out[name] = pj.simulate(DRIVE, pj.FOC.from_drive(DRIVE), pj.SensoredObserver(), sc,
                                T_s=T_S, theta0=THETA0, w_m0=w0)
    return out


@pytest.mark.parametrize("rec", list(RECORDINGS))
@pytest.mark.parametrize("name", observer_names())
def test_replay_from_an_unknown_start_locks_and_keeps_the_static_error(recordings, rec,
                                                                        name):
    tr = recordings[rec]
    obs = make_observer(name, DRIVE)
    th, wh = pj.replay(obs, tr)
    th, wh = np.asarray(th), np.asarray(wh)
    assert np.all(np.isfinite(th)) and np.all(np.isfinite(wh))
    t = np.asarray(tr.t)
    err = np.asarray(pj.wrap_angle(np.asarray(tr.theta) - th))
    st = {k: float(v) for k, v in pj.lock_status(t, err).items()}
    assert st["acquired"]
    w_m = np.asarray(tr.w_m)
    if rec == "reversal" and st["lost"]:
        # lost only inside the low-speed band, and locked again at the end
        k = int(np.searchsorted(t, st["t_lost"]))
        assert abs(w_m[k]) < LOW_SPEED, (st, w_m[k] / W)
        again = pj.lock_status(t[k:], err[k:])
        assert bool(again["acquired"]) and not bool(again["lost"])
    else:
        assert not st["lost"], st
    (t0, t1), w = RECORDINGS[rec][2], RECORDINGS[rec][3]
    m = (t >= t0) & (t < t1)
    op = analysis.OperatingPoint(w, np.asarray(tr.i_dq)[m].mean(0))
    design = float(obs.designed_error(op, DRIVE.three_phase_motor)[obs.coordinates.angle])
    dev = np.abs(np.asarray(pj.wrap_angle(err[m] - design)))
    assert dev.max() < TOL, (math.degrees(dev.max()), math.degrees(design))


def test_unknown_start_reads_a_turning_rotor_and_not_one_at_rest(recordings):
    """`initial_estimate`: on the recording turning from the first sample the flying
    start's angle and speed (within 1 deg and 1 %); at rest zero."""
    obs = make_observer("eso", DRIVE)
    th, w, turning = pj.initial_estimate(obs, recordings["turning"])
    assert bool(turning)
    assert abs(float(pj.wrap_angle(float(th) - THETA0))) < math.radians(1.0)
    assert float(w) == pytest.approx(0.3 * W, rel=1e-2)
    th, w, turning = pj.initial_estimate(obs, recordings["standstill-then-ramp"])
    assert not bool(turning) and float(th) == 0.0 and float(w) == 0.0
    # given values are used as they are: from zero speed the ESO ends in its false lock
    th, _ = pj.replay(obs, recordings["turning"], theta0=0.0, w0=0.0)
    t = np.asarray(recordings["turning"].t)
    err = np.asarray(pj.wrap_angle(np.asarray(recordings["turning"].theta) - np.asarray(th)))
    assert not bool(pj.lock_status(t, err)["acquired"]) or \
        bool(pj.lock_status(t, err)["lost"])


@pytest.mark.parametrize("bad, fragment", [("u_ab", "`u_ab` (V) is not finite at sample 7"),
                                           ("i_ab", "`i_ab` (A) is not finite at sample 7"),
                                           ("theta0", "theta0"), ("w0", "w0")])
def test_non_finite_inputs_raise_a_named_error(recordings, bad, fragment):
    tr = recordings["turning"]
    obs = make_observer("eso", DRIVE)
    u = np.array(tr.u_ab)
    i = np.array(tr.i_meas_ab)
    kw = {}
    if bad == "u_ab":
        u[7, 1] = np.nan
    elif bad == "i_ab":
        i[7, 0] = np.inf
    else:
        kw[bad] = np.nan
    with pytest.raises(pj.NonFiniteInputError, match=fragment.replace("(", r"\(")
                       .replace(")", r"\)")):
        pj.replay(obs, np.asarray(tr.t), u, i, **kw)


@pytest.mark.parametrize("arg", ["theta0", "w_m0", "theta_hat0", "w_hat0", "i_dq0"])
def test_simulate_names_a_non_finite_initial_value(arg):
    sc = pj.Scenario(t_end=0.01, w_m_ref=pj.Profile.constant(100.0))
    value = (np.nan, 0.0) if arg == "i_dq0" else np.inf
    with pytest.raises(pj.NonFiniteInputError, match=rf"simulate\({arg}=\.\.\.\)"):
        pj.simulate(DRIVE, pj.FOC.from_drive(DRIVE), make_observer("eso", DRIVE), sc,
                    **{arg: value})


def test_replay_inside_jit_with_the_recording_closed_over(recordings):
    """The default start and the input checks trace: a jitted replay (the recording
    closed over, the design traced) equals the plain one."""
    import jax

    tr = recordings["turning"]
    t, u, i = np.asarray(tr.t), np.asarray(tr.u_ab), np.asarray(tr.i_meas_ab)
    obs = make_observer("eso", DRIVE)
    plain = np.asarray(pj.replay(obs, t, u, i)[0])
    jitted = np.asarray(jax.jit(lambda o: pj.replay(o, t, u, i)[0])(obs))
    np.testing.assert_allclose(jitted, plain, atol=1e-9)
