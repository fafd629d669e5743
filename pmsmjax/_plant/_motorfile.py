r"""Motor files: a user's drive as a small TOML file (`load_motor_file`, `motor_file_text`).

A motor file holds everything `Drive` holds: the machine (three-phase or dual
three-phase, optional back-EMF harmonics), the mechanics, the inverter, the ratings and
the per-unit bases, all in SI units. Every preset can be written as one
(`pmsmjax motor --export NAME`), and a file written that way loads back to the identical
`Drive`. Example (the `zhang750` preset):

```toml
format = "pmsmjax-motor"
version = 1
name = "zhang750"
notes = "zhang2022 Table I ..."

[motor]
type = "three-phase"     # or "dual-three-phase"
R_s = 0.78               # Ohm, > 0
L_d = 0.00246            # H, > 0
L_q = 0.00268            # H, > 0
psi_f = 0.056            # V s, >= 0
n_p = 5.0                # pole pairs, > 0

[mechanics]
J = 0.0015               # kg m^2, > 0
B = 0.0                  # N m s/rad, >= 0

[inverter]
u_dc = 311.0             # V, > 0

[ratings]
w_rated = 1256.6370614359173   # rad/s electrical, > 0 (or n_rated_rpm)
tau_rated = 2.4                # N m, > 0
i_max = 13.576450198781712     # A peak, > 0

[base]
U_b = 179.55...          # V peak phase (or U_rated_ll and I_rated_rms)
I_b = 6.788...           # A peak
w_b = 1256.63...         # rad/s electrical
```

A saturated machine adds `[saturation]`: `flux_map = "map.csv"` (a CSV or NPZ file,
`read_flux_map`, its path relative to the motor file) or `model = "algebraic"` with the
`AlgebraicSaturation` parameters, and optionally `constants = "small-current" | "rated" |
"fit"`: then `[motor]` `L_d`, `L_q`, `psi_f` (the constants the controllers and
observers deploy) may be omitted and are derived with `constant_model`
(`read_motor_file` returns the console note saying how). `save_motor_file` writes a
`FluxMap` as a CSV beside the motor file.

`MOTOR_FILE_SCHEMA` lists every section and field with its unit, allowed range and
whether it is required; `docs/motor-file.md` is written from it. A malformed file
raises `MotorFileError` (a `ValueError`) whose message names the file, the section and
field, the value found and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np


try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the same parser as a package
    import tomli as tomllib

from ._fluxmap_file import FluxMapError, read_flux_map
from ._magnetic import AlgebraicSaturation, constant_model
from ._params import (
    BaseValues,
    Drive,
    DualThreePhaseParams,
    EMFHarmonics,
    Inverter,
    Mechanics,
    PMSMParams,
)


FORMAT = "pmsmjax-motor"
VERSION = 1
MOTOR_TYPES = ("three-phase", "dual-three-phase")
SATURATION_MODELS = ("algebraic",)
CONSTANTS = ("small-current", "rated", "fit")
_ALGEBRAIC = ("a_d0", "a_dd", "a_q0", "a_qq", "a_dq", "i_f", "S", "T", "U", "V")
_ALGEBRAIC_REQUIRED = _ALGEBRAIC[:6]
_CONSTANT_NAMES = ("L_d", "L_q", "psi_f")


class MotorFileError(ValueError):
    """A malformed motor file: the message names the file, the field and what is
    allowed."""


@dataclasses.dataclass(frozen=True)
class Field:
    """One field of a motor file: unit, allowed range (`lo`/`hi`, open or closed), kind
    (`"number"`, `"string"`, `"bool"`, `"numbers"`, `"integers"`), whether it is
    required, and what it is."""

    unit: str
    doc: str
    kind: str = "number"
    required: bool = True
    lo: float | None = None
    lo_open: bool = False
    hi: float | None = None

    def allowed(self) -> str:
        if self.kind == "string":
            return "a string"
        if self.kind == "bool":
            return "true or false"
        if self.kind == "integers":
            return "a list of integers other than 0 and 1"
        what = "a list of finite numbers" if self.kind == "numbers" else "a finite number"
        if self.lo is not None:
            what += f" {'>' if self.lo_open else '>='} {self.lo:g}"
        if self.hi is not None:
            what += f" and <= {self.hi:g}"
        return what


_POS = dict(lo=0.0, lo_open=True)
_NONNEG = dict(lo=0.0)

#: Every section of a motor file and its fields (`Field`); top-level keys under "".
MOTOR_FILE_SCHEMA: dict[str, dict[str, Field]] = {
    "": {
        "format": Field("", f'always "{FORMAT}"', kind="string"),
        "version": Field("", f"format version, {VERSION}", lo=VERSION, hi=VERSION),
        "name": Field("", "name of the drive (reports, plots)", kind="string",
                      required=False),
        "notes": Field("", "source of the data and every assumption made", kind="string",
                       required=False),
    },
    "motor": {
        "type": Field("", f"machine type: {' or '.join(MOTOR_TYPES)}", kind="string",
                      required=False),
        "R_s": Field("Ohm", "stator resistance", **_POS),
        "L_d": Field("H", "d-axis inductance (with [saturation]: optional, the constant "
                     "the controllers and observers deploy; derived when absent)",
                     required=False, **_POS),
        "L_q": Field("H", "q-axis inductance (with [saturation]: optional, as L_d)",
                     required=False, **_POS),
        "psi_f": Field("V s", "permanent-magnet flux linkage (peak, per three-phase set; "
                       "with [saturation]: optional, as L_d)", required=False, **_NONNEG),
        "n_p": Field("-", "pole pairs", **_POS),
        "L_xy": Field("H", "x-y subspace inductance (dual three-phase only)",
                      required=False, **_POS),
        "gamma": Field("rad", "angle between the two winding sets (dual three-phase "
                       "only; default pi/6)", required=False, lo=0.0, hi=math.pi),
    },
    "motor.harmonics": {
        "order": Field("-", "signed harmonic orders (positive: rotating with the rotor, "
                       "e.g. 7; negative: against it, e.g. -5)", kind="integers"),
        "amplitude": Field("-", "back-EMF amplitude of each harmonic relative to the "
                           "fundamental", kind="numbers"),
        "phase": Field("rad", "phase of each harmonic at theta = 0 (default zeros)",
                       kind="numbers", required=False),
    },
    "saturation": {
        "flux_map": Field("", "flux-map file (CSV or NPZ, see read_flux_map), its path "
                          "relative to the motor file (give this or model)", kind="string",
                          required=False),
        "model": Field("", f"analytical saturation model: {' or '.join(SATURATION_MODELS)} "
                       "(AlgebraicSaturation; give this or flux_map)", kind="string",
                       required=False),
        "constants": Field("", "how the [motor] L_d, L_q, psi_f that are absent are derived "
                           f"(constant_model): {', '.join(CONSTANTS)} (default "
                           f"{CONSTANTS[0]})", kind="string", required=False),
        "a_d0": Field("1/H", "algebraic: unsaturated d-axis inverse inductance",
                      required=False, **_POS),
        "a_dd": Field("A/(V s)^(S+1)", "algebraic: d-axis self-saturation", required=False,
                      **_NONNEG),
        "a_q0": Field("1/H", "algebraic: unsaturated q-axis inverse inductance",
                      required=False, **_POS),
        "a_qq": Field("A/(V s)^(T+1)", "algebraic: q-axis self-saturation", required=False,
                      **_NONNEG),
        "a_dq": Field("A/(V s)^(U+V+3)", "algebraic: cross-saturation", required=False,
                      **_NONNEG),
        "i_f": Field("A", "algebraic: equivalent magnet current (0: reluctance machine)",
                     required=False, **_NONNEG),
        "S": Field("-", "algebraic: exponent of a_dd (default 5)", required=False, **_NONNEG),
        "T": Field("-", "algebraic: exponent of a_qq (default 1)", required=False, **_NONNEG),
        "U": Field("-", "algebraic: d exponent of a_dq (default 1)", required=False,
                   **_NONNEG),
        "V": Field("-", "algebraic: q exponent of a_dq (default 0)", required=False,
                   **_NONNEG),
    },
    "mechanics": {
        "J": Field("kg m^2", "total moment of inertia", **_POS),
        "B": Field("N m s/rad", "viscous friction (default 0)", required=False, **_NONNEG),
    },
    "inverter": {
        "u_dc": Field("V", "DC-link voltage", **_POS),
        "u_max": Field("V", "largest voltage-vector amplitude, peak phase (default "
                       "u_dc / sqrt(3); at most 2 u_dc / 3)", required=False, **_POS),
        "delay": Field("", "one-sample computational delay (default false)", kind="bool",
                       required=False),
        "u_dt": Field("V", "dead-time and device-drop voltage error per phase (default: "
                      "none, an ideal inverter)", required=False, **_NONNEG),
        "i_dt": Field("A", "width of the dead-time error's transition around zero phase "
                      "current, u_dt tanh(i / i_dt); 0: the hard model u_dt sign(i) "
                      "(default 0.1)", required=False, **_NONNEG),
    },
    "ratings": {
        "w_rated": Field("rad/s", "rated electrical speed (give this or n_rated_rpm)",
                         required=False, **_POS),
        "n_rated_rpm": Field("rpm", "rated mechanical speed (give this or w_rated)",
                             required=False, **_POS),
        "tau_rated": Field("N m", "rated torque", **_POS),
        "i_max": Field("A", "current-vector amplitude limit of the controller (peak)",
                       **_POS),
    },
    "base": {
        "U_b": Field("V", "base voltage, peak phase (with I_b, w_b)", required=False,
                     **_POS),
        "I_b": Field("A", "base current, peak (with U_b, w_b)", required=False, **_POS),
        "w_b": Field("rad/s", "base electrical speed (default: w_rated)", required=False,
                     **_POS),
        "U_rated_ll": Field("V", "rated line-to-line rms voltage: U_b = sqrt(2/3) "
                            "U_rated_ll (instead of U_b)", required=False, **_POS),
        "I_rated_rms": Field("A", "rated rms current: I_b = sqrt(2) I_rated_rms "
                             "(instead of I_b)", required=False, **_POS),
    },
    "control": {
        "T_s": Field("s", "the drive's sampling period: the default of every command that "
                     "runs the observer in time, and a recording's period is checked "
                     "against it", required=False, **_POS),
    },
}

#: Sections that must be present.
REQUIRED_SECTIONS = ("motor", "mechanics", "inverter", "ratings")


def _where(section: str, key: str) -> str:
    return f"[{section}] {key}" if section else key


class _Reader:
    def __init__(self, source: str):
        self.source = source

    def fail(self, msg: str):
        raise MotorFileError(f"motor file {self.source}: {msg}")

    def section(self, data: dict, section: str, required: bool) -> dict | None:
        parts = section.split(".") if section else []
        node = data
        for p in parts:
            if not isinstance(node, dict) or p not in node:
                if required:
                    self.fail(f"missing section [{section}] (required sections: "
                              f"{', '.join(f'[{s}]' for s in REQUIRED_SECTIONS)})")
                return None
            node = node[p]
        if not isinstance(node, dict):
            self.fail(f"[{section}] must be a table (a [{section}] section); got "
                      f"{node!r}")
        schema = MOTOR_FILE_SCHEMA[section]
        sub = set(MOTOR_FILE_SCHEMA)  # sub-sections are keys of their parent table
        for key in node:
            if key not in schema and f"{section}.{key}".lstrip(".") not in sub:
                self.fail(f"unknown field {_where(section, key)!r}; allowed in "
                          f"[{section or 'top level'}]: {', '.join(schema)}")
        out = {}
        for key, f in schema.items():
            if key not in node:
                if f.required:
                    self.fail(f"missing field {_where(section, key)} ({f.doc}; "
                              f"{f.allowed()}{', ' + f.unit if f.unit else ''})")
                continue
            out[key] = self.value(section, key, node[key], f)
        return out

    def value(self, section: str, key: str, v, f: Field):
        where = _where(section, key)
        unit = f" ({f.unit})" if f.unit else ""
        bad = lambda: self.fail(f"{where} = {v!r}{unit}: must be {f.allowed()}")  # noqa: E731
        if f.kind == "string":
            return v if isinstance(v, str) else bad()
        if f.kind == "bool":
            return v if isinstance(v, bool) else bad()
        if f.kind in ("numbers", "integers"):
            if not isinstance(v, list) or not v:
                bad()
            if f.kind == "integers":
                if not all(isinstance(x, int) and not isinstance(x, bool) and x not in (0, 1)
                           for x in v):
                    bad()
                return tuple(v)
            if not all(isinstance(x, int | float) and not isinstance(x, bool)
                       and math.isfinite(x) for x in v):
                bad()
            return tuple(float(x) for x in v)
        if not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v):
            bad()
        x = float(v)
        if f.lo is not None and (x <= f.lo if f.lo_open else x < f.lo):
            bad()
        if f.hi is not None and x > f.hi:
            bad()
        return x


def _saturation(r: _Reader, sat: dict | None, m: dict, i_max: float):
    """The magnetic model of `[saturation]` (or `None`) and the console notes on how the
    absent `[motor]` constants were derived (they are filled into `m`)."""
    absent = [k for k in _CONSTANT_NAMES if k not in m]
    if sat is None:
        if absent:
            f = MOTOR_FILE_SCHEMA["motor"][absent[0]]
            r.fail(f"missing field [motor] {absent[0]} ({f.unit}; {f.allowed()}; optional "
                   f"only with a [saturation] section, which it is then derived from)")
        return None, []
    if ("flux_map" in sat) == ("model" in sat):
        r.fail('[saturation]: give exactly one of flux_map = "FILE" (a flux-map CSV or NPZ, '
               f'path relative to the motor file) and model = "{SATURATION_MODELS[0]}"')
    params = [k for k in _ALGEBRAIC if k in sat]
    if "flux_map" in sat:
        if params:
            r.fail(f"[saturation] {params[0]}: a parameter of model = \"algebraic\"; with "
                   "flux_map the map is the model (remove it)")
        rel = sat["flux_map"]
        path = rel if os.path.isabs(rel) else os.path.join(os.path.dirname(r.source), rel)
        try:
            model = read_flux_map(path)
        except FluxMapError as e:
            r.fail(f"[saturation] flux_map = {rel!r}: {e}")
        except OSError as e:
            r.fail(f"[saturation] flux_map = {rel!r}: cannot read {path} ({e.strerror}); "
                   "the path is relative to the motor file")
        what = "the flux map's"
    else:
        if sat["model"] not in SATURATION_MODELS:
            r.fail(f"[saturation] model = {sat['model']!r}: must be one of "
                   f"{', '.join(map(repr, SATURATION_MODELS))}")
        for k in _ALGEBRAIC_REQUIRED:
            if k not in sat:
                f = MOTOR_FILE_SCHEMA["saturation"][k]
                r.fail(f"missing field [saturation] {k} ({f.doc.removeprefix('algebraic: ')}"
                       f"; {f.allowed()}, {f.unit}) of model = \"algebraic\"")
        try:
            model = AlgebraicSaturation(**{k: sat[k] for k in params})
        except ValueError as e:
            r.fail(f"[saturation]: {e}")
        what = "the algebraic model's"
    how = sat.get("constants")
    if how is not None and how not in CONSTANTS:
        r.fail(f"[saturation] constants = {how!r}: must be one of "
               f"{', '.join(map(repr, CONSTANTS))}")
    if how is not None and not absent:
        r.fail(f"[saturation] constants = {how!r}: [motor] gives L_d, L_q and psi_f, so "
               "nothing is derived; remove constants, or the [motor] values to derive")
    if not absent:
        return model, []
    how = how or CONSTANTS[0]
    values = dict(zip(_CONSTANT_NAMES, constant_model(model, how, i_max)))
    m.update({k: values[k] for k in absent})
    shown = {"L_d": lambda v: f"L_d {1e3 * v:.5g} mH", "L_q": lambda v: f"L_q {1e3 * v:.5g} mH",
             "psi_f": lambda v: f"psi_f {v:.5g} V s"}
    given = [k for k in _CONSTANT_NAMES if k not in absent]
    return model, [f"{', '.join(absent)} from {what} {how} values (constant_model"
                   f"{'' if how == CONSTANTS[0] else f', i_max {i_max:g} A'}): "
                   + ", ".join(shown[k](values[k]) for k in absent)
                   + (f"; {', '.join(given)} as given in [motor]" if given else "")]


def parse_motor_file(text: str, source: str = "<text>") -> Drive:
    """The `Drive` described by the motor-file text `text` (`source` names it in
    errors; a `[saturation] flux_map` path is relative to its folder). Raises
    `MotorFileError` naming the field for any malformed input."""
    return _parse(text, source)[0]


def _parse(text: str, source: str) -> tuple[Drive, list[str]]:
    r = _Reader(source)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        r.fail(f"not valid TOML: {e}")
    if "version" in data and data["version"] != VERSION:
        r.fail(f"version = {data['version']!r}: this pmsmjax reads motor-file version "
               f"{VERSION}")
    top = r.section(data, "", True)
    if top["format"] != FORMAT:
        r.fail(f"format = {top['format']!r}: must be {FORMAT!r}")
    m = r.section(data, "motor", True)
    harm = r.section(data, "motor.harmonics", False)
    mech = r.section(data, "mechanics", True)
    inv = r.section(data, "inverter", True)
    rat = r.section(data, "ratings", True)
    base = r.section(data, "base", False) or {}
    sat = r.section(data, "saturation", False)
    control = r.section(data, "control", False) or {}
    for s in data:
        if s not in MOTOR_FILE_SCHEMA[""] and s not in MOTOR_FILE_SCHEMA:
            r.fail(f"unknown section or field {s!r}; allowed sections: "
                   f"{', '.join(f'[{k}]' for k in MOTOR_FILE_SCHEMA if k)}")

    kind = m.get("type", "three-phase")
    if kind not in MOTOR_TYPES:
        r.fail(f"[motor] type = {kind!r}: must be one of {', '.join(map(repr, MOTOR_TYPES))}")
    dual = kind == "dual-three-phase"
    for key in ("L_xy", "gamma"):
        if key in m and not dual:
            r.fail(f"[motor] {key}: only for type = \"dual-three-phase\" (this motor is "
                   f"{kind})")
    if dual and "L_xy" not in m:
        r.fail("missing field [motor] L_xy (x-y subspace inductance, H, > 0) of a "
               "dual three-phase machine")

    def build(what: str, fn):
        try:
            return fn()
        except MotorFileError:
            raise
        except ValueError as e:
            r.fail(f"[{what}]: {e}")

    harmonics = None
    if harm is not None:
        n = len(harm["order"])
        for key in ("amplitude", "phase"):
            if key in harm and len(harm[key]) != n:
                r.fail(f"[motor.harmonics] {key} has {len(harm[key])} entries; must have "
                       f"one per order ({n})")
        harmonics = build("motor.harmonics", lambda: EMFHarmonics(
            order=harm["order"], amplitude=np.asarray(harm["amplitude"]),
            phase=None if "phase" not in harm else np.asarray(harm["phase"])))
    magnetic, notes = _saturation(r, sat, m, rat["i_max"])
    ab = build("motor", lambda: PMSMParams(R_s=m["R_s"], L_d=m["L_d"], L_q=m["L_q"],
                                           psi_f=m["psi_f"], n_p=m["n_p"],
                                           harmonics=harmonics, magnetic=magnetic))
    motor = ab
    if dual:
        motor = build("motor", lambda: DualThreePhaseParams(
            ab=ab, L_xy=m["L_xy"], gamma=m.get("gamma", math.pi / 6)))
    mechanics = build("mechanics", lambda: Mechanics(J=mech["J"], B=mech.get("B", 0.0)))
    inverter = build("inverter", lambda: Inverter(u_dc=inv["u_dc"], u_max=inv.get("u_max"),
                                                  delay=inv.get("delay", False),
                                                  u_dt=inv.get("u_dt"),
                                                  i_dt=inv.get("i_dt", 0.1)))

    if ("w_rated" in rat) == ("n_rated_rpm" in rat):
        r.fail("[ratings]: give exactly one of w_rated (rad/s electrical) and n_rated_rpm "
               "(rpm mechanical)")
    w_rated = rat["w_rated"] if "w_rated" in rat else \
        m["n_p"] * 2 * math.pi * rat["n_rated_rpm"] / 60
    for direct, rated in (("U_b", "U_rated_ll"), ("I_b", "I_rated_rms")):
        if (direct in base) == (rated in base) and base:
            r.fail(f"[base]: give exactly one of {direct} and {rated}")
    if base:
        U_b = base["U_b"] if "U_b" in base else math.sqrt(2.0 / 3.0) * base["U_rated_ll"]
        I_b = base["I_b"] if "I_b" in base else math.sqrt(2.0) * base["I_rated_rms"]
        w_b = base.get("w_b", w_rated)
    else:  # no [base]: the inverter's linear range, the current limit, the rated speed
        U_b, I_b, w_b = float(inverter.u_lim), rat["i_max"], w_rated
        notes.append(
            f"no [base] section: the per-unit bases are U_b = {U_b:.4g} V (the inverter's "
            f"linear range), I_b = {I_b:.4g} A (the current limit [ratings] i_max) and w_b = "
            f"w_rated, not the rated values docs/conventions.md names: currents in p.u. "
            f"(--i-q, --load) are fractions of {I_b:.4g} A. Add [base] I_rated_rms and "
            f"U_rated_ll (or I_b, U_b) to use the rated ones")
    bases = build("base", lambda: BaseValues(U_b=U_b, I_b=I_b, w_b=w_b, n_p=m["n_p"]))
    name = top.get("name", os.path.splitext(os.path.basename(source))[0] or "custom")
    return build("ratings", lambda: Drive(
        motor=motor, mechanics=mechanics, inverter=inverter, base=bases, w_rated=w_rated,
        tau_rated=rat["tau_rated"], i_max=rat["i_max"], name=name,
        notes=top.get("notes", ""), T_s=control.get("T_s"))), notes


def load_motor_file(path) -> Drive:
    """The `Drive` of the motor file at `path` (TOML, schema `MOTOR_FILE_SCHEMA`; a
    `[saturation] flux_map` is read from its path relative to the motor file).

    Raises `MotorFileError` (a `ValueError`) naming the file, the section and field, the
    value and the allowed range for a malformed file (and, for a bad flux map, what
    `read_flux_map` found), and `OSError` if it cannot be read.
    """
    return read_motor_file(path)[0]


def read_motor_file(path) -> tuple[Drive, list[str]]:
    """`load_motor_file(path)` and the notes a console shows with it: how the `[motor]`
    constants absent from a saturated motor file were derived (empty otherwise)."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    return _parse(text, os.fspath(path))
