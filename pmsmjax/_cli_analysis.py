r"""Analysis subcommands of the command line (GitHub issue 4, item 6):

- `pmsmjax feasibility`: feasibility maps of the flux-gain design over a
  $(\zeta_1, \omega_1/|\omega_0|)$ grid (Fig. 1), one per speed, written to
  `DIR/feasibility.npz` and `DIR/feasibility.png`;
- `pmsmjax equilibria`: every equilibrium of the error dynamics (11) of one design at one
  operating point, with its stability and the eigenvalues of its Jacobian (37);
- `pmsmjax certify`: the slowly-varying-speed certificate of §V (the admissible
  $|\mathrm{d}\omega/\mathrm{d}t|$) of a design over a speed range, as JSON.

They share `add_operating_point_options` (`--motor`, `--set`, the speed, `--i-d`, `--i-q`,
`--zeta2`, `--w2`, `--mismatch-L-d`, `--mismatch-L-q`). The numbers come from the public
API of `pmsmjax.analysis` (`feasibility_map`, `eso_equilibria`,
`slowly_varying_certificate`) with the same arguments, so the files equal what those
functions return.

This module registers the commands into the registry of `pmsmjax/__main__.py`, which
imports it once. Under `python -m pmsmjax` that registry lives in the module
`sys.modules["__main__"]`, not in a second copy imported as `pmsmjax.__main__`;
`_cli_module` picks the running one so that `CLIError` and `COMMANDS` are the ones `main`
uses.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect
import json
import math
import os
import re
import sys
import time

import equinox as eqx
import numpy as np

import pmsmjax as pj


def _cli_module():
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if spec is not None and spec.name == "pmsmjax.__main__":
        return main
    return importlib.import_module("pmsmjax.__main__")


_cli = _cli_module()
CLIError = _cli.CLIError
register = _cli.register
add_drive_options = _cli.add_drive_options
drive_from_args = _cli.drive_from_args
add_output_options = _cli.add_output_options
prepare_out_dir = _cli.prepare_out_dir
write_json = _cli.write_json

W2_DEFAULT = 2 * math.pi * 50.0  # rad/s, the default of the analysis functions


# ---------------------------------------------------------------------------------------
# Argument types
# ---------------------------------------------------------------------------------------

def _number(text: str, what: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} {text.strip()!r} is not a number") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"{what} {text.strip()!r} must be finite")
    return x


def _finite(text: str) -> float:
    return _number(text, "value")


def _positive(text: str) -> float:
    x = _number(text, "value")
    if x <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0")
    return x


def _grid(*, nonneg: bool):
    """Type of a `LO:HI:N` grid option (N points from LO to HI inclusive); a single
    number X is X:X:1. Returns `(lo, hi, n)`."""

    def parse(text: str):
        parts = text.split(":")
        if len(parts) == 1:
            parts = [parts[0], parts[0], "1"]
        if len(parts) != 3:
            raise argparse.ArgumentTypeError(
                f"{text!r} is not LO:HI:N (N points from LO to HI inclusive, e.g. 0:5:101) "
                f"or a single number")
        lo, hi = _number(parts[0], "LO"), _number(parts[1], "HI")
        try:
            n = int(parts[2])
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"N in {text!r} must be an integer >= 1; got {parts[2].strip()!r}") from None
        if n < 1:
            raise argparse.ArgumentTypeError(f"N in {text!r} must be an integer >= 1")
        if nonneg and lo < 0:
            raise argparse.ArgumentTypeError(f"LO in {text!r} must be >= 0 (allowed: "
                                             f"0 <= LO <= HI)")
        if lo > hi:
            raise argparse.ArgumentTypeError(f"LO > HI in {text!r} (allowed: LO <= HI)")
        if n == 1 and lo != hi:
            raise argparse.ArgumentTypeError(f"N = 1 in {text!r} needs LO = HI (or give a "
                                             f"single number)")
        if n > 1 and lo == hi:
            raise argparse.ArgumentTypeError(f"LO = HI in {text!r} needs N = 1")
        return lo, hi, n

    return parse


def grid_values(spec) -> np.ndarray:
    """The points of a parsed `LO:HI:N` grid (float64, N of them)."""
    lo, hi, n = spec
    return np.linspace(lo, hi, n)


def _speed_list(text: str) -> list[float]:
    items = [s.strip() for s in text.split(",")]
    if not all(items):
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of numbers")
    return [_number(s, "speed") for s in items]


def _speed_range(text: str) -> tuple[float, float]:
    parts = text.split(":")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not LO:HI (p.u., 0 < LO < HI, e.g. "
                                         f"0.1:1)")
    lo, hi = _number(parts[0], "LO"), _number(parts[1], "HI")
    if not lo > 0:
        raise argparse.ArgumentTypeError(
            f"LO in {text!r} must be > 0 (allowed: 0 < LO < HI, p.u.): the flux gains "
            f"vanish at w0 = 0 (w1 is proportional to |w0| in the ratio and (38) designs), "
            f"so A is not Hurwitz there and no certificate covers standstill")
    if not lo < hi:
        raise argparse.ArgumentTypeError(f"{text!r} needs LO < HI (allowed: 0 < LO < HI, "
                                         f"p.u.)")
    return lo, hi


# ---------------------------------------------------------------------------------------
# Shared options: drive, operating point, observer design and model
# ---------------------------------------------------------------------------------------

_NEGATIVE_VALUE = re.compile(r"^-\.?[0-9][0-9.eE+\-:,]*$")


def add_operating_point_options(parser: argparse.ArgumentParser, *, speed: str) -> None:
    """Add the options shared by `feasibility`, `equilibria` and `certify`.

    `--motor`, `--set` (via `add_drive_options`); the speed; `--i-d`, `--i-q`; `--zeta2`,
    `--w2`; `--mismatch-L-d`, `--mismatch-L-q`. `speed` says how the speed is given:
    `"list"` (`--speed`, repeatable or comma-separated), `"one"` (`--speed`, one value) or
    `"range"` (`--speed-range LO:HI`).
    """
    if speed not in ("list", "one", "range"):
        raise ValueError(f"speed must be 'list', 'one' or 'range'; got {speed!r}")
    # Let values that start with a minus sign but are not plain numbers (-0.5,0.5 or
    # -1:1 or -1e-3) be read as values, not as unknown options; argparse's own pattern
    # only accepts -12 and -1.5. (`--speed=-0.5,0.5` works either way.)
    if hasattr(parser, "_negative_number_matcher"):
        parser._negative_number_matcher = _NEGATIVE_VALUE
    add_drive_options(parser)
    g = parser.add_argument_group("operating point")
    w0_text = ("electrical speed w0 in p.u. of the rated speed (Drive.w_rated, rad/s "
               "electrical), any sign")
    if speed == "list":
        g.add_argument("--speed", action="append", type=_speed_list, default=None,
                       metavar="PU[,PU...]",
                       help=f"{w0_text}; repeatable or comma-separated: one map per speed, "
                            "overlaid in the PNG (default: 0.5). 0 is allowed (the ratio "
                            "design's gains stay finite there, w1 = ratio |w0| = 0) but every "
                            "design is degenerate at standstill (status -1)")
    elif speed == "one":
        g.add_argument("--speed", type=_finite, default=0.5, metavar="PU",
                       help=f"{w0_text}, nonzero (default: %(default)s)")
    else:
        g.add_argument("--speed-range", type=_speed_range, default=(0.1, 1.0),
                       metavar="LO:HI",
                       help="speed range Omega = [LO, HI] of the certificate, p.u. of the "
                            "rated speed (electrical), 0 < LO < HI (default: 0.1:1)")
    g.add_argument("--i-d", type=_finite, default=0.0, metavar="PU",
                   help="d-axis operating current in p.u. of the preset's base current "
                        "(Drive.base.I_b, A peak): the controlled current in the estimator "
                        "frame, as (34)-(35) assume (default: %(default)s)")
    g.add_argument("--i-q", type=_finite, default=0.0, metavar="PU",
                   help="q-axis operating current, p.u. of Drive.base.I_b, estimator frame "
                        "(default: %(default)s)")
    g = parser.add_argument_group("observer (speed/angle design (25) and machine model)")
    g.add_argument("--zeta2", type=_positive, default=1.0, metavar="Z",
                   help="damping ratio of the speed/angle poles (-, > 0, default: "
                        "%(default)s)")
    g.add_argument("--w2", type=_positive, default=W2_DEFAULT, metavar="RAD_S",
                   help="natural frequency of the speed/angle poles (rad/s, > 0, default: "
                        "2 pi 50 = %(default).4g)")
    note = ("; only 1 is accepted here: the certificate assumes the matched model"
            if speed == "range" else
            "; a value other than 1 uses the general (slower) route of the analysis"
            if speed == "list" else "")
    for ax in ("d", "q"):
        g.add_argument(f"--mismatch-L-{ax}", dest=f"mismatch_L_{ax}", type=_positive,
                       default=1.0, metavar="RATIO",
                       help=f"observer's L_{ax} / true L_{ax} (-, > 0, default: "
                            "%(default)s = matched); the observer's model, from which its "
                            "gains are computed, has L = RATIO x the plant's L" + note)


@dataclasses.dataclass(frozen=True)
class OperatingPoint:
    """The resolved shared options (SI units unless the name says p.u.)."""

    drive: pj.Drive
    motor: pj.PMSMParams  # the plant (three-phase subspace of the machine)
    motor_hat: pj.PMSMParams | None  # the observer's model; None = matched
    i_dq_pu: tuple[float, float]
    i0: np.ndarray  # A, estimator frame
    zeta2: float
    w2: float
    mismatch: tuple[float, float]  # observer L_d, L_q over the true ones

    @property
    def w_rated(self) -> float:
        return float(self.drive.w_rated)

    @property
    def I_b(self) -> float:
        return float(self.drive.base.I_b)

    @property
    def observer_motor(self) -> pj.PMSMParams:
        return self.motor if self.motor_hat is None else self.motor_hat

    def info(self) -> dict:
        return {
            "i_dq_pu": list(self.i_dq_pu),
            "i_dq_A": [float(v) for v in self.i0],
            "observer_model": {
                "L_d_ratio": self.mismatch[0], "L_q_ratio": self.mismatch[1],
                "L_d_H": float(self.observer_motor.L_d), "L_q_H": float(self.observer_motor.L_q),
                "plant_L_d_H": float(self.motor.L_d), "plant_L_q_H": float(self.motor.L_q)},
        }


def operating_point_from_args(args: argparse.Namespace) -> OperatingPoint:
    """Resolve the shared options (raises `CLIError` for unusable values)."""
    drive = drive_from_args(args)
    motor = drive.three_phase_motor
    mismatch = (float(args.mismatch_L_d), float(args.mismatch_L_q))
    motor_hat = None
    if mismatch != (1.0, 1.0):
        motor_hat = eqx.tree_at(lambda m: (m.L_d, m.L_q), motor,
                                (mismatch[0] * float(motor.L_d), mismatch[1] * float(motor.L_q)))
    i_pu = (float(args.i_d), float(args.i_q))
    i0 = np.asarray(i_pu) * float(drive.base.I_b)
    mh = motor if motor_hat is None else motor_hat
    dL = float(mh.L_d) - float(mh.L_q)
    psi_a0 = np.array([dL * i0[0] + float(mh.psi_f), -dL * i0[1]])
    scale = abs(float(mh.psi_f)) + abs(dL) * float(np.hypot(*i0))
    if not np.hypot(*psi_a0) > 1e-12 * scale:
        raise CLIError(
            f"--i-d/--i-q: the auxiliary flux (7) of the observer's model vanishes at i_dq = "
            f"({i_pu[0]:g}, {i_pu[1]:g}) p.u., so the gains (17), (25) are infinite; "
            f"allowed: any current with psi_a0 != 0, i.e. i_q != 0 or i_d != "
            f"-psi_f / (L_d - L_q) = {-float(mh.psi_f) / dL / float(drive.base.I_b):.6g} p.u.")
    return OperatingPoint(drive=drive, motor=motor, motor_hat=motor_hat, i_dq_pu=i_pu,
                          i0=i0, zeta2=float(args.zeta2), w2=float(args.w2),
                          mismatch=mismatch)


def _add_design_options(parser, *, grid: bool, optional: bool) -> None:
    g = parser.add_argument_group("flux-gain design (17): zeta1 and w1 = ratio |w0|")
    if grid:
        g.add_argument("--zeta1", type=_grid(nonneg=True), default=(0.0, 5.0, 101),
                       metavar="LO:HI:N",
                       help="damping ratios of the flux poles (-, >= 0): N points from LO to "
                            "HI inclusive, or a single number (default: 0:5:101, Fig. 1)")
        g.add_argument("--ratio", type=_grid(nonneg=True), default=(0.0, 2.0, 101),
                       metavar="LO:HI:N",
                       help="w1 / |w0| (-, >= 0; 0 is degenerate): N points from LO to HI "
                            "inclusive, or a single number (default: 0:2:101, Fig. 1)")
        return
    extra = (" Give both --zeta1 and --ratio, or neither for the schedule (38): zeta1 = "
             "1.5 + |w0|/w_rated, w1 = 1.5 |w0| / zeta1.") if optional else ""
    g.add_argument("--zeta1", type=_positive, default=None, metavar="Z",
                   help="damping ratio of the flux poles (-, > 0)." + extra)
    g.add_argument("--ratio", type=_positive, default=None, metavar="R",
                   help="w1 / |w0| (-, > 0; 0 would leave a continuum of equilibria)."
                        + extra)


def _design_from_args(args, op: OperatingPoint):
    """`(ESODesign, description dict)` from --zeta1/--ratio or the schedule (38)."""
    if (args.zeta1 is None) != (args.ratio is None):
        raise CLIError("give both --zeta1 and --ratio (the fixed-ratio design w1 = ratio |w0|)"
                       ", or neither (the schedule (38))")
    if args.zeta1 is None:
        design = pj.ESODesign.zhang38(op.w_rated, w2=op.w2, zeta2=op.zeta2)
        info = {"schedule": "zhang38",
                "description": "(38): zeta1 = 1.5 + |w0|/w_rated, w1 = 1.5 |w0| / zeta1 "
                               "(so w1/|w0| = 1.5 / zeta1)",
                "w_rated_rad_s": op.w_rated}
    else:
        design = pj.ESODesign.fixed_ratio(args.zeta1, args.ratio, w2=op.w2, zeta2=op.zeta2)
        info = {"schedule": "fixed_ratio", "description": "zeta1 constant, w1 = ratio |w0|",
                "zeta1": float(args.zeta1), "ratio": float(args.ratio)}
    info.update(zeta2=op.zeta2, w2_rad_s=op.w2,
                gains="flux gain (17), minimum-norm speed/angle gains (25), computed from "
                      "the observer's model")
    return design, info


def _dumps(obj) -> str:
    return json.dumps(_cli._json_safe(obj), indent=2, allow_nan=False)


def _header(command, op: OperatingPoint, args) -> dict:
    return {"command": command, "pmsmjax_version": pj.__version__,
            **_cli._drive_info(op.drive, args)}


def _fmt_op(op: OperatingPoint) -> str:
    mm = ("" if op.motor_hat is None else
          f", observer L_d x {op.mismatch[0]:g}, L_q x {op.mismatch[1]:g}")
    return (f"{op.drive.name}, i_dq = ({op.i_dq_pu[0]:g}, {op.i_dq_pu[1]:g}) p.u. of "
            f"{op.I_b:.4g} A, zeta2 = {op.zeta2:g}, w2 = {op.w2:.4g} rad/s{mm}")


# ---------------------------------------------------------------------------------------
# feasibility
# ---------------------------------------------------------------------------------------

FEASIBILITY_KEYS = ("zeta1", "ratio", "status", "n_nonzero", "stable_theta_deg")


def _feasibility_arguments(p: argparse.ArgumentParser) -> None:
    add_operating_point_options(p, speed="list")
    _add_design_options(p, grid=True, optional=False)
    add_output_options(p, "results")


@register(
    "feasibility",
    help="feasibility map of the ESO flux-gain design over a (zeta1, w1/w0) grid (Fig. 1)",
    arguments=_feasibility_arguments,
    description=(
        "Classify every design (zeta1, w1/|w0|) of a grid at one or more speeds: feasible "
        "when no equilibrium of the error dynamics (11) other than the designed one is "
        "stable. Writes DIR/feasibility.npz (no pickled objects) with zeta1 (N1,), ratio "
        "(N2,) = w1/|w0|, status (N2, N1) ints (0 feasible, 1 infeasible, -1 degenerate or "
        "failed, including 'no equilibrium at all', which only parameter mismatch causes), "
        "n_nonzero (N2, N1, number of nonzero equilibria), stable_theta_deg (N2, N1, angle "
        "of a stable nonzero equilibrium in deg, the one closest to 0; NaN if none); also "
        "no_equilibrium, principal_stable, principal_theta_deg (N2, N1) and the inputs: "
        "speed (p.u.), i_dq (p.u.), zeta2, w2 (rad/s), mismatch_L_d, mismatch_L_q, "
        "w_rated (rad/s), I_b (A), motor, method. With several speeds every per-design array "
        "gets a leading speed axis (S, N2, N1) and speed has shape (S,); with one speed "
        "speed is a scalar. DIR/feasibility.png overlays the maps of all nonzero speeds."
    ),
)
def feasibility_command(args: argparse.Namespace) -> int:
    from .analysis import feasibility_map

    op = operating_point_from_args(args)
    speeds = [s for group in (args.speed or [[0.5]]) for s in group]
    z, r = grid_values(args.zeta1), grid_values(args.ratio)
    out = prepare_out_dir(args.out)
    S, N1, N2 = len(speeds), len(z), len(r)
    print(f"pmsmjax feasibility: {_fmt_op(op)}; {N1} x {N2} designs (zeta1 x w1/w0) at "
          f"{S} speed{'s' if S > 1 else ''}")

    nonzero = [s for s in speeds if s != 0.0]
    fm = None
    t0 = time.perf_counter()
    if nonzero:
        fm = feasibility_map(op.drive, nonzero, z, r, i_dq=op.i_dq_pu, motor_hat=op.motor_hat,
                             zeta2=op.zeta2, w2=op.w2)
    t_map = time.perf_counter() - t0

    status = np.full((S, N2, N1), -1, np.int32)
    no_eq = np.zeros((S, N2, N1), bool)
    n_nonzero = np.zeros((S, N2, N1), np.int32)
    stable_theta = np.full((S, N2, N1), np.nan)
    principal_stable = np.zeros((S, N2, N1), bool)
    principal_theta = np.full((S, N2, N1), np.nan)
    j = 0
    for i, s in enumerate(speeds):
        if s == 0.0:
            continue
        # FeasibilityMap arrays are (speed, load, zeta1, ratio); the file's are (ratio, zeta1)
        st = np.asarray(fm.status)[j, 0].T
        no_eq[i] = st == 2
        status[i] = np.where(st == 2, -1, st)
        n_nonzero[i] = np.asarray(fm.n_nonzero)[j, 0].T
        stable_theta[i] = np.asarray(fm.stable_theta_deg)[j, 0].T
        principal_stable[i] = np.asarray(fm.principal_stable)[j, 0].T
        principal_theta[i] = np.asarray(fm.principal_theta_deg)[j, 0].T
        j += 1

    one = S == 1
    per_design = {"status": status, "n_nonzero": n_nonzero, "stable_theta_deg": stable_theta,
                  "no_equilibrium": no_eq, "principal_stable": principal_stable,
                  "principal_theta_deg": principal_theta}
    if one:
        per_design = {k: v[0] for k, v in per_design.items()}
    method = fm.method if fm is not None else "none (standstill only)"
    files = {"data": os.path.join(out, "feasibility.npz")}
    np.savez(files["data"], zeta1=z, ratio=r, **per_design,
             speed=np.asarray(speeds[0] if one else speeds, float),
             i_dq=np.asarray(op.i_dq_pu, float), zeta2=np.float64(op.zeta2),
             w2=np.float64(op.w2), mismatch_L_d=np.float64(op.mismatch[0]),
             mismatch_L_q=np.float64(op.mismatch[1]), w_rated=np.float64(op.w_rated),
             I_b=np.float64(op.I_b), motor=np.str_(op.drive.name), method=np.str_(method))

    plot_note = ""
    if not args.no_plot:
        if fm is None:
            plot_note = "no PNG: every speed is 0"
        elif N1 < 2 or N2 < 2:
            plot_note = "no PNG: the map needs at least 2 values of --zeta1 and of --ratio"
        else:
            from matplotlib.figure import Figure

            from .plotting_analysis import plot_feasibility

            fig = Figure(figsize=(6.5, 5.0))
            ax = fig.add_subplot()
            plot_feasibility(fm, ax=ax)
            fig.suptitle(f"{op.drive.name}"
                         + ("" if op.motor_hat is None else
                            f", observer L_d x {op.mismatch[0]:g}, L_q x {op.mismatch[1]:g}"),
                         fontsize=10)
            files["plot"] = os.path.join(out, "feasibility.png")
            fig.savefig(files["plot"], dpi=120)

    print(f"classified {len(nonzero) * N1 * N2} designs in {t_map:.2f} s ({method})")
    for i, s in enumerate(speeds):
        st = status[i]
        n_deg, n_none = int(np.sum(st == -1)), int(np.sum(no_eq[i]))
        th = stable_theta[i][np.isfinite(stable_theta[i])]
        line = (f"speed {s:g} p.u.: feasible {int(np.sum(st == 0))}, infeasible "
                f"{int(np.sum(st == 1))}, degenerate {n_deg}"
                + (f" (of which {n_none} without any equilibrium)" if n_none else ""))
        if th.size:
            line += f"; static error of infeasible designs {th.min():.3g}..{th.max():.3g} deg"
        if s == 0.0:
            line += " (standstill: w1 = ratio |w0| = 0, a continuum of equilibria)"
        print(line)
    if plot_note:
        print(plot_note)
    print(f"wrote {', '.join(files.values())}")
    return 0


# ---------------------------------------------------------------------------------------
# equilibria
# ---------------------------------------------------------------------------------------

def _equilibria_arguments(p: argparse.ArgumentParser) -> None:
    add_operating_point_options(p, speed="one")
    _add_design_options(p, grid=False, optional=True)
    g = p.add_argument_group("output")
    g.add_argument("--json", action="store_true",
                   help="print the result as JSON only (strict JSON: NaN becomes null) "
                        "instead of a table")
    g.add_argument("--out", default=None, metavar="DIR",
                   help="also write the JSON to DIR/equilibria.json (created if missing)")


def equilibria_report(op: OperatingPoint, speed_pu: float, design, design_info: dict):
    """The `Equilibria` of `design` at `speed_pu` and the JSON-ready report."""
    from .analysis import eso_equilibria, eso_linearization

    w0 = speed_pu * op.w_rated
    gains = design(op.observer_motor, w0, op.i0)
    zeta1, w1 = (float(v) for v in design.zeta1_w1(w0))
    eq = eso_equilibria(w0, op.i0, gains, op.motor, op.motor_hat)
    valid = np.asarray(eq.valid)
    principal = int(eq.principal)
    items = []
    for k in np.flatnonzero(valid):
        x = np.asarray(eq.x)[k]
        A = np.asarray(eso_linearization(w0, op.i0, gains, op.motor, op.motor_hat, x=x))
        ev = np.sort_complex(np.linalg.eigvals(A))[::-1]
        items.append({
            "theta_deg": math.degrees(float(eq.theta[k])),
            "theta_rad": float(eq.theta[k]),
            "designed": bool(k == principal),
            "stable": bool(eq.stable[k]),
            "tangent": bool(eq.tangent[k]),
            "eigenvalues": [{"re": float(e.real), "im": float(e.imag)} for e in ev],
            "max_real_eigenvalue": float(np.max(ev.real)),
            "state": {"psi_err_d_Vs": float(x[0]), "psi_err_q_Vs": float(x[1]),
                      "theta_err_rad": float(x[2]), "w_err_rad_s": float(x[3])},
            "residual": float(eq.residual[k]),
        })
    ok = int(eq.status) == 0
    other_stable = [e for e in items if e["stable"] and not e["designed"]]
    if not ok or not items:
        feas = -1
    else:
        feas = 1 if other_stable else 0
    report = {
        "operating_point": {"speed_pu": speed_pu, "w0_rad_s": w0, **op.info()},
        "design": {**design_info, "zeta1_at_w0": zeta1, "ratio_at_w0": w1 / abs(w0),
                   "w1_rad_s": w1},
        "frame": "observer",
        "method": "pmsmjax.analysis.eso_equilibria (general route: bracketing and "
                  "bisection of the reduced function; Routh-Hurwitz on the Jacobian (37))",
        "status": "ok" if ok else "degenerate or failed",
        "n_equilibria": len(items),
        "n_nonzero": int(eq.n_nonzero),
        "feasibility_status": feas,
        "feasibility": {0: "feasible", 1: "infeasible", -1: "degenerate or failed"}[feas],
        "units": {"eigenvalues": "1/s (Jacobian (37) in SI units of the state)",
                  "theta": "deg (theta_rad: rad), error = true - estimate"},
        "equilibria": items,
    }
    return eq, report


@register(
    "equilibria",
    help="every equilibrium of the ESO error dynamics for one design and operating point",
    arguments=_equilibria_arguments,
    description=(
        "List every equilibrium of the error dynamics (11) of the ESO with the flux gain "
        "(17) at constant speed: its angle error (deg), whether it is stable, and the "
        "eigenvalues of its Jacobian (37) (1/s), computed by pmsmjax.analysis."
        "eso_equilibria. The design is --zeta1 and --ratio (w1 = ratio |w0|), or the "
        "schedule (38) when both are left out. With --json only JSON is printed on stdout; "
        "--out DIR also writes it to DIR/equilibria.json."
    ),
)
def equilibria_command(args: argparse.Namespace) -> int:
    op = operating_point_from_args(args)
    if args.speed == 0.0:
        raise CLIError("--speed 0: at standstill w1 = ratio |w0| = 0 and the equilibria form "
                       "a continuum (det(w0 J + G1) = w1^2 = 0), so they cannot be listed; "
                       "allowed: any finite nonzero speed (p.u.)")
    design, info = _design_from_args(args, op)
    eq, report = equilibria_report(op, float(args.speed), design, info)
    report = {**_header("equilibria", op, args), **report}
    if args.out:
        path = os.path.join(prepare_out_dir(args.out), "equilibria.json")
        write_json(path, report)
    if args.json:
        print(_dumps(report))
    else:
        d = report["design"]
        print(f"pmsmjax equilibria: {_fmt_op(op)}")
        print(f"speed {args.speed:g} p.u. ({report['operating_point']['w0_rad_s']:.4g} rad/s), "
              f"design {d['schedule']}: zeta1 = {d['zeta1_at_w0']:.4g}, w1/|w0| = "
              f"{d['ratio_at_w0']:.4g}")
        print(f"{'theta (deg)':>12}  {'stable':>6}  eigenvalues of the Jacobian (1/s)")
        for e in report["equilibria"]:
            ev = ", ".join(f"{v['re']:.4g}{v['im']:+.4g}j" for v in e["eigenvalues"])
            tag = " (designed)" if e["designed"] else (" (tangent)" if e["tangent"] else "")
            print(f"{e['theta_deg']:12.4f}  {'yes' if e['stable'] else 'no':>6}  {ev}{tag}")
        print(f"{report['n_equilibria']} equilibria; design {report['feasibility']}")
        if args.out:
            print(f"wrote {path}")
    if report["status"] != "ok":
        print("pmsmjax equilibria: the computation was degenerate or failed (status -1); the "
              "list may be incomplete", file=sys.stderr)
        return 1
    return 0


# ---------------------------------------------------------------------------------------
# certify
# ---------------------------------------------------------------------------------------

QUICK = dict(n_speed=21, n_dirs=256, alphas=(0.8, 0.99), n_time=80, n_k1_speeds=5)


def _certificate_defaults() -> dict:
    """The resolution arguments of `slowly_varying_certificate` at their defaults (so the
    JSON records what was used)."""
    from .analysis import slowly_varying_certificate

    params = inspect.signature(slowly_varying_certificate).parameters
    return {k: params[k].default for k in ("n_speed", "alphas", "n_time", "n_dirs",
                                           "n_refine", "n_k1_speeds")}


def _certify_arguments(p: argparse.ArgumentParser) -> None:
    add_operating_point_options(p, speed="range")
    _add_design_options(p, grid=False, optional=True)
    g = p.add_argument_group("certificate")
    g.add_argument("--c3", type=_positive, default=0.5, metavar="C3",
                   help="target constant c3 of (43c), in (0, 1): the ball radius r is the "
                        "largest with c3 = 1 - 2 c2 k1 r (default: %(default)s)")
    g.add_argument("--scale", choices=("pu", "si"), default="pu",
                   help="state scaling of the norms: 'pu' (flux / psi_b, speed error / w_b) "
                        "or 'si' (default: %(default)s)")
    g.add_argument("--quick", action="store_true",
                   help="coarser resolution: 21 speeds, 256 sample points for k1, alphas "
                        "0.8, 0.99, 80 time points, 5 speeds for k1 (faster; the constants "
                        "are a few per cent less accurate)")
    g.add_argument("--n-speed", type=_cli._positive_int, default=None, metavar="N",
                   help="speeds of the grid over the range (default: 101, or 21 with "
                        "--quick)")
    g.add_argument("--n-dirs", type=_cli._positive_int, default=None, metavar="N",
                   help="random points of the ball per speed for k1 (54) (default: 1024, "
                        "or 256 with --quick)")
    g = p.add_argument_group("output")
    g.add_argument("--out", default=None, metavar="DIR",
                   help="write DIR/certificate.json (created if missing) and print a summary; "
                        "without --out the JSON is printed on stdout and nothing else is")


def certificate_report(op: OperatingPoint, design, design_info, speed_range, *, c3, scale,
                       resolution: dict):
    """The `LyapunovCertificate` and its JSON-ready report."""
    from .analysis import slowly_varying_certificate

    cert = slowly_varying_certificate(op.drive, design, speed_range, i_dq=op.i_dq_pu, c3=c3,
                                      scale=scale, **resolution)
    f = {k.name: np.asarray(getattr(cert, k.name)) for k in dataclasses.fields(cert)}
    v = {k: float(a) for k, a in f.items() if a.ndim == 0}
    ok = int(v.pop("status")) == 0
    lo, hi = speed_range
    paper = ("c1", "c2", "c3", "c4", "c5", "c5_paper", "k1", "r", "r_init", "eps",
             "eps_paper", "eps_sup")
    sharp = ("c1_sharp", "c2_sharp", "c3_sharp", "c4_sharp", "c5_sharp", "k1_sharp",
             "r_sharp", "r_init_sharp", "eps_sharp", "eps_sup_sharp")
    report = {
        "design": design_info,
        "operating_point": op.info(),
        "speed_range": {"pu": [lo, hi], "rad_s": [lo * op.w_rated, hi * op.w_rated],
                        "n_speed": int(f["speeds"].shape[0])},
        "scale": scale,
        "frame": "observer",
        "status": "ok" if ok else "failed",
        "dw_dt_bound_rad_s2": v["eps"] if ok else None,
        "dw_dt_bound_pu_per_s": v["eps"] / op.w_rated if ok else None,
        "dw_dt_bound_sharp_rad_s2": v["eps_sharp"] if ok else None,
        "bound_definition": (
            "|dw/dt| <= eps = c3 / c5 (rad/s^2, electrical) certifies exponential stability "
            "of (40) on the speed range, for initial errors in the ball of radius r_init "
            "(scaled state); paper constants (51)/(55)-(64) with the true b = max "
            "||dA/dw||. dw_dt_bound_sharp_rad_s2: the same from the sharp constants of P "
            "itself. null when status is 'failed' (A not uniformly Hurwitz on the range, or "
            "no radius found)"),
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
    return cert, report


@register(
    "certify",
    help="slowly-varying-speed certificate (zhang2022 §V): the admissible |dw/dt| of a design",
    arguments=_certify_arguments,
    description=(
        "Compute the Lyapunov certificate of zhang2022 §V (Khalil's Theorem 9.3) for the ESO "
        "design over --speed-range: the constants c1..c5, the ball radius and the certified "
        "bound on |dw/dt| (rad/s^2), with pmsmjax.analysis.slowly_varying_certificate. The "
        "design is --zeta1/--ratio, or the schedule (38) when both are left out. Prints the "
        "certificate as JSON, or writes DIR/certificate.json with --out. Exit status 1 if "
        "the certificate fails (A not uniformly Hurwitz on the range)."
    ),
)
def certify_command(args: argparse.Namespace) -> int:
    op = operating_point_from_args(args)
    if op.motor_hat is not None:
        raise CLIError("--mismatch-L-d/--mismatch-L-q: the certificate assumes the matched "
                       "observer model (slowly_varying_certificate has no observer-model "
                       "argument); allowed: 1")
    if not 0 < args.c3 < 1:
        raise CLIError(f"--c3 {args.c3:g}: allowed 0 < C3 < 1")
    design, info = _design_from_args(args, op)
    resolution = _certificate_defaults()
    if args.quick:
        resolution.update(QUICK)
    if args.n_speed is not None:
        if args.n_speed < 2:
            raise CLIError("--n-speed: allowed an integer >= 2")
        resolution["n_speed"] = args.n_speed
    if args.n_dirs is not None:
        resolution["n_dirs"] = args.n_dirs
    info_out = sys.stdout if args.out else sys.stderr
    out = prepare_out_dir(args.out) if args.out else None
    lo, hi = args.speed_range
    print(f"pmsmjax certify: {_fmt_op(op)}; design {info['schedule']}, speeds {lo:g}..{hi:g} "
          f"p.u.; computing...", file=info_out, flush=True)
    t0 = time.perf_counter()
    cert, report = certificate_report(op, design, info, (lo, hi), c3=args.c3,
                                      scale=args.scale, resolution=resolution)
    report = {**_header("certify", op, args), **report,
              "wall_time_s": time.perf_counter() - t0}
    ok = report["status"] == "ok"
    if out is None:
        print(_dumps(report))
    else:
        path = os.path.join(out, "certificate.json")
        write_json(path, report)
        if ok:
            print(f"certified |dw/dt| <= {report['dw_dt_bound_rad_s2']:.4g} rad/s^2 "
                  f"({report['dw_dt_bound_pu_per_s']:.4g} p.u./s; sharp constants "
                  f"{report['dw_dt_bound_sharp_rad_s2']:.4g} rad/s^2) in "
                  f"{report['wall_time_s']:.1f} s")
        print(f"wrote {path}")
    if not ok:
        print("pmsmjax certify: no certificate: A is not uniformly Hurwitz on the speed range "
              "or no ball radius was found (status -1)", file=sys.stderr)
        return 1
    return 0
