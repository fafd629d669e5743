"""The drive of every command: `--motor NAME` or `--motor-file FILE` and `--set
NAME=VALUE` (the plant, `drive_from_args`), what the JSON reports record of it
(`header`), and the initial state of a run in time (`--theta0 DEG`, `--speed0 PU`)."""

from __future__ import annotations

import argparse
import math
import sys

import pmsmjax as pj
from pmsmjax._plant._motorfile import read_motor_file

from ._values import CLIError, finite_float, name_value


_SETTABLE = ("R_s (Ohm), L_d (H), L_q (H), psi_f (V s), n_p (pole pairs), J (kg m^2), "
             "B (N m s/rad), u_dc (V), u_max (V, peak phase), u_dt (V, the inverter's "
             "dead-time error per phase), i_dt (A, its transition width; 0: the hard model u_dt "
             "sign(i)); dual three-phase "
             "machines "
             "also L_xy (H), gamma (rad)")


def add_drive_options(parser: argparse.ArgumentParser) -> None:
    """`--motor NAME` or `--motor-file FILE`, and `--set NAME=VALUE` (the plant)."""
    g = parser.add_argument_group("drive (the plant)")
    g.add_argument("--motor", default=None, choices=pj.PRESET_NAMES, metavar="NAME",
                   help=f"motor preset, one of {', '.join(pj.PRESET_NAMES)} "
                        f"(default: {DEFAULT_MOTOR} unless --motor-file is given); each "
                        "preset states its source and assumptions in summary.json")
    g.add_argument("--motor-file", dest="motor_file", default=None, metavar="FILE",
                   help="your own drive as a motor file (TOML, SI units; `pmsmjax motor "
                        "--export NAME` writes a preset as one to start from; schema in "
                        "docs/motor-file.md), instead of --motor")
    g.add_argument("--set", dest="set_params", action="append", default=[], type=name_value,
                   metavar="NAME=VALUE",
                   help=f"replace a parameter of the drive (the plant), in SI units; "
                        f"repeatable. Names: {_SETTABLE}. Example: --set J=3e-3 --set "
                        "R_s=0.9. The observer's model follows the plant unless "
                        "--observer-set (or a --mismatch option) changes it")


#: The preset used when neither --motor nor --motor-file is given.
DEFAULT_MOTOR = "zhang750"
#: The sampling period (s) of a command that runs in time when neither `--T-s` nor the
#: drive (a motor file's `[control] T_s`) gives one.
DEFAULT_T_S = 125e-6
T_S_HELP = ("(s; default: the motor file's [control] T_s, else 125e-6)")


def sampling_period_from_args(args: argparse.Namespace, drive: pj.Drive) -> float:
    """`--T-s`, else the drive's `T_s` (a motor file's `[control] T_s`), else
    `DEFAULT_T_S`; also stored back into `args.T_s`."""
    if getattr(args, "T_s", None) is None:
        args.T_s = float(drive.T_s) if drive.T_s is not None else DEFAULT_T_S
    return float(args.T_s)


def drive_from_args(args: argparse.Namespace) -> pj.Drive:
    """The preset of `--motor` (or the drive of `--motor-file`) with the `--set`
    replacements applied."""
    motor_file = getattr(args, "motor_file", None)
    if motor_file is not None:
        if args.motor is not None:
            raise CLIError(f"--motor {args.motor} and --motor-file {motor_file}: give one "
                           f"of the two")
        try:
            drive, notes = read_motor_file(motor_file)
        except OSError as e:
            raise CLIError(f"--motor-file {motor_file}: cannot read it ({e.strerror})"
                           ) from None
        for note in notes:  # how the constants of a saturated machine were derived
            print(f"motor file {motor_file}: {note}", file=sys.stderr)
    else:
        drive = pj.preset(DEFAULT_MOTOR if args.motor is None else args.motor)
    values = dict(args.set_params)
    if values:
        try:
            drive = pj.replace_params(drive, **values)
        except ValueError as e:
            raise CLIError(f"--set: {e}") from None
    return drive


def drive_info(drive: pj.Drive, args) -> dict:
    return {
        "motor": drive.name,
        "motor_file": getattr(args, "motor_file", None),
        "preset_notes": drive.notes,
        "parameter_overrides": dict(args.set_params),
        "ratings": {"w_rated_rad_s": float(drive.w_rated), "tau_rated_Nm": float(drive.tau_rated),
                    "i_max_A": float(drive.i_max)},
        "base": {"U_b_V": float(drive.base.U_b), "I_b_A": float(drive.base.I_b),
                 "w_b_rad_s": float(drive.base.w_b), "tau_b_Nm": float(drive.base.tau_b)},
    }


def motor_text(drive: pj.Drive, args) -> str:
    """The drive a command used, for its console: `motor NAME` (the preset's or the motor
    file's name), the motor file and the `--set` replacements."""
    text = f"motor {drive.name}"
    if getattr(args, "motor_file", None) is not None:
        text += f" from {args.motor_file}"
    if args.set_params:
        text += " with " + ", ".join(f"{k} = {v:g}" for k, v in args.set_params)
    return text


def header(command: str, drive: pj.Drive, args) -> dict:
    """The first keys of every JSON report: command, version, drive."""
    return {"command": command, "pmsmjax_version": pj.__version__, **drive_info(drive, args)}


def add_initial_state_options(group, *, what: str, unknown: str | None = None) -> None:
    """`--theta0 DEG` and `--speed0 PU`: the initial angle and speed of `what` (the rotor,
    or the observer's estimate), in the units of every command (degrees, p.u. of the
    rated electrical speed). `unknown`: what happens when neither is given (the defaults
    are then 0). `initial_state_from_args` reads them."""
    default = f"default: {unknown}" if unknown else "default: 0"
    group.add_argument("--theta0", type=finite_float, default=None, metavar="DEG",
                       help=f"initial electrical angle of {what} (deg; {default})")
    group.add_argument("--speed0", type=finite_float, default=None, metavar="PU",
                       help=f"initial electrical speed of {what} (p.u. of the rated speed "
                            f"Drive.w_rated, any sign; {default})")


def initial_state_from_args(args, drive: pj.Drive) -> tuple[float, float]:
    """`(theta0 in rad, speed0 in rad/s)` of `--theta0 DEG` and `--speed0 PU`."""
    return (math.radians(float(args.theta0 or 0.0)),
            float(args.speed0 or 0.0) * float(drive.w_rated))


def initial_state_given(args) -> bool:
    """Whether `--theta0` or `--speed0` was given."""
    return args.theta0 is not None or args.speed0 is not None
