"""`pmsmjax feasibility`, `pmsmjax equilibria`, `pmsmjax certify`, run in-process through
`main([...])` and compared with the `pmsmjax.analysis` functions they wrap.

The generic equilibria route compiles once per observer structure and process (about 10-30
s here), so the equilibria tests share one: the LESO with the fixed-ratio flux design
(`--zeta1 --ratio`); mismatch only changes leaves, not the structure."""

import json
import math

import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.cli import main
from pmsmjax.observers import make_observer


DRIVE = pj.preset("zhang750")
# A strongly salient variant of Table I: it has infeasible designs at i_q = 2 p.u. (Table I
# itself is feasible everywhere), so the maps below are not trivially all-zero.
SALIENT = ["--set", "L_d=1e-3", "--set", "L_q=4.9e-3"]
SALIENT_DRIVE = pj.replace_params(DRIVE, L_d=1e-3, L_q=4.9e-3)
FEASIBILITY_KEYS = {"zeta1", "ratio", "status", "n_nonzero", "stable_theta_deg", "speed",
                    "principal_stable", "principal_theta_deg", "i_dq", "zeta2", "w2",
                    "mismatch_R_s", "mismatch_L_d", "mismatch_L_q", "mismatch_psi_f",
                    "w_rated", "I_b", "motor", "method", "x", "y", "x_name", "y_name",
                    "observer", "observer_class", "design", "observer_model", "status_codes"}


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
    for option in ("--motor", "--set", "--i-d", "--i-q", "--zeta2", "--w2", "--mismatch",
                   "--zeta1", "--ratio", "--observer", "--observer-set", "--gain"):
        assert option in text, option
    assert "--speed-range" in text if command == "certify" else "--speed" in text
    assert "rad/s" in text and "p.u." in text and "Drive.base.I_b" in text
    assert "one of eso, leso, afo" in text  # the registry's names
    assert ("--x NAME=LO:HI:N" in text) == (command == "feasibility")


def test_feasibility_file_matches_the_api(tmp_path, capsys):
    out = tmp_path / "map"
    assert main(["feasibility", "--observer", "leso", *SALIENT, "--i-q", "2", "--zeta1",
                 "0:5:11", "--ratio", "0:2:9", "--speed", "0.5", "--out", str(out)]) == 0
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
    assert set(np.unique(st)) <= {-1, 0, 1, 2}
    # codes and counts as int8 (a quarter of int32's bytes; the counts are bounded by the
    # equilibria's slots)
    assert st.dtype == np.int8 and data["n_nonzero"].dtype == np.int8
    assert str(data["x_name"]) == "zeta1" and str(data["y_name"]) == "ratio"
    np.testing.assert_array_equal(data["x"], z)
    assert str(data["observer"]) == "leso" and str(data["method"]) == "closed_form"
    assert np.all(st[0] == -1)  # ratio 0: degenerate
    assert np.any(st == 1) and np.any(st == 0)  # the salient machine has both
    assert np.all(np.isfinite(data["stable_theta_deg"]) == (st == 1))  # NaN if none

    fm = analysis.feasibility_map(SALIENT_DRIVE, [0.5], z, r, i_dq=(0.0, 2.0))
    np.testing.assert_array_equal(st, np.asarray(fm.status)[0, 0].T)
    np.testing.assert_array_equal(data["n_nonzero"], np.asarray(fm.n_nonzero)[0, 0].T)
    # the command evaluates the same kernel point by point in chunks (run_sweep): XLA's
    # code for another batch shape may differ in the last bit
    np.testing.assert_allclose(data["stable_theta_deg"],
                               np.asarray(fm.stable_theta_deg)[0, 0].T, rtol=1e-13)
    Z, R = np.meshgrid(z, r)  # (N2, N1)
    c = analysis.classify_designs(SALIENT_DRIVE.motor, 0.5 * SALIENT_DRIVE.w_rated,
                                  np.array([0.0, 2.0]) * SALIENT_DRIVE.base.I_b, Z, R)
    np.testing.assert_array_equal(st, np.asarray(c.status))
    np.testing.assert_allclose(data["stable_theta_deg"],  # degrees() inside/outside jit
                               np.degrees(np.asarray(c.stable_theta)), rtol=1e-13)

    counts = {s: int(np.sum(st == s)) for s in (0, 1, -1)}
    assert (f"speed 0.5 p.u.: feasible {counts[0]}, infeasible {counts[1]}, no equilibrium "
            f"0, degenerate {counts[-1]}") in printed
    assert str(out / "feasibility.npz") in printed and str(out / "feasibility.png") in printed


def test_feasibility_several_speeds_and_standstill(tmp_path):
    assert main(["feasibility", "--observer", "leso", *SALIENT, "--i-q", "2", "--zeta1", "0.5:2:4",
                 "--ratio", "0.5:2:3", "--speeds", "0.2", "1", "--speed", "0",
                 "--no-plot", "--out", str(tmp_path)]) == 0
    assert not (tmp_path / "feasibility.png").exists()
    with np.load(tmp_path / "feasibility.npz", allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    np.testing.assert_array_equal(data["speed"], [0.2, 1.0, 0.0])
    for key in ("status", "n_nonzero", "stable_theta_deg", "principal_stable"):
        assert data[key].shape == (3, 3, 4), key  # (speed, N2, N1)
    fm = analysis.feasibility_map(SALIENT_DRIVE, [0.2, 1.0], np.linspace(0.5, 2, 4),
                                  np.linspace(0.5, 2, 3), i_dq=(0.0, 2.0))
    np.testing.assert_array_equal(data["status"][:2],
                                  np.asarray(fm.status)[:, 0].transpose(0, 2, 1))
    # standstill: w1 = ratio |w0| = 0, every design degenerate, nothing else reported
    assert np.all(data["status"][2] == -1) and np.all(data["n_nonzero"][2] == 0)
    assert np.all(np.isnan(data["stable_theta_deg"][2]))


def test_feasibility_with_inductance_mismatch(tmp_path, capsys):
    assert main(["feasibility", "--observer", "leso", "--i-q", "1", "--mismatch",
                 "L_d=0.7", "--mismatch",
                 "L_q=1.5", "--zeta1", "0.5:2:2", "--ratio", "0.5:1:2", "--speed", "0.05",
                 "--no-plot", "--out", str(tmp_path)]) == 0
    assert "(general)" in capsys.readouterr().out
    with np.load(tmp_path / "feasibility.npz", allow_pickle=False) as f:
        st = f["status"]
        assert float(f["mismatch_L_d"]) == 0.7 and str(f["method"]) == "general"
        assert float(f["mismatch_R_s"]) == 1.0
    m = DRIVE.motor
    m_hat = pj.PMSMParams(R_s=m.R_s, L_d=0.7 * m.L_d, L_q=1.5 * m.L_q, psi_f=m.psi_f,
                          n_p=m.n_p)
    fm = analysis.feasibility_map(DRIVE, [0.05], [0.5, 2.0], [0.5, 1.0], i_dq=(0.0, 1.0),
                                  motor_hat=m_hat)
    api = np.asarray(fm.status)[0, 0].T
    np.testing.assert_array_equal(st, api)  # "no equilibrium" is its own status, 2


def _leso(**kw):
    return make_observer("leso", DRIVE, **kw)


def test_equilibria_json_fig9_design(capsys):
    assert main(["equilibria", "--observer", "leso", "--zeta1", "0.5", "--ratio", "0.5",
                 "--speed", "0.5", "--json"]) == 0
    captured = capsys.readouterr()
    report = _strict_json(captured.out)  # stdout holds the JSON and nothing else
    assert captured.err == ""
    w0, i0 = 0.5 * float(DRIVE.w_rated), np.zeros(2)
    # the CLI is analysis.equilibria of the default observer (the LESO) with this design
    # (with the command's Newton starts, n_starts = 64: one program with the mismatch
    # test's reference below)
    eq = analysis.equilibria(_leso(zeta1=0.5, ratio=0.5), DRIVE.motor, w0, i0, n_starts=64)
    valid = np.asarray(eq.valid)
    got = report["equilibria"]
    assert report["status"] == "ok" and len(got) == int(eq.n) == 2
    np.testing.assert_array_equal([e["theta_rad"] for e in got], np.asarray(eq.theta)[valid])
    assert [e["stable"] for e in got] == list(np.asarray(eq.stable)[valid])
    for e, k in zip(got, np.flatnonzero(valid)):
        ev = np.linalg.eigvals(np.asarray(eq.jacobian)[k])
        got_ev = np.array([v["re"] + 1j * v["im"] for v in e["eigenvalues"]])
        np.testing.assert_allclose(np.sort_complex(got_ev), np.sort_complex(ev), rtol=1e-12)
        assert e["stable"] == bool(np.max(ev.real) < 0)
        assert list(e["state"]) == ["psi_d", "psi_q", "theta", "w"]
    # zhang2022's closed form: the designed equilibrium at 0 and the one of
    # tan(theta/2) = w1/(2 zeta1 w0) = 0.5 (`tests/test_contract.py` compares the generic
    # route with zhang2022's own in detail)
    np.testing.assert_allclose(sorted(abs(e["theta_deg"]) for e in got),
                               [0.0, 2 * math.degrees(math.atan(0.5))], atol=1e-7)
    # on Table I's machine every design is feasible (zhang2022 Sec. IV; the closed form
    # in tests/test_feasibility.py): the other equilibrium is unstable, the verdict
    # "feasible"
    other_stable = any(e["stable"] and not e["designed"] for e in got)
    assert not other_stable
    assert report["feasibility_status"] == 0 and report["feasibility"] == "feasible"


def test_equilibria_table_and_file(tmp_path, capsys):
    assert main(["equilibria", *SALIENT, "--i-q", "2", "--speed", "0.5", "--out",
                 str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "design zhang38: zeta1 = 2," in out and "(designed)" in out
    assert "design feasible" in out and str(tmp_path / "equilibria.json") in out
    report = _strict_json((tmp_path / "equilibria.json").read_text())
    assert report["design"]["schedule"] == "zhang38" and report["feasibility_status"] == 0


EQUILIBRIUM_KEYS = {"theta_deg", "theta_rad", "designed", "stable", "tangent", "eigenvalues",
                    "max_real_eigenvalue", "state", "residual"}


def test_equilibria_mismatch_json_schema(capsys):
    """`--observer leso --mismatch L_q=1.5 --json`: the schema of every observer, state
    names and units from `observer.coordinates`; the designed equilibrium moves off 0.
    The fixed-ratio design of `test_equilibria_json_fig9_design` (the module's one
    equilibria program, command and API: a mismatch changes leaves only; the (38)
    schedule's report is `test_equilibria_table_and_file`'s)."""
    assert main(["equilibria", "--observer", "leso", "--zeta1", "0.5", "--ratio", "0.5",
                 "--mismatch", "L_q=1.5", "--i-q", "1", "--json"]) == 0
    report = _strict_json(capsys.readouterr().out)
    assert {"command", "motor", "operating_point", "observer", "design", "status",
            "status_code", "n_equilibria", "n_nonzero", "feasibility_status", "feasibility",
            "coordinates", "units", "equilibria"} <= set(report)
    coords = pj.LESOObserver.coordinates
    assert [c["name"] for c in report["coordinates"]] == list(coords.names)
    assert [c["unit"] for c in report["coordinates"]] == list(coords.units)
    assert report["units"]["state"] == dict(zip(coords.names, coords.units))
    obs = report["observer"]
    assert obs["name"] == "leso" and obs["class"] == "LESOObserver" and obs["mismatch"]
    assert obs["model"]["L_q_ratio"] == pytest.approx(1.5)
    assert obs["model"]["L_q"] == pytest.approx(1.5 * float(DRIVE.motor.L_q))
    assert obs["model"]["L_d_ratio"] == 1.0
    assert report["design"]["schedule"] == "fixed_ratio"
    assert report["design"]["observer"] == "leso"
    assert report["status"] == "ok" and report["status_code"] == 0
    assert report["n_equilibria"] == len(report["equilibria"]) >= 1
    for e in report["equilibria"]:
        assert set(e) == EQUILIBRIUM_KEYS
        assert list(e["state"]) == list(coords.names)
        assert len(e["eigenvalues"]) == coords.n
    designed = [e for e in report["equilibria"] if e["designed"]]
    assert len(designed) == 1 and abs(designed[0]["theta_deg"]) > 1  # static error
    m_hat = pj.replace_params(DRIVE, L_q=1.5 * float(DRIVE.motor.L_q)).motor
    # the command's call (with the grid's Newton starts, n_starts = 64)
    eq = analysis.equilibria(_leso(zeta1=0.5, ratio=0.5, motor=m_hat), DRIVE.motor,
                             0.5 * float(DRIVE.w_rated),
                             np.array([0.0, 1.0]) * float(DRIVE.base.I_b), n_starts=64)
    np.testing.assert_array_equal([e["theta_rad"] for e in report["equilibria"]],
                                  np.asarray(eq.theta)[np.asarray(eq.valid)])


def test_equilibria_no_equilibrium_is_its_own_status(capsys):
    """A mismatch without any equilibrium: status 'no equilibrium' (code 2) in the text and
    the JSON, exit 0; --observer-set gives the same observer model as --mismatch L_q=RATIO."""
    base = ["equilibria", "--observer", "leso", "--i-q", "2", "--speed", "0.02", "--zeta1",
            "0.5", "--ratio", "0.25"]
    assert main([*base, "--mismatch", "L_q=1.5"]) == 0
    out = capsys.readouterr().out
    assert "0 equilibria; status no equilibrium; design no equilibrium" in out
    L_q = repr(1.5 * float(DRIVE.motor.L_q))
    assert main([*base, "--observer-set", f"L_q={L_q}", "--json"]) == 0
    report = _strict_json(capsys.readouterr().out)
    assert report["status"] == "no equilibrium" and report["status_code"] == 2
    assert report["feasibility_status"] == 2 and report["feasibility"] == "no equilibrium"
    assert report["equilibria"] == [] and report["observer"]["mismatch"]
    assert report["observer"]["model"]["L_q_ratio"] == pytest.approx(1.5)


def _expm(M):
    """exp of a batch of small matrices by NumPy alone: scaling and squaring of a degree-24
    Taylor polynomial (independent of the certificate's Pade approximant)."""
    n1 = np.abs(M).sum(-2).max(-1)
    s = np.maximum(0, np.ceil(np.log2(np.maximum(n1, 1e-300))) + 1).astype(int)
    X = M / (2.0 ** s)[..., None, None]
    eye = np.eye(M.shape[-1])
    E = np.broadcast_to(eye, M.shape).copy()
    for j in range(24, 0, -1):
        E = eye + X @ E / j
    for k in range(int(s.max())):
        E = np.where((s > k)[..., None, None], E @ E, E)
    return E


def _certificate_by_scipy(obs, report):
    """The bounds of a certificate report recomputed independently: the linearisation by
    central differences of the observer's error dynamics (`error_rhs`), in the report's
    per-unit scaling, on its speed grid; P by SciPy's Lyapunov solver, dP/dw by central
    differences; k(gamma) = max sup_t ||exp(t (A + gamma I))|| on a geometric time grid
    refined twice around each speed's peak, with gamma = alpha sigma for each alpha of
    the report's resolution, the best bound taken; eps = c3 / c5 with the target
    c3 = 1/2 and zhang2022 (64) c5 = k^4 b / (2 gamma^2), sharp: c5 = max ||dP/dw||.
    Returns (eps, eps_sharp, {"sigma", "b", "k"})."""
    import jax
    import scipy.linalg

    m = DRIVE.three_phase_motor
    i0 = np.asarray(report["operating_point"]["i_dq_A"])
    psi_b, w_b = float(DRIVE.base.psi_b), float(DRIVE.base.w_b)
    d = np.array([1 / psi_b, 1 / psi_b, 1.0, 1 / w_b])
    f = jax.jit(lambda x, w: obs.error_rhs(x, analysis.OperatingPoint(w, i0), m))

    def A(w):
        cols = []
        for j in range(4):
            e = np.zeros(4)
            e[j] = 1e-7 / d[j]
            cols.append((np.asarray(f(e, w)) - np.asarray(f(-e, w))) / (2 * e[j]))
        return d[:, None] * np.stack(cols, 1) / d[None, :]

    def P(a):
        return scipy.linalg.solve_continuous_lyapunov(a.T, -np.eye(4))

    lo, hi = report["speed_range"]["rad_s"]
    ws = np.linspace(lo, hi, report["speed_range"]["n_speed"])
    h = 1e-3 * w_b
    As = np.stack([A(w) for w in ws])
    b = max(np.linalg.norm((A(w + h) - A(w - h)) / (2 * h), 2) for w in ws)
    c5_sharp = max(np.linalg.norm((P(A(w + h)) - P(A(w - h))) / (2 * h), 2) for w in ws)
    sigma = min(-np.linalg.eigvals(a).real.max() for a in As)

    def k_of(gam):
        M = As + gam * np.eye(4)

        def norms(ts):  # (speeds, times)
            return np.linalg.norm(_expm(ts[..., None, None] * M[:, None]), 2, axis=(-2, -1))

        ts = np.concatenate([[0.0], np.geomspace(1e-5, 60 / (sigma - gam), 400)])
        v = norms(np.broadcast_to(ts, (len(ws), ts.size)))
        j = np.argmax(v, 1)
        a, z = ts[np.maximum(j - 1, 0)], ts[np.minimum(j + 1, ts.size - 1)]
        best = v.max()
        for _ in range(2):
            tt = a[:, None] + (z - a)[:, None] * np.linspace(0, 1, 101)
            vv = norms(tt)
            best = max(best, vv.max())
            j = np.argmax(vv, 1)
            step = (z - a) / 100
            a, z = tt[np.arange(len(ws)), j] - step, tt[np.arange(len(ws)), j] + step
        return best

    eps, kk = {}, {}
    for alpha in report["resolution"]["alphas"]:
        gam = alpha * sigma
        kk[alpha] = k_of(gam)
        eps[alpha] = 0.5 / (kk[alpha] ** 4 * b / (2 * gam ** 2))
    alpha = max(eps, key=eps.get)
    return eps[alpha], 0.5 / c5_sharp, {"sigma": sigma, "b": b, "k": kk[alpha]}


def test_certify_matches_the_api(tmp_path, capsys):
    args = ["certify", "--observer", "leso", "--quick", "--speed-range", "0.3:1", "--i-q",
            "0.5"]
    assert main([*args, "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "certified |dw/dt| <=" in printed and str(tmp_path / "certificate.json") in printed
    report = _strict_json((tmp_path / "certificate.json").read_text())

    resolution = dict(n_speed=21, n_dirs=256, alphas=(0.8, 0.99), n_time=80, n_k1_speeds=5)
    cert = analysis.slowly_varying_certificate(
        DRIVE, pj.ESODesign.zhang38(DRIVE.w_rated), (0.3, 1.0), i_dq=(0.0, 0.5), **resolution)
    assert int(cert.status) == 0
    assert report["status"] == "ok"
    # the bounds against SciPy/NumPy (measured: 2.2e-8 and 1.0e-5 relative, the central
    # differences' error in b and dP/dw; sigma 1.4e-9, b 2.1e-8, k 4e-10)
    eps, eps_sharp, c = _certificate_by_scipy(_leso(), report)
    assert report["dw_dt_bound_rad_s2"] == pytest.approx(eps, rel=6e-8)
    assert report["dw_dt_bound_sharp_rad_s2"] == pytest.approx(eps_sharp, rel=3e-5)
    k = report["constants"]
    assert (k["sigma"], k["b"], k["k"]) == pytest.approx((c["sigma"], c["b"], c["k"]),
                                                         rel=6e-8)
    assert f"certified |dw/dt| <= {eps:.4g} rad/s^2" in printed
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
    eps2, eps2_sharp, _ = _certificate_by_scipy(_leso(zeta1=2.0, ratio=0.75), report2)
    assert report2["dw_dt_bound_rad_s2"] == pytest.approx(eps2, rel=6e-8)
    assert report2["dw_dt_bound_sharp_rad_s2"] == pytest.approx(eps2_sharp, rel=3e-5)
    assert abs(eps2 / eps - 1) > 0.01  # another design, another bound
    assert "computing" in captured.err


def _fake_certificate(real):
    """A stand-in for `slowly_varying_certificate` that records its arguments (the real
    one with observer-model mismatch at the command line's resolution compiles for tens
    of seconds; it is checked against independent computations on small grids in
    test_lyapunov.py, and against this command in the slow test below) and returns a
    certificate with every constant 1."""
    import dataclasses
    import functools

    seen = {}

    @functools.wraps(real)  # keeps the signature: the CLI records the default resolution
    def fake(drive, design, speed_range, **kw):
        seen.update(drive=drive, observer=design, speed_range=speed_range, **kw)
        values = {f.name: np.float64(1.0)
                  for f in dataclasses.fields(analysis.LyapunovCertificate)}
        values.update(speeds=np.linspace(*speed_range, 3), status=np.int32(0))
        return analysis.LyapunovCertificate(**values)

    return fake, seen


def test_certify_passes_any_observer_with_mismatch(monkeypatch, tmp_path, capsys):
    fake, seen = _fake_certificate(analysis.slowly_varying_certificate)
    monkeypatch.setattr(analysis, "slowly_varying_certificate", fake)
    assert main(["certify", "--observer", "eso", "--mismatch", "R_s=1.2", "--observer-set",
                 "L_d=3e-3", "--gain", "w2=400", "--a", "0.7", "--speed-range", "0.3:1",
                 "--i-q", "0.5", "--quick", "--out", str(tmp_path)]) == 0
    obs = seen["observer"]
    assert isinstance(obs, pj.ESOObserver) and seen["plant"] == DRIVE.motor
    assert float(obs.motor.R_s) == pytest.approx(1.2 * float(DRIVE.motor.R_s))
    assert float(obs.motor.L_d) == 3e-3 and float(obs.motor.L_q) == float(DRIVE.motor.L_q)
    assert obs.design_parameters()["w2"] == 400 and obs.design_parameters()["a"] == 0.7
    assert seen["speed_range"] == (0.3, 1.0) and seen["i_dq"] == (0.0, 0.5)
    assert seen["n_speed"] == 21  # --quick
    report = _strict_json((tmp_path / "certificate.json").read_text())
    assert report["observer"]["name"] == "eso" and report["observer"]["mismatch"]
    assert report["observer"]["model"]["R_s_ratio"] == pytest.approx(1.2)
    assert report["design"]["w2"] == 400 and report["design"]["given"] == {"w2": 400,
                                                                           "a": 0.7}
    assert report["status"] == "ok"


# the fast suite covers the same in parts: the command's handling of a mismatch
# (test_certify_passes_any_observer_with_mismatch), the command against the API without one
# (test_certify_matches_the_api) and the certificate under observer-model mismatch against
# independent computations (tests/test_lyapunov.py)
@pytest.mark.slow
def test_certify_with_mismatch_matches_the_api(capsys):
    args = ["certify", "--observer", "leso", "--quick", "--n-speed", "3", "--n-dirs", "16",
            "--speed-range", "0.3:1", "--i-q", "0.5", "--mismatch", "L_q=1.2"]
    assert main(args) == 0
    report = _strict_json(capsys.readouterr().out)
    m_hat = pj.replace_params(DRIVE, L_q=1.2 * float(DRIVE.motor.L_q)).motor
    resolution = {**report["resolution"], "alphas": tuple(report["resolution"]["alphas"])}
    cert = analysis.slowly_varying_certificate(DRIVE, _leso(motor=m_hat), (0.3, 1.0),
                                               i_dq=(0.0, 0.5), **resolution)
    assert report["status"] == "ok" and int(cert.status) == 0
    assert report["dw_dt_bound_rad_s2"] == pytest.approx(float(cert.eps), rel=1e-9)


def test_feasibility_any_two_design_parameters(tmp_path, capsys):
    """--x/--y over any two design parameters: the map of `analysis.design_map`."""
    x, y = np.linspace(200, 400, 3), np.linspace(0.7, 1.3, 2)
    assert main(["feasibility", "--observer", "leso", *SALIENT, "--i-q", "2", "--x",
                 "w2=200:400:3", "--y",
                 "zeta2=0.7:1.3:2", "--gain", "zeta1=0.5",
                 "--gain", "ratio=0.5", "--speed", "0.5", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "3 x 2 designs (w2 x zeta2)" in printed
    assert (tmp_path / "feasibility.png").stat().st_size > 0
    with np.load(tmp_path / "feasibility.npz", allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    assert str(data["x_name"]) == "w2" and str(data["y_name"]) == "zeta2"
    np.testing.assert_array_equal(data["w2"], x)
    np.testing.assert_array_equal(data["zeta2"], y)
    assert float(data["zeta1"]) == 0.5 and float(data["ratio"]) == 0.5  # fixed design
    assert data["status"].shape == (2, 3)  # (y, x)
    obs = make_observer("leso", SALIENT_DRIVE, zeta1=0.5, ratio=0.5)
    fm = analysis.design_map(obs, SALIENT_DRIVE, [0.5], ("w2", x), ("zeta2", y),
                             i_dq=(0.0, 2.0))
    np.testing.assert_array_equal(data["status"], np.asarray(fm.status)[0, 0].T)
    assert str(data["method"]) == fm.method


def test_observer_choices_come_from_the_registry(monkeypatch, capsys):
    """An observer registered later appears in every command without touching the CLI, and
    --gain checks its own design names."""
    from pmsmjax.observers import _registry

    monkeypatch.setitem(_registry._REGISTRY, "copy-leso", pj.LESOObserver)
    for command in ("simulate", "replay", "feasibility", "equilibria", "certify"):
        assert main([command, "--help"]) == 0
        assert "copy-leso" in " ".join(capsys.readouterr().out.split()), command
    assert main(["equilibria", "--observer", "copy-leso", "--gain", "a=0.5"]) == 2
    line = _one_line_error(capsys)
    assert "--gain a=0.5: the copy-leso observer has no design parameter 'a'" in line
    assert "allowed: w2, zeta2," in line


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
    (["feasibility", "--mismatch-L-q", "0"], ["unrecognized arguments: --mismatch-L-q 0"]),
    (["equilibria", "--speed", "0", "--zeta1", "0.5", "--ratio", "0.5"],
     ["--speed 0", "continuum", "nonzero"]),
    (["equilibria", "--zeta1", "0.5"], ["--ratio"]),
    (["equilibria", "--i-d", _psi_a0_zero_current()], ["--i-d", "infinite"]),
    (["certify", "--speed-range", "0:1"], ["--speed-range", "0 < LO < HI"]),
    (["certify", "--speed-range", "1:0.5"], ["--speed-range", "LO < HI"]),
    (["certify", "--c3", "1.5"], ["--c3 1.5", "0 < C3 < 1"]),
    # observers from the registry: --observer, --gain, --observer-set, --mismatch
    (["equilibria", "--observer", "kalman"],
     ["--observer", "invalid choice: 'kalman'", "'eso', 'leso', 'afo'"]),
    (["equilibria", "--observer", "leso", "--gain", "foo=1"],
     ["--gain foo=1", "the leso observer has no design parameter 'foo'", "allowed: w2,"]),
    (["feasibility", "--observer", "afo", "--gain", "a=0.5"],
     ["--gain a=0.5", "the afo observer has no design parameter 'a'", "allowed: w2,"]),
    (["equilibria", "--gain", "w2"], ["--gain", "'w2'", "NAME=VALUE"]),
    (["equilibria", "--gain", "w2=fast"], ["--gain", "'w2=fast'", "not a number"]),
    (["equilibria", "--w2", "100", "--gain", "w2=200"], ["--w2 100", "--gain w2=200",
                                                         "give it once"]),
    (["equilibria", "--schedule", "fixed_w1", "--zeta1", "1"],
     ["--schedule fixed_w1 needs --w1 and --w-min", "allowed schedules"]),
    (["equilibria", "--observer-set", "Lq=0.01"],
     ["--observer-set Lq=0.01", "unknown parameter 'Lq'", "allowed: R_s (Ohm), L_d (H), "
      "L_q (H), psi_f (V s)"]),
    (["equilibria", "--observer-set", "L_q=-0.01"],
     ["--observer-set L_q=-0.01", "L_q", "must be finite and > 0"]),
    (["certify", "--observer-set", "L_q=big"], ["--observer-set", "'L_q=big'", "not a number"]),
    (["certify", "--mismatch-psi-f", "1.5"], ["unrecognized arguments: --mismatch-psi-f"]),
    (["equilibria", "--mismatch", "L_q=1.5", "--observer-set", "L_q=0.004"],
     ["--mismatch L_q=1.5", "--observer-set L_q=0.004", "both set the observer's L_q",
      "allowed: one of the two"]),
    (["equilibria", "--mismatch", "L_q=0"], ["--mismatch L_q=0", "> 0"]),
    (["equilibria", "--mismatch", "Lq=1.2"], ["--mismatch Lq=1.2", "unknown parameter",
                                             "allowed: R_s, L_d, L_q, psi_f"]),
    (["equilibria", "--mismatch", "L_q"], ["--mismatch", "'L_q'", "NAME=VALUE"]),
    # design axes of the map
    (["feasibility", "--x", "zeta1"], ["--x", "'zeta1'", "NAME=LO:HI:N"]),
    (["feasibility", "--x", "zeta1=0:5"], ["--x", "'0:5'", "LO:HI:N"]),
    (["feasibility", "--y", "ratio=2:1:5"], ["--y", "LO <= HI"]),
    (["feasibility", "--observer", "leso", "--x", "foo=0:1:3", "--y", "ratio=0:2:3"],
     ["--x foo=0:1:3", "the leso observer has no design parameter 'foo'", "allowed: w2,"]),
    (["feasibility", "--x", "w2=100:200:3"], ["--x needs --y", "w2, zeta2"]),
    (["feasibility", "--x", "w2=100:200:3", "--y", "w2=1:2:2"], ["different", "allowed"]),
    (["feasibility", "--x", "w2=100:200:3", "--y", "zeta2=1:2:2", "--zeta1", "0:1:3"],
     ["--zeta1/--ratio and --x/--y", "allowed: one of the two"]),
    (["feasibility", "--x", "w2=100:200:3", "--y", "zeta2=1:2:2", "--w2", "300"],
     ["--x w2", "both set w2"]),
])
def test_bad_inputs_exit_2_with_one_line(argv, words, capsys):
    assert main(argv) == 2
    line = _one_line_error(capsys)
    assert line.startswith(f"pmsmjax {argv[0]}: error:")
    for w in words:
        assert w in line, (w, line)
