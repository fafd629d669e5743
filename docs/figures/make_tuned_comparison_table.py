"""The "tuned comparison" table of docs/comparison.md: on each paper's drive, the lost
runs of the paper's design, of the comparison job's own tuned design (the tuner on its
small problem) and of the design the full tuner deployed (`python -m tuning --observer
NAME`, handed over with `--tuned-from`), from the jobs' `comparison.json`.

    python docs/figures/make_tuned_comparison_table.py --jobs A/comparison.json ... \\
        --given B/comparison.json ...

`--jobs`: default comparison jobs (`pmsmjax compare --motor M`); `--given`: jobs of the
same drives with `--observers ... --tuned-from DIR ...` (one row per observer given a
design there). Where the observer's class declares a low-speed limit, "fewer" counts the
runs the low-speed rule judges (the report's `lock_comparison`). It prints the table,
writes it between the page's `<!-- tuned comparison -->` markers and the rows to
`tuned_comparison.json` beside this script.
"""

import argparse
import json
import os

from _page import markdown_table, write_block


HERE = os.path.dirname(os.path.abspath(__file__))
PAGE = os.path.join(HERE, os.pardir, "comparison.md")
BEGIN, END = "<!-- tuned comparison -->", "<!-- /tuned comparison -->"


def _load(paths: list[str]) -> dict:
    jobs = {}
    for p in paths:
        with open(p) as f:
            job = json.load(f)
        jobs[job["motor"]] = job
    return jobs


def _only(c: dict) -> str:
    """The runs lost only by the tuned design: how many, in which phases."""
    from tuning.scenarios import phase_counts

    runs = c["only_tuned"]
    if not runs:
        return "0"
    speeds = sorted({abs(w["speed_pu"]) for w in runs})
    return (f"{len(runs)} ({phase_counts(w['phase'] for w in runs)}; "
            f"{', '.join(f'{s:g}' for s in speeds)} p.u.)")


def rows(jobs: dict, given: dict) -> list[dict]:
    out = []
    for motor, g in given.items():
        names = [n for n, _ in g["config"].get("tuned_designs", [])]
        for name in names:
            c = g["observers"][name]["lock_comparison"]
            d = g["observers"][name]["designs"]
            small = jobs.get(motor, {}).get("observers", {}).get(name, {})
            small_c = small.get("lock_comparison")
            out.append(dict(
                motor=motor, observer=name, n_runs=d["paper"]["n_runs"],
                lost_paper=c["paper"], lost_small=None if small_c is None else small_c["tuned"],
                lost_full=c["tuned"], fewer=c["fewer"], why_not=c["why_not"],
                low_speed_limit_pu=c.get("low_speed_limit_pu"),
                beyond_limit=c.get("beyond_limit"), lost_paper_within=c.get("paper_within"),
                lost_full_within=c.get("tuned_within"),
                only_full=_only(c),
                static_rms_paper_deg=d["paper"]["static_rms_deg"],
                static_rms_full_deg=d["tuned"]["static_rms_deg"],
                coordinates=g["observers"][name]["tuning"]["coordinates"]))
    return out


def _within(r: dict) -> str:
    """The lost runs the low-speed rule judges (the class's declared limit; "-" where it
    declares none, and every run is judged)."""
    if r["low_speed_limit_pu"] is None:
        return "-"
    return (f"{r['lost_paper_within']}, {r['lost_full_within']} "
            f"(limit {r['low_speed_limit_pu']:g} p.u.; {r['beyond_limit']} runs beyond)")


def table(rs: list[dict]) -> str:
    columns = [("drive", "l"), ("observer", "l"),
               ("lost: paper, small-problem tuner, full tuner", "l"),
               ("within the class's low-speed limit: paper, full tuner", "l"),
               ("fewer (full tuner)", "l"), ("lost only by the full tuner's design", "l"),
               ("RMS static error: paper, full tuner (deg)", "r")]
    return markdown_table(columns, [
        [f"`{r['motor']}`", f"`{r['observer']}`",
         f"{r['lost_paper']}, {'-' if r['lost_small'] is None else r['lost_small']}, "
         f"{r['lost_full']} of {r['n_runs']}", _within(r),
         "yes" if r["fewer"] else "no", r["only_full"],
         f"{r['static_rms_paper_deg']:.2f}, {r['static_rms_full_deg']:.2f}"] for r in rs])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", nargs="+", required=True, metavar="JSON")
    ap.add_argument("--given", nargs="+", required=True, metavar="JSON")
    args = ap.parse_args(argv)
    rs = rows(_load(args.jobs), _load(args.given))
    text = table(rs)
    print(text)
    with open(os.path.join(HERE, "tuned_comparison.json"), "w") as f:
        json.dump(rs, f, indent=1)
        f.write("\n")
    write_block(PAGE, BEGIN, END, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
