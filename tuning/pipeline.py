r"""The tuner's pipeline, one stage after another:

    problem -> scenarios -> design space -> objective -> search -> report

`tune(problem)` builds the three scenario sets (`tuning.scenarios`, disjoint by
construction, checked), the design space (`tuning.design_space`), an `Evaluator` per set
(`tuning.evaluate`), runs every search strategy at the same budget of closed-loop
simulations (`tuning.search`), polishes the chosen strategy's design towards both ends of
the tracking-versus-noise front, scores every design on the held-out and validation runs
and returns a `TuningReport` (`tuning.report` turns it into files).

**The low-speed rule** (`TuningProblem.low_speed_limit_pu`, `apply_low_speed_rule`):
before any search, every run is run once in a sensored drive. A run that takes it
slower than the observer class's limit only because its load step stalls it is replaced
by its unloaded twin, which is judged like any other run (`verdict.low_speed_rule.
unloaded`, the accounting's `unloaded`); a run slower than the limit even unloaded (a
reversal, a start below it) is set apart, and the validation accounting counts the
other runs (`accounting(beyond=...)`). The same rule shapes the training and held-out
sets the search sees (`verdict.low_speed_rule.left_out`, `unloaded_search`): in runs
beyond the limit the observer loses lock chaotically, and a search pulled by them
trades the other runs for noise; the search's sets are then drawn larger, so that it
sees `n_train` and `n_heldout` runs within the rule (`search_set`).

**The rule's floor.** The paper's design is also scored with its coordinates changed by
1e-9 (relative), `paper-perturbed`: where even that fails the validation rule, the runs in
which the paper's design loses lock are chaotic (the angle error after lock loss depends
on the last digit of the gains), no design can pass a per-run rule there, and the verdict
says so.

**Which design is the default.** The strategy named by `problem.search` gives the
"tuned" design. The front designs are the gradient polish of it with the noise weight
divided and multiplied by 4. The default is the tuned design if it holds on the
validation runs (`tuning.objective.holds`), else the first front design that holds; if
none holds, the tuned design with the verdict "does not hold" and the runs that block it.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj

from .blocking import (
    END_VERDICTS,
    NOISE_FLOOR_KEYS,
    end_analysis,
    main_phase,
    noise_floor,
    phase_split,
)
from .design_space import DesignSpace
from .evaluate import Evaluator
from .objective import BASELINE, VOCABULARY, accounting, holds, judged, objective
from .problem import TuningProblem
from .scenarios import (
    ScenarioSet,
    apply_low_speed_rule,
    check_disjoint,
    judged_speeds,
    phase_at,
    phase_counts,
    search_set,
    sensored_lowest_speed,
    validation_set,
)
from .search import STRATEGIES, SearchResult, gradient_search


#: The paper's design perturbed by 1e-9 (relative): the floor of the per-run rule.
FLOOR = "paper-perturbed"
#: Noise-weight factors of the front designs (tracking end, noise end).
FRONT = {"front-tracking": 0.25, "front-quiet": 4.0}
PEERS = ("gradient", "cmaes", "hybrid", "random", "local")


@dataclasses.dataclass
class TuningReport:
    """What `tune` found (plain data and metrics; `tuning.report` writes it).

    - `problem`, `space`; `sets`: `{"train", "heldout", "validation"}` -> `ScenarioSet`;
      `disjoint`: smallest distances between the sets' values.
    - `designs`: name -> physical coordinates (`None` for "paper": the published design);
      `searches`: strategy -> `SearchResult`.
    - `metrics`: split -> design -> `Metrics`; `objective`: split -> design -> J.
    - `accounting`: split -> design -> per-metric comparison with the paper's design.
    - `default`: the design name deployed; `verdict`: `{"holds", "where_not",
      "statement", ...}` (`statement`: the verdict as counted, `pmsmjax.verdict_text`).
    - `wall_s`: total wall time (s).
    - `blocking_trace`: where the verdict fails on a run's RMS angle error, the worst
      blocking run's angle error over time for both designs (`tuning.phase_split` with
      `traces`, and its `case`: the run's row of the validation table), for the report's
      `blocking.png`; None otherwise.
    """

    problem: TuningProblem
    space: DesignSpace
    sets: dict
    disjoint: dict
    designs: dict
    searches: dict
    metrics: dict
    objective: dict
    accounting: dict
    default: str
    verdict: dict
    wall_s: float
    blocking_trace: dict | None = None

    @property
    def tuned(self):
        return self.designs[self.default]


def _say(log, msg):
    if log is not None:
        log(msg)


def tune(problem: TuningProblem, *, progress: bool = True, log=print,
         peers: tuple = PEERS) -> TuningReport:
    """Run the whole tuning job for `problem` (see the module docstring). `peers`: the
    strategies run side by side at the same budget (the chosen `problem.search` always
    runs)."""
    t_start = time.perf_counter()
    space = DesignSpace(problem)
    # the low-speed rule, before any search: a run whose load step alone takes even a
    # sensored drive below the observer's class's limit is judged without it; validation
    # runs still beyond the limit are counted apart, the search's own left out (and drawn
    # anew, so that the search sees as many runs)
    sets, searched = {}, {}
    for split in ("train", "heldout"):
        sets[split], searched[split] = search_set(problem, split)
    sets["validation"], rule = apply_low_speed_rule(problem, validation_set(problem))
    disjoint = check_disjoint(*sets.values())
    _say(log, f"tuning the {problem.observer} observer on {problem.drive().name}: "
              f"{space.n} coordinates ({', '.join(space.names)}); "
              f"{sets['train'].n} training, {sets['heldout'].n} held-out and "
              f"{sets['validation'].n} validation closed-loop runs (disjoint)"
              + ("" if problem.speed_from_angle is None else
                 f"; the speed loop on the speed of the observer's angle "
                 f"({problem.speed_from_angle:g} Hz tracking loop)"))
    beyond, unloaded = rule["beyond"], rule["unloaded"]
    limit = f"{problem.low_speed_limit_pu:g} p.u."
    if unloaded.any():
        _say(log, f"low-speed rule: {int(unloaded.sum())} of {unloaded.size} validation "
                  f"runs' load step takes a sensored drive below {limit}, the limit the "
                  f"observer's class declares: judged without their load step")
    if beyond.any():
        _say(log, f"low-speed rule: {int(beyond.sum())} of {beyond.size} validation runs "
                  f"turn slower than {limit} in a sensored drive even without their load "
                  f"step (lowest {np.nanmin(rule['lowest_pu'][beyond]):.3g} p.u.): "
                  f"counted apart")
    for split, c in searched.items():
        if c["left_out"] or c["unloaded"]:
            _say(log, f"low-speed rule: {c['unloaded']} of the {sets[split].n} {split} runs "
                      f"judged without their load step; {c['left_out']} runs left out, "
                      f"of {c['drawn']} drawn")
    evs = {k: Evaluator(problem, space, s) for k, s in sets.items()}
    ev = evs["train"]
    z0 = space.to_unconstrained(space.paper_point())
    key = jax.random.PRNGKey(problem.seed)
    strategies = tuple(dict.fromkeys((problem.search, *peers)))
    searches: dict[str, SearchResult] = {}
    for name in strategies:
        _say(log, f"search: {name} ({problem.budget} closed-loop simulations)")
        searches[name] = STRATEGIES[name](
            ev, z0, budget=problem.budget, population=problem.population, key=key,
            learning_rate=problem.learning_rate, clip_norm=problem.clip_norm,
            progress=progress)
    designs = {"paper": None}
    for name, res in searches.items():
        designs[name] = np.asarray(space.to_physical(jnp.asarray(res.z)))
    designs["tuned"] = designs[problem.search]
    z_t = searches[problem.search].z
    for name, factor in FRONT.items():
        evf = ev.with_noise_weight(problem.w_noise * factor)
        res = gradient_search(evf, z_t, budget=max(ev.cost, problem.budget // 4),
                              learning_rate=problem.learning_rate,
                              clip_norm=problem.clip_norm, progress=progress, name=name)
        designs[name] = np.asarray(space.to_physical(jnp.asarray(res.z)))
        searches[name] = res
    metrics, obj, acc = {}, {}, {}
    names = [n for n in designs if n != "paper"]
    xs = jnp.asarray(np.stack([designs[n] for n in names]))
    for split, e in evs.items():
        _say(log, f"scoring {len(names) + 1} designs on the {split} runs")
        many = e.metrics_many(xs)
        metrics[split] = {"paper": e.reference}
        apart = beyond if split == "validation" else None
        twins = unloaded if split == "validation" else None
        obj[split] = {"paper": _objective_kept(e.reference, e.reference, problem, apart)}
        acc[split] = {}
        # the rule's floor: the paper's design with its gains changed by 1e-9 (relative).
        # Where that alone fails the rule, runs that lose lock are chaotic and no design
        # can pass a per-run rule on them (a measurement, reported with the verdict)
        floor = e.perturbed_reference(1e-9)
        for i, n in enumerate([*names, FLOOR]):
            m = floor if n == FLOOR else jax.tree_util.tree_map(lambda a, i=i: a[i], many)
            metrics[split][n] = m
            obj[split][n] = _objective_kept(m, e.reference, problem, apart)
            acc[split][n] = accounting(m, e.reference, problem.regression_tol, apart,
                                       twins)
    designs[FLOOR] = None
    default, verdict = _choose(acc["validation"], sets["validation"])
    same = _paper_not_bettered(
        obj["train"], default, designs[default] is not None and bool(np.allclose(
            designs[default], np.asarray(space.paper_point()), rtol=1e-12, atol=0.0)))
    if not verdict["holds"] and same:
        verdict["where_not"].append(same)
    judged = judged_speeds(sets["validation"], beyond)
    verdict["low_speed_rule"] = {
        "limit_pu": float(problem.low_speed_limit_pu),
        "rule": LOW_SPEED_RULE, "runs": [int(j) for j in np.nonzero(beyond)[0]],
        "unloaded": [int(j) for j in np.nonzero(unloaded)[0]],
        "lowest_speed_pu": [None if np.isnan(v) else float(v) for v in rule["lowest_pu"]],
        "left_out": {k: c["left_out"] for k, c in searched.items()},
        "unloaded_search": {k: c["unloaded"] for k, c in searched.items()},
        "drawn": {k: c["drawn"] for k, c in searched.items()}}
    if judged is not None:
        # the speeds the verdict covers, where the rule sets runs apart
        verdict["judged_speeds_pu"] = list(judged)
    fa = acc["validation"][FLOOR]
    # the per-run parts of the rule (a perturbation is not meant to be better)
    floor_why = [w for w in holds(fa)[1] if not w.startswith("better in")]
    floor_ok = not floor_why
    verdict["floor"] = {"holds": floor_ok, "where_not": floor_why,
                        "worst_rms_change_pct": fa["worst_rms_change_pct"]}
    if not verdict["holds"] and not floor_ok:
        verdict["where_not"].append(
            f"blocked: the paper's own design with its gains changed by 1e-9 (relative) "
            f"already fails the rule ({'; '.join(floor_why)}): runs in which it loses lock "
            f"are chaotic, so no design passes a per-run rule on them")
    _lost_by_both(problem, space, sets["validation"], metrics["validation"], default,
                  designs[default], beyond, verdict, log)
    trace = None
    if not verdict["holds"]:
        trace = _blocking(problem, sets["validation"], metrics["validation"], verdict, log,
                          beyond, rule["sensored"], space=space, x=designs["tuned"])
    # the verdict as counted (the console's last line, gains.h, `pmsmjax gains`)
    a = acc["validation"][default]
    verdict["statement"] = pj.verdict_text({
        "holds": verdict["holds"], "baseline": BASELINE,
        "accounting": {k: a[k] for k in VOCABULARY},
        **({"judged_speeds_pu": list(judged)} if judged is not None else {})})
    return TuningReport(problem=problem, space=space, sets=sets, disjoint=disjoint,
                        designs=designs, searches=searches, metrics=metrics,
                        objective=obj, accounting=acc, default=default, verdict=verdict,
                        wall_s=time.perf_counter() - t_start, blocking_trace=trace)


def _paper_not_bettered(obj_train: dict, default: str, same_point: bool = False) -> str | None:
    """Where the deployed design is no better than the paper's on the training runs (the
    searches keep the best design they evaluate, the paper's among them), the verdict's
    reason: the design deployed is the paper's own, to round-off. `same_point`: its
    coordinates are the paper's (to 1e-12, relative), whatever the objectives say (a
    batch of designs and the paper's own evaluation can part on runs lost chaotically).
    None otherwise."""
    tuned, paper = obj_train[default], obj_train["paper"]
    if not same_point and tuned < paper - 1e-9 * abs(paper):
        return None
    return (f"no search found a design better than the paper's on the training runs "
            f"(training objective {tuned:.6g} against the paper's {paper:.6g}): the "
            f"design deployed is the paper's own, to round-off")


def _objective_kept(m, ref, problem, beyond=None) -> float:
    """The objective of metrics `m` against `ref` over the runs the low-speed rule keeps
    (`beyond`: the runs it sets apart; None: every run), as the verdict counts them."""
    if beyond is not None and beyond.any():
        keep = np.nonzero(~beyond)[0]
        m, ref = (jax.tree_util.tree_map(lambda a: a[..., keep], t) for t in (m, ref))
    return float(objective(m, ref, problem)[0])


def _blocking(problem, vset: ScenarioSet, metrics_val: dict, verdict: dict, log,
              beyond, sensored=None, *, space=None, x=None) -> dict | None:
    """The runs that block the verdict (the tuned design's RMS angle error worse than the
    paper's by more than the tolerance, or lock lost that the paper's design holds, among
    the runs the low-speed rule keeps, not `beyond`),
    each measured in a sensored drive of the same scenario (`sensored_lowest_speed`):
    `verdict["blocking_runs"]`, and a line of `where_not` with their lowest speeds and
    back-EMF. `sensored`: the low-speed rule's records of every run, where it measured
    them (not simulated again). With the design space `space` and the tuned design `x`,
    also what each blocking run says (`tuning.blocking`): its noise floor
    (`noise_floor_pct`: how far the paper design's RMS on it moves with the noise
    realisation alone) and where in the run the change comes from (`phases`), summed up
    in a line of `where_not`; returns the worst of them over time
    (`TuningReport.blocking_trace`), else None."""
    m, ref = metrics_val["tuned"], metrics_val["paper"]
    rms_rel = np.asarray(m.rms_deg) / np.asarray(ref.rms_deg) - 1.0
    new_lost = np.asarray(m.lost_lock) & ~np.asarray(ref.lost_lock)
    worse = (rms_rel > problem.regression_tol) & judged(m.lost_lock, ref.lost_lock)
    runs = np.nonzero((worse | new_lost) & ~beyond)[0]
    if not runs.size:
        verdict["blocking_runs"] = []
        return None
    rows = vset.table()
    if sensored is None:
        _say(log, f"measuring the {runs.size} blocking validation runs in a sensored drive")
        found = sensored_lowest_speed(problem, vset, runs)
    else:
        found = [dict(sensored[j]) for j in runs]
    for r in found:
        j = r["run"]
        r.update({k: rows[j][k] for k in ("s0", "s1", "k_d", "k_q", "k_R", "k_psi",
                                          "k_noise")},
                 rms_change_pct=float(100.0 * rms_rel[j]), new_lost_lock=bool(new_lost[j]))
    verdict["blocking_runs"] = found

    def span(key):
        lo, hi = (f"{f(r[key] for r in found):.3g}" for f in (min, max))
        return lo if lo == hi else f"{lo}-{hi}"

    verdict["where_not"].append(
        f"the {len(found)} blocking runs in a sensored drive (the true angle and speed): "
        f"lowest speed {span('lowest_speed_pu')} p.u., back-EMF there "
        f"{span('back_emf_V')} V; the rotor reverses in "
        f"{sum(r['reverses'] for r in found)} of them")
    if space is None:
        return None
    return _what_blocking_runs_say(problem, space, vset, found, x, verdict, log)


def _lost_by_both(problem, space, vset: ScenarioSet, metrics_val: dict, name: str, x,
                  beyond, verdict: dict, log) -> None:
    """The validation runs (among those the low-speed rule keeps) that both the paper's
    design and the deployed one (`name`, coordinates `x`) lose lock in, ties of the
    accounting (`tuning.judged`), with what the analysis says at each one's end
    (`tuning.end_analysis` of the deployed design) and, where the metrics carry it, when
    the deployed design lost lock (`t_lost_s`) and in which phase of the run (`phase`,
    `tuning.scenarios.PHASES`): `verdict["lost_by_both"]`, a line of the log, and one of
    `where_not` where the verdict does not hold."""
    m, ref = metrics_val[name], metrics_val["paper"]
    runs = np.nonzero(~judged(m.lost_lock, ref.lost_lock) & ~beyond)[0]
    if not runs.size:
        verdict["lost_by_both"] = []
        return
    _say(log, f"the analysis at the end of the {runs.size} validation runs both designs "
              f"lose lock in")
    rows = vset.table()
    found = end_analysis(problem, space, vset, runs, x)
    for r in found:
        r.update({k: rows[r["run"]][k] for k in ("s0", "k_d", "k_q", "k_R", "k_psi",
                                                   "k_noise")})
        if m.t_lost is not None:
            j = r["run"]
            t = float(np.asarray(m.t_lost)[j])
            r.update(t_lost_s=t, phase=phase_at(t, *(float(np.asarray(a)[j]) for a in (
                vset.t0, vset.t1, vset.t_load))))
    verdict["lost_by_both"] = found
    counts = {k: sum(r["end"] == k for r in found) for k in END_VERDICTS}
    line = (f"{runs.size} runs lost by both designs are ties (after a lock loss the "
            f"angle error is chaotic: `verdict.floor`); the analysis at their end, for the "
            f"deployed design: " + "; ".join(f"{v} {END_VERDICTS[k]}" for k, v in
                                             counts.items() if v))
    on_way = [r["phase"] for r in found if r["end"] == "feasible" and "phase" in r]
    if on_way:
        line += "; those lost on the way, by phase: " + phase_counts(on_way)
    _say(log, line)
    if not verdict["holds"]:
        verdict["where_not"].append(line)


def _what_blocking_runs_say(problem, space, vset, found, x, verdict, log) -> dict:
    """The noise floor and the phase split of each blocking run (`tuning.blocking`), into
    its record and a line of `where_not`; returns the worst run's angle error over time
    (its `phase_split` row with `traces`, and `case`, its validation row)."""
    runs = [r["run"] for r in found]
    _say(log, f"measuring the noise floor of the {len(runs)} blocking runs "
              f"({NOISE_FLOOR_KEYS} other noise realisations each) and where in each run "
              f"the change comes from")
    floor = (noise_floor(problem, space, vset, runs) if problem.noise_std > 0
             else np.zeros(len(runs)))
    splits = phase_split(problem, space, vset, runs, x, traces=True)
    within = 0
    phases: dict[str, int] = {}
    worst = max(range(len(found)), key=lambda i: found[i]["rms_change_pct"])
    case = {k: found[worst][k] for k in ("s0", "s1", "k_d", "k_q", "k_R", "k_psi", "k_noise")}
    trace = dict(splits[worst], case=case,
                 rms_change_pct=found[worst]["rms_change_pct"],
                 noise_floor_pct=float(100.0 * floor[worst]))
    for r, f, sp in zip(found, floor, splits):
        r["noise_floor_pct"] = float(100.0 * f)
        r["phases"] = sp["phases"]
        within += r["rms_change_pct"] <= 100.0 * f
        name, _ = main_phase(sp)
        phases[name] = phases.get(name, 0) + 1
    where = ", ".join(f"{k} in {v}" for k, v in sorted(phases.items(), key=lambda kv: -kv[1]))
    lo, hi = (f"{100 * f(floor):.1f}" for f in (min, max))
    verdict["where_not"].append(
        f"the noise floor of the blocking runs (the paper design's RMS with "
        f"{NOISE_FLOOR_KEYS} other noise realisations) is "
        f"{lo if lo == hi else f'{lo}-{hi}'} %: {within} of {len(found)} "
        f"runs' RMS change lies within it; the phase with the largest share of the "
        f"change (`phases`): {where}")
    return trace


def _choose(acc_val: dict, vset: ScenarioSet) -> tuple[str, dict]:
    """The default design and the verdict (see the module docstring)."""
    rows = vset.table()
    for name in ("tuned", *FRONT):
        ok, why = holds(acc_val[name])
        if ok:
            return name, {"holds": True, "design": name, "where_not": [],
                          "rule": RULE}
    ok, why = holds(acc_val["tuned"])
    a = acc_val["tuned"]
    # the worst run is named where its change shows at the precision printed (a change
    # of round-off, as when the paper's design is deployed, names no run)
    if a["worst_run"] is not None and round(a["worst_rms_change_pct"], 1) > 0:
        r = rows[a["worst_run"]]
        why.append(f"the worst run: speed {r['s0']:+g} -> {r['s1']:+g} p.u., k_d "
                   f"{r['k_d']:g}, k_q {r['k_q']:g}, k_R {r['k_R']:g}, k_psi {r['k_psi']:g}, "
                   f"noise x{r['k_noise']:g}: RMS angle error "
                   f"{a['worst_rms_change_pct']:+.1f} %")
    return "tuned", {"holds": False, "design": "tuned", "where_not": why, "rule": RULE}


RULE = ("better than the paper's design (validation loss lower by more than 0.1 %) in at "
        "least 75 % of the "
        "validation runs, no run's RMS angle error worse by more than the tolerance, no "
        "run losing lock that the paper's design holds; a run both designs lose lock in "
        "is a tie; runs beyond the observer's class by the low-speed rule counted apart")
#: The low-speed rule, as the report states it (`TuningProblem.low_speed_limit_pu`).
LOW_SPEED_RULE = ("written before tuning: a validation run in which the sensored drive "
                  "(the same controller on the true angle and speed, the same noise) turns "
                  "slower than `limit_pu` of rated speed is judged without its load step "
                  "(`unloaded`) where that keeps the sensored drive above the limit, and is "
                  "otherwise beyond the observer's class, whose declared limit it is "
                  "(`low_speed_limit_pu`: li's PLL observers 0.05, below which their PLL's "
                  "loop gain fades; 0 for the others)")


__all__ = ["FRONT", "PEERS", "TuningReport", "tune"]
