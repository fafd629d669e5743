"""What the validation runs do not judge (docs/tuning.md): the designs the tuner deployed
for li's C-, GI- and FA-LESO on `li_dtp`, against the paper's, on validation runs
without the load step at the low speeds. Every default validation run steps the load to
0.4 p.u.; at 0.1 p.u. that stalls even the sensored drive, so the low-speed rule sets
all of them apart and no judged run is slower than 0.4 p.u.

Per observer and speed: the tuner's validation cases at that speed, both signs, started
at 0.6 of it, the load step removed (`TuningProblem(val_speeds_pu=(s,),
val_load_pu=0)`); the runs the low-speed rule sets apart (none: unloaded, the sensored
drive's lowest speed is the start's), the lost runs of each design and the accounting of
`tuning.objective.accounting` at the default rule (10 %). The deployed designs come from
a family-table run (`make_family_table.py --out DIR` writes `DIR/NAME/design.json`).
About three minutes on two cores. Writes the table between the page's
`<!-- unloaded low speed -->` markers and the rows to `unloaded_low_speed.json`.

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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--designs", required=True, metavar="DIR",
                    help="a family-table run's output folder (DIR/NAME/design.json)")
    args = ap.parse_args(argv)
    rows = []
    for name in OBSERVERS:
        with open(os.path.join(args.designs, name, "design.json")) as f:
            coords = json.load(f)["coordinates"]
        for s in SPEEDS_PU:
            rows.append(measure(name, coords, s))
            print(rows[-1], flush=True)
    table = markdown_table(
        [("observer", "l"), ("speed (p.u.), from 0.6 of it", "r"), ("runs", "r"),
         ("beyond the rule", "r"), ("lost lock: paper -> tuned", "l"),
         ("`new_lost_lock`", "r"), ("`better`", "r"),
         ("mean RMS: paper -> tuned (deg)", "l")],
        [[f"`{r['observer']}`", f"{r['speed_pu']:g}", str(r["runs"]),
          str(r["beyond_limit"]), f"{r['lost_paper']} -> {r['lost_tuned']}",
          str(r["new_lost_lock"]), f"{r['better']}/{r['runs'] - r['beyond_limit']}",
          f"{r['mean_rms_paper_deg']:.2f} -> {r['mean_rms_tuned_deg']:.2f}"] for r in rows])
    stamp = (f"(`docs/figures/measure_unloaded_low_speed.py`, {time.strftime('%Y-%m-%d')}, "
             f"{platform.machine()}, Python {platform.python_version()}):")
    write_block(PAGE, BEGIN, END, f"{stamp}\n\n{table}")
    with open(os.path.join(HERE, "unloaded_low_speed.json"), "w") as f:
        json.dump({"rows": rows}, f, indent=1)
        f.write("\n")
    print(f"wrote {PAGE} and unloaded_low_speed.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
