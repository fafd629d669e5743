"""The `pmsmjax` command line, run in-process through `main([...])`."""

import argparse
import contextlib
import io
import json

import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.cli.__main__ import COMMANDS, build_parser, main
from pmsmjax.observers import make_observer

from .helpers import lock_status_loop, read_npz


# s: the built-in default run's length (`simulate` without --t-end). The module's
# recording is that run: test_simulate_default_run checks it as the default, the other
# tests replay it and re-run its plant (12000 samples, run times well below a second;
# one compiled program less than a separate shorter run)
T_END = 1.5
DRIVE = pj.preset("zhang750")

SIMULATE_KEYS = {
    "motor", "preset_notes", "scenario", "T_s", "steps", "wall_time_s", "compile_time_s",
    "run_time_s", "final_speed", "speed_error_after_settling", "max_current", "status",
}


def _main_printing(argv):
    """`main(argv)` with its standard output captured (for module-scoped runs, where the
    function-scoped `capsys` is not available): `(exit status, printed text)`."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        status = main(argv)
    return status, buf.getvalue()


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    """`pmsmjax simulate --out DIR`: the built-in default run; `(DIR, printed text)`."""
    out = tmp_path_factory.mktemp("simulate")
    status, printed = _main_printing(["simulate", "--out", str(out)])
    assert status == 0
    return out, printed


@pytest.fixture(scope="module")
def sim_dir(sim_run):
    return sim_run[0]


def test_simulate_writes_files(sim_dir):
    for name in ("trajectory.npz", "recording.npz", "summary.json", "simulation.png"):
        assert (sim_dir / name).stat().st_size > 0, name
    summary = json.loads((sim_dir / "summary.json").read_text())
    assert SIMULATE_KEYS <= set(summary)
    assert summary["motor"] == "zhang750"
    assert summary["preset_notes"] == pj.preset("zhang750").notes
    assert summary["status"] == "successful"
    assert summary["T_s"] == 125e-6
    assert summary["steps"] == round(T_END / 125e-6)
    assert summary["scenario"]["name"] == "default"
    assert "load step" in summary["scenario"]["description"]
    assert summary["max_current"]["A"] > 0

    traj = read_npz(sim_dir / "trajectory.npz")
    # extras: under their own names (none when sensored); the x-y subspace only for a dual
    # three-phase drive
    fields = {f for f in pj.Trajectory.__dataclass_fields__} - {"extras", "i_xy", "u_xy"}
    assert fields <= set(traj) and not {"i_xy", "u_xy"} & set(traj)
    assert traj["t"].shape == (summary["steps"],)
    assert traj["i_dq"].shape == (summary["steps"], 2)
    assert int(traj["status"]) == 0

    rec = pj.load_recording(sim_dir / "recording.npz")
    assert rec.names == ("t", "u_ab", "i_ab", "theta", "w_m", "tau_L")
    np.testing.assert_array_equal(rec.u_ab, traj["u_ab"])
    np.testing.assert_array_equal(rec.i_ab, traj["i_meas_ab"])
    assert summary["final_speed"]["rad_s"] == pytest.approx(float(rec.w_m[-1]))


@pytest.fixture(scope="module")
def if_start_run(tmp_path_factory):
    """A sensorless run from standstill at an unknown angle without a plot: `simulate
    --observer c-leso --scenario ramp --t-end 0.6 --theta-hat0 114.59 --no-plot`;
    `(DIR, printed text)`. One compiled program for the two tests that read it."""
    out = tmp_path_factory.mktemp("if_start")
    status, printed = _main_printing(["simulate", "--observer", "c-leso", "--scenario",
                                      "ramp", "--t-end", "0.6", "--theta-hat0", "114.59",
                                      "--no-plot", "--out", str(out)])
    assert status == 0
    return out, printed


def test_simulate_prints_summary(if_start_run):
    out_dir, out = if_start_run
    assert "compiling..." in out
    assert "final speed" in out
    assert str(out_dir / "summary.json") in out
    assert not (out_dir / "simulation.png").exists()
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["scenario"]["load_pu"] is None


def test_replay_writes_every_estimate(sim_dir, tmp_path, capsys):
    """`replay --observer eso`: replay.npz holds the inputs, theta_hat, w_hat and every
    extra of the Estimate (the zhang2022 observers' psi_ab_hat), the numbers of
    `pj.replay_estimates` with the registry's observer."""
    out = tmp_path / "replay"
    assert main(["replay", "--observer", "eso", "--data", str(sim_dir / "recording.npz"),
                 "--t-settle", "0.1", "--out", str(out)]) == 0
    assert "angle error after 0.1 s" in capsys.readouterr().out
    for name in ("replay.npz", "stats.json", "replay.png"):
        assert (out / name).stat().st_size > 0, name
    rec = pj.load_recording(sim_dir / "recording.npz")
    est = pj.replay_estimates(make_observer("eso", DRIVE), rec)
    with np.load(out / "replay.npz", allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    assert set(data) == {"t", "u_ab", "i_ab", "theta", "w_m", "tau_L", "theta_hat", "w_hat",
                         "psi_ab_hat"}
    assert data["psi_ab_hat"].shape == (rec.n, 2)
    np.testing.assert_array_equal(data["psi_ab_hat"], np.asarray(est.extras["psi_ab_hat"]))
    np.testing.assert_array_equal(data["theta_hat"], np.asarray(est.theta_hat))
    np.testing.assert_array_equal(data["u_ab"], rec.u_ab)
    # still a recording: load_recording reads it (and ignores the extras)
    assert pj.load_recording(out / "replay.npz").names[-2:] == ("theta_hat", "w_hat")
    stats = json.loads((out / "stats.json").read_text())
    assert stats["observer"] == "eso" and stats["t_settle"] == 0.1
    assert stats["arrays"]["psi_ab_hat"].startswith("V s")
    assert stats["observer_details"]["design"]["w2"] == pytest.approx(2 * np.pi * 50)


def test_replay_flying_start_catches_a_turning_rotor(tmp_path, capsys):
    """A log that starts with the rotor turning at 0.5 p.u.: with no initial estimate
    (the default) and with `--flying-start` the ESO starts at the angle and speed read off
    the first samples and is locked (within 5 deg, the load steps included) from the
    start; from a given zero estimate (`--speed0 0`) it is not."""
    rec_dir = tmp_path / "sim"
    assert main(["simulate", "--scenario", "load-step", "--t-end", "0.1", "--no-plot",
                 "--out", str(rec_dir)]) == 0
    errs, starts = {}, {}
    for key, flag in (("default", []), ("flying", ["--flying-start"]),
                      ("zero", ["--speed0", "0"])):
        out = tmp_path / key
        assert main(["replay", "--observer", "eso", "--data",
                     str(rec_dir / "recording.npz"), "--no-plot", "--out", str(out),
                     *flag]) == 0
        with np.load(out / "replay.npz") as f:
            errs[key] = np.abs(np.asarray(pj.wrap_angle(f["theta"] - f["theta_hat"])))
        stats = json.loads((out / "stats.json").read_text())
        assert stats["initial_estimate"]["flying_start"] is (key == "flying")
        starts[key] = stats["initial_estimate"]["start"]
    printed = capsys.readouterr().out
    assert "flying start: theta0" in printed
    assert "start: a turning rotor caught from the first samples" in printed
    assert starts == {"default": "caught turning", "flying": "flying start", "zero": "given"}
    assert errs["flying"].max() < np.radians(5.0)  # the lock tolerance of lock_basin
    assert errs["default"].max() < np.radians(5.0)
    assert errs["zero"][-100:].max() > np.radians(30.0)


def test_replay_observer_model_and_gains(sim_dir, tmp_path):
    """--observer-set changes the observer's machine model (not the plant's), --gain a
    design parameter; the shorthand --bandwidth HZ is --gain w2=2 pi HZ."""
    out = tmp_path / "leso"
    assert main(["replay", "--observer", "leso", "--observer-set", "L_q=3e-3",
                 "--observer-set", "R_s=0.9", "--gain", "zeta2=0.8", "--bandwidth", "80",
                 "--data", str(sim_dir / "recording.npz"), "--no-plot", "--out",
                 str(out)]) == 0
    assert not (out / "replay.png").exists()
    motor = pj.replace_params(DRIVE, L_q=3e-3, R_s=0.9).motor
    obs = make_observer("leso", DRIVE, motor=motor, zeta2=0.8, w2=2 * np.pi * 80)
    est = pj.replay_estimates(obs, pj.load_recording(sim_dir / "recording.npz"))
    with np.load(out / "replay.npz", allow_pickle=False) as f:
        np.testing.assert_array_equal(f["theta_hat"], np.asarray(est.theta_hat))
        np.testing.assert_array_equal(f["psi_ab_hat"], np.asarray(est.extras["psi_ab_hat"]))
    stats = json.loads((out / "stats.json").read_text())
    model = stats["observer_details"]["model"]
    assert model["L_q"] == 3e-3 and model["R_s"] == 0.9 and model["L_d_ratio"] == 1.0
    assert stats["observer_details"]["mismatch"]
    assert stats["observer_details"]["design"]["given"] == {"w2": pytest.approx(
        2 * np.pi * 80), "zeta2": 0.8}


def test_simulate_with_a_sensorless_observer(tmp_path, capsys):
    """`simulate --observer NAME` runs any observer of the registry in the loop; its
    extras go into trajectory.npz under their names."""
    # 0.1 s: the length of the recording of test_replay_flying_start_..., whose lock
    # judge (compiled for that length) runs again
    assert main(["simulate", "--observer", "eso", "--gain", "w2=400", "--scenario",
                 "load-step", "--t-end", "0.1", "--no-plot", "--out", str(tmp_path)]) == 0
    assert "observer eso, w2 = 400" in capsys.readouterr().out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["observer"] == "eso" and summary["status"] == "successful"
    assert summary["observer_details"]["design"]["w2"] == 400
    traj = read_npz(tmp_path / "trajectory.npz")
    assert traj["psi_ab_hat"].shape == (summary["steps"], 2)


def test_simulate_starts_a_sensorless_drive_with_the_if_start(if_start_run, tmp_path):
    """`--startup auto` picks the I/f start for a sensorless observer from standstill
    (and none for a rotor that starts turning); from an unknown angle the C-LESO drive
    reaches the set-point."""
    out, printed = if_start_run
    assert "start-up: I/f" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["controller"]["startup"]["type"] == "I/f"
    assert summary["theta_hat0_deg"] == 114.59
    assert abs(summary["final_speed"]["pu"] - 0.5) < 0.01
    # the turning rotor: the run of test_simulate_with_a_sensorless_observer (the ESO,
    # load-step, 0.1 s), whose compiled program this one runs again
    assert main(["simulate", "--observer", "eso", "--scenario", "load-step", "--t-end",
                 "0.1", "--no-plot", "--out", str(tmp_path / "b")]) == 0
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    # the rotor turns from the start: the catch, not the I/f start
    assert summary["controller"]["startup"] == {"type": "catch", "window_samples": 64}


def test_if_damping_starts_the_ipm_from_an_unknown_angle(tmp_path, capsys):
    """`--if-damping 0.7` turns on the I/f start's stabiliser: on morawiec_ipm3k5 from
    2 rad (114.59 deg) off, where the plain start leaves the rotor swinging backwards
    (`tests/test_startup.py`), the ESO drive reaches the set-point (measured 1.3 % over
    it at 0.5 s, still settling) and the summary records the stabiliser's gain."""
    assert main(["simulate", "--motor", "morawiec_ipm3k5", "--observer", "eso",
                 "--scenario", "ramp", "--t-end", "0.5", "--theta-hat0", "114.59",
                 "--if-damping", "0.7", "--no-plot", "--out", str(tmp_path)]) == 0
    assert "stabiliser c_damp" in capsys.readouterr().out
    summary = json.loads((tmp_path / "summary.json").read_text())
    su = pj.IfStartup.from_drive(pj.preset("morawiec_ipm3k5"), zeta=0.7)
    assert summary["controller"]["startup"]["stabiliser_c_damp_s"] == pytest.approx(
        float(su.c_damp), rel=1e-12)
    assert abs(summary["final_speed"]["pu"] - 0.5) < 0.02
    # and the observer holds the rotor's angle by then (measured: within 1.2 deg over the
    # last 0.1 s; the lock judge's start, the first sample above the handover speed,
    # falls inside the rotor's swing and reports the transient before the lock as lost)
    traj = read_npz(tmp_path / "trajectory.npz")
    last = traj["t"] >= traj["t"][-1] - 0.1
    assert np.degrees(np.abs(traj["theta_err"][last])).max() < 3.6


def test_python_m_pmsmjax():
    """`python -m pmsmjax` (the shim `pmsmjax/__main__.py`) runs the same command line."""
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-m", "pmsmjax", "--version"], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.startswith("pmsmjax "), res
    res = subprocess.run([sys.executable, "-m", "pmsmjax", "equilibria", "--gain", "x=1"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "no design parameter 'x'" in res.stderr, res


def test_plant_reproduces_simulation(sim_dir, tmp_path):
    """`plant` on the recording of `simulate` is the same plant driven by the same ZOH
    voltages from the same initial state, with the same RK4 step (1 substep per T_s): the
    two runs perform the same floating-point operations up to reordering by the compiler,
    so they agree to rounding level (~1e-15 relative per step, growing at most linearly
    over 12000 stable steps). 1e-9 relative leaves a wide margin for that and is still far
    below any modelling difference (4 substeps instead of 1 already differ by ~1e-6)."""
    out = tmp_path / "plant"
    assert main(["plant", "--data", str(sim_dir / "recording.npz"), "--substeps", "1",
                 "--out", str(out)]) == 0
    rec = pj.load_recording(sim_dir / "recording.npz")
    sim = pj.load_recording(out / "plant.npz")
    assert sim.names == ("t", "u_ab", "i_ab", "theta", "w_m", "tau_L")
    np.testing.assert_array_equal(sim.t, rec.t)
    np.testing.assert_array_equal(sim.u_ab, rec.u_ab)
    np.testing.assert_array_equal(sim.tau_L, rec.tau_L)
    drive = pj.preset("zhang750")
    i_scale = np.max(np.abs(rec.i_ab))
    assert i_scale > 0.1 * drive.base.I_b  # the run did draw current
    np.testing.assert_allclose(sim.i_ab, rec.i_ab, rtol=0, atol=1e-9 * i_scale)
    np.testing.assert_allclose(sim.w_m, rec.w_m, rtol=0,
                               atol=1e-9 * np.max(np.abs(rec.w_m)))
    np.testing.assert_allclose(np.asarray(pj.wrap_angle(sim.theta - rec.theta)), 0.0,
                               atol=1e-9)
    summary = json.loads((out / "summary.json").read_text())
    cmp = summary["comparison_with_data"]
    assert set(cmp) == {"i_ab", "theta", "w_m"}
    assert cmp["i_ab"]["rms_diff"] < 1e-9 * i_scale
    assert (out / "plant.png").stat().st_size > 0


def test_plant_csv_and_substeps(sim_dir, tmp_path, capsys):
    """CSV output; with 2 RK4 substeps instead of 1 the comparison sees the (small)
    integration-error difference, which scales as RK4's error does."""
    out = tmp_path / "plant_csv"
    assert main(["plant", "--data", str(sim_dir / "recording.npz"), "--format", "csv",
                 "--substeps", "2", "--no-plot", "--out", str(out)]) == 0
    assert "simulated - recorded i_ab: rms" in capsys.readouterr().out
    sim = pj.load_recording(out / "plant.csv")
    rec = pj.load_recording(sim_dir / "recording.npz")
    rms = json.loads((out / "summary.json").read_text())["comparison_with_data"]["i_ab"]
    d = np.sqrt(np.mean(np.sum((sim.i_ab - rec.i_ab) ** 2, axis=-1)))
    assert d == pytest.approx(rms["rms_diff"], rel=1e-6)
    # the difference is RK4's truncation error of the recording's single step: error
    # C h^4, so 1 against 2 substeps differs by (1 - 1/16) of it and 1 against 4 by
    # (1 - 1/256): Richardson's ratio 0.941 (measured 0.9425; 1e-2 for the higher-order terms)
    out4 = tmp_path / "plant_4"
    assert main(["plant", "--data", str(sim_dir / "recording.npz"), "--substeps", "4",
                 "--no-plot", "--out", str(out4)]) == 0
    d4 = json.loads((out4 / "summary.json").read_text())["comparison_with_data"]["i_ab"]
    assert rms["rms_diff"] / d4["rms_diff"] == pytest.approx((15 / 16) / (255 / 256),
                                                             rel=1e-2)


def test_plant_minimal_input(tmp_path):
    """Only t and u_ab: a locked-rotor-like start from rest with zero load, no comparison."""
    n = 12000  # the length of the module's recording: its plant program runs again
    t = np.arange(n) * 125e-6
    u_ab = np.tile([5.0, 0.0], (n, 1))  # a constant d-axis voltage at theta = 0
    path = tmp_path / "in.csv"
    pj.save_recording(path, pj.RecordedData(t=t, u_ab=u_ab))
    out = tmp_path / "out"
    assert main(["plant", "--data", str(path), "--substeps", "1", "--no-plot",
                 "--out", str(out)]) == 0
    sim = pj.load_recording(out / "plant.npz")
    np.testing.assert_array_equal(sim.tau_L, 0.0)
    # d-axis voltage on a rotor at angle 0: no torque, the rotor stays put and
    # i_d -> u / R_s (time constant L_d / R_s = 3.2 ms, 1.5 s simulated).
    motor = pj.preset("zhang750").motor
    assert sim.i_ab[-1, 0] == pytest.approx(5.0 / motor.R_s, rel=1e-4)
    assert json.loads((out / "summary.json").read_text())["comparison_with_data"] == {}


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help(command, capsys):
    argv = ["--help"] if command is None else [command, "--help"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: pmsmjax")
    if command not in (None, "cache", "worker"):  # these two work on no drive
        assert "--motor" in out and "--set" in out and "--out" in out


def test_every_option_has_help():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(sub.choices) == set(COMMANDS) >= {"simulate", "plant"}
    for name, p in sub.choices.items():
        for action in p._actions:
            assert action.help, f"{name} {action.option_strings} has no help"


def test_a_command_is_its_module_and_one_line():
    """Every module that `COMMAND_MODULES` lists registers its `COMMAND`, in that order;
    every module of the package that defines a `COMMAND` is listed; the reference of
    docs/cli.md (written from the parsers) has a section for every command."""
    import importlib
    import pkgutil

    import pmsmjax.cli
    from pmsmjax.cli.__main__ import COMMAND_MODULES
    from pmsmjax.cli._reference import reference_markdown

    def module(name):
        return importlib.import_module(f"pmsmjax.cli.{name}")

    assert list(COMMANDS.values()) == [module(m).COMMAND for m in COMMAND_MODULES]
    defining = {m.name for m in pkgutil.iter_modules(pmsmjax.cli.__path__)
                if m.name != "__main__" and hasattr(module(m.name), "COMMAND")}
    assert defining == set(COMMAND_MODULES)
    text = reference_markdown()
    for name in COMMANDS:
        assert f"## `pmsmjax {name}`" in text, name


@pytest.mark.parametrize("command, argv, observer, work", [
    ("equilibria", ["--zeta1", "0.5", "--ratio", "0.5"], "eso, zeta1 = 0.5",
     "equilibria_report"),
    ("feasibility", ["--zeta1", "0:5:3", "--ratio", "0:2:3"], "eso", "_map"),
    ("certify", ["--quick"], "eso", "certificate_report"),  # the ESO, as everywhere
    ("response", [], "eso", "response_report"),
    ("gains", ["--design", "TABLE"], "eso of the gains table", "gains_check"),
])
def test_an_analysis_names_its_observer_and_motor_first(command, argv, observer, work,
                                                        tmp_path, capsys, monkeypatch):
    """The first console line of every analysis command names the observer and the motor
    it analyses, printed before the work starts (stopped here by a stand-in)."""
    import importlib

    from pmsmjax.cli import CLIError

    def stop(*args, **kwargs):
        raise CLIError("stopped after the first line")

    monkeypatch.setattr(importlib.import_module(f"pmsmjax.cli._{command}"), work, stop)
    drive = pj.replace_params(DRIVE, J=2e-3)
    paper = make_observer("eso", drive)
    table = pj.gains_table_constant("eso", dict(paper.design_parameters()),
                                    dict(type(paper).design_units), drive=drive.name)
    pj.write_gains_table(table, tmp_path / "table")
    argv = [str(tmp_path / "table") if a == "TABLE" else a for a in argv]
    assert main([command, "--set", "J=0.002", *argv, "--out", str(tmp_path / "out")]) == 2
    captured = capsys.readouterr()
    first = captured.out.splitlines()[0]
    assert first.startswith(f"pmsmjax {command}: motor zhang750 with J = 0.002; observer "
                            f"{observer}"), first
    assert "stopped after the first line" in captured.err


def _write_bad_csv(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("t,i_ab_a,i_ab_b\n0,0,0\n0.000125,0,0\n")
    return path


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["simulate", "--motor", "nosuchmotor"], "invalid choice: 'nosuchmotor'"),
        (["simulate", "--set", "J"], "NAME=VALUE"),
        (["simulate", "--set", "J=heavy"], "not a number"),
        (["simulate", "--set", "Jx=1e-3"], "Unknown parameter 'Jx'"),
        (["simulate", "--set", "J=-1"], "`Mechanics(J=...)` (kg m^2) must be finite and > 0"),
        (["simulate", "--t-end", "-1"], "must be a finite number > 0"),
        (["simulate", "--scenario", "nope"], "invalid choice"),
        (["simulate", "--scenario", "ramp", "--load", "0.3"], "--load is not used"),
        (["simulate", "--T-s", "0.01"], "too long for RK4"),
        (["plant", "--out", "OUT"], "required: --data"),
        (["plant", "--data", "DIR/none.npz", "--out", "OUT"], "No such file"),
        (["plant", "--data", "DIR/data.json", "--out", "OUT"], "unknown file extension"),
        (["plant", "--data", "BADCSV", "--out", "OUT"], "missing: `u_ab` (V)"),
        (["simulate", "--observer", "kalman"],
         "argument --observer: invalid choice: 'kalman' (choose from 'sensored', 'eso'"),
        (["simulate", "--gain", "w2=300"],
         "--gain w2=300: the sensored observer has no design parameter 'w2'; allowed: none"),
        (["simulate", "--observer", "leso", "--gain", "eta=0.01"],
         "--gain eta=0.01: the leso observer has no design parameter 'eta'; allowed: w2,"),
        (["simulate", "--observer", "eso", "--observer-set", "J=1"],
         "--observer-set J=1: unknown parameter 'J' of the observer's machine model; "
         "allowed: R_s (Ohm), L_d (H), L_q (H), psi_f (V s)"),
        (["simulate", "--startup", "if"], "--startup if needs a sensorless observer"),
        (["simulate", "--observer", "eso", "--observer-set", "psi_f=-0.1"],
         "--observer-set psi_f=-0.1: `PMSMParams(psi_f=...)` (V s) must be finite and >= 0"),
        (["replay", "--data", "DIR/none.npz", "--out", "OUT", "--observer", "afo", "--gain",
          "ratio=0.5"], "the fixed_ratio flux schedule needs zeta1 as well"),
        (["replay", "--data", "DIR/none.npz", "--out", "OUT", "--zeta1", "1"],
         "--zeta1 1: give --zeta1 with --ratio"),
        (["replay", "--data", "DIR/none.npz", "--out", "OUT", "--schedule", "zhang38",
          "--ratio", "1"], "--ratio: not used by --schedule zhang38"),
        (["frobnicate"], "invalid choice: 'frobnicate'"),
        ([], "required: COMMAND"),
    ],
)
def test_bad_inputs_exit_2(argv, fragment, tmp_path, capsys):
    (tmp_path / "data.json").write_text("{}")
    subs = {"OUT": str(tmp_path / "out"), "BADCSV": str(_write_bad_csv(tmp_path))}
    argv = [subs.get(a, a.replace("DIR", str(tmp_path))) for a in argv]
    if argv and argv[0] == "simulate":
        argv += ["--out", str(tmp_path / "out"), "--no-plot"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err  # one line, no traceback
    assert "Traceback" not in err
    assert err.startswith("pmsmjax")
    assert fragment in err


def test_a_runaway_rotor_diverges_and_exits_1(tmp_path, capsys):
    """A real divergence, nothing injected: an overhauling load of 400 p.u. drives the
    rotor past the simulator's bound of 20 x the rated speed within the run. The files
    are still written, the summary and stderr say "diverged", the exit status is 1; the
    recorded speed is the mechanical equation's (a trapezoid of the recorded torques, by
    NumPy), frozen at the last good sample, from which the next step leaves the bound."""
    # 0.1 s: the length of the load-step recording of
    # test_replay_flying_start_catches_a_turning_rotor, whose compiled program this runs
    assert main(["simulate", "--scenario", "load-step", "--load", "-400", "--t-end", "0.1",
                 "--no-plot", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "pmsmjax simulate: the run diverged" in err and "20 w_rated" in err
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["status"] == "diverged" and summary["lock"]["status"] == "diverged"
    assert "diverged" in summary["status_message"] and summary["lock"]["lost"]
    tr = read_npz(tmp_path / "trajectory.npz")
    assert int(tr["status"]) != 0
    assert pj.load_recording(tmp_path / "recording.npz").n == tr["t"].size
    t, w = tr["t"], tr["w_m"]
    T_s, w_r = t[1] - t[0], float(DRIVE.w_rated)
    assert summary["lock"]["t_lost_s"] == pytest.approx(t[-1])  # diverged: lost at the end
    frozen = np.flatnonzero(np.diff(w) == 0.0)
    k0 = int(frozen[0])  # the last good sample; nothing moves after it
    assert np.all(np.diff(w[k0:]) == 0.0) and np.all(np.diff(tr["i_dq"][k0:], axis=0) == 0)
    m = DRIVE.mechanics
    n_p, J, B = float(DRIVE.motor.n_p), float(m.J), float(m.B)
    rate = n_p * (tr["tau_M"] - B * w / n_p - tr["tau_L"]) / J  # dw/dt (rad/s^2)
    kl = int(np.flatnonzero(tr["tau_L"] < 0)[0])
    gain = np.sum(0.5 * (rate[kl:k0] + rate[kl + 1:k0 + 1])) * T_s
    # measured: 5e-4 (the trapezoid of the sampled torque against the solver's steps)
    assert (w[k0] - w[kl]) / gain - 1 == pytest.approx(0.0, abs=1.5e-3)
    assert w[k0] < 20 * w_r < w[k0] + T_s * rate[k0]


def test_a_lost_lock_is_reported_with_its_time(tmp_path, capsys):
    """A sensorless run that really loses lock: zhang2022's ESO with a model wrong in
    every parameter (L_d x0.6, L_q x1.4, R_s x1.5, psi_f x0.7) through a slow reversal.
    The summary's lock fields against the plain-loop reference of `lock_status` on the
    angle error recomputed from the recorded angles, judged from the I/f handover (the
    first sample at which the rotor and the reference have reached its speed); the run
    itself succeeded (exit 0) and stderr says when lock was lost."""
    assert main(["simulate", "--observer", "eso", "--mismatch", "L_d=0.6", "--mismatch",
                 "L_q=1.4", "--mismatch", "R_s=1.5", "--mismatch", "psi_f=0.7",
                 "--scenario", "reversal", "--speed", "0.2", "--t-end", "0.3", "--no-plot",
                 "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    s = json.loads((tmp_path / "summary.json").read_text())
    lock = s["lock"]
    tr = read_npz(tmp_path / "trajectory.npz")
    t = tr["t"]
    e = np.asarray(pj.wrap_angle(tr["theta"] - tr["theta_hat"]))
    w_hand = float(pj.IfStartup.from_drive(DRIVE).w_hand)
    k = max(int(np.flatnonzero(np.abs(tr[x]) >= w_hand)[0]) for x in ("w_m", "w_m_ref"))
    acq, t_acq, lost, t_lost = lock_status_loop(t[k:], e[k:])
    assert lock["judged_from_s"] == t[k]
    assert (lock["acquired"], lock["lost"]) == (acq, lost) == (True, True)
    assert lock["t_acquired_s"] == pytest.approx(t_acq, abs=1e-12)
    assert lock["t_lost_s"] == pytest.approx(t_lost, abs=1e-12)
    assert s["status"] == lock["status"] == f"lost lock at t = {t_lost:.4g} s"
    assert s["status_message"] == pj.RESULTS[pj.RESULTS.successful]
    # after the reversal's zero crossing (0.1875 s), and out of lock by the definition
    assert 0.1875 < t_lost < t[-1]
    j = int(np.searchsorted(t, t_lost))
    assert np.degrees(np.abs(e[j:j + 80]).mean()) > pj.LOCK_DEG  # 80 samples: 10 ms
    assert f"the observer lost lock at t = {t_lost:.4g} s" in err


def test_simulate_default_run(sim_run):
    """`pmsmjax simulate` on its built-in default (it was the main job before gain
    tuning became it): zhang750, sensored FOC, 1.5 s at T_s = 125 us (the module's
    recording, `sim_run`)."""
    out, printed = sim_run
    assert "status: successful" in printed

    for name in ("trajectory.npz", "recording.npz", "summary.json", "simulation.png"):
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    # The built-in default: zhang750, sensored FOC, 1.5 s at T_s = 125 us.
    assert summary["motor"] == "zhang750"
    assert summary["observer"] == "sensored"
    assert summary["T_s"] == 125e-6
    assert summary["steps"] == 12000
    assert summary["scenario"]["name"] == "default"
    assert summary["scenario"]["speed_pu"] == 0.5 and summary["scenario"]["load_pu"] == 0.5
    assert summary["controller"]["current_bandwidth_rad_s"] == pytest.approx(2 * np.pi * 500)
    assert summary["controller"]["speed_bandwidth_rad_s"] == pytest.approx(2 * np.pi * 5)
    assert summary["status"] == "successful"
    # The speed loop ends at its set-point, the settled error is small and the current
    # stays within the drive's limit.
    assert summary["final_speed"]["pu"] == pytest.approx(0.5, abs=5e-3)
    se = summary["speed_error_after_settling"]
    assert se["samples"] > 1000
    assert se["max_abs_pu"] < 0.02
    assert 0 < summary["max_current"]["A"] < pj.preset("zhang750").i_max
    print(f"simulate default: compile {summary['compile_time_s']:.2f} s, run "
          f"{summary['run_time_s']:.3f} s, wall {summary['wall_time_s']:.2f} s")

    rec = pj.load_recording(out / "recording.npz")
    assert rec.n == 12000
    assert np.max(rec.tau_L) == pytest.approx(0.5 * pj.preset("zhang750").tau_rated)
