"""`pmsmjax simulate`: one closed-loop run (FOC and an observer of the registry)."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time

import equinox as eqx
import jax
import numpy as np

import pmsmjax as pj

from .._files import save_npz, write_json
from ._command import Command
from ._design import add_design_option, observer_with_design
from ._drive_options import (
    T_S_HELP,
    add_drive_options,
    drive_from_args,
    drive_info,
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
from ._runs import compile_and_run, run_lock_status
from ._scenarios import SCENARIOS
from ._values import CLIError, finite_float, nonneg_float, positive_float, positive_int


_CATCH_TEXT = ("catch: the observer re-started from the back-EMF of the first 64 samples "
               "where the rotor turns (pmsmjax.FlyingCatch)")


def _startup_info(su, catch: bool = False) -> dict | None:
    if catch:
        return {"type": "catch", "window_samples": 64}
    if su is None:
        return None
    return {"type": "I/f", "i_start_A": float(su.i_start), "a_max_rad_s2": float(su.a_max),
            "w_hand_rad_s": float(su.w_hand), "t_blend_s": float(su.t_blend),
            "stabiliser_c_damp_s": float(su.c_damp)}


def _startup_text(su) -> str:
    if su is None:
        return "none (the observer's frame from the first sample)"
    return (f"I/f, {float(su.i_start):.3g} A open loop, handover at {float(su.w_hand):.4g} "
            f"rad/s over {float(su.t_blend):.3g} s" + (
                f", stabiliser c_damp {float(su.c_damp):.3g} s" if su.c_damp > 0 else ""))


def _speed_error_stats(x: np.ndarray, scale: float) -> dict:
    """`pj.error_stats` of the settled speed error (rad/s) and the same in p.u. of
    `scale`; None everywhere when no sample has settled."""
    keys = ("mean", "std", "rms", "max_abs")
    if np.size(x) == 0:
        return {k: None for k in keys} | {f"{k}_pu": None for k in keys}
    s = pj.error_stats(x)
    return s | {f"{k}_pu": s[k] / scale for k in keys}


def _simulate_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    g = p.add_argument_group("scenario")
    g.add_argument("--scenario", default="default", choices=tuple(SCENARIOS), metavar="NAME",
                   help="; ".join(f"'{k}': {v.help}" for k, v in SCENARIOS.items())
                   + " (default: %(default)s)")
    g.add_argument("--t-end", type=positive_float, default=1.5, metavar="S",
                   help="duration of the run (s, default: %(default)s)")
    g.add_argument("--speed", type=finite_float, default=0.5, metavar="PU",
                   help="speed set-point (p.u. of the rated speed, default: %(default)s)")
    g.add_argument("--load", type=finite_float, default=None, metavar="PU",
                   help="load-torque step (p.u. of the rated torque; default 0.5 for the "
                        "scenarios with a load step, not allowed for the others)")
    g = p.add_argument_group("control and sensing")
    g.add_argument("--T-s", dest="T_s", type=positive_float, default=None, metavar="S",
                   help="sampling period of the controller " + T_S_HELP)
    g.add_argument("--current-bw", type=positive_float, default=500.0, metavar="HZ",
                   help="current-loop bandwidth (Hz; alpha_c = 2 pi HZ rad/s, "
                        "default: %(default)s)")
    g.add_argument("--speed-bw", type=positive_float, default=5.0, metavar="HZ",
                   help="speed-loop bandwidth (Hz; alpha_s = 2 pi HZ rad/s, "
                        "default: %(default)s)")
    g.add_argument("--noise", type=nonneg_float, default=0.0, metavar="A",
                   help="standard deviation of white noise on each sampled current "
                        "component (A, default: %(default)s)")
    g.add_argument("--delay", action="store_true",
                   help="one-sample computational delay: the voltage computed at t_k is "
                        "applied over [t_(k+1), t_(k+2))")
    g.add_argument("--observer-u-dt", type=nonneg_float, default=None, metavar="V",
                   help="the inverter error (V per phase) that the drive's dead-time "
                        "compensation assumes for the observer's voltage (default: the "
                        "drive's own u_dt, set with --set u_dt=V; 0: the observer sees the "
                        "commanded voltage). The recording's u_ab is the commanded voltage: "
                        "replay it with --voltage commanded")
    g.add_argument("--seed", type=int, default=0, metavar="N",
                   help="seed of the noise generator (integer, default: %(default)s)")
    g.add_argument("--substeps", type=positive_int, default=1, metavar="N",
                   help="RK4 steps of the plant per sampling period (default: %(default)s)")
    g.add_argument("--startup", default="auto", choices=("auto", "if", "catch", "none"),
                   help="start-up of a sensorless drive: 'if' an open-loop current-vector "
                        "(I/f) start with a handover to the observer at 0.1 p.u. "
                        "(pmsmjax.IfStartup.from_drive; speed-controlled scenarios), "
                        "'catch' the observer re-started from the back-EMF of the first 64 "
                        "samples where the rotor turns (pmsmjax.FlyingCatch, a drive's "
                        "catch-on-the-fly), 'none' the observer's frame from the first "
                        "sample; 'auto' (default) for a sensorless observer 'if' when the "
                        "rotor starts at standstill, 'catch' when it turns (all: a "
                        "drive's practice, not the papers')")
    g.add_argument("--if-damping", type=nonneg_float, default=0.0, metavar="ZETA",
                   help="the I/f start's stabiliser: the damping ratio it gives the rotor's "
                        "swing about the aligned current (0.7 its design value; default "
                        "%(default)s: off; pmsmjax.IfStartup.from_drive(zeta=...))")
    add_speed_from_angle_option(g, "; the controller takes it")
    g.add_argument("--theta-hat0", type=finite_float, default=None, metavar="DEG",
                   help="the observer's initial angle estimate (deg, electrical; default: "
                        "the rotor's initial angle 0, i.e. a known angle)")
    g.add_argument("--speed-hat0", type=finite_float, default=None, metavar="PU",
                   help="the observer's initial speed estimate (p.u. of the rated speed; "
                        "default: the rotor's initial speed, i.e. known)")
    add_observer_options(p, default="sensored", sensored=True, mismatch=True, scheduled=True,
                         default_note=": the encoder angle and speed")
    add_design_option(p)
    add_output_options(p, "results")


def simulate_command(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    spec = SCENARIOS[args.scenario]
    if args.load is not None and not spec.uses_load:
        raise CLIError(f"--load is not used by scenario {args.scenario!r} (it has no load step)")
    load = spec.default_load if args.load is None else args.load
    drive = drive_from_args(args)
    sampling_period_from_args(args, drive)
    if args.delay:
        # The Inverter's delay flag is static: replace the whole Inverter.
        inv = drive.inverter
        drive = eqx.tree_at(lambda d: d.inverter, drive,
                            pj.Inverter(u_dc=inv.u_dc, u_max=inv.u_max, delay=True,
                                    u_dt=inv.u_dt, i_dt=inv.i_dt))
    scenario, description, w_m0 = spec.build(drive, args.t_end, args.speed, load)
    alpha_c, alpha_s = 2 * math.pi * args.current_bw, 2 * math.pi * args.speed_bw
    choice = observer_with_design(args, drive, default="sensored")
    observer = choice.observer
    startup = args.startup
    if startup == "auto":
        startup = "none"
        if args.observer != "sensored":
            startup = ("if" if scenario.speed_mode else "none") if w_m0 == 0.0 else "catch"
    if startup in ("if", "catch") and args.observer == "sensored":
        raise CLIError(f"--startup {startup} needs a sensorless observer (--observer NAME): "
                       "the sensored drive knows its angle from the start")
    if args.speed_from_angle is not None:
        if args.observer == "sensored":
            raise CLIError("--speed-from-angle needs a sensorless observer (--observer NAME): "
                           "the sensored drive reads its speed from the encoder")
        observer = with_speed_from_angle(args, observer)
    if startup == "catch":
        observer = pj.FlyingCatch(observer)
    controller = pj.FOC.from_drive(
        drive, alpha_c=alpha_c, alpha_s=alpha_s,
        startup=pj.IfStartup.from_drive(drive, zeta=args.if_damping) if startup == "if"
        else None)
    sensing = pj.Sensing(noise_std=args.noise)
    n_steps = scenario.n_steps(args.T_s)
    out = prepare_out_dir(args.out)

    text = ("observer sensored (the encoder's angle and speed)" if args.observer ==
            "sensored" else choice.describe())
    text += speed_from_angle_text(args)
    print(first_line("simulate", motor_text(drive, args), text + ", FOC",
                     f"scenario {args.scenario!r}: {description}"))
    if args.observer != "sensored":
        print("start-up: " + (_CATCH_TEXT if startup == "catch" else
                              _startup_text(controller.startup)))
    print(f"{n_steps} steps at T_s = {args.T_s:g} s")
    traj, t_compile, t_run = compile_and_run(
        pj.simulate, drive, controller, observer, scenario, T_s=args.T_s,
        n_substeps=args.substeps, sensing=sensing, key=jax.random.PRNGKey(args.seed),
        w_m0=w_m0, theta_hat0=None if args.theta_hat0 is None else math.radians(
            args.theta_hat0), w_hat0=None if args.speed_hat0 is None else
        args.speed_hat0 * float(drive.w_rated), throw=False,
        observer_u_dt=args.observer_u_dt)

    ok = bool(traj.ok)
    # every array of the trajectory (a three-phase drive has no x-y current: no `i_xy`,
    # where NumPy pickled a None before)
    arrays = {f.name: np.asarray(getattr(traj, f.name)) for f in dataclasses.fields(traj)
              if f.name not in ("status", "extras") and getattr(traj, f.name) is not None}
    arrays.update({k: np.asarray(v) for k, v in traj.extras.items()})
    files = {
        "trajectory": os.path.join(out, "trajectory.npz"),
        "recording": os.path.join(out, "recording.npz"),
        "summary": os.path.join(out, "summary.json"),
    }
    save_npz(files["trajectory"], {**arrays, "status": np.asarray(traj.status._value)})
    pj.save_recording(files["recording"], pj.RecordedData.from_trajectory(traj))
    if not args.no_plot:
        from pmsmjax.plotting import plot_trajectory

        files["plot"] = os.path.join(out, "simulation.png")
        fig = plot_trajectory(traj, drive, title=f"{drive.name}: {args.scenario} scenario, "
                                                  f"{args.observer} FOC")
        fig.savefig(files["plot"], dpi=120)

    w_b, I_b = float(drive.w_rated), float(drive.base.I_b)
    t = arrays["t"]
    lock = run_lock_status(t, arrays["theta_err"], ok, arrays["w_m"], controller.startup,
                           arrays["w_m_ref"])
    t_settle = 5.0 / alpha_s
    mask = pj.settled_mask(t, arrays["w_m_ref"], arrays["tau_L"], t_settle=t_settle)
    e_w = (arrays["w_m_ref"] - arrays["w_m"])[mask]
    i_abs = np.hypot(arrays["i_dq"][:, 0], arrays["i_dq"][:, 1])
    w_end = float(arrays["w_m"][-1])
    summary = {
        "command": "simulate",
        "pmsmjax_version": pj.__version__,
        **drive_info(drive, args),
        "scenario": {"name": args.scenario, "description": description,
                     "t_end_s": float(args.t_end), "speed_pu": float(args.speed),
                     "load_pu": float(load) if spec.uses_load else None},
        "controller": {"type": "FOC", "strategy": "id_const (i_d = 0)",
                       "current_bandwidth_rad_s": alpha_c, "speed_bandwidth_rad_s": alpha_s,
                       "startup": _startup_info(controller.startup, startup == "catch")},
        "theta_hat0_deg": args.theta_hat0,
        "speed_hat0_pu": args.speed_hat0,
        "observer": args.observer,
        "observer_details": choice.info() if args.observer != "sensored" else None,
        "speed_from_angle_Hz": args.speed_from_angle,
        "design_file": getattr(args, "design", None),
        "sensing": {"noise_std_A": float(args.noise), "seed": int(args.seed)},
        "computational_delay": bool(args.delay),
        "inverter_error": {
            "u_dt_V": None if drive.inverter.u_dt is None else float(drive.inverter.u_dt),
            "i_dt_A": float(drive.inverter.i_dt),
            "observer_u_dt_V": (args.observer_u_dt if args.observer_u_dt is not None else
                                None if drive.inverter.u_dt is None else
                                float(drive.inverter.u_dt)),
            "recording_voltage": "commanded"},
        "T_s": float(args.T_s),
        "steps": int(n_steps),
        "n_substeps": int(args.substeps),
        "compile_time_s": t_compile,
        "run_time_s": t_run,
        "wall_time_s": None,  # filled in below
        "final_speed": {"rad_s": w_end, "pu": w_end / w_b,
                        "rpm": w_end / float(drive.motor.n_p) * 60 / (2 * math.pi)},
        "speed_error_after_settling": {
            "definition": "w_m_ref - w_m (rad/s electrical; _pu: of the rated speed) at the "
                          "samples where the speed reference and the load have been constant "
                          "for at least settle_time_s = 5 / alpha_s",
            "settle_time_s": t_settle,
            "samples": int(np.sum(mask)),
            **_speed_error_stats(e_w, w_b),
        },
        "angle_error_deg": {"rms": float(np.degrees(np.sqrt(np.mean(arrays["theta_err"] ** 2)))),
                            "max_abs": float(np.degrees(np.max(np.abs(arrays["theta_err"]))))},
        "max_current": {"A": float(np.max(i_abs)), "pu": float(np.max(i_abs)) / I_b,
                        "i_max_A": float(drive.i_max)},
        "status": lock["status"],
        "status_message": pj.RESULTS[traj.status],
        "lock": lock,
        "files": {k: os.path.basename(v) for k, v in files.items()},
    }
    summary["wall_time_s"] = time.perf_counter() - t_start
    write_json(files["summary"], summary)

    se = summary["speed_error_after_settling"]
    print(f"final speed {summary['final_speed']['pu']:.4f} p.u. ({w_end:.1f} rad/s electrical, "
          f"{summary['final_speed']['rpm']:.0f} rpm); max current "
          f"{summary['max_current']['pu']:.3f} p.u. ({summary['max_current']['A']:.3g} A)")
    if se["samples"]:
        print(f"speed error after settling: rms {se['rms_pu']:.2e} p.u., max "
              f"{se['max_abs_pu']:.2e} p.u. ({se['samples']} samples)")
    print(f"status: {summary['status']}")
    print(f"wrote {', '.join(files.values())}")
    if ok and lock["lost"]:
        print(f"pmsmjax simulate: the observer lost lock at t = {lock['t_lost_s']:.4g} s "
              f"(mean |angle error| over {1e3 * lock['dwell_s']:g} ms above "
              f"{lock['lock_deg']:g} deg): its estimates after that are not an angle",
              file=sys.stderr)
    if not ok:
        print(f"pmsmjax simulate: the run diverged: {summary['status_message']}",
              file=sys.stderr)
        return 1
    return 0


COMMAND = Command(
    name="simulate",
    help="closed-loop simulation of a drive (FOC and any observer); writes trajectory, "
         "recording, summary and plot",
    description=(
        "Simulate one closed-loop run (FOC with PI current and speed control, the rotor "
        "angle and speed from --observer: the encoder by default, or any sensorless "
        "observer of the registry with its paper's default design, changed by --gain and "
        "--observer-set) and write to --out: trajectory.npz (every Trajectory array, and "
        "the observer's extras under their names), recording.npz (recorded-data format: "
        "t, u_ab, i_ab, theta, w_m, tau_L, for `pmsmjax plant` and `pmsmjax replay`), "
        "summary.json and simulation.png. The built-in default is a sensored speed ramp "
        "0 -> 0.5 p.u. followed by a load step to 0.5 p.u. and back, 1.5 s, on the zhang750 "
        "motor."
    ),
    add_arguments=_simulate_arguments,
    run=simulate_command,
)
