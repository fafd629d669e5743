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

Usage (from the repository root):

    python -m benchmarks.commands.tune [--observer NAME] [--budget SIMS]
        [--horizons 0.05,0.1,0.2,0.3,0.5] [--quick]

`--quick` uses the small problem of `python -m tuning --quick` (`TuningProblem.quick()`)
and two horizons. Prints two tables and writes JSON.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj
import tuning as tg

from .. import _harness as h


MODULE = "benchmarks.commands.tune"


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


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the small problem and two horizons")
    ap.add_argument("--observer", default="eso")
    ap.add_argument("--budget", type=int, default=None)
    ap.add_argument("--horizons", default=None,
                    help="run lengths, s (default 0.05,0.1,0.2,0.3,0.5; --quick: 0.05,0.1)")
    args = ap.parse_args(argv)
    pj.runtime.configure()  # the job's process settings, before any work
    kw = {} if args.budget is None else {"budget": args.budget}
    make = tg.TuningProblem.quick if args.quick else tg.TuningProblem
    problem = make(observer=args.observer, **kw)
    start, srows = searches(problem)
    print(f"searches: {problem.observer} on {problem.drive().name}, budget {problem.budget} "
          f"closed-loop simulations, paper design's objective {start:.4f}")
    h.table(srows, [("strategy", "strategy", ""), ("objective", "objective", ".4f"),
                    ("simulations", "sims", "d"), ("wall s", "wall_s", ".1f"),
                    ("sims to 50 %", "sims_to_50pct", "d"),
                    ("wall to 50 %", "wall_to_50pct", ".1f"),
                    ("sims to 90 %", "sims_to_90pct", "d"),
                    ("wall to 90 %", "wall_to_90pct", ".1f")])
    hs = [float(x) for x in (args.horizons or ("0.05,0.1" if args.quick else
                                                "0.05,0.1,0.2,0.3,0.5")).split(",")]
    hrows = horizons(problem, hs)
    print("\ngradient against horizon (one training run of each kind)")
    h.table(hrows, [("kind", "kind", ""), ("t_end s", "t_end", ".2f"),
                    ("|grad|", "grad_norm", ".3g"), ("|fd|", "fd_norm", ".3g"),
                    ("relative difference", "rel_error", ".2e"), ("cosine", "cos", ".5f"),
                    ("value and gradient, s", "grad_time_s", ".3f")])
    h.write_report(args.json, dict(searches=srows, horizons=hrows), benchmark=MODULE,
                   observer=problem.observer, budget=problem.budget, paper_objective=start,
                   quick=args.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
