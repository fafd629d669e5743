"""Command-line interface: `pmsmjax COMMAND [options]` (also `python -m pmsmjax`).

Subcommands live in a registry: decorate a function `run(args) -> int` with
`@register(name, help=..., arguments=add_arguments)` where `add_arguments(parser)` adds the
command's options (use `add_drive_options` and `add_output_options` for the shared ones:
`--motor`, `--set NAME=VALUE`, `--out DIR`, `--no-plot`). `main` builds one argparse
subparser per registered command.

Errors in the inputs (a bad file, a bad `--set`, an unknown motor, an invalid option value)
end the command with exit status 2 and a one-line message on stderr, without a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable

import equinox as eqx
import jax
import numpy as np

import pmsmjax as pj


# ---------------------------------------------------------------------------------------
# Registry and shared helpers
# ---------------------------------------------------------------------------------------

class CLIError(Exception):
    """A user error: printed as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise CLIError(f"{self.prog}: error: {message} (see `{self.prog} --help`)")


@dataclasses.dataclass(frozen=True)
class Command:
    """One registered subcommand."""

    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


COMMANDS: dict[str, Command] = {}


def register(name: str, *, help: str, arguments: Callable[[argparse.ArgumentParser], None],
             description: str | None = None):
    """Decorator registering `run(args) -> exit status` as subcommand `name`."""

    def deco(run):
        if name in COMMANDS:
            raise ValueError(f"subcommand {name!r} is registered twice")
        COMMANDS[name] = Command(name=name, help=help, description=description or help,
                                 add_arguments=arguments, run=run)
        return run

    return deco


def _positive_float(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0")
    return x


def _nonneg_float(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(x) and x >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number >= 0")
    return x


def _finite_float(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"{text!r} must be finite")
    return x


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be an integer >= 1")
    return n


def _name_value(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"{text!r} is not of the form NAME=VALUE")
    try:
        x = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"the value in {text!r} is not a number (SI units, e.g. L_q=2.7e-3)") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"the value in {text!r} must be finite")
    return name, x


_SETTABLE = ("R_s (Ohm), L_d (H), L_q (H), psi_f (V s), n_p (pole pairs), J (kg m^2), "
             "B (N m s/rad), u_dc (V), u_max (V, peak phase); dual three-phase machines "
             "also L_xy (H), gamma (rad)")


def add_drive_options(parser: argparse.ArgumentParser) -> None:
    """Add `--motor NAME` and `--set NAME=VALUE` (shared by every drive-level command)."""
    g = parser.add_argument_group("drive")
    g.add_argument("--motor", default="zhang750", choices=pj.PRESET_NAMES, metavar="NAME",
                   help=f"motor preset, one of {', '.join(pj.PRESET_NAMES)} "
                        "(default: %(default)s); each preset states its source and "
                        "assumptions in summary.json")
    g.add_argument("--set", dest="set_params", action="append", default=[], type=_name_value,
                   metavar="NAME=VALUE",
                   help=f"replace a drive parameter, in SI units; repeatable. Names: {_SETTABLE}."
                        " Example: --set J=3e-3 --set R_s=0.9")


def drive_from_args(args: argparse.Namespace) -> pj.Drive:
    """The preset of `--motor` with the `--set` replacements applied."""
    drive = pj.preset(args.motor)
    values = dict(args.set_params)
    if values:
        try:
            drive = pj.replace_params(drive, **values)
        except ValueError as e:
            raise CLIError(f"--set: {e}") from None
    return drive


def add_output_options(parser: argparse.ArgumentParser, default_out: str | None):
    """Add `--out DIR` (required if `default_out` is None) and `--no-plot`; return the group."""
    g = parser.add_argument_group("output")
    if default_out is None:
        g.add_argument("--out", required=True, metavar="DIR",
                       help="output directory (created if missing)")
    else:
        g.add_argument("--out", default=default_out, metavar="DIR",
                       help="output directory, created if missing (default: %(default)s)")
    g.add_argument("--no-plot", action="store_true", help="do not write the PNG figure")
    return g


def prepare_out_dir(path: str) -> str:
    if os.path.exists(path) and not os.path.isdir(path):
        raise CLIError(f"--out {path!r} exists and is not a directory")
    os.makedirs(path, exist_ok=True)
    return path


def _json_safe(obj):
    """`obj` with non-finite floats replaced by None (JSON has no NaN or infinity)."""
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json(path: str, obj) -> None:
    """Write `obj` as indented, strict JSON (non-finite numbers become null)."""
    with open(path, "w", encoding="utf-8") as f:
        json.dump(_json_safe(obj), f, indent=2, allow_nan=False)
        f.write("\n")


def compile_and_run(fn, *args, **kwargs):
    """Run the (internally jitted) function `fn` twice: the first call compiles and runs,
    the second only runs, so compile time = first - second.

    Returns `(result, compile_time_s, run_time_s)`; prints "compiling..." and timings.
    """
    print("compiling...", end=" ", flush=True)
    try:
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args, **kwargs))
        t1 = time.perf_counter()
        print(f"done in {t1 - t0:.2f} s (with one run); running...", end=" ", flush=True)
        out = jax.block_until_ready(fn(*args, **kwargs))
        t2 = time.perf_counter()
    except BaseException:
        print("failed", flush=True)
        raise
    print(f"done in {t2 - t1:.3f} s")
    return out, max(t1 - t0 - (t2 - t1), 0.0), t2 - t1


def _stats(x: np.ndarray, scale: float) -> dict:
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return {"mean": None, "rms": None, "max_abs": None, "mean_pu": None, "rms_pu": None,
                "max_abs_pu": None}
    mean, rms, mx = float(np.mean(x)), float(np.sqrt(np.mean(x ** 2))), float(np.max(np.abs(x)))
    return {"mean": mean, "rms": rms, "max_abs": mx, "mean_pu": mean / scale,
            "rms_pu": rms / scale, "max_abs_pu": mx / scale}


def _drive_info(drive: pj.Drive, args) -> dict:
    return {
        "motor": drive.name,
        "preset_notes": drive.notes,
        "parameter_overrides": dict(args.set_params),
        "ratings": {"w_rated_rad_s": float(drive.w_rated), "tau_rated_Nm": float(drive.tau_rated),
                    "i_max_A": float(drive.i_max)},
        "base": {"U_b_V": float(drive.base.U_b), "I_b_A": float(drive.base.I_b),
                 "w_b_rad_s": float(drive.base.w_b), "tau_b_Nm": float(drive.base.tau_b)},
    }


# ---------------------------------------------------------------------------------------
# Scenarios of `simulate`
# ---------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class _ScenarioSpec:
    help: str
    uses_load: bool
    default_load: float
    build: Callable  # (drive, t_end, speed_pu, load_pu) -> (Scenario, description, w_m0)


def _fmt_t(x: float) -> str:
    return f"{x:.4g} s"


def _build_default(drive, T, s, l):
    w, tau = s * float(drive.w_rated), l * float(drive.tau_rated)
    t0, t1, t_on, t_off = T / 30, 11 * T / 30, 8 * T / 15, 4 * T / 5
    sc = pj.Scenario(t_end=T, w_m_ref=pj.Profile.ramp(t0, t1, 0.0, w),
                     tau_L=pj.Profile.steps([t_on, t_off], [tau, 0.0]))
    desc = (f"speed ramp 0 -> {s:g} p.u. ({w:.1f} rad/s electrical) from {_fmt_t(t0)} to "
            f"{_fmt_t(t1)}, load step 0 -> {l:g} p.u. ({tau:.3g} N m) at {_fmt_t(t_on)} and "
            f"back to 0 at {_fmt_t(t_off)}; {_fmt_t(T)} in all")
    return sc, desc, 0.0


def _build_ramp(drive, T, s, l):
    del l
    w = s * float(drive.w_rated)
    t0, t1 = T / 30, 11 * T / 30
    sc = pj.Scenario(t_end=T, w_m_ref=pj.Profile.ramp(t0, t1, 0.0, w))
    desc = (f"speed ramp 0 -> {s:g} p.u. ({w:.1f} rad/s electrical) from {_fmt_t(t0)} to "
            f"{_fmt_t(t1)}, no load; {_fmt_t(T)} in all")
    return sc, desc, 0.0


def _build_load_step(drive, T, s, l):
    w, tau = s * float(drive.w_rated), l * float(drive.tau_rated)
    t_on, t_off = T / 3, 2 * T / 3
    sc = pj.Scenario(t_end=T, w_m_ref=pj.Profile.constant(w),
                     tau_L=pj.Profile.steps([t_on, t_off], [tau, 0.0]))
    desc = (f"constant speed {s:g} p.u. ({w:.1f} rad/s electrical, rotor starting at that "
            f"speed), load step 0 -> {l:g} p.u. ({tau:.3g} N m) at {_fmt_t(t_on)} and back to "
            f"0 at {_fmt_t(t_off)}; {_fmt_t(T)} in all")
    return sc, desc, w


def _build_reversal(drive, T, s, l):
    del l
    w = s * float(drive.w_rated)
    a0, a1, b0, b1 = 0.05 * T, 0.3 * T, 0.5 * T, 0.75 * T
    sc = pj.Scenario(t_end=T, w_m_ref=pj.Profile([0.0, a0, a1, b0, b1], [0.0, 0.0, w, w, -w]))
    desc = (f"speed ramp 0 -> {s:g} p.u. ({w:.1f} rad/s electrical) from {_fmt_t(a0)} to "
            f"{_fmt_t(a1)}, reversal to {-s:g} p.u. from {_fmt_t(b0)} to {_fmt_t(b1)}, no "
            f"load; {_fmt_t(T)} in all")
    return sc, desc, 0.0


SCENARIOS: dict[str, _ScenarioSpec] = {
    "default": _ScenarioSpec("speed ramp 0 -> SPEED, then a load step 0 -> LOAD and back "
                             "(event times scale with --t-end)", True, 0.5, _build_default),
    "ramp": _ScenarioSpec("speed ramp 0 -> SPEED, no load", False, 0.0, _build_ramp),
    "load-step": _ScenarioSpec("rotor at SPEED from the start, load step 0 -> LOAD at "
                               "t_end/3, back to 0 at 2 t_end/3", True, 0.5, _build_load_step),
    "reversal": _ScenarioSpec("ramp 0 -> +SPEED, then reversal to -SPEED, no load", False,
                              0.0, _build_reversal),
}

OBSERVERS: dict[str, Callable[[pj.Drive], pj.AbstractObserver]] = {
    "sensored": lambda drive: pj.SensoredObserver(),
}


def _settled_mask(t, w_ref, tau_L, t_settle):
    """True at samples where `w_ref` and `tau_L` have been constant for >= t_settle."""
    def changed(x):
        x = np.asarray(x, dtype=float)
        tol = 1e-12 * max(1.0, float(np.max(np.abs(x))))
        return np.r_[True, np.abs(np.diff(x)) > tol]

    idx = np.arange(len(t))
    last = np.maximum.accumulate(np.where(changed(w_ref) | changed(tau_L), idx, 0))
    return (t - t[last]) >= t_settle - 1e-12


# ---------------------------------------------------------------------------------------
# simulate
# ---------------------------------------------------------------------------------------

def _simulate_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    g = p.add_argument_group("scenario")
    g.add_argument("--scenario", default="default", choices=tuple(SCENARIOS), metavar="NAME",
                   help="; ".join(f"'{k}': {v.help}" for k, v in SCENARIOS.items())
                   + " (default: %(default)s)")
    g.add_argument("--t-end", type=_positive_float, default=1.5, metavar="S",
                   help="duration of the run (s, default: %(default)s)")
    g.add_argument("--speed", type=_finite_float, default=0.5, metavar="PU",
                   help="speed set-point (p.u. of the rated speed, default: %(default)s)")
    g.add_argument("--load", type=_finite_float, default=None, metavar="PU",
                   help="load-torque step (p.u. of the rated torque; default 0.5 for the "
                        "scenarios with a load step, not allowed for the others)")
    g = p.add_argument_group("control and sensing")
    g.add_argument("--T-s", dest="T_s", type=_positive_float, default=125e-6, metavar="S",
                   help="sampling period of the controller (s, default: %(default)s)")
    g.add_argument("--current-bw", type=_positive_float, default=500.0, metavar="HZ",
                   help="current-loop bandwidth (Hz; alpha_c = 2 pi HZ rad/s, "
                        "default: %(default)s)")
    g.add_argument("--speed-bw", type=_positive_float, default=5.0, metavar="HZ",
                   help="speed-loop bandwidth (Hz; alpha_s = 2 pi HZ rad/s, "
                        "default: %(default)s)")
    g.add_argument("--observer", default="sensored", choices=tuple(OBSERVERS), metavar="NAME",
                   help=f"position/speed observer, one of {', '.join(OBSERVERS)} "
                        "(default: %(default)s)")
    g.add_argument("--noise", type=_nonneg_float, default=0.0, metavar="A",
                   help="standard deviation of white noise on each sampled current "
                        "component (A, default: %(default)s)")
    g.add_argument("--delay", action="store_true",
                   help="one-sample computational delay: the voltage computed at t_k is "
                        "applied over [t_(k+1), t_(k+2))")
    g.add_argument("--seed", type=int, default=0, metavar="N",
                   help="seed of the noise generator (integer, default: %(default)s)")
    g.add_argument("--substeps", type=_positive_int, default=1, metavar="N",
                   help="RK4 steps of the plant per sampling period (default: %(default)s)")
    add_output_options(p, "results")


@register(
    "simulate",
    help="closed-loop simulation of a drive; writes trajectory, recording, summary and plot",
    arguments=_simulate_arguments,
    description=(
        "Simulate one closed-loop run (FOC with PI current and speed control) and write to "
        "--out: trajectory.npz (every Trajectory array), recording.npz (recorded-data format: "
        "t, u_ab, i_ab, theta, w_m, tau_L, for `pmsmjax plant`), summary.json and "
        "simulation.png. The built-in default is a sensored speed ramp 0 -> 0.5 p.u. followed "
        "by a load step to 0.5 p.u. and back, 1.5 s, on the zhang750 motor."
    ),
)
def simulate_command(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    spec = SCENARIOS[args.scenario]
    if args.load is not None and not spec.uses_load:
        raise CLIError(f"--load is not used by scenario {args.scenario!r} (it has no load step)")
    load = spec.default_load if args.load is None else args.load
    drive = drive_from_args(args)
    if args.delay:
        # The Inverter's delay flag is static: replace the whole Inverter.
        inv = drive.inverter
        drive = eqx.tree_at(lambda d: d.inverter, drive,
                            pj.Inverter(u_dc=inv.u_dc, u_max=inv.u_max, delay=True))
    scenario, description, w_m0 = spec.build(drive, args.t_end, args.speed, load)
    alpha_c, alpha_s = 2 * math.pi * args.current_bw, 2 * math.pi * args.speed_bw
    controller = pj.FOC.from_drive(drive, alpha_c=alpha_c, alpha_s=alpha_s)
    observer = OBSERVERS[args.observer](drive)
    sensing = pj.Sensing(noise_std=args.noise)
    n_steps = scenario.n_steps(args.T_s)
    out = prepare_out_dir(args.out)

    print(f"pmsmjax simulate: {drive.name}, {args.observer} FOC, scenario {args.scenario!r}: "
          f"{description}")
    print(f"{n_steps} steps at T_s = {args.T_s:g} s")
    traj, t_compile, t_run = compile_and_run(
        pj.simulate, drive, controller, observer, scenario, T_s=args.T_s,
        n_substeps=args.substeps, sensing=sensing, key=jax.random.PRNGKey(args.seed),
        w_m0=w_m0, throw=False)

    ok = bool(traj.ok)
    arrays = {f.name: np.asarray(getattr(traj, f.name)) for f in dataclasses.fields(traj)
              if f.name not in ("status", "extras")}
    arrays.update({k: np.asarray(v) for k, v in traj.extras.items()})
    files = {
        "trajectory": os.path.join(out, "trajectory.npz"),
        "recording": os.path.join(out, "recording.npz"),
        "summary": os.path.join(out, "summary.json"),
    }
    np.savez(files["trajectory"], **arrays, status=np.asarray(traj.status._value))
    pj.save_recording(files["recording"], pj.RecordedData.from_trajectory(traj))
    if not args.no_plot:
        from .plotting import plot_trajectory

        files["plot"] = os.path.join(out, "simulation.png")
        fig = plot_trajectory(traj, drive, title=f"{drive.name}: {args.scenario} scenario, "
                                                  f"{args.observer} FOC")
        fig.savefig(files["plot"], dpi=120)

    w_b, I_b = float(drive.w_rated), float(drive.base.I_b)
    t = arrays["t"]
    t_settle = 5.0 / alpha_s
    mask = _settled_mask(t, arrays["w_m_ref"], arrays["tau_L"], t_settle)
    e_w = (arrays["w_m_ref"] - arrays["w_m"])[mask]
    i_abs = np.hypot(arrays["i_dq"][:, 0], arrays["i_dq"][:, 1])
    w_end = float(arrays["w_m"][-1])
    summary = {
        "command": "simulate",
        "pmsmjax_version": pj.__version__,
        **_drive_info(drive, args),
        "scenario": {"name": args.scenario, "description": description,
                     "t_end_s": float(args.t_end), "speed_pu": float(args.speed),
                     "load_pu": float(load) if spec.uses_load else None},
        "controller": {"type": "FOC", "strategy": "id_const (i_d = 0)",
                       "current_bandwidth_rad_s": alpha_c, "speed_bandwidth_rad_s": alpha_s},
        "observer": args.observer,
        "sensing": {"noise_std_A": float(args.noise), "seed": int(args.seed)},
        "computational_delay": bool(args.delay),
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
            **_stats(e_w, w_b),
        },
        "angle_error_deg": {"rms": float(np.degrees(np.sqrt(np.mean(arrays["theta_err"] ** 2)))),
                            "max_abs": float(np.degrees(np.max(np.abs(arrays["theta_err"]))))},
        "max_current": {"A": float(np.max(i_abs)), "pu": float(np.max(i_abs)) / I_b,
                        "i_max_A": float(drive.i_max)},
        "status": "successful" if ok else "diverged",
        "status_message": pj.RESULTS[traj.status],
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
    if not ok:
        print(f"pmsmjax simulate: the run diverged: {summary['status_message']}",
              file=sys.stderr)
        return 1
    return 0


# ---------------------------------------------------------------------------------------
# plant
# ---------------------------------------------------------------------------------------

def _plant_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    g = p.add_argument_group("input")
    g.add_argument("--data", required=True, metavar="FILE",
                   help="recorded drive data (.npz or .csv, format in README.md): t (s) and "
                        "u_ab (V) are required, tau_L (N m) is used if present (else zero "
                        "load); i_ab (A), theta (rad) and w_m (rad/s), if present, are "
                        "compared with the simulation")
    g.add_argument("--theta0", type=_finite_float, default=0.0, metavar="RAD",
                   help="initial electrical rotor angle (rad, default: %(default)s)")
    g.add_argument("--w-m0", type=_finite_float, default=0.0, metavar="RAD_S",
                   help="initial electrical rotor speed (rad/s, default: %(default)s)")
    g.add_argument("--init-from-data", action="store_true",
                   help="take the initial angle, speed and current from the first sample of "
                        "the data (needs theta; uses w_m and i_ab if present) instead of "
                        "--theta0/--w-m0 and zero current")
    g.add_argument("--substeps", type=_positive_int, default=4, metavar="N",
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


@register(
    "plant",
    help="open-loop plant run driven by recorded voltages; compares with recorded currents",
    arguments=_plant_arguments,
    description=(
        "Drive the plant model with the voltages u_ab (and load torque tau_L) of a recorded-"
        "data file (ZOH between samples) and write the simulated i_ab, theta (unwrapped), w_m "
        "in the same format to --out (plant.npz or plant.csv, with t, u_ab, tau_L copied), plus "
        "plant.png and summary.json. If the file holds i_ab, theta or w_m, the RMS "
        "difference between simulation and recording is reported."
    ),
)
def plant_command(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    data = pj.load_recording(args.data, require=("t", "u_ab"))
    drive = drive_from_args(args)
    theta0, w_m0, i_dq0 = args.theta0, args.w_m0, (0.0, 0.0)
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
        from .plotting import plot_plant_trace

        files["plot"] = os.path.join(out, "plant.png")
        fig = plot_plant_trace(trace, drive, data=data,
                               title=f"{drive.name}: plant driven by {os.path.basename(args.data)}")
        fig.savefig(files["plot"], dpi=120)

    i_abs = np.hypot(sim.i_ab[:, 0], sim.i_ab[:, 1])
    summary = {
        "command": "plant",
        "pmsmjax_version": pj.__version__,
        **_drive_info(drive, args),
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


# ---------------------------------------------------------------------------------------
# replay (implementation in _replay.py); the zhang2022 observers for `simulate --observer`
# ---------------------------------------------------------------------------------------

def _replay_arguments(p: argparse.ArgumentParser) -> None:
    from ._replay import add_replay_arguments

    add_drive_options(p)
    add_replay_arguments(p)
    add_output_options(p, None)


@register(
    "replay",
    help="run a position/speed observer (eso, leso, afo) over recorded voltages and currents",
    arguments=_replay_arguments,
    description=(
        "Run an observer over the recorded u_ab, i_ab of a data file (.npz or .csv) from zero "
        "initial angle (unless --theta0) and write replay.npz (theta_hat, w_hat at each t_k "
        "with the inputs), stats.json (angle-error mean/std/max in deg after --t-settle and "
        "speed error, when the file has theta and w_m) and replay.png to --out. Gains come "
        "from the design functions of zhang2022 (38)/(25) unless overridden."
    ),
)
def replay_command(args: argparse.Namespace) -> int:
    from ._replay import run_replay_cli

    prepare_out_dir(args.out)
    stats = run_replay_cli(args, drive_from_args(args))
    if "theta_err_mean_deg" in stats:
        print(f"angle error after {stats['t_settle']:g} s: mean "
              f"{stats['theta_err_mean_deg']:.4g} deg, std {stats['theta_err_std_deg']:.4g} "
              f"deg, max {stats['theta_err_max_deg']:.4g} deg")
    print(f"wrote {', '.join(os.path.join(args.out, f) for f in ('replay.npz', 'stats.json'))}"
          + ("" if args.no_plot else f", {os.path.join(args.out, 'replay.png')}"))
    return 0


def _zhang_observer(name):
    def make(drive):
        from ._replay import make_observer

        return make_observer(name, drive)

    return make


OBSERVERS.update({name: _zhang_observer(name) for name in ("eso", "leso", "afo")})

from . import _cli_analysis  # noqa: E402,F401  (registers feasibility, equilibria, certify)


# ---------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    """The argparse parser with one subparser per registered command."""
    parser = _Parser(
        prog="pmsmjax",
        description="Differentiable PMSM drive simulator: command-line front end. "
                    "Run `pmsmjax COMMAND --help` for the options of each command.",
    )
    parser.add_argument("--version", action="version", version=f"pmsmjax {pj.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                parser_class=_Parser)
    for cmd in COMMANDS.values():
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.description)
        cmd.add_arguments(p)
        p.set_defaults(_run=cmd.run)
    return parser


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


def main(argv: list[str] | None = None) -> int:
    """Run the command line `argv` (default `sys.argv[1:]`); return the exit status.

    0 = success, 1 = the run finished but failed (e.g. diverged), 2 = bad input.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except CLIError as e:
        print(_one_line(e), file=sys.stderr)
        return 2
    except SystemExit as e:  # --help, --version
        return e.code if isinstance(e.code, int) else 0
    try:
        return int(args._run(args))
    except CLIError as e:
        print(f"pmsmjax {args.command}: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except (ValueError, OSError) as e:
        print(f"pmsmjax {args.command}: error: {_one_line(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
