"""The family table of docs/tuning.md ("Results for every observer family"): every
tunable observer with `python -m tuning --observer NAME` on its paper's motor and the
defaults, each in a fresh process as a user runs it; the table is written between the
page's `<!-- family table -->` markers and to docs/figures/tuning_families.json.

Run from the repository root: `python docs/figures/make_family_table.py [--out DIR]
[--observers a,b] [--speed-from-angle] [--motor NAME]` (DIR keeps each run's output;
default a temporary folder). The whole table takes about 35 minutes on a 2-core machine.
`--motor NAME` runs every family on that preset instead of its paper's motor; the table
of `--motor ipm3k5_sat` goes to docs/saturation.md (`SATURATED`) and
tuning_families_ipm3k5_sat.json.
`--observers` runs those rows again and keeps the others from the JSON; every row
carries the date it was measured, and the page says which rows are from which day."""

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

from _page import markdown_table, write_block


HERE = os.path.dirname(os.path.abspath(__file__))
PAGE = os.path.join(HERE, os.pardir, "tuning.md")
BEGIN, END = "<!-- family table -->", "<!-- /family table -->"
#: Pages of the tables of other motors (`--motor`): preset -> (page, begin, end).
SATURATED = {"ipm3k5_sat": (os.path.join(HERE, os.pardir, "saturation.md"),
                            "<!-- saturated family table -->",
                            "<!-- /saturated family table -->")}


def tunable_observers() -> list[str]:
    from pmsmjax.observers import observer_class, observer_names

    return [n for n in observer_names() if observer_class(n).tunable]


def run_one(name: str, out: str, extra: list[str]) -> dict:
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "tuning", "--observer", name, "--out", out, "--no-plot",
           "--no-progress", *extra]
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} -> exit {p.returncode}\n{p.stderr[-2000:]}")
    s = json.loads(open(os.path.join(out, "summary.json")).read())
    a = s["accounting"]["validation"]
    return dict(observer=name, motor=s["motor"], paper_rms_deg=a["mean_rms_deg_reference"],
                tuned_rms_deg=a["mean_rms_deg"], better=a["better"], n=a["n"],
                worst_rms_change_pct=a["worst_rms_change_pct"],
                lost_lock_paper=a["lost_lock_reference"], lost_lock_tuned=a["lost_lock"],
                new_lost_lock=a["new_lost_lock"], beyond_limit=a.get("beyond_limit", 0),
                unloaded=a.get("unloaded", 0),
                lost_lock_beyond=a.get("lost_lock_beyond", 0),
                lost_lock_beyond_reference=a.get("lost_lock_beyond_reference", 0),
                verdict="holds" if s["verdict"]["holds"] else "does not hold", wall_s=wall,
                date=time.strftime("%Y-%m-%d"))


def _beyond(r: dict) -> str:
    """The low-speed rule's runs: those judged without their load step (counted among the
    n; rows measured before the rule had twins have none), those set apart and their lost
    locks (paper -> tuned)."""
    b, u = r.get("beyond_limit", 0), r.get("unloaded", 0)
    apart = (f"{b} apart (lost {r['lost_lock_beyond_reference']} -> "
             f"{r['lost_lock_beyond']})" if b else "")
    return ", ".join(([f"{u} unloaded"] if u else []) + ([apart] if apart else [])) or "0"


def table(rows: list[dict]) -> str:
    columns = [("observer", "l"), ("motor", "l"), ("paper RMS (deg)", "r"),
               ("tuned RMS (deg)", "r"), ("`better`", "r"), ("`worst_rms_change_pct`", "r"),
               ("lost lock paper -> tuned (`new_lost_lock`)", "l"),
               ("low-speed rule (`unloaded`, `beyond_limit`)", "r"),
               ("verdict", "l"), ("wall", "r")]
    return markdown_table(columns, [
        [r["observer"], r["motor"], f"{r['paper_rms_deg']:.2f}", f"{r['tuned_rms_deg']:.2f}",
         f"{r['better']}/{r['n']}", f"{r['worst_rms_change_pct']:+.1f} %",
         f"{r['lost_lock_paper']} -> {r['lost_lock_tuned']} ({r['new_lost_lock']} new)",
         _beyond(r), r["verdict"], f"{r['wall_s']:.0f} s"] for r in rows])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None, help="keep each run's output here")
    ap.add_argument("--observers", default=None, help="comma-separated (default: all)")
    ap.add_argument("--speed-from-angle", action="store_true",
                    help="every run with the speed loop on the angle's speed (30 Hz); "
                         "written to tuning_families_speed_from_angle.json, page untouched")
    ap.add_argument("--motor", default=None, choices=sorted(SATURATED),
                    help="every family on this preset instead of its paper's motor")
    ap.add_argument("--from-json", action="store_true",
                    help="only write the page's table from tuning_families.json")
    args = ap.parse_args(argv)
    stem = ("tuning_families" + ("_speed_from_angle" if args.speed_from_angle else "")
            + (f"_{args.motor}" if args.motor else ""))
    path = os.path.join(HERE, stem + ".json")
    saved = json.loads(open(path).read()) if os.path.exists(path) else None
    if saved is not None:  # rows written before rows carried their date
        for r in saved["rows"]:
            r.setdefault("date", saved["date"])
    if args.from_json:
        rows, machine = saved["rows"], saved["machine"]
    else:
        names = args.observers.split(",") if args.observers else tunable_observers()
        extra = (["--speed-from-angle"] if args.speed_from_angle else []) + (
            ["--motor", args.motor] if args.motor else [])
        base = args.out or tempfile.mkdtemp(prefix="families-")
        rows = []
        for name in names:
            r = run_one(name, os.path.join(base, name), extra)
            rows.append(r)
            print(f"{name}: {r['verdict']}, {r['better']}/{r['n']}, "
                  f"{r['worst_rms_change_pct']:+.1f} %, {r['wall_s']:.0f} s", flush=True)
        machine = (f"{platform.machine()}, {os.cpu_count()} cores, Python "
                   f"{platform.python_version()}")
        if args.observers and saved is not None:  # the other rows as measured before
            new = {r["observer"]: r for r in rows}
            rows = [new.pop(r["observer"], r) for r in saved["rows"]] + list(new.values())
        with open(path, "w") as f:
            json.dump(dict(machine=machine, date=max(r["date"] for r in rows), rows=rows),
                      f, indent=1)
    text = table(rows)
    print(text)
    if not args.speed_from_angle:
        dates = sorted({r["date"] for r in rows})
        when = dates[0] if len(dates) == 1 else "; ".join(
            f"{d}: {', '.join(r['observer'] for r in rows if r['date'] == d)}" for d in dates)
        stamp = f"(`docs/figures/make_family_table.py`, {when}, {machine})"
        page, begin, end = SATURATED[args.motor] if args.motor else (PAGE, BEGIN, END)
        write_block(page, begin, end, f"{stamp}:\n\n{text}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
