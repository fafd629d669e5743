"""Flux-map files (`read_flux_map`, its named errors, `check_flux_map`) and saturated motor
files (`[saturation] flux_map` / `model = "algebraic"`, derived constants, round trip, the
command line on a saturated drive)."""

import dataclasses
import json
import re

import equinox as eqx
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax._plant._motorfile import read_motor_file
from pmsmjax.cli.__main__ import main


# A small linear map with cross-coupling: psi_d = PSI_F + L_D i_d + K_DQ i_q,
# psi_q = L_Q i_q + K_QD i_d on a 5 x 6 grid.
PSI_F, L_D, L_Q = 0.2, 4e-3, 9e-3
I_D = np.array([-10.0, -7.5, -5.0, -2.5, 0.0])
I_Q = np.array([-10.0, -6.0, -2.0, 2.0, 6.0, 10.0])


def _tables(k_dq=0.0, k_qd=0.0):
    dd, qq = np.meshgrid(I_D, I_Q, indexing="ij")
    return PSI_F + L_D * dd + k_dq * qq, L_Q * qq + k_qd * dd


def _rows(k_dq=0.0, k_qd=0.0):
    psi_d, psi_q = _tables(k_dq, k_qd)
    return [[float(I_D[a]), float(I_Q[b]), float(psi_d[a, b]), float(psi_q[a, b])]
            for a in range(len(I_D)) for b in range(len(I_Q))]


def _write(path, rows, header="i_d,i_q,psi_d,psi_q"):
    path.write_text(header + "\n" + "\n".join(",".join(repr(v) for v in r) for r in rows)
                    + "\n")
    return path


def _error(path, *fragments):
    with pytest.raises(pj.FluxMapError) as e:
        pj.read_flux_map(path)
    msg = str(e.value)
    assert str(path) in msg
    for f in fragments:
        assert f in msg, (f, msg)
    return msg


# ---------------------------------------------------------------------------------------
# read_flux_map
# ---------------------------------------------------------------------------------------

def test_any_row_order_csv_and_both_npz_layouts_give_the_same_map(tmp_path):
    """Shuffled rows (with a comment, a blank line and an extra torque column), the
    sorted CSV and the two NPZ layouts read to the identical map, whose tables are the
    values written (exactly: repr floats)."""
    rows = _rows(k_dq=1e-4, k_qd=1e-4)
    ref = pj.read_flux_map(_write(tmp_path / "sorted.csv", rows))
    psi_d, psi_q = _tables(1e-4, 1e-4)
    np.testing.assert_array_equal(ref.i_d, I_D)
    np.testing.assert_array_equal(ref.i_q, I_Q)
    np.testing.assert_array_equal(ref.psi_d, psi_d)
    np.testing.assert_array_equal(ref.psi_q, psi_q)
    perm = np.random.default_rng(0).permutation(len(rows))
    shuffled = tmp_path / "shuffled.csv"
    shuffled.write_text("# from an FE tool\npsi_q, tau, i_q, i_d, psi_d\n\n" + "\n".join(
        f"{rows[k][3]!r}, 1.0, {rows[k][1]!r}, {rows[k][0]!r}, {rows[k][2]!r}"
        for k in perm) + "\n")
    assert bool(eqx.tree_equal(pj.read_flux_map(shuffled), ref))
    cols = np.asarray(rows)[perm].T
    np.savez(tmp_path / "cols.npz", i_d=cols[0], i_q=cols[1], psi_d=cols[2], psi_q=cols[3])
    assert bool(eqx.tree_equal(pj.read_flux_map(tmp_path / "cols.npz"), ref))
    np.savez(tmp_path / "tables.npz", i_d=I_D, i_q=I_Q, psi_d=psi_d, psi_q=psi_q)
    assert bool(eqx.tree_equal(pj.read_flux_map(tmp_path / "tables.npz"), ref))


def test_named_errors(tmp_path):
    """Every fault of a map file is a FluxMapError naming the file, the fault and where."""
    rows = _rows()
    _error(_write(tmp_path / "cols.csv", [r[:3] for r in rows], "i_d,i_q,psi_d"),
           "missing column psi_q in the header (line 1")
    _error(_write(tmp_path / "cols2.csv", [r[:2] for r in rows], "i_d,i_q"),
           "missing columns psi_d, psi_q")
    # non-rectangular: the point (-5, 6) (row 2 * 6 + 4 of the grid) is missing
    _error(_write(tmp_path / "hole.csv", rows[:16] + rows[17:]),
           "not a rectangular grid", "missing (i_d, i_q) = (-5, 6) A")
    _error(_write(tmp_path / "dup.csv", rows + [rows[7]]),
           "duplicate grid points: (i_d, i_q) = (-7.5, -6) A in line 9 and line 32")
    bad = [list(r) for r in rows]
    bad[3][2], bad[10][3] = float("nan"), float("inf")
    _error(_write(tmp_path / "nan.csv", bad), "non-finite values (NaN or inf) in line 5, "
           "line 12 (columns psi_d, psi_q)")
    # psi_d falls from i_d = -7.5 to -5 A at i_q = 2 A (grid rows 1, 2; column 3)
    bad = [list(r) for r in rows]
    bad[2 * 6 + 3][2] = bad[1 * 6 + 3][2] - 1e-3
    _error(_write(tmp_path / "mono.csv", bad), "psi_d does not increase with i_d",
           "between i_d -7.5 -> -5 A at i_q = 2 A")
    bad = [list(r) for r in rows]
    bad[4 * 6 + 1][3] = bad[4 * 6 + 2][3]  # psi_q flat from i_q -6 to -2 A at i_d = 0
    _error(_write(tmp_path / "mono_q.csv", bad), "psi_q does not increase with i_q",
           "between i_q -6 -> -2 A at i_d = 0 A")
    # symmetric cross-coupling k with k^2 > L_D L_Q: each flux still increases with its
    # own current, but the energy is not convex
    k = 1.5 * np.sqrt(L_D * L_Q)
    _error(_write(tmp_path / "pd.csv", _rows(k, k)),
           "incremental inductance matrix d psi_dq / d i_dq not positive definite at "
           "(i_d, i_q) = (-10, -10) A")
    _error(_write(tmp_path / "short.csv", [r for r in rows if r[0] > -6]),
           "i_d has 3 grid values")
    np.savez(tmp_path / "miss.npz", i_d=I_D, i_q=I_Q, psi_d=_tables()[0])
    _error(tmp_path / "miss.npz", "missing array psi_q (found i_d, i_q, psi_d)")


def test_check_flux_map_report_reciprocity_and_coverage(tmp_path):
    """On the linear map the report holds the closed forms (psi_f, L at zero and rated
    current, the reciprocity asymmetry k / sqrt(L_D L_Q)); an asymmetric map warns with
    its measured asymmetry, a grid narrower than the current limit warns about the linear
    extension."""
    k_dq = 0.1 * np.sqrt(L_D * L_Q)  # 10 % asymmetry: d psi_d / d i_q = k_dq, L_qd = 0
    fm = pj.read_flux_map(_write(tmp_path / "asym.csv", _rows(k_dq, 0.0)))
    r = pj.check_flux_map(fm, i_max=10.0)
    assert r.grid == (5, 6) and r.i_d_range == (-10.0, 0.0) and r.i_q_range == (-10.0, 10.0)
    assert r.psi_f == pytest.approx(PSI_F, rel=1e-12)
    np.testing.assert_allclose(r.L_inc_zero, (L_D, k_dq, 0.0, L_Q), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(r.L_inc_rated, (L_D, k_dq, 0.0, L_Q), rtol=1e-9, atol=1e-15)
    assert r.psi_f_rated == pytest.approx(PSI_F + k_dq * 10.0, rel=1e-12)
    np.testing.assert_allclose(r.L_app_rated, (L_D, L_Q), rtol=1e-9)
    assert r.reciprocity == pytest.approx(0.1, rel=1e-9)
    assert r.covers and not r.errors and len(r.warnings) == 1
    assert "the map is not reciprocal" in r.warnings[0]
    assert "reaches 10 %" in r.warnings[0] and "above the tolerance 5 %" in r.warnings[0]
    assert pj.check_flux_map(fm, 10.0, reciprocity_tol=0.11).warnings == ()
    sym = pj.read_flux_map(_write(tmp_path / "sym.csv", _rows(k_dq, k_dq)))
    r = pj.check_flux_map(sym, i_max=12.0)
    assert r.reciprocity < 1e-9 and r.covers is False and len(r.warnings) == 1
    assert "does not cover the drive's current range under the limit i_max = 12 A" in \
        r.warnings[0]
    assert "extended linearly with the incremental inductance of the grid's edge" in \
        r.warnings[0]
    assert any("covers the current limit i_max = 12 A: no" in s for s in r.lines())
    # a map built in Python is not checked by FluxMap itself: the report's errors
    k = 1.5 * np.sqrt(L_D * L_Q)
    r = pj.check_flux_map(pj.FluxMap(I_D, I_Q, *_tables(k, k)), i_max=10.0)
    assert len(r.errors) == 1 and "not positive definite at (i_d, i_q) = (-10, -10) A" in \
        r.errors[0] and r.lines()[-1].startswith("error: incremental inductance matrix")
    psi_d, psi_q = _tables()
    r = pj.check_flux_map(pj.FluxMap(I_D, I_Q, psi_d[::-1], psi_q))
    assert "psi_d does not increase with i_d (d psi_d/d i_d <= 0) between i_d -10 -> -7.5 A" \
        in r.errors[0] and r.i_max is None and r.covers is None and r.L_inc_rated is None
    # the preset's map: the report at rated current is the model's it was sampled from
    drive = pj.preset("ipm3k5_sat")
    r = pj.check_flux_map(drive.motor.magnetic, drive.i_max)
    model = pj.ipm3k5_saturation()
    L = np.asarray(model.incremental_inductance(np.array([0.0, float(drive.i_max)])))
    np.testing.assert_allclose(r.L_inc_rated, L.ravel(), rtol=3e-3, atol=3e-5)
    assert r.covers and not r.warnings and not r.errors and r.reciprocity < 0.01


# ---------------------------------------------------------------------------------------
# Motor files with [saturation]
# ---------------------------------------------------------------------------------------

_BASE = pj.motor_file_text(pj.preset("morawiec_ipm3k5"))


def _without_constants(text):
    return re.sub(r"\nL_d = .*\nL_q = .*\npsi_f = .*\n", "\n", text)


def _with_saturation(text, section):
    return text.replace("\n[mechanics]", f"\n[saturation]\n{section}\n\n[mechanics]", 1)


def test_motor_file_with_a_flux_map(tmp_path):
    """`flux_map = "FILE"` (relative to the motor file): the plant gets the map; [motor]
    constants given are deployed as given, absent ones are constant_model's (small-current
    by default, or `constants = "rated"`), and the notes say how."""
    sub = tmp_path / "maps"
    sub.mkdir()
    fm = pj.read_flux_map(_write(sub / "m.csv", _rows(2e-4, 2e-4)))
    path = tmp_path / "sat.toml"
    path.write_text(_with_saturation(_BASE, 'flux_map = "maps/m.csv"'))
    drive, notes = read_motor_file(path)
    ref = pj.preset("morawiec_ipm3k5").motor
    assert notes == [] and bool(eqx.tree_equal(drive.motor.magnetic, fm))
    assert (drive.motor.L_d, drive.motor.L_q, drive.motor.psi_f) == (ref.L_d, ref.L_q,
                                                                     ref.psi_f)
    path.write_text(_without_constants(_with_saturation(_BASE, 'flux_map = "maps/m.csv"')))
    drive, notes = read_motor_file(path)
    got = (drive.motor.L_d, drive.motor.L_q, drive.motor.psi_f)
    assert got == pj.constant_model(fm)
    np.testing.assert_allclose(got, (L_D, L_Q, PSI_F), rtol=1e-9)
    assert notes == ["L_d, L_q, psi_f from the flux map's small-current values "
                     "(constant_model): L_d 4 mH, L_q 9 mH, psi_f 0.2 V s"]
    text = _with_saturation(_BASE, 'flux_map = "maps/m.csv"\nconstants = "rated"')
    path.write_text(re.sub(r"\nL_q = .*\n", "\n", text))
    drive, notes = read_motor_file(path)
    assert drive.motor.L_q == pj.constant_model(fm, "rated", drive.i_max)[1]
    assert drive.motor.L_d == ref.L_d and drive.motor.psi_f == ref.psi_f
    assert "L_q from the flux map's rated values (constant_model, i_max 10.6066 A)" \
        in notes[0] and "L_d, psi_f as given in [motor]" in notes[0]


def test_motor_file_with_the_algebraic_model_and_round_trip(tmp_path):
    """`model = "algebraic"`: the AlgebraicSaturation of the parameters (S..V defaulting
    to the class's), constants derived with constant_model; a drive with the model writes
    `model = "algebraic"` and loads back identical."""
    params = dict(a_d0=35.7, a_dd=7.2, a_q0=17.4, a_qq=0.71, a_dq=1000.0, i_f=31.3)
    sec = 'model = "algebraic"\n' + "\n".join(f"{k} = {v!r}" for k, v in params.items())
    drive, notes = read_motor_file(_write_text(tmp_path / "a.toml", _without_constants(
        _with_saturation(_BASE, sec + '\nconstants = "fit"'))))
    model = pj.AlgebraicSaturation(**params)
    assert bool(eqx.tree_equal(drive.motor.magnetic, model))
    assert (drive.motor.L_d, drive.motor.L_q, drive.motor.psi_f) == pj.constant_model(
        model, "fit", drive.i_max)
    assert notes[0].startswith("L_d, L_q, psi_f from the algebraic model's fit values")
    sat = pj.ipm3k5_saturation()
    d = pj.preset("morawiec_ipm3k5")
    d = dataclasses.replace(d, motor=eqx.tree_at(lambda m: m.magnetic, d.motor, sat,
                                                 is_leaf=lambda x: x is None))
    text = pj.motor_file_text(d)
    assert '[saturation]\nmodel = "algebraic"' in text and "S = 4.0" in text
    assert bool(eqx.tree_equal(pj.parse_motor_file(text), d))


def _write_text(path, text):
    path.write_text(text)
    return path


@pytest.mark.parametrize("section, fragment", [
    ('flux_map = "m.csv"\nmodel = "algebraic"', "[saturation]: give exactly one of flux_map"),
    ('constants = "rated"', "[saturation]: give exactly one of flux_map"),
    ('model = "spline"', "[saturation] model = 'spline': must be one of 'algebraic'"),
    ('model = "algebraic"\na_d0 = 30.0', "missing field [saturation] a_dd"),
    ('flux_map = "m.csv"\na_d0 = 30.0', "[saturation] a_d0: a parameter of model"),
    ('flux_map = "m.csv"\nconstants = "rated"', "[saturation] constants = 'rated': "
                                                "[motor] gives L_d, L_q and psi_f"),
    ('flux_map = "m.csv"\nconstants = "mean"', "constants = 'mean': must be one of"),
    ('flux_map = "none.csv"', "[saturation] flux_map = 'none.csv': cannot read"),
    ('flux_map = "bad.csv"', "[saturation] flux_map = 'bad.csv': flux map"),
])
def test_saturation_section_errors(section, fragment, tmp_path):
    _write(tmp_path / "m.csv", _rows())
    _write(tmp_path / "bad.csv", [r[:3] for r in _rows()], "i_d,i_q,psi_d")
    path = _write_text(tmp_path / "s.toml", _with_saturation(_BASE, section))
    with pytest.raises(pj.MotorFileError, match=re.escape(fragment)):
        pj.load_motor_file(path)


def test_motor_check_of_a_bad_map_exits_2(tmp_path, capsys):
    _write(tmp_path / "bad.csv", _rows(0.0, 0.0)[1:])
    path = _write_text(tmp_path / "s.toml", _with_saturation(_BASE, 'flux_map = "bad.csv"'))
    assert main(["motor", "--check", "--motor-file", str(path)]) == 2
    err = capsys.readouterr().err
    assert "[saturation] flux_map = 'bad.csv': flux map" in err
    assert "not a rectangular grid: 29 points on 5 i_d values x 6 i_q values, missing " \
           "(i_d, i_q) = (-10, -10) A" in err


def test_constants_required_without_saturation():
    with pytest.raises(pj.MotorFileError, match=re.escape(
            "missing field [motor] L_d (H; a finite number > 0; optional only with a "
            "[saturation] section")):
        pj.parse_motor_file(_without_constants(_BASE))


# ---------------------------------------------------------------------------------------
# The command line on a saturated motor file
# ---------------------------------------------------------------------------------------

def test_commands_run_the_saturated_motor_file(tmp_path, capsys):
    """`motor --export ipm3k5_sat` writes the TOML and its map; `motor --check` reports
    the map; `simulate`, `plant` and `replay` take the file. The plant run on the saturated
    recording reproduces it (the same map), the constant-inductance preset with the same
    constants does not (the map is used)."""
    out = tmp_path / "motor"
    assert main(["motor", "--export", "ipm3k5_sat", "--out", str(out)]) == 0
    motor = out / "motor.toml"
    assert (out / "motor_flux_map.csv").is_file()
    capsys.readouterr()
    derived = _write_text(tmp_path / "derived.toml", _without_constants(motor.read_text()
                          ).replace('"motor_flux_map.csv"', '"motor/motor_flux_map.csv"'))
    assert main(["motor", "--check", "--motor-file", str(derived)]) == 0
    cap = capsys.readouterr()
    assert "flux map: 26 x 41 grid, i_d -21.21..5.303 A" in cap.out
    assert "covers the current limit i_max = 10.61 A: yes" in cap.out
    assert "L_d, L_q, psi_f from the flux map's small-current values" in cap.err
    assert main(["motor", "--export", "ipm3k5_sat"]) == 2
    assert "give --out DIR" in capsys.readouterr().err

    sim = tmp_path / "sim"
    assert main(["simulate", "--motor-file", str(motor), "--t-end", "0.2", "--no-plot",
                 "--out", str(sim)]) == 0
    rec = pj.load_recording(sim / "recording.npz")
    i_scale = float(np.max(np.abs(rec.i_ab)))
    runs = {}
    for name, opt in (("sat", ["--motor-file", str(motor)]),
                      ("const", ["--motor", "morawiec_ipm3k5"])):
        assert main(["plant", *opt, "--data", str(sim / "recording.npz"), "--substeps", "1",
                     "--no-plot", "--out", str(tmp_path / name)]) == 0
        runs[name] = pj.load_recording(tmp_path / name / "plant.npz").i_ab
    err_sat = float(np.max(np.abs(runs["sat"] - rec.i_ab))) / i_scale
    err_const = float(np.max(np.abs(runs["const"] - rec.i_ab))) / i_scale
    assert err_sat < 1e-9 and err_const > 0.05, (err_sat, err_const)
    assert main(["replay", "--motor-file", str(motor), "--observer", "eso", "--data",
                 str(sim / "recording.npz"), "--no-plot", "--out",
                 str(tmp_path / "replay")]) == 0
    stats = json.loads((tmp_path / "replay" / "stats.json").read_text())
    assert stats["motor"] == "ipm3k5_sat" and (tmp_path / "replay" / "replay.npz").is_file()
