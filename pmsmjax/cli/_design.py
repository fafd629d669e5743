"""`--design FILE` of `pmsmjax simulate` and `pmsmjax replay`: run a tuned design.

FILE is the tuner's output: the gains table `gains.json` that `python -m tuning` writes,
or its output folder (or any file in it, such as `tuned_schedule.eqx`). The observer is
the table's (`--observer` may be left out or must name the same one); its machine model
follows `--observer-set` / `--mismatch` as usual, and the design replaces the paper's
(`pmsmjax.apply_gains_table`), so `--gain` and the design shorthands are not allowed
with it.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import pmsmjax as pj

from ._observer_options import ObserverChoice, observer_from_args, scheduled_observer
from ._values import CLIError


def add_design_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--design", default=None, metavar="FILE",
        help="run a tuned design: the gains table gains.json written by `python -m "
             "tuning` (or its output folder). The observer is the table's; its gains "
             "follow the table over speed (linear interpolation)")


def observer_with_design(args, drive: pj.Drive, *, default: str) -> ObserverChoice:
    """`observer_from_args`, with the design of `--design` applied when given
    (`default`: the command's default `--observer`)."""
    if getattr(args, "design", None) is None:
        return observer_from_args(args, drive)
    table = pj.load_gains_table(args.design)
    name = table["observer"]
    if args.observer not in (default, name):
        raise CLIError(f"--design {args.design} is a design of the {name} observer; "
                       f"--observer {args.observer} names another (leave --observer out "
                       f"or give --observer {name})")
    if args.gain or getattr(args, "fixed_at", None) is not None:
        raise CLIError(f"--design {args.design} sets the whole design; --gain and "
                       f"--fixed-at are not allowed with it")
    args.observer = name
    choice = observer_from_args(args, drive)
    if choice.gains:
        raise CLIError(f"--design {args.design} sets the whole design; the design options "
                       f"({', '.join(choice.gains)}) are not allowed with it")
    observer = scheduled_observer(args, pj.apply_gains_table(table, choice.observer), drive)
    warning = pj.verdict_warning(table)
    if warning is not None:
        print(f"warning: --design {args.design}: {warning}", file=sys.stderr)
    if table.get("T_s") is not None and getattr(args, "T_s", None) is not None \
            and abs(float(args.T_s) - float(table["T_s"])) > 1e-9 * float(table["T_s"]):
        print(f"warning: --design {args.design} was tuned at T_s = {table['T_s']:g} s; "
              f"this run uses {float(args.T_s):g} s", file=sys.stderr)
    if "speed_from_angle_Hz" in table and hasattr(args, "speed_from_angle"):
        tuned, here = table["speed_from_angle_Hz"], args.speed_from_angle
        if (tuned is None) != (here is None) or (tuned is not None and abs(
                float(here) - tuned) > 1e-9 * tuned):
            now = ("the observer's own speed" if here is None else
                   f"the speed of its angle at {float(here):g} Hz")
            print(f"warning: --design {args.design}: "
                  f"{pj.speed_loop_text(table).split(':')[0]}; this run takes {now} "
                  + ("(pass --speed-from-angle "
                     f"{tuned:g})" if tuned is not None else "(leave out --speed-from-angle)"),
                  file=sys.stderr)
    if table.get("drive") and table["drive"] != drive.name:
        print(f"note: --design {args.design} was tuned for drive {table['drive']!r}; this "
              f"run uses {drive.name!r} (pass its motor file with --motor-file)",
              file=sys.stderr)
    return dataclasses.replace(choice, observer=observer)
