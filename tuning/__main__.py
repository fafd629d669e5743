"""`python -m tuning`: tune an observer's design under inductance mismatch (the main job).

Runs `tuning.run_tuning` on the built-in default (zhang2022's ESO on zhang750) or the
options given (`--observer NAME`: any registered observer that declares a tunable
design), validates every design on closed-loop runs it never trained on
(`tuning.validation`), and writes `summary.json`, `tuned_schedule.eqx` and the plots into
`--out` (default `results/tuning`), with the tuned gains as a lookup table (`gains.csv`,
`gains.json`, `gains.h`) and the drive as a motor file (`motor.toml`). The drive is a
preset (`--motor`) or your own (`--motor-file`), changed by `--set`. Exit status 0 on
success, 2 for a bad configuration (one-line message, no traceback).

`python -m tuning compare ...` runs the side-by-side comparison of every observer instead
(`tuning.compare`; `python -m tuning compare --help`). `pmsmjax tune` and `pmsmjax
compare` run the same two commands; the options they share with the other `pmsmjax`
commands (`--motor`, `--motor-file`, `--set`, lists, deprecated spellings) come from
`pmsmjax.cli._options`.
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys
import time

import pmsmjax as pj
from pmsmjax.cli._options import (
    DeprecatedOption,
    ListOption,
    add_drive_options,
    finite_float,
    out_dir_transaction,
)
from pmsmjax.observers import observer_names

from .scenarios import MOTOR_QUICK_DEFAULTS, OBJECTIVES, OPTIMISERS, PARAMETRISATIONS, TuningConfig


def build_parser(prog: str = "python -m tuning") -> argparse.ArgumentParser:
    d = TuningConfig()
    compare = prog.replace("tune", "compare") if prog.endswith("tune") else \
        f"{prog} compare"
    p = argparse.ArgumentParser(
        prog=prog,
        epilog=(f"`{compare} --help`: the other command of the tuner, every observer "
                "(paper design and tuned) side by side on one common grid of closed-loop "
                "runs. The tuned gains are written as gains.json, gains.csv and gains.h "
                "with the sampling period and the verdict; gains.h warns when compiled if "
                "the tuned design did not pass validation."),
        description=(
            "Gradient-based tuning of a sensorless observer's design (default: the "
            "zhang2022 ESO gain schedule) so that the observer stays fast, accurate and "
            "stable when its inductances are wrong. Simulates a vmapped batch of "
            "sensorless runs over an inductance-mismatch grid, speeds and loads, "
            "differentiates through it, and compares with the paper's design (for the "
            "ESO: (38)/(25); with the same tuning within the minimum-norm gains (25)) and "
            "two gradient-free searches with the same number of simulations, on training "
            "and held-out mismatch and on closed-loop, speed-controlled validation runs "
            "(speed ramp, load step, other speeds, R_s/psi_f/inductance mismatch, more "
            "noise) the tuner never sees; 'tuned beats' is printed only if it holds on all "
            "three with no scenario worse, else where it does not. Any registered observer "
            "that declares a tunable design can be tuned (--observer)."),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", default="results/tuning", metavar="DIR",
                   help="output folder (summary.json, tuned_schedule.eqx, plots)")
    add_drive_options(p)  # --motor, --motor-file, --set: as every pmsmjax command
    p.add_argument("--observer", default=d.observer, choices=observer_names(),
                   metavar="NAME",
                   help=f"observer to tune, one of {', '.join(observer_names())} (its "
                        f"class declares the tunable design, its from_drive the paper's "
                        f"design)")
    p.add_argument("--parametrisation", default=d.parametrisation, choices=PARAMETRISATIONS,
                   help="auto: speed-scheduled gains if the observer declares them, else "
                        "constant factors on its paper design; or force one")
    p.add_argument("--optimiser", default=d.optimiser, choices=OPTIMISERS,
                   help="optax Adam, optimistix BFGS or Levenberg-Marquardt")
    p.add_argument("--objective", default=d.objective, choices=OBJECTIVES,
                   help="no_regression: the robust objective with no training scenario "
                        "worse than the paper's design by more than --regression-tol "
                        "(smooth penalty, and only such designs are kept); robust: smooth "
                        "maximum over scenarios (regressions elsewhere allowed); average")
    p.add_argument("--regression-tol", type=float, default=d.regression_tol,
                   metavar="REL", help="tolerance of no_regression and of the "
                                       "per-scenario accounting (relative change of a "
                                       "scenario's loss)")
    p.add_argument("--steps", type=int, default=d.steps,
                   help="optimiser steps (the random search gets as many designs)")
    p.add_argument("--lr", type=float, default=d.learning_rate,
                   help="Adam learning rate (unconstrained units)")
    p.add_argument("--patience", type=int, default=d.patience,
                   help="early stop after this many steps without improvement (0: never)")
    p.add_argument("--seed", type=int, default=d.seed, metavar="N",
                   help="seed of the noise keys and of the random search")
    p.add_argument("--mismatch-range", dest="mismatch", type=finite_float, nargs=2,
                   default=d.mismatch, metavar=("LO", "HI"),
                   help="range of the training mismatch ratios L_hat / L (observer / "
                        "plant, -) of L_d and L_q")
    p.add_argument("--mismatch", dest="mismatch", type=finite_float, nargs=2,
                   default=d.mismatch, metavar=("LO", "HI"), action=DeprecatedOption,
                   instead="give --mismatch-range LO HI (in the analysis commands "
                           "--mismatch NAME=RATIO is one ratio)",
                   help="deprecated: --mismatch-range LO HI")
    p.add_argument("--n-mismatch", type=int, default=d.n_mismatch,
                   help="training values per inductance (grid n x n)")
    p.add_argument("--n-heldout", type=int, default=d.n_heldout,
                   help="held-out values per inductance (midpoints, disjoint)")
    p.add_argument("--speeds", action=ListOption, item=finite_float, default=d.speeds_pu,
                   metavar="PU", help="operating speeds (p.u. of rated, nonzero), separated "
                                      "by spaces")
    p.add_argument("--loads", action=ListOption, item=finite_float, default=d.loads_pu,
                   metavar="PU", help="loads (p.u. of rated torque), separated by spaces")
    p.add_argument("--nodes", action=ListOption, item=finite_float, default=d.nodes_pu,
                   metavar="PU", help="speed nodes of the gain schedule (p.u.; scheduled "
                                      "designs), separated by spaces")
    p.add_argument("--tune", action=ListOption, default=None, metavar="NAME",
                   help=f"quantities to tune, separated by spaces (default: every quantity "
                        f"the observer declares; for the ESO {' '.join(d.tuned)})")
    p.add_argument("--t-end", type=float, default=d.t_end, metavar="S",
                   help="length of each run (s)")
    p.add_argument("--t-transient", type=float, default=d.t_transient, metavar="S",
                   help="errors and noise are measured from this time on (s)")
    p.add_argument("--T-s", type=float, default=d.T_s, metavar="S",
                   help="sampling period (s)")
    p.add_argument("--noise", type=float, default=d.noise_std, metavar="A",
                   help="current-sensor noise std per component (A)")
    p.add_argument("--theta0", type=float, default=d.theta_err0_deg, metavar="DEG",
                   help="initial angle error, true minus estimate (deg)")
    p.add_argument("--temperature", type=float, default=d.temperature,
                   help="temperature of the smooth maximum (loss units)")
    p.add_argument("--quick", action="store_true",
                   help="tiny configuration for tests and smoke runs (TuningConfig.quick)")
    p.add_argument("--no-ablation", action="store_true",
                   help="skip the tuning restricted to the minimum-norm gains (25)")
    p.add_argument("--no-plot", action="store_true", help="do not write the plots")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def config_from_args(args) -> TuningConfig:
    d = TuningConfig()
    motor = d.motor if args.motor is None else args.motor
    base = TuningConfig.quick(**MOTOR_QUICK_DEFAULTS.get(motor, {})) if args.quick \
        else TuningConfig.for_motor(motor)
    kw = {"motor": motor} if motor != d.motor else {}
    # an option changes the configuration only if it differs from the CLI default, so
    # that --quick keeps its own values unless an option overrides them
    for opt, field in (("observer", "observer"),
                       ("parametrisation", "parametrisation"), ("optimiser", "optimiser"),
                       ("objective", "objective"), ("regression_tol", "regression_tol"),
                       ("steps", "steps"), ("lr", "learning_rate"),
                       ("patience", "patience"), ("seed", "seed"),
                       ("n_mismatch", "n_mismatch"), ("n_heldout", "n_heldout"),
                       ("t_end", "t_end"), ("t_transient", "t_transient"), ("T_s", "T_s"),
                       ("noise", "noise_std"), ("theta0", "theta_err0_deg"),
                       ("temperature", "temperature")):
        v = getattr(args, opt)
        if v != getattr(d, field):
            kw[field] = v
    for opt, field in (("mismatch", "mismatch"), ("speeds", "speeds_pu"),
                       ("loads", "loads_pu"), ("nodes", "nodes_pu")):
        v = tuple(getattr(args, opt))
        if v != tuple(getattr(d, field)):
            kw[field] = v
    if args.motor_file is not None:
        if args.motor is not None:
            raise ValueError(f"--motor {args.motor} and --motor-file {args.motor_file}: give "
                             f"one of the two")
        kw["motor_file"] = args.motor_file
    if args.set_params:
        kw["set_params"] = tuple(args.set_params)
    if args.tune is not None:
        kw["tuned"] = tuple(args.tune)
    # the motor's own defaults (`MOTOR_DEFAULTS`) are in `base` (`TuningConfig.for_motor`)
    return base.replace(**kw)


def main(argv=None, prog: str = "python -m tuning") -> int:
    """Run the tuner's command line `argv` (default `sys.argv[1:]`; `compare ...`: the
    comparison job); `prog`: the name the messages use (`pmsmjax tune` hands over with
    its own). Returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "compare":  # `python -m tuning compare ...`: the comparison job
        from ._compare_cli import main as compare_main

        return compare_main(argv[1:], prog=f"{prog} compare")
    # process settings of an entry point, before any computation (building the parser
    # builds the default `TuningConfig`, which already computes)
    pj.runtime.configure()
    parser = build_parser(prog)
    args = parser.parse_args(argv)  # bad options: argparse exits with status 2
    try:
        config = config_from_args(args)
    except ValueError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    out = pathlib.Path(args.out)
    from ._pipeline import run_tuning
    from ._report import write_report
    from .objectives import report_objective

    t0 = time.perf_counter()
    report = run_tuning(config, progress=not args.no_progress, log=print,
                        ablation=not args.no_ablation)
    with out_dir_transaction(str(out)):  # a failed write leaves nothing half-written
        s = write_report(report, out, plot=not args.no_plot)
    wall = time.perf_counter() - t0
    print()
    print(f"{'design':<16}{'train loss':>14}{'held-out loss':>15}{'validation':>14}"
          f"{'feasible':>10}")
    for name, row in s["designs"].items():  # 5 significant digits: columns stay apart
        print(f"{name:<16}{row['train_loss']:>14.5g}{row['heldout_loss']:>15.5g}"
              f"{row['validation_loss']:>14.5g}{str(row['feasible']):>10}")
    imp = s["improvement_pct"]
    v = s["verdict"]
    change = (f"{imp['train']:+.1f} % (training), {imp['heldout']:+.1f} % (held-out), "
              f"{imp['validation']:+.1f} % (validation) lower "
              f"{report_objective(config)} loss")
    if v["holds"]:
        print(f"tuned beats {s['baseline_label']}: {change}; no scenario worse by more "
              f"than {s['accounting']['train']['tolerance_pct']:g} %; feasible on every "
              f"scenario: {s['feasible']}")
    else:
        print(f"tuned does NOT beat {s['baseline_label']} everywhere: {change}; feasible "
              f"on every scenario: {s['feasible']}; where it does not:")
        for line in v["where_not"]:
            print(f"  {line}")
        print(f"warning: {out / 'gains.h'} (and gains.json, gains.csv) hold this tuned "
              f"design, which did NOT pass the tuner's checks: the table records the "
              f"verdict and gains.h warns when compiled; deploy "
              f"{s['baseline_label']} or validate the tuned gains yourself", file=sys.stderr)
    from ._report import SPLITS, accounting_lines

    for split in SPLITS:
        for line in accounting_lines(s["accounting"][split], split):
            print(line)
    print(f"wall time {wall:.1f} s (job {s['wall_time_s']:.1f} s); wrote {out / 'summary.json'}")
    return 0 if all(math.isfinite(s[k]) for k in ("tuned_loss", "heldout_tuned_loss")) else 1


if __name__ == "__main__":
    sys.exit(main())
