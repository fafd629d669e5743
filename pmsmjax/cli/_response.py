"""`pmsmjax response`: the response of any observer to back-EMF harmonics at signed orders
of the electrical speed: the angle-error ripple per 1 % harmonic from the linearisation
(`pmsmjax.analysis.harmonic_ripple`), and for a back-EMF observer the frequency response
of its estimate, computed from the observer's own discrete step
(`pmsmjax.analysis.bemf_response`), next to its continuous transfer function."""

from __future__ import annotations

import argparse
import math
import os

import numpy as np

from .._files import write_json
from ._command import Command
from ._drive_options import add_drive_options, drive_from_args, header, motor_text
from ._observer_options import add_observer_options, observer_from_args
from ._operating_point import (
    add_operating_point_options,
    current_from_args,
    saturated_operating_point_from_args,
)
from ._output import add_json_option, add_output_options, first_line, prepare_out_dir, print_json
from ._values import CLIError, ListOption, positive_float


def _order(text: str) -> int:
    """One signed harmonic order (a nonzero integer)."""
    try:
        h = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--orders must be signed integers (e.g. 1 -5 7); got {text!r}") from None
    if h == 0:
        raise argparse.ArgumentTypeError(
            f"--orders needs nonzero signed orders (e.g. 1 -5 7); got {text!r}")
    return h


def _arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    add_operating_point_options(p, speed="one")
    add_observer_options(p, default="eso", mismatch=True, flux=None, fixed_at=False,
                         default_note=": zhang2022's nonlinear ESO, the default of "
                                      "every command; any registered observer")
    p.add_argument("--orders", action=ListOption, item=_order, default=[1, -5, 7],
                   metavar="H",
                   help="signed harmonic orders of the electrical frequency, separated by "
                        "spaces: 1 the fundamental, -5 the negative-sequence 5th, 7 the "
                        "positive-sequence 7th (default: 1 -5 7)")
    p.add_argument("--T-s", dest="T_s", type=positive_float, default=1e-4, metavar="S",
                   help="sampling period of the discrete observer (s) (default: %(default)s)")
    g = add_output_options(p, None, plot=False,
                           out_help="also write the JSON to DIR/response.json (created if "
                                    "missing)")
    add_json_option(g)
    g.add_argument("--plot", action="store_true",
                   help="also write DIR/response.png (needs --out): the angle ripple per "
                        "1 % harmonic over the signed orders -25 to 25 and, for a back-EMF "
                        "observer, the Bode plot (magnitude and phase, continuous and "
                        "discrete at --T-s) of its estimate over frequency")


def response_report(choice, drive, speed_pu: float, i_pu, orders, T_s: float) -> dict:
    """The JSON-ready report: for each order the angle-error ripple per 1 % harmonic
    (`angle_ripple_deg_per_pct`, every observer) and, for a back-EMF observer, the
    discrete gain (`bemf_gain`) and, where it has one, its continuous transfer function
    (`continuous_gain`)."""
    import jax.numpy as jnp

    from pmsmjax.analysis import OperatingPoint, bemf_response, harmonic_ripple

    obs = choice.observer
    w = speed_pu * float(drive.w_rated)
    if w == 0.0:
        raise CLIError("pmsmjax response: --speed must be nonzero (the orders are "
                       "multiples of the electrical frequency)")
    i_a = np.asarray(i_pu, float) * float(drive.base.I_b)
    ripple = np.asarray(harmonic_ripple(obs, drive, OperatingPoint(w, jnp.asarray(i_a)),
                                        tuple(orders)))
    has_bemf = "e_ab_hat" in type(obs).extras
    G = bemf_response(obs, w, orders, T_s) if has_bemf else None
    tf = getattr(obs, "transfer_function", None)
    Gc = np.asarray(tf(1j * w * np.asarray(orders, float), w)) if tf else None
    items = []
    for k, h in enumerate(orders):
        item = {"order": int(h), "frequency_hz": h * w / (2 * math.pi),
                "rotor_frame_frequency_hz": (h - 1) * w / (2 * math.pi),
                "angle_ripple_deg_per_pct": float(ripple[k])}
        if G is not None:
            item["bemf_gain"] = {"mag": float(abs(G[k])),
                                 "phase_deg": math.degrees(float(np.angle(G[k]))),
                                 "re": float(G[k].real), "im": float(G[k].imag)}
        if Gc is not None:
            item["continuous_gain"] = {"mag": float(abs(Gc[k])),
                                       "phase_deg": math.degrees(float(np.angle(Gc[k])))}
        items.append(item)
    return {
        "operating_point": {"speed_pu": speed_pu, "w_rad_s": w,
                            "f_electrical_hz": w / (2 * math.pi), "i_dq_pu": list(i_pu)},
        "observer": choice.info(),
        "T_s": T_s,
        "method": "angle_ripple_deg_per_pct: pmsmjax.analysis.harmonic_ripple, the peak "
                  "steady-state angle error (deg) a back-EMF harmonic of 1 % of the "
                  "fundamental causes, from the continuous linearisation of the error "
                  "dynamics at the operating point (ideal current control; order 1: the "
                  "static error of a 1 % PM-flux error). bemf_gain (back-EMF observers): "
                  "pmsmjax.analysis.bemf_response, the observer's step linearised at its "
                  "zero state with the speed estimate at the operating speed, driven by "
                  "the sampled current of the back-EMF component through the observer's "
                  "model (4) with zero voltage; gain = estimate / back-EMF component "
                  "(positive-rotating part)",
        "units": {"frequency_hz": "Hz (signed: negative = negative sequence)",
                  "rotor_frame_frequency_hz": "Hz, (h - 1) times the electrical "
                                              "frequency: the ripple's frequency",
                  "angle_ripple_deg_per_pct": "deg (peak) per 1 % harmonic",
                  "phase_deg": "deg, estimate relative to the true component"},
        "orders": items,
    }


#: Signed orders of the ripple curve of `--plot`.
PLOT_ORDERS = tuple(h for h in range(-25, 26) if h)


def response_curves(choice, drive, speed_pu: float, i_pu, orders, T_s: float) -> dict:
    """The curves of `--plot` (`pmsmjax.plotting.plot_response`): the angle
    ripple over `PLOT_ORDERS` and, for an observer with a continuous transfer function,
    `analysis.bode_data` over signed frequencies up to 0.4 / T_s (log-spaced, 1 Hz to
    that)."""
    import jax.numpy as jnp

    from pmsmjax.analysis import OperatingPoint, bode_data, harmonic_ripple

    obs = choice.observer
    w = speed_pu * float(drive.w_rated)
    i_a = np.asarray(i_pu, float) * float(drive.base.I_b)
    ripple = np.asarray(harmonic_ripple(obs, drive, OperatingPoint(w, jnp.asarray(i_a)),
                                        PLOT_ORDERS))
    out = {"orders": list(PLOT_ORDERS), "ripple_deg": ripple, "marked": list(orders),
           "f_electrical_hz": w / (2 * math.pi)}
    if getattr(obs, "transfer_function", None) is not None and \
            "e_ab_hat" in type(obs).extras:
        f = np.logspace(0.0, math.log10(0.4 / T_s), 60)
        out["bode"] = bode_data(obs, w, np.concatenate([-f[::-1], f]), T_s=T_s)
    return out


def response_command(args: argparse.Namespace) -> int:
    drive = drive_from_args(args)
    choice = observer_from_args(args, drive)
    choice, saturated = saturated_operating_point_from_args(args, drive, choice,
                                                            float(args.speed))
    i_pu, _ = current_from_args(args, drive)
    if args.plot and not args.out:
        raise CLIError("--plot writes DIR/response.png: give --out DIR")
    if not args.json:  # (stdout holds the JSON and nothing else)
        w = float(args.speed) * float(drive.w_rated)
        print(first_line("response", motor_text(drive, args), choice.describe(),
                         f"speed {args.speed:g} p.u. ({w / (2 * math.pi):.4g} Hz)",
                         f"T_s = {args.T_s:g} s"), flush=True)
        if saturated:
            print(saturated, flush=True)
    try:
        report = response_report(choice, drive, float(args.speed), i_pu, args.orders,
                                 float(args.T_s))
    except ValueError as e:
        raise CLIError(f"{choice.describe()}: {e}") from None
    report = {**header("response", drive, args), **report}
    if args.out:
        write_json(os.path.join(prepare_out_dir(args.out), "response.json"), report)
    if args.plot:
        from pmsmjax.plotting import plot_response

        curves = response_curves(choice, drive, float(args.speed), i_pu, args.orders,
                                 float(args.T_s))
        fig = plot_response(curves, title=f"{drive.name}, {choice.describe()}, speed "
                                          f"{args.speed:g} p.u., T_s = {args.T_s:g} s")
        fig.savefig(os.path.join(args.out, "response.png"), dpi=120)
    if args.json:
        print_json(report)
        return 0
    bemf = "bemf_gain" in report["orders"][0]
    print(f"{'order':>6} {'f (Hz)':>10} {'ripple (deg/%)':>15}"
          + (f" {'|G|':>9} {'phase (deg)':>12}   continuous" if bemf else ""))
    for it in report["orders"]:
        line = (f"{it['order']:>6} {it['frequency_hz']:10.3f} "
                f"{it['angle_ripple_deg_per_pct']:15.5f}")
        if bemf:
            g = it["bemf_gain"]
            c = it.get("continuous_gain")
            tail = f"{c['mag']:9.5f} {c['phase_deg']:10.4f}" if c else ""
            line += f" {g['mag']:9.5f} {g['phase_deg']:12.4f}   {tail}"
        print(line)
    return 0


COMMAND = Command(
    name="response",
    help="response of any observer to back-EMF harmonics at orders of the speed",
    description=(
        "For each signed harmonic order h (--orders, e.g. 1,-5,7), for every observer: "
        "the peak angle-error ripple (deg) that a back-EMF harmonic of 1 % of the "
        "fundamental causes at the operating point (--speed, --i-d, --i-q), from the "
        "linearisation of its error dynamics (ideal current control; a harmonic of "
        "order h appears at (h - 1) times the electrical frequency in the rotor frame; "
        "order 1: the static angle error of a 1 % PM-flux error). For observers that "
        "estimate a back-EMF (c-leso, gi-leso, fa-leso) also the complex gain from the "
        "plant's back-EMF component at h times the electrical frequency to the "
        "observer's estimate e_ab_hat, computed from the observer's own discrete step "
        "(linearised) at sampling period --T-s, with its continuous transfer function "
        "(li-fa-leso (17), (26), (29)) next to it. JSON fields: orders[].order, "
        "orders[].frequency_hz, orders[].angle_ripple_deg_per_pct, and for back-EMF "
        "observers orders[].bemf_gain.mag, orders[].bemf_gain.phase_deg."
    ),
    add_arguments=_arguments,
    run=response_command,
)
