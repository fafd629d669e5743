"""Gain tuning: simulations and wall time to reach a given robust loss, gradient-based
(Adam, optax; BFGS, optimistix) versus gradient-free (uniform random search over the box;
a local (1+1) evolution strategy), in one run.

Problem: the main job's default `tuning.TuningConfig()` (zhang750, ESO, 54 sensorless runs
of 0.2 s at 8 kHz per evaluation; `--quick` for the tiny test configuration). Every method
starts from the paper's design (38)/(25) and gets the same budget of `--steps`
evaluations (one evaluation = one simulation of every training scenario; a gradient
evaluation also runs the backward pass through the batch).

Each method is first run for two evaluations so that its functions are compiled, then
timed from a warm start; compilation times are reported separately. Targets: the robust
losses 25 / 50 / 75 / 90 % of the way from the (38) loss down to the best loss any method
reached, and the (38) loss minus 10 %. Reported per method and target: evaluations,
simulations and warm wall time until the best-so-far loss first reaches it.

Usage:

    .venv/bin/python benchmarks/bench_tuning.py [--quick] [--steps N]
        [--observer NAME] [--methods adam,bfgs,random,local] [--out FILE.json]

`--observer` tunes another registered observer (its declared tunable design; see
`python -m tuning --observer`).

Prints a table and writes JSON (default `benchmarks/out/bench_tuning.json`).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import tuning as tg  # noqa: E402


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def run_method(name, cfg, scen, steps):
    s0 = cfg.initial_schedule()
    kw = dict(progress=False)
    if name == "random":
        fn = lambda n: tg.random_search(s0, cfg, scen, n_designs=n, **kw)  # noqa: E731
    elif name == "local":
        fn = lambda n: tg.local_search(s0, cfg, scen, n_designs=n, **kw)  # noqa: E731
    else:
        fn = lambda n: tg.optimise(s0, cfg, scen, method=name, steps=n, **kw)  # noqa: E731
    t = time.perf_counter()
    warm = fn(2)
    warmup_s = time.perf_counter() - t
    t = time.perf_counter()
    res = fn(steps)
    total_s = time.perf_counter() - t
    st = res.stats
    per_eval = float(np.median(np.diff(st["wall_time_s"]))) if st["steps"] > 1 else total_s
    return res, dict(method=name, steps=int(st["steps"]), result=res.result,
                     best_loss=float(res.loss), compile_and_warmup_s=warmup_s,
                     first_eval_compile_s=float(warm.stats["compile_time_s"]),
                     run_s=total_s, per_evaluation_s=per_eval,
                     n_simulations=int(st["n_simulations"][-1]),
                     loss=st["loss"].tolist(), best=st["best"].tolist(),
                     wall_time_s=st["wall_time_s"].tolist())


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="TuningConfig.quick() (tests)")
    ap.add_argument("--steps", type=int, default=None,
                    help="evaluations per method (default: the config's steps)")
    ap.add_argument("--observer", default="eso",
                    help="registered observer to tune (its class declares the design)")
    ap.add_argument("--methods", default="adam,bfgs,random,local",
                    help="comma-separated: adam, bfgs, lm (gradient-based), random (uniform "
                         "over the box), local ((1+1) evolution strategy)")
    ap.add_argument("--out", default=str(HERE / "out" / "bench_tuning.json"),
                    help="JSON output file")
    args = ap.parse_args()
    # a fixed budget: no early stopping, so every method gets the same evaluations; the
    # robust objective (the targets are robust losses; the main job's default adds the
    # no-regression constraint)
    cfg = (tg.TuningConfig.quick() if args.quick else tg.TuningConfig()).replace(
        patience=0, observer=args.observer, objective="robust")
    steps = cfg.steps if args.steps is None else args.steps
    scen = tg.training_scenarios(cfg)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    print(f"gain tuning benchmark: {cfg.motor}, {cfg.observer} ({cfg.design_kind}: "
          f"{', '.join(cfg.tuned)}), {scen.n} scenarios per "
          f"evaluation, {steps} evaluations per method; CPU {cpu_model()}, "
          f"{os.cpu_count()} cores")
    t = time.perf_counter()
    base, _ = tg.evaluate(cfg.initial_schedule(), cfg, scen)
    base = float(base)
    label = cfg.initial_schedule().label
    print(f"{label} robust loss {base:.4f} ({time.perf_counter() - t:.1f} s incl. "
          f"compilation)")
    results, rows = {}, {}
    for m in methods:
        print(f"running {m} ...", flush=True)
        res, row = run_method(m, cfg, scen, steps)
        results[m], rows[m] = res, row
        print(f"  best {row['best_loss']:.4f}, {row['run_s']:.1f} s warm "
              f"({row['per_evaluation_s']:.3f} s per evaluation), compile+warm-up "
              f"{row['compile_and_warmup_s']:.1f} s", flush=True)

    best = min(r.loss for r in results.values())
    fracs = (0.25, 0.5, 0.75, 0.9)
    targets = [(f"{label} - 10 %", 0.9 * base)] + [
        (f"{int(100 * f)} % to best", base - f * (base - best)) for f in fracs]
    table = []
    for label, tgt in targets:
        for m, res in results.items():
            hist = np.asarray(res.stats["best"])
            hit = np.nonzero(hist <= tgt + 1e-12)[0]
            if hit.size:
                k = int(hit[0])
                table.append(dict(target=label, loss=tgt, method=m, reached=True,
                                  evaluations=k + 1,
                                  n_simulations=int(res.stats["n_simulations"][k]),
                                  wall_time_s=float(res.stats["wall_time_s"][k])))
            else:
                table.append(dict(target=label, loss=tgt, method=m, reached=False,
                                  evaluations=None, n_simulations=None, wall_time_s=None))
    print()
    print(f"{'target':<20}{'loss':>9}  {'method':<8}{'evals':>7}{'sims':>8}{'wall (s)':>10}")
    for r in table:
        if r["reached"]:
            print(f"{r['target']:<20}{r['loss']:>9.4f}  {r['method']:<8}{r['evaluations']:>7}"
                  f"{r['n_simulations']:>8}{r['wall_time_s']:>10.1f}")
        else:
            miss = f"not reached in {rows[r['method']]['n_simulations']} sims"
            print(f"{r['target']:<20}{r['loss']:>9.4f}  {r['method']:<8}{miss:>25}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    payload = dict(
        date=datetime.datetime.now().isoformat(timespec="seconds"),
        machine=dict(cpu=cpu_model(), cores=os.cpu_count(), platform=platform.platform(),
                     jax=jax.__version__, devices=[str(d) for d in jax.devices()]),
        config=cfg.to_dict(), n_scenarios=scen.n, steps=steps, baseline_loss=base,
        best_loss=best, methods=rows, targets=table)
    out.write_text(json.dumps(payload, indent=1))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
