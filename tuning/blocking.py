r"""What a blocking validation run says: two measurements per run that the verdict's
report gives beside the sensored drive's lowest speed (`tuning.sensored_lowest_speed`).

- **The noise floor** (`noise_floor`): the paper's design on the same run with
  `NOISE_FLOOR_KEYS` other realisations of the current noise (the run's own key
  replaced, nothing else changed). The largest relative change of its RMS angle error
  is how far that run's RMS moves with the noise alone, with no design changed. A
  regression smaller than it cannot be told apart from the noise the run happened to
  draw; one well above it is the design's.
- **Where in the run** (`phase_split`): the run's angle error split by the scenario's
  phases (`PHASES`: before the speed ramp, the ramp, between the ramp and the load step,
  the load step and after), as the RMS over each phase for the paper's design and the
  deployed one, and each phase's share of the change of the run's mean square. The
  phases' mean squares, weighted by their samples, add up to the run's: $\mathrm{rms}^2
  = \sum_p (n_p / n)\,\mathrm{rms}_p^2$, so the shares add up to 100 %.

And for a run that both designs lose lock in (a tie of the accounting,
`tuning.judged`), **what the analysis says at its end** (`end_analysis`): the
equilibrium analysis of the deployed design with the run's observer model at the
run's final speed and load (`tuning.scenarios.designed_feasible`). Where it finds no
equilibrium at all, or no stable designed one, the angle error cannot settle at that
point whatever happens on the way; where the designed equilibrium is stable, the run
was lost on the way (the start, the ramp or the load step).

"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import pmsmjax as pj

from .design_space import DesignSpace
from .evaluate import Evaluator
from .problem import TuningProblem
from .scenarios import (
    PHASES,
    STREAMS,
    ScenarioSet,
    designed_feasible,
    observer_model,
    simulate_set,
)


#: Other noise realisations per run that measure its noise floor.
NOISE_FLOOR_KEYS = 4
#: The noise keys' stream of the noise floor (none of the scenario sets' `STREAMS`).
NOISE_FLOOR_STREAM = max(STREAMS.values()) + 1


def noise_floor(problem: TuningProblem, space: DesignSpace, sset: ScenarioSet, runs,
                n_keys: int = NOISE_FLOOR_KEYS) -> np.ndarray:
    """Per run of `runs` (indices into `sset`), the largest relative change of the paper
    design's RMS angle error when the run's noise key is replaced by one of `n_keys`
    others (a fraction; 0 where the problem has no current noise). One batch of
    `len(runs) x (n_keys + 1)` closed-loop runs."""
    runs = [int(j) for j in runs]
    if n_keys < 1:
        raise ValueError(f"`noise_floor(n_keys=...)`: got {n_keys!r}; at least 1 other "
                         f"noise realisation is needed.")
    if not runs:
        return np.zeros(0)
    k = len(runs)
    batch = sset.take(np.tile(np.asarray(runs), n_keys + 1))
    base = jr.fold_in(jr.PRNGKey(problem.seed), NOISE_FLOOR_STREAM)
    others = jr.split(base, n_keys * k)
    keys = jnp.concatenate([sset.keys[np.asarray(runs)], others])
    batch = eqx.tree_at(lambda s: s.keys, batch, keys)
    rms = np.asarray(Evaluator(problem, space, batch).reference.rms_deg).reshape(
        n_keys + 1, k)
    return np.max(np.abs(rms[1:] / rms[0] - 1.0), axis=0)


def phase_split(problem: TuningProblem, space: DesignSpace, sset: ScenarioSet, runs,
                x, *, traces: bool = False) -> list[dict]:
    """Per run of `runs` (indices into `sset`), the RMS angle error (deg) over each of
    `PHASES` for the paper's design and the design `x` (physical coordinates), the
    phase's share of the samples, and its share of the change of the run's mean square
    (%; the shares add up to 100; all 0 where the mean square does not change). Also
    the whole run's RMS of both (`rms_deg`), the same number as the tuner's `rms_deg`
    metric. `traces`: each row also carries the run's sample times (`t_s`, s), its
    phases' start times (`phase_start_s`) and both designs' angle error
    (`error_deg`, wrapped, true minus estimate), arrays for a figure."""
    runs = [int(j) for j in runs]
    if not runs:
        return []
    sub = sset.take(np.asarray(runs))
    drive, foc = problem.drive(), problem.controller()
    err = {}
    for name, design in (("paper", None), ("tuned", x)):
        traj = simulate_set(lambda motor, d=design: space.observer(d, motor), drive, foc,
                            sub, T_s=problem.T_s, noise_std=problem.noise_std,
                            save_every=problem.save_every,
                            speed_from_angle=problem.speed_from_angle)
        err[name] = np.asarray(pj.run_errors(traj)[0])
        t = np.asarray(traj.t)
    bounds = np.stack([np.zeros(len(runs)), np.asarray(sub.t0), np.asarray(sub.t1),
                       np.asarray(sub.t_load), np.full(len(runs), np.inf)], axis=1)
    out = []
    for j in range(len(runs)):
        ms = {n: e[j] ** 2 for n, e in err.items()}
        total = {n: float(np.mean(v)) for n, v in ms.items()}
        change = total["tuned"] - total["paper"]
        rows = {}
        for p, name in enumerate(PHASES):
            sel = (t[j] >= bounds[j, p]) & (t[j] < bounds[j, p + 1])
            frac = float(np.mean(sel))
            ph = {n: float(np.mean(v[sel])) if sel.any() else 0.0 for n, v in ms.items()}
            rows[name] = {"samples_pct": 100.0 * frac,
                          "rms_deg": {n: float(np.sqrt(v)) for n, v in ph.items()},
                          "share_of_change_pct": (100.0 * frac * (ph["tuned"] - ph["paper"])
                                                  / change) if change else 0.0}
        out.append({"run": runs[j], "rms_deg": {n: float(np.sqrt(v)) for n, v in
                                                total.items()}, "phases": rows})
        if traces:
            out[-1].update(t_s=t[j], phase_start_s=bounds[j, :-1],
                           error_deg={n: e[j] for n, e in err.items()})
    return out


#: `end_analysis`'s words for the analysis at a run's end.
END_VERDICTS = {
    "no equilibrium": "with no equilibrium at all (the angle error drifts)",
    "infeasible": "with no stable designed equilibrium (or a second stable one)",
    "feasible": "with the designed equilibrium stable (lost on the way)",
    "failed": "where the analysis failed (no verdict)",
}


def end_analysis(problem: TuningProblem, space: DesignSpace, sset: ScenarioSet, runs,
                 x=None) -> list[dict]:
    """Per run of `runs` (indices into `sset`), the equilibrium analysis of the design `x`
    (physical coordinates; None: the paper's) with the run's observer model at the run's
    end: its final speed `s1` and the current of its braking load
    (`tuning.scenarios.designed_feasible`). Each row: `run`, `speed_pu`, `load_pu`,
    `analysis_status` (0 ok, 2 no equilibrium, -1 failed) and `end`, one of
    `END_VERDICTS`. One vmapped program over the runs."""
    runs = [int(j) for j in runs]
    if not runs:
        return []
    sub = sset.take(np.asarray(runs))
    drive = problem.drive()

    def one(s1, load, k_d, k_q, k_R, k_psi):
        obs = space.observer(x, observer_model(drive, k_d, k_q, k_R, k_psi))
        return designed_feasible(obs, drive, s1, load)

    r = jax.jit(jax.vmap(one))(sub.s1, sub.load_pu, sub.k_d, sub.k_q, sub.k_R, sub.k_psi)
    feasible, status = np.asarray(r["feasible"]), np.asarray(r["status"])
    out = []
    for j, run in enumerate(runs):
        st = int(status[j])
        end = ("failed" if st < 0 else "no equilibrium" if st == 2 else
               "feasible" if feasible[j] else "infeasible")
        out.append(dict(run=run, speed_pu=float(sub.s1[j]), load_pu=float(sub.load_pu[j]),
                        analysis_status=st, end=end))
    return out


def main_phase(split: dict) -> tuple[str, float]:
    """The phase of a `phase_split` row with the largest share of the change, and that
    share (%)."""
    name = max(split["phases"], key=lambda p: split["phases"][p]["share_of_change_pct"])
    return name, split["phases"][name]["share_of_change_pct"]


__all__ = ["END_VERDICTS", "NOISE_FLOOR_KEYS", "PHASES", "end_analysis", "noise_floor",
           "phase_split"]
