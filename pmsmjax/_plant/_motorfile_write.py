"""Writing a drive as a motor file (`motor_file_text`, `save_motor_file`): the inverse of
`pmsmjax._plant._motorfile`'s reader, every number written exactly."""

from __future__ import annotations

import json
import math
import os

import numpy as np

from .._files import atomic_write
from ._fluxmap_file import flux_map_csv
from ._magnetic import AlgebraicSaturation, FluxMap
from ._motorfile import _ALGEBRAIC, FORMAT, MOTOR_FILE_SCHEMA, VERSION
from ._params import Drive


def _num(x) -> str:
    x = float(np.asarray(x))
    if not math.isfinite(x):
        raise ValueError(f"a motor file holds finite numbers only; got {x!r}")
    return repr(x)


def _str(s: str) -> str:
    return json.dumps(s)  # a TOML basic string: the same escapes as JSON


def _line(key: str, value: str, comment: str) -> str:
    return f"{key} = {value}".ljust(34) + f"  # {comment}" if comment else f"{key} = {value}"


#: The flux-map file a motor file references when none is named (`motor_file_text`).
FLUX_MAP_FILE = "flux_map.csv"


def motor_file_text(drive: Drive, flux_map_file: str = FLUX_MAP_FILE) -> str:
    """The motor file (TOML text) of `drive`; `parse_motor_file` of it gives back a
    `Drive` equal to `drive` (every number is written exactly). Values must be concrete
    (not traced).

    A saturated drive gets a `[saturation]` section: an `AlgebraicSaturation` as
    `model = "algebraic"` with its parameters, a `FluxMap` as `flux_map =
    flux_map_file` (a path relative to the motor file; `save_motor_file` writes the map
    there). Other magnetic models raise `ValueError` (sample them into a `FluxMap`)."""
    S = MOTOR_FILE_SCHEMA

    def row(section, key, value, text=None):
        f = S[section][key]
        note = ", ".join(p for p in (f.unit, f.allowed().removeprefix("a finite number ")
                                     if f.kind == "number" else "") if p and p != "-")
        return _line(key, text if text is not None else _num(value), note)

    ab = drive.three_phase_motor
    lines = ["# pmsmjax motor file: SI units; the schema is in docs/motor-file.md.",
             f"format = {_str(FORMAT)}", f"version = {VERSION}",
             f"name = {_str(drive.name)}", f"notes = {_str(drive.notes)}", "",
             "[motor]",
             _line("type", _str("dual-three-phase" if drive.dual else "three-phase"), "")]
    lines += [row("motor", k, getattr(ab, k)) for k in ("R_s", "L_d", "L_q", "psi_f", "n_p")]
    if drive.dual:
        lines += [row("motor", "L_xy", drive.motor.L_xy),
                  row("motor", "gamma", drive.motor.gamma)]
    if ab.harmonics is not None:
        h = ab.harmonics
        arr = lambda xs: "[" + ", ".join(_num(x) for x in np.asarray(xs)) + "]"  # noqa: E731
        lines += ["", "[motor.harmonics]",
                  _line("order", "[" + ", ".join(str(int(o)) for o in h.order) + "]", ""),
                  _line("amplitude", arr(h.amplitude), "relative to the fundamental"),
                  _line("phase", arr(h.phase), "rad")]
    lines += _saturation_lines(ab.magnetic, flux_map_file, row)
    inv = drive.inverter
    lines += ["", "[mechanics]", row("mechanics", "J", drive.mechanics.J),
              row("mechanics", "B", drive.mechanics.B),
              "", "[inverter]", row("inverter", "u_dc", inv.u_dc)]
    if inv.u_max is not None:
        lines.append(row("inverter", "u_max", inv.u_max))
    if inv.delay:
        lines.append(_line("delay", "true", "one-sample computational delay"))
    if inv.u_dt is not None:
        lines += [row("inverter", "u_dt", inv.u_dt), row("inverter", "i_dt", inv.i_dt)]
    lines += ["", "[ratings]", row("ratings", "w_rated", drive.w_rated),
              row("ratings", "tau_rated", drive.tau_rated),
              row("ratings", "i_max", drive.i_max),
              "", "[base]", row("base", "U_b", drive.base.U_b),
              row("base", "I_b", drive.base.I_b), row("base", "w_b", drive.base.w_b)]
    if drive.T_s is not None:
        lines += ["", "[control]", row("control", "T_s", drive.T_s)]
    return "\n".join(lines) + "\n"


def _saturation_lines(model, flux_map_file: str, row) -> list[str]:
    if model is None:
        return []
    if isinstance(model, FluxMap):
        return ["", "[saturation]",
                _line("flux_map", _str(flux_map_file), "i_d,i_q,psi_d,psi_q (A, A, V s, V s), "
                      "relative to this file")]
    if isinstance(model, AlgebraicSaturation):
        if model.newton_steps != AlgebraicSaturation.newton_steps:
            raise ValueError(f"a motor file holds AlgebraicSaturation with the default "
                             f"newton_steps = {AlgebraicSaturation.newton_steps}; got "
                             f"{model.newton_steps}")
        return ["", "[saturation]", _line("model", _str("algebraic"), "AlgebraicSaturation")
                ] + [row("saturation", k, getattr(model, k)) for k in _ALGEBRAIC]
    raise ValueError(f"a motor file holds a FluxMap or an AlgebraicSaturation as the "
                     f"magnetic model; got {type(model).__name__} (sample it into a FluxMap: "
                     f"model.sample(i_d, i_q))")


def save_motor_file(drive: Drive, path, flux_map_file: str | None = None) -> None:
    """Write the motor file of `drive` to `path` (`motor_file_text`), atomically: an
    interrupted write leaves the previous file. A drive with a `FluxMap` also gets its
    map as a CSV beside the motor file, `flux_map_file` (default: the motor file's name
    with `_flux_map.csv` for `.toml`), referenced from `[saturation] flux_map`."""
    path = os.fspath(path)
    magnetic = drive.three_phase_motor.magnetic
    if isinstance(magnetic, FluxMap):
        if flux_map_file is None:
            flux_map_file = os.path.splitext(os.path.basename(path))[0] + "_flux_map.csv"
        atomic_write(os.path.join(os.path.dirname(path), flux_map_file),
                     flux_map_csv(magnetic))
    atomic_write(path, motor_file_text(drive, flux_map_file or FLUX_MAP_FILE))
