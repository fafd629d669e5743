"""`pmsmjax.firmware`: the generated C observer, compiled with gcc, against `replay`.

For each supported observer one short synthetic recording (a PMSM whose speed steps up
and ramps, currents and the interval-mean voltages that produce them, from the flux
equation in closed form), one gcc build in double and one in float, and the C output
compared with `pmsmjax.replay` in float64: 1e-6 rad / rad/s in double; the float32
deviation is printed (docs/firmware.md records it).
"""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.firmware import SUPPORTED, export_c
from pmsmjax.observers import make_observer


T_S = 125e-6
N = 400

pytestmark = pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc")


def _recording(drive, n=N, T_s=T_S):
    """t, u_ab, i_ab of the drive's motor: speed 0.2 p.u., stepping to 0.5 p.u. and
    ramping; i_dq = (-0.5, 3) A with a step. The voltage over [t_k, t_{k+1}) is the
    interval mean that moves the flux exactly from psi(t_k) to psi(t_{k+1})."""
    m = drive.three_phase_motor
    t = np.arange(n + 1) * T_s
    w = float(drive.w_rated) * np.where(t < 0.4 * n * T_s, 0.2,
                                        0.5 + 2.0 * (t - 0.4 * n * T_s))
    theta = 0.3 + np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * T_s)])
    i_d = np.where(t < 0.6 * n * T_s, -0.5, -1.0)
    i_q = np.where(t < 0.6 * n * T_s, 3.0, 5.0)
    c, s = np.cos(theta), np.sin(theta)
    psi_d, psi_q = float(m.L_d) * i_d + float(m.psi_f), float(m.L_q) * i_q
    psi = np.stack([c * psi_d - s * psi_q, s * psi_d + c * psi_q], 1)
    i_ab = np.stack([c * i_d - s * i_q, s * i_d + c * i_q], 1)
    u_ab = (np.diff(psi, axis=0) / T_s
            + float(m.R_s) * 0.5 * (i_ab[1:] + i_ab[:-1]))
    return t[:n], u_ab, i_ab[:n]


def _csv(t, u_ab, i_ab) -> str:
    rows = ["t,u_a,u_b,i_a,i_b"]
    rows += [",".join(repr(float(x)) for x in (t[k], *u_ab[k], *i_ab[k]))
             for k in range(len(t))]
    return "\n".join(rows) + "\n"


def run_c(observer, tmp_path, csv, *, float32=False, theta0=0.2, w0=0.0):
    """Generate, compile (gcc -std=c99 -O2 -Wall -Werror) and run replay_main."""
    out = tmp_path / ("f32" if float32 else "f64")
    export_c(observer, T_S, out, float32=float32)
    exe = out / "replay"
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-o",
                    str(exe), str(out / "replay_main.c"), str(out / "pmsm_observer.c"),
                    "-lm"], check=True, capture_output=True, text=True)
    res = subprocess.run([str(exe), repr(theta0), repr(w0)], input=csv, check=True,
                         capture_output=True, text=True)
    a = np.loadtxt(res.stdout.splitlines(), delimiter=",", ndmin=2)
    return a[:, 0], a[:, 1]


def _case(case):
    """(drive, observer) of a test case: the registered observers with their default
    design (rotor-flux and parallel-model on their papers' machines), and other gain schedules."""
    drive = pj.preset({"rotor-flux": "morawiec_ipm3k5", "parallel-model": "stumper_mt5",
                       "c-leso": "li_dtp", "gi-leso": "li_dtp", "fa-leso": "li_dtp"}
                      .get(case, "zhang750"))
    if case in SUPPORTED:
        return drive, make_observer(case, drive)
    return drive, {
        "eso-fixed": lambda: make_observer("eso", drive, fixed_at=0.2),
        "afo-fixed_w1": lambda: make_observer("afo", drive, zeta1=1.0, w1=200.0,
                                              w_min=50.0),
        "leso-fixed_ratio": lambda: make_observer("leso", drive, zeta1=0.8, ratio=1.2,
                                                  n2=10.0),
    }[case]()


@pytest.mark.parametrize("case", [*SUPPORTED, "eso-fixed", "afo-fixed_w1",
                                  "leso-fixed_ratio"])
def test_c_observer_equals_replay(case, tmp_path):
    drive, obs = _case(case)
    t, u_ab, i_ab = _recording(drive)
    w0 = 0.2 * float(drive.w_rated)  # the recording's initial speed
    theta_py, w_py = pj.replay(obs, t=t, u_ab=u_ab, i_ab=i_ab, T_s=T_S, theta0=0.2, w0=w0)
    theta_py, w_py = np.asarray(theta_py), np.asarray(w_py)
    # the recording exercises the observer: its speed estimate changes by > 0.1 p.u.
    assert np.ptp(w_py) > 0.1 * float(drive.w_rated)
    csv = _csv(t, u_ab, i_ab)
    theta_c, w_c = run_c(obs, tmp_path, csv, w0=w0)
    assert theta_c.shape == (N,)
    d_theta = np.abs(np.asarray(pj.wrap_angle(theta_c - theta_py)))
    np.testing.assert_array_less(d_theta, 1e-6)
    np.testing.assert_array_less(np.abs(w_c - w_py), 1e-6 * np.maximum(1.0, np.abs(w_py)))
    theta_32, w_32 = run_c(obs, tmp_path, csv, float32=True, w0=w0)
    d32 = np.abs(np.asarray(pj.wrap_angle(theta_32 - theta_py)))
    print(f"\n{case}: float32 C vs float64 replay: max |theta| {d32.max():.3g} rad, "
          f"max |w| {np.abs(w_32 - w_py).max():.3g} rad/s "
          f"(float64 C: {d_theta.max():.3g} rad)")
    # single-precision rounding only: far below the observers' own angle errors
    assert np.all(np.isfinite(theta_32)) and np.all(np.isfinite(w_32))
    assert d32.max() < 1e-3 and np.abs(w_32 - w_py).max() < 1e-4 * float(drive.w_rated)


def test_cli_export_c_tuned_design(tmp_path):
    """`pmsmjax export-c --design DIR` for a speed-scheduled gains table (as the tuner
    writes it): the C code equals `replay` of the observer the table gives, in double,
    and the header documents the sampling period and the table."""
    from pmsmjax.cli.__main__ import main

    drive = pj.preset("zhang750")
    wr = float(drive.w_rated)
    w = np.array([-0.5, 0.0, 0.3, 0.6]) * wr  # the recording spans 0.2 .. 0.7 p.u.
    sched = pj.TabulatedDesign(
        w_m=w, zeta1=np.array([1.6, 1.5, 1.8, 2.1]), w1=np.array([300.0, 0.0, 200.0, 400.0]),
        zeta2=np.array([1.0, 0.9, 1.2, 1.1]), w2=np.array([250.0, 300.0, 350.0, 280.0]),
        nu2=np.array([0.0, 0.1, -0.2, 0.0]), nu3=np.array([0.0, 0.0, 0.1, 0.05]))
    table = pj.gains_table_scheduled("eso", sched, drive.three_phase_motor, drive=drive.name)
    pj.write_gains_table(table, tmp_path / "tuned")
    out = tmp_path / "c"
    assert main(["export-c", "--motor", "zhang750", "--design", str(tmp_path / "tuned"),
                 "--T-s", repr(T_S), "--out", str(out)]) == 0
    header = (out / "pmsm_observer.h").read_text()
    assert f"PMSM_OBS_T_S PMSM_R({T_S!r})" in header and "4 rows" in header
    obs = pj.apply_gains_table(pj.load_gains_table(tmp_path / "tuned"),
                               make_observer("eso", drive))
    t, u_ab, i_ab = _recording(drive)
    theta_py, w_py = (np.asarray(x) for x in pj.replay(obs, t=t, u_ab=u_ab, i_ab=i_ab,
                                                       T_s=T_S, theta0=0.2))
    exe = out / "replay"
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-o", str(exe),
                    str(out / "replay_main.c"), str(out / "pmsm_observer.c"), "-lm"],
                   check=True, capture_output=True, text=True)
    res = subprocess.run([str(exe), "0.2"], input=_csv(t, u_ab, i_ab), check=True,
                         capture_output=True, text=True)
    assert res.stderr == ""
    a = np.loadtxt(res.stdout.splitlines(), delimiter=",", ndmin=2)
    np.testing.assert_array_less(np.abs(np.asarray(pj.wrap_angle(a[:, 0] - theta_py))), 1e-6)
    # a recording at another sampling period is flagged on stderr
    res = subprocess.run([str(exe)], input=_csv(2.0 * t, u_ab, i_ab), check=True,
                         capture_output=True, text=True)
    assert "not PMSM_OBS_T_S" in res.stderr
    np.testing.assert_array_less(np.abs(a[:, 1] - w_py), 1e-6 * np.maximum(1.0, abs(w_py)))


def test_cli_export_c_refuses_unstable_sampling(tmp_path, capsys):
    """The parallel-model observer's forward-Euler filters need T_s < 2 min(T_LP, T_w)
    (1 ms with its defaults): export-c refuses a longer period, naming the limit."""
    from pmsmjax.cli.__main__ import main

    assert main(["export-c", "--motor", "stumper_mt5", "--observer", "parallel-model",
                 "--T-s", "2e-3", "--out", str(tmp_path / "c")]) == 2
    assert "2 min(T_LP, T_w)" in capsys.readouterr().err
