"""`pmsmjax replay`: any observer of the registry over recorded voltages and currents."""

from __future__ import annotations

import argparse
import math
import os
import sys

import numpy as np

import pmsmjax as pj

from .._files import save_npz, write_json
from ._command import Command
from ._design import add_design_option, observer_with_design
from ._drive_options import (
    add_drive_options,
    add_initial_state_options,
    drive_from_args,
    drive_info,
    initial_state_from_args,
    initial_state_given,
    motor_text,
)
from ._observer_options import (
    add_observer_options,
    add_speed_from_angle_option,
    speed_from_angle_text,
    with_speed_from_angle,
)
from ._output import add_output_options, first_line, prepare_out_dir
from ._runs import run_lock_status
from ._values import CLIError, nonneg_float


def _replay_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    g = p.add_argument_group("input")
    g.add_argument("--data", required=True, metavar="FILE",
                   help="recorded drive data (.npz or .csv, format in docs/conventions.md) "
                        "with t, u_ab, i_ab (and optionally theta, w_m to score the estimates)")
    add_initial_state_options(
        g, what="the observer's estimate",
        unknown="unknown: a rotor that turns from the first samples is caught from their "
                "back-EMF (as --flying-start), otherwise 0")
    g.add_argument("--voltage", choices=("applied", "commanded"), default="applied",
                   help="what the recording's u_ab is: the voltage the inverter applied "
                        "(default), or the one the drive's controller commanded; with "
                        "'commanded' the observer sees it less the drive's inverter error "
                        "model (u_dt, i_dt of the motor file's [inverter] or --set u_dt=V)")
    g.add_argument("--flying-start", action="store_true",
                   help="start the observer from the angle and speed read off the model "
                        "back-EMF of the first 64 samples (pmsmjax.flying_start) even "
                        "where they do not look like a turning rotor; replaces "
                        "--theta0/--speed0")
    g.add_argument("--t-settle", type=nonneg_float, default=None, metavar="S",
                   help="statistics over the samples after this time (s, from the first "
                        "sample; default: half the record)")
    add_observer_options(p, default="eso", mismatch=True, scheduled=True)
    add_speed_from_angle_option(p, "; the replayed w_hat is then that speed")
    add_design_option(p)
    add_output_options(p, None)


def _plot(path, data: pj.RecordedData, theta_hat, w_hat, name: str) -> None:
    from matplotlib.figure import Figure

    t = np.asarray(data.t)
    rows = 3 if data.theta is not None else 2
    fig = Figure(figsize=(8, 2.4 * rows), layout="constrained")
    ax = fig.subplots(rows, 1, sharex=True)
    if data.w_m is not None:
        ax[0].plot(t, data.w_m, "k", lw=1, label="w_m")
    ax[0].plot(t, w_hat, "r", lw=1, label=f"w_hat ({name})")
    ax[0].set_ylabel("speed (rad/s, el.)")
    ax[0].legend(loc="best")
    if data.theta is not None:
        ax[1].plot(t, np.asarray(pj.wrap_angle(data.theta)), "k", lw=1, label="theta")
    ax[1].plot(t, theta_hat, "r", lw=0.8, label="theta_hat")
    ax[1].set_ylabel("angle (rad)")
    ax[1].legend(loc="best")
    if data.theta is not None:
        err = np.degrees(np.asarray(pj.wrap_angle(data.theta - theta_hat)))
        ax[2].plot(t, err, "b", lw=1)
        ax[2].set_ylabel("theta error (deg)")
    ax[-1].set_xlabel("t (s)")
    fig.savefig(path, dpi=110)


def _lost_lock_hints(args, drive: pj.Drive, log_warnings: list[str]) -> list[str]:
    """What to check after a lost lock, from what the command knows of the log."""
    hints = []
    if args.voltage == "applied":
        hints.append(
            "if the log's voltages are the controller's commands (duty cycles, references), "
            "replay with --voltage commanded" + (
                f" (the drive's dead time u_dt = {float(drive.inverter.u_dt):g} V)"
                if drive.inverter.u_dt is not None else
                " and the drive's dead time u_dt (pmsmjax identify --fit u_dt --voltage "
                "commanded)"))
    if log_warnings:
        hints.append("see the warnings above about the log")
    return hints


def replay_command(args: argparse.Namespace) -> int:
    drive = drive_from_args(args)
    choice = observer_with_design(args, drive, default="eso")
    data = pj.load_recording(args.data, require=("t", "u_ab", "i_ab"))
    inverter = None
    if args.voltage == "commanded":
        if drive.inverter.u_dt is None:
            raise CLIError("--voltage commanded needs the drive's inverter error model: "
                           "u_dt (V) in the motor file's [inverter] section or --set u_dt=V "
                           "(pmsmjax identify --fit u_dt estimates it from a recording)")
        if drive.dual:
            raise CLIError("--voltage commanded: the dead-time compensation of a dual "
                           "three-phase drive needs its x-y currents, which recordings do "
                           "not carry; allowed for three-phase drives")
        inverter = drive.inverter
    out = prepare_out_dir(args.out)
    duration = float(data.t[-1] - data.t[0])
    t_settle = 0.5 * duration if args.t_settle is None else float(args.t_settle)
    if t_settle > duration:
        raise CLIError(f"--t-settle {t_settle:g}: the record lasts {duration:.6g} s; allowed: "
                       f"0 <= S <= {duration:.6g}")
    print(first_line("replay", motor_text(drive, args),
                     choice.describe() + speed_from_angle_text(args),
                     f"{data.n} samples at T_s = {data.T_s:g} s from {args.data}"))
    log_warnings = pj.recording_warnings(data, drive, inverter=inverter)
    for msg in log_warnings:
        print(f"warning: {msg}")
    theta0, w0 = initial_state_from_args(args, drive)
    start = "given"
    if not args.flying_start and not initial_state_given(args):
        th, w, turning = pj.initial_estimate(choice.observer, data, inverter=inverter)
        theta0, w0 = float(th), float(w)
        start = "caught turning" if bool(turning) else "at rest"
        what = ("a turning rotor caught from the first samples" if bool(turning) else
                "the first samples show no turning rotor")
        print(f"start: {what}: theta0 = {math.degrees(theta0):.4g} deg, w0 = {w0:.5g} rad/s "
              "(--theta0/--speed0 to choose)")
    if args.flying_start:
        start = "flying start"
        model = choice.observer.motor
        if not isinstance(model, pj.PMSMParams):
            model = drive.three_phase_motor
        fs = pj.flying_start(model, data.u_ab, data.i_ab, data.T_s,
                             n=min(64, data.n - 1))
        theta0, w0 = float(fs.theta0), float(fs.w0)
        print(f"flying start: theta0 = {math.degrees(theta0):.4g} deg, w0 = {w0:.5g} rad/s "
              f"(back-EMF {float(fs.e_mag):.3g} V)")
    unknown = start in ("caught turning", "at rest")  # replay's own default start
    est = pj.replay_estimates(with_speed_from_angle(args, choice.observer), data,
                              theta0=None if unknown else theta0,
                              w0=None if unknown else w0, inverter=inverter)
    theta_hat, w_hat = np.asarray(est.theta_hat), np.asarray(est.w_hat)
    extras = {k: np.asarray(v) for k, v in est.extras.items()}
    clash = sorted(set(extras) & (set(pj.RecordedData.__dataclass_fields__) | {"t"}))
    if clash:  # an observer must not shadow the recorded-data names
        raise ValueError(f"the {choice.name} observer's extras {', '.join(clash)} clash with "
                         f"the recorded-data names")

    files = {"data": os.path.join(out, "replay.npz"),
             "stats": os.path.join(out, "stats.json")}
    rec = pj.RecordedData(t=data.t, u_ab=data.u_ab, i_ab=data.i_ab, theta=data.theta,
                          w_m=data.w_m, tau_L=data.tau_L, theta_hat=theta_hat, w_hat=w_hat)
    # The recorded-data arrays (`pj.load_recording` reads them back) and every extra of the
    # Estimate under its name; plain arrays, no pickled objects.
    save_npz(files["data"], {**rec.arrays(), **extras})
    stats = pj.replay_stats(data.t, theta_hat, w_hat, data.theta, data.w_m, t_settle=t_settle)
    finite = bool(np.all(np.isfinite(theta_hat)) and np.all(np.isfinite(w_hat)))
    if data.theta is not None:
        lock = run_lock_status(data.t, np.asarray(data.theta) - theta_hat, finite)
        status = lock["status"]
    else:
        lock = None
        status = ("successful (the recording has no true angle: lock not checked)"
                  if finite else "diverged")
    report = {
        "command": "replay",
        "pmsmjax_version": pj.__version__,
        **drive_info(drive, args),
        "observer": choice.name,
        "observer_details": choice.info(),
        "design_file": getattr(args, "design", None),
        "speed_from_angle_Hz": args.speed_from_angle,
        "data": str(args.data),
        "T_s": data.T_s,
        "voltage": args.voltage,
        "inverter_model": None if inverter is None else {
            "u_dt": float(inverter.u_dt), "i_dt": float(inverter.i_dt),
            "dead_time": inverter.dead_time},
        "initial_estimate": {"theta0_deg": math.degrees(theta0), "w0_rad_s": w0,
                             "flying_start": bool(args.flying_start), "start": start},
        "arrays": {"theta_hat": "rad, estimated electrical angle at t_k, wrapped",
                   "w_hat": "rad/s, estimated electrical speed at t_k",
                   **{k: choice.cls.extras.get(k, "") for k in extras}},
        **stats,
        "status": status,
        "lock": lock,
        "log_warnings": log_warnings,
    }
    if not args.no_plot:
        files["plot"] = os.path.join(out, "replay.png")
        _plot(files["plot"], data, theta_hat, w_hat, choice.name)
    report["files"] = {k: os.path.basename(v) for k, v in files.items()}
    write_json(files["stats"], report)

    if "theta_err_mean_deg" in stats:
        print(f"angle error after {stats['t_settle']:g} s: mean "
              f"{stats['theta_err_mean_deg']:.4g} deg, std {stats['theta_err_std_deg']:.4g} "
              f"deg, max {stats['theta_err_max_deg']:.4g} deg")
    print(f"status: {status}")
    print(f"wrote {', '.join(files.values())}")
    if lock is not None and lock["lost"] and finite:
        print(f"pmsmjax replay: the observer lost lock at t = {lock['t_lost_s']:.4g} s "
              f"(mean |angle error| over {1e3 * lock['dwell_s']:g} ms above "
              f"{lock['lock_deg']:g} deg)" + "".join(f"; {h}" for h in _lost_lock_hints(
                  args, drive, log_warnings)),
              file=sys.stderr)
    return 0


COMMAND = Command(
    name="replay",
    help="run any observer of the registry over recorded voltages and currents",
    description=(
        "Run an observer (--observer, any of the registry, with its paper's default design "
        "changed by --gain and the shorthands, and its machine model changed by "
        "--observer-set) over the recorded u_ab, i_ab of a data file (.npz or .csv) from "
        "the initial estimate --theta0 (deg)/--speed0 (p.u.), and write to --out: "
        "replay.npz (the input "
        "arrays t, u_ab, i_ab and, when present, theta, w_m, tau_L; theta_hat and w_hat at "
        "each t_k; and every observer-specific output of the Estimate under its name, e.g. "
        "psi_ab_hat (V s) for the zhang2022 observers; plain arrays, readable by "
        "pmsmjax.load_recording and numpy.load), stats.json (the observer, its design and "
        "model, and the angle-error mean/std/max in deg after --t-settle and the speed "
        "error, when the file has theta and w_m) and replay.png."
    ),
    add_arguments=_replay_arguments,
    run=replay_command,
)
