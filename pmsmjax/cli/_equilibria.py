"""`pmsmjax equilibria`: every equilibrium of any observer's error dynamics at one
operating point, with its stability and the eigenvalues of its Jacobian
(`pmsmjax.analysis.equilibria`)."""

from __future__ import annotations

import argparse
import math
import os
import sys

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
from ._values import CLIError


#: status of the equilibria computation and feasibility of the design, by code
#: (`pmsmjax.analysis`: 0 ok, 2 no equilibrium, -1 degenerate).
STATUS = {0: "ok", 2: "no equilibrium", -1: "degenerate"}
FEASIBILITY = {0: "feasible", 1: "infeasible", 2: "no equilibrium", -1: "degenerate"}


def _equilibria_arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    add_operating_point_options(p, speed="one")
    add_observer_options(p, default="eso", mismatch=True,
                         default_note=": zhang2022's nonlinear ESO, the default of "
                                      "every command; any registered observer")
    g = add_output_options(p, None, plot=False,
                           out_help="also write the JSON to DIR/equilibria.json (created "
                                    "if missing)")
    add_json_option(g)


def equilibria_report(choice, drive, speed_pu: float, i_pu) -> dict:
    """The JSON-ready report of `pmsmjax.analysis.equilibria` for `choice.observer` at
    `speed_pu` (p.u.) and `i_pu` (p.u., estimated frame)."""
    import jax

    from pmsmjax.analysis._generic import equilibria_stored

    obs = choice.observer
    w0 = speed_pu * float(drive.w_rated)
    i0 = np.asarray(i_pu) * float(drive.base.I_b)
    # the analysis as one stored program (`pmsmjax.runtime.stored_call`: a repeated
    # command skips the tracing), then everything else on host (NumPy) arrays
    # Newton starts from every grid point where the inner problem shows two branches
    # (`pmsmjax.analysis.equilibria`, n_starts): one point, so their cost does not matter
    eq = jax.device_get(equilibria_stored(obs, choice.plant, w0, i0, n_starts=64))
    coords = obs.coordinates
    valid = np.asarray(eq.valid)
    stable = np.asarray(eq.stable)
    principal = int(eq.principal)
    jac = np.asarray(eq.jacobian)
    items = []
    for k in np.flatnonzero(valid):
        x = np.asarray(eq.x)[k]
        ev = np.sort_complex(np.linalg.eigvals(jac[k]))[::-1]
        items.append({
            "theta_deg": math.degrees(float(eq.theta[k])),
            "theta_rad": float(eq.theta[k]),
            "designed": bool(k == principal),
            "stable": bool(stable[k]),
            "tangent": bool(np.asarray(eq.tangent)[k]),
            "eigenvalues": [{"re": float(e.real), "im": float(e.imag)} for e in ev],
            "max_real_eigenvalue": float(np.max(ev.real)),
            "state": {name: float(v) for name, v in zip(coords.names, x)},
            "residual": float(eq.residual[k]),
        })
    status = int(eq.status)
    if status != 0:
        feas = status
    else:
        feas = 1 if any(e["stable"] and not e["designed"] for e in items) else 0
    design = choice.design()
    flux = getattr(getattr(obs, "design", None), "zeta1_w1", None)
    if flux is not None:  # the zhang2022 flux design at this speed
        zeta1, w1 = (float(v) for v in flux(w0))
        design.update(zeta1_at_w0=zeta1, w1_rad_s=w1, ratio_at_w0=w1 / abs(w0) if w0 else None)
    return {
        "operating_point": {"speed_pu": speed_pu, "w0_rad_s": w0, "i_dq_pu": list(i_pu),
                            "i_dq_A": [float(v) for v in i0]},
        "observer": choice.info(design=False),
        "design": design,
        "frame": "observer",
        "method": "pmsmjax.analysis.equilibria (generic route: bracketing and refinement "
                  "of the reduced function over the angle error; Routh-Hurwitz on the "
                  "Jacobian of the observer's error_rhs)",
        "status": STATUS.get(status, "degenerate"),
        "status_code": status,
        "n_equilibria": len(items),
        "n_nonzero": int(sum(not e["designed"] for e in items)),
        "feasibility_status": feas,
        "feasibility": FEASIBILITY[feas],
        "coordinates": [{"name": n, "unit": u, "meaning": d} for n, u, d in
                        zip(coords.names, coords.units,
                            coords.doc or ("",) * len(coords.names))],
        "units": {"eigenvalues": "1/s (Jacobian of the error dynamics in SI units of the "
                                 "state)",
                  "theta": "deg (theta_rad: rad), error = true - estimate",
                  "state": {n: u for n, u in zip(coords.names, coords.units)}},
        "equilibria": items,
    }


def equilibria_command(args: argparse.Namespace) -> int:
    drive = drive_from_args(args)
    choice = observer_from_args(args, drive)
    choice, saturated = saturated_operating_point_from_args(args, drive, choice,
                                                            float(args.speed))
    i_pu, _ = current_from_args(args, drive)
    check_operating_point(choice.observer, drive, i_pu, speed_pu=float(args.speed))
    if not args.json:  # (stdout holds the JSON and nothing else)
        print(first_line("equilibria", motor_text(drive, args), choice.describe(),
                         f"i_dq = ({i_pu[0]:.4g}, {i_pu[1]:.4g}) p.u. of "
                         f"{float(drive.base.I_b):.4g} A"), flush=True)
        if saturated:
            print(saturated, flush=True)
    try:
        report = equilibria_report(choice, drive, float(args.speed), i_pu)
    except ValueError as e:
        raise CLIError(f"{choice.describe()}: {e}") from None
    report = {**header("equilibria", drive, args), **report}
    if saturated:
        report["saturated"] = saturated
    if args.out:
        path = os.path.join(prepare_out_dir(args.out), "equilibria.json")
        write_json(path, report)
    if args.json:
        print_json(report)
    else:
        d = report["design"]
        line = f"speed {args.speed:g} p.u. ({report['operating_point']['w0_rad_s']:.4g} rad/s)"
        if "zeta1_at_w0" in d:
            line += (f", design {d.get('schedule', 'fixed')}: zeta1 = {d['zeta1_at_w0']:.4g}, "
                     f"w1/|w0| = {d['ratio_at_w0']:.4g}")
        print(line)
        print(f"{'theta (deg)':>12}  {'stable':>6}  eigenvalues of the Jacobian (1/s)")
        for e in report["equilibria"]:
            ev = ", ".join(f"{v['re']:.4g}{v['im']:+.4g}j" for v in e["eigenvalues"])
            tag = " (designed)" if e["designed"] else (" (tangent)" if e["tangent"] else "")
            print(f"{e['theta_deg']:12.4f}  {'yes' if e['stable'] else 'no':>6}  {ev}{tag}")
        print(f"{report['n_equilibria']} equilibria; status {report['status']}; design "
              f"{report['feasibility']}")
        if args.out:
            print(f"wrote {path}")
    if report["status"] == "degenerate":
        print("pmsmjax equilibria: the computation was degenerate or failed (status -1); the "
              "list may be incomplete", file=sys.stderr)
        return 1
    if report["status"] == "no equilibrium" and not args.json:
        print("no equilibrium: the error dynamics have no rest point at this operating "
              "point (the estimate cannot settle; only observer-model mismatch causes this)")
    return 0


COMMAND = Command(
    name="equilibria",
    help="every equilibrium of any observer's error dynamics at one operating point",
    description=(
        "List every equilibrium of the error dynamics of the observer (--observer, any of "
        "the registry; default eso, zhang2022's nonlinear ESO with its design "
        "(38)/(25), the default of every command) at constant speed and current: its "
        "angle error (deg), its state in the observer's error coordinates, whether it is "
        "stable, and the eigenvalues of its "
        "Jacobian (1/s), computed by pmsmjax.analysis.equilibria. The status is 'ok', 'no "
        "equilibrium' (possible with observer-model mismatch: --observer-set or --mismatch "
        "NAME=RATIO) "
        "or 'degenerate' (exit status 1); the design is 'feasible' when no equilibrium "
        "other than the designed one is stable. With --json only JSON is printed on "
        "stdout; --out DIR also writes it to DIR/equilibria.json."
    ),
    add_arguments=_equilibria_arguments,
    run=equilibria_command,
)
