"""`pmsmjax export-c`: C99 code of an observer's discrete step, exactly as `pmsmjax
replay` computes it (`pmsmjax.firmware`), with its gains or tuned gains table."""

from __future__ import annotations

import argparse

from pmsmjax.firmware import export_c, supported_observers
from pmsmjax.firmware._cost import cost_lines
from pmsmjax.firmware._dead_time import compensation

from ._command import Command
from ._design import add_design_option, observer_with_design
from ._drive_options import (
    T_S_HELP,
    add_drive_options,
    drive_from_args,
    motor_text,
    sampling_period_from_args,
)
from ._observer_options import (
    add_observer_options,
    add_speed_from_angle_option,
    speed_from_angle_text,
    with_speed_from_angle,
)
from ._output import add_output_options, first_line, prepare_out_dir
from ._values import CLIError, positive_float


def _arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    add_observer_options(p, default="eso")
    add_design_option(p)
    g = add_output_options(p, None, plot=False)
    g.add_argument("--T-s", dest="T_s", type=positive_float, default=None, metavar="S",
                   help="sampling period compiled into the code " + T_S_HELP + "; the "
                        "recording replayed must have this sampling period")
    g.add_argument("--float32", action="store_true",
                   help="generate float (single precision) arithmetic instead of double")
    add_speed_from_angle_option(g, "; the generated step returns it as w_hat")


def export_c_command(args: argparse.Namespace) -> int:
    if args.observer not in supported_observers():
        raise CLIError(f"--observer {args.observer}: export-c has no C code for it; it "
                       f"supports {', '.join(supported_observers())}")
    drive = drive_from_args(args)
    sampling_period_from_args(args, drive)
    choice = observer_with_design(args, drive, default="eso")
    inverter = drive.inverter if drive.inverter.dead_time != "none" else None
    if inverter is not None and drive.dual:
        raise CLIError("export-c: the dead-time compensation of a dual three-phase drive "
                       "needs its x-y currents, which the generated step does not take; "
                       "allowed for three-phase drives (drop u_dt with --set u_dt=0 to "
                       "generate code that takes applied voltages)")
    try:
        paths = export_c(with_speed_from_angle(args, choice.observer), args.T_s,
                         prepare_out_dir(args.out),
                         float32=args.float32, inverter=inverter)
    except ValueError as e:
        raise CLIError(str(e)) from e
    print(first_line("export-c", motor_text(drive, args),
                     choice.describe() + speed_from_angle_text(args),
                     f"T_s = {args.T_s:g} s, {'float' if args.float32 else 'double'}"))
    print(f"wrote {', '.join(paths.values())}")
    if inverter is None:
        print("no dead-time compensation (the drive's inverter has no u_dt): pmsm_obs_step "
              "expects the APPLIED voltage; for commanded voltages (duty cycles, references) "
              "give the drive's [inverter] u_dt (and i_dt) in the motor file or --set")
    else:
        print(f"dead-time compensation: {compensation(inverter).model}; pmsm_obs_step takes "
              f"the COMMANDED voltage and hands the observer what replay --voltage commanded "
              f"does")
    cost = cost_lines(args.observer, args.T_s, args.float32)
    if cost:
        print(" ".join(cost))
    print(f"build: cc -std=c99 -O2 -o replay {args.out}/replay_main.c "
          f"{args.out}/pmsm_observer.c -lm; run: ./replay < recording.csv")
    return 0


COMMAND = Command(
    name="export-c",
    help="write C99 code of an observer's discrete step (as replay computes it)",
    description=(
        "Write plain C99 (no allocation, libm only) of the observer's discrete step exactly "
        "as `pmsmjax replay` computes it, with its gains (or the tuned gains table of "
        "--design) and the drive's dead-time compensation (the motor file's [inverter] u_dt, "
        "i_dt: the step then takes commanded voltages, as replay --voltage commanded; "
        "without u_dt it takes applied ones), into --out: pmsm_observer.h (state, inputs, "
        "units, sampling period), pmsm_observer.c (pmsm_obs_init, pmsm_obs_step) and "
        "replay_main.c, which reads a CSV recording t,u_a,u_b,i_a,i_b (one header line, "
        "SI units, stationary alpha-beta frame) on standard input and prints "
        "theta_hat,w_hat per sample. "
        f"Observers: {', '.join(supported_observers())}. See docs/firmware.md."
    ),
    add_arguments=_arguments,
    run=export_c_command,
)
