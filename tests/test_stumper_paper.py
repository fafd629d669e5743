"""`pmsmjax.papers.stumper`: the closed-loop experiments (Figs. 3-5) and the ramp lag,
simulated numbers against the published ones where the model can be compared."""

import math

import numpy as np
import pytest

from pmsmjax.papers import stumper


def test_fig5_feedforward_sign_and_speedup():
    """No load, reference ramped at the current-limited acceleration: the corrected
    feedforward (48) commands a negative d current and reaches the slope of the
    reference, steeper than without it by the ratio of the torques the two current
    vectors make (the paper reports about 17 %); the printed
    sign commands a positive d current and is slower than no feedforward at all."""
    kw = dict(t_end=0.16)
    plain = stumper.acceleration(0.0, feedforward=False, **kw).summary
    ff = stumper.acceleration(0.0, feedforward=True, **kw).summary
    printed = stumper.acceleration(0.0, feedforward=True, printed_sign=True, **kw).summary
    assert plain["ok"] and ff["ok"] and printed["ok"]
    assert ff["i_d_ref_min_A"] < -2.0 and printed["i_d_ref_min_A"] >= 0.3
    speedup = ff["slope_rpm_s"] / plain["slope_rpm_s"] - 1
    # a second route, the mechanics: without load J dw/dt = tau_M - B w, so the slope
    # ratio is the ratio of the mean electromagnetic torque over the same speed band
    # (the reluctance torque of the negative d current under the same current limit);
    # measured 16.50 % against 16.59 % (the friction term B w differs slightly)
    taus, accs = [], []
    for feedforward in (True, False):
        tr = stumper.acceleration(0.0, feedforward=feedforward, **kw).traj
        wm = np.asarray(tr.w_m)
        w0, w1 = 300 * stumper.RPM, 3000 * stumper.RPM
        band = (wm >= w0 + 0.1 * (w1 - w0)) & (wm <= w0 + 0.9 * (w1 - w0))
        taus.append(np.asarray(tr.tau_M)[band].mean())
        accs.append(np.polyfit(np.asarray(tr.t)[band], wm[band], 1)[0])  # rad/s^2, el.
    assert speedup > 0.05
    assert speedup == pytest.approx(taus[0] / taus[1] - 1, abs=0.005)
    assert printed["slope_rpm_s"] < plain["slope_rpm_s"]
    assert ff["t_setpoint_s"] < plain["t_setpoint_s"]
    assert not printed["t_setpoint_s"] < plain["t_setpoint_s"]  # NaN: not reached
    # the largest lag of the tracking filter is (39)'s acc / v1 at the acceleration the
    # drive reached (fitted over the 10-90 % band; the paper's figure shows about 35 deg):
    # measured 34.91 against 34.73 deg, 0.5 %; 2 % as the sensored test of (39) in
    # test_parallel_model.py (the filter's settling and the 7 mH model's static offset)
    v1 = float(stumper.ParallelModelObserver.from_drive(stumper.preset("stumper_mt5"),
                                                        L_hat=7e-3).v1)
    assert ff["theta_err_max_deg"] == pytest.approx(-math.degrees(accs[0] / v1), rel=0.02)


def test_fig3_low_speed_full_load_is_held():
    """100 rpm at 95 % of the current-limited torque, encoderless, with the paper's single
    7 mH: the drive holds speed; the offset is the closed form's for the 0.2 mH error
    against L_q (the paper measures about 7 deg on its test bench)."""
    r = stumper.steady_state(100.0, t_end=0.3)
    s = r.summary
    assert s["ok"] and s["speed_ripple_rpm"] < 0.1
    tr = r.traj
    i_rot = np.asarray(tr.i_dq)[-400:].mean(0)
    m = stumper.preset("stumper_mt5").three_phase_motor
    want = math.degrees(float(stumper.parallel_model_offset(
        m, 0.0, 7e-3 - float(m.L_q), 100 * stumper.RPM, i_rot)))
    assert s["theta_err_mean_deg"] == pytest.approx(want, abs=0.01)
