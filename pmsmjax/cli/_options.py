r"""Options and helpers shared by the subcommands of `pmsmjax`, each defined once.

- drive: `--motor NAME` or `--motor-file FILE`, `--set NAME=VALUE` (the plant);
- output: `--out DIR`, `--no-plot`, `--json`; the JSON helpers `json_safe`, `write_json`,
  `dumps_json` (strict JSON: non-finite numbers become null);
- operating point of the analysis commands: `--speed`/`--speed-range`, `--i-d`, `--i-q`;
- observer, for every observer of the registry `pmsmjax.observers`: `--observer NAME`,
  `--observer-set NAME=VALUE` (the observer's machine model), `--gain NAME=VALUE` (a design
  parameter, checked against the class's `design_units`), `--mismatch NAME=RATIO`
  (analysis commands) and the documented shorthands of the zhang2022 observers
  (`--w2`/`--bandwidth`, `--zeta2`, `--schedule`, `--zeta1`, `--ratio`, `--w1`, `--w-min`,
  `--fixed-at`, `--a`, `--eta`), which only translate into `--gain` values.

**One spelling and one unit per option, across `pmsmjax` and `python -m tuning`:**
angles in degrees (`--theta0 DEG`), speeds in p.u. of the rated electrical speed
(`--speed PU`, `--speeds PU ...`, `--speed0 PU`), lists as space-separated values after
a plural option (`--speeds 0.2 0.6`, `--observers eso leso`), observer-model mismatch as
ratios observer / plant (`--mismatch L_q=1.3` in simulate, replay and the analysis
commands), `--out` always a folder.

A bad value raises `CLIError` (or `argparse.ArgumentTypeError` while parsing); `main`
prints it as one line and exits with status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import inspect
import json
import math
import os
import re
import time
from collections.abc import Callable

import jax
import numpy as np

import pmsmjax as pj
from pmsmjax.observers import SensoredObserver, make_observer, observer_class, observer_names


class CLIError(Exception):
    """A user error: printed as one line, exit status 2."""


@dataclasses.dataclass(frozen=True)
class Command:
    """One subcommand: its name, help texts, `add_arguments(parser)` and `run(args) ->
    exit status`."""

    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


# ---------------------------------------------------------------------------------------
# Argument types
# ---------------------------------------------------------------------------------------

def _number(text: str, what: str = "value") -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} {text.strip()!r} is not a number") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"{what} {text.strip()!r} must be finite")
    return x


def finite_float(text: str) -> float:
    return _number(text)


def positive_float(text: str) -> float:
    x = _number(text)
    if not x > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0")
    return x


def nonneg_float(text: str) -> float:
    x = _number(text)
    if not x >= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number >= 0")
    return x


def _int_at_least(text: str, lo: int) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if n < lo:
        raise argparse.ArgumentTypeError(f"{text!r} must be an integer >= {lo}")
    return n


def positive_int(text: str) -> int:
    return _int_at_least(text, 1)


def nonneg_int(text: str) -> int:
    return _int_at_least(text, 0)


def name_value(text: str) -> tuple[str, float]:
    """`NAME=VALUE` with a finite number VALUE."""
    name, sep, value = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"{text!r} is not of the form NAME=VALUE")
    try:
        x = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"the value in {text!r} is not a number (SI units, e.g. L_q=2.7e-3)") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"the value in {text!r} must be finite")
    return name, x


def grid(*, nonneg: bool):
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


def named_grid(text: str) -> tuple[str, tuple[float, float, int]]:
    """`NAME=LO:HI:N` (a design parameter and its grid); returns `(name, (lo, hi, n))`."""
    name, sep, spec = text.partition("=")
    name = name.strip()
    if not sep or not name or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not NAME=LO:HI:N (a design parameter and N points from LO to HI "
            f"inclusive, e.g. zeta1=0:5:101)")
    try:
        return name, grid(nonneg=False)(spec)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentTypeError(f"{text!r}: {e}") from None


def grid_values(spec) -> np.ndarray:
    """The points of a parsed `LO:HI:N` grid (float64, N of them)."""
    lo, hi, n = spec
    return np.linspace(lo, hi, n)


def speed_range(text: str) -> tuple[float, float]:
    parts = text.split(":")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not LO:HI (p.u., 0 < LO < HI, e.g. "
                                         f"0.1:1)")
    lo, hi = _number(parts[0], "LO"), _number(parts[1], "HI")
    if not lo > 0:
        raise argparse.ArgumentTypeError(
            f"LO in {text!r} must be > 0 (allowed: 0 < LO < HI, p.u.): the flux gains of "
            f"the zhang2022 designs vanish at w0 = 0 (w1 is proportional to |w0| in the "
            f"ratio and zhang2022 (38) designs), so A is not Hurwitz there and no "
            f"certificate covers standstill")
    if not lo < hi:
        raise argparse.ArgumentTypeError(f"{text!r} needs LO < HI (allowed: 0 < LO < HI, "
                                         f"p.u.)")
    return lo, hi


class ListOption(argparse.Action):
    """A list option: space-separated values (`nargs="+"`), each converted by `item`;
    repeating the option adds to the list (with `groups=True` each occurrence is one
    group, a list of lists). A value with a comma is refused with the spaced form of this
    option (or of `plural`, for a one-value option, `nargs=None`) in the message."""

    def __init__(self, option_strings, dest, *, item=str, groups: bool = False,
                 plural: str | None = None, **kw):
        self.item = item
        self.groups = groups
        self.plural = plural  # the list option to suggest (for a one-value option)
        kw.setdefault("nargs", "+")
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        items = []
        for v in [values] if isinstance(values, str) else values:
            if "," in v:
                spaced = " ".join(x.strip() for x in v.split(","))
                raise argparse.ArgumentError(
                    self, f"{v!r}: give the values separated by spaces, e.g. "
                          f"{self.plural or option_string} {spaced}")
            try:
                items.append(self.item(v.strip()))
            except argparse.ArgumentTypeError as e:
                raise argparse.ArgumentError(self, str(e)) from None
            except ValueError:
                raise argparse.ArgumentError(self, f"invalid value {v.strip()!r}") from None
        cur = getattr(namespace, self.dest, None)
        cur = list(cur) if cur is not None and cur is not self.default else []
        setattr(namespace, self.dest, cur + ([items] if self.groups else items))


def add_initial_state_options(group, *, what: str, unknown: str | None = None) -> None:
    """`--theta0 DEG` and `--speed0 PU`: the initial angle and speed of `what` (the rotor,
    or the observer's estimate), in the units of every command (degrees, p.u. of the
    rated electrical speed). `unknown`: what happens when neither is given (the defaults
    are then 0). `initial_state_from_args` reads them."""
    default = f"default: {unknown}" if unknown else "default: 0"
    group.add_argument("--theta0", type=finite_float, default=None, metavar="DEG",
                       help=f"initial electrical angle of {what} (deg; {default})")
    group.add_argument("--speed0", type=finite_float, default=None, metavar="PU",
                       help=f"initial electrical speed of {what} (p.u. of the rated speed "
                            f"Drive.w_rated, any sign; {default})")


def initial_state_from_args(args, drive: pj.Drive) -> tuple[float, float]:
    """`(theta0 in rad, speed0 in rad/s)` of `--theta0 DEG` and `--speed0 PU`."""
    return (math.radians(float(args.theta0 or 0.0)),
            float(args.speed0 or 0.0) * float(drive.w_rated))


def initial_state_given(args) -> bool:
    """Whether `--theta0` or `--speed0` was given."""
    return args.theta0 is not None or args.speed0 is not None


# Let values that start with a minus sign but are not plain numbers (-1:1 or -1e-3) be
# read as values, not as unknown options; argparse's own pattern only accepts -12 and
# -1.5. (`--zeta1=-1:1` works either way.)
_NEGATIVE_VALUE = re.compile(r"^-\.?[0-9][0-9.eE+\-:]*$")


def allow_negative_values(parser: argparse.ArgumentParser) -> None:
    if hasattr(parser, "_negative_number_matcher"):
        parser._negative_number_matcher = _NEGATIVE_VALUE


# ---------------------------------------------------------------------------------------
# Drive
# ---------------------------------------------------------------------------------------

_SETTABLE = ("R_s (Ohm), L_d (H), L_q (H), psi_f (V s), n_p (pole pairs), J (kg m^2), "
             "B (N m s/rad), u_dc (V), u_max (V, peak phase), u_dt (V, the inverter's "
             "dead-time error per phase), i_dt (A, its transition width); dual three-phase "
             "machines "
             "also L_xy (H), gamma (rad)")


def add_drive_options(parser: argparse.ArgumentParser) -> None:
    """`--motor NAME` or `--motor-file FILE`, and `--set NAME=VALUE` (the plant)."""
    g = parser.add_argument_group("drive (the plant)")
    g.add_argument("--motor", default=None, choices=pj.PRESET_NAMES, metavar="NAME",
                   help=f"motor preset, one of {', '.join(pj.PRESET_NAMES)} "
                        f"(default: {DEFAULT_MOTOR} unless --motor-file is given); each "
                        "preset states its source and assumptions in summary.json")
    g.add_argument("--motor-file", dest="motor_file", default=None, metavar="FILE",
                   help="your own drive as a motor file (TOML, SI units; `pmsmjax motor "
                        "--export NAME` writes a preset as one to start from; schema in "
                        "docs/motor-file.md), instead of --motor")
    g.add_argument("--set", dest="set_params", action="append", default=[], type=name_value,
                   metavar="NAME=VALUE",
                   help=f"replace a parameter of the drive (the plant), in SI units; "
                        f"repeatable. Names: {_SETTABLE}. Example: --set J=3e-3 --set "
                        "R_s=0.9. The observer's model follows the plant unless "
                        "--observer-set (or a --mismatch option) changes it")


#: The preset used when neither --motor nor --motor-file is given.
DEFAULT_MOTOR = "zhang750"


def drive_from_args(args: argparse.Namespace) -> pj.Drive:
    """The preset of `--motor` (or the drive of `--motor-file`) with the `--set`
    replacements applied."""
    motor_file = getattr(args, "motor_file", None)
    if motor_file is not None:
        if args.motor is not None:
            raise CLIError(f"--motor {args.motor} and --motor-file {motor_file}: give one "
                           f"of the two")
        try:
            drive = pj.load_motor_file(motor_file)
        except OSError as e:
            raise CLIError(f"--motor-file {motor_file}: cannot read it ({e.strerror})"
                           ) from None
    else:
        drive = pj.preset(DEFAULT_MOTOR if args.motor is None else args.motor)
    values = dict(args.set_params)
    if values:
        try:
            drive = pj.replace_params(drive, **values)
        except ValueError as e:
            raise CLIError(f"--set: {e}") from None
    return drive


def drive_info(drive: pj.Drive, args) -> dict:
    return {
        "motor": drive.name,
        "motor_file": getattr(args, "motor_file", None),
        "preset_notes": drive.notes,
        "parameter_overrides": dict(args.set_params),
        "ratings": {"w_rated_rad_s": float(drive.w_rated), "tau_rated_Nm": float(drive.tau_rated),
                    "i_max_A": float(drive.i_max)},
        "base": {"U_b_V": float(drive.base.U_b), "I_b_A": float(drive.base.I_b),
                 "w_b_rad_s": float(drive.base.w_b), "tau_b_Nm": float(drive.base.tau_b)},
    }


def header(command: str, drive: pj.Drive, args) -> dict:
    """The first keys of every JSON report: command, version, drive."""
    return {"command": command, "pmsmjax_version": pj.__version__, **drive_info(drive, args)}


# ---------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------

def add_output_options(parser: argparse.ArgumentParser, default_out: str | None, *,
                       plot: bool = True, out_help: str | None = None):
    """`--out DIR` (required if `default_out` is None) and, with `plot`, `--no-plot`;
    returns the group."""
    g = parser.add_argument_group("output")
    if out_help is not None:
        g.add_argument("--out", default=default_out, metavar="DIR", help=out_help)
    elif default_out is None:
        g.add_argument("--out", required=True, metavar="DIR",
                       help="output directory (created if missing)")
    else:
        g.add_argument("--out", default=default_out, metavar="DIR",
                       help="output directory, created if missing (default: %(default)s)")
    if plot:
        g.add_argument("--no-plot", action="store_true", help="do not write the PNG figure")
    return g


def add_json_option(group) -> None:
    group.add_argument("--json", action="store_true",
                       help="print the result as JSON only (strict JSON: NaN becomes null) "
                            "instead of a table")


@contextlib.contextmanager
def out_dir_transaction(path: str | None):
    """Leave nothing half-written in the output folder `path` when the block fails: every
    file the block created or changed in it is removed again (and the folder itself if
    the block created it), then the exception propagates. Files that were there before and
    that the block did not touch stay, and so do the files under the folders given to
    `keep_on_failure` (a sweep's finished chunks)."""
    if not path:
        yield
        return
    existed = os.path.isdir(path)

    def snapshot():
        out = {}
        for root, _, files in os.walk(path):
            for f in files:
                q = os.path.join(root, f)
                try:
                    st = os.stat(q)
                except OSError:
                    continue
                out[q] = (st.st_mtime_ns, st.st_size)
        return out

    before = snapshot() if existed else {}
    _KEEP.clear()
    try:
        yield
    except BaseException:
        if os.path.isdir(path):
            for q, sig in snapshot().items():
                if before.get(q) != sig and not _kept(q):
                    with contextlib.suppress(OSError):
                        os.remove(q)
            for root, dirs, _ in os.walk(path, topdown=False):
                for d in dirs:
                    with contextlib.suppress(OSError):
                        os.rmdir(os.path.join(root, d))  # only empty ones
            if not existed:
                with contextlib.suppress(OSError):
                    os.rmdir(path)
        raise


#: Folders whose files a failing `out_dir_transaction` keeps (`keep_on_failure`).
_KEEP: set[str] = set()


def keep_on_failure(path: str) -> None:
    """Keep the files under `path` when the command fails or is interrupted inside
    `out_dir_transaction`: a sweep's finished chunks, which the next run resumes from."""
    _KEEP.add(os.path.abspath(path))


def _kept(path: str) -> bool:
    q = os.path.abspath(path)
    return any(q == k or q.startswith(k + os.sep) for k in _KEEP)


def prepare_out_dir(path: str) -> str:
    if os.path.exists(path) and not os.path.isdir(path):
        raise CLIError(f"--out {path!r} exists and is not a directory")
    os.makedirs(path, exist_ok=True)
    return path


def json_safe(obj):
    """`obj` as plain JSON values: NumPy/JAX scalars and arrays become numbers and lists,
    non-finite floats None (JSON has no NaN or infinity)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, bool | int | str) or obj is None:
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, np.generic | np.ndarray | jax.Array):
        a = np.asarray(obj)
        if a.dtype.kind == "b":
            return a.tolist()
        if a.dtype.kind in "iu":
            return a.tolist()
        if a.dtype.kind == "f":
            return json_safe(a.tolist())
        if a.dtype.kind in "US":
            return a.tolist()
    return obj


def write_json(path: str, obj) -> None:
    """Write `obj` as indented, strict JSON (non-finite numbers become null)."""
    with open(path, "w", encoding="utf-8") as f:
        f.write(dumps_json(obj))
        f.write("\n")


def dumps_json(obj) -> str:
    """`obj` as indented, strict JSON text (for stdout)."""
    return json.dumps(json_safe(obj), indent=2, allow_nan=False)


def compile_and_run(fn, *args, **kwargs):
    """Run the (internally jitted) function `fn` twice: the first call compiles and runs,
    the second only runs, so compile time = first - second.

    Returns `(result, compile_time_s, run_time_s)`; prints "compiling..." and timings.
    """
    print("compiling...", end=" ", flush=True)
    try:
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args, **kwargs))
        t1 = time.perf_counter()
        print(f"done in {t1 - t0:.2f} s (with one run); running...", end=" ", flush=True)
        out = jax.block_until_ready(fn(*args, **kwargs))
        t2 = time.perf_counter()
    except BaseException:
        print("failed", flush=True)
        raise
    print(f"done in {t2 - t1:.3f} s")
    return out, max(t1 - t0 - (t2 - t1), 0.0), t2 - t1


# ---------------------------------------------------------------------------------------
# Operating point of the analysis commands
# ---------------------------------------------------------------------------------------

def add_operating_point_options(parser: argparse.ArgumentParser, *, speed: str) -> None:
    """The speed and the current of the analysis commands.

    `speed` says how the speed is given: `"list"` (`--speeds PU ...`, and `--speed PU`
    repeatable), `"one"` (`--speed`, one value) or `"range"` (`--speed-range LO:HI`).
    """
    if speed not in ("list", "one", "range"):
        raise ValueError(f"speed must be 'list', 'one' or 'range'; got {speed!r}")
    allow_negative_values(parser)
    g = parser.add_argument_group("operating point")
    w0_text = ("electrical speed w0 in p.u. of the rated speed (Drive.w_rated, rad/s "
               "electrical), any sign")
    if speed == "list":
        g.add_argument("--speeds", dest="speed", action=ListOption, item=finite_float,
                       groups=True, default=None, metavar="PU",
                       help=f"{w0_text}; one or more, separated by spaces: one map per "
                            "speed, overlaid in the PNG (default: 0.5). 0 is allowed (the "
                            "ratio design's gains stay finite there, w1 = ratio |w0| = 0) "
                            "but every zhang2022 design is degenerate at standstill "
                            "(status -1)")
        g.add_argument("--speed", action=ListOption, item=finite_float, groups=True,
                       nargs=None, plural="--speeds", default=None,
                       metavar="PU", help="one speed (p.u.), as in the other commands; "
                                          "repeatable, and with --speeds")
    elif speed == "one":
        g.add_argument("--speed", type=finite_float, default=0.5, metavar="PU",
                       help=f"{w0_text}, nonzero for the zhang2022 schedules (default: "
                            "%(default)s)")
    else:
        g.add_argument("--speed-range", type=speed_range, default=(0.1, 1.0),
                       metavar="LO:HI",
                       help="speed range Omega = [LO, HI] of the certificate, p.u. of the "
                            "rated speed (electrical), 0 < LO < HI (default: 0.1:1)")
    g.add_argument("--i-d", type=finite_float, default=0.0, metavar="PU",
                   help="d-axis operating current in p.u. of the preset's base current "
                        "(Drive.base.I_b, A peak): the controlled current in the estimator "
                        "frame, as zhang2022 (34)-(35) assume (default: %(default)s)")
    g.add_argument("--i-q", type=finite_float, default=0.0, metavar="PU",
                   help="q-axis operating current, p.u. of Drive.base.I_b, estimator frame "
                        "(default: %(default)s)")


def current_from_args(args, drive: pj.Drive) -> tuple[tuple[float, float], np.ndarray]:
    """`((i_d, i_q) in p.u., the same in A)`."""
    i_pu = (float(args.i_d), float(args.i_q))
    return i_pu, np.asarray(i_pu) * float(drive.base.I_b)


def check_operating_point(observer, drive: pj.Drive, i_pu, *, speed_pu=None) -> None:
    """Reject operating points at which the observer's own design is singular (for the
    zhang2022 observers: a vanishing auxiliary flux, or standstill with w1 ~ |w0|)."""
    if not hasattr(observer, "linear_gains"):
        return  # only the zhang2022 flux observers have these singularities
    mh = observer.motor
    i0 = np.asarray(i_pu) * float(drive.base.I_b)
    dL = float(mh.L_d) - float(mh.L_q)
    psi_a0 = np.array([dL * i0[0] + float(mh.psi_f), -dL * i0[1]])
    scale = abs(float(mh.psi_f)) + abs(dL) * float(np.hypot(*i0))
    if not np.hypot(*psi_a0) > 1e-12 * scale:
        at = ("i_d != -psi_f / (L_d - L_q) = "
              f"{-float(mh.psi_f) / dL / float(drive.base.I_b):.6g} p.u." if dL else
              "psi_f > 0")
        raise CLIError(
            f"--i-d/--i-q: the auxiliary flux zhang2022 (7) of the observer's model vanishes "
            f"at i_dq = ({i_pu[0]:g}, {i_pu[1]:g}) p.u., so the gains zhang2022 (17), (25) "
            f"are infinite; allowed: any current with psi_a0 != 0, i.e. i_q != 0 or {at}")
    schedule = getattr(getattr(observer, "design", None), "schedule", None)
    if speed_pu == 0.0 and schedule in ("zhang38", "fixed_ratio"):
        raise CLIError(
            "--speed 0: at standstill w1 = ratio |w0| = 0 and the equilibria of zhang2022 "
            "(11) form a continuum (det(w0 J + G1) = w1^2 = 0), so they cannot be listed; "
            "allowed: any finite nonzero speed (p.u.), or the fixed_w1 schedule")


# ---------------------------------------------------------------------------------------
# Observer: name, machine model, design
# ---------------------------------------------------------------------------------------

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
                         default_note: str = "") -> None:
    """`--observer` (choices: the registry, plus `sensored` with `sensored=True`),
    `--observer-set`, `--gain`, with `mismatch` the `--mismatch NAME=RATIO` ratios, and the
    zhang2022 shorthands. `flux`: `"one"` (`--schedule`, `--zeta1`, `--ratio`, `--w1`, `--w-min` as
    single values), `"grid"` (the caller adds `--zeta1`/`--ratio` as map axes) or None."""
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
                      "extras": dict(self.cls.extras)}

    def describe(self) -> str:
        """One line for the text output."""
        parts = [f"observer {self.name}"]
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
    return ObserverChoice(name=name, observer=observer, plant=plant, gains=gains,
                          fixed_at=fixed_at)
