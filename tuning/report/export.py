"""The tuned design as a gains table for firmware (`pmsmjax.load_gains_table` format):
one row of the observer's design parameters (constants; zhang2022's flux schedule is
(38) with its damping and decay rate scaled, `zeta1_scale` and `decay_scale`, or for the
AFO the fixed-ratio law w1 = ratio x |w0|, which the observer evaluates at run time at
its speed estimate), with the sampling period and the tuner's verdict with its
validation counts (`VOCABULARY`, as summary.json names them); `gains.h` states them in
its header comment and warns when compiled if the verdict does not hold."""

from __future__ import annotations

import numpy as np

import pmsmjax as pj
from pmsmjax.observers import observer_class

from ..objective import BASELINE, VOCABULARY


def gains_table(report, name: str | None = None) -> dict:
    """The gains table (JSON-ready) of design `name` (default the report's default)."""
    name = report.default if name is None else name
    problem, space = report.problem, report.space
    drive = problem.drive()
    x = report.designs[name]
    values = {k: float(np.asarray(v)) for k, v in space.design(np.asarray(x)).items()}
    units = dict(observer_class(problem.observer).design_units)
    notes = [f"tuned by `python -m tuning` ({problem.search} search, CVaR objective) for "
             f"the {problem.observer} observer on drive {drive.name}; closed-loop training "
             f"runs with L_d, L_q in {problem.mismatch_range}, R_s in "
             f"{problem.resistance_range}, psi_f in {problem.flux_range} (observer / "
             f"plant); design '{name}'"]
    acc = report.accounting["validation"][name]
    verdict = {"holds": bool(report.verdict["holds"]), "baseline": BASELINE,
               "where_not": list(report.verdict["where_not"]),
               "accounting": {k: acc[k] for k in VOCABULARY}}
    if "judged_speeds_pu" in report.verdict:
        verdict["judged_speeds_pu"] = list(report.verdict["judged_speeds_pu"])
    return pj.gains_table_constant(problem.observer, values, units, drive=drive.name,
                                   notes=notes, T_s=float(problem.T_s),
                                   objective="cvar", verdict=verdict,
                                   speed_from_angle_Hz=problem.speed_from_angle)
