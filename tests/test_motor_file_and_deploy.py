"""Your own drive: motor files (round trip, validation, every command and the tuner accept
them) and deploying a tuned design (gains table -> observer, `--design`)."""

import json
import math
import pathlib
import re
import shutil
import subprocess

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
import tuning as tg
from pmsmjax.cli.__main__ import main
from pmsmjax.observers import make_observer

from .helpers import scheduled_gains_table


# ---------------------------------------------------------------------------------------
# Motor files
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", pj.PRESET_NAMES)
def test_motor_file_round_trip(name, tmp_path, capsys):
    """`pmsmjax motor --export NAME` -> `load_motor_file` gives the identical `Drive`
    (every parameter bit for bit, name and notes)."""
    path = tmp_path / name / "motor.toml"
    assert main(["motor", "--export", name, "--out", str(path.parent)]) == 0
    assert f"wrote {path}" in capsys.readouterr().out
    back = pj.load_motor_file(path)
    assert bool(eqx.tree_equal(back, pj.preset(name)))
    assert back.name == name and back.notes == pj.preset(name).notes
    # a saturated preset's flux map is the CSV written beside the motor file
    text = pj.motor_file_text(back, f"{path.stem}_flux_map.csv")
    assert pj.parse_motor_file(text, str(path)).dual == pj.preset(name).dual


_GOOD = pj.motor_file_text(pj.preset("zhang750"))


def _edit(old, new):
    assert old in _GOOD, old
    return _GOOD.replace(old, new, 1)


@pytest.mark.parametrize("text, fragment", [
    ("R_s = ", "not valid TOML"),                                     # syntax
    (_edit('format = "pmsmjax-motor"', 'format = "other"'), "format = 'other'"),
    (_edit("version = 1", "version = 2"), "version = 2: this pmsmjax reads motor-file version 1"),
    (_edit("[mechanics]", "[mech]"), "unknown field 'mech'; allowed in [top level]"),
    (_GOOD[:_GOOD.index("[ratings]")], "missing section [ratings]"),
    (_edit("R_s = 0.78", "# R_s"), "missing field [motor] R_s (stator resistance"),
    (_edit("R_s = 0.78", "R_s = 0.78\nR_S = 1.0"), "unknown field '[motor] R_S'"),
    (_edit("R_s = 0.78", 'R_s = "0.78"'), "[motor] R_s = '0.78' (Ohm): must be a finite"),
    (_edit("L_d = 0.00246", "L_d = -0.00246"), "[motor] L_d = -0.00246 (H): must be a "
                                               "finite number > 0"),
    (_edit("psi_f = 0.056", "psi_f = nan"), "[motor] psi_f = nan (V s)"),
    (_edit('type = "three-phase"', 'type = "five-phase"'), "type = 'five-phase': must be "
                                                           "one of"),
    (_edit('type = "three-phase"', 'type = "dual-three-phase"'), "missing field [motor] "
                                                                 "L_xy"),
    (_edit("n_p = 5.0", "n_p = 5.0\nL_xy = 1e-3"), "[motor] L_xy: only for type"),
    (_edit("[mechanics]", "[motor.harmonics]\norder = [1]\namplitude = [0.1]\n\n"
                          "[mechanics]"), "[motor.harmonics] order = [1]"),
    (_edit("[mechanics]", "[motor.harmonics]\norder = [-5, 7]\namplitude = [0.1]\n\n"
                          "[mechanics]"), "amplitude has 1 entries; must have one per "
                                          "order (2)"),
    (_edit("u_dc = 311.0", "u_dc = 311.0\nu_max = 300.0"), "[inverter]: `Inverter(u_max"),
    (_edit("w_rated = ", "n_rated_rpm = 2400.0\nw_rated = "), "give exactly one of w_rated"),
    (_edit("[base]\n", "[base]\nU_rated_ll = 220.0\n"), "give exactly one of U_b and "
                                                        "U_rated_ll"),
    (_edit("tau_rated = 2.4", "tau_rated = 0.0"), "[ratings] tau_rated = 0.0 (N m)"),
    (_edit("J = 0.0015", "J = true"), "[mechanics] J = True (kg m^2)"),
])
def test_malformed_motor_files_name_the_field(text, fragment):
    with pytest.raises(pj.MotorFileError) as e:
        pj.parse_motor_file(text, "my.toml")
    assert str(e.value).startswith("motor file my.toml: ")
    assert fragment in str(e.value), str(e.value)


def test_minimal_motor_file_defaults():
    """Optional fields: no [base] (U_b = u_dc/sqrt(3), I_b = i_max, w_b = w_rated),
    n_rated_rpm instead of w_rated, B = 0, no harmonics; the name from the file name."""
    d = pj.parse_motor_file(
        'format = "pmsmjax-motor"\nversion = 1\n[motor]\nR_s = 1.0\nL_d = 0.01\n'
        'L_q = 0.02\npsi_f = 0.1\nn_p = 2\n[mechanics]\nJ = 0.01\n[inverter]\n'
        'u_dc = 300.0\n[ratings]\nn_rated_rpm = 1500.0\ntau_rated = 5.0\ni_max = 10.0\n',
        "/somewhere/my_motor.toml")
    assert d.name == "my_motor" and not d.dual and float(d.mechanics.B) == 0.0
    assert d.w_rated == pytest.approx(2 * 2 * math.pi * 1500 / 60)
    assert d.base.U_b == pytest.approx(300 / math.sqrt(3)) and d.base.I_b == 10.0
    assert d.base.w_b == d.w_rated


def test_every_command_accepts_a_motor_file(tmp_path, capsys):
    """--motor-file in the shared drive options: the drive of the file, changed by --set;
    --motor with --motor-file and a malformed file are one-line errors (status 2)."""
    path = tmp_path / "mine.toml"
    path.write_text(_edit('name = "zhang750"', 'name = "mine"'))
    assert main(["equilibria", "--motor-file", str(path), "--set", "R_s=0.9", "--json",
                 "--speed", "0.5"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["motor"] == "mine" and s["motor_file"] == str(path)
    assert s["parameter_overrides"] == {"R_s": 0.9}
    assert main(["motor", "--motor", "stumper_mt5", "--motor-file", str(path)]) == 2
    assert "give one of the two" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text(_edit("J = 0.0015", "J = -1.0"))
    assert main(["motor", "--motor-file", str(bad), "--check"]) == 2
    err = capsys.readouterr().err
    assert "[mechanics] J = -1.0 (kg m^2): must be a finite number > 0" in err
    assert len(err.strip().splitlines()) == 1


def test_tuning_problem_from_a_motor_file(tmp_path):
    """TuningProblem(motor_file=..., set_params=...) tunes the file's drive (the same
    drive as the preset with the same replacement); the whole tuner on a motor file runs
    in tests/test_readme_commands.py (the README's "your own drive" example)."""
    path = tmp_path / "mine.toml"
    path.write_text(_edit('name = "zhang750"', 'name = "mine"'))
    cfg = tg.TuningProblem.quick(motor_file=str(path), set_params=(("J", 2e-3),))
    ref = tg.TuningProblem.quick(set_params=(("J", 2e-3),))
    assert cfg.drive().name == "mine" and cfg.motor_file == str(path)
    assert float(cfg.drive().mechanics.J) == 2e-3
    assert bool(eqx.tree_equal(cfg.drive().motor, ref.drive().motor))
    assert tg.DesignSpace(cfg).bounds_table() == tg.DesignSpace(ref).bounds_table()
    with pytest.raises(ValueError, match=r"\[motor\] R_s = -1.0"):
        path.write_text(_edit("R_s = 0.78", "R_s = -1.0"))
        tg.TuningProblem.quick(motor_file=str(path)).drive()
    with pytest.raises(ValueError, match="Unknown parameter 'X'"):
        tg.TuningProblem.quick(set_params=(("X", 1.0),)).drive()


def test_tuner_command_line_motor_file_errors(tmp_path, capsys):
    """`python -m tuning --motor-file`: a malformed file, or --motor with it, is a
    one-line error with exit status 2 before anything runs."""
    from tuning.__main__ import main as tuning_main

    bad = tmp_path / "bad.toml"
    bad.write_text(_edit("L_q = 0.00268", "L_q = 0"))
    assert tuning_main(["--motor-file", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "[motor] L_q = 0 (H): must be a finite number > 0" in capsys.readouterr().err
    good = tmp_path / "good.toml"
    good.write_text(_GOOD)
    assert tuning_main(["--motor", "stumper_mt5", "--motor-file", str(good), "--out",
                        str(tmp_path / "o")]) == 2
    assert "give one of the two" in capsys.readouterr().err
    assert tuning_main(["--set", "J=-1", "--out", str(tmp_path / "o")]) == 2
    assert "`Mechanics(J=...)` (kg m^2) must be finite and > 0" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


# ---------------------------------------------------------------------------------------
# Deploying a tuned design: gains table
# ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tuned():
    """A speed-scheduled table (zhang2022 (38) with other w2, zeta2) and its observer."""
    cfg = tg.TuningProblem.quick()
    table, obs = scheduled_gains_table(cfg.drive(), cfg.T_s)
    return cfg, obs, table


def test_gains_table_gives_the_tuned_gains(tuned):
    """Between the rows (half a step off) and at currents != 0 the table's gains match the
    schedule's within the interpolation error (1 % of the gain; the largest error is at
    the first row next to standstill, where the flux gains vanish); at the rows exactly;
    the gain columns are the gains at i_dq = 0."""
    cfg, gs, table = tuned
    drive = cfg.drive()
    m = drive.three_phase_motor
    a = gs
    b = pj.apply_gains_table(table, make_observer("eso", drive))
    cols = {c: np.array([r[j] for r in table["rows"]]) for j, c in
            enumerate(table["columns"])}
    w = cols["w_m"]
    step = w[1] - w[0]
    assert w[0] == -w[-1] and w[-1] >= 1.5 * float(drive.w_rated) - 1e-9
    for w0 in np.concatenate([w[::7], 0.5 * (w[1:] + w[:-1])[::5]]):
        for i_dq in ([0.0, 0.0], [-1.0, 4.0]):
            ga = a.linear_gains(jnp.asarray(w0), jnp.asarray(i_dq))
            gb = b.linear_gains(jnp.asarray(w0), jnp.asarray(i_dq))
            for x, y in ((ga.G1, gb.G1), (ga.g2, gb.g2), (ga.g3, gb.g3)):
                x, y = np.asarray(x), np.asarray(y)
                tol = 1e-12 if np.any(np.isclose(w0, w, rtol=0, atol=1e-9)) else 1e-2
                assert np.max(np.abs(x - y)) <= tol * np.max(np.abs(x)) + 1e-12, (w0, i_dq)
    j = len(w) // 2 + 11  # a positive speed
    g = a.linear_gains(jnp.asarray(w[j]), jnp.zeros(2))
    np.testing.assert_allclose([cols["G1_11"][j], cols["G1_21"][j], cols["g3_2"][j]],
                               [g.G1[0, 0], g.G1[1, 0], g.g3[1]], rtol=1e-12)
    assert step / float(drive.w_rated) == pytest.approx(0.025)
    # float32 works and stays float32
    m32 = pj.astype(m, jnp.float32)
    g32 = b.design(m32, jnp.float32(w[j]), jnp.zeros(2, jnp.float32))
    assert g32.G1.dtype == g32.g3.dtype == jnp.float32
    np.testing.assert_allclose(g32.G1, g.G1, rtol=1e-5, atol=1e-3)


def test_gains_table_round_trip_estimates(tuned, tmp_path):
    """tuned design -> gains.json -> observer from the table: the same estimates as the
    tuned design on a recording, within the interpolation error."""
    cfg, gs, table = tuned
    drive = cfg.drive()
    paths = pj.write_gains_table(table, tmp_path)
    back = pj.load_gains_table(tmp_path)  # the folder, as --design takes it
    assert back == json.loads(json.dumps(table))
    w_r = float(drive.w_rated)
    sc = pj.Scenario(t_end=0.15, w_m_imposed=pj.Profile.ramp(0.0, 0.15, 0.3 * w_r, 0.9 * w_r),
                     i_d_ref=pj.Profile.constant(0.0), i_q_ref=pj.Profile.constant(2.0))
    traj = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver.from_drive(drive),
                       sc, T_s=cfg.T_s, w_m0=0.3 * w_r)
    rec = pj.RecordedData.from_trajectory(traj)
    kw = dict(theta0=-0.5, w0=float(rec.w_m[0]))  # converge from a 29 deg angle error
    ea = pj.replay_estimates(gs, rec, **kw)
    eb = pj.replay_estimates(pj.apply_gains_table(back, make_observer("eso", drive)), rec,
                             **kw)
    d_theta = np.degrees(np.abs(np.asarray(pj.wrap_angle(ea.theta_hat - eb.theta_hat))))
    assert d_theta.max() < 0.05  # measured 0.007 deg
    assert np.max(np.abs(np.asarray(ea.w_hat - eb.w_hat))) < 1e-4 * w_r  # 0.015 rad/s
    # CSV: the same numbers; C header: compiles (where a C compiler is installed)
    csv = np.loadtxt(paths["csv"], delimiter=",", skiprows=1)
    np.testing.assert_array_equal(csv, np.asarray(table["rows"]))
    text = pathlib.Path(paths["c"]).read_text()
    assert f"#define PMSMJAX_GAINS_N_ROWS {len(table['rows'])}" in text
    if shutil.which("gcc"):
        subprocess.run(["gcc", "-fsyntax-only", "-Wall", "-x", "c", paths["c"]], check=True)


def test_design_option_in_replay_and_simulate(tuned, tmp_path, capsys):
    """`simulate --design` and `replay --design` run the table's observer and design:
    replay.npz holds the estimates of `apply_gains_table`."""
    cfg, gs, table = tuned
    drive = cfg.drive()
    pj.write_gains_table(table, tmp_path / "tuned")
    sim = tmp_path / "sim"
    assert main(["simulate", "--design", str(tmp_path / "tuned" / "gains.json"),
                 "--scenario", "load-step", "--speed", "0.4", "--t-end", "0.1", "--no-plot",
                 "--out", str(sim)]) == 0
    s = json.loads((sim / "summary.json").read_text())
    assert s["observer"] == "eso" and s["status"] == "successful"
    assert s["design_file"].endswith("gains.json")
    rep = tmp_path / "rep"
    assert main(["replay", "--design", str(tmp_path / "tuned"), "--data",
                 str(sim / "recording.npz"), "--no-plot", "--out", str(rep)]) == 0
    rec = pj.load_recording(sim / "recording.npz")
    est = pj.replay_estimates(pj.apply_gains_table(table, make_observer("eso", drive)), rec)
    with np.load(rep / "replay.npz") as f:
        np.testing.assert_array_equal(f["theta_hat"], np.asarray(est.theta_hat))
    capsys.readouterr()
    assert main(["replay", "--design", str(tmp_path / "tuned"), "--observer", "leso",
                 "--data", str(sim / "recording.npz"), "--out", str(rep)]) == 2
    assert "is a design of the eso observer" in capsys.readouterr().err
    assert main(["replay", "--design", str(tmp_path / "tuned"), "--w2", "300",
                 "--data", str(sim / "recording.npz"), "--out", str(rep)]) == 2
    assert "not allowed with it" in capsys.readouterr().err
    assert main(["replay", "--design", str(tmp_path), "--data",
                 str(sim / "recording.npz"), "--out", str(rep)]) == 2
    assert "no gains table there" in capsys.readouterr().err


def test_gains_table_carries_sampling_period_objective_and_verdict(tuned, tmp_path, capsys):
    """The table records the sampling period, the objective and the tuner's verdict; a
    verdict that does not hold (or none) makes gains.h warn when compiled (unless
    PMSMJAX_GAINS_ACCEPT_UNVALIDATED is defined) and `--design` warn on the console."""
    cfg, gs, _ = tuned
    failed = {"holds": False, "baseline": "zhang2022 (38)/(25)",
              "where_not": ["validation: 85 of 88 scenarios worse", "held-out: worse"]}
    table, _ = scheduled_gains_table(cfg.drive(), cfg.T_s, verdict=failed)
    assert table["T_s"] == cfg.T_s and table["objective"] == "cvar"
    assert table["verdict"] == failed
    ok, _ = scheduled_gains_table(cfg.drive(), cfg.T_s,
                                  verdict=dict(failed, holds=True, where_not=[]))
    assert pj.verdict_warning(ok) is None
    msg = pj.verdict_warning(table)
    assert "did NOT beat zhang2022 (38)/(25)" in msg and "85 of 88" in msg
    assert "and 1 more" in msg
    old = {k: v for k, v in table.items() if k not in ("verdict", "T_s", "objective")}
    assert "records no tuner verdict" in pj.verdict_warning(pj.check_gains_table(old))
    for bad, what in (({"T_s": -1.0}, "T_s"), ({"T_s": True}, "T_s"),
                      ({"verdict": {"holds": "no"}}, "verdict"),
                      ({"verdict": {"holds": False, "where_not": [1]}}, "where_not")):
        with pytest.raises(ValueError, match=what):
            pj.check_gains_table({**table, **bad})
    # gains.h: the period as a define, the verdict as a define and a compiler warning
    for name, t in (("failed", table), ("ok", ok), ("old", old)):
        pj.write_gains_table(t, tmp_path / name)
    text = (tmp_path / "failed" / "gains.h").read_text()
    T_s = float(re.search(r"#define PMSMJAX_GAINS_T_S (\S+)", text).group(1))
    assert T_s == cfg.T_s
    assert "#define PMSMJAX_GAINS_VERDICT_HOLDS 0" in text
    assert "#define PMSMJAX_GAINS_VERDICT_HOLDS 1" in (tmp_path / "ok" / "gains.h").read_text()
    if shutil.which("gcc"):
        def warnings(name, *flags):
            p = subprocess.run(["gcc", "-fsyntax-only", "-Wall", *flags, "-x", "c",
                                str(tmp_path / name / "gains.h")], capture_output=True,
                               text=True, check=True)
            return p.stderr

        assert "did NOT beat" in warnings("failed")
        assert "records no tuner verdict" in warnings("old")
        assert warnings("ok") == ""
        assert warnings("failed", "-DPMSMJAX_GAINS_ACCEPT_UNVALIDATED") == ""
    # the console: --design warns about the verdict and a different sampling period
    sim = tmp_path / "sim"
    capsys.readouterr()
    assert main(["simulate", "--design", str(tmp_path / "failed"), "--scenario",
                 "load-step", "--speed", "0.4", "--t-end", "0.05", "--T-s",
                 str(2 * cfg.T_s), "--no-plot", "--out", str(sim)]) == 0
    err = capsys.readouterr().err
    assert "did NOT beat" in err and f"tuned at T_s = {cfg.T_s:g} s" in err
    assert main(["simulate", "--design", str(tmp_path / "ok"), "--scenario", "load-step",
                 "--speed", "0.4", "--t-end", "0.05", "--T-s", str(cfg.T_s), "--no-plot",
                 "--out", str(sim)]) == 0
    assert "warning" not in capsys.readouterr().err


def test_a_motor_file_without_base_says_which_bases_it_takes(tmp_path):
    """Without [base] the bases are the inverter's linear range and the current limit,
    not the rated values of docs/conventions.md: the reading notes say so, with the
    numbers, so the same `--i-q 0.5` is not silently twice the preset's current."""
    from pmsmjax._plant._motorfile import read_motor_file

    text = pj.motor_file_text(pj.preset("zhang750"))
    head, _ = text.split("[base]")
    (tmp_path / "m.toml").write_text(head)
    drive, notes = read_motor_file(tmp_path / "m.toml")
    i_max = float(pj.preset("zhang750").i_max)
    assert float(drive.base.I_b) == i_max
    assert any("no [base] section" in n and f"I_b = {i_max:.4g} A" in n for n in notes)
    example = pathlib.Path(__file__).parents[1] / "docs" / "examples" / "zhang750.toml"
    _, notes = read_motor_file(example)
    assert not any("[base]" in n for n in notes)
