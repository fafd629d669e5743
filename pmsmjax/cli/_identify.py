"""`pmsmjax identify`: fit a drive's parameters to recordings through the plant."""

from __future__ import annotations

import argparse
import os
import time
import warnings

import pmsmjax as pj

from .._files import write_json
from ._command import Command
from ._drive_options import add_drive_options, drive_from_args, drive_info
from ._output import add_output_options, prepare_out_dir
from ._values import CLIError, positive_float, positive_int


def _names(values: list[str]) -> list[str]:
    """`--fit R_s L_q` or `--fit R_s,L_q`: the names, in order, once each."""
    out = []
    for v in values:
        out += [s.strip() for s in v.split(",") if s.strip()]
    bad = [n for n in out if n not in pj.IDENTIFIABLE]
    if bad or not out:
        raise CLIError(f"--fit {' '.join(values)}: {', '.join(bad) or 'no name'} is not a "
                       f"parameter identify can fit; allowed: {', '.join(pj.IDENTIFIABLE)}")
    return list(dict.fromkeys(out))


def _identify_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    g = p.add_argument_group("identification")
    g.add_argument("--data", required=True, nargs="+", metavar="FILE",
                   help="one or more recordings (.npz or .csv, recorded-data format) with t, "
                        "u_ab, i_ab and the rotor angle theta (an encoder log), and w_m "
                        "(else derived from theta) and tau_L (else zero) where recorded")
    g.add_argument("--voltage", choices=("applied", "commanded"), default="applied",
                   help="what the recordings' u_ab is: the voltage the windings received "
                        "(default), or the one the controller commanded (the plant then "
                        "applies the inverter's dead-time error u_dt, which --fit u_dt "
                        "estimates)")
    g.add_argument("--fit", required=True, nargs="+", metavar="NAME",
                   help=f"the parameters to fit, space- or comma-separated, among "
                        f"{', '.join(f'{n} ({u})' for n, (u, _) in pj.IDENTIFIABLE.items())}; "
                        f"the others keep the drive's values, and the drive's values are "
                        f"the starting point")
    g.add_argument("--segment", type=positive_float, default=0.02, metavar="S",
                   help="multiple-shooting segment length (s, default: %(default)s): each "
                        "segment restarts the model from the measured state")
    g.add_argument("--max-steps", type=positive_int, default=100, metavar="N",
                   help="Levenberg-Marquardt steps per solve (default: %(default)s)")
    add_output_options(p, None)


def identify_command(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    drive = drive_from_args(args)
    fit = _names(args.fit)
    recs = [pj.load_recording(f, require=("t", "u_ab", "i_ab", "theta")) for f in args.data]
    out = prepare_out_dir(args.out)
    print(f"pmsmjax identify: {drive.name}, fitting {', '.join(fit)} to {len(recs)} "
          f"recording(s) ({sum(r.n for r in recs)} samples, {args.voltage} voltages)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", pj.IdentifiabilityWarning)
        res = pj.identify(drive, recs, fit, voltage=args.voltage, segment=args.segment,
                          max_steps=args.max_steps)
    for w in caught:
        if not issubclass(w.category, pj.IdentifiabilityWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    files = {"result": os.path.join(out, "identify.json"),
             "motor_file": os.path.join(out, "identified.toml")}
    pj.save_motor_file(res.drive, files["motor_file"])
    if not args.no_plot:
        from pmsmjax.plotting import plot_identification

        files["plot"] = os.path.join(out, "identify.png")
        plot_identification(res).savefig(files["plot"], dpi=110)
    report = {
        "command": "identify",
        "pmsmjax_version": pj.__version__,
        **drive_info(drive, args),
        "data": list(args.data),
        "voltage": args.voltage,
        "formulation": "multiple shooting: each segment restarts the plant from the measured "
                       "state; residuals = model - measured current (A) and speed (rad/s), "
                       "each channel divided by its residual RMS; Levenberg-Marquardt",
        "segment_s": res.segment_s,
        "parameters": res.parameters,
        "residual_rms": res.residual_rms,
        "cost_per_dof": res.cost,
        "condition": res.condition,
        "correlation": {"names": list(res.names), "matrix": res.correlation},
        "n_residuals": res.n_residuals,
        "n_segments": res.n_segments,
        "solver_steps": res.steps,
        "warnings": list(res.warnings),
        "wall_time_s": time.perf_counter() - t0,
        "files": {k: os.path.basename(v) for k, v in files.items()},
    }
    write_json(files["result"], report)
    for n, p in res.parameters.items():
        print(f"  {n:6s} {p['value']:.6g} {p['unit']} +- {p['std']:.2g} (from {p['initial']:.6g})")
    print(f"residual RMS {res.residual_rms['i_A']:.3g} A, {res.residual_rms['w_rad_s']:.3g} "
          f"rad/s; condition {res.condition:.3g}")
    for msg in res.warnings:
        print(f"warning: {msg}")
    print(f"wrote {', '.join(files.values())}")
    return 0


COMMAND = Command(
    name="identify",
    help="fit a drive's parameters (R_s, L_d, L_q, psi_f, J, B, u_dt) to recordings",
    description=(
        "Fit the parameters --fit of the drive (--motor or --motor-file, after --set; its "
        "values are the starting point) to one or more recordings --data by least squares "
        "through the differentiable plant (multiple shooting, Levenberg-Marquardt), with the "
        "recorded voltages taken as applied or as commanded (--voltage; then the inverter's "
        "dead-time error u_dt acts and can be fitted). Writes to --out: identify.json "
        "(parameters.NAME.{value, initial, std} in SI units, the residual, the condition of "
        "the problem, the correlations), identified.toml (a motor file with the fitted "
        "values, for --motor-file) and identify.png (measured against model currents and "
        "speed). A parameter the recordings cannot determine ends the command with a message "
        "that names it and the excitation it needs; a weakly determined one is a warning."
    ),
    add_arguments=_identify_arguments,
    run=identify_command,
)
