"""The li observers at low speed without load (docs/tuning.md): the designs the tuner
deployed for li's C-, GI- and FA-LESO on `li_dtp`, against the paper's, on validation
runs without the load step at the low speeds. At 0.1 p.u. the default validation runs'
0.4 p.u. load step stalls even the sensored drive, so the low-speed rule judges those
runs without it (`tuning.apply_low_speed_rule`); 0.15 and 0.2 p.u. are speeds no
validation run has.

Per observer and speed: the tuner's validation cases at that speed, both signs, started
at 0.6 of it, the load step removed (`TuningProblem(val_speeds_pu=(s,),
val_load_pu=0)`); the runs the low-speed rule sets apart (none: unloaded, the sensored
drive's lowest speed is the start's), the lost runs of each design and the accounting of
`tuning.objective.accounting` at the default rule (10 %). The deployed designs come from
a family-table run (`make_family_table.py --out DIR` writes `DIR/NAME/design.json`).
**Which coordinate** (`cause`): at 0.1 p.u., the lost runs of the paper's design with one
coordinate of the deployed design taken over, and of the deployed design with one
coordinate set back to the paper's: which of the design's changes loses the slow runs.
About five minutes on two cores. Writes the tables between the page's
`<!-- unloaded low speed -->` and `<!-- low speed cause -->` markers and the rows to
`unloaded_low_speed.json` (`--from-json`: only the tables, from it).

    .venv/bin/python docs/figures/measure_unloaded_low_speed.py --designs DIR
"""

import argparse
import json
import os
import platform
import time

import numpy as np
from _page import markdown_table, write_block

import tuning
from tuning.design_space import DesignSpace
from tuning.evaluate import Evaluator
from tuning.objective import accounting
from tuning.scenarios import low_speed_runs, validation_set


HERE = os.path.dirname(os.path.abspath(__file__))
PAGE = os.path.join(HERE, os.pardir, "tuning.md")
BEGIN, END = "<!-- unloaded low speed -->", "<!-- /unloaded low speed -->"
CAUSE = "<!-- low speed cause -->", "<!-- /low speed cause -->"
OBSERVERS = ("c-leso", "gi-leso", "fa-leso")
SPEEDS_PU = (0.1, 0.15, 0.2)


def measure(name: str, coordinates: dict, speed: float) -> dict:
    problem = tuning.TuningProblem(observer=name, val_speeds_pu=(speed,), val_load_pu=0.0)
    space = DesignSpace(problem)
    sset = validation_set(problem)
    beyond, lowest = low_speed_runs(problem, sset)
    ev = Evaluator(problem, space, sset)
    m = ev.metrics(np.asarray([coordinates[k] for k in space.names]))
    acc = accounting(m, ev.reference, problem.regression_tol, beyond=beyond)
    return dict(observer=name, motor=problem.motor, speed_pu=speed, runs=sset.n,
                beyond_limit=int(beyond.sum()), lowest_speed_pu=float(np.min(lowest)),
                lost_paper=int(np.sum(ev.reference.lost_lock)),
                lost_tuned=int(np.sum(m.lost_lock)),
                mean_rms_paper_deg=float(np.mean(ev.reference.rms_deg)),
                mean_rms_tuned_deg=float(np.mean(m.rms_deg)),
                **{k: acc[k] for k in ("better", "worse", "new_lost_lock")})


def cause(name: str, coordinates: dict, speed: float = SPEEDS_PU[0]) -> dict:
    """Lost runs at `speed` (unloaded) of the paper's design with each coordinate of the
    deployed one taken over alone, and of the deployed one with each set back alone."""
    problem = tuning.TuningProblem(observer=name, val_speeds_pu=(speed,), val_load_pu=0.0)
    space = DesignSpace(problem)
    ev = Evaluator(problem, space, validation_set(problem))
    paper = dict(zip(space.names, map(float, space.paper_point())))
    tuned = {k: float(coordinates[k]) for k in space.names}
    designs = {"paper": paper, "tuned": tuned}
    for k in space.names:
        designs[f"paper, {k} tuned"] = dict(paper, **{k: tuned[k]})
        designs[f"tuned, {k} as paper"] = dict(tuned, **{k: paper[k]})
    xs = np.asarray([[d[k] for k in space.names] for d in designs.values()])
    m = ev.metrics_many(xs)
    lost = np.asarray(m.lost_lock).sum(axis=-1)
    rms = np.asarray(m.rms_deg).mean(axis=-1)
    return dict(observer=name, speed_pu=speed, runs=ev.sset.n, paper=paper, tuned=tuned,
                lost={n: int(v) for n, v in zip(designs, lost)},
                mean_rms_deg={n: float(v) for n, v in zip(designs, rms)})


def cause_table(rows: list[dict]) -> str:
    """Per observer: lost runs (mean RMS angle error, deg) of each design of `cause`."""
    def cell(r, name):
        return f"{r['lost'][name]} ({r['mean_rms_deg'][name]:.2f})"

    out = []
    for r in rows:
        one = ", ".join(f"{k} {cell(r, f'paper, {k} tuned')}" for k in r["tuned"])
        back = ", ".join(f"{k} {cell(r, f'tuned, {k} as paper')}" for k in r["tuned"])
        coords = ", ".join(f"{k} {r['paper'][k]:.4g} -> {r['tuned'][k]:.4g}"
                           for k in r["tuned"])
        out.append([f"`{r['observer']}`", coords,
                    f"{cell(r, 'paper')} -> {cell(r, 'tuned')}", one, back])
    return markdown_table(
        [("observer", "l"), ("design: paper -> deployed", "l"),
         (f"lost of {rows[0]['runs']} (mean RMS, deg): paper -> deployed", "l"),
         ("the paper's with one coordinate deployed", "l"),
         ("the deployed with one coordinate the paper's", "l")], out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--designs", metavar="DIR",
                    help="a family-table run's output folder (DIR/NAME/design.json)")
    ap.add_argument("--from-json", action="store_true",
                    help="only write the page's tables from unloaded_low_speed.json")
    args = ap.parse_args(argv)
    path = os.path.join(HERE, "unloaded_low_speed.json")
    if args.from_json:
        with open(path) as f:
            saved = json.load(f)
        rows, causes, stamp = saved["rows"], saved["cause"], saved["stamp"]
    elif args.designs is None:
        ap.error("--designs DIR is needed (or --from-json)")
    else:
        rows, causes = [], []
        for name in OBSERVERS:
            with open(os.path.join(args.designs, name, "design.json")) as f:
                coords = json.load(f)["coordinates"]
            for s in SPEEDS_PU:
                rows.append(measure(name, coords, s))
                print(rows[-1], flush=True)
            causes.append(cause(name, coords))
            print(causes[-1], flush=True)
        stamp = (f"(`docs/figures/measure_unloaded_low_speed.py`, "
                 f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, Python "
                 f"{platform.python_version()}):")
        with open(path, "w") as f:
            json.dump({"stamp": stamp, "rows": rows, "cause": causes}, f, indent=1)
            f.write("\n")
    table = markdown_table(
        [("observer", "l"), ("speed (p.u.), from 0.6 of it", "r"), ("runs", "r"),
         ("beyond the rule", "r"), ("lost lock: paper -> tuned", "l"),
         ("`new_lost_lock`", "r"), ("`better`", "r"),
         ("mean RMS: paper -> tuned (deg)", "l")],
        [[f"`{r['observer']}`", f"{r['speed_pu']:g}", str(r["runs"]),
          str(r["beyond_limit"]), f"{r['lost_paper']} -> {r['lost_tuned']}",
          str(r["new_lost_lock"]), f"{r['better']}/{r['runs'] - r['beyond_limit']}",
          f"{r['mean_rms_paper_deg']:.2f} -> {r['mean_rms_tuned_deg']:.2f}"] for r in rows])
    write_block(PAGE, BEGIN, END, f"{stamp}\n\n{table}")
    write_block(PAGE, *CAUSE, f"{stamp}\n\n{cause_table(causes)}")
    print(f"wrote {PAGE}" + ("" if args.from_json else " and unloaded_low_speed.json"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
