"""The tuner's rule and sets widened (docs/tuning.md, "Inductance mismatch up to +-50 %"):
observers tuned with the 5 % rule, each on its paper's motor (the main job's ESO on the
default sets, L_d and L_q off by up to +-30 %, and on `TuningProblem.wide_mismatch`,
+-50 % with the validation set's +-50 % cases; the ESO also with the default's 24
training runs and with the flux loop kept as the paper's (38), only w2, zeta2 tuned; the
LESO, the AFO, the parallel-model estimator, the two peer observers and li's three
LESOs on the +-50 % sets). Each row also names the search strategies whose own
design passes the rule (the verdict judges the deployed one). For every run that blocks
the verdict, the analysis' static angle error of both designs (the principal equilibrium
of `pmsmjax.analysis.equilibria` with the run's observer model, at its final speed, under
its load with i_d = 0) beside the simulated RMS angle errors: whether the inductance
error's static error explains the run.

Writes docs/figures/wide_mismatch.json and the table between the page's
`<!-- wide mismatch -->` markers (`--from-json`: only the table, from the JSON; `--only
N ...`: measure only those rows, by their number in `CONFIGS`, and keep the others'
saved measurement, each row with its own date). About 50 minutes on a 2-core machine:

    .venv/bin/python docs/figures/measure_wide_mismatch.py
"""

import argparse
import json
import math
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from _page import markdown_table, write_block

import pmsmjax as pj
import tuning as tg
from tuning.scenarios import observer_model


HERE = os.path.dirname(os.path.abspath(__file__))
PAGE = os.path.join(HERE, os.pardir, "tuning.md")
BEGIN, END = "<!-- wide mismatch -->", "<!-- /wide mismatch -->"
#: (label, problem) of each row: the main job's observer (the ESO) first, then the LESO
#: (the two whose flux loop the tuner moves along (38)'s shape) on the same sets, then
#: the other families whose default verdict holds, each on its paper's motor.
CONFIGS = (
    ("ESO, +-30 % sets (default)", lambda: tg.TuningProblem(regression_tol=0.05)),
    ("ESO, +-50 % sets", lambda: tg.TuningProblem.wide_mismatch(regression_tol=0.05)),
    ("ESO, +-50 % sets, 24 training runs (the default's number)",
     lambda: tg.TuningProblem.wide_mismatch(regression_tol=0.05, n_train=24)),
    ("ESO, +-50 % sets, flux loop kept as (38): `--tune w2 zeta2`",
     lambda: tg.TuningProblem.wide_mismatch(regression_tol=0.05, tune=("w2", "zeta2"))),
    ("LESO, +-50 % sets",
     lambda: tg.TuningProblem.wide_mismatch(regression_tol=0.05, observer="leso")),
    ("AFO, +-50 % sets",
     lambda: tg.TuningProblem.wide_mismatch(regression_tol=0.05, observer="afo")),
    ("parallel-model (stumper_mt5), +-50 % sets",
     lambda: tg.TuningProblem.wide_mismatch(regression_tol=0.05, observer="parallel-model")),
    ("reduced-order (morawiec_ipm3k5), +-50 % sets",
     lambda: tg.TuningProblem.wide_mismatch(regression_tol=0.05, observer="reduced-order")),
    ("nonlinear-flux, +-50 % sets",
     lambda: tg.TuningProblem.wide_mismatch(regression_tol=0.05, observer="nonlinear-flux")),
    *((f"{o} (li_dtp), +-50 % sets",
       lambda o=o: tg.TuningProblem.wide_mismatch(regression_tol=0.05, observer=o))
      for o in ("c-leso", "gi-leso", "fa-leso")),
)


def static_error_deg(space, drive, x, row) -> float:
    """The designed static angle error (deg) of design `x` (None: the paper's) in the
    validation run `row`: its observer model, final speed, and load with i_d = 0."""
    obs = space.observer(x, observer_model(drive, row["k_d"], row["k_q"], row["k_R"],
                                           row["k_psi"]))
    m = drive.three_phase_motor
    i_q = row["load_pu"] * float(drive.tau_rated) / (1.5 * float(m.n_p) * float(m.psi_f))
    eq = pj.analysis.equilibria(obs, m, row["s1"] * float(drive.w_rated),
                                jnp.array([0.0, math.copysign(i_q, row["s1"])]))
    return math.degrees(float(eq.theta[int(eq.principal)]))


def measure(label, problem) -> dict:
    t0 = time.perf_counter()
    rep = tg.tune(problem, progress=False, log=lambda msg: None)
    wall = time.perf_counter() - t0
    a = rep.accounting["validation"][rep.default]
    rows = rep.sets["validation"].table()
    rms = {k: np.asarray(rep.metrics["validation"][k].rms_deg) for k in ("paper", "tuned")}
    drive, x = problem.drive(), jnp.asarray(rep.designs["tuned"])
    blocking = []
    for b in rep.verdict.get("blocking_runs", []):
        j, r = b["run"], rows[b["run"]]
        blocking.append(dict(
            run=j, s0=r["s0"], s1=r["s1"], k_d=r["k_d"], k_q=r["k_q"], k_R=r["k_R"],
            k_psi=r["k_psi"], k_noise=r["k_noise"], rms_paper_deg=float(rms["paper"][j]),
            rms_tuned_deg=float(rms["tuned"][j]), rms_change_pct=b["rms_change_pct"],
            static_paper_deg=static_error_deg(rep.space, drive, None, r),
            static_tuned_deg=static_error_deg(rep.space, drive, x, r)))
    return dict(config=label, motor=problem.motor, date=time.strftime("%Y-%m-%d"),
                mismatch_range=list(problem.mismatch_range),
                regression_tol=problem.regression_tol, w_constraint=problem.w_constraint,
                observer=problem.observer, n_train=problem.n_train,
                design=rep.default, coordinates=dict(zip(rep.space.names,
                                                         map(float, rep.designs["tuned"]))),
                peers={k: dict(better=v["better"], worst_rms_change_pct=v["worst_rms_change_pct"],
                               new_lost_lock=v["new_lost_lock"], passes=tg.holds(v)[0])
                       for k, v in rep.accounting["validation"].items() if k in rep.searches},
                better=a["better"], n=a["n"], worst_rms_change_pct=a["worst_rms_change_pct"],
                new_lost_lock=a["new_lost_lock"], holds=bool(rep.verdict["holds"]),
                blocking=blocking, wall_s=wall)


def _span(vals, fmt="{:.2f}") -> str:
    lo, hi = (fmt.format(f(vals)) for f in (min, max))
    return lo if lo == hi else f"{lo}..{hi}"


def _passing(r: dict) -> list[str]:
    """The search strategies whose own design passes the row's rule (`tuning.holds`; the
    verdict judges the deployed one)."""
    return [k for k, v in r["peers"].items() if v["passes"]]


def table(rows: list[dict]) -> str:
    columns = [("sets", "l"), ("`better`", "r"), ("`worst_rms_change_pct`", "r"),
               ("verdict (5 %)", "l"), ("blocking runs: (k_d, k_q)", "l"),
               ("their static error paper -> tuned (deg, analysis)", "l"),
               ("strategies whose design passes", "l")]
    cells = []
    for r in rows:
        b = r["blocking"]
        cases = ", ".join(sorted({f"({x['k_d']:g}, {x['k_q']:g})" for x in b})) or "none"
        static = (f"{_span([abs(x['static_paper_deg']) for x in b])} -> "
                  f"{_span([abs(x['static_tuned_deg']) for x in b])}" if b else "")
        cells.append([r["config"], f"{r['better']}/{r['n']}",
                      f"{r['worst_rms_change_pct']:+.1f} %",
                      "holds" if r["holds"] else "does not hold", f"{len(b)}: {cases}",
                      static, ", ".join(_passing(r)) or "none"])
    return markdown_table(columns, cells)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--from-json", action="store_true",
                    help="only write the page's table from wide_mismatch.json")
    ap.add_argument("--only", type=int, nargs="+", metavar="N",
                    help=f"measure only these rows (0..{len(CONFIGS) - 1}, CONFIGS' order); "
                         "the others keep their saved measurement")
    args = ap.parse_args(argv)
    path = os.path.join(HERE, "wide_mismatch.json")
    saved = json.loads(open(path).read()) if os.path.exists(path) else None
    only = range(len(CONFIGS)) if args.only is None else args.only
    for n in only:
        if not 0 <= n < len(CONFIGS):
            raise SystemExit(f"--only {n}: rows are 0..{len(CONFIGS) - 1}")
    if args.from_json:
        rows, machine = saved["rows"], saved["machine"]
    else:
        old = {r["config"]: r for r in (saved["rows"] if saved and args.only else [])}
        for r in old.values():  # a row from before rows carried their own date and motor
            r.setdefault("date", saved.get("date"))
            r.setdefault("motor", saved.get("motor"))
        pj.runtime.configure()
        jax.config.update("jax_enable_x64", True)
        rows = []
        for n, (label, make) in enumerate(CONFIGS):
            if n not in only:
                if label not in old:
                    raise SystemExit(f"row {n} ({label}) has no saved measurement: "
                                     f"measure it too (--only ... {n})")
                rows.append(old[label])
                continue
            rows.append(measure(label, make()))
            r = rows[-1]
            print(f"{label}: {r['better']}/{r['n']}, {r['worst_rms_change_pct']:+.1f} %, "
                  f"{len(r['blocking'])} blocking, {r['wall_s']:.0f} s", flush=True)
        machine = (f"{platform.machine()}, {os.cpu_count()} cores, Python "
                   f"{platform.python_version()}")
        with open(path, "w") as f:
            json.dump(dict(machine=machine, rows=rows), f, indent=1)
    dates = sorted({r.get("date", saved and saved.get("date")) for r in rows})
    text = table(rows)
    print(text)
    stamp = f"(`docs/figures/measure_wide_mismatch.py`, {', '.join(dates)}, {machine})"
    write_block(PAGE, BEGIN, END, f"{stamp}:\n\n{text}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
