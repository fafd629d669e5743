"""`pmsmjax certify`: the slowly-varying-speed certificate of zhang2022 §V for any
observer, with or without observer-model mismatch
(`pmsmjax.analysis.slowly_varying_certificate`)."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import os
import sys
import time

import numpy as np

from .._files import write_json
from ._command import Command
from ._drive_options import add_drive_options, drive_from_args, header, motor_text
from ._observer_options import add_observer_options, observer_from_args
from ._operating_point import (
    add_operating_point_options,
    check_operating_point,
    current_from_args,
    saturated_operating_point_from_args,
)
from ._output import add_json_option, add_output_options, first_line, prepare_out_dir, print_json
from ._values import CLIError, positive_float, positive_int


QUICK = dict(n_speed=21, n_dirs=256, alphas=(0.8, 0.99), n_time=80, n_k1_speeds=5)


def _certificate_defaults() -> dict:
    """The resolution arguments of `slowly_varying_certificate` at their defaults (so the
    JSON records what was used)."""
    from pmsmjax.analysis import slowly_varying_certificate

    params = inspect.signature(slowly_varying_certificate).parameters
    return {k: params[k].default for k in ("n_speed", "alphas", "n_time", "n_dirs",
                                           "n_refine", "n_k1_speeds")}


def _certify_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    add_operating_point_options(p, speed="range")
    add_observer_options(p, default="eso", mismatch=True)
    g = p.add_argument_group("certificate")
    g.add_argument("--c3", type=positive_float, default=0.5, metavar="C3",
                   help="target constant c3 of zhang2022 (43c), in (0, 1): the ball radius r "
                        "is the largest with c3 = 1 - 2 c2 k1 r (default: %(default)s)")
    g.add_argument("--scale", choices=("pu", "si"), default="pu",
                   help="state scaling of the norms: 'pu' (each error coordinate over its "
                        "per-unit base, e.g. flux / psi_b, speed error / w_b) or 'si' "
                        "(default: %(default)s)")
    g.add_argument("--quick", action="store_true",
                   help="coarser resolution: 21 speeds, 256 sample points for k1, alphas "
                        "0.8, 0.99, 80 time points, 5 speeds for k1 (faster; the constants "
                        "are a few per cent less accurate)")
    g.add_argument("--n-speed", type=positive_int, default=None, metavar="N",
                   help="speeds of the grid over the range (default: 101, or 21 with "
                        "--quick)")
    g.add_argument("--n-dirs", type=positive_int, default=None, metavar="N",
                   help="random points of the ball per speed for k1 zhang2022 (54) (default: "
                        "1024, or 256 with --quick)")
    g = add_output_options(p, None, plot=False,
                           out_help="write DIR/certificate.json (created if missing) and "
                                    "print a summary; without --out the JSON is printed on "
                                    "stdout and nothing else is")
    add_json_option(g)


def certificate_report(choice, drive, speed_range, i_pu, *, c3, scale,
                       resolution: dict) -> dict:
    """The JSON-ready report of the `LyapunovCertificate` of `choice.observer`."""
    from pmsmjax.analysis import slowly_varying_certificate

    cert = slowly_varying_certificate(drive, choice.observer, speed_range, i_dq=i_pu,
                                      plant=choice.plant, c3=c3, scale=scale, **resolution)
    f = {k.name: np.asarray(getattr(cert, k.name)) for k in dataclasses.fields(cert)}
    v = {k: float(a) for k, a in f.items() if a.ndim == 0}
    ok = int(v.pop("status")) == 0
    lo, hi = speed_range
    w_r = float(drive.w_rated)
    paper = ("c1", "c2", "c3", "c4", "c5", "c5_paper", "k1", "r", "r_init", "eps",
             "eps_paper", "eps_sup")
    sharp = ("c1_sharp", "c2_sharp", "c3_sharp", "c4_sharp", "c5_sharp", "k1_sharp",
             "r_sharp", "r_init_sharp", "eps_sharp", "eps_sup_sharp")
    return {
        "observer": choice.info(design=False),
        "design": choice.design(),
        "operating_point": {"i_dq_pu": list(i_pu),
                            "i_dq_A": [float(x) * float(drive.base.I_b) for x in i_pu]},
        "speed_range": {"pu": [lo, hi], "rad_s": [lo * w_r, hi * w_r],
                        "n_speed": int(f["speeds"].shape[0])},
        "scale": scale,
        "frame": "observer",
        "status": "ok" if ok else "failed",
        "dw_dt_bound_rad_s2": v["eps"] if ok else None,
        "dw_dt_bound_pu_per_s": v["eps"] / w_r if ok else None,
        "dw_dt_bound_sharp_rad_s2": v["eps_sharp"] if ok else None,
        "bound_definition": (
            "|dw/dt| <= eps = c3 / c5 (rad/s^2, electrical) certifies exponential stability "
            "of zhang2022 (40) on the speed range, for initial errors in the ball of radius "
            "r_init (scaled state) around the equilibrium (the origin; with observer-model "
            "mismatch the principal equilibrium at each speed); paper constants zhang2022 "
            "(51)/(55)-(64) with the true b = max ||dA/dw||. dw_dt_bound_sharp_rad_s2: the "
            "same from the sharp constants of P itself. null when status is 'failed' (A not "
            "uniformly Hurwitz on the range, no equilibrium, or no radius found)"),
        "constants": {
            "sigma": v["sigma"], "rho": v["rho"], "b": v["b"], "alpha": v["alpha"],
            "gamma": v["gamma"], "k": v["k"],
            "paper": {k: v[k] for k in paper},
            "sharp": {k.removesuffix("_sharp"): v[k] for k in sharp},
            "lyap_residual": v["lyap_residual"], "min_eig_P": v["min_eig_P"],
        },
        "resolution": {k: (list(x) if isinstance(x, tuple) else x)
                       for k, x in resolution.items()},
        "method": "pmsmjax.analysis.slowly_varying_certificate",
    }


def certify_command(args: argparse.Namespace) -> int:
    drive = drive_from_args(args)
    choice = observer_from_args(args, drive)
    lo, hi = args.speed_range
    # a saturated motor: the mismatch from the map at the range's middle speed
    choice, saturated = saturated_operating_point_from_args(args, drive, choice,
                                                            0.5 * (lo + hi))
    i_pu, _ = current_from_args(args, drive)
    check_operating_point(choice.observer, drive, i_pu)
    if not 0 < args.c3 < 1:
        raise CLIError(f"--c3 {args.c3:g}: allowed 0 < C3 < 1")
    resolution = _certificate_defaults()
    if args.quick:
        resolution.update(QUICK)
    if args.n_speed is not None:
        if args.n_speed < 2:
            raise CLIError(f"--n-speed {args.n_speed}: allowed an integer >= 2")
        resolution["n_speed"] = args.n_speed
    if args.n_dirs is not None:
        resolution["n_dirs"] = args.n_dirs
    to_stdout = args.json or not args.out
    info_out = sys.stderr if to_stdout else sys.stdout
    out = prepare_out_dir(args.out) if args.out else None
    print(first_line("certify", motor_text(drive, args), choice.describe(),
                     f"i_dq = ({i_pu[0]:g}, {i_pu[1]:g}) p.u.", f"speeds {lo:g}..{hi:g} p.u.",
                     "computing..."), file=info_out, flush=True)
    if saturated:
        print(saturated + f" (at the range's middle speed {0.5 * (lo + hi):g} p.u.; the "
              "mismatch is held over the range)", file=info_out, flush=True)
    t0 = time.perf_counter()
    try:
        report = certificate_report(choice, drive, (lo, hi), i_pu, c3=args.c3,
                                    scale=args.scale, resolution=resolution)
    except ValueError as e:
        raise CLIError(f"{choice.describe()}: {e}") from None
    report = {**header("certify", drive, args), **report,
              "wall_time_s": time.perf_counter() - t0}
    ok = report["status"] == "ok"
    if out is not None:
        path = os.path.join(out, "certificate.json")
        write_json(path, report)
    if to_stdout:
        print_json(report)
    else:
        if ok:
            print(f"certified |dw/dt| <= {report['dw_dt_bound_rad_s2']:.4g} rad/s^2 "
                  f"({report['dw_dt_bound_pu_per_s']:.4g} p.u./s; sharp constants "
                  f"{report['dw_dt_bound_sharp_rad_s2']:.4g} rad/s^2) in "
                  f"{report['wall_time_s']:.1f} s")
        print(f"wrote {path}")
    if not ok:
        print("pmsmjax certify: no certificate: A is not uniformly Hurwitz on the speed range, "
              "the equilibrium was not found, or no ball radius was found (status -1)",
              file=sys.stderr)
        return 1
    return 0


COMMAND = Command(
    name="certify",
    help="slowly-varying-speed certificate (zhang2022 §V) of any observer: the admissible "
         "|dw/dt|",
    description=(
        "Compute the Lyapunov certificate of zhang2022 §V (Khalil's Theorem 9.3) for the "
        "observer (--observer, any of the registry; default eso) over --speed-range: the "
        "constants c1..c5, the ball radius and the certified bound on |dw/dt| (rad/s^2), "
        "with pmsmjax.analysis.slowly_varying_certificate. Observer-model mismatch "
        "(--observer-set, --mismatch NAME=RATIO) certifies the principal (static-error) "
        "equilibrium "
        "at each speed. Prints the certificate as JSON, or writes DIR/certificate.json with "
        "--out (and prints it too with --json). Exit status 1 if the certificate fails (A "
        "not uniformly Hurwitz on the range)."
    ),
    add_arguments=_certify_arguments,
    run=certify_command,
)
