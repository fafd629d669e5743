"""`pmsmjax feasibility`, `pmsmjax equilibria`, `pmsmjax certify`, run in-process through
`main([...])` and compared with the `pmsmjax.analysis` functions they wrap."""

import json
import math

import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.__main__ import main


DRIVE = pj.preset("zhang750")
# A strongly salient variant of Table I: it has infeasible designs at i_q = 2 p.u. (Table I
# itself is feasible everywhere), so the maps below are not trivially all-zero.
SALIENT = ["--set", "L_d=1e-3", "--set", "L_q=4.9e-3"]
SALIENT_DRIVE = pj.replace_params(DRIVE, L_d=1e-3, L_q=4.9e-3)
FEASIBILITY_KEYS = {"zeta1", "ratio", "status", "n_nonzero", "stable_theta_deg", "speed",
                    "no_equilibrium", "principal_stable", "principal_theta_deg", "i_dq",
                    "zeta2", "w2", "mismatch_L_d", "mismatch_L_q", "w_rated", "I_b", "motor",
                    "method"}


def _strict_json(text):
    def bad(token):
        raise AssertionError(f"non-strict JSON constant {token}")

    return json.loads(text, parse_constant=bad)


def _one_line_error(capsys):
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    return lines[0]


@pytest.mark.parametrize("command", ["feasibility", "equilibria", "certify"])
def test_help(command, capsys):
    assert main([command, "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for option in ("--motor", "--set", "--i-d", "--i-q", "--zeta2", "--w2", "--mismatch-L-d",
                   "--mismatch-L-q", "--zeta1", "--ratio"):
        assert option in text, option
    assert "--speed-range" in text if command == "certify" else "--speed" in text
    assert "rad/s" in text and "p.u." in text and "Drive.base.I_b" in text


def test_feasibility_file_matches_the_api(tmp_path, capsys):
    out = tmp_path / "map"
    assert main(["feasibility", *SALIENT, "--i-q", "2", "--zeta1", "0:5:11",
                 "--ratio", "0:2:9", "--speed", "0.5", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert (out / "feasibility.png").stat().st_size > 0
    with np.load(out / "feasibility.npz", allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    assert FEASIBILITY_KEYS <= set(data)
    z, r = np.linspace(0, 5, 11), np.linspace(0, 2, 9)
    np.testing.assert_array_equal(data["zeta1"], z)
    np.testing.assert_array_equal(data["ratio"], r)
    for key in ("status", "n_nonzero", "stable_theta_deg"):
        assert data[key].shape == (9, 11), key  # (N2, N1): ratio x zeta1
    assert data["speed"].shape == () and float(data["speed"]) == 0.5
    st = data["status"]
    assert set(np.unique(st)) <= {-1, 0, 1}
    assert np.all(st[0] == -1)  # ratio 0: degenerate
    assert np.any(st == 1) and np.any(st == 0)  # the salient machine has both
    assert np.all(np.isfinite(data["stable_theta_deg"]) == (st == 1))  # NaN if none

    fm = analysis.feasibility_map(SALIENT_DRIVE, [0.5], z, r, i_dq=(0.0, 2.0))
    np.testing.assert_array_equal(st, np.asarray(fm.status)[0, 0].T)
    np.testing.assert_array_equal(data["n_nonzero"], np.asarray(fm.n_nonzero)[0, 0].T)
    np.testing.assert_array_equal(data["stable_theta_deg"],
                                  np.asarray(fm.stable_theta_deg)[0, 0].T)
    Z, R = np.meshgrid(z, r)  # (N2, N1)
    c = analysis.classify_designs(SALIENT_DRIVE.motor, 0.5 * SALIENT_DRIVE.w_rated,
                                  np.array([0.0, 2.0]) * SALIENT_DRIVE.base.I_b, Z, R)
    np.testing.assert_array_equal(st, np.asarray(c.status))
    np.testing.assert_allclose(data["stable_theta_deg"],  # degrees() inside/outside jit
                               np.degrees(np.asarray(c.stable_theta)), rtol=1e-13)

    counts = {s: int(np.sum(st == s)) for s in (0, 1, -1)}
    assert (f"speed 0.5 p.u.: feasible {counts[0]}, infeasible {counts[1]}, degenerate "
            f"{counts[-1]}") in printed
    assert str(out / "feasibility.npz") in printed and str(out / "feasibility.png") in printed


def test_feasibility_several_speeds_and_standstill(tmp_path):
    assert main(["feasibility", *SALIENT, "--i-q", "2", "--zeta1", "0.5:2:4",
                 "--ratio", "0.5:2:3", "--speed", "0.2,1", "--speed", "0",
                 "--no-plot", "--out", str(tmp_path)]) == 0
    assert not (tmp_path / "feasibility.png").exists()
    with np.load(tmp_path / "feasibility.npz", allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    np.testing.assert_array_equal(data["speed"], [0.2, 1.0, 0.0])
    for key in ("status", "n_nonzero", "stable_theta_deg", "no_equilibrium"):
        assert data[key].shape == (3, 3, 4), key  # (speed, N2, N1)
    fm = analysis.feasibility_map(SALIENT_DRIVE, [0.2, 1.0], np.linspace(0.5, 2, 4),
                                  np.linspace(0.5, 2, 3), i_dq=(0.0, 2.0))
    np.testing.assert_array_equal(data["status"][:2],
                                  np.asarray(fm.status)[:, 0].transpose(0, 2, 1))
    # standstill: w1 = ratio |w0| = 0, every design degenerate, nothing else reported
    assert np.all(data["status"][2] == -1) and np.all(data["n_nonzero"][2] == 0)
    assert np.all(np.isnan(data["stable_theta_deg"][2]))


def test_feasibility_with_inductance_mismatch(tmp_path, capsys):
    assert main(["feasibility", "--i-q", "1", "--mismatch-L-d", "0.7", "--mismatch-L-q",
                 "1.5", "--zeta1", "0.5:2:2", "--ratio", "0.5:1:2", "--speed", "0.05",
                 "--no-plot", "--out", str(tmp_path)]) == 0
    assert "(general)" in capsys.readouterr().out
    with np.load(tmp_path / "feasibility.npz", allow_pickle=False) as f:
        st, none = f["status"], f["no_equilibrium"]
        assert float(f["mismatch_L_d"]) == 0.7 and str(f["method"]) == "general"
    m = DRIVE.motor
    m_hat = pj.PMSMParams(R_s=m.R_s, L_d=0.7 * m.L_d, L_q=1.5 * m.L_q, psi_f=m.psi_f,
                          n_p=m.n_p)
    fm = analysis.feasibility_map(DRIVE, [0.05], [0.5, 2.0], [0.5, 1.0], i_dq=(0.0, 1.0),
                                  motor_hat=m_hat)
    api = np.asarray(fm.status)[0, 0].T
    np.testing.assert_array_equal(none, api == 2)  # "no equilibrium" is reported as -1
    np.testing.assert_array_equal(st, np.where(api == 2, -1, api))


def test_equilibria_json_fig9_design(capsys):
    assert main(["equilibria", "--zeta1", "0.5", "--ratio", "0.5", "--speed", "0.5",
                 "--json"]) == 0
    captured = capsys.readouterr()
    report = _strict_json(captured.out)  # stdout holds the JSON and nothing else
    assert captured.err == ""
    w0, i0 = 0.5 * float(DRIVE.w_rated), np.zeros(2)
    gains = pj.ESODesign.fixed_ratio(0.5, 0.5)(DRIVE.motor, w0, i0)
    eq = analysis.eso_equilibria(w0, i0, gains, DRIVE.motor)
    valid = np.asarray(eq.valid)
    got = report["equilibria"]
    assert report["status"] == "ok" and len(got) == int(eq.n) == 2
    np.testing.assert_allclose([e["theta_deg"] for e in got],
                               np.degrees(np.asarray(eq.theta)[valid]), rtol=0, atol=1e-12)
    assert [e["stable"] for e in got] == list(np.asarray(eq.stable)[valid])
    # the designed equilibrium at 0 and the one of tan(theta/2) = w1/(2 zeta1 w0) = 0.5
    np.testing.assert_allclose(sorted(abs(e["theta_deg"]) for e in got),
                               [0.0, 2 * math.degrees(math.atan(0.5))], atol=1e-9)
    for e, k in zip(got, np.flatnonzero(valid)):
        A = analysis.eso_linearization(w0, i0, gains, DRIVE.motor, x=np.asarray(eq.x)[k])
        ev = np.linalg.eigvals(np.asarray(A))
        got_ev = np.array([v["re"] + 1j * v["im"] for v in e["eigenvalues"]])
        np.testing.assert_allclose(np.sort_complex(got_ev), np.sort_complex(ev), rtol=1e-12)
        assert e["stable"] == bool(np.max(ev.real) < 0)
    assert report["feasibility_status"] == int(analysis.classify_designs(
        DRIVE.motor, w0, i0, 0.5, 0.5).status)


def test_equilibria_table_and_file(tmp_path, capsys):
    assert main(["equilibria", *SALIENT, "--i-q", "2", "--speed", "0.5", "--out",
                 str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "design zhang38: zeta1 = 2," in out and "(designed)" in out
    assert "design feasible" in out and str(tmp_path / "equilibria.json") in out
    report = _strict_json((tmp_path / "equilibria.json").read_text())
    assert report["design"]["schedule"] == "zhang38" and report["feasibility_status"] == 0


def test_certify_matches_the_api(tmp_path, capsys):
    args = ["certify", "--quick", "--speed-range", "0.3:1", "--i-q", "0.5"]
    assert main([*args, "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "certified |dw/dt| <=" in printed and str(tmp_path / "certificate.json") in printed
    report = _strict_json((tmp_path / "certificate.json").read_text())

    resolution = dict(n_speed=21, n_dirs=256, alphas=(0.8, 0.99), n_time=80, n_k1_speeds=5)
    cert = analysis.slowly_varying_certificate(
        DRIVE, pj.ESODesign.zhang38(DRIVE.w_rated), (0.3, 1.0), i_dq=(0.0, 0.5), **resolution)
    assert int(cert.status) == 0
    assert report["status"] == "ok"
    assert report["dw_dt_bound_rad_s2"] > 0
    assert report["dw_dt_bound_rad_s2"] == pytest.approx(float(cert.eps), rel=1e-9)
    assert report["dw_dt_bound_sharp_rad_s2"] == pytest.approx(float(cert.eps_sharp),
                                                               rel=1e-9)
    assert report["constants"]["paper"]["c5"] == pytest.approx(float(cert.c5), rel=1e-9)
    assert report["constants"]["sharp"]["c1"] == pytest.approx(float(cert.c1_sharp), rel=1e-9)
    assert report["design"]["schedule"] == "zhang38"
    assert report["speed_range"]["pu"] == [0.3, 1.0]
    assert report["operating_point"]["i_dq_pu"] == [0.0, 0.5]
    assert {k: report["resolution"][k] for k in resolution} == {
        **resolution, "alphas": [0.8, 0.99]}

    # without --out: the same JSON on stdout, nothing else there
    assert main([*args, "--zeta1", "2", "--ratio", "0.75"]) == 0
    captured = capsys.readouterr()
    report2 = _strict_json(captured.out)
    assert report2["design"]["schedule"] == "fixed_ratio"
    assert report2["design"]["zeta1"] == 2.0 and report2["design"]["ratio"] == 0.75
    assert report2["dw_dt_bound_rad_s2"] > 0
    assert "computing" in captured.err


def _psi_a0_zero_current():
    m = DRIVE.motor
    return repr(-float(m.psi_f) / (float(m.L_d) - float(m.L_q)) / float(DRIVE.base.I_b))


@pytest.mark.parametrize("argv, words", [
    (["feasibility", "--zeta1", "0:5"], ["--zeta1", "LO:HI:N"]),
    (["feasibility", "--zeta1", "0:5:x"], ["--zeta1", "integer >= 1"]),
    (["feasibility", "--zeta1", "0:5:0"], ["--zeta1", "integer >= 1"]),
    (["feasibility", "--ratio", "2:1:5"], ["--ratio", "LO <= HI"]),
    (["feasibility", "--ratio", "-1:2:5"], ["--ratio", ">= 0"]),
    (["feasibility", "--zeta1", "0:inf:5"], ["--zeta1", "finite"]),
    (["feasibility", "--zeta1", "1:2:1"], ["--zeta1", "LO = HI"]),
    (["feasibility", "--speed", "0.5,x"], ["--speed"]),
    (["feasibility", "--motor", "nope"], ["--motor", "zhang750"]),
    (["feasibility", "--set", "L_q=abc"], ["--set", "not a number"]),
    (["feasibility", "--set", "Lq=1e-3"], ["--set", "Unknown parameter"]),
    (["feasibility", "--mismatch-L-q", "0"], ["--mismatch-L-q", "> 0"]),
    (["equilibria", "--speed", "0", "--zeta1", "0.5", "--ratio", "0.5"],
     ["--speed 0", "continuum", "nonzero"]),
    (["equilibria", "--zeta1", "0.5"], ["--ratio"]),
    (["equilibria", "--i-d", _psi_a0_zero_current()], ["--i-d", "infinite"]),
    (["certify", "--speed-range", "0:1"], ["--speed-range", "0 < LO < HI"]),
    (["certify", "--speed-range", "1:0.5"], ["--speed-range", "LO < HI"]),
    (["certify", "--mismatch-L-d", "1.2"], ["--mismatch-L-d", "allowed: 1"]),
])
def test_bad_inputs_exit_2_with_one_line(argv, words, capsys):
    assert main(argv) == 2
    line = _one_line_error(capsys)
    assert line.startswith(f"pmsmjax {argv[0]}: error:")
    for w in words:
        assert w in line, (w, line)
