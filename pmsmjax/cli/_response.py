"""`pmsmjax response`: the frequency response of a back-EMF observer at harmonic orders of
the electrical speed, computed from the observer's own discrete step
(`pmsmjax.analysis.bemf_response`), next to its continuous transfer function."""

from __future__ import annotations

import argparse
import math
import os

import numpy as np

from ._options import (
    CLIError,
    Command,
    add_drive_options,
    add_json_option,
    add_observer_options,
    add_operating_point_options,
    add_output_options,
    current_from_args,
    drive_from_args,
    dumps_json,
    header,
    observer_from_args,
    positive_float,
    prepare_out_dir,
    write_json,
)


def _orders(text: str) -> list[int]:
    try:
        out = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--orders must be comma-separated signed integers (e.g. 1,-5,7); got "
            f"{text!r}") from None
    if not out or 0 in out:
        raise argparse.ArgumentTypeError(
            f"--orders needs at least one nonzero signed order (e.g. 1,-5,7); got {text!r}")
    return out


def _arguments(p: argparse.ArgumentParser) -> None:
    add_drive_options(p)
    add_operating_point_options(p, speed="one")
    add_observer_options(p, default="fa-leso", mismatch=True, flux=None, fixed_at=False,
                         default_note=": li-fa-leso's frequency-adaptive LESO")
    p.add_argument("--orders", type=_orders, default=[1, -5, 7], metavar="H[,H...]",
                   help="signed harmonic orders of the electrical frequency: 1 the "
                        "fundamental, -5 the negative-sequence 5th, 7 the positive-"
                        "sequence 7th (default: 1,-5,7)")
    p.add_argument("--T-s", dest="T_s", type=positive_float, default=1e-4, metavar="S",
                   help="sampling period of the discrete observer (s) (default: %(default)s)")
    g = add_output_options(p, None, plot=False,
                           out_help="also write the JSON to DIR/response.json (created if "
                                    "missing)")
    add_json_option(g)


def response_report(choice, drive, speed_pu: float, i_pu, orders, T_s: float) -> dict:
    """The JSON-ready report: for each order the discrete gain (`bemf_gain`) and, where
    the observer has one, its continuous transfer function (`continuous_gain`)."""
    from pmsmjax.analysis import bemf_response

    obs = choice.observer
    w = speed_pu * float(drive.w_rated)
    if w == 0.0:
        raise CLIError("pmsmjax response: --speed must be nonzero (the orders are "
                       "multiples of the electrical frequency)")
    G = bemf_response(obs, w, orders, T_s)
    tf = getattr(obs, "transfer_function", None)
    Gc = np.asarray(tf(1j * w * np.asarray(orders, float), w)) if tf else None
    items = []
    for k, h in enumerate(orders):
        item = {"order": int(h), "frequency_hz": h * w / (2 * math.pi),
                "bemf_gain": {"mag": float(abs(G[k])),
                              "phase_deg": math.degrees(float(np.angle(G[k]))),
                              "re": float(G[k].real), "im": float(G[k].imag)}}
        if Gc is not None:
            item["continuous_gain"] = {"mag": float(abs(Gc[k])),
                                       "phase_deg": math.degrees(float(np.angle(Gc[k])))}
        items.append(item)
    return {
        "operating_point": {"speed_pu": speed_pu, "w_rad_s": w,
                            "f_electrical_hz": w / (2 * math.pi), "i_dq_pu": list(i_pu)},
        "observer": choice.info(),
        "T_s": T_s,
        "method": "pmsmjax.analysis.bemf_response: the observer's step linearised at its "
                  "zero state with the speed estimate at the operating speed, driven by "
                  "the sampled current of the back-EMF component through the observer's "
                  "model (4) with zero voltage; gain = estimate / back-EMF component "
                  "(positive-rotating part)",
        "units": {"frequency_hz": "Hz (signed: negative = negative sequence)",
                  "phase_deg": "deg, estimate relative to the true component"},
        "orders": items,
    }


def response_command(args: argparse.Namespace) -> int:
    drive = drive_from_args(args)
    choice = observer_from_args(args, drive)
    i_pu, _ = current_from_args(args, drive)
    try:
        report = response_report(choice, drive, float(args.speed), i_pu, args.orders,
                                 float(args.T_s))
    except ValueError as e:
        raise CLIError(f"{choice.describe()}: {e}") from None
    report = {**header("response", drive, args), **report}
    if args.out:
        write_json(os.path.join(prepare_out_dir(args.out), "response.json"), report)
    if args.json:
        print(dumps_json(report))
        return 0
    op = report["operating_point"]
    print(f"pmsmjax response: {drive.name}, {choice.describe()}, speed {args.speed:g} p.u. "
          f"({op['f_electrical_hz']:.4g} Hz), T_s = {args.T_s:g} s")
    print(f"{'order':>6} {'f (Hz)':>10} {'|G|':>9} {'phase (deg)':>12}   continuous")
    for it in report["orders"]:
        g = it["bemf_gain"]
        c = it.get("continuous_gain")
        tail = f"{c['mag']:9.5f} {c['phase_deg']:10.4f}" if c else ""
        print(f"{it['order']:>6} {it['frequency_hz']:10.3f} {g['mag']:9.5f} "
              f"{g['phase_deg']:12.4f}   {tail}")
    return 0


COMMAND = Command(
    name="response",
    help="frequency response of a back-EMF observer at harmonic orders of the speed",
    description=(
        "For each signed harmonic order h (--orders, e.g. 1,-5,7), the complex gain from "
        "the plant's back-EMF component at h times the electrical frequency to the "
        "observer's estimate e_ab_hat, computed from the observer's own discrete step "
        "(linearised) at sampling period --T-s, with its continuous transfer function "
        "(li-fa-leso (17), (26), (29)) next to it. For observers that estimate a back-EMF "
        "(c-leso, gi-leso, fa-leso). JSON fields: orders[].order, orders[].frequency_hz, "
        "orders[].bemf_gain.mag, orders[].bemf_gain.phase_deg."
    ),
    add_arguments=_arguments,
    run=response_command,
)
