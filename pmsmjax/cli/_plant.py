"""`pmsmjax plant`: the open-loop plant driven by recorded voltages."""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

import pmsmjax as pj

from .._files import write_json
from ._command import Command
from ._drive_options import (
    add_drive_options,
    add_initial_state_options,
    drive_from_args,
    drive_info,
    initial_state_from_args,
)
from ._output import add_output_options, prepare_out_dir
from ._runs import compile_and_run
from ._values import CLIError, positive_int


def _plant_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    g = p.add_argument_group("input")
    g.add_argument("--data", required=True, metavar="FILE",
                   help="recorded drive data (.npz or .csv, format in "
                        "docs/conventions.md): t (s) and u_ab (V) are required, tau_L (N m) "
                        "is used if present (else zero load); i_ab (A), theta (rad) and w_m "
                        "(rad/s), if present, are compared with the simulation")
    add_initial_state_options(g, what="the rotor")
    g.add_argument("--init-from-data", action="store_true",
                   help="take the initial angle, speed and current from the first sample of "
                        "the data (needs theta; uses w_m and i_ab if present) instead of "
                        "--theta0/--speed0 and zero current")
    g.add_argument("--substeps", type=positive_int, default=4, metavar="N",
                   help="RK4 steps per sampling period (default: %(default)s; use the "
                        "simulation's value, 1 for `pmsmjax simulate`, to reproduce it)")
    add_output_options(p, None).add_argument(
        "--format", choices=("npz", "csv"), default="npz",
        help="format of the output data file plant.npz/plant.csv (default: %(default)s)")


def _compare(sim: pj.RecordedData, rec: pj.RecordedData) -> dict:
    """RMS/max differences simulated - recorded for i_ab, theta (wrapped), w_m."""
    out = {}
    units = {"i_ab": "A", "theta": "rad", "w_m": "rad/s"}
    for name, unit in units.items():
        r = getattr(rec, name)
        if r is None:
            continue
        s = getattr(sim, name)
        if name == "theta":  # angles: the wrapped difference; no meaningful relative size
            d = np.asarray(pj.wrap_angle(s - r))
            scale = None
        else:  # vectors: the length of the difference vector at each sample
            d = s - r
            scale = float(np.sqrt(np.mean(np.sum(r.reshape(len(r), -1) ** 2, axis=-1))))
        d_abs = np.sqrt(np.sum(d.reshape(len(d), -1) ** 2, axis=-1))
        rms = float(np.sqrt(np.mean(d_abs ** 2)))
        out[name] = {"unit": unit, "rms_diff": rms, "max_abs_diff": float(np.max(d_abs)),
                     "rms_recorded": scale,
                     "relative_rms_diff": rms / scale if scale else None}
    return out


def plant_command(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    data = pj.load_recording(args.data, require=("t", "u_ab"))
    drive = drive_from_args(args)
    theta0, w_m0 = initial_state_from_args(args, drive)
    i_dq0 = (0.0, 0.0)
    if args.init_from_data:
        if data.theta is None:
            raise CLIError(f"--init-from-data needs `theta` in {args.data}")
        theta0 = float(data.theta[0])
        if data.w_m is not None:
            w_m0 = float(data.w_m[0])
        if data.i_ab is not None:
            i_dq0 = tuple(float(x) for x in np.asarray(pj.park(data.i_ab[0], theta0)))
    tau_L = data.tau_L if data.tau_L is not None else np.zeros(data.n)
    out = prepare_out_dir(args.out)

    print(f"pmsmjax plant: {drive.name}, {data.n} samples at T_s = {data.T_s:g} s from "
          f"{args.data} ({', '.join(data.names)})")
    trace, t_compile, t_run = compile_and_run(
        pj.run_plant, drive, data.t, data.u_ab, tau_L, n_substeps=args.substeps,
        theta0=theta0, w_m0=w_m0, i_dq0=i_dq0)
    sim = pj.RecordedData(t=data.t, u_ab=data.u_ab, i_ab=trace.i_ab, theta=trace.theta,
                          w_m=trace.w_m, tau_L=tau_L)
    comparison = _compare(sim, data)
    files = {"data": os.path.join(out, f"plant.{args.format}"),
             "summary": os.path.join(out, "summary.json")}
    pj.save_recording(files["data"], sim)
    if not args.no_plot:
        from pmsmjax.plotting import plot_plant_trace

        files["plot"] = os.path.join(out, "plant.png")
        fig = plot_plant_trace(trace, drive, data=data,
                               title=f"{drive.name}: plant driven by {os.path.basename(args.data)}")
        fig.savefig(files["plot"], dpi=120)

    i_abs = np.hypot(sim.i_ab[:, 0], sim.i_ab[:, 1])
    summary = {
        "command": "plant",
        "pmsmjax_version": pj.__version__,
        **drive_info(drive, args),
        "data": os.path.abspath(args.data),
        "arrays_in_data": list(data.names),
        "samples": data.n,
        "T_s": data.T_s,
        "n_substeps": int(args.substeps),
        "initial_state": {"theta0_rad": float(theta0), "w_m0_rad_s": float(w_m0),
                          "i_dq0_A": list(i_dq0)},
        "compile_time_s": t_compile,
        "run_time_s": t_run,
        "wall_time_s": None,
        "final_speed": {"rad_s": float(sim.w_m[-1]), "pu": float(sim.w_m[-1] / drive.w_rated)},
        "max_current": {"A": float(np.max(i_abs)), "pu": float(np.max(i_abs) / drive.base.I_b)},
        "comparison_with_data": comparison,
        "files": {k: os.path.basename(v) for k, v in files.items()},
    }
    summary["wall_time_s"] = time.perf_counter() - t_start
    write_json(files["summary"], summary)

    print(f"final speed {summary['final_speed']['pu']:.4f} p.u.; max current "
          f"{summary['max_current']['A']:.3g} A")
    for name, c in comparison.items():
        rel = c["relative_rms_diff"]
        rel_txt = "" if rel is None else f" ({rel:.2e} relative)"
        print(f"simulated - recorded {name}: rms {c['rms_diff']:.3e} {c['unit']}{rel_txt}, "
              f"max {c['max_abs_diff']:.3e} {c['unit']}")
    print(f"wrote {', '.join(files.values())}")
    return 0


COMMAND = Command(
    name="plant",
    help="open-loop plant run driven by recorded voltages; compares with recorded currents",
    description=(
        "Drive the plant model with the voltages u_ab (and load torque tau_L) of a recorded-"
        "data file (ZOH between samples) and write the simulated i_ab, theta (unwrapped), w_m "
        "in the same format to --out (plant.npz or plant.csv, with t, u_ab, tau_L copied), plus "
        "plant.png and summary.json. If the file holds i_ab, theta or w_m, the RMS "
        "difference between simulation and recording is reported."
    ),
    add_arguments=_plant_arguments,
    run=plant_command,
)
