r"""Gains tables: a tuned observer design as a plain lookup table a drive's firmware can use.

`python -m tuning` writes the tuned design three ways, with the same numbers (SI units):
`gains.json` (this module reads it back: `load_gains_table`), `gains.csv` (one row per
speed, header row of column names) and `gains.h` (a C header with one array per column).
`pmsmjax replay --design` and `pmsmjax simulate --design` run the observer the table
describes (`apply_gains_table`).

**Speed-scheduled designs** (zhang2022's ESO, LESO, AFO): one row per electrical speed
`w_m` (rad/s, signed, increasing, symmetric about 0) with

- the design quantities of zhang2022 Sec. III at that speed: `zeta1` (-) and `w1`
  (rad/s) of the flux poles zhang2022 (16)-(17), `zeta2` (-) and `w2` (rad/s) of the
  speed/angle poles zhang2022 (18)-(19), and `nu2`, `nu3` (-), the null-space
  components of zhang2022 (19) as multiples of the minimum-norm gain sizes
  ($n_2 = \nu_2 2\zeta_2\omega_2/|\psi_{a0}|$, $n_3 = \nu_3\omega_2^2/|\psi_{a0}|$);
- the gains themselves for the observer's nominal model at $i_{dq} = 0$ (so
  $\psi_{a0} = [\psi_f, 0]$): `G1_11`, `G1_12`, `G1_21`, `G1_22` (1/s, zhang2022 (17)),
  `g2_1`, `g2_2` (rad/s per V s) and `g3_1`, `g3_2` (rad/s^2 per V s) of zhang2022
  (25), and `k_p`, `k_i` of the AFO's speed law zhang2022 (53).

**Interpolation rule** (`INTERPOLATION`): every column is interpolated linearly in the
speed estimate $\hat\omega$ between neighbouring rows and held at the first/last row
outside the table. Firmware that recomputes the gains on line from the current (the
observer's adaptive gains, as `TabulatedDesign` does) interpolates the design columns
and applies zhang2022 (17), (25); firmware with fixed gain matrices interpolates the
gain columns, which are exact at $i_{dq} = 0$ (for a salient machine $\psi_{a0}$, and so
the gains, change with the current).

**Constant designs** (observers tuned by constant factors): the table is one row of the
observer's design parameters (`design_units`), applied with `with_design`.

**Provenance** (optional keys, all written by `python -m tuning`): `T_s` (s), the sampling
period the design was tuned and validated at (a discrete observer's poles move with it:
the gains are not valid at another period without checking); `objective`, the tuner's
objective; `verdict`, `{"holds": bool, "baseline": str, "where_not": [str, ...]}`:
whether the tuned design passed the tuner's rule against the baseline on closed-loop
validation runs (`where_not` says where it did not), optionally with `accounting`, its
counts under the names summary.json gives them (`VERDICT_COUNTS`: `n` runs, `better` /
`worse`: loss lower / higher than the baseline's by more than 0.1 %, `fraction_better`,
`worst_rms_change_pct`, `new_lost_lock`: runs losing lock that the baseline holds),
and where the low-speed rule set runs apart, `judged_speeds_pu`, the lowest and highest
final speed (p.u.) of the runs it judged: the speeds the verdict covers.
`verdict_text(verdict)` states it as counted (the tuner's last line, `gains.h`'s header
comment, `pmsmjax gains`); `speed_from_angle_Hz`, the speed the design's speed loop was
tuned on (null: the observer's own estimate; a number: the speed of its angle through a
tracking loop of that bandwidth, Hz), stated in `gains.h` (`speed_loop_text`).

A table whose verdict does not hold (or has none) is not a validated improvement:
`gains.h` then emits a compiler warning (silenced by defining
`PMSMJAX_GAINS_ACCEPT_UNVALIDATED`), and `verdict_warning(table)` gives the line the
command line prints.
"""

from __future__ import annotations

import json
import math
import os
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._plant._params import PMSMParams
from ..observers import (
    AbstractGainSchedule,
    AbstractObserver,
    eso_gains,
    gains_pi,
    observer_class,
    psi_a,
)


FORMAT = "pmsmjax-gains"
VERSION = 1
#: File names of a gains table in a tuner output folder.
GAINS_TABLE_FILES = {"json": "gains.json", "csv": "gains.csv", "c": "gains.h"}

INTERPOLATION = (
    "linear in the electrical speed estimate w_hat (rad/s) between neighbouring rows, "
    "held at the first/last row outside the table; the design columns (zeta1, w1, zeta2, "
    "w2, nu2, nu3) give the gains at any current by zhang2022 (17), (25), (53) from the "
    "observer's machine model; the gain columns are those gains at i_dq = 0")

#: Columns of a speed-scheduled table and their units.
DESIGN_COLUMNS = {"w_m": "rad/s", "zeta1": "-", "w1": "rad/s", "zeta2": "-", "w2": "rad/s",
                  "nu2": "-", "nu3": "-"}
#: The validation counts a tuner verdict may record (`verdict.accounting`; the names and
#: definitions of `tuning.objective.VOCABULARY`).
VERDICT_COUNTS = ("n", "better", "worse", "fraction_better", "worst_rms_change_pct",
                  "new_lost_lock")
#: Counts a verdict records where they apply (a table written before them has none):
#: `beyond_limit`, the validation runs the low-speed rule counts apart; `unloaded`, those
#: among the `n` it judged without their load step.
VERDICT_OPTIONAL = ("beyond_limit", "unloaded")
GAIN_COLUMNS = {"G1_11": "1/s", "G1_12": "1/s", "G1_21": "1/s", "G1_22": "1/s",
                "g2_1": "rad/s per V s", "g2_2": "rad/s per V s",
                "g3_1": "rad/s^2 per V s", "g3_2": "rad/s^2 per V s",
                "k_p": "rad/s per V s", "k_i": "rad/s^2 per V s"}


class TabulatedDesign(AbstractGainSchedule):
    r"""zhang2022's gain design tabulated over speed (the `design` of an ESO, LESO or
    AFO), interpolated as `INTERPOLATION` says.

    At electrical speed $\omega_0$ and current $i_{dq}$ the gains are
    `eso_gains(psi_a(motor, i_dq), w0, zeta1, w1, zeta2, w2, n2, n3)` with the columns
    interpolated at $\omega_0$ and $n_2 = \nu_2 2\zeta_2\omega_2/|\psi_{a0}|$,
    $n_3 = \nu_3\omega_2^2/|\psi_{a0}|$; `pi` gives zhang2022 (53) from `zeta2`, `w2`.

    **Arguments:** `w_m` (rad/s, strictly increasing, >= 2 rows), `zeta1` (-), `w1`
    (rad/s, >= 0), `zeta2` (-), `w2` (rad/s), `nu2`, `nu3` (-), one value per row.
    """

    w_m: jnp.ndarray
    zeta1: jnp.ndarray
    w1: jnp.ndarray
    zeta2: jnp.ndarray
    w2: jnp.ndarray
    nu2: jnp.ndarray
    nu3: jnp.ndarray

    def __check_init__(self):
        w = np.asarray(self.w_m, dtype=float)
        if w.ndim != 1 or w.size < 2 or np.any(~np.isfinite(w)) or np.any(np.diff(w) <= 0):
            raise ValueError("`TabulatedDesign(w_m=...)` (rad/s) must be a strictly "
                             f"increasing 1-D array of >= 2 finite speeds; got {w}.")
        for name in ("zeta1", "w1", "zeta2", "w2", "nu2", "nu3"):
            a = np.asarray(getattr(self, name), dtype=float)
            if a.shape != w.shape or np.any(~np.isfinite(a)):
                raise ValueError(f"`TabulatedDesign({name}=...)` must hold one finite value "
                                 f"per row ({w.size}); got shape {a.shape}.")
            if name in ("zeta1", "zeta2", "w2") and np.any(a <= 0):
                raise ValueError(f"`TabulatedDesign({name}=...)` must be > 0.")
            if name == "w1" and np.any(a < 0):
                raise ValueError("`TabulatedDesign(w1=...)` (rad/s) must be >= 0.")

    def values(self, w0) -> dict:
        """The design columns interpolated at electrical speed `w0` (rad/s), in the dtype
        of `w0` (a float32 observer stays float32)."""
        w0 = jnp.asarray(w0)
        dt = w0.dtype if jnp.issubdtype(w0.dtype, jnp.floating) else jnp.result_type(float)
        return {n: jnp.interp(w0.astype(dt), self.w_m.astype(dt), getattr(self, n).astype(dt))
                for n in ("zeta1", "w1", "zeta2", "w2", "nu2", "nu3")}

    def __call__(self, motor: PMSMParams, w0, i_dq):
        v = self.values(w0)
        pa = psi_a(motor, i_dq)
        pn = jnp.sqrt(jnp.sum(pa ** 2))
        n2 = v["nu2"] * 2.0 * v["zeta2"] * v["w2"] / pn
        n3 = v["nu3"] * v["w2"] ** 2 / pn
        return eso_gains(pa, w0, v["zeta1"], v["w1"], v["zeta2"], v["w2"], n2=n2, n3=n3)

    def pi(self, motor: PMSMParams, w0, i_dq):
        v = self.values(w0)
        return gains_pi(psi_a(motor, i_dq), v["zeta2"], v["w2"])


def gain_columns(schedule: AbstractGainSchedule, motor: PMSMParams, w_m) -> dict:
    """The gain columns (`GAIN_COLUMNS`) of `schedule` for the machine model `motor` at
    the speeds `w_m` (rad/s) and `i_dq = 0`, as NumPy arrays."""
    def one(w):
        i0 = jnp.zeros(2, dtype=w.dtype)
        g = schedule(motor, w, i0)
        k_p, k_i = schedule.pi(motor, w, i0)
        return jnp.stack([g.G1[0, 0], g.G1[0, 1], g.G1[1, 0], g.G1[1, 1],
                          g.g2.reshape(-1)[0], g.g2.reshape(-1)[1], g.g3.reshape(-1)[0],
                          g.g3.reshape(-1)[1], jnp.asarray(k_p, w.dtype),
                          jnp.asarray(k_i, w.dtype)])

    a = np.asarray(jax.vmap(one)(jnp.asarray(w_m, dtype=float)), dtype=float)
    return {k: a[:, j] for j, k in enumerate(GAIN_COLUMNS)}


def _provenance(T_s, objective, verdict, speed_from_angle_Hz=False) -> dict:
    """The optional provenance keys (module docstring), checked (`speed_from_angle_Hz`:
    False leaves the key out; None records the observer's own speed)."""
    out = {}
    if speed_from_angle_Hz is not False:
        out["speed_from_angle_Hz"] = _check_tracking(speed_from_angle_Hz, "gains table")
    if T_s is not None:
        if not (isinstance(T_s, int | float) and math.isfinite(T_s) and T_s > 0):
            raise ValueError(f"gains table: `T_s` (s) must be a finite number > 0; got "
                             f"{T_s!r}.")
        out["T_s"] = float(T_s)
    if objective is not None:
        out["objective"] = str(objective)
    if verdict is not None:
        out["verdict"] = _check_verdict(verdict, "gains table")
    return out


def _check_tracking(hz, source: str):
    if hz is not None and not (isinstance(hz, int | float) and not isinstance(hz, bool)
                               and math.isfinite(hz) and hz > 0):
        raise ValueError(f"{source}: `speed_from_angle_Hz` must be null (the speed loop "
                         f"on the observer's own speed) or a tracking bandwidth > 0 (Hz); "
                         f"got {hz!r}")
    return None if hz is None else float(hz)


def _check_verdict(verdict, source: str) -> dict:
    if not isinstance(verdict, dict) or not isinstance(verdict.get("holds"), bool):
        raise ValueError(f"{source}: `verdict` must be a dict with a bool `holds` (and "
                         f"optionally `baseline`, `where_not`); got {verdict!r}")
    where_not = verdict.get("where_not", [])
    if not isinstance(where_not, list | tuple) or not all(isinstance(w, str)
                                                         for w in where_not):
        raise ValueError(f"{source}: `verdict.where_not` must be a list of strings; got "
                         f"{where_not!r}")
    out = {"holds": verdict["holds"], "baseline": str(verdict.get("baseline", "")),
           "where_not": list(where_not)}
    if "accounting" in verdict:
        a = verdict["accounting"]
        if not isinstance(a, dict) or any(
                isinstance(a.get(k), bool) or not isinstance(a.get(k), int | float)
                or not math.isfinite(a[k]) for k in VERDICT_COUNTS):
            raise ValueError(f"{source}: `verdict.accounting` must give a finite number for "
                             f"each of {', '.join(VERDICT_COUNTS)}; got {a!r}")
        out["accounting"] = {k: a[k] for k in VERDICT_COUNTS}
        for k in VERDICT_OPTIONAL:
            if k not in a:
                continue
            if isinstance(a[k], bool) or not isinstance(a[k], int) or a[k] < 0:
                raise ValueError(f"{source}: `verdict.accounting.{k}` must be an integer "
                                 f">= 0; got {a[k]!r}")
            out["accounting"][k] = a[k]
    if "judged_speeds_pu" in verdict:
        r = verdict["judged_speeds_pu"]
        ok = (isinstance(r, list | tuple) and len(r) == 2
              and all(isinstance(v, int | float) and not isinstance(v, bool)
                      and math.isfinite(v) and v >= 0 for v in r) and r[0] <= r[1])
        if not ok:
            raise ValueError(f"{source}: `verdict.judged_speeds_pu` must be [lowest, highest]"
                             f", finite speeds >= 0 (p.u.) in that order; got {r!r}")
        out["judged_speeds_pu"] = [float(v) for v in r]
    return out


def verdict_text(verdict: dict | None) -> str:
    """The tuner's verdict stated as counted, one line: "holds: tuned better than the
    paper's design in 74 of 88 validation runs; worst RMS change +7.6 %; no new lost
    lock" (from `verdict.accounting`; where the low-speed rule judged runs without their
    load step, how many; where it set runs apart, how many,
    and the final speeds of the runs judged, `verdict.judged_speeds_pu`, when recorded;
    "holds (no counts recorded)" for a table that records none, "not recorded" without a
    verdict). The tuner's last line, `gains.h`'s
    header comment and `pmsmjax gains` print it."""
    if verdict is None:
        return "not recorded"
    word = "holds" if verdict["holds"] else "does NOT hold"
    a = verdict.get("accounting")
    if not a:
        return f"{word} (no counts recorded)"
    k = int(a["new_lost_lock"])
    lost = "no new lost lock" if k == 0 else f"{k} new lost lock{'s' if k > 1 else ''}"
    rule = low_speed_text(a, verdict.get("judged_speeds_pu"))
    apart = f" ({rule})" if rule else ""
    return (f"{word}: tuned better than {verdict.get('baseline') or 'the paper design'} "
            f"in {int(a['better'])} of {int(a['n'])} validation runs{apart}; worst RMS "
            f"change {a['worst_rms_change_pct']:+.1f} %; {lost}")


def low_speed_text(accounting: dict, judged_speeds_pu=None) -> str:
    """What the tuner's low-speed rule did to the validation runs a verdict counts, in the
    verdict's words: "22 of them without their load step; 2 more beyond the observer's
    low-speed limit, counted apart; the runs judged end at 0.4-0.8 p.u." (the parts that
    apply: `accounting`'s `unloaded` and `beyond_limit`, and the final speeds (p.u.) of the
    runs judged where given, after the runs set apart); "" where it did neither."""
    b, u = int(accounting.get("beyond_limit") or 0), int(accounting.get("unloaded") or 0)
    r = judged_speeds_pu
    judged = "" if r is None else f"; the runs judged end at {r[0]:g}-{r[1]:g} p.u."
    return "; ".join(([f"{u} of them without their load step"] if u else []) + (
        [f"{b} more beyond the observer's low-speed limit, counted apart{judged}"] if b
        else []))


def verdict_warning(table: dict) -> str | None:
    """`None` when the table's tuner verdict holds, else one line saying that the design
    was not validated (no verdict recorded, or where the tuned design did not beat the
    paper's)."""
    v = table.get("verdict")
    what = f"the {table.get('observer', '?')} gains table"
    if v is None:
        return (f"{what} records no tuner verdict: it is not known to beat the paper's "
                f"design on closed-loop validation")
    if v["holds"]:
        return None
    first = v["where_not"][0] if v["where_not"] else "no reason recorded"
    more = f" (and {len(v['where_not']) - 1} more)" if len(v["where_not"]) > 1 else ""
    return (f"{what} did NOT beat {v['baseline'] or 'the paper design'} on the tuner's "
            f"checks: {first}{more}; deploy it only after your own validation")


def gains_table_scheduled(observer: str, schedule: TabulatedDesign, motor: PMSMParams, *,
                    drive: str = "", notes=(), T_s: float | None = None,
                    objective: str | None = None, verdict: dict | None = None) -> dict:
    """The gains table (a JSON-ready dict) of a speed-scheduled design given as a
    `TabulatedDesign`, with the gain columns for the machine model `motor`; `T_s` (s),
    `objective` and `verdict`: the provenance keys (module docstring)."""
    cols = {"w_m": np.asarray(schedule.w_m)}
    cols.update({n: np.asarray(getattr(schedule, n)) for n in list(DESIGN_COLUMNS)[1:]})
    cols.update(gain_columns(schedule, motor, schedule.w_m))
    units = {**DESIGN_COLUMNS, **GAIN_COLUMNS}
    return {
        "format": FORMAT, "version": VERSION, "observer": observer, "kind": "scheduled",
        "drive": drive, "interpolation": INTERPOLATION,
        "observer_model": {k: float(getattr(motor, k)) for k in ("R_s", "L_d", "L_q",
                                                                 "psi_f")},
        "columns": list(units), "units": units,
        "rows": [[float(cols[c][j]) for c in units] for j in range(len(cols["w_m"]))],
        "notes": list(notes), **_provenance(T_s, objective, verdict),
    }


def gains_table_constant(observer: str, values: dict, units: dict, *, drive: str = "",
                   notes=(), T_s: float | None = None, objective: str | None = None,
                   verdict: dict | None = None, speed_from_angle_Hz=False) -> dict:
    """The gains table of a constant design: `values` `{name: value}` (SI, `units`);
    `T_s`, `objective`, `verdict` as for `gains_table_scheduled`; `speed_from_angle_Hz`:
    the speed loop the design was tuned with (None: the observer's own speed; a number:
    the speed of its angle, `SpeedFromAngle` at that bandwidth, Hz; False: not recorded)."""
    names = list(values)
    return {
        "format": FORMAT, "version": VERSION, "observer": observer, "kind": "constant",
        "drive": drive, "interpolation": "none: constant design parameters",
        "columns": names, "units": {n: units.get(n, "") for n in names},
        "rows": [[float(values[n]) for n in names]], "notes": list(notes),
        **_provenance(T_s, objective, verdict, speed_from_angle_Hz),
    }


def check_gains_table(table: dict, source: str = "gains table") -> dict:
    """Validate a gains table dict; returns it. `ValueError` naming what is wrong."""
    def fail(msg):
        raise ValueError(f"{source}: {msg}")

    if not isinstance(table, dict) or table.get("format") != FORMAT:
        fail(f"not a pmsmjax gains table (format must be {FORMAT!r})")
    if table.get("version") != VERSION:
        fail(f"version {table.get('version')!r}; this pmsmjax reads version {VERSION}")
    for key in ("observer", "kind", "columns", "rows"):
        if key not in table:
            fail(f"missing key {key!r}")
    observer_class(table["observer"])  # a registered name (ValueError lists them)
    if table["kind"] not in ("scheduled", "constant"):
        fail(f"kind {table['kind']!r}; allowed: 'scheduled', 'constant'")
    cols, rows = table["columns"], table["rows"]
    if not rows or any(len(r) != len(cols) for r in rows):
        fail(f"every row must have one value per column ({len(cols)})")
    a = np.asarray(rows, dtype=float)
    if not np.all(np.isfinite(a)):
        fail("every value must be finite")
    if table["kind"] == "scheduled":
        missing = [c for c in DESIGN_COLUMNS if c not in cols]
        if missing:
            fail(f"missing columns {', '.join(missing)}")
    elif len(rows) != 1:
        fail("a constant design has exactly one row")
    T_s = table.get("T_s")
    if T_s is not None and not (isinstance(T_s, int | float) and not isinstance(T_s, bool)
                                and math.isfinite(T_s) and T_s > 0):
        fail(f"T_s {T_s!r}; allowed: a finite sampling period > 0 (s)")
    if "verdict" in table:
        _check_verdict(table["verdict"], source)
    if "speed_from_angle_Hz" in table:
        _check_tracking(table["speed_from_angle_Hz"], source)
    return table


def load_gains_table(path) -> dict:
    """Read a gains table: `gains.json`, or a tuner output folder (or a file in it, e.g.
    `tuned_schedule.eqx`) that holds one. Returns the validated dict."""
    p = pathlib.Path(path)
    if p.is_dir():
        p = p / GAINS_TABLE_FILES["json"]
    elif p.suffix != ".json":
        p = p.parent / GAINS_TABLE_FILES["json"]
    if not p.is_file():
        raise ValueError(f"{path}: no gains table there (expected "
                         f"{GAINS_TABLE_FILES['json']}, written by `python -m tuning`)")
    try:
        table = json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{p}: not valid JSON ({e})") from None
    return check_gains_table(table, str(p))


def table_columns(table: dict) -> dict:
    """`{column: (n_rows,) array}` of a gains table."""
    a = np.asarray(table["rows"], dtype=float).reshape(len(table["rows"]), -1)
    return {c: a[:, j] for j, c in enumerate(table["columns"])}


def tabulated_design(table: dict) -> TabulatedDesign:
    """The `TabulatedDesign` of a speed-scheduled gains table."""
    c = table_columns(check_gains_table(table))
    return TabulatedDesign(**{n: jnp.asarray(c[n]) for n in DESIGN_COLUMNS})


def apply_gains_table(table: dict, observer: AbstractObserver) -> AbstractObserver:
    """`observer` (of the table's class, e.g. from `make_observer`) with the table's
    design: a speed-scheduled table replaces its gain schedule by `TabulatedDesign`,
    a constant one is applied with `with_design`."""
    check_gains_table(table)
    cls = observer_class(table["observer"])
    if type(observer) is not cls:
        raise ValueError(f"the gains table is for the {table['observer']!r} observer "
                         f"({cls.__name__}); got a {type(observer).__name__}.")
    if table["kind"] == "constant":
        return observer.with_design(**{k: float(v[0]) for k, v in
                                       table_columns(table).items()})
    if not isinstance(getattr(observer, "design", None), AbstractGainSchedule):
        raise ValueError(f"{cls.__name__} holds no gain schedule in its `design` field; a "
                         f"speed-scheduled gains table cannot be applied to it.")
    return eqx.tree_at(lambda o: o.design, observer, tabulated_design(table))


# ---------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------

def gains_csv(table: dict) -> str:
    """The CSV text: a header row of column names, then one row per speed."""
    lines = [",".join(table["columns"])]
    lines += [",".join(repr(float(x)) for x in row) for row in table["rows"]]
    return "\n".join(lines) + "\n"


def _c_name(s: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in s)


def _c_comment(s: str) -> str:
    return s.replace("*/", "* /")


def _c_string(s: str) -> str:
    return s.replace("\\", "\\\\").replace('"', "'")


def speed_loop_text(table: dict) -> str:
    """Which speed the design's speed loop was tuned on (`speed_from_angle_Hz`)."""
    hz = table.get("speed_from_angle_Hz", False)
    if hz is False:
        return "not recorded"
    if hz is None:
        return "tuned with the speed loop on the observer's own speed estimate"
    return (f"tuned with the speed loop on the speed of the observer's angle (a tracking "
            f"loop of {hz:g} Hz, SpeedFromAngle): deploy the step with it "
            f"(`pmsmjax export-c --speed-from-angle {hz:g}`)")


def gains_c_header(table: dict, prefix: str = "pmsmjax_gains") -> str:
    """A C header with the table: `#define`s for the row count and one `static const`
    array per column (`PMSMJAX_GAINS_REAL`, default `float`), units and the
    interpolation rule in comments."""
    P = prefix.upper()
    n = len(table["rows"])
    c = table_columns(table)
    T_s = table.get("T_s")
    warning = verdict_warning(table)
    out = [f"/* Gains table of the {table['observer']} observer, drive "
           f"{table.get('drive') or '(unnamed)'}, written by pmsmjax (SI units).",
           f" * Interpolation: {table['interpolation']}.",
           " * Sampling period: " + (f"{T_s:.9g} s (the gains were tuned and validated at "
                                     f"this period only)" if T_s is not None else
                                     "not recorded"),
           f" * Tuner objective: {table.get('objective') or 'not recorded'}.",
           f" * Tuner verdict: {_c_comment(verdict_text(table.get('verdict')))}.",
           *([f" * Speed loop: {speed_loop_text(table)}."] if "speed_from_angle_Hz" in
             table else []),
           *([f" * Warning: {_c_comment(warning)}."] if warning is not None else []),
           " */",
           f"#ifndef {P}_H", f"#define {P}_H", ""]
    if warning is not None:
        out += [f"#ifndef {P}_ACCEPT_UNVALIDATED",
                "#if defined(__GNUC__) || defined(__clang__)",
                f'#warning "{_c_string(warning)}"',
                "#elif defined(_MSC_VER)",
                f'#pragma message("{_c_string(warning)}")',
                "#endif", "#endif", ""]
    out += [f"#ifndef {P}_REAL", f"#define {P}_REAL float", "#endif", "",
            f"#define {P}_N_ROWS {n}",
            f"#define {P}_VERDICT_HOLDS {0 if warning is not None else 1}"]
    if T_s is not None:
        out.append(f"#define {P}_T_S {T_s:.17g} /* s */")
    if table.get("speed_from_angle_Hz") is not None:
        out.append(f"#define {P}_SPEED_FROM_ANGLE_HZ {table['speed_from_angle_Hz']:.17g}")
    out.append("")
    for name in table["columns"]:
        unit = table.get("units", {}).get(name, "")
        vals = ", ".join(f"{float(x):.9g}" for x in c[name])
        out.append(f"/* {name} ({unit or '-'}) */")
        out.append(f"static const {P}_REAL {prefix}_{_c_name(name)}[{P}_N_ROWS] = "
                   f"{{{vals}}};")
    out += ["", f"#endif /* {P}_H */", ""]
    return "\n".join(out)


def write_gains_table(table: dict, folder) -> dict:
    """Write `gains.json`, `gains.csv` and `gains.h` into `folder`; returns their paths."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    check_gains_table(table)
    paths = {k: folder / v for k, v in GAINS_TABLE_FILES.items()}
    paths["json"].write_text(json.dumps(table, indent=1, allow_nan=False) + "\n")
    paths["csv"].write_text(gains_csv(table))
    paths["c"].write_text(gains_c_header(table))
    return {k: os.fspath(v) for k, v in paths.items()}


def gains_speed_grid(w_rated: float, s_max: float, n_half: int) -> np.ndarray:
    """Signed electrical speeds `s w_rated` for `s` in `linspace(-s_max, s_max,
    2 n_half + 1)` (rad/s): the rows of a speed-scheduled table."""
    if not (math.isfinite(s_max) and s_max > 0 and n_half >= 1):
        raise ValueError(f"`gains_speed_grid`: s_max must be > 0 (p.u.) and n_half >= 1; got "
                         f"{s_max!r}, {n_half!r}.")
    return np.linspace(-s_max, s_max, 2 * n_half + 1) * float(w_rated)
