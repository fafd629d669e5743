"""The operating point of the analysis commands: the speed (`--speed PU`, `--speeds PU
...` or `--speed-range LO:HI`) and the current (`--i-d PU`, `--i-q PU`), and the check
that the observer's own design is not singular there."""

from __future__ import annotations

import argparse

import numpy as np

import pmsmjax as pj

from ._values import CLIError, ListOption, allow_negative_values, finite_float, speed_range


def add_operating_point_options(parser: argparse.ArgumentParser, *, speed: str) -> None:
    """The speed and the current of the analysis commands.

    `speed` says how the speed is given: `"list"` (`--speeds PU ...`, and `--speed PU`
    repeatable), `"one"` (`--speed`, one value) or `"range"` (`--speed-range LO:HI`).
    """
    if speed not in ("list", "one", "range"):
        raise ValueError(f"speed must be 'list', 'one' or 'range'; got {speed!r}")
    allow_negative_values(parser)
    g = parser.add_argument_group("operating point")
    w0_text = ("electrical speed w0 in p.u. of the rated speed (Drive.w_rated, rad/s "
               "electrical), any sign")
    if speed == "list":
        g.add_argument("--speeds", dest="speed", action=ListOption, item=finite_float,
                       groups=True, default=None, metavar="PU",
                       help=f"{w0_text}; one or more, separated by spaces: one map per "
                            "speed, overlaid in the PNG (default: 0.5). 0 is allowed (the "
                            "ratio design's gains stay finite there, w1 = ratio |w0| = 0) "
                            "but every zhang2022 design is degenerate at standstill "
                            "(status -1)")
        g.add_argument("--speed", action=ListOption, item=finite_float, groups=True,
                       nargs=None, plural="--speeds", default=None,
                       metavar="PU", help="one speed (p.u.), as in the other commands; "
                                          "repeatable, and with --speeds")
    elif speed == "one":
        g.add_argument("--speed", type=finite_float, default=0.5, metavar="PU",
                       help=f"{w0_text}, nonzero for the zhang2022 schedules (default: "
                            "%(default)s)")
    else:
        g.add_argument("--speed-range", type=speed_range, default=(0.1, 1.0),
                       metavar="LO:HI",
                       help="speed range Omega = [LO, HI] of the certificate, p.u. of the "
                            "rated speed (electrical), 0 < LO < HI (default: 0.1:1)")
    g.add_argument("--i-d", type=finite_float, default=0.0, metavar="PU",
                   help="d-axis operating current in p.u. of the preset's base current "
                        "(Drive.base.I_b, A peak): the controlled current in the estimator "
                        "frame, as zhang2022 (34)-(35) assume (default: %(default)s)")
    g.add_argument("--i-q", type=finite_float, default=0.0, metavar="PU",
                   help="q-axis operating current, p.u. of Drive.base.I_b, estimator frame "
                        "(default: %(default)s)")
    g.add_argument("--load", type=finite_float, default=None, metavar="PU",
                   help="saturated motors only ([saturation] in the motor file, or a "
                        "saturated preset such as ipm3k5_sat): the load torque (p.u. of "
                        "the rated torque) of the operating point; the current and the "
                        "observer-model mismatch then follow from the flux map at the "
                        "drive's steady state (pmsmjax.analysis.saturated_operating_point), "
                        "replacing --i-d/--i-q. Default on a saturated motor: the mismatch "
                        "at the --i-d/--i-q current")


def current_from_args(args, drive: pj.Drive) -> tuple[tuple[float, float], np.ndarray]:
    """`((i_d, i_q) in p.u., the same in A)`."""
    i_pu = (float(args.i_d), float(args.i_q))
    return i_pu, np.asarray(i_pu) * float(drive.base.I_b)


def check_operating_point(observer, drive: pj.Drive, i_pu, *, speed_pu=None) -> None:
    """Reject operating points at which the observer's own design is singular (for the
    zhang2022 observers: a vanishing auxiliary flux, or standstill with w1 ~ |w0|)."""
    if not hasattr(observer, "linear_gains"):
        return  # only the zhang2022 flux observers have these singularities
    mh = observer.motor
    i0 = np.asarray(i_pu) * float(drive.base.I_b)
    dL = float(mh.L_d) - float(mh.L_q)
    psi_a0 = np.array([dL * i0[0] + float(mh.psi_f), -dL * i0[1]])
    scale = abs(float(mh.psi_f)) + abs(dL) * float(np.hypot(*i0))
    if not np.hypot(*psi_a0) > 1e-12 * scale:
        at = ("i_d != -psi_f / (L_d - L_q) = "
              f"{-float(mh.psi_f) / dL / float(drive.base.I_b):.6g} p.u." if dL else
              "psi_f > 0")
        raise CLIError(
            f"--i-d/--i-q: the auxiliary flux zhang2022 (7) of the observer's model vanishes "
            f"at i_dq = ({i_pu[0]:g}, {i_pu[1]:g}) p.u., so the gains zhang2022 (17), (25) "
            f"are infinite; allowed: any current with psi_a0 != 0, i.e. i_q != 0 or {at}")
    schedule = getattr(getattr(observer, "design", None), "schedule", None)
    if speed_pu == 0.0 and schedule in ("zhang38", "fixed_ratio"):
        raise CLIError(
            "--speed 0: at standstill w1 = ratio |w0| = 0 and the equilibria of zhang2022 "
            "(11) form a continuum (det(w0 J + G1) = w1^2 = 0), so they cannot be listed; "
            "allowed: any finite nonzero speed (p.u.), or the fixed_w1 schedule")


def saturated_operating_point_from_args(args, drive: pj.Drive, choice, speed_pu: float):
    """On a saturated drive, the plant the analysis runs against and the current: the
    apparent constant machine of the flux map at the operating point (the observer keeps
    its constant model, so the mismatch follows from the map). With `--load` the point
    is the drive's steady state at `speed_pu` and that load (current, angle error:
    `pmsmjax.analysis.saturated_operating_point`), and `args.i_d`/`args.i_q` are set to
    its controller-frame current; without it, the map at the `--i-d/--i-q` current.
    Returns `(choice, line)`: the choice with that plant and the console line saying
    which mismatch follows from the map (None for a constant-inductance drive)."""
    import dataclasses

    from pmsmjax.analysis import apparent_plant, saturated_operating_point
    from pmsmjax.analysis._saturated import describe_mismatch

    if drive.three_phase_motor.magnetic is None:
        if getattr(args, "load", None) is not None:
            raise CLIError(f"--load: {drive.name!r} has constant inductances (no [saturation] "
                           "in the motor file); --load sets the operating point of a "
                           "saturated motor only. Give the current with --i-d/--i-q")
        return choice, None
    I_b = float(drive.base.I_b)
    if args.load is not None:
        if speed_pu == 0.0:
            raise CLIError("--load on a saturated motor needs a nonzero --speed (the steady "
                           "state of the drive at standstill is not an operating point of "
                           "the observer)")
        p = saturated_operating_point(choice.observer, drive, speed_pu * float(drive.w_rated),
                                      float(args.load) * float(drive.tau_rated))
        if not bool(p.converged):
            raise CLIError(
                f"--speed {speed_pu:g} --load {args.load:g}: the drive has no steady state "
                f"with this observer on the saturated machine (verdict 'cannot hold': the "
                f"controller cannot deliver the load torque within its limits at the angle "
                f"error the observer settles to); allowed: a smaller load")
        args.i_d, args.i_q = (float(v) / I_b for v in p.i_ref)
        line = (f"{describe_mismatch(choice.observer, p)}; operating point: the drive's steady "
                f"state at {speed_pu:g} p.u. speed and {args.load:g} p.u. load, controller "
                f"current ({args.i_d:.4g}, {args.i_q:.4g}) p.u.")
        plant = apparent_plant(drive.three_phase_motor, p.i_dq)
    else:
        i = np.array([args.i_d, args.i_q]) * I_b
        plant = apparent_plant(drive.three_phase_motor, i)
        m = choice.observer.motor
        line = (f"saturated plant: mismatch from the map at i_dq = ({i[0]:.3g}, {i[1]:.3g}) A "
                f"(--i-d/--i-q, angle error neglected; --load PU for the drive's steady "
                f"state): apparent L_d {float(plant.L_d) * 1e3:.4g} mH, L_q "
                f"{float(plant.L_q) * 1e3:.4g} mH, psi_f {float(plant.psi_f):.4g} V s "
                f"(observer {float(m.L_d) * 1e3:.4g} mH, {float(m.L_q) * 1e3:.4g} mH, "
                f"{float(m.psi_f):.4g} V s)")
    plant = pj.PMSMParams(R_s=float(plant.R_s), L_d=float(plant.L_d), L_q=float(plant.L_q),
                          psi_f=float(plant.psi_f), n_p=float(plant.n_p),
                          harmonics=plant.harmonics)
    return dataclasses.replace(choice, plant=plant), line
