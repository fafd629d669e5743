"""`LogLayout`: how a drive logger's CSV names and scales its columns (`pmsmjax convert`).

A layout is written once per logger, as a TOML file (`load_log_layout`) or in Python, and
says for each quantity of the recorded-data format (pmsmjax._data._recording) which
column(s) hold it, in which unit and with which scale. docs/your-own-drive.md, step 4,
shows two layouts; the file's sections and keys are:

| section | key | meaning |
|---|---|---|
| `[csv]` | `delimiter` | column separator (default `","`) |
| | `skip_rows` | lines before the header row (default 0) |
| `[time]` | `column`, `unit` | time stamps in `s`, `ms` or `us` |
| | `jitter` | largest deviation of a time step from the median, a fraction (0.01) |
| `[current]` | `columns` | phases `[a, b, c]`, `[a, b]` (c = -a - b) or `[alpha, beta]` |
| | `frame` | `"phase"` (default) or `"alpha_beta"` |
| | `scale`, `offset` | A = scale * (value - offset) (counts of an ADC: its gain and zero) |
| | `adc_range` | `[low, high]` raw limits of the converter: a value at a limit is clipped |
| `[voltage]` | `columns`, `frame` | as for the current, and `frame = "duty"` for duty cycles |
| | `scale`, `offset` | V (or duty) = scale * (value - offset) |
| | `u_dc` | duty cycles only: the DC-bus voltage, a column name or a number (V) |
| | `duty_range` | duty cycles only: `[0, 1]` (default) or `[-1, 1]` (centred) |
| | `delay` | samples from the row that logs a voltage to the period it is applied over |
| | `commanded` | the voltages are the controller's references (default: duty only) |
| `[angle]` | `column`, `unit` | `mech_deg`, `mech_rad`, `elec_deg`, `elec_rad` or `counts` |
| | `counts_per_rev` | counts per mechanical revolution (`unit = "counts"`) |
| | `offset` | subtracted, in the column's unit, or `"estimate"` (from the voltages) |
| | `direction` | -1 when the encoder counts against the phase sequence a -> b -> c |
| | `n_p` | pole pairs for mechanical units (default: the drive's) |
| | `speed_window` | no speed column: the angle's centred difference over this span (s, 0.002) |
| `[speed]` | `column`, `unit` | `rpm`, `mech_rad/s` or `elec_rad/s` (default: from the angle) |
| `[load]` | `column`, `scale` | load torque, N m = scale * value |
"""

from __future__ import annotations

import dataclasses
import math
import os

import tomllib

from ._recording import SPEED_WINDOW


TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
FRAMES = ("phase", "alpha_beta")
VOLTAGE_FRAMES = (*FRAMES, "duty")
ANGLE_UNITS = ("mech_deg", "mech_rad", "elec_deg", "elec_rad", "counts")
SPEED_UNITS = ("rpm", "mech_rad/s", "elec_rad/s")
DUTY_RANGES = ((0.0, 1.0), (-1.0, 1.0))

#: The keys of each section of a layout file.
SECTIONS: dict[str, tuple[str, ...]] = {
    "csv": ("delimiter", "skip_rows"),
    "time": ("column", "unit", "jitter"),
    "current": ("columns", "frame", "scale", "offset", "adc_range"),
    "voltage": ("columns", "frame", "scale", "offset", "u_dc", "duty_range", "delay",
                "commanded"),
    "angle": ("column", "unit", "counts_per_rev", "offset", "direction", "n_p",
              "speed_window"),
    "speed": ("column", "unit"),
    "load": ("column", "scale"),
}
REQUIRED = ("time", "current", "voltage")


def _fail(field: str, value, allowed: str):
    raise ValueError(f"log layout: {field} = {value!r}: {allowed}")


def _number(field: str, v, *, positive=False, nonzero=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        _fail(field, v, "must be a finite number")
    if positive and v <= 0:
        _fail(field, v, "must be a finite number > 0")
    if nonzero and v == 0:
        _fail(field, v, "must be a finite number other than 0")
    return float(v)


def _name(field: str, v) -> str:
    if not isinstance(v, str) or not v.strip():
        _fail(field, v, "must be a column name (a non-empty string)")
    return v


def _choice(field: str, v, allowed) -> str:
    if v not in allowed:
        _fail(field, v, f"allowed: {', '.join(repr(a) for a in allowed)}")
    return v


def _columns(field: str, v, frame: str) -> tuple[str, ...]:
    if isinstance(v, str) or not isinstance(v, (list, tuple)):
        _fail(field, v, "must be a list of column names")
    names = tuple(_name(field, c) for c in v)
    allowed = (3,) if frame == "duty" else (2,) if frame == "alpha_beta" else (2, 3)
    if len(names) not in allowed:
        what = {"duty": "three duty cycles [a, b, c]",
                "alpha_beta": "two columns [alpha, beta]",
                "phase": "three phases [a, b, c] or two phases [a, b] (c = -a - b)"}[frame]
        _fail(field, list(v), f"frame {frame!r} takes {what}")
    return names


@dataclasses.dataclass(frozen=True)
class LogLayout:
    """Where a logger's CSV keeps each quantity, in which unit and scale (module docstring:
    the same keys as a layout file, flattened as `<section>_<key>`; the column names
    `time`, `current`, `voltage`, `angle`, `speed`, `load`). Construction checks every
    value and raises `ValueError` naming the field, the value and what is allowed."""

    time: str
    current: tuple[str, ...]
    voltage: tuple[str, ...]
    time_unit: str = "s"
    time_jitter: float = 0.01
    current_frame: str = "phase"
    current_scale: float = 1.0
    current_offset: float = 0.0
    current_adc_range: tuple[float, float] | None = None
    voltage_frame: str = "phase"
    voltage_scale: float = 1.0
    voltage_offset: float = 0.0
    voltage_u_dc: str | float | None = None
    voltage_duty_range: tuple[float, float] = (0.0, 1.0)
    voltage_delay: int = 0
    voltage_commanded: bool | None = None
    angle: str | None = None
    angle_unit: str = "elec_rad"
    angle_counts_per_rev: float | None = None
    angle_offset: float | str = 0.0
    angle_direction: int = 1
    angle_n_p: float | None = None
    angle_speed_window: float = SPEED_WINDOW
    speed: str | None = None
    speed_unit: str = "elec_rad/s"
    load: str | None = None
    load_scale: float = 1.0
    delimiter: str = ","
    skip_rows: int = 0

    def __post_init__(self):
        def put(name, value):
            object.__setattr__(self, name, value)

        _name("[time] column", self.time)
        _choice("[time] unit", self.time_unit, tuple(TIME_UNITS))
        jitter = _number("[time] jitter", self.time_jitter)
        if not 0.0 <= jitter < 0.5:
            _fail("[time] jitter", jitter, "must be in [0, 0.5)")
        _choice("[current] frame", self.current_frame, FRAMES)
        put("current", _columns("[current] columns", self.current, self.current_frame))
        _number("[current] scale", self.current_scale, nonzero=True)
        _number("[current] offset", self.current_offset)
        if self.current_adc_range is not None:
            r = self.current_adc_range
            key = "[current] adc_range"
            if isinstance(r, str) or len(r) != 2 or _number(key, r[0]) >= _number(key, r[1]):
                _fail("[current] adc_range", r, "must be [low, high] with low < high")
            put("current_adc_range", (float(r[0]), float(r[1])))
        _choice("[voltage] frame", self.voltage_frame, VOLTAGE_FRAMES)
        put("voltage", _columns("[voltage] columns", self.voltage, self.voltage_frame))
        _number("[voltage] scale", self.voltage_scale, nonzero=True)
        _number("[voltage] offset", self.voltage_offset)
        duty = self.voltage_frame == "duty"
        if duty:
            if self.voltage_u_dc is None:
                _fail("[voltage] u_dc", None, "duty cycles need the DC-bus voltage: a column "
                      "name or a number (V)")
            if not isinstance(self.voltage_u_dc, str):
                _number("[voltage] u_dc", self.voltage_u_dc, positive=True)
            rng = tuple(float(x) for x in self.voltage_duty_range)
            if rng not in DUTY_RANGES:
                _fail("[voltage] duty_range", list(self.voltage_duty_range),
                      "allowed: [0, 1] or [-1, 1]")
            put("voltage_duty_range", rng)
        elif self.voltage_u_dc is not None:
            _fail("[voltage] u_dc", self.voltage_u_dc, 'only for frame = "duty"')
        d = self.voltage_delay
        if isinstance(d, bool) or not isinstance(d, int) or d < 0:
            _fail("[voltage] delay", d, "must be a whole number of samples >= 0")
        if self.voltage_commanded is None:
            put("voltage_commanded", duty)
        elif not isinstance(self.voltage_commanded, bool):
            _fail("[voltage] commanded", self.voltage_commanded, "must be true or false")
        if self.angle is not None:
            _name("[angle] column", self.angle)
            _choice("[angle] unit", self.angle_unit, ANGLE_UNITS)
            if self.angle_unit == "counts":
                if self.angle_counts_per_rev is None:
                    _fail("[angle] counts_per_rev", None, 'unit = "counts" needs the counts '
                          "per mechanical revolution")
                _number("[angle] counts_per_rev", self.angle_counts_per_rev, positive=True)
            if self.angle_offset != "estimate":
                _number("[angle] offset", self.angle_offset)
            if self.angle_direction not in (1, -1):
                _fail("[angle] direction", self.angle_direction, "allowed: 1 or -1")
            if self.angle_n_p is not None:
                _number("[angle] n_p", self.angle_n_p, positive=True)
            _number("[angle] speed_window", self.angle_speed_window, positive=True)
        if self.speed is not None:
            _name("[speed] column", self.speed)
            _choice("[speed] unit", self.speed_unit, SPEED_UNITS)
        if self.load is not None:
            _name("[load] column", self.load)
            _number("[load] scale", self.load_scale, nonzero=True)
        if not isinstance(self.delimiter, str) or len(self.delimiter) != 1:
            _fail("[csv] delimiter", self.delimiter, "must be one character")
        if isinstance(self.skip_rows, bool) or not isinstance(self.skip_rows, int) \
                or self.skip_rows < 0:
            _fail("[csv] skip_rows", self.skip_rows, "must be a whole number >= 0")

    @property
    def mechanical(self) -> bool:
        """Whether the angle or the speed is mechanical (pole pairs needed)."""
        return ((self.angle is not None and not self.angle_unit.startswith("elec"))
                or (self.speed is not None and self.speed_unit != "elec_rad/s"))

    def columns(self) -> dict[str, str]:
        """Every column the layout reads, by the field that names it."""
        out = {"[time] column": self.time}
        out |= {f"[current] columns[{k}]": c for k, c in enumerate(self.current)}
        out |= {f"[voltage] columns[{k}]": c for k, c in enumerate(self.voltage)}
        if isinstance(self.voltage_u_dc, str):
            out["[voltage] u_dc"] = self.voltage_u_dc
        for sec in ("angle", "speed", "load"):
            if getattr(self, sec) is not None:
                out[f"[{sec}] column"] = getattr(self, sec)
        return out


def layout_from_dict(data: dict, source: str = "<layout>") -> LogLayout:
    """A `LogLayout` from the tables of a layout file (module docstring)."""
    unknown = [s for s in data if s not in SECTIONS]
    if unknown:
        raise ValueError(f"{source}: unknown section [{unknown[0]}]; allowed: "
                         f"{', '.join(f'[{s}]' for s in SECTIONS)}")
    missing = [s for s in REQUIRED if s not in data]
    if missing:
        raise ValueError(f"{source}: missing section [{missing[0]}] (required: "
                         f"{', '.join(f'[{s}]' for s in REQUIRED)})")
    kw = {}
    for sec, table in data.items():
        if not isinstance(table, dict):
            raise ValueError(f"{source}: [{sec}] must be a table")
        for key, v in table.items():
            if key not in SECTIONS[sec]:
                raise ValueError(f"{source}: unknown key {key!r} in [{sec}]; allowed: "
                                 f"{', '.join(SECTIONS[sec])}")
            if sec == "csv":
                kw[key] = v
            elif key in ("column", "columns"):
                kw[sec] = tuple(v) if isinstance(v, list) else v
            else:
                kw[f"{sec}_{key}"] = tuple(v) if isinstance(v, list) else v
        if sec in ("time", "current", "voltage", "angle", "speed", "load") and sec not in kw:
            raise ValueError(f"{source}: [{sec}] needs "
                             f"{'columns' if sec in ('current', 'voltage') else 'column'}")
    try:
        return LogLayout(**kw)
    except ValueError as e:
        raise ValueError(f"{source}: {e}") from None


def load_log_layout(path) -> LogLayout:
    """Read a layout file (TOML, module docstring); `ValueError` names the file, the field
    and what is allowed."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ValueError(f"log layout {path}: no such file") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"log layout {path}: not valid TOML: {e}") from None
    return layout_from_dict(data, f"log layout {path}")
