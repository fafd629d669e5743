r"""The per-observer metrics of the comparison (`aggregate`) and its table,
`comparison.md` (`markdown`).

**Per-observer metrics** (`aggregate`), over the runs that kept lock (runs that lost lock
are counted and located instead, their angle error is meaningless):

- `static_worst_deg`: largest $|$`static_deg`$|$; `static_rms_deg`: RMS of `static_deg`;
- `rms_worst_deg`: largest `rms_deg`;
- `settle_worst_s`, `settle_median_s`: over the runs that settled; `n_unsettled` counts
  the others;
- `noise_median_rad_s`, `noise_worst_rad_s`;
- `lost_lock`: count, and `lost_lock_where`: the grid points (speed, load, case), each
  with `t_lost_s`, when the run lost lock (`pmsmjax.lock_status`), and `phase`, the part
  of the run that was then under way (`tuning.scenarios.PHASES`: "start", before the
  ramp; "ramp"; "steady", between the ramp and the load step; "loaded", the load step
  and after), and with
  `feasible`, the analysis's verdict at that point, and `analysis_status` (its
  `Equilibria.status`: 0 ok, 2 no equilibrium, -1 failed), when the analysis ran;
- `feasible_fraction`: the fraction of the analysis grid (the same speeds, both signs,
  loads and mismatch cases, at constant speed and the braking load's current, which
  takes the speed's sign as in the runs) where the generic analysis
  (`pmsmjax.analysis.equilibria_traced`, or the family's own route) finds the designed
  equilibrium stable and no other stable equilibrium;
- `harmonic_deg_per_pct`: the largest peak angle-error ripple per 1 % back-EMF harmonic
  (`pmsmjax.analysis.harmonic_ripple`, orders `harmonic_orders` at `harmonic_speeds_pu`,
  matched model, no load), where that analysis is available;
- `observer_us_per_step`: compute cost of one observer step (us; `pmsmjax.replay` of a
  recorded run, batch 1, best of three after compilation; in the `timing` block of the
  JSON: it is a measurement of this machine, not of the observer alone).

A metric that cannot be computed is `null` in the JSON with its reason in `flags`.

**Lost lock, tuned against paper** (`lock_comparison`, per observer in the JSON and a
section of `comparison.md`): the two designs' counts, whether the tuned design loses
fewer runs, and, where it does not, why: the runs only the tuned design loses, each
with the reason the analysis gives (no stable designed equilibrium at that point: the
design cannot hold it; or feasible there: lost on the way, in the phase of the run
each line names; or that the analysis failed at that point, status -1, which is no
verdict at all), or that the paper's design loses none. Where the observer's class
declares a low-speed limit (`low_speed_limit_pu`), the tuner's low-speed rule, fixed
before tuning, applies (`beyond_points`): the runs in which the sensored drive turns
slower than the limit are beyond the class, counted apart, and "fewer" compares the
others.
"""

from __future__ import annotations

import numpy as np

import pmsmjax as pj

from ..scenarios import phase_at, phase_counts
from .config import CASE_NAMES, DESIGNS, CompareConfig, case_label
from .points import phase_times


def aggregate(runs: dict, feas: dict | None, config: CompareConfig, grid) -> dict:
    """Per-observer metrics of one design from its per-run metrics `runs` and the
    analysis `feas` (numpy arrays over the grid, or None if not run; see the module
    docstring). Every value
    is a float, an int, a list or None with its reason in `flags`."""
    flags = {}
    lost = np.asarray(runs["lost_lock"]).reshape(-1)
    t_lost = np.asarray(runs["t_lost"]).reshape(-1)
    times = phase_times(config)
    keep = ~lost
    static = np.asarray(runs["static_deg"]).reshape(-1)[keep]
    out = {"n_runs": int(lost.size), "lost_lock": int(lost.sum())}
    where = []
    feasible = None if feas is None else np.asarray(feas["feasible"]).reshape(-1)
    status = None if feas is None else np.asarray(feas["status"]).reshape(-1)
    for j in np.nonzero(lost)[0]:
        c = int(grid["case"][j])
        where.append(dict(speed_pu=float(grid["speed_pu"][j]),
                          load_pu=float(grid["load_pu"][j]),
                          **dict(zip(CASE_NAMES, config.cases[c])),
                          t_lost_s=float(t_lost[j]),
                          phase=phase_at(float(t_lost[j]), *times)))
        if feasible is not None:
            where[-1]["feasible"] = bool(feasible[j])
            where[-1]["analysis_status"] = int(status[j])
    out["lost_lock_where"] = where

    def put(name, values, fn, why):
        v = values[np.isfinite(values)] if values.size else values
        if v.size == 0:
            out[name] = None
            flags[name] = why
        else:
            out[name] = float(fn(v))

    none_kept = "every run lost lock"
    put("static_worst_deg", static, lambda v: np.max(np.abs(v)), none_kept)
    put("static_rms_deg", static, lambda v: np.sqrt(np.mean(v ** 2)), none_kept)
    put("rms_worst_deg", np.asarray(runs["rms_deg"]).reshape(-1)[keep], np.max, none_kept)
    st = np.asarray(runs["settle_s"]).reshape(-1)[keep]
    out["n_unsettled"] = int(np.sum(~np.isfinite(st)))
    why = none_kept if st.size == 0 else "no run settled within the band"
    put("settle_worst_s", st, np.max, why)
    put("settle_median_s", st, np.median, why)
    nz = np.asarray(runs["noise_rad_s"]).reshape(-1)[keep]
    put("noise_median_rad_s", nz, np.median, none_kept)
    put("noise_worst_rad_s", nz, np.max, none_kept)
    if feas is None:
        out["feasible_fraction"] = out["analysis_failed"] = None
        flags["feasible_fraction"] = flags["analysis_failed"] = \
            "the analysis was not run (analysis = False)"
    else:
        f = np.asarray(feas["feasible"]).reshape(-1)
        out["feasible_fraction"] = float(np.mean(f))
        out["analysis_failed"] = int(np.sum(np.asarray(feas["status"]).reshape(-1) < 0))
    out["flags"] = flags
    return out


def _point(w: dict) -> tuple:
    return (w["speed_pu"], w["load_pu"]) + tuple(w[k] for k in CASE_NAMES)


def beyond_points(lowest, limit_pu: float, grid, config: CompareConfig) -> dict | None:
    """The low-speed rule on the common grid for an observer class whose declared limit
    is `limit_pu` (p.u.; `low_speed_limit_pu`): `{"limit_pu", "points"}`, the grid points
    (as `lost_lock_where` names them) where the sensored drive's lowest speed `lowest`
    (per grid point, `tuning.compare.points.sensored_point`) is below the limit; None
    where the class declares no limit (or nothing was measured)."""
    if lowest is None or not limit_pu > 0:
        return None
    lowest = np.asarray(lowest).reshape(-1)
    points = {(float(grid["speed_pu"][j]), float(grid["load_pu"][j]),
               *(float(v) for v in config.cases[int(grid["case"][j])]))
              for j in np.nonzero(lowest < limit_pu)[0]}
    return dict(limit_pu=float(limit_pu), points=points)


def lock_comparison(entry: dict, low_speed: dict | None = None) -> dict | None:
    """The tuned design's lost runs against the paper design's (module docstring), from
    one observer's entry (`entry["designs"]`); None where a design has no runs (the
    tuner was not run or failed: its reason is in that design's `flags`).

    `low_speed` (`beyond_points`): the tuner's low-speed rule, fixed before tuning, on
    the common grid. The runs at its points are beyond the observer's class and counted
    apart, as the tuner's accounting counts them (`beyond_limit`): `fewer` compares the
    lost runs within the limit (`paper_within`, `tuned_within`), and each run lost only
    by the tuned design says whether it is beyond (`beyond_limit`)."""
    d = entry.get("designs", {})
    if any(d.get(n, {}).get("lost_lock") is None for n in DESIGNS):
        return None
    paper, tuned = (d[n]["lost_lock_where"] for n in DESIGNS)
    p_at, t_at = {_point(w) for w in paper}, {_point(w) for w in tuned}
    only_tuned = [w for w in tuned if _point(w) not in p_at]
    out = dict(paper=len(paper), tuned=len(tuned), fewer=len(tuned) < len(paper),
               only_tuned=only_tuned,
               only_paper=[w for w in paper if _point(w) not in t_at])
    beyond = set() if low_speed is None else low_speed["points"]
    if low_speed is not None:
        within = [sum(_point(w) not in beyond for w in ws) for ws in (paper, tuned)]
        only_tuned = [dict(w, beyond_limit=_point(w) in beyond) for w in only_tuned]
        out.update(low_speed_limit_pu=low_speed["limit_pu"], beyond_limit=len(beyond),
                   paper_within=within[0], tuned_within=within[1],
                   fewer=within[1] < within[0], only_tuned=only_tuned)
    n_paper, n_tuned = ((out["paper_within"], out["tuned_within"]) if low_speed
                        else (len(paper), len(tuned)))
    if out["fewer"]:
        out["why_not"] = None
    elif not n_paper and not n_tuned:
        out["why_not"] = ("neither design loses a run" + (
            " within the class's low-speed limit" if low_speed else "")
            + ": none to lose fewer of")
    else:
        n = len(only_tuned)
        why = [f"{n} run{'s' if n != 1 else ''} lost only by the tuned design"]
        n_beyond = sum(bool(w.get("beyond_limit")) for w in only_tuned)
        if n_beyond:
            why.append(f"{n_beyond} of them beyond the class's low-speed limit "
                       f"({low_speed['limit_pu']:g} p.u.: a sensored drive turns slower "
                       f"there; counted apart)")
        only_tuned = [w for w in only_tuned if not w.get("beyond_limit")]
        kinds = [_analysis_kind(w) for w in only_tuned]
        for kind, text in (
                ("infeasible", "{} of them where the analysis finds no stable designed "
                               "equilibrium for it (it cannot hold that point)"),
                ("feasible", "{} where it is feasible (lost on the way, by phase: "
                             + _phase_counts(only_tuned) + ")"),
                ("failed", "{} where the analysis failed (status -1: no verdict)"),
                ("unknown", "{} without the analysis")):
            if kinds.count(kind):
                why.append(text.format(kinds.count(kind)))
        if not n_paper:
            why.append("the paper's design loses none")
        out["why_not"] = "; ".join(why)
    return out


def _lock_lines(summary: dict) -> list[str]:
    lines = []
    for name, e in summary["observers"].items():
        if "lock_comparison" not in e:
            continue
        c = e["lock_comparison"]
        if c is None:
            lines.append(f"- {name}: no tuned design to compare (its flags say why)")
            continue
        head = f"- {name}: paper {c['paper']}, tuned {c['tuned']}"
        if "low_speed_limit_pu" in c:
            head += (f" (within the class's low-speed limit of {c['low_speed_limit_pu']:g}"
                     f" p.u., {c['beyond_limit']} grid runs beyond it counted apart: paper "
                     f"{c['paper_within']}, tuned {c['tuned_within']})")
        if c["fewer"]:
            lines.append(f"{head}: fewer")
            continue
        lines.append(f"{head}: not fewer; {c['why_not']}")
        for w in c["only_tuned"]:
            lines.append(f"  - {w['speed_pu']:g} p.u., load {w['load_pu']:g}, "
                         f"{case_label(w)}; lost at {w['t_lost_s']:.3f} s ({w['phase']})"
                         + ("; beyond the class's low-speed limit" if w.get("beyond_limit")
                            else _REASONS[_analysis_kind(w)]))
    return lines


def _phase_counts(lost: list[dict]) -> str:
    """How many of the feasible points among `lost` were lost in each phase."""
    return phase_counts(w["phase"] for w in lost if _analysis_kind(w) == "feasible")


def _analysis_kind(w: dict) -> str:
    """The analysis's verdict at a lost run's grid point `w` (an entry of
    `lost_lock_where`): "feasible", "infeasible" (no stable designed equilibrium, or
    none at all: the design cannot hold the point), "failed" (status -1, a degenerate
    point: no verdict, not a physical reason) or "unknown" (the analysis did not run)."""
    if "feasible" not in w:
        return "unknown"
    if w.get("analysis_status", 0) < 0:
        return "failed"
    return "feasible" if w["feasible"] else "infeasible"


#: The report's words for each `_analysis_kind` of a run lost only by the tuned design.
_REASONS = {"unknown": "", "feasible": "; analysis: feasible",
            "infeasible": "; analysis: no stable designed equilibrium",
            "failed": "; analysis: failed at this point (status -1): no verdict"}


COLUMNS = (
    ("static_worst_deg", "worst static error (deg)", "{:.2f}"),
    ("static_rms_deg", "RMS static error (deg)", "{:.2f}"),
    ("rms_worst_deg", "worst run RMS error (deg)", "{:.2f}"),
    ("settle_worst_s", "worst settling (s)", "{:.3f}"),
    ("noise_median_rad_s", "median speed noise (rad/s)", "{:.3g}"),
    ("lost_lock", "lost lock (runs)", "{}"),
    ("feasible_fraction", "feasible (analysis)", "{:.0%}"),
    ("harmonic_deg_per_pct", "harmonic ripple (deg / %)", "{:.3g}"),
)


def _fmt(v, f):
    return "n/a" if v is None else f.format(v)


def markdown(summary: dict) -> str:
    """`comparison.md`: the table (observers as rows, paper and tuned design) and the
    definitions of the metrics."""
    c = summary["config"]
    g = summary["grid"]
    lines = [f"# Observer comparison on {summary['motor']}", "",
             f"{g['n_runs']} closed-loop, speed-controlled sensorless runs per observer and "
             f"design: speeds {', '.join(f'{s:g}' for s in g['speeds_pu'])} p.u., loads "
             f"{', '.join(f'{x:g}' for x in g['loads_pu'])} p.u. (step at 0.6 t_end), "
             f"{len(g['cases'])} observer-model mismatch cases (k_d, k_q, k_R, k_psi), "
             f"current noise {c['noise_std']:g} A, T_s = {c['T_s']:g} s, "
             f"t_end = {c['t_end']:g} s." + (
                 "" if c.get("speed_from_angle") is None else
                 f" The speed loop takes the speed of the observer's angle "
                 f"({c['speed_from_angle']:g} Hz tracking loop), in the tuning too."), "",
             "| observer | design | " + " | ".join(h for _, h, _ in COLUMNS)
             + " | observer step (us) |",
             "|---|---|" + "---|" * (len(COLUMNS) + 1)]
    for name, e in summary["observers"].items():
        cost = _fmt(e.get("observer_us_per_step"), "{:.3g}")
        for dname in DESIGNS:
            m = e["designs"].get(dname, {})
            cells = [_fmt(m.get(k), f) for k, _, f in COLUMNS]
            lines.append(f"| {name} | {dname} | " + " | ".join(cells) + f" | {cost} |")
    lines += ["", "n/a: not computed; the reason is in `flags` in comparison.json."]
    if summary["skipped"]:
        lines += ["", "Not applicable to this motor: " + "; ".join(
            f"{k} ({v})" for k, v in summary["skipped"].items())]
    lock = _lock_lines(summary)
    if lock:
        lines += ["", "## Lost lock: tuned against paper", ""] + lock
    flags = sorted({f"{n}/{d}: {k}: {v}" for n, e in summary["observers"].items()
                    for d, m in e["designs"].items() for k, v in m.get("flags", {}).items()})
    if flags:
        lines += ["", "## Flags", ""] + [f"- {f}" for f in flags]
    lines += ["", "## Definitions", "",
              f"- static error: mean angle error (true minus estimate) over the last "
              f"{pj.STATIC_WINDOW:.0%} of each run; worst = largest magnitude, RMS over the "
              f"runs that kept lock;",
              "- run RMS error: RMS of the angle error over the whole run;",
              f"- settling: from the start of the speed ramp (0.1 t_end) until the angle "
              f"error stays within {c['settle_band_deg']:g} deg of its static value;",
              "- speed noise: standard deviation of the speed-estimate error over the "
              "static window (rad/s, electrical);",
              f"- lost lock: |angle error| above {c['lock_deg']:g} deg, or a diverged or "
              "non-finite run (these runs are left out of the other columns);",
              "- feasible: fraction of the grid (constant speed and current) where the "
              "generic equilibrium analysis finds the designed equilibrium stable and no "
              "other stable equilibrium;",
              "- harmonic ripple: largest peak angle-error ripple per 1 % back-EMF "
              "harmonic (orders " + ", ".join(str(o) for o in c["harmonic_orders"])
              + ");",
              "- observer step: compute cost of one observer step (replay at batch 1, "
              "best of three; a measurement of this machine);",
              _tuned_line(c), ""]
    return "\n".join(lines)


def _tuned_line(c: dict) -> str:
    """The definitions' line on where the "tuned" designs come from."""
    given = [n for n, _ in c.get("tuned_designs", ())]
    small = (f"the existing tuner from the paper design on a small training problem "
             f"({c['tuner']}, {c['tune_steps']} steps)")
    if not given:
        return f"- tuned: {small}."
    return (f"- tuned: for {', '.join(given)}, the design a full tuning run "
            f"(`python -m tuning`) deployed (`--tuned-from`); for the others, {small}.")


__all__ = ["COLUMNS", "aggregate", "beyond_points", "lock_comparison", "markdown"]
