"""`python -m tuning`: tune an observer's design in the closed loop (the main job).

Argument parsing and the console summary: the options build a `TuningProblem`,
`tuning.tune` runs the pipeline and `tuning.write_report` writes the folder
(`summary.json`, `design.json`, `gains.json`/`gains.csv`/`gains.h`, `motor.toml`, the
figures). The built-in default is zhang2022's ESO on zhang750. The console prints the RMS
angle error (deg) of the paper's and the tuned design first, then each design's
accounting in summary.json's words (`console_summary`); the last line is the verdict as
counted (`verdict_line`). Exit status 0 when the job ran (whatever the verdict), 2 for a
bad configuration (one-line message).

`python -m tuning compare ...` runs the side-by-side comparison of every observer
(`tuning.compare`). `pmsmjax tune` / `pmsmjax compare` hand over to these two.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import pmsmjax as pj
from pmsmjax.cli import (
    ListOption,
    add_drive_options,
    add_speed_from_angle_option,
    finite_float,
    out_dir_transaction,
    write_json,
)
from pmsmjax.observers import observer_names

from .problem import SEARCHES, TRAIN_ERRORS, TuningProblem


def build_parser(prog: str = "python -m tuning") -> argparse.ArgumentParser:
    d = TuningProblem()
    compare = prog.replace("tune", "compare") if prog.endswith("tune") else \
        f"{prog} compare"
    p = argparse.ArgumentParser(
        prog=prog,
        epilog=(f"`{compare} --help`: every observer (paper design and tuned) side by "
                "side on one common grid of closed-loop runs."),
        description=(
            "Tune a sensorless observer's design in the closed loop it will run in: "
            "speed control on the estimate, ramps up to the current limit, reversals, "
            "load steps, observer-model mismatch of L_d, L_q, R_s and psi_f, current "
            "noise. Searches bandwidths and damping within bounds derived from the drive "
            "(gradient through the closed loops, CMA-ES, their hybrid, random and local "
            "search, all with the same number of simulations), and checks the result on "
            "validation runs it never saw against the paper's design: better in at least "
            "75 % of them, no run's RMS angle error worse by more than the tolerance, no "
            "lock lost that the paper's design holds; runs beyond the observer's "
            "low-speed limit, by a rule fixed before tuning, judged without their load "
            "step or counted apart."),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", default="results/tuning", metavar="DIR",
                   help="output folder (summary.json, gains table, figures)")
    add_drive_options(p)  # --motor, --motor-file, --set: as every pmsmjax command
    p.add_argument("--observer", default=d.observer, choices=observer_names(),
                   metavar="NAME", help=f"observer to tune, one of "
                                        f"{', '.join(observer_names())} (default motor: "
                                        f"its paper's)")
    p.add_argument("--search", default=d.search, choices=SEARCHES,
                   help="the strategy whose design is deployed (all run as peers)")
    p.add_argument("--budget", type=int, default=d.budget, metavar="SIMS",
                   help="closed-loop simulations per strategy")
    p.add_argument("--regression-tol", type=float, default=d.regression_tol,
                   metavar="REL", help="no run's RMS angle error may be worse than the "
                                       "paper design's by more than this (relative)")
    p.add_argument("--n-train", type=int, default=d.n_train, help="training runs")
    p.add_argument("--t-end", type=float, default=d.t_end, metavar="S",
                   help="length of a training run (s)")
    p.add_argument("--T-s", type=float, default=None, metavar="S",
                   help="sampling period (s; default the motor's paper drive's)")
    p.add_argument("--noise", type=float, default=d.noise_std, metavar="A",
                   help="current-sensor noise std per component (A)")
    add_speed_from_angle_option(p, "; every run's speed loop takes it")
    p.add_argument("--val-speeds", action=ListOption, item=finite_float,
                   default=d.val_speeds_pu, metavar="PU",
                   help="validation speeds (p.u., each with both signs)")
    p.add_argument("--low-speed-limit", type=float, default=None, metavar="PU",
                   help="the low-speed rule: a run in which a sensored drive turns "
                        "slower than this (p.u. of rated) is judged without its load "
                        "step where that keeps the drive above it, else counted apart "
                        "(validation) or left out (training, held-out) (default: the "
                        "observer class's declared limit, 0.05 for li's PLL observers, 0 "
                        "for the others; 0: judge every run)")
    p.add_argument("--seed", type=int, default=d.seed, metavar="N",
                   help="seed of the scenario draws, noise keys and searches")
    p.add_argument("--peers", action=ListOption, default=None, metavar="NAME",
                   help=f"strategies run side by side (default all: {' '.join(SEARCHES)})")
    p.add_argument("--tune", action=ListOption, default=None, metavar="NAME",
                   help="the design coordinates the searches change (default all; e.g. "
                        "w2 zeta2: the zhang2022 family's flux loop keeps the paper's "
                        "speed schedule (38)); the others keep the paper's design")
    p.add_argument("--quick", action="store_true",
                   help="a small problem for smoke runs (TuningProblem.quick)")
    p.add_argument("--wide-mismatch", action="store_true",
                   help="the observer model's L_d and L_q off by up to +-50 %% in every "
                        "set: training and held-out draws over 0.5..1.5, validation with "
                        "the +-50 %% cases, jointly and separately, added "
                        "(TuningProblem.wide_mismatch)")
    p.add_argument("--train-errors", choices=TRAIN_ERRORS, default=d.train_errors,
                   help="the training and held-out runs' model errors: structured (in "
                        "turn all at once, the inductances, and each parameter alone; "
                        "the default) or joint (every parameter in every run) "
                        "(TuningProblem.train_errors)")
    p.add_argument("--no-plot", action="store_true", help="do not write the figures")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def problem_from_args(args) -> TuningProblem:
    d = TuningProblem()
    kw = {"observer": args.observer}
    for opt, field in (("search", "search"), ("budget", "budget"),
                       ("regression_tol", "regression_tol"), ("n_train", "n_train"),
                       ("t_end", "t_end"), ("noise", "noise_std"), ("seed", "seed")):
        v = getattr(args, opt)
        if v != getattr(d, field):
            kw[field] = v
    if tuple(args.val_speeds) != tuple(d.val_speeds_pu):
        kw["val_speeds_pu"] = tuple(args.val_speeds)
    if args.T_s is not None:
        kw["T_s"] = args.T_s
    if args.low_speed_limit is not None:
        kw["low_speed_limit_pu"] = args.low_speed_limit
    if args.speed_from_angle is not None:
        kw["speed_from_angle"] = args.speed_from_angle
    if args.tune is not None:
        kw["tune"] = tuple(args.tune)
    if args.train_errors != d.train_errors:
        kw["train_errors"] = args.train_errors
    if args.motor_file is not None:
        if args.motor is not None:
            raise ValueError(f"--motor {args.motor} and --motor-file {args.motor_file}: give "
                             f"one of the two")
        kw["motor_file"] = args.motor_file
    elif args.motor is not None:
        kw["motor"] = args.motor
    if args.set_params:
        kw["set_params"] = tuple(args.set_params)
    if args.quick and args.wide_mismatch:
        raise ValueError("--quick and --wide-mismatch: give one of the two (the quick "
                         "problem's three validation cases have no +-50 % mismatch)")
    if args.quick:
        return TuningProblem.quick(**kw)
    return TuningProblem.wide_mismatch(**kw) if args.wide_mismatch else TuningProblem(**kw)


#: The console table's columns: heading, where summary.json keeps the value
#: (`designs.NAME.KEY` or `designs.NAME.accounting.validation.KEY`), key and format; the
#: RMS angle error first, the accounting under its own names.
COLUMNS = (("RMS deg", "design", "validation_rms_deg", "{:.2f}"),
           ("better", "accounting", "better", "{}/{n}"),
           ("worse", "accounting", "worse", "{}"),
           ("worst_rms_change_pct", "accounting", "worst_rms_change_pct", "{:+.1f} %"),
           ("new_lost_lock", "accounting", "new_lost_lock", "{}"),
           ("train objective", "design", "train_objective", "{:.4g}"))


def console_summary(s: dict) -> str:
    """The console's summary of a summary.json `s`: the RMS angle error of the paper's
    and the deployed design on the validation runs first, then one row per design in the
    accounting's words (`tuning.objective.VOCABULARY`, defined under the table), the
    training objective labelled as such (dimensionless, not degrees)."""
    from .objective import VOCABULARY

    a, h = s["accounting"]["validation"], s["rms_angle_error_deg"]
    rule = pj.low_speed_text(a)
    apart = f" ({rule}: `verdict.low_speed_rule`)" if rule else ""
    # the deployed design by where it came from: the chosen search's design ("tuned") is
    # named by its search, a design of the front by its own name
    search = (s.get("problem") or {}).get("search")
    origin = f"{search} search" if h["design"] == "tuned" and search else h["design"]
    lines = [f"RMS angle error (deg), mean over the {a['n']} validation runs{apart}: paper "
             f"design {h['paper']:.2f}, tuned ({origin}) {h['tuned']:.2f}", ""]
    widths = [max(len(head) + 2, 8) for head, *_ in COLUMNS]
    lines.append(f"{'design':<16}" + "".join(f"{head:>{w}}" for (head, *_), w in
                                             zip(COLUMNS, widths)) + f"{'sims':>7}{'wall s':>8}")
    for name, row in s["designs"].items():
        acc = row.get("accounting", {}).get("validation")
        cells = [fmt.format((row if where == "design" else acc)[key], n=acc and acc["n"])
                 if where == "design" or acc else "-" for _, where, key, fmt in COLUMNS]
        sr = row.get("search") or {}
        wall = f"{sr['wall_s']:.1f}" if "wall_s" in sr else "-"
        lines.append(f"{name:<16}" + "".join(f"{c:>{w}}" for c, w in zip(cells, widths))
                     + f"{sr.get('sims', '-'):>7}{wall:>8}")
    lines += ["", "RMS deg: each validation run's RMS angle error, mean over the runs (deg)"]
    lines += [f"{key}: {VOCABULARY[key]}" for _, _, key, _ in COLUMNS if key in VOCABULARY]
    lines.append("train objective: what the searches minimise on the training runs "
                 "(dimensionless, not degrees; the paper design's is 1 plus penalties)")
    return "\n".join(lines)


def verdict_line(s: dict) -> str:
    """The job's last line: the verdict as counted (`verdict.statement`), and where it
    does not hold, why."""
    v = s["verdict"]
    return "verdict: " + "; ".join([v["statement"], *v["where_not"]])


def main(argv=None, prog: str = "python -m tuning") -> int:
    """Run the tuner's command line `argv` (default `sys.argv[1:]`; `compare ...`: the
    comparison job). Returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "compare":
        from .compare.cli import main as compare_main

        return compare_main(argv[1:], prog=f"{prog} compare")
    pj.runtime.configure()
    args = build_parser(prog).parse_args(argv)  # bad options: argparse exits with 2
    try:
        problem = problem_from_args(args)
        peers = tuple(args.peers) if args.peers is not None else None
        if peers is not None and set(peers) - set(SEARCHES):
            raise ValueError(f"--peers: unknown {sorted(set(peers) - set(SEARCHES))}; "
                             f"allowed: {', '.join(SEARCHES)}")
    except ValueError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    from .pipeline import PEERS, tune
    from .report import MISMATCHES, heldout_simulate, heldout_text, write_report

    t0 = time.perf_counter()
    report = tune(problem, progress=not args.no_progress, log=print,
                  peers=PEERS if peers is None else peers)
    out = pathlib.Path(args.out)
    with out_dir_transaction(str(out)):  # a failed write leaves nothing half-written
        s = write_report(report, out, plot=not args.no_plot)
        # held out: `pmsmjax simulate` with +-50 % inductance errors (tuning.report.corners)
        print("held-out check: pmsmjax simulate, paper's and tuned design, "
              f"{len(MISMATCHES)} inductance mismatches")
        s["heldout_simulate"] = heldout_simulate(
            out, problem, t_end=problem.t_end if args.quick else None)
        write_json(out / "summary.json", s, indent=1)
    print()
    print(console_summary(s))
    print()
    print(heldout_text(s["heldout_simulate"]))
    print(f"wall time {time.perf_counter() - t0:.1f} s; wrote {out / 'summary.json'}")
    if not s["verdict"]["holds"]:
        print(f"warning: {out / 'gains.h'} holds a design that did NOT pass validation; "
              f"deploy the paper's design or check the tuned one yourself",
              file=sys.stderr)
    print(verdict_line(s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
