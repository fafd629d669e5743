"""`pmsmjax identify`: fit a drive's parameters to recordings through the plant."""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np

import pmsmjax as pj

from .._data._identify_motion import LOAD_MODES, load_mode, mechanics_mode
from .._data._identify_saturation import flux_map_rows, saturation_table, write_flux_map
from .._files import atomic_write, write_json
from ._command import Command
from ._drive_options import add_drive_options, drive_from_args, drive_info
from ._output import add_output_options, prepare_out_dir
from ._values import CLIError, positive_float, positive_int


def _names(values: list[str]) -> list[str]:
    """`--fit R_s L_q` or `--fit R_s,L_q`: the names, in order, once each (`saturation`
    stands for the six coefficients of the saturation model)."""
    out = []
    for v in values:
        out += [s.strip() for s in v.split(",") if s.strip()]
    bad = [n for n in out if n not in pj.IDENTIFIABLE and n != "saturation"]
    if bad or not out:
        raise CLIError(f"--fit {' '.join(values)}: {', '.join(bad) or 'no name'} is not a "
                       f"parameter identify can fit; allowed: {', '.join(pj.IDENTIFIABLE)} "
                       f"or saturation")
    return list(dict.fromkeys(out))


def _exponents(text: str) -> tuple:
    """`--saturation-exponents 4,2,2,2`: S, T, U, V (>= 0)."""
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 4 or not all(v >= 0 and v < float("inf") for v in vals):
        raise argparse.ArgumentTypeError(
            f"{text!r}: four comma-separated numbers S,T,U,V >= 0 (e.g. 4,2,2,2)")
    return vals


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
                        "applies the inverter's dead-time error u_dt, hard or smooth as "
                        "the drive's i_dt says, which --fit u_dt i_dt estimates)")
    g.add_argument("--fit", required=True, nargs="+", metavar="NAME",
                   help=f"the parameters to fit, space- or comma-separated, among "
                        f"{', '.join(f'{n} ({u})' for n, (u, _) in pj.IDENTIFIABLE.items())}; "
                        f"'saturation' stands for the six coefficients a_d0 .. i_f of an "
                        f"algebraic saturation model (the plant then saturates; not with "
                        f"L_d, L_q, psi_f, which become the fitted model's small-current "
                        f"values); the others keep the drive's values, and the drive's "
                        f"values are the starting point")
    g.add_argument("--saturation-exponents", type=_exponents, default=None,
                   metavar="S,T,U,V",
                   help="the saturation model's exponents, held in the fit (default: the "
                        "motor file's algebraic model's, else 4,2,2,2)")
    g.add_argument("--min-coverage", type=float, default=0.5, metavar="F",
                   help="with --fit saturation: the fraction of the current range (i_d "
                        "over -i_max..0, |i_q| up to i_max) the recordings must cover per "
                        "axis; less gives a warning naming the axis and the coefficients it "
                        "leaves undetermined (default: %(default)s)")
    g.add_argument("--mechanics", choices=("auto", "measured", "integrated"), default="auto",
                   help="the rotor's motion in the model: 'measured' runs it on the "
                        "recorded angle and speed (any speed profile, a dyno's included; "
                        "no load torque needed), 'integrated' integrates the mechanics "
                        "with the recorded load torque (needed for J, B); 'auto' "
                        "(default): integrated when J or B is fitted, else measured")
    g.add_argument("--load-model", choices=LOAD_MODES, default="auto",
                   help="with the mechanics integrated, the load torque that drives them: "
                        "'recorded' (the log's tau_L, zero where none), 'segment' (a "
                        "constant load torque per segment fitted with the parameters, on "
                        "top of a logged one), 'auto' (default): fitted per segment for a "
                        "recording that logs none")
    g.add_argument("--segment", type=positive_float, default=0.02, metavar="S",
                   help="multiple-shooting segment length (s, default: %(default)s): each "
                        "segment restarts the model from the logged angle and a fitted "
                        "current (and speed) near the logged one")
    g.add_argument("--max-steps", type=positive_int, default=100, metavar="N",
                   help="Levenberg-Marquardt steps per solve (default: %(default)s)")
    add_output_options(p, None)


def identify_command(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    drive = drive_from_args(args)
    fit = _names(args.fit)
    recs = [pj.load_recording(f, require=("t", "u_ab", "i_ab", "theta")) for f in args.data]
    out = prepare_out_dir(args.out)
    mech = mechanics_mode(fit, args.mechanics)
    fit_load = load_mode(recs, mech, args.load_model)
    print(f"pmsmjax identify: {drive.name}, fitting {', '.join(fit)} to {len(recs)} "
          f"recording(s) ({sum(r.n for r in recs)} samples, {args.voltage} voltages)")
    print("mechanics: " + (
        "measured (the model runs on the recorded angle and speed; the speed is not a "
        "residual)" if mech == "measured" else
        "integrated over each segment from its measured start; the speed is a residual; "
        "load torque " + ("fitted per segment (constant over each)" if all(fit_load) else
                          "recorded (zero where none is logged)" if not any(fit_load) else
                          "fitted per segment where none is logged, else recorded")))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", pj.IdentifiabilityWarning)
        res = pj.identify(drive, recs, fit, voltage=args.voltage, segment=args.segment,
                          max_steps=args.max_steps, exponents=args.saturation_exponents,
                          min_coverage=args.min_coverage, mechanics=mech, load=args.load_model)
    # the log's own checks, with the motor file's machine (a fit absorbs a voltage shift
    # into the inductances, so the fitted values would hide it) and, for commanded
    # voltages, the fitted inverter (a dead time started from a guess would read as an
    # offset or a delay)
    inverter = res.drive.inverter if args.voltage == "commanded" else None
    log_warnings = [f"{f}: {w}" for f, r in zip(args.data, recs)
                    for w in pj.recording_warnings(r, drive, inverter=inverter)]
    for msg in log_warnings:
        print(f"warning: {msg}")
    for w in caught:
        if not issubclass(w.category, pj.IdentifiabilityWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    files = {"result": os.path.join(out, "identify.json"),
             "motor_file": os.path.join(out, "identified.toml")}
    text = pj.motor_file_text(res.drive)
    sat = res.saturation
    if sat is not None:
        files["flux_map"] = os.path.join(out, "flux_map.csv")
        write_flux_map(files["flux_map"], flux_map_rows(sat["model"], sat["currents"]))
        if "[saturation]" not in text:
            text += "\n" + saturation_table(sat["model"])
    atomic_write(files["motor_file"], text)
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
        "mechanics": res.mechanics,
        "load": [None if ld is None else {k: ld[k] for k in ("t_start", "value", "std")}
                 for ld in res.loads],
        "formulation": "multiple shooting: each segment restarts the plant from the logged "
                       "angle and a fitted current (and, with the mechanics integrated, "
                       "speed; and a load torque per segment where fitted); residuals = "
                       "model - measured current (A) and, with the mechanics integrated, "
                       "speed (rad/s), each channel divided by its residual RMS; "
                       "Levenberg-Marquardt",
        "segment_s": res.segment_s,
        "parameters": res.parameters,
        "residual_rms": res.residual_rms,
        "noise_estimate": res.noise,
        "cost_per_dof": res.cost,
        "condition": res.condition,
        "correlation": {"names": list(res.names), "matrix": res.correlation},
        "n_residuals": res.n_residuals,
        "n_segments": res.n_segments,
        "solver_steps": res.steps,
        "warnings": log_warnings + list(res.warnings),
        **({} if sat is None else {"saturation": {
            "model": "algebraic", **{k: float(getattr(sat["model"], k))
                                     for k in ("S", "T", "U", "V")},
            "currents": sat["currents"], "flux_std": sat["flux_std"],
            "deployed_constants": "L_d, L_q, psi_f of identified.toml are the fitted "
                                  "model's small-current values"}}),
        "wall_time_s": time.perf_counter() - t0,
        "files": {k: os.path.basename(v) for k, v in files.items()},
    }
    write_json(files["result"], report)
    for n, p in res.parameters.items():
        print(f"  {n:6s} {p['value']:.6g} {p['unit']} +- {p['std']:.2g} (from {p['initial']:.6g})")
    speed = ("speed measured" if res.mechanics == "measured"
             else f"{res.residual_rms['w_rad_s']:.3g} rad/s")
    print(f"residual RMS {res.residual_rms['i_A']:.3g} A (the log's current noise about "
          f"{res.noise['i_A']:.3g} A), {speed}; condition {res.condition:.3g}")
    for f, ld in zip(args.data, res.loads):
        if ld is not None:
            print(f"  load torque fitted per segment ({f}): {ld['value'].min():.3g} .. "
                  f"{ld['value'].max():.3g} N m over {ld['value'].size} segments, median "
                  f"+- {np.median(ld['std']):.2g}")
    if sat is not None:
        c, f = sat["currents"], sat["flux_std"]
        print(f"saturation: recorded i_d {c['i_d_A'][0]:.3g}..{c['i_d_A'][1]:.3g} A, i_q "
              f"{c['i_q_A'][0]:.3g}..{c['i_q_A'][1]:.3g} A (coverage d {c['coverage_d']:.0%}, "
              f"q {c['coverage_q']:.0%}); flux 1-sigma over them {f['psi_d_std_Vs']:.2g} / "
              f"{f['psi_q_std_Vs']:.2g} V s (d / q)")
    for msg in res.warnings:
        print(f"warning: {msg}")
    print(f"wrote {', '.join(files.values())}")
    return 0


COMMAND = Command(
    name="identify",
    help="fit a drive's parameters (R_s, L_d, L_q, psi_f, J, B, u_dt, i_dt, a saturation "
         "model) to recordings",
    description=(
        "Fit the parameters --fit of the drive (--motor or --motor-file, after --set; its "
        "values are the starting point) to one or more recordings --data by least squares "
        "through the differentiable plant (multiple shooting, Levenberg-Marquardt), with the "
        "recorded voltages taken as applied or as commanded (--voltage; then the inverter's "
        "dead-time error u_dt, i_dt acts and can be fitted). Writes to --out: identify.json "
        "(parameters.NAME.{value, initial, std} in SI units, the residual, the condition of "
        "the problem, the correlations), identified.toml (a motor file with the fitted "
        "values, for --motor-file; with --fit saturation, a [saturation] table with model = "
        "\"algebraic\" and its coefficients, and flux_map.csv: the fitted flux map sampled "
        "over the recorded currents) and identify.png (measured against model currents and "
        "speed). A parameter the recordings cannot determine ends the command with a message "
        "that names it and the excitation it needs; a weakly determined one, or recorded "
        "currents that cover too little of the range a saturation model needs, is a warning."
    ),
    add_arguments=_identify_arguments,
    run=identify_command,
)
