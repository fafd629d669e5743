"""Closed-loop gain tuning: the searches at one budget, and gradients against horizon.

1. **Searches** (`--observer`, default the main job's ESO on zhang750): every strategy
   (`tuning.search`) from the paper's design with the same budget of closed-loop
   simulations on the training runs of `tuning.TuningProblem()`; reported per strategy:
   the best training objective, its wall time (compilation included), and the
   simulations and wall time until the best-so-far objective first reached 50 % and
   90 % of the largest improvement any strategy found.
2. **Gradient against horizon**: on one training run of each kind (ramp, reversal,
   load step), the reverse-mode gradient of the objective against central finite
   differences (step 1e-4 in the unconstrained coordinates) for runs of 0.05 to 0.5 s:
   norms, relative difference and cosine, and the time of one value-and-gradient.

Usage:

    .venv/bin/python benchmarks/bench_tuning.py [--observer NAME] [--budget SIMS]
        [--horizons 0.05,0.1,0.2,0.3,0.5] [--out FILE.json]

Prints two tables and writes JSON (default `benchmarks/out/bench_tuning.json`).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj


pj.runtime.configure()
import tuning as tg  # noqa: E402


HERE = Path(__file__).parent


def searches(problem):
    space = tg.DesignSpace(problem)
    ev = tg.Evaluator(problem, space, tg.training_set(problem))
    z0 = space.to_unconstrained(space.paper_point())
    start = float(ev.value(z0))
    res = {}
    for name, fn in tg.STRATEGIES.items():
        res[name] = fn(ev, z0, budget=problem.budget, population=problem.population,
                       key=jax.random.PRNGKey(problem.seed),
                       learning_rate=problem.learning_rate, clip_norm=problem.clip_norm)
    best = min(r.value for r in res.values())
    rows = []
    for name, r in res.items():
        row = {"strategy": name, "objective": r.value, "sims": r.sims, "wall_s": r.wall_s}
        for frac in (0.5, 0.9):
            sims, wall = r.to_reach(start - frac * (start - best))
            row[f"sims_to_{int(100 * frac)}pct"], row[f"wall_to_{int(100 * frac)}pct"] = \
                sims, wall
        rows.append(row)
    return start, rows


def horizons(problem, hs):
    space = tg.DesignSpace(problem)
    train = tg.training_set(problem)
    z = space.to_unconstrained(space.to_physical(jnp.zeros(space.n)))
    rows = []
    for kind in range(3):
        j = int(np.flatnonzero(np.asarray(train.kind) == kind)[0])

        def make(t_end, j=j):
            q = problem.replace(t_end=t_end)
            return tg.Evaluator(q, space, tg.training_set(q).take([j]))

        for t_end in hs:
            ev = make(t_end)
            ev.value_and_grad(z)  # compile
            t0 = time.perf_counter()
            jax.block_until_ready(ev.value_and_grad(z))
            dt = time.perf_counter() - t0
            r = tg.gradient_vs_horizon(lambda _t, ev=ev: ev, z, (t_end,), eps=1e-4)[0]
            rows.append({"kind": tg.scenarios.KINDS[kind], **r, "grad_time_s": dt})
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--observer", default="eso")
    ap.add_argument("--budget", type=int, default=None)
    ap.add_argument("--horizons", default="0.05,0.1,0.2,0.3,0.5")
    ap.add_argument("--out", default=str(HERE / "out" / "bench_tuning.json"))
    args = ap.parse_args()
    kw = {} if args.budget is None else {"budget": args.budget}
    problem = tg.TuningProblem(observer=args.observer, **kw)
    start, srows = searches(problem)
    print(f"searches: {problem.observer} on {problem.drive().name}, budget {problem.budget} "
          f"closed-loop simulations, paper design's objective {start:.4f}")
    print(f"{'strategy':>10} {'objective':>10} {'sims':>6} {'wall s':>8} {'sims 50%':>9} "
          f"{'wall 50%':>9} {'sims 90%':>9} {'wall 90%':>9}")
    f = lambda v, fmt: "-" if v is None else format(v, fmt)  # noqa: E731
    for r in srows:
        print(f"{r['strategy']:>10} {r['objective']:10.4f} {r['sims']:6d} {r['wall_s']:8.1f} "
              f"{f(r['sims_to_50pct'], 'd'):>9} {f(r['wall_to_50pct'], '.1f'):>9} "
              f"{f(r['sims_to_90pct'], 'd'):>9} {f(r['wall_to_90pct'], '.1f'):>9}")
    hs = [float(x) for x in args.horizons.split(",")]
    hrows = horizons(problem, hs)
    print("\ngradient against horizon (one training run of each kind)")
    print(f"{'kind':>9} {'t_end s':>8} {'|grad|':>10} {'|fd|':>10} {'rel diff':>10} "
          f"{'cosine':>9} {'grad s':>8}")
    for r in hrows:
        print(f"{r['kind']:>9} {r['t_end']:8.2f} {r['grad_norm']:10.3g} {r['fd_norm']:10.3g} "
              f"{r['rel_error']:10.2e} {r['cos']:9.5f} {r['grad_time_s']:8.3f}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": platform.machine(), "cpus": os.cpu_count(),
                               "observer": problem.observer, "budget": problem.budget,
                               "paper_objective": start, "searches": srows,
                               "horizons": hrows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
