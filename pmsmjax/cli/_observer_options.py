"""The observer of every command that runs or analyses one, for every observer of the
registry `pmsmjax.observers`: `--observer NAME`, `--observer-set NAME=VALUE` (the
observer's machine model), `--gain NAME=VALUE` (a design parameter, checked against the
class's `design_units`), `--mismatch NAME=RATIO` and the documented shorthands of the
zhang2022 observers (`--w2`/`--bandwidth`, `--zeta2`, `--schedule`, `--zeta1`, `--ratio`,
`--w1`, `--w-min`, `--fixed-at`, `--a`, `--eta`), which only translate into `--gain`
values. `observer_from_args` makes the observer (an `ObserverChoice`)."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import math

import pmsmjax as pj
from pmsmjax.observers import SensoredObserver, make_observer, observer_class, observer_names

from .._files import json_safe
from ._values import CLIError, finite_float, name_value, positive_float


#: Parameters of the observer's machine model that --observer-set and --mismatch change.
MODEL_PARAMETERS = {"R_s": "Ohm", "L_d": "H", "L_q": "H", "psi_f": "V s"}

#: The zhang2022 shorthands: option dest -> (option, design parameter, factor).
_SHORTHANDS = {
    "w2": ("--w2", "w2", 1.0),
    "bandwidth": ("--bandwidth", "w2", 2 * math.pi),
    "zeta2": ("--zeta2", "zeta2", 1.0),
    "zeta1": ("--zeta1", "zeta1", 1.0),
    "ratio": ("--ratio", "ratio", 1.0),
    "w1": ("--w1", "w1", 1.0),
    "w_min": ("--w-min", "w_min", 1.0),
    "a": ("--a", "a", 1.0),
    "eta": ("--eta", "eta", 1.0),
}
_SCHEDULE_OPTIONS = {"zhang38": (), "fixed_ratio": ("zeta1", "ratio"),
                     "fixed_w1": ("zeta1", "w1", "w_min")}


def _observer_classes(sensored: bool) -> dict:
    out = {"sensored": SensoredObserver} if sensored else {}
    out.update({name: observer_class(name) for name in observer_names()})
    return out


def _design_list(classes: dict) -> str:
    return "; ".join(f"{name}: {', '.join(cls.design_units) or '(none)'}"
                     for name, cls in classes.items())


def add_observer_options(parser: argparse.ArgumentParser, *, default: str,
                         sensored: bool = False, mismatch: bool = False,
                         flux: str | None = "one", fixed_at: bool = True,
                         scheduled: bool = False, default_note: str = "") -> None:
    """`--observer` (choices: the registry, plus `sensored` with `sensored=True`),
    `--observer-set`, `--gain`, with `mismatch` the `--mismatch NAME=RATIO` ratios, and the
    zhang2022 shorthands; with `scheduled` also `--scheduled`. `flux`: `"one"` (`--schedule`,
    `--zeta1`, `--ratio`, `--w1`, `--w-min` as single values), `"grid"` (the caller adds
    `--zeta1`/`--ratio` as map axes) or None."""
    classes = _observer_classes(sensored)
    g = parser.add_argument_group(
        "observer (any observer of the registry pmsmjax.observers; design and machine model)")
    g.add_argument("--observer", default=default, choices=tuple(classes), metavar="NAME",
                   help=f"position/speed observer, one of {', '.join(classes)} (default: "
                        f"%(default)s{default_note}); its gains follow its paper's default "
                        "design for the drive unless --gain changes them")
    g.add_argument("--observer-set", dest="observer_set", action="append", default=[],
                   type=name_value, metavar="NAME=VALUE",
                   help="replace a parameter of the observer's machine model (SI units; "
                        "observer-model mismatch), repeatable: "
                        + ", ".join(f"{k} ({u})" for k, u in MODEL_PARAMETERS.items())
                        + ". Example: --observer-set L_q=0.012. Default: the plant's "
                          "(after --set)")
    g.add_argument("--gain", action="append", default=[], type=name_value,
                   metavar="NAME=VALUE",
                   help="set a design parameter of the observer (SI units, as its class's "
                        "design_units), repeatable. Names by observer: "
                        + _design_list(classes))
    if scheduled:
        g.add_argument("--scheduled", action="store_true",
                       help="schedule the observer's machine model on the motor's magnetic "
                            "model (a saturated motor: its motor file's [saturation] or a "
                            "preset such as ipm3k5_sat): at every step its L_d, L_q and "
                            "psi_f are the apparent values at the measured current "
                            "(AbstractObserver.with_magnetic), replacing those of "
                            "--observer-set/--mismatch; its gains stay those of its constant "
                            "model. Default: the constant model, as a drive deploys it")
    if mismatch:
        g.add_argument("--mismatch", action="append", default=[], type=name_value,
                       metavar="NAME=RATIO",
                       help="observer-model mismatch, repeatable: the observer's model, "
                            "from which its gains are computed, has NAME = RATIO x the "
                            "plant's NAME (-, > 0; default 1 = matched), for NAME in "
                            + ", ".join(MODEL_PARAMETERS) + ". Example: --mismatch "
                            "L_q=1.3. The same as --observer-set NAME=RATIO*plant value "
                            "(give one of the two)")
    z = parser.add_argument_group(
        "zhang2022 observers (eso, leso, afo): shorthands for --gain")
    bw = z.add_mutually_exclusive_group()
    bw.add_argument("--w2", type=positive_float, default=None, metavar="RAD_S",
                    help="speed/angle natural frequency zhang2022 (25), the observer "
                         "bandwidth (rad/s, > 0; default 2 pi 50 = 314.2): --gain w2=RAD_S")
    bw.add_argument("--bandwidth", type=positive_float, default=None, metavar="HZ",
                    help="the same in Hz: --gain w2=2*pi*HZ (default 50)")
    z.add_argument("--zeta2", type=positive_float, default=None, metavar="Z",
                   help="damping ratio of the speed/angle poles zhang2022 (25) (-, > 0; "
                        "default 1): --gain zeta2=Z")
    if flux == "one":
        z.add_argument("--schedule", default=None, choices=tuple(_SCHEDULE_OPTIONS),
                       help="flux-gain schedule: zhang38 = zhang2022 (38), zeta1 = 1.5 + "
                            "|w0|/w_rated, w1 = 1.5 |w0| / zeta1 (the default); fixed_ratio "
                            "(--zeta1, --ratio: w1 = ratio |w0|); fixed_w1 (--zeta1, --w1, "
                            "--w-min). Implied by the options given when left out")
        z.add_argument("--zeta1", type=positive_float, default=None, metavar="Z",
                       help="damping ratio of the flux poles zhang2022 (17) (-, > 0): "
                            "--gain zeta1=Z; with --ratio the fixed-ratio design, with --w1 "
                            "and --w-min the fixed-w1 one")
        z.add_argument("--ratio", type=positive_float, default=None, metavar="R",
                       help="w1 / |w0| (-, > 0; 0 would leave a continuum of equilibria): "
                            "--gain ratio=R; needs --zeta1")
        z.add_argument("--w1", type=positive_float, default=None, metavar="RAD_S",
                       help="constant flux natural frequency (rad/s, > 0, fixed_w1 "
                            "schedule): --gain w1=RAD_S; needs --zeta1 and --w-min")
        z.add_argument("--w-min", dest="w_min", type=positive_float, default=None,
                       metavar="RAD_S",
                       help="clamp of |w0| in w1^2/w0 of zhang2022 (17) (rad/s, > 0, "
                            "fixed_w1 schedule): --gain w_min=RAD_S")
    if fixed_at:
        z.add_argument("--fixed-at", dest="fixed_at", type=positive_float, default=None,
                       metavar="PU",
                       help="freeze every gain at this speed (p.u. of the rated speed) and "
                            "zero current (the fixed-gain observer of zhang2022 Fig. 11)")
    z.add_argument("--a", type=finite_float, default=None, metavar="A",
                   help="fal exponent zhang2022 (9) of the eso (-, in (0, 1]; default 0.5): "
                        "--gain a=A")
    z.add_argument("--eta", type=finite_float, default=None, metavar="VS",
                   help="half-width of fal's linear zone zhang2022 (9) of the eso (V s, > 0; "
                        "default 0.05 psi_f): --gain eta=VS")


@dataclasses.dataclass(frozen=True)
class ObserverChoice:
    """The observer the options describe, and how it came about."""

    name: str
    observer: pj.AbstractObserver
    plant: pj.PMSMParams  # the drive's machine (three-phase subspace)
    gains: dict  # design parameter -> value as given (SI)
    fixed_at: float | None

    @property
    def cls(self) -> type:
        return type(self.observer)

    @property
    def mismatched(self) -> bool:
        m = self.observer.motor
        return m is not None and any(
            float(getattr(m, p)) != float(getattr(self.plant, p)) for p in MODEL_PARAMETERS)

    def model(self) -> dict:
        """The observer's machine model and its ratios to the plant's values."""
        m = self.observer.motor
        if m is None:
            return {}
        out = {f"{p}": float(getattr(m, p)) for p in MODEL_PARAMETERS}
        out.update({f"{p}_ratio": float(getattr(m, p)) / float(getattr(self.plant, p))
                    if float(getattr(self.plant, p)) else None for p in MODEL_PARAMETERS})
        out["units"] = dict(MODEL_PARAMETERS)
        return out

    def design(self) -> dict:
        """The design parameters (SI, JSON-ready), with the flux schedule when there is
        one."""
        out = {"observer": self.name, "class": self.cls.__name__}
        schedule = getattr(getattr(self.observer, "design", None), "schedule", None)
        if schedule is not None:
            out["schedule"] = schedule
        elif self.fixed_at is not None:
            out["schedule"] = "fixed"
        if self.fixed_at is not None:
            out["fixed_at_pu"] = float(self.fixed_at)
        params = json_safe(dict(self.observer.design_parameters()))
        out.update(params)
        out["units"] = {k: self.cls.design_units.get(k, "") for k in params}
        out["given"] = dict(self.gains)
        return out

    def info(self, *, design: bool = True) -> dict:
        """Name, class, (with `design`) the design, machine model, extras (JSON-ready)."""
        out = {"name": self.name, "class": self.cls.__name__}
        if design:
            out["design"] = self.design()
        return out | {"model": self.model(), "mismatch": self.mismatched,
                      "scheduled": self.observer.magnetic is not None,
                      "extras": dict(self.cls.extras)}

    def describe(self) -> str:
        """One line for the text output."""
        parts = [f"observer {self.name}"]
        if self.observer.magnetic is not None:
            parts.append("model scheduled on the flux map")
        if self.gains:
            parts.append(", ".join(f"{k} = {v:g}" for k, v in self.gains.items()))
        if self.fixed_at is not None:
            parts.append(f"gains fixed at {self.fixed_at:g} p.u.")
        m = self.observer.motor
        if m is not None and self.mismatched:
            parts.append("model " + ", ".join(
                f"{p} x {float(getattr(m, p)) / float(getattr(self.plant, p)):g}"
                for p in MODEL_PARAMETERS
                if float(getattr(m, p)) != float(getattr(self.plant, p))))
        return ", ".join(parts)


def _observer_motor(args, plant: pj.PMSMParams) -> pj.PMSMParams:
    values: dict[str, tuple[float, str]] = {}
    for name, value in args.observer_set:
        if name not in MODEL_PARAMETERS:
            raise CLIError(
                f"--observer-set {name}={value:g}: unknown parameter {name!r} of the "
                f"observer's machine model; allowed: "
                + ", ".join(f"{k} ({u})" for k, u in MODEL_PARAMETERS.items()))
        values[name] = (value, f"--observer-set {name}={value:g}")
    for p, ratio in getattr(args, "mismatch", None) or []:
        if p not in MODEL_PARAMETERS:
            raise CLIError(f"--mismatch {p}={ratio:g}: unknown parameter {p!r} of the "
                           f"observer's machine model; allowed: "
                           f"{', '.join(MODEL_PARAMETERS)}")
        if not ratio > 0:
            raise CLIError(f"--mismatch {p}={ratio:g}: RATIO must be > 0 (observer's {p} "
                           f"/ plant's {p})")
        spelled = f"--mismatch {p}={ratio:g}"
        if p in values:
            raise CLIError(
                f"{spelled} and {values[p][1]} both set the observer's {p}; allowed: "
                f"one of the two (the ratio to the plant's value, or the value in "
                f"{MODEL_PARAMETERS[p]})")
        values[p] = (ratio * float(getattr(plant, p)), spelled)
    motor = plant
    for p, (value, spelled) in values.items():
        fields = {f: getattr(motor, f) for f in type(motor).__dataclass_fields__}
        try:
            motor = type(motor)(**{**fields, p: value})
        except ValueError as e:
            raise CLIError(f"{spelled}: {e}") from None
    return motor


def _gains(args, name: str, cls: type, skip=()) -> dict:
    """The design parameters of the options: the shorthands (except the dests in `skip`),
    then `--gain`."""
    allowed = ", ".join(cls.design_units) or "none (it has no design parameters)"
    gains: dict[str, tuple[float, str]] = {}

    def put(param, value, spelled):
        if param not in cls.design_units:
            raise CLIError(f"{spelled}: the {name} observer has no design parameter "
                           f"{param!r}; allowed: {allowed}")
        if param in gains and gains[param][1] != spelled:
            raise CLIError(f"{spelled} and {gains[param][1]} both set {param}; give it once")
        gains[param] = (value, spelled)

    schedule = getattr(args, "schedule", None)
    given = {dest: getattr(args, dest, None) for dest in _SHORTHANDS if dest not in skip}
    given.update({dest: None for dest in skip})
    if schedule is not None:
        need = _SCHEDULE_OPTIONS[schedule]
        missing = [_SHORTHANDS[d][0] for d in need if given[d] is None]
        if missing:
            raise CLIError(f"--schedule {schedule} needs {' and '.join(missing)}; allowed "
                           f"schedules: zhang38 (no flux options), fixed_ratio (--zeta1, "
                           f"--ratio), fixed_w1 (--zeta1, --w1, --w-min)")
        extra = [_SHORTHANDS[d][0] for d in ("zeta1", "ratio", "w1", "w_min")
                 if given[d] is not None and d not in need]
        if extra:
            raise CLIError(f"{', '.join(extra)}: not used by --schedule {schedule} "
                           f"(it uses {', '.join(_SHORTHANDS[d][0] for d in need) or 'none'})")
        if schedule == "zhang38":
            put("w_rated", None, "--schedule zhang38")
    elif {"zeta1", "ratio", "w1", "w_min"} <= set(cls.design_units):
        flux = {d for d in ("zeta1", "ratio", "w1", "w_min") if given[d] is not None}
        if flux and flux not in ({"zeta1", "ratio"}, {"zeta1", "w1", "w_min"}):
            raise CLIError(
                f"{', '.join(f'{_SHORTHANDS[d][0]} {given[d]:g}' for d in sorted(flux))}: "
                f"give --zeta1 with "
                f"--ratio (fixed-ratio design w1 = ratio |w0|), or --zeta1 with --w1 and "
                f"--w-min (fixed-w1 design), or none of them (zhang2022 (38))")
    for dest, (opt, param, factor) in _SHORTHANDS.items():
        if given.get(dest) is not None:
            put(param, factor * given[dest], f"{opt} {given[dest]:g}")
    for param, value in getattr(args, "gain", []):
        put(param, value, f"--gain {param}={value:g}")
    return {k: v for k, (v, _) in gains.items()}


def observer_from_args(args, drive: pj.Drive, *, skip=()) -> ObserverChoice:
    """The observer of `--observer`, `--observer-set`/`--mismatch`, `--gain` and the
    shorthands, made by the registry (`pmsmjax.observers.make_observer`). `skip`: shorthand
    dests that the command uses otherwise (`feasibility`'s `zeta1`/`ratio` axes)."""
    name = args.observer
    classes = _observer_classes(sensored=(name == "sensored"))
    if name not in classes:  # argparse checks the choices; this is for direct callers
        raise CLIError(f"--observer {name}: unknown observer; allowed: "
                       f"{', '.join(classes)}")
    cls = classes[name]
    plant = drive.three_phase_motor
    motor = _observer_motor(args, plant)
    gains = _gains(args, name, cls, skip)
    if "w_rated" in gains and gains["w_rated"] is None:
        gains["w_rated"] = float(drive.w_rated)  # --schedule zhang38: the drive's rating
    fixed_at = getattr(args, "fixed_at", None)
    kw = {}
    if fixed_at is not None:
        if "fixed_at" not in inspect.signature(cls.from_drive).parameters:
            raise CLIError(f"--fixed-at {fixed_at:g}: the {name} observer cannot freeze its "
                           f"gains (its from_drive has no fixed_at); allowed with "
                           + ", ".join(n for n, c in classes.items() if "fixed_at" in
                                       inspect.signature(c.from_drive).parameters))
        kw["fixed_at"] = fixed_at
    spelled = " ".join([f"--observer {name}"] + [f"{k}={v:g}" for k, v in gains.items()])
    try:
        if name == "sensored":
            observer = SensoredObserver.from_drive(drive, motor=motor, **gains)
        else:
            observer = make_observer(name, drive, motor=motor, **gains, **kw)
    except ValueError as e:
        raise CLIError(f"{spelled}: {e}") from None
    return ObserverChoice(name=name, observer=scheduled_observer(args, observer, drive),
                          plant=plant, gains=gains, fixed_at=fixed_at)


def scheduled_observer(args, observer: pj.AbstractObserver, drive: pj.Drive):
    """`observer` scheduled on the drive's magnetic model with `--scheduled`, else itself;
    a one-line error when the motor has none or the observer is the encoder."""
    if not getattr(args, "scheduled", False):
        return observer
    magnetic = drive.three_phase_motor.magnetic
    if magnetic is None:
        raise CLIError(f"--scheduled: the motor {drive.name!r} has no magnetic model to "
                       "schedule the observer on; allowed with a saturated motor: a motor "
                       "file with a [saturation] section, or a preset such as ipm3k5_sat")
    if isinstance(observer, SensoredObserver):
        raise CLIError("--scheduled: the sensored observer (the encoder) has no machine "
                       "model; give a sensorless --observer")
    return observer.with_magnetic(magnetic)


def add_speed_from_angle_option(group, what: str = "") -> None:
    """`--speed-from-angle [HZ]` (`pmsmjax.SpeedFromAngle`), the same for every command that
    takes it; `what` ends the help (what the command does with it)."""
    group.add_argument(
        "--speed-from-angle", type=positive_float, default=None, metavar="HZ", nargs="?",
        const=pj.observers.W_TRACK_HZ,
        help="the speed of the observer's angle estimate through a type-2 tracking loop of "
             "this natural frequency (Hz; without a value "
             f"{pj.observers.W_TRACK_HZ:g} Hz) in place of the observer's own speed "
             "estimate (pmsmjax.SpeedFromAngle; a drive's practice: it keeps the AFO, "
             "rotor-flux and parallel-model observers' speed loops stable where their "
             "models are off, e.g. on a saturated machine)" + what)


def speed_from_angle_text(args) -> str:
    """What the console's first line adds for `--speed-from-angle` (empty without it)."""
    f = getattr(args, "speed_from_angle", None)
    return "" if f is None else f", speed from its angle ({f:g} Hz tracking loop)"


def with_speed_from_angle(args, observer):
    """`observer` wrapped in `SpeedFromAngle` when `--speed-from-angle` was given."""
    f = getattr(args, "speed_from_angle", None)
    return observer if f is None else pj.SpeedFromAngle(observer, w_track=2 * math.pi * f)
