"""The "which observer for which drive" table of docs/comparison.md, from the comparison
jobs' `comparison.json` (`pmsmjax compare --motor NAME --out DIR`, one per drive).

Rule, written before the jobs ran: an observer-design pair ranks first by the runs it
loses lock in (fewer is better), then by the RMS static angle error over the runs it
keeps (smaller is better). For each drive the table gives the first three pairs and where
the observers drives already run (`PEERS`) rank: the answer to "is a paper's observer
better than what my drive runs?".

    python docs/figures/make_choice_table.py DIR1/comparison.json DIR2/comparison.json ...

It prints the markdown table and writes `observer_choice.json` beside this script (the
ranked rows of every drive).
"""

import json
import pathlib
import sys


HERE = pathlib.Path(__file__).resolve().parent
#: The observers most deployed drives run (docs/observers.md).
PEERS = ("nonlinear-flux", "reduced-order")


def ranked(job: dict) -> list[dict]:
    """Every (observer, design) of one job, best first (the module docstring's rule)."""
    rows = []
    for name, obs in job["observers"].items():
        for design, d in obs["designs"].items():
            if d.get("lost_lock") is None:  # not run (e.g. `--quick`: no tuned design)
                continue
            rows.append({"observer": name, "design": design, "lost_lock": d["lost_lock"],
                         "n_runs": d["n_runs"], "static_rms_deg": d["static_rms_deg"],
                         "static_worst_deg": d["static_worst_deg"],
                         "rms_worst_deg": d["rms_worst_deg"]})
    return sorted(rows, key=lambda r: (r["lost_lock"], r["static_rms_deg"]))


def cell(r: dict) -> str:
    return (f"`{r['observer']}` ({r['design']}): {r['lost_lock']}/{r['n_runs']} lost, "
            f"{r['static_rms_deg']:.1f} deg")


if __name__ == "__main__":
    out = {}
    lines = ["| drive | first | second | third | the peer observers: rank |",
             "|---|---|---|---|---|"]
    for path in sys.argv[1:]:
        job = json.loads(pathlib.Path(path).read_text())
        motor = job["motor"]
        rows = ranked(job)
        out[motor] = rows
        peers = "; ".join(f"{cell(r)}: {i + 1}" for i, r in enumerate(rows)
                          if r["observer"] in PEERS)
        lines.append(f"| `{motor}` | " + " | ".join(cell(r) for r in rows[:3])
                     + f" | {peers or '-'} |")
    print("\n".join(lines))
    (HERE / "observer_choice.json").write_text(json.dumps(out, indent=1) + "\n")
