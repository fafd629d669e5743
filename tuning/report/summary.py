"""`summary.json` and the output folder of a tuning run.

It leads with the metric a user reads, `rms_angle_error_deg`: each validation run's RMS
angle error (deg), mean over the runs, of the paper's design and of the deployed one.
The accounting against the paper's design uses one vocabulary (`tuning.objective.
VOCABULARY`, written into the file as `vocabulary`): `accounting.SPLIT.{n, better, worse,
fraction_better, worst_rms_change_pct, new_lost_lock}`, the same names as the console
and the docs. The keys it replaced stay one release (`deprecated_keys`: old key -> new
key). Other tools also read `verdict.holds`, `verdict.statement` (the verdict as
counted) and `designs.NAME.validation_loss` (the mean per-run loss on the validation
runs the low-speed rule keeps, dimensionless; `validation_objective` and
`validation_rms_deg` over the same runs), with every search strategy (the CMA-ES peer
among them) in `designs`.
"""

from __future__ import annotations

import json
import pathlib

import numpy as np

import pmsmjax as pj
from pmsmjax.cli import json_safe, write_json

from ..objective import DEPRECATED_KEYS, VOCABULARY
from .export import gains_table


SUMMARY_FILE = "summary.json"
DESIGN_FILE = "design.json"
MOTOR_FILE = "motor.toml"
REQUIRED_KEYS = ("accounting", "verdict", "designs", "default", "problem")
SPLITS = ("train", "heldout", "validation")


def _targets(report) -> dict:
    """Simulations and wall time each strategy needed to reach 50 % and 90 % of the best
    improvement over the paper's design found by any of them (training objective)."""
    start = report.objective["train"]["paper"]
    peers = {k: r for k, r in report.searches.items() if not k.startswith("front")}
    best = min(r.value for r in peers.values())
    out = {}
    for frac in (0.5, 0.9):
        target = start - frac * (start - best)
        out[f"{int(100 * frac)}pct"] = {
            k: dict(zip(("sims", "wall_s"), r.to_reach(target))) | {"target": target}
            for k, r in peers.items()}
    return out


def summary(report) -> dict:
    """The content of summary.json (plain Python types)."""
    p, space = report.problem, report.space
    acc = report.accounting
    # the validation runs the verdict counts: those the low-speed rule keeps
    kept = {s: slice(None) for s in SPLITS}
    kept["validation"] = np.setdiff1d(np.arange(report.sets["validation"].n),
                                      report.verdict.get("low_speed_rule", {}).get("runs", []))
    designs = {}
    for name, x in report.designs.items():
        row = {f"{s}_rms_deg": float(np.mean(np.asarray(
            report.metrics[s][name].rms_deg)[kept[s]])) for s in SPLITS}
        row |= {f"{s}_objective": report.objective[s][name] for s in SPLITS}
        row |= {f"{s}_loss": float(np.mean(np.asarray(
            report.metrics[s][name].loss)[kept[s]])) for s in SPLITS}
        row["validation_lost_lock"] = int(np.sum(np.asarray(
            report.metrics["validation"][name].lost_lock)[kept["validation"]]))
        if x is None:
            row["coordinates"] = None
            row["description"] = ("the paper's published design" if name == "paper" else
                                  "the paper's design with its gains changed by 1e-9 "
                                  "(relative): the floor of the per-run rule")
        else:
            row["coordinates"] = space.as_dict(x)
            row["design"] = {k: float(np.asarray(v))
                             for k, v in space.design(np.asarray(x)).items()}
        if name in report.searches:
            r = report.searches[name]
            row["search"] = {"sims": r.sims, "wall_s": r.wall_s,
                             "train_objective": r.value}
        if name != "paper":
            row["accounting"] = {s: acc[s][name] for s in SPLITS}
        designs[name] = row
    d = report.default
    va = acc["validation"][d]
    out = dict(
        rms_angle_error_deg={
            "what": f"each validation run's RMS angle error (deg), mean over the "
                    f"{va['n']} runs",
            "paper": va["mean_rms_deg_reference"], "tuned": va["mean_rms_deg"],
            "design": d},
        observer=p.observer, motor=p.drive().name, default=d,
        baseline_label="paper design",
        verdict=report.verdict,
        accounting={s: acc[s][d] for s in SPLITS},
        vocabulary=dict(VOCABULARY),
        deprecated_keys={
            "where": "every accounting dict (accounting.SPLIT, designs.NAME.accounting."
                     "SPLIT); kept this release, removed in the next",
            "replaced_by": dict(DEPRECATED_KEYS),
            "note": "`improved` counted the runs whose loss is lower by more than the "
                    "tolerance; `better` counts those lower by more than 0.1 %. `worse` "
                    "now counts the runs whose loss is higher by more than 0.1 % (it "
                    "used the tolerance before)"},
        designs=designs,
        bounds=space.bounds_table(),
        paper_inside_bounds=space.paper_inside(),
        scenarios={s: {"n": report.sets[s].n, "runs": report.sets[s].table()}
                   for s in SPLITS},
        disjoint=report.disjoint,
        peers=_targets(report),
        histories={k: {"sims": [h[0] for h in r.history],
                       "best": [h[1] for h in r.history],
                       "wall_s": [h[2] for h in r.history]}
                   for k, r in report.searches.items()},
        problem=p.to_dict(),
        wall_time_s=report.wall_s,
        files={"design": DESIGN_FILE, "motor": MOTOR_FILE,
               "gains_table": dict(pj.GAINS_TABLE_FILES)},
        notes=[
            "Every run of every split is a closed-loop sensorless run (speed controlled "
            "on the estimate, nothing imposed); training, held-out and validation runs "
            "share no speed, mismatch value or noise key (`disjoint`).",
            "rms_angle_error_deg and designs.*.*_rms_deg: each run's RMS angle error "
            "(deg), mean over the split's runs (validation: the runs the low-speed rule "
            "keeps, `verdict.low_speed_rule`): the metric to read first.",
            "Loss of a run (dimensionless): RMS angle error / theta_unit + w_peak * smooth "
            "peak / peak_unit + w_noise * speed-estimate noise / noise_unit; "
            "designs.*.*_loss is its mean over the split's runs; *_objective the tuner's "
            "objective (dimensionless: 0.5 mean + 0.5 CVaR of the ratio to the paper "
            "design, plus the per-metric no-regression penalties), 1 + penalties for the "
            "paper design itself. Neither is in degrees.",
            "accounting: against the paper design on the same runs, in the words of "
            "`vocabulary` (better / worse: loss lower / higher by more than 0.1 %), with "
            "mean_rms_deg (the design's) and mean_rms_deg_reference (the paper design's).",
        ])
    return json_safe(out)


def write_report(report, out, *, plot: bool = True) -> dict:
    """Write summary.json, design.json, the gains table (gains.json, gains.csv,
    gains.h), the drive's motor file and (if `plot`) the figures into `out`."""
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    s = summary(report)
    write_json(out / DESIGN_FILE, {
        "observer": report.problem.observer, "name": report.default,
        "coordinates": report.space.as_dict(report.tuned),
        "design": s["designs"][report.default]["design"]}, indent=1)
    pj.write_gains_table(gains_table(report), out)
    pj.save_motor_file(report.problem.drive(), out / MOTOR_FILE)
    write_json(out / SUMMARY_FILE, s, indent=1)
    if plot:
        from .figures import plot_report

        plot_report(report, out)
    return s


def load_design(out) -> dict:
    """The deployed design of an output folder: `{name: value}` of the observer's design
    parameters (SI), as `make_observer(observer, drive, **design)` takes them."""
    return json.loads((pathlib.Path(out) / DESIGN_FILE).read_text())["design"]
