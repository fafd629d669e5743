"""`pmsmjax motor`: write a drive as a motor file, or check one."""

from __future__ import annotations

import argparse
import math
import os
import sys

import pmsmjax as pj

from ._command import Command
from ._drive_options import add_drive_options, drive_from_args
from ._output import prepare_out_dir
from ._values import CLIError


#: The file name `--out DIR` writes (the tuner writes its drive under the same name).
MOTOR_FILE = "motor.toml"


def _motor_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    g = p.add_argument_group("motor file")
    g.add_argument("--export", default=None, choices=pj.PRESET_NAMES, metavar="NAME",
                   help=f"write the motor file of the preset NAME (one of "
                        f"{', '.join(pj.PRESET_NAMES)}); the same as --motor NAME")
    g.add_argument("--out", dest="out_dir", default=None, metavar="DIR",
                   help="write the motor file to DIR/motor.toml, DIR created if missing, "
                        "as every command writes into its --out folder (default: print it "
                        "on stdout)")
    g.add_argument("--check", action="store_true",
                   help="only validate the drive (--motor-file FILE) and print a summary: "
                        "parameters, per-unit bases and derived ratings, and for a "
                        "saturated machine the check of its flux map (pmsmjax."
                        "check_flux_map; exit status 2 on an unusable map)")


def _summary(drive: pj.Drive) -> list[str]:
    m = drive.three_phase_motor
    w_M = float(drive.w_rated) / float(m.n_p)
    e_rated = float(drive.w_rated) * float(m.psi_f)
    lines = [
        f"drive {drive.name}: {'dual three-phase' if drive.dual else 'three-phase'} PMSM",
        f"  R_s {float(m.R_s):.4g} Ohm, L_d {1e3 * float(m.L_d):.4g} mH, L_q "
        f"{1e3 * float(m.L_q):.4g} mH, psi_f {float(m.psi_f):.4g} V s, n_p {float(m.n_p):g}",
        f"  J {float(drive.mechanics.J):.4g} kg m^2, B {float(drive.mechanics.B):.4g} N m s/rad,"
        f" u_dc {float(drive.inverter.u_dc):.4g} V (voltage limit "
        f"{float(drive.inverter.u_lim):.4g} V peak)",
        f"  rated: {float(drive.w_rated):.4g} rad/s electrical = "
        f"{w_M * 60 / (2 * math.pi):.4g} rpm, {float(drive.tau_rated):.4g} N m, current "
        f"limit {float(drive.i_max):.4g} A peak",
        f"  back-EMF at rated speed {e_rated:.4g} V peak "
        f"({e_rated / float(drive.inverter.u_lim):.3g} of the voltage limit)",
        f"  base: U_b {float(drive.base.U_b):.4g} V, I_b {float(drive.base.I_b):.4g} A, w_b "
        f"{float(drive.base.w_b):.4g} rad/s, tau_b {float(drive.base.tau_b):.4g} N m",
    ]
    if m.harmonics is not None:
        lines.append("  back-EMF harmonics: " + ", ".join(
            f"{h:+d}: {100 * float(a):.3g} %" for h, a in zip(m.harmonics.order,
                                                               m.harmonics.amplitude)))
    return lines


def motor_command(args: argparse.Namespace) -> int:
    if args.export is not None:
        if args.motor is not None or args.motor_file is not None:
            raise CLIError(f"--export {args.export} with --motor/--motor-file: give one "
                           f"(--export NAME is --motor NAME)")
        args.motor = args.export
    drive = drive_from_args(args)
    magnetic = drive.three_phase_motor.magnetic
    if args.check:
        print("\n".join(_summary(drive)))
        if magnetic is not None:
            report = pj.check_flux_map(magnetic, i_max=float(drive.i_max))
            print("\n".join(report.lines()))
            if report.errors:
                raise CLIError(f"the magnetic model is not usable: {report.errors[0]}")
        print("valid")
        return 0
    if args.out_dir is None:
        if isinstance(magnetic, pj.FluxMap):
            raise CLIError(f"drive {drive.name} has a flux map, written as a CSV file beside "
                           "the motor file: give --out DIR (stdout holds one file)")
        sys.stdout.write(pj.motor_file_text(drive))
        return 0
    path = os.path.join(prepare_out_dir(args.out_dir), MOTOR_FILE)
    pj.save_motor_file(drive, path)
    print("\n".join(_summary(drive)))
    if isinstance(magnetic, pj.FluxMap):
        print(f"wrote {os.path.splitext(path)[0]}_flux_map.csv (the flux map)")
    print(f"wrote {path}")
    return 0


COMMAND = Command(
    name="motor",
    help="write a drive as a motor file (TOML), or check one",
    description=(
        "Write the drive given by --motor NAME (or --export NAME) or --motor-file FILE, "
        "after the --set replacements, as a motor file (TOML, SI units) to --out "
        "DIR/motor.toml or stdout; every command (tune and compare too) accepts it with "
        "--motor-file. With --check, only validate it and print its parameters, bases "
        "and rated back-EMF, and for a saturated machine what its flux map or model holds "
        "(grid, current range, PM flux, incremental and apparent inductances at zero and "
        "rated current, reciprocity, whether the grid covers the current limit). A drive "
        "with a flux map is written with the map as a CSV file beside the motor file "
        "(needs --out). "
        "A malformed file ends with exit status 2 and a message that names the field and "
        "the allowed range."
    ),
    add_arguments=_motor_arguments,
    run=motor_command,
)
