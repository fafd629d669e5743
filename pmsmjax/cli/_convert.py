"""`pmsmjax convert`: a drive logger's CSV to the recorded-data format (`pmsmjax.convert_log`)."""

from __future__ import annotations

import argparse
import os

import pmsmjax as pj

from .._files import write_json
from ._command import Command
from ._drive_options import add_drive_options, drive_from_args
from ._output import add_json_option, add_output_options, prepare_out_dir, print_json
from ._values import CLIError


def _convert_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", metavar="LOG",
                   help="the logger's CSV file (any delimiter, column names, units and scales "
                        "the layout describes)")
    p.add_argument("--layout", required=True, metavar="FILE",
                   help="the log's layout (TOML): which columns hold time, currents, "
                        "voltages or duty cycles, angle, speed and load, in which units and "
                        "scales, and the voltages' delay; keys in docs/your-own-drive.md")
    add_drive_options(p)
    g = add_output_options(p, None)  # and --no-plot
    g.add_argument("--format", choices=("npz", "csv"), default="npz",
                   help="format of the recording written to --out (default: %(default)s)")
    add_json_option(g)


def convert_command(args: argparse.Namespace) -> int:
    layout = pj.load_log_layout(args.layout)
    given = args.motor is not None or args.motor_file is not None
    if args.set_params and not given:
        raise CLIError("--set changes the drive: give it with --motor-file or --motor")
    drive = drive_from_args(args) if given else None
    result = pj.convert_log(args.log, layout, drive=drive)
    out = prepare_out_dir(args.out)
    files = {"data": os.path.join(out, f"recording.{args.format}"),
             "summary": os.path.join(out, "convert.json")}
    pj.save_recording(files["data"], result.data)
    if not args.no_plot:
        from pmsmjax.plotting import plot_recording

        files["plot"] = os.path.join(out, "recording.png")
        plot_recording(result.data, title=f"{os.path.basename(args.log)} converted",
                       t_window=0.1).savefig(files["plot"], dpi=110)
    summary = {"command": "convert", "pmsmjax_version": pj.__version__,
               "log": os.path.abspath(args.log), "layout": os.path.abspath(args.layout),
               "drive": None if drive is None else drive.name, **result.summary(),
               "files": {k: os.path.basename(v) for k, v in files.items()}}
    write_json(files["summary"], summary)
    if args.json:
        print_json(summary)
        return 0
    print(f"pmsmjax convert: {args.log} with layout {args.layout}"
          + ("" if drive is None else f"; drive {drive.name}"))
    print("\n".join(result.lines()))
    if drive is None and layout.angle is not None:
        print("  (give the drive, --motor-file or --motor, to check the encoder offset "
              "against the voltages)")
    print(f"wrote {', '.join(files.values())}")
    return 0


COMMAND = Command(
    name="convert",
    help="a drive logger's CSV (your column names, units, scales, duty cycles) to the "
         "recorded-data format",
    description=(
        "Read a CSV written by a drive's logger through a layout file (the columns of time, "
        "phase or alpha-beta currents and voltages or duty cycles with the DC bus, encoder "
        "angle, speed and load; units and scales; the voltages' computational delay) and "
        "write the recorded-data format that replay, identify and plant read "
        "(--out/recording.npz, convert.json, and recording.png: its first 0.1 s with the "
        "currents in the rotor frame of the logged angle, to check by eye). The console "
        "states the timing convention it assumed; a mismatch between log and layout (a "
        "missing column, a cell that is not a number, time that does not increase, a gap, "
        "a clipped ADC) is a one-line error naming the line and column. With the drive "
        "(--motor-file), the encoder offset and a shift of the voltages are estimated from "
        "the voltages and reported (the offset removed with [angle] offset = "
        "\"estimate\")."
    ),
    add_arguments=_convert_arguments,
    run=convert_command,
)
