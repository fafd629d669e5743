"""Logs as loggers write them: `convert_log` reads a drive logger's CSV through a
`LogLayout` and returns the recorded-data format (`RecordedData`) with a report of what
it assumed; `estimate_encoder_offset` finds an encoder's offset from the voltages.

**Timing convention** (the report states it for every conversion): a row's currents,
angle and speed are sampled at its time stamp t_k; the voltage a row logs is the one the
controller computed at t_k, applied over [t_{k+d}, t_{k+d+1}) with d = `[voltage] delay`
samples (the computational delay: 1 for a drive that computes in one period what it
applies in the next, 0 when the log already holds the applied voltage). The recording's
`u_ab[k]` is the voltage over [t_k, t_{k+1}), so the converter shifts the voltages by d
samples and drops the first d rows. Time stamps with jitter up to `[time] jitter` of the
period are taken as the uniform grid t_0 + k T_s (the converter's clock, not the
logger's stamp, is what sampled); a larger deviation or a gap is an error.

**Voltages**: phase voltages to any common point and duty cycles lose their common mode
in the amplitude-invariant Clarke transform (docs/conventions.md), so duty cycles d_x in
[0, 1] become u_ab = clarke(d u_dc) (centred duty cycles in [-1, 1]: clarke(d u_dc / 2)).
Duty cycles are what the controller commanded: the inverter's dead-time error is not in
them, and the report says to replay and identify them with `--voltage commanded`.
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import math
import os

import numpy as np

from ._log_checks import (
    drive_period_warnings,
    encoder_warnings,
    estimate_encoder_offset,
    sampling_period_warnings,
    wrap,
)
from ._log_layout import TIME_UNITS, LogLayout
from ._recording import RecordedData, centred_speed


_SQRT3 = math.sqrt(3.0)


class LogFormatError(ValueError):
    """A log that does not match its layout, or data that cannot be a drive's log; the
    message names the file, the line, the column and the layout field."""


@dataclasses.dataclass(frozen=True)
class ConvertedLog:
    """`convert_log`'s result: the recording and what the conversion assumed and found.

    - `data`: the `RecordedData`.
    - `T_s`: sampling period (s); `jitter`: largest deviation of a spacing from it (fraction).
    - `rows`: data rows read; `dropped`: rows dropped for the voltage delay.
    - `timing`: the sample timing convention, one line each.
    - `commanded`: the voltages are the controller's references.
    - `offset_estimate_deg`: the encoder offset found from the voltages (electrical deg,
      the logged angle minus the rotor's), None without an angle or a machine model;
      `offset_removed_deg`: the offset subtracted (electrical deg).
    - `warnings`: what a newcomer should check, each saying what to do.
    """

    data: RecordedData
    T_s: float
    jitter: float
    rows: int
    dropped: int
    timing: tuple[str, ...]
    commanded: bool
    offset_estimate_deg: float | None
    offset_removed_deg: float
    warnings: tuple[str, ...]

    def lines(self) -> list[str]:
        """The report for a console."""
        out = [f"{self.rows} rows, T_s = {self.T_s * 1e6:.6g} us (largest deviation of a "
               f"time step {100 * self.jitter:.2g} %), {self.data.n} samples written"]
        out += [f"  {s}" for s in self.timing]
        if self.offset_estimate_deg is not None:
            out.append(f"encoder offset estimated from the voltages: "
                       f"{self.offset_estimate_deg:+.2f} deg electrical (removed: "
                       f"{self.offset_removed_deg:+.2f} deg)")
        out += [f"warning: {w}" for w in self.warnings]
        return out

    def summary(self) -> dict:
        """The report as JSON-ready values."""
        return dict(rows=self.rows, samples=self.data.n, dropped=self.dropped, T_s=self.T_s,
                    jitter=self.jitter, timing=list(self.timing), commanded=self.commanded,
                    offset_estimate_deg=self.offset_estimate_deg,
                    offset_removed_deg=self.offset_removed_deg, names=list(self.data.names),
                    warnings=list(self.warnings))


def _read_columns(path: str, layout: LogLayout) -> tuple[dict[str, np.ndarray], list[int]]:
    """The columns the layout names, as float arrays, and each row's line number."""
    want = layout.columns()
    with open(path, newline="") as f:
        for _ in range(layout.skip_rows):
            f.readline()
        reader = csv.reader(f, delimiter=layout.delimiter)
        header = [h.strip() for h in next(reader, [])]
        header_line = layout.skip_rows + 1
        if not any(header):
            raise LogFormatError(f"{path}: line {header_line}: no header row (after "
                                 f"[csv] skip_rows = {layout.skip_rows})")
        index = {}
        for field, name in want.items():
            if name not in header:
                close = difflib.get_close_matches(name, header, n=2)
                hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
                sep = "" if len(header) > 1 else (
                    f" (one column only: is [csv] delimiter = {layout.delimiter!r} right?)")
                raise LogFormatError(
                    f"{path}: column {name!r} ({field}) is not in the header; its columns "
                    f"are {', '.join(repr(h) for h in header)}{sep}{hint}")
            index[name] = header.index(name)
        names = list(dict.fromkeys(want.values()))
        cols = {n: [] for n in names}
        lines = []
        for k, row in enumerate(reader):
            line = header_line + 1 + k
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise LogFormatError(f"{path}: line {line} has {len(row)} fields, the header "
                                     f"{len(header)}")
            for n in names:
                cell = row[index[n]].strip()
                try:
                    v = float(cell)
                except ValueError:
                    raise LogFormatError(f"{path}: line {line}, column {n!r}: {cell!r} is not "
                                         f"a number") from None
                if not math.isfinite(v):
                    raise LogFormatError(f"{path}: line {line}, column {n!r}: {cell!r} (a "
                                         f"logged value must be finite)")
                cols[n].append(v)
            lines.append(line)
    if len(lines) < 2:
        raise LogFormatError(f"{path}: {len(lines)} data rows; a log needs at least 2")
    return {n: np.asarray(v) for n, v in cols.items()}, lines


def _time_axis(path, t_raw, lines, layout) -> tuple[np.ndarray, float, float, list[str]]:
    t = t_raw * TIME_UNITS[layout.time_unit]
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0))
        raise LogFormatError(f"{path}: line {lines[k + 1]}: time {float(t_raw[k + 1])!r} "
                             f"({layout.time}) is not after the previous row's "
                             f"{float(t_raw[k])!r}: time must increase")
    T_s = float(np.median(dt))
    gaps = np.flatnonzero(dt > 1.5 * T_s)
    if gaps.size:
        k = int(gaps[0])
        raise LogFormatError(
            f"{path}: a gap between line {lines[k]} and line {lines[k + 1]}: "
            f"{dt[k] / T_s:.3g} sampling periods of {T_s:.6g} s "
            f"(about {round(dt[k] / T_s) - 1} samples missing; {gaps.size} gaps in all): "
            f"replay and identify need every sample; split the log at its gaps")
    dev = np.abs(dt - T_s) / T_s
    if np.any(dev > layout.time_jitter):
        k = int(np.argmax(dev))
        raise LogFormatError(
            f"{path}: line {lines[k + 1]}: time step {dt[k]:.6g} s deviates {100 * dev[k]:.3g} "
            f"% from the median {T_s:.6g} s, more than [time] jitter = {layout.time_jitter} "
            f"allows")
    warnings = sampling_period_warnings(T_s, layout.time_unit)
    return t[0] + T_s * np.arange(t.size), T_s, float(dev.max(initial=0.0)), warnings


def _clarke2(x: np.ndarray) -> np.ndarray:
    """Two or three phase columns (c = -a - b for two) -> alpha-beta, amplitude invariant."""
    if x.shape[1] == 2:
        a, b = x[:, 0], x[:, 1]
        return np.stack([a, (a + 2.0 * b) / _SQRT3], axis=1)
    a, b, c = x.T
    return np.stack([(2.0 * a - b - c) / 3.0, (b - c) / _SQRT3], axis=1)


def _vector(path, cols, lines, names, frame, scale, offset):
    raw = np.stack([cols[n] for n in names], axis=1)
    x = scale * (raw - offset)
    return x if frame == "alpha_beta" else _clarke2(x)


def _duty_voltages(path, cols, lines, layout) -> np.ndarray:
    d = layout.voltage_scale * (np.stack([cols[n] for n in layout.voltage], axis=1)
                                - layout.voltage_offset)
    lo, hi = layout.voltage_duty_range
    bad = (d < lo - 1e-9) | (d > hi + 1e-9)
    if np.any(bad):
        k, j = (int(v[0]) for v in np.nonzero(bad))
        hint = (" (percent: [voltage] scale = 0.01)" if np.max(np.abs(d)) <= 100.0 * hi
                and np.max(np.abs(d)) > hi else "")
        raise LogFormatError(
            f"{path}: line {lines[k]}, column {layout.voltage[j]!r}: duty cycle {d[k, j]:.6g} "
            f"(after [voltage] scale and offset) is outside [voltage] duty_range = "
            f"[{lo:g}, {hi:g}]{hint}")
    if isinstance(layout.voltage_u_dc, str):
        u_dc = cols[layout.voltage_u_dc]
        if np.any(u_dc <= 0):
            k = int(np.argmax(u_dc <= 0))
            raise LogFormatError(f"{path}: line {lines[k]}, column {layout.voltage_u_dc!r} "
                                 f"([voltage] u_dc): DC-bus voltage {float(u_dc[k])!r} must "
                                 f"be > 0 V")
    else:
        u_dc = np.full(d.shape[0], float(layout.voltage_u_dc))
    v = d * u_dc[:, None] if lo == 0.0 else 0.5 * d * u_dc[:, None]
    return _clarke2(v)


def _electrical(layout: LogLayout, n_p: float | None, path: str) -> float | None:
    if not layout.mechanical:
        return None
    n = layout.angle_n_p if layout.angle_n_p is not None else n_p
    if n is None:
        raise LogFormatError(f"{path}: the log's angle or speed is mechanical, so the "
                             "conversion needs the pole pairs: give the drive (--motor-file / "
                             "--motor) or [angle] n_p")
    return float(n)


def _angle_rad(raw: np.ndarray, layout: LogLayout, n_p) -> np.ndarray:
    """Electrical angle (rad, unwrapped as logged) from the column, offset subtracted when
    it is a number."""
    off = 0.0 if layout.angle_offset == "estimate" else float(layout.angle_offset)
    x = layout.angle_direction * (raw - off)
    unit = layout.angle_unit
    if unit == "counts":
        return x * (2.0 * math.pi / layout.angle_counts_per_rev) * n_p
    rad = np.radians(x) if unit.endswith("deg") else x
    return rad * n_p if unit.startswith("mech") else rad


def convert_log(path, layout: LogLayout, *, drive=None) -> ConvertedLog:
    """Read a logger's CSV at `path` through `layout` (`LogLayout`, or
    `load_log_layout(file)`) into the recorded-data format (module docstring: timing
    and voltage conventions).

    **Arguments:**

    - `drive`: the `Drive` (pole pairs for mechanical angles and speeds; the machine model
      for the encoder-offset estimate); optional where neither is needed.

    Raises `LogFormatError` naming the line, the column and the layout field for: a
    missing column, a cell that is not a finite number, time that does not increase, a
    gap, irregular spacing, an ADC at its limit, a duty cycle outside its range, a DC bus
    at or below zero, a mechanical quantity without pole pairs, an offset to estimate
    without a machine.
    """
    path = os.fspath(path)
    if not isinstance(layout, LogLayout):
        raise TypeError(f"layout must be a LogLayout (load_log_layout(file)); got "
                        f"{type(layout).__name__}")
    motor = None if drive is None else drive.three_phase_motor
    n_p = _electrical(layout, None if motor is None else float(motor.n_p), path)
    try:
        cols, lines = _read_columns(path, layout)
    except FileNotFoundError:
        raise LogFormatError(f"{path}: no such file") from None
    t, T_s, jitter, warnings = _time_axis(path, cols[layout.time], lines, layout)
    warnings += drive_period_warnings(T_s, drive)
    if layout.current_adc_range is not None:
        lo, hi = layout.current_adc_range
        for n in layout.current:
            clipped = (cols[n] <= lo) | (cols[n] >= hi)
            if np.any(clipped):
                k = int(np.argmax(clipped))
                raise LogFormatError(
                    f"{path}: line {lines[k]}, column {n!r}: {float(cols[n][k])!r} is at the "
                    f"converter's limit ([current] adc_range = [{lo:g}, {hi:g}]; "
                    f"{int(clipped.sum())} clipped samples in this column): the current "
                    f"exceeded the sensor's range, and no model can fit a clipped current")
    i_ab = _vector(path, cols, lines, layout.current, layout.current_frame,
                   layout.current_scale, layout.current_offset)
    u_ab = (_duty_voltages(path, cols, lines, layout) if layout.voltage_frame == "duty"
            else _vector(path, cols, lines, layout.voltage, layout.voltage_frame,
                         layout.voltage_scale, layout.voltage_offset))
    d = layout.voltage_delay
    if d >= t.size - 1:
        raise LogFormatError(f"{path}: [voltage] delay = {d} samples leaves fewer than 2 of "
                             f"the {t.size} rows")
    keep = slice(d, None)
    arrays = dict(t=t[keep], i_ab=i_ab[keep], u_ab=u_ab[:t.size - d])
    theta_unwrapped = None
    if layout.angle is not None:
        theta_unwrapped = np.unwrap(_angle_rad(cols[layout.angle], layout, n_p or 1.0))[keep]
    if layout.speed is not None:
        raw = cols[layout.speed][keep]
        f = {"rpm": 2.0 * math.pi / 60.0 * (n_p or 1.0), "mech_rad/s": n_p or 1.0,
             "elec_rad/s": 1.0}[layout.speed_unit]
        arrays["w_m"] = raw * f
    elif theta_unwrapped is not None:
        arrays["w_m"] = centred_speed(theta_unwrapped, arrays["t"],
                                       layout.angle_speed_window)
    if layout.load is not None:
        arrays["tau_L"] = layout.load_scale * cols[layout.load][keep]
    estimate = None
    removed = 0.0
    if theta_unwrapped is not None:
        arrays["theta"] = wrap(theta_unwrapped)
        if motor is not None:
            estimate = math.degrees(estimate_encoder_offset(RecordedData(**arrays),
                                                            motor).offset)
        if layout.angle_offset == "estimate":
            if estimate is None:
                raise LogFormatError(f"{path}: [angle] offset = \"estimate\" needs the "
                                     "machine: give the drive (--motor-file / --motor)")
            arrays["theta"] = wrap(theta_unwrapped - math.radians(estimate))
            removed = estimate
        else:
            removed = _offset_deg(layout, n_p or 1.0) + 0.0  # no negative zero
    data = RecordedData(**arrays)
    if motor is not None and not drive.dual:
        warnings += encoder_warnings(data, motor, layout=True)
    timing = [f"i_ab{', theta, w_m' if 'theta' in arrays else ''}: sampled at the row's "
              f"time t_k",
              (f"u_ab over [t_k, t_k+1): the voltage logged {d} row(s) earlier ([voltage] "
               f"delay = {d}: the voltage computed at t_k is applied over [t_k+{d}, "
               f"t_k+{d + 1})); the first {d} row(s) dropped" if d else
               "u_ab over [t_k, t_k+1): the voltage of the same row ([voltage] delay = 0: "
               "the log holds the voltage applied after the row's sampling instant)")]
    if layout.voltage_commanded:
        timing.append("the voltages are the controller's commands (the inverter's dead-time "
                      "error is not in them): replay and identify with --voltage commanded "
                      "and the drive's [inverter] u_dt")
    return ConvertedLog(data=data, T_s=T_s, jitter=jitter, rows=len(lines), dropped=d,
                        timing=tuple(timing), commanded=bool(layout.voltage_commanded),
                        offset_estimate_deg=estimate,
                        offset_removed_deg=float(removed), warnings=tuple(warnings))


def _offset_deg(layout: LogLayout, n_p) -> float:
    """The numeric `[angle] offset` in electrical degrees."""
    off = float(layout.angle_offset)
    unit = layout.angle_unit
    if unit == "counts":
        return layout.angle_direction * off * 360.0 / layout.angle_counts_per_rev * n_p
    deg = off if unit.endswith("deg") else math.degrees(off)
    return layout.angle_direction * (deg * n_p if unit.startswith("mech") else deg)
