"""The whole tuning job: baselines, tuning, gradient-free search, held-out evaluation,
feasibility checks and time traces (`run_tuning`), as `python -m tuning` runs it."""

from __future__ import annotations

import dataclasses
import math
import time

import equinox as eqx
import jax
import numpy as np

from .objectives import Metrics, evaluate, feasibility, objective_value, report_objective
from .optimise import TuningResult, adam, local_search, optimise, random_search
from .scenarios import (
    ScenarioSet,
    TuningConfig,
    heldout_scenarios,
    simulate_scenarios,
    training_scenarios,
)
from .validation import ValidationSet, validate, validation_scenarios


#: Names of the designs in a report, in the order they are reported ("paper": the
#: observer's paper design, the tuner's start; the ablation's name comes from the
#: parametrisation, `AbstractDesign.ablation`: "min_norm_25" for `GainSchedule`).
DESIGNS = ("paper", "tuned", "min_norm_25", "random_search", "local_search")

DESCRIPTIONS = {
    "tuned": "gradient-based tuning of the design (all tuned quantities)",
    "random_search": "gradient-free random search, uniform over the same unconstrained box "
                     "(+-3 around the start), with the same number of simulations as the "
                     "gradient-based run",
    "local_search": "gradient-free (1+1) evolution strategy from the paper's design "
                    "(Gaussian steps in the unconstrained variables, 1/5th rule), the same "
                    "number of simulations",
}


def descriptions(design) -> dict:
    """`{name: description}` of the designs of a report whose baseline is `design`."""
    out = {"paper": design.describe(), **DESCRIPTIONS}
    if design.ablation is not None:
        out[design.ablation[0]] = design.ablation[2]
    return out


@dataclasses.dataclass
class TuningReport:
    """Everything `run_tuning` computed (see `tuning._report.summary` for the JSON).

    - `config`, `train`, `heldout`: the problem; `validation`: the closed-loop validation
      runs (`tuning.validation`), never used in tuning.
    - `designs`: `{name: design}` for the names of `DESIGNS` that were run ("paper" is
      the observer's paper design, the tuner's starting point).
    - `losses`: `{name: {"train": float, "heldout": float, "validation": float}}`
      (objective `report_objective(config)`: the robust aggregate for the
      "no_regression" objective, so that both report the same quantity).
    - `metrics`: `{name: {"train": Metrics, "heldout": Metrics, "validation": Metrics}}`
      per scenario.
    - `feasibility`: `{name: {"train": dict, "heldout": dict}}` (`objectives.feasibility`).
    - `results`: `{name: TuningResult}` of the optimisers.
    - `traces`: time traces of the hardest training scenario of the baseline.
    - `wall_time_s`: the whole job; `timings`: its parts (s).
    """

    config: TuningConfig
    train: ScenarioSet
    heldout: ScenarioSet
    validation: ValidationSet
    designs: dict
    losses: dict
    metrics: dict
    feasibility: dict
    results: dict
    traces: dict
    wall_time_s: float
    timings: dict

    @property
    def tuned(self):
        return self.designs["tuned"]

    @property
    def label(self) -> str:
        """How the paper's design is labelled ("(38)/(25)" for zhang2022's schedule)."""
        return self.designs["paper"].label

    def improvement_pct(self, split: str, name: str = "tuned") -> float:
        """Relative reduction of the objective against the paper's design on `split`
        (%)."""
        b = self.losses["paper"][split]
        return 100.0 * (b - self.losses[name][split]) / b

    def all_feasible(self, name: str = "tuned") -> bool:
        return bool(all(np.all(self.feasibility[name][s]["feasible"])
                        for s in ("train", "heldout")))


def _say(log, msg):
    if log is not None:
        log(msg)


def run_tuning(config: TuningConfig, *, progress: bool = True, log=print,
               ablation: bool = True, random: bool = True) -> TuningReport:
    """Run the whole job for `config` and return a `TuningReport`.

    1. the observer's paper design (zhang2022's ESO family: (38)/(25)) on the training
       and held-out grids;
    2. the tuner (`config.optimiser`) from it (`config.initial_schedule()`);
    3. (`ablation`) the parametrisation's ablation, if it has one (`GainSchedule`: the
       same tuner restricted to the minimum-norm gains (25));
    4. (`random`) two gradient-free searches with the same number of simulations:
       uniform random search over the box, and a local (1+1) evolution strategy;
    5. every design on the held-out grid, the exact feasibility check on both grids, and
       time traces of the hardest training scenario (for the paper's design);
    6. every design on the validation set (`tuning.validation`: closed-loop,
       speed-controlled runs with a ramp and a load step at other speeds, with mismatch
       in every machine parameter and more noise).
    """
    t_start = time.perf_counter()
    timings = {}
    train, held = training_scenarios(config), heldout_scenarios(config)
    n = train.n
    _say(log, f"tuning: {config.motor}, {config.observer.upper()} observer "
              f"({config.observer_class().__name__}, {config.design_kind} design: "
              f"{', '.join(config.tuned)}), "
              f"{n} training scenarios ({len(config.training_mismatch())}^2 inductance "
              f"factors x {len(config.speeds_pu)} speeds x {len(config.loads_pu)} loads), "
              f"{held.n} held-out, {config.t_end:g} s runs at T_s = {config.T_s:g} s")
    init = config.initial_schedule()  # the paper's design exactly, e.g. (38)/(25)
    label = init.label
    designs = {"paper": init}
    losses, metrics, results = {}, {}, {}

    rep = report_objective(config)

    def score(name, split, scen):
        value, m = evaluate(designs[name], config, scen, chunk=n, objective=rep)
        losses.setdefault(name, {})[split] = float(value)
        metrics.setdefault(name, {})[split] = m

    t = time.perf_counter()
    _say(log, f"evaluating the paper's design {label} (compiling the batch) ...")
    score("paper", "train", train)
    timings["baseline_s"] = time.perf_counter() - t
    _say(log, f"  {label}: {rep} loss {losses['paper']['train']:.4f}")
    # the "no_regression" objective keeps every training loss near the paper design's
    ref = metrics["paper"]["train"].loss

    t = time.perf_counter()
    _say(log, f"tuning with {config.optimiser} ({config.steps} steps; the first step "
              f"compiles the gradient) ...")
    res = optimise(init, config, train, progress=progress, reference=ref)
    results["tuned"], designs["tuned"] = res, res.value
    timings["tuning_s"] = time.perf_counter() - t
    _say(log, f"  {res.result}; best loss {res.loss:.4f}")

    if ablation and init.ablation is not None and config.optimiser == "adam":
        name, frozen, about = init.ablation
        restricted = tuple(q for q in config.tuned if q not in frozen)
        if restricted and restricted != config.tuned:
            t = time.perf_counter()
            _say(log, f"ablation: {about} ...")
            r = adam(init, config, train, tuned=restricted, progress=progress, reference=ref)
            results[name], designs[name] = r, r.value
            timings[f"{name}_s"] = time.perf_counter() - t
            _say(log, f"  {r.result}; best loss {r.loss:.4f}")

    if random:
        t = time.perf_counter()
        n_designs = int(res.stats["steps"])
        _say(log, f"random search with the same budget ({n_designs} designs = "
                  f"{n_designs * n} simulations) ...")
        r = random_search(init, config, train, n_designs=n_designs, progress=progress,
                          reference=ref)
        results["random_search"], designs["random_search"] = r, r.value
        timings["random_search_s"] = time.perf_counter() - t
        _say(log, f"  best loss {r.loss:.4f}")
        t = time.perf_counter()
        _say(log, "local (1+1) random search with the same budget ...")
        r = local_search(init, config, train, n_designs=n_designs, progress=progress,
                         reference=ref)
        results["local_search"], designs["local_search"] = r, r.value
        timings["local_search_s"] = time.perf_counter() - t
        _say(log, f"  best loss {r.loss:.4f}")

    t = time.perf_counter()
    _say(log, "evaluating on the held-out grid and checking feasibility ...")
    for name in designs:
        if name != "paper":
            score(name, "train", train)
        score(name, "heldout", held)
    feas = {name: {"train": feasibility(d, config, train, chunk=n),
                   "heldout": feasibility(d, config, held, chunk=n)}
            for name, d in designs.items()}
    timings["evaluation_s"] = time.perf_counter() - t

    t = time.perf_counter()
    val = validation_scenarios(config)
    _say(log, f"validating on {val.n} closed-loop speed-controlled runs (ramp, load step, "
              f"speeds +-{', '.join(f'{v:g}' for v in config.val_speeds_pu)} p.u., "
              f"{len(config.val_cases)} mismatch/noise cases) ...")
    for name, d in designs.items():
        m = validate(d, config, val)
        metrics[name]["validation"] = m
        losses[name]["validation"] = float(objective_value(m.loss, config, objective=rep))
    timings["validation_s"] = time.perf_counter() - t

    t = time.perf_counter()
    traces = time_traces(designs, config, train, metrics["paper"]["train"])
    timings["traces_s"] = time.perf_counter() - t
    wall = time.perf_counter() - t_start
    return TuningReport(config=config, train=train, heldout=held, validation=val,
                        designs=designs,
                        losses=losses, metrics=metrics, feasibility=feas, results=results,
                        traces=traces, wall_time_s=wall, timings=timings)


def time_traces(designs: dict, config: TuningConfig, scenarios: ScenarioSet,
                reference: Metrics, names=("paper", "tuned")) -> dict:
    """Every-sample traces of the scenario with the largest loss under `reference`:
    `{"scenario": dict, "t": array, name: {"theta_err_deg": ..., "w_err": ...}}`."""
    j = int(np.argmax(np.asarray(reference.loss)))
    one = jax.tree_util.tree_map(lambda a: a[j:j + 1], scenarios)
    out = {"scenario": scenarios.table()[j], "index": j}
    sim = eqx.filter_jit(lambda d: simulate_scenarios(d, config, one, save_every=1))
    for name in names:
        if name not in designs:
            continue
        tr = sim(designs[name])
        out["t"] = np.asarray(tr.t[0])
        out[name] = {"theta_err_deg": np.degrees(np.asarray(tr.theta_err[0])),
                     "w_err": np.asarray(tr.w_m[0] - tr.w_hat[0])}
    return out


def targets_reached(results: dict, baseline: float, fractions=(0.25, 0.5, 0.75, 0.9)
                    ) -> dict:
    """Simulations and wall time each optimiser needed to reach given losses.

    Wall times are cumulative from the start of each loop, with (`wall_time_s`) and
    without (`wall_time_warm_s`) the first evaluation's compilation.

    The targets lie `fractions` of the way from the paper design's loss `baseline` down to the
    best loss any of `results` found. Returns `{"targets": [...], name: [{"target",
    "reached", "n_simulations", "wall_time_s", "step"}, ...]}`.
    """
    best = min(r.loss for r in results.values())
    targets = [baseline - f * (baseline - best) for f in fractions]
    out = {"targets": targets, "fractions": list(fractions), "baseline": baseline,
           "best": best}
    for name, r in results.items():
        rows = []
        hist = np.asarray(r.stats["best"])
        for f, tgt in zip(fractions, targets):
            hit = np.nonzero(hist <= tgt + 1e-12)[0]
            if hit.size and math.isfinite(tgt):
                k = int(hit[0])
                rows.append(dict(fraction=f, target=tgt, reached=True, step=k + 1,
                                 n_simulations=int(r.stats["n_simulations"][k]),
                                 wall_time_s=float(r.stats["wall_time_s"][k]),
                                 wall_time_warm_s=float(r.stats["wall_time_warm_s"][k])))
            else:
                rows.append(dict(fraction=f, target=tgt, reached=False, step=None,
                                 n_simulations=None, wall_time_s=None,
                                 wall_time_warm_s=None))
        out[name] = rows
    return out


__all__ = ["DESIGNS", "TuningReport", "descriptions", "run_tuning", "targets_reached",
           "time_traces", "TuningResult"]
