"""A held-out check the tuner never trains on: `pmsmjax simulate` itself, run as a user
runs it, with the observer's inductances off by up to +-50 %.

After the report is written, the command's default scenario (a speed ramp to 0.5 p.u.
from standstill, the start-up the command chooses, a load step to 0.5 p.u. and back) runs
on the tuned drive (`motor.toml` of the output folder) with the tuner's sampling period
and current noise, once with the paper's design and once with the deployed one
(`--design`, the gains table), at every point of `MISMATCHES`: the observer's L_d and
L_q each x0.5, x1 or x1.5 of the plant's (the matched point, four single and four joint
mismatches). The tuning sets stop at `TuningProblem.mismatch_range`; this grid reaches
further, and its scenario is not one the tuner draws. Reported beside each other in
`summary.json` (`heldout_simulate`; per run `acquired_lock` and `lost_lock`, as
`pmsmjax.lock_status` says: a start that never acquires lock has lost none) and on the
console ("no lock", "lost"); it enters no verdict, and a run
that fails (a bad input, an exception) is reported as failed with its message instead of
costing the job its report.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import pathlib
import tempfile


#: The check's (L_d, L_q) ratios, observer model / plant (-), the matched point first.
MISMATCHES = tuple(p for p in itertools.product((1.0, 0.5, 1.5), repeat=2))


def _simulate(argv: list[str]) -> dict:
    """One in-process `pmsmjax simulate` (its output folder `--out` given in `argv`); the
    run's summary.json, with the exit status."""
    from pmsmjax.cli import main

    err = io.StringIO()
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            rc = main(["simulate", *argv])
    except Exception as e:  # a check that fails must not cost the job its report
        return dict(rc=3, error=f"{type(e).__name__}: {e}")
    out = pathlib.Path(argv[argv.index("--out") + 1])
    if rc not in (0, 1) or not (out / "summary.json").exists():
        lines = err.getvalue().strip().splitlines()
        return dict(rc=rc, error=lines[-1] if lines else f"exit status {rc}")
    return dict(rc=rc, **json.loads((out / "summary.json").read_text()))


def heldout_simulate(out, problem, *, t_end: float | None = None) -> dict:
    """Run the check for the tuner's output folder `out` (its `motor.toml` and gains
    table) and `problem` (a `TuningProblem`); `t_end` (s): the runs' length (default the
    command's). Returns the table for `summary.json`."""
    out = pathlib.Path(out)
    common = ["--motor-file", str(out / "motor.toml"), "--observer", problem.observer,
              "--T-s", repr(float(problem.T_s)), "--noise", repr(float(problem.noise_std)),
              "--seed", str(int(problem.seed)), "--no-plot"]
    if t_end is not None:
        common += ["--t-end", repr(float(t_end))]
    if problem.speed_from_angle is not None:
        common += ["--speed-from-angle", repr(float(problem.speed_from_angle))]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, (k_d, k_q) in enumerate(MISMATCHES):
            row = {"L_d": k_d, "L_q": k_q}
            for label, extra in (("paper", []), ("tuned", ["--design", str(out)])):
                s = _simulate([*common, *extra, "--mismatch", f"L_d={k_d!r}", "--mismatch",
                               f"L_q={k_q!r}", "--out", f"{tmp}/{label}{k}"])
                err = s.get("angle_error_deg") or {}
                lock = s.get("lock") or {}
                row[label] = {"rms_deg": err.get("rms"), "max_abs_deg": err.get("max_abs"),
                              "acquired_lock": bool(lock.get("acquired")),
                              "lost_lock": bool(lock.get("lost")),
                              "diverged": s.get("rc") == 1, "error": s.get("error")}
            rows.append(row)
    return {"what": _what(problem, t_end),
            "mismatch": "observer model / plant ratio of L_d and L_q", "rows": rows}


def _what(problem, t_end) -> str:
    """What the check ran, for the report and the console's first line of its table."""
    return ("`pmsmjax simulate` (default scenario: ramp to 0.5 p.u., load step to 0.5 p.u. "
            f"and back{'' if t_end is None else f', {t_end:g} s'}), T_s "
            f"{float(problem.T_s):g} s, noise {float(problem.noise_std):g} A, paper's and "
            "tuned design, the observer's L_d and L_q x0.5, 1, 1.5")


def _never_locked(r: dict) -> bool:
    """The run never acquired lock (`pmsmjax.lock_status`: a start from standstill that
    never settles within 45 deg, e.g. at the angle's pi ambiguity). Such a run has lost
    nothing, so `lost_lock` alone would call it held. Rows written before this key
    existed count as acquired."""
    return not r.get("acquired_lock", True)


def heldout_text(h: dict) -> str:
    """The console's table of `heldout_simulate`'s result."""
    lines = [f"held out, never trained on: {h['what']}",
             f"{'L_d x':>6}{'L_q x':>7}{'paper RMS deg':>15}{'tuned RMS deg':>15}"
             f"{'change':>9}"]

    def cell(r):
        if r.get("error"):
            return "failed"
        if r["diverged"]:
            return "diverged"
        return f"{r['rms_deg']:.2f}" + (" no lock" if _never_locked(r) else
                                         " lost" if r["lost_lock"] else "")

    for row in h["rows"]:
        p, t = row["paper"], row["tuned"]
        # a run out of lock (lost, never acquired) or diverged: its RMS error is not an
        # angle error the observer tracks, no change to state
        gone = any(r["diverged"] or r["lost_lock"] or _never_locked(r) or r.get("error")
                   for r in (p, t))
        change = ("-" if gone or not p["rms_deg"] else
                  f"{100 * (t['rms_deg'] / p['rms_deg'] - 1):+.0f} %")
        lines.append(f"{row['L_d']:>6g}{row['L_q']:>7g}{cell(p):>15}{cell(t):>15}"
                     f"{change:>9}")
    failed = {r[k]["error"] for r in h["rows"] for k in ("paper", "tuned") if r[k].get("error")}
    lines += [f"failed: {e}" for e in sorted(failed)]
    return "\n".join(lines)
