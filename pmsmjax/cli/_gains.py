"""`pmsmjax gains`: check a gains table before it goes into firmware.

Reads the tuner's gains table (`--design`), prints what it records (observer, drive,
sampling period, objective, the tuner's verdict as counted: `pmsmjax.verdict_text`), and
compares the tuned design with the paper's design of the same observer for the same drive
over speed: the gains, and the poles of the discrete observer at the table's sampling period
(`pmsmjax.analysis.discrete_poles`: the eigenvalues of one real observer step at its
designed equilibrium, at an operating current `--i-d`/`--i-q`). Writes `gains_check.json`
into `--out`, and with `--plot` `gains.png` (gains versus speed, tuned and paper) and
`poles.png` (the largest pole magnitude versus speed, and the poles in the z-plane).
"""

from __future__ import annotations

import argparse
import math
import os
import sys

import numpy as np

import pmsmjax as pj
from pmsmjax._data._gains_table import GAIN_COLUMNS, gain_columns, table_columns

from .._files import write_json
from ._command import Command
from ._drive_options import add_drive_options, drive_from_args, header, motor_text
from ._output import add_output_options, first_line, prepare_out_dir
from ._values import CLIError, finite_float, positive_float


#: Speeds of the check for a constant design (p.u. of the rated speed, both signs).
CONSTANT_SPEEDS_PU = np.arange(0.05, 1.5001, 0.05)


def _arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    g = p.add_argument_group("gains table")
    g.add_argument("--design", required=True, metavar="FILE",
                   help="the gains table gains.json written by `pmsmjax tune` (or its "
                        "output folder)")
    g.add_argument("--T-s", dest="T_s", type=positive_float, default=None, metavar="S",
                   help="sampling period of the discrete observer (s; default: the "
                        "table's, else 125e-6)")
    g.add_argument("--i-d", type=finite_float, default=0.0, metavar="PU",
                   help="d-axis operating current of the poles, p.u. of Drive.base.I_b, "
                        "estimated frame (default: %(default)s)")
    g.add_argument("--i-q", type=finite_float, default=0.0, metavar="PU",
                   help="q-axis operating current of the poles, p.u. of Drive.base.I_b, "
                        "estimated frame (default: %(default)s)")
    out = add_output_options(p, None, plot=False)
    out.add_argument("--plot", action="store_true",
                     help="also write gains.png (gains versus speed, tuned and paper) and "
                          "poles.png (the discrete observer's poles versus speed)")


def _speeds(table: dict, drive: pj.Drive) -> np.ndarray:
    """The speeds of the check (rad/s): the table's rows at |w| >= 0.05 p.u. (the
    zhang2022 flux gains vanish at standstill), or a grid for a constant design."""
    w_r = float(drive.w_rated)
    if table["kind"] == "scheduled":
        w = table_columns(table)["w_m"]
        return w[np.abs(w) >= 0.05 * w_r - 1e-9]
    s = CONSTANT_SPEEDS_PU
    return np.concatenate([-s[::-1], s]) * w_r


def gains_check(table: dict, drive: pj.Drive, T_s: float, i_pu) -> dict:
    """Gains and discrete poles of the table's design and of the paper's design of the
    same observer on `drive`, over the speeds of the check (JSON-ready; arrays as
    lists). Keys: `w_m` (rad/s), `speed_pu`, `gains` (`{column: {"tuned": [...],
    "paper": [...]}}`, scheduled tables; for a constant table the design parameters),
    `poles_tuned`, `poles_paper` (`[[re, im], ...]` per speed), `max_abs_pole_tuned`,
    `max_abs_pole_paper`."""
    import jax
    import jax.numpy as jnp

    from pmsmjax.analysis import discrete_poles
    from pmsmjax.observers import make_observer

    paper = make_observer(table["observer"], drive)
    tuned = pj.apply_gains_table(table, paper)
    plant = drive.three_phase_motor
    w = _speeds(table, drive)
    i_a = jnp.asarray(np.asarray(i_pu, float) * float(drive.base.I_b))
    out = {"w_m": w.tolist(), "speed_pu": (w / float(drive.w_rated)).tolist(),
           "i_dq_pu": list(i_pu), "T_s": T_s}
    from pmsmjax.observers import AbstractGainSchedule

    # a speed-scheduled observer (zhang2022's) has gains over speed whether its table
    # is scheduled or a constant design of its schedule (the closed-loop tuner's)
    if table["kind"] == "scheduled" or isinstance(getattr(paper, "design", None),
                                                  AbstractGainSchedule):
        a = gain_columns(tuned.design, plant, w)
        b = gain_columns(paper.design, plant, w)
        out["gains"] = {k: {"tuned": a[k].tolist(), "paper": b[k].tolist(),
                            "unit": GAIN_COLUMNS[k]} for k in a}
    else:
        pt, pp = dict(tuned.design_parameters()), dict(paper.design_parameters())
        units = type(paper).design_units
        out["gains"] = {k: {"tuned": [float(pt[k])] * len(w), "paper": [float(pp[k])] *
                            len(w), "unit": units.get(k, "")} for k in table["columns"]}
    for name, obs in (("tuned", tuned), ("paper", paper)):
        z = np.asarray(jax.vmap(lambda ww, o=obs: discrete_poles(o, plant, ww, i_a, T_s))(
            jnp.asarray(w)))
        out[f"poles_{name}"] = [[[float(v.real), float(v.imag)] for v in row] for row in z]
        out[f"max_abs_pole_{name}"] = np.max(np.abs(z), axis=1).tolist()
    return out


def gains_command(args: argparse.Namespace) -> int:
    table = pj.load_gains_table(args.design)
    drive = drive_from_args(args)
    T_s = float(args.T_s if args.T_s is not None else table.get("T_s") or 125e-6)
    i_pu = (float(args.i_d), float(args.i_q))
    print(first_line("gains", motor_text(drive, args),
                     f"observer {table['observer']} of the gains table {args.design}",
                     f"discrete poles at T_s = {T_s:g} s"), flush=True)
    if table.get("drive") and table["drive"] != drive.name:
        print(f"note: --design {args.design} was tuned for drive {table['drive']!r}; the "
              f"check uses {drive.name!r} (pass its motor file with --motor-file)",
              file=sys.stderr)
    out = prepare_out_dir(args.out)
    try:
        check = gains_check(table, drive, T_s, i_pu)
    except ValueError as e:
        raise CLIError(f"--design {args.design}: {e}") from None
    warning = pj.verdict_warning(table)
    v = table.get("verdict")
    report = {**header("gains", drive, args), "design_file": os.path.abspath(args.design),
              "observer": table["observer"], "kind": table["kind"],
              "table_T_s": table.get("T_s"), "objective": table.get("objective"),
              "verdict": v, "verdict_text": pj.verdict_text(v), "verdict_warning": warning,
              **check}
    files = {"report": os.path.join(out, "gains_check.json")}
    write_json(files["report"], report)
    tuned_at = (f"tuned at T_s = {table['T_s']:g} s" if table.get("T_s") else
                "sampling period not recorded")
    print(f"gains table: {table['kind']}, {len(table['rows'])} rows, for drive "
          f"{table.get('drive') or '?'}; {tuned_at}")
    print(f"objective: {table.get('objective') or 'not recorded'}; tuner's verdict: "
          f"{pj.verdict_text(v)}")
    print(f"speed loop: {pj.speed_loop_text(table)}")
    if warning is not None:
        print(f"warning: {warning}", file=sys.stderr)
    mt, mp = np.asarray(check["max_abs_pole_tuned"]), np.asarray(check["max_abs_pole_paper"])
    s = np.asarray(check["speed_pu"])
    print(f"discrete poles at T_s = {T_s:g} s, i_dq = ({i_pu[0]:g}, {i_pu[1]:g}) p.u., "
          f"{len(s)} speeds from {s.min():g} to {s.max():g} p.u.: largest |z| tuned "
          f"{mt.max():.6f} (at {s[np.argmax(mt)]:g} p.u.), paper {mp.max():.6f} (at "
          f"{s[np.argmax(mp)]:g} p.u.)" + ("" if mt.max() < 1 else
                                           "; |z| >= 1: the tuned observer is unstable "
                                           "there"))
    if args.plot:
        from pmsmjax.plotting import plot_gains_vs_speed, plot_poles_vs_speed

        title = f"{table['observer']} on {drive.name}, T_s = {T_s:g} s"
        files["gains_plot"] = os.path.join(out, "gains.png")
        plot_gains_vs_speed(check, title=title).savefig(files["gains_plot"], dpi=120)
        files["poles_plot"] = os.path.join(out, "poles.png")
        plot_poles_vs_speed(check, title=title).savefig(files["poles_plot"], dpi=120)
    print("wrote " + ", ".join(files.values()))
    return 0 if math.isfinite(float(mt.max())) else 1


COMMAND = Command(
    name="gains",
    help="check a tuned gains table: verdict, gains and discrete poles versus speed",
    description=(
        "Read the gains table of --design (written by `pmsmjax tune`), print the sampling "
        "period, objective and tuner's verdict it records, and compare the tuned design "
        "with the paper's design of the same observer on the drive over speed: the "
        "gains, and the poles of the discrete observer at the table's sampling period "
        "(eigenvalues of one real observer step at its designed equilibrium, at the "
        "current --i-d/--i-q; |z| < 1 is stable). Writes gains_check.json and, with "
        "--plot, gains.png and poles.png into --out."
    ),
    add_arguments=_arguments,
    run=gains_command,
)
