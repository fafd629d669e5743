"""`pmsmjax convert` / `convert_log`: logs as loggers write them.

The reference recording is made here with NumPy (a machine at constant speed and dq
current, its voltages the exact zero-order-hold flux increments), and each logger layout
is written from it by NumPy code of this file (inverse Clarke, duty cycles with a common
mode, ADC counts, encoder counts and offsets, time in ms or us, a one-sample voltage
delay): the converter, which shares none of it, must give the reference back.
"""

import json
import math
import pathlib

import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.cli import main


DRIVE = pj.preset("zhang750")
M = DRIVE.three_phase_motor
N_P = float(M.n_p)
T_S = 125e-6
N = 800
W = 0.3 * float(DRIVE.w_rated)  # rad/s electrical
I_DQ = (-0.5, 3.0)  # A
OFFSET_MECH_DEG = 12.3


def reference(noise=0.0, seed=0, ramp=0.0):
    """(t, theta, i_ab, u_ab, w_m) of a machine at constant dq current, its speed W (or a
    ramp from W to W (1 + ramp)), its voltages the exact flux increments over each period
    (R_s times the mean current)."""
    t = T_S * np.arange(N + 1)
    w = W * (1.0 + ramp * t / t[-1])
    theta = 0.4 + W * t + 0.5 * W * ramp * t ** 2 / t[-1]
    e = np.exp(1j * theta)
    i = (I_DQ[0] + 1j * I_DQ[1]) * e
    psi = (float(M.L_d) * I_DQ[0] + float(M.psi_f) + 1j * float(M.L_q) * I_DQ[1]) * e
    u = float(M.R_s) * 0.5 * (i[1:] + i[:-1]) + np.diff(psi) / T_S
    i = i[:-1] + noise * np.random.default_rng(seed).standard_normal((N, 2)) @ [1, 1j]
    ab = lambda z: np.stack([z.real, z.imag], axis=1)  # noqa: E731
    return t[:-1], theta[:-1], ab(i), ab(u), w[:-1]


def phases(x_ab):
    """Inverse amplitude-invariant Clarke (written here, not the package's)."""
    a = x_ab[:, 0]
    b = -0.5 * x_ab[:, 0] + math.sqrt(3) / 2 * x_ab[:, 1]
    return np.stack([a, b, -a - b], axis=1)


def write_csv(path, columns: dict, delimiter=","):
    names = list(columns)
    rows = np.stack([np.asarray(columns[n], float) for n in names], axis=1)
    with open(path, "w") as f:
        f.write(delimiter.join(names) + "\n")
        for r in rows:
            f.write(delimiter.join(repr(float(v)) for v in r) + "\n")


def logger_a(tmp_path, noise=0.0, **edit):
    """';'-separated, time in ms, two phase currents, duty cycles in percent with a
    common mode and a DC-bus column, mechanical encoder angle in degrees with an offset."""
    t, theta, i_ab, u_ab, _ = reference(noise)
    u_dc = 311.0 + 2.0 * np.sin(2 * np.pi * 100 * t)
    v = phases(u_ab)
    v = v - v.min(axis=1, keepdims=True) + 0.5 * (u_dc[:, None] - np.ptp(v, axis=1)[:, None])
    i3 = phases(i_ab)
    cols = {"time_ms": 1e3 * t, "ia": i3[:, 0], "ib": i3[:, 1],
            "da": 100 * v[:, 0] / u_dc, "db": 100 * v[:, 1] / u_dc,
            "dc": 100 * v[:, 2] / u_dc, "vbus": u_dc,
            "enc_deg": np.degrees(theta / N_P) % 360 + OFFSET_MECH_DEG}
    cols.update(edit)
    path = tmp_path / "a.csv"
    write_csv(path, cols, ";")
    layout = dict(time="time_ms", time_unit="ms", current=("ia", "ib"),
                  voltage=("da", "db", "dc"), voltage_frame="duty", voltage_u_dc="vbus",
                  voltage_scale=0.01, angle="enc_deg", angle_unit="mech_deg",
                  angle_offset=OFFSET_MECH_DEG, delimiter=";")
    return path, layout


def logger_b(tmp_path, **edit):
    """Time in us, currents as 12-bit ADC counts (zero at 2048, 0.01 A per count),
    alpha-beta voltages logged one sample before they apply, encoder counts (4096 per
    mechanical revolution, counting backwards), speed in rpm."""
    t, theta, i_ab, u_ab, w = reference()
    counts = np.round(2048 + phases(i_ab) / 0.01)
    u_log = np.vstack([u_ab[1:], u_ab[-1:]])  # row k logs the voltage applied at k + 1
    enc = np.round(-(theta / N_P) / (2 * np.pi) * 4096) % 4096
    cols = {"t_us": 1e6 * t, "adc_a": counts[:, 0], "adc_b": counts[:, 1],
            "adc_c": counts[:, 2], "v_alpha": u_log[:, 0], "v_beta": u_log[:, 1],
            "enc": enc, "rpm": w / N_P * 60 / (2 * np.pi)}
    cols.update(edit)
    path = tmp_path / "b.csv"
    write_csv(path, cols)
    layout = dict(time="t_us", time_unit="us", current=("adc_a", "adc_b", "adc_c"),
                  current_scale=0.01, current_offset=2048.0, current_adc_range=(0, 4095),
                  voltage=("v_alpha", "v_beta"), voltage_frame="alpha_beta",
                  voltage_delay=1, voltage_commanded=True, angle="enc",
                  angle_unit="counts", angle_counts_per_rev=4096, angle_direction=-1,
                  speed="rpm", speed_unit="rpm")
    return path, layout


def wrapped_deg(x):
    return np.degrees(np.remainder(x + np.pi, 2 * np.pi) - np.pi)


def test_duty_cycle_log_in_ms_with_an_encoder_offset(tmp_path):
    path, layout = logger_a(tmp_path)
    res = pj.convert_log(path, pj.LogLayout(**layout), drive=DRIVE)
    t, theta, i_ab, u_ab, w = reference()
    d = res.data
    assert d.n == N and res.dropped == 0 and res.commanded
    np.testing.assert_allclose(d.t, t, rtol=0, atol=1e-12)
    assert math.isclose(res.T_s, T_S, rel_tol=1e-9)
    np.testing.assert_allclose(d.i_ab, i_ab, rtol=0, atol=1e-9)
    np.testing.assert_allclose(d.u_ab, u_ab, rtol=0, atol=1e-7)
    assert np.max(np.abs(wrapped_deg(d.theta - theta))) < 1e-9
    np.testing.assert_allclose(d.w_m, w, rtol=1e-7)
    assert math.isclose(res.offset_removed_deg, N_P * OFFSET_MECH_DEG, rel_tol=1e-12)
    # the estimate from the voltages sees what is left after the layout's offset: nothing
    assert abs(res.offset_estimate_deg) < 1e-6 and not res.warnings
    assert any("--voltage commanded" in s for s in res.timing)


def test_encoder_offset_estimated_from_the_voltages(tmp_path):
    path, layout = logger_a(tmp_path, noise=0.02)
    raw = pj.convert_log(path, pj.LogLayout(**{**layout, "angle_offset": 0.0}), drive=DRIVE)
    # not removed: reported as a warning with the value, electrical degrees
    assert math.isclose(raw.offset_estimate_deg, N_P * OFFSET_MECH_DEG, abs_tol=0.1)
    assert any("offset" in w and "estimate" in w for w in raw.warnings)
    est = pj.convert_log(path, pj.LogLayout(**{**layout, "angle_offset": "estimate"}),
                         drive=DRIVE)
    assert est.offset_removed_deg == est.offset_estimate_deg
    _, theta, *_ = reference()
    assert np.max(np.abs(wrapped_deg(est.data.theta - theta))) < 0.1


def test_adc_counts_alpha_beta_delay_encoder_counts_and_rpm(tmp_path):
    path, layout = logger_b(tmp_path)
    res = pj.convert_log(path, pj.LogLayout(**layout), drive=DRIVE)
    t, theta, i_ab, u_ab, w = reference()
    d = res.data
    assert res.dropped == 1 and d.n == N - 1
    np.testing.assert_allclose(d.t, t[1:], atol=1e-12)
    np.testing.assert_allclose(d.u_ab, u_ab[1:N], atol=1e-9)  # row k logged u[k + 1]
    assert np.max(np.abs(d.i_ab - i_ab[1:])) <= 0.01 * 0.5 * 2  # half a count per phase
    lsb_deg = 360 / 4096 * N_P
    assert np.max(np.abs(wrapped_deg(d.theta - theta[1:]))) <= 0.5 * lsb_deg + 1e-9
    np.testing.assert_allclose(d.w_m, w[1:], rtol=1e-9)
    assert abs(res.offset_estimate_deg) < 0.5 * lsb_deg


def test_estimator_against_the_closed_form_of_a_phase_shift():
    """The back-EMF direction of exact flux increments is the mid-period angle: an angle
    offset comes back to round-off, at one speed (offset only) and on a speed ramp
    (offset and no voltage shift)."""
    for ramp in (0.0, 1.0):
        t, theta, i_ab, u_ab, w = reference(ramp=ramp)
        for shift_deg in (-170.0, -20.0, 0.0, 35.0, 179.0):
            data = pj.RecordedData(t=t, u_ab=u_ab, i_ab=i_ab, w_m=w, theta=np.remainder(
                theta + math.radians(shift_deg), 2 * np.pi))
            chk = pj.estimate_encoder_offset(data, M)
            assert abs(wrapped_deg(chk.offset - math.radians(shift_deg))) < 1e-9
            assert chk.spread < 1e-9 and chk.n == N - 1
            assert math.isnan(chk.shift) if ramp == 0 else abs(chk.shift) < 1e-6
    # turning backwards: the back-EMF leads by -90 deg
    t, theta, i_ab, u_ab, w = reference()
    data = pj.RecordedData(t=t, u_ab=u_ab * [1, -1], i_ab=i_ab * [1, -1],
                           theta=np.remainder(-theta + 0.3, 2 * np.pi), w_m=-w)
    assert abs(wrapped_deg(pj.estimate_encoder_offset(data, M).offset - 0.3)) < 1e-9


@pytest.mark.parametrize("k", [1, -1, 2])
def test_a_voltage_shift_is_told_from_an_offset_on_a_speed_ramp(k):
    """Voltages logged k samples before they apply (row j holds u[j + k]) on a ramp from
    0.3 to 0.6 p.u., with an encoder offset of 10 deg and current noise: the estimator
    finds both, and the warning names the shift; at one speed it cannot tell them apart
    and says so."""
    def shifted(noise):
        t, theta, i_ab, u_ab, w = reference(noise=noise, ramp=1.0)
        sl = slice(2, N - 2) if k < 0 else slice(0, N - 4)
        return pj.RecordedData(t=t[sl], u_ab=np.roll(u_ab, -k, axis=0)[sl], i_ab=i_ab[sl],
                               w_m=w[sl], theta=np.remainder(theta[sl] + math.radians(10.0),
                                                             2 * np.pi))

    exact = pj.estimate_encoder_offset(shifted(0.0), M)  # exact flux increments
    assert abs(exact.shift - k) < 1e-6 and abs(math.degrees(exact.offset) - 10.0) < 1e-6
    data = shifted(0.02)
    chk = pj.estimate_encoder_offset(data, M)
    assert abs(chk.shift - k) < 3 * chk.shift_std and chk.shift_std < 0.06  # measured 0.052
    assert abs(math.degrees(chk.offset) - 10.0) < 0.05  # measured 0.016 at most
    msgs = pj.recording_warnings(data, DRIVE)
    assert any(f"applied {abs(k)} period(s) {'after' if k > 0 else 'before'}" in m
               for m in msgs)
    assert any("+10." in m and "encoder offset" in m for m in msgs)
    # one speed: no shift, the offset includes it, and the warning says so
    t, theta, i_ab, u_ab, w = reference(noise=0.02)
    data = pj.RecordedData(t=t[:-2], u_ab=np.roll(u_ab, -1, axis=0)[:-2], i_ab=i_ab[:-2],
                           w_m=w[:-2], theta=theta[:-2])
    chk = pj.estimate_encoder_offset(data, M)
    assert math.isnan(chk.shift)
    assert abs(math.degrees(chk.offset) + math.degrees(W * T_S)) < 0.5  # -w T_s
    assert not pj.recording_warnings(data, DRIVE)  # 1.3 deg: below the warning's 3 deg


def test_layout_file_and_cli(tmp_path, capsys):
    path, _ = logger_a(tmp_path)
    (tmp_path / "layout.toml").write_text(
        '[csv]\ndelimiter = ";"\n[time]\ncolumn = "time_ms"\nunit = "ms"\n'
        '[current]\ncolumns = ["ia", "ib"]\n'
        '[voltage]\ncolumns = ["da", "db", "dc"]\nframe = "duty"\nu_dc = "vbus"\nscale = 0.01\n'
        '[angle]\ncolumn = "enc_deg"\nunit = "mech_deg"\noffset = "estimate"\n')
    out = tmp_path / "out"
    assert main(["convert", str(path), "--layout", str(tmp_path / "layout.toml"),
                 "--motor", "zhang750", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "encoder offset estimated" in text and "--voltage commanded" in text
    data = pj.load_recording(out / "recording.npz", require=("t", "u_ab", "i_ab", "theta"))
    _, theta, *_ = reference()
    assert np.max(np.abs(wrapped_deg(data.theta - theta))) < 1e-6
    report = json.loads((out / "convert.json").read_text())
    assert math.isclose(report["offset_removed_deg"], N_P * OFFSET_MECH_DEG, abs_tol=1e-6)
    # a missing column: exit status 2, one line naming it and the close match
    (tmp_path / "wrong.toml").write_text(
        (tmp_path / "layout.toml").read_text().replace('"ib"]', '"i_b"]'))
    assert main(["convert", str(path), "--layout", str(tmp_path / "wrong.toml"),
                 "--motor", "zhang750", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "column 'i_b'" in err and "did you mean 'ib'" in err
    # --set without the drive it changes
    assert main(["convert", str(path), "--layout", str(tmp_path / "layout.toml"),
                 "--out", str(out), "--set", "R_s=1"]) == 2
    assert "--set changes the drive" in capsys.readouterr().err


def _error(tmp_path, make, match, **layout_edit):
    path, layout = make(tmp_path)
    with pytest.raises(pj.LogFormatError, match=match):
        pj.convert_log(path, pj.LogLayout(**{**layout, **layout_edit}), drive=DRIVE)


def test_named_errors_of_the_log(tmp_path):
    _error(tmp_path, logger_a, r"column 'ia_x' \(\[current\] columns\[0\]\) is not in the "
           r"header.*did you mean 'ia'", current=("ia_x", "ib"))
    _error(tmp_path, logger_a, r"one column only: is \[csv\] delimiter", delimiter=",")
    t, *_ = reference()
    bad = 1e3 * t.copy()
    bad[10] = bad[9]
    _error(tmp_path, lambda p: logger_a(p, time_ms=bad), r"line 12: .*time must increase")
    gap = 1e3 * np.where(np.arange(N) >= 100, t + 3 * T_S, t)
    _error(tmp_path, lambda p: logger_a(p, time_ms=gap), r"gap between line 101 and line "
           r"102.*about 3 samples missing")
    jit = 1e3 * (t + 0.05 * T_S * (np.arange(N) == 50))
    _error(tmp_path, lambda p: logger_a(p, time_ms=jit), r"deviates 5 % from the median")
    nan = np.ones(N)
    nan[7] = np.nan
    _error(tmp_path, lambda p: logger_a(p, ia=nan), r"line 9, column 'ia': 'nan'.*finite")
    _error(tmp_path, logger_a, r"duty cycle .* outside \[voltage\] duty_range.*percent",
           voltage_scale=1.0)
    _error(tmp_path, lambda p: logger_a(p, vbus=np.zeros(N)), r"DC-bus voltage 0.0 must be")
    clip = np.full(N, 2048.0)
    clip[[20, 30]] = 4095
    _error(tmp_path, lambda p: logger_b(p, adc_b=clip), r"line 22, column 'adc_b'.*"
           r"converter's limit.*2 clipped samples")
    path, layout = logger_a(tmp_path)
    with pytest.raises(pj.LogFormatError, match="needs the pole pairs"):
        pj.convert_log(path, pj.LogLayout(**layout))
    with pytest.raises(pj.LogFormatError, match="needs the machine"):
        pj.convert_log(path, pj.LogLayout(**{**layout, "angle_offset": "estimate",
                                             "angle_n_p": N_P}))
    (tmp_path / "text.csv").write_text("t,ia,ib,ua,ub\n0,1,2,3,x\n")
    with pytest.raises(pj.LogFormatError, match=r"line 2, column 'ub': 'x' is not a number"):
        pj.convert_log(tmp_path / "text.csv", pj.LogLayout(
            time="t", current=("ia", "ib"), voltage=("ua", "ub"), voltage_frame="alpha_beta"))


def test_time_in_the_wrong_unit_is_a_warning_with_the_right_one(tmp_path):
    path, layout = logger_a(tmp_path)
    res = pj.convert_log(path, pj.LogLayout(**{**layout, "time_unit": "s"}), drive=DRIVE)
    assert "T_s = 0.125 s is not a drive's" in res.warnings[0]
    assert "unit = 'ms' gives T_s = 0.000125 s" in res.warnings[0]


@pytest.mark.parametrize("edit, match", [
    (dict(time_unit="min"), r"\[time\] unit = 'min': allowed: 's', 'ms', 'us'"),
    (dict(current=("a",)), r"\[current\] columns = \['a'\]: frame 'phase' takes three"),
    (dict(voltage_frame="duty", voltage=("a", "b", "c")), r"\[voltage\] u_dc = None"),
    (dict(voltage_delay=-1), r"\[voltage\] delay = -1: must be a whole number"),
    (dict(angle="x", angle_unit="counts"), r"\[angle\] counts_per_rev = None"),
    (dict(angle="x", angle_direction=2), r"\[angle\] direction = 2: allowed: 1 or -1"),
    (dict(current_adc_range=(10, 0)), r"adc_range = \(10, 0\): must be \[low, high\]"),
    (dict(voltage_duty_range=(0, 2), voltage_frame="duty", voltage=("a", "b", "c"),
          voltage_u_dc=300.0), r"duty_range = \[0, 2\]"),
])
def test_named_errors_of_the_layout(edit, match):
    base = dict(time="t", current=("a", "b"), voltage=("x", "y"))
    with pytest.raises(ValueError, match=match):
        pj.LogLayout(**{**base, **edit})


def test_layout_file_errors(tmp_path):
    f = tmp_path / "l.toml"
    for text, match in (
            ('[time]\ncolumn = "t"\n[current]\ncolumns = ["a", "b"]\n', r"missing section "
             r"\[voltage\]"),
            ('[tim]\n', r"unknown section \[tim\]"),
            ('[time]\ncolumn = "t"\nscale = 2\n[current]\ncolumns = ["a", "b"]\n[voltage]\n'
             'columns = ["x", "y"]\n', r"unknown key 'scale' in \[time\]; allowed: column, "
             r"unit, jitter"),
            ('[time]\nunit = "s"\n[current]\ncolumns = ["a", "b"]\n[voltage]\n'
             'columns = ["x", "y"]\n', r"\[time\] needs column")):
        f.write_text(text)
        with pytest.raises(ValueError, match=match):
            pj.load_log_layout(f)


def test_the_two_example_logs_of_the_guide_are_one_run(tmp_path):
    """docs/examples/logs: one simulated run written by two loggers; their layouts must
    give the same recording (to the loggers' resolution), the first with the encoder's
    12.3 deg mounting offset found from the voltages."""
    logs = pathlib.Path(__file__).parents[1] / "docs" / "examples" / "logs"
    a, b = (pj.convert_log(logs / f"logger_{x}.csv", pj.load_log_layout(logs / f"logger_{x}.toml"),
                           drive=DRIVE) for x in "ab")
    assert (a.rows, b.rows, b.dropped) == (1600, 1600, 1)
    assert math.isclose(a.T_s, T_S, rel_tol=1e-12) and math.isclose(b.T_s, T_S, rel_tol=1e-12)
    np.testing.assert_allclose(a.data.t[1:], b.data.t, atol=1e-12)
    # currents: 1e-4 A digits against 0.01 A counts (half a count per phase)
    assert np.max(np.abs(a.data.i_ab[1:] - b.data.i_ab)) < 0.01
    # voltages: duty cycles to 1e-5 % of 311 V against 1 mV digits
    assert np.max(np.abs(a.data.u_ab[1:] - b.data.u_ab)) < 2e-3
    # the same encoder; a's offset estimated: a constant difference, within 0.5 deg of
    # the true 5 x 12.3 deg (the estimate's bias: commanded voltages, a 3 V dead time)
    d = wrapped_deg(a.data.theta[1:] - b.data.theta)
    assert np.ptp(d) <= N_P * 1e-4 + 1e-9 and abs(d.mean()) < 0.5  # 4 decimals of mech. deg
    assert abs(a.offset_estimate_deg - N_P * OFFSET_MECH_DEG) < 0.5
    # speed: a's from the encoder over 2 ms, b's logged in rpm
    assert np.max(np.abs(a.data.w_m[8:-8] / b.data.w_m[7:-8] - 1)) < 0.01


def test_replay_prints_the_log_checks_and_lost_lock_hints(tmp_path, capsys):
    """`pmsmjax replay` on a log whose voltages are one sample early (a speed ramp) prints
    the shift warning and records it in stats.json; a lost lock names what to check."""
    import argparse

    from pmsmjax.cli._replay import _lost_lock_hints

    t, theta, i_ab, u_ab, w = reference(noise=0.02, ramp=1.0)
    data = pj.RecordedData(t=t[:-1], u_ab=u_ab[1:], i_ab=i_ab[:-1], w_m=w[:-1],
                           theta=np.remainder(theta[:-1], 2 * np.pi))
    pj.save_recording(tmp_path / "early.npz", data)
    assert main(["replay", "--motor", "zhang750", "--data", str(tmp_path / "early.npz"),
                 "--out", str(tmp_path / "r"), "--no-plot"]) == 0
    out = capsys.readouterr().out
    assert "warning: the voltages fit the machine best applied 1 period(s) after" in out
    stats = json.loads((tmp_path / "r" / "stats.json").read_text())
    assert len(stats["log_warnings"]) == 1 and "[voltage] delay" in stats["log_warnings"][0]
    hints = _lost_lock_hints(argparse.Namespace(voltage="applied"),
                             pj.replace_params(DRIVE, u_dt=3.0), ["a warning"])
    assert "--voltage commanded (the drive's dead time u_dt = 3 V)" in hints[0]
    assert hints[1] == "see the warnings above about the log"
    assert _lost_lock_hints(argparse.Namespace(voltage="commanded"), DRIVE, []) == []


def test_identify_figure_shows_the_worst_segments_of_every_recording():
    """`plot_identification`: one column per recording, each on the three segments around
    its largest current residual, named in the column's title."""
    from types import SimpleNamespace

    from pmsmjax.plotting import plot_identification

    t = 1e-4 * np.arange(2000)  # 10 segments of 20 ms
    traces = []
    for worst in (2, 9):
        i = np.zeros((t.size, 2))
        model = i + 1e-3
        model[(t >= 0.02 * worst) & (t < 0.02 * (worst + 1)), 0] += 0.5
        traces.append(dict(t=t, i_ab=i, i_model=model, w_m=np.ones_like(t),
                           w_model=np.ones_like(t)))
    res = SimpleNamespace(traces=traces, segment_s=0.02,
                          parameters={"R_s": {"value": 1.0, "unit": "Ohm"}})
    fig = plot_identification(res)
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert len(titles) == 2
    assert "worst segments 0.02-0.0799 s" in titles[0]  # segments 1, 2, 3
    assert "worst segments 0.14-0.2 s" in titles[1]  # the last three
    in_worst = 0.501 ** 2 + 1e-6  # squared residual per sample there, 2e-6 elsewhere
    assert f"residual {math.sqrt(in_worst):.3g} A" in titles[0]
    # the whole recording's RMS: one segment of ten at the large residual
    assert f"(whole recording {math.sqrt(0.1 * in_worst + 0.9 * 2e-6):.3g} A)" in titles[0]


def test_the_drive_sampling_period_in_the_motor_file(tmp_path, capsys):
    """`[control] T_s` in a motor file: read and written back, the default of export-c
    (and simulate), and a recording at another period is a warning that names the
    likely cause."""
    from pmsmjax._plant._motorfile import read_motor_file

    text = pj.motor_file_text(DRIVE) + "\n[control]\nT_s = 0.0001\n"
    (tmp_path / "m.toml").write_text(text)
    drive, _ = read_motor_file(tmp_path / "m.toml")
    assert drive.T_s == 1e-4 and pj.parse_motor_file(pj.motor_file_text(drive)).T_s == 1e-4
    assert main(["export-c", "--motor-file", str(tmp_path / "m.toml"), "--out",
                 str(tmp_path / "c")]) == 0
    assert "T_s = 0.0001 s" in capsys.readouterr().out
    t, theta, i_ab, u_ab, w = reference()
    data = pj.RecordedData(t=t, u_ab=u_ab, i_ab=i_ab, theta=theta, w_m=w)  # 125 us
    msgs = pj.recording_warnings(data, drive)
    assert len(msgs) == 1 and "differs from the drive's [control] T_s = 0.0001 s" in msgs[0]
    drive_125 = pj.parse_motor_file(pj.motor_file_text(DRIVE) + "\n[control]\nT_s = 125e-6\n")
    assert not pj.recording_warnings(data, drive_125)
    data_ms = pj.RecordedData(t=1e3 * t, u_ab=u_ab, i_ab=i_ab)  # time left in ms
    msgs = pj.recording_warnings(data_ms, drive_125)
    assert any("a ratio of 1000: a time column in ms or us?" in m for m in msgs)
    assert any("decimated" in m for m in pj.recording_warnings(
        pj.RecordedData(t=4 * t, u_ab=u_ab, i_ab=i_ab), drive_125))  # every 4th sample
    with pytest.raises(pj.MotorFileError, match=r"\[control\] T_s"):
        pj.parse_motor_file(pj.motor_file_text(DRIVE) + "\n[control]\nT_s = -1\n")


def test_log_checks_take_the_dead_time_off_commanded_voltages():
    """zhang750 with 3 V of dead time under current control at 0.3 p.u. (i_q reversing,
    i_d steps, 0.02 A of noise), the commanded voltages logged, angle and voltages exact:
    taken as applied, the dead-time error (along the current, which has a d component)
    reads as an encoder offset and a one-sample voltage delay (the warnings a user saw on
    such a log before); with the inverter given, its error is taken off the voltages
    first and no warning remains."""
    import jax

    d = pj.replace_params(DRIVE, u_dt=3.0)
    i_m, T = float(d.i_max), 1.0
    sc = pj.Scenario(
        t_end=T,
        i_q_ref=pj.Profile.steps(list(np.linspace(0, T, 11)[1:-1]),
                                 [0.3 * i_m * (-1) ** k for k in range(1, 10)],
                                 initial=0.3 * i_m),
        i_d_ref=pj.Profile.steps([0.2, 0.45, 0.7], [-0.25 * i_m, -0.05 * i_m, -0.3 * i_m]))
    tr = pj.simulate(d, pj.FOC.from_drive(d), pj.SensoredObserver(), sc, T_s=1e-4,
                     w_m0=0.3 * float(d.w_rated), sensing=pj.Sensing(noise_std=0.02),
                     key=jax.random.PRNGKey(5))
    data = pj.RecordedData.from_trajectory(tr)
    as_applied = pj.recording_warnings(data, d)
    assert any("ahead of the rotor" in m for m in as_applied), as_applied
    assert pj.recording_warnings(data, d, inverter=d.inverter) == []
