"""One command line: `pmsmjax tune`/`pmsmjax compare` hand over to `tuning` (imported
only then), every command takes `--motor-file`/`--set`, one spelling and one unit per
option across the commands, and the old spellings are refused with a one-line error."""

import argparse
import json
import math
import subprocess
import sys

import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.cli import CLIError, observer_from_args
from pmsmjax.cli.__main__ import COMMANDS, build_parser, main
from pmsmjax.cli._drive_options import initial_state_from_args
from tuning.__main__ import build_parser as tuning_parser, problem_from_args
from tuning.compare.cli import build_parser as compare_parser


def _subparsers(parser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise AssertionError("no subcommands")


def _all_parsers() -> dict:
    """Every parser of the command line: the `pmsmjax` commands, with `tune` and
    `compare` as the `tuning` parsers that run them."""
    out = {n: p for n, p in _subparsers(build_parser()).items()
           if n not in ("tune", "compare")}
    out["tune"] = tuning_parser("pmsmjax tune")
    out["compare"] = compare_parser("pmsmjax compare")
    return out


def _options_of(parser) -> dict:
    return {s: a for a in parser._actions for s in a.option_strings if s.startswith("--")}


def test_every_command_takes_a_drive_and_the_tuner_commands_are_listed():
    assert {"tune", "compare"} <= set(COMMANDS)
    for name, parser in _all_parsers().items():
        if name in ("cache", "worker"):  # the compilation cache and the workers: no drive
            continue
        opts = _options_of(parser)
        assert {"--motor", "--motor-file", "--set"} <= set(opts), name


def test_one_spelling_one_unit_across_commands():
    """An option spelled the same in two commands has the same unit (metavar), except
    the feasibility map's grid axes (documented there); angles are in degrees and speeds
    in p.u. wherever they are options."""
    seen: dict[str, tuple] = {}
    grid_axes = {("feasibility", "--zeta1"), ("feasibility", "--ratio")}
    for name, parser in _all_parsers().items():
        for opt, action in _options_of(parser).items():
            if (name, opt) in grid_axes:
                continue
            if opt in ("--theta0",):
                assert action.metavar == "DEG", (name, opt)
            if opt in ("--speed", "--speeds", "--speed0", "--loads", "--nodes",
                       "--val-speeds"):
                assert action.metavar == "PU", (name, opt)
            if opt == "--out":
                assert action.metavar == "DIR", (name, opt)
            meta = action.metavar if isinstance(action.metavar, tuple) else (action.metavar,)
            if opt in seen:
                assert seen[opt][1] == meta, (opt, seen[opt][0], name, meta)
            else:
                seen[opt] = (name, meta)
    # lists: space-separated (nargs "+") everywhere
    for name, opt in (("feasibility", "--speeds"), ("tune", "--val-speeds"),
                      ("tune", "--peers"), ("compare", "--observers"),
                      ("response", "--orders")):
        assert _options_of(_all_parsers()[name])[opt].nargs == "+", (name, opt)


def test_lists_parse_space_separated_and_commas_are_refused(capsys):
    p = build_parser()
    a = p.parse_args(["feasibility", "--speeds", "0.2", "-0.5", "--out", "x"])
    assert a.speed == [[0.2, -0.5]]
    a = p.parse_args(["feasibility", "--speeds", "0.2", "0.5", "--speed", "1", "--out", "x"])
    assert a.speed == [[0.2, 0.5], [1.0]]
    assert capsys.readouterr().err == ""
    # the old comma-separated form: an error that spells the list with spaces
    for argv, spaced in ((["--speeds", "0.2,0.5"], "--speeds 0.2 0.5"),
                         (["--speed", "0.2,0.5"], "--speeds 0.2 0.5")):
        with pytest.raises(CLIError, match=f"separated by spaces, e.g. {spaced}"):
            p.parse_args(["feasibility", *argv, "--out", "x"])
    a = p.parse_args(["response", "--orders", "1", "-5", "7", "--out", "x"])
    assert a.orders == [1, -5, 7]
    with pytest.raises(CLIError, match="--orders"):
        p.parse_args(["response", "--orders", "1", "0"])
    t = tuning_parser().parse_args(["--val-speeds", "0.2", "0.6", "--peers", "cmaes",
                                    "gradient"])
    assert t.val_speeds == [0.2, 0.6] and t.peers == ["cmaes", "gradient"]
    capsys.readouterr()
    with pytest.raises(SystemExit):
        tuning_parser().parse_args(["--val-speeds", "0.2,0.6"])
    assert "e.g. --val-speeds 0.2 0.6" in capsys.readouterr().err
    c = compare_parser().parse_args(["--observers", "eso", "leso"])
    assert c.observers == ["eso", "leso"]


def test_mismatch_is_one_ratio_per_parameter(capsys):
    """`--mismatch L_q=1.3` gives the observer model of `--observer-set L_q=1.3 L_q`; the
    old `--mismatch-L-q 1.3` is an unknown option."""
    drive = pj.preset("zhang750")
    L_q = float(drive.three_phase_motor.L_q)
    p = build_parser()
    models = []
    for extra in (["--mismatch", "L_q=1.3", "--mismatch", "R_s=0.8"],
                  ["--observer-set", f"L_q={1.3 * L_q!r}", "--mismatch", "R_s=0.8"]):
        args = p.parse_args(["equilibria", *extra])
        models.append(observer_from_args(args, drive).observer.motor)
    for m in models:
        assert float(m.L_q) == pytest.approx(1.3 * L_q, rel=1e-15)
        assert float(m.R_s) == pytest.approx(0.8 * float(drive.three_phase_motor.R_s))
    for bad, fragment in ((["--mismatch", "L_x=1.3"], "unknown parameter 'L_x'"),
                          (["--mismatch", "L_q=0"], "must be > 0"),
                          (["--mismatch", "L_q=1.3", "--mismatch", "L_q=1.2"], "both set")):
        args = p.parse_args(["equilibria", *bad])
        with pytest.raises(CLIError, match=fragment):
            observer_from_args(args, drive)
    with pytest.raises(CLIError, match="equilibria: error: unrecognized arguments: "
                                       "--mismatch-L-q 1.3"):
        p.parse_args(["equilibria", "--mismatch-L-q", "1.3"])
    for cmd in (["simulate", "--observer", "eso"], ["replay", "--data", "x", "--out", "o"]):
        args = p.parse_args([*cmd, "--mismatch", "L_q=1.3"])
        m = observer_from_args(args, drive).observer.motor
        assert float(m.L_q) == pytest.approx(1.3 * L_q, rel=1e-15)


def test_initial_state_in_degrees_and_per_unit(capsys):
    """plant and replay: `--theta0 DEG` and `--speed0 PU`; the old rad/s spellings
    (`--w-m0`, `--w0`) are unknown options."""
    drive = pj.preset("zhang750")
    w_r = float(drive.w_rated)
    p = build_parser()
    for cmd, old in (("plant", "--w-m0"), ("replay", "--w0")):
        base = [cmd, "--data", "x.npz", "--out", "o"]
        a = p.parse_args([*base, "--theta0", "90", "--speed0", "0.5"])
        theta0, w0 = initial_state_from_args(a, drive)
        assert theta0 == pytest.approx(math.pi / 2) and w0 == pytest.approx(0.5 * w_r)
        assert capsys.readouterr().err == ""
        with pytest.raises(CLIError, match=f"unrecognized arguments: {old} 100"):
            p.parse_args([*base, old, "100"])


def test_plant_run_takes_degrees_and_per_unit(tmp_path, capsys):
    """A cheap run: the initial state written to summary.json is --theta0 in rad and
    --speed0 x w_rated."""
    drive = pj.preset("zhang750")
    t = np.arange(40) * 1e-4
    pj.save_recording(tmp_path / "rec.npz", pj.RecordedData(t=t, u_ab=np.zeros((40, 2))))
    assert main(["plant", "--data", str(tmp_path / "rec.npz"), "--theta0", "45",
                 "--speed0", "0.25", "--no-plot", "--out", str(tmp_path / "o")]) == 0
    s = json.loads((tmp_path / "o" / "summary.json").read_text())["initial_state"]
    assert s["theta0_rad"] == pytest.approx(math.pi / 4)
    assert s["w_m0_rad_s"] == pytest.approx(0.25 * float(drive.w_rated))


def test_motor_out_is_a_folder(tmp_path, capsys):
    assert main(["motor", "--export", "zhang750", "--out", str(tmp_path / "d")]) == 0
    assert pj.load_motor_file(tmp_path / "d" / "motor.toml").name == "zhang750"
    capsys.readouterr()
    (tmp_path / "m.toml").write_text("")  # the old meaning, --out FILE: refused
    assert main(["motor", "--export", "zhang750", "--out", str(tmp_path / "m.toml")]) == 2
    assert "exists and is not a directory" in capsys.readouterr().err
    assert (tmp_path / "m.toml").read_text() == ""


def test_tune_and_compare_hand_over_to_tuning(tmp_path, capsys):
    """`pmsmjax tune`/`compare` parse with the tuner's parsers (help, bad options, the
    drive options); `python -m tuning --help` names `compare`; compare takes a motor
    file."""
    assert main(["tune", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: pmsmjax tune") and "pmsmjax compare --help" in out
    assert main(["compare", "--help"]) == 0
    assert capsys.readouterr().out.startswith("usage: pmsmjax compare")
    assert main(["tune", "--no-such-option"]) == 2
    assert main(["tune", "--quick", "--motor", "zhang750", "--motor-file", "x.toml",
                 "--out", str(tmp_path / "t")]) == 2
    assert "give one of the two" in capsys.readouterr().err
    assert "compare --help" in tuning_parser().format_help()
    # a motor file (and --set) in the tuner and the comparison
    pj.save_motor_file(pj.replace_params(pj.preset("zhang750"), R_s=1.1), tmp_path / "m.toml")
    cfg = problem_from_args(tuning_parser().parse_args(
        ["--quick", "--motor-file", str(tmp_path / "m.toml"), "--set", "J=0.01"]))
    assert cfg.drive().name == "zhang750" and float(cfg.drive().mechanics.J) == 0.01
    from tuning.compare import CompareConfig

    c = CompareConfig.quick(motor_file=str(tmp_path / "m.toml"), set_params=(("J", 0.01),))
    assert c.motor == "zhang750" and float(c.drive().mechanics.J) == 0.01
    assert CompareConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    capsys.readouterr()
    assert main(["compare", "--motor-file", str(tmp_path / "nope.toml"), "--quick",
                 "--out", str(tmp_path / "c")]) == 2
    assert "nope.toml" in capsys.readouterr().err


def test_the_command_line_does_not_import_tuning():
    code = ("import sys; from pmsmjax.cli.__main__ import build_parser; build_parser(); "
            "import pmsmjax.cli; print('tuning' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert out.stdout.strip() == "False"


def test_compare_runs_on_a_motor_file(tmp_path, capsys):
    """`pmsmjax compare --motor-file F --set ...`: the quick comparison of one observer on
    a drive of one's own (the job records the file and the replacements)."""
    drive = pj.replace_params(pj.preset("zhang750"), R_s=1.1)
    pj.save_motor_file(drive, tmp_path / "m.toml")
    out = tmp_path / "cmp"
    assert main(["compare", "--motor-file", str(tmp_path / "m.toml"), "--set", "J=0.002",
                 "--quick", "--observers", "eso", "--jobs", "1", "--no-plot",
                 "--no-progress", "--out", str(out)]) == 0
    s = json.loads((out / "comparison.json").read_text())
    assert s["config"]["motor_file"] == str(tmp_path / "m.toml")
    assert s["config"]["set_params"] == [["J", 0.002]]
    assert list(s["observers"]) == ["eso"]


def test_wide_mismatch_sets_reach_fifty_percent_and_stay_disjoint():
    """`python -m tuning --wide-mismatch` (`TuningProblem.wide_mismatch`): training and
    held-out ratios of L_d and L_q drawn over 0.5..1.5, the training runs' reaching past
    the default +-30 % on both sides; validation with every +-50 % case (both inductances jointly,
    crossed, one at a time) on top of the default cases; the three sets still share no
    value; `--quick` with it is refused by name."""
    from tuning.problem import VALIDATION_CASES, WIDE_CASES
    from tuning.scenarios import check_disjoint, heldout_set, training_set, validation_set

    p = problem_from_args(tuning_parser().parse_args(["--wide-mismatch",
                                                      "--regression-tol", "0.05"]))
    assert p.mismatch_range == (0.5, 1.5) and p.regression_tol == 0.05
    assert p.val_cases == VALIDATION_CASES + WIDE_CASES
    wanted = {(a, b) for a in (0.5, 1.0, 1.5) for b in (0.5, 1.0, 1.5)} - {(1.0, 1.0)}
    assert {(c[0], c[1]) for c in WIDE_CASES} == wanted
    assert all(c[2:] == (1.0, 1.0, 1.0) for c in WIDE_CASES)
    sets = [training_set(p), heldout_set(p), validation_set(p)]
    check_disjoint(*sets)  # raises on any shared value
    n_speeds = 2 * len(p.val_speeds_pu)
    assert sets[2].n == n_speeds * (len(VALIDATION_CASES) + len(WIDE_CASES))
    val = {(r["k_d"], r["k_q"]) for r in sets[2].table()}
    assert wanted <= val
    for s in sets[:2]:
        for k in ("k_d", "k_q"):
            v = np.asarray(getattr(s, k))
            assert v.min() >= 0.5 and v.max() <= 1.5
    # 72 training runs (2.8 times the default's area), their errors structured
    # (`tuning.ERROR_PATTERNS`): each inductance alone wrong beyond +-30 % on both sides,
    # and both wrong together in every quadrant of the square
    from tuning import WIDE_N_TRAIN

    assert p.n_train == WIDE_N_TRAIN == 72 and p.train_errors == "structured"
    kd, kq = np.asarray(sets[0].k_d) - 1, np.asarray(sets[0].k_q) - 1
    for alone, other in ((kd, kq), (kq, kd)):
        v = alone[(alone != 0) & (other == 0)]
        assert v.min() < -0.3 and v.max() > 0.3, v
    both = (kd != 0) & (kq != 0)
    for a in (-1, 1):
        for b in (-1, 1):
            assert np.any(both & (a * kd > 0.2) & (b * kq > 0.2)), (a, b)
    assert problem_from_args(tuning_parser().parse_args([])).mismatch_range == (0.7, 1.3)
    with pytest.raises(ValueError, match="--quick and --wide-mismatch"):
        problem_from_args(tuning_parser().parse_args(["--quick", "--wide-mismatch"]))


def test_tune_keeps_the_paper_design_outside_the_chosen_coordinates():
    """`python -m tuning --tune w2 zeta2` (`TuningProblem.tune`): the design space has
    those coordinates alone, so a design changes w2 and zeta2 and keeps the paper's flux
    schedule (38) (its gains at every speed are the paper's design's with the new w2,
    zeta2, built independently here); a name the observer has not, a repeated one, or
    part of a reparametrised class's coordinates is refused by name."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import tuning as tg
    from pmsmjax.observers import ESODesign, make_observer

    p = problem_from_args(tuning_parser().parse_args(["--tune", "w2", "zeta2"]))
    assert p.tune == ("w2", "zeta2")
    space = tg.DesignSpace(p)
    assert space.names == ("w2", "zeta2")
    x = jnp.array([400.0, 0.7])
    obs = space.observer(x)
    drive = p.drive()
    ref = make_observer("eso", drive)
    ref = eqx.tree_at(lambda o: o.design, ref, ESODesign.zhang38(drive.w_rated, 400.0, 0.7))
    assert obs.design.schedule == "zhang38"
    for w in (0.1, 0.5, 1.0):
        w0 = w * float(drive.w_rated)
        a, b = obs.linear_gains(w0, jnp.zeros(2)), ref.linear_gains(w0, jnp.zeros(2))
        for u, v in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_allclose(np.asarray(u), np.asarray(v), rtol=1e-12)
    # every coordinate, as before
    assert tg.DesignSpace(tg.TuningProblem()).names == ("zeta1_scale", "decay_scale", "w2",
                                                        "zeta2")
    for tune, fragment in ((("w3",), "zeta1_scale, decay_scale, w2, zeta2"),
                           (("w2", "w2"), "distinct names")):
        with pytest.raises(ValueError, match=fragment):
            tg.TuningProblem(tune=tune)
    joint = tuple(pj.observers.observer_class("rotor-flux").tuning_coordinates)
    with pytest.raises(ValueError, match="one reparametrisation"):
        tg.TuningProblem(observer="rotor-flux", tune=joint[:1])
