"""Quick compiles (`PMSMJAX_QUICK_COMPILE=1`, `pmsmjax.runtime.QUICK_COMPILE_FLAGS`)
against the default build: what a program saves in compile time and pays in run time.

Each measurement runs in a fresh process with the persistent compilation cache off and
`XLA_FLAGS` cleared, once with the default settings and once with quick compiles:

- the generic equilibrium analysis as `pmsmjax equilibria --observer NAME` calls it
  (`bench_compile.py`'s child: the CLI's default drive and operating point): the first
  call (trace, compile, run) and the better of two further calls (the run alone);
- a single closed-loop run (`bench_simulate.py`'s scenario: zhang750, sensored speed
  control, 125 us, 8000 steps, one drive): the first call and the best of five runs,
  in drive-steps per second.

Usage:

    .venv/bin/python benchmarks/bench_quick_compile.py [--observers eso,leso] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _report import write_report  # noqa: E402
from bench_compile import api  # noqa: E402


N_STEPS = 8000
SINGLE_RUN = f"""
import json, time, sys
sys.path.insert(0, {str(HERE)!r})
import pmsmjax as pj
import bench_simulate as b
import jax
run = jax.jit(b.make_pmsmjax_run("float64", {N_STEPS}))
w = float(b.w_finals(1)[0])
t = time.perf_counter(); jax.block_until_ready(run(w)); first = time.perf_counter() - t
best = 1e9
for _ in range(5):
    t = time.perf_counter(); jax.block_until_ready(run(w)); best = min(best, time.perf_counter() - t)
print(json.dumps(dict(first_s=first, second_s=best, steps_per_s={N_STEPS} / best)))
"""

OBSERVERS = ("eso", "leso", "parallel-model", "rotor-flux", "c-leso", "gi-leso")


def _env(quick: bool) -> dict:
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    env["PMSMJAX_QUICK_COMPILE"] = "1" if quick else "0"
    env["PMSMJAX_CACHE"] = "0"
    return env


def single_run(quick: bool) -> dict:
    res = subprocess.run([sys.executable, "-c", SINGLE_RUN], env=_env(quick), check=True,
                         capture_output=True, text=True, timeout=600)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--observers", default=",".join(OBSERVERS),
                    help="comma-separated observers of the registry (default: %(default)s)")
    ap.add_argument("--out", default="benchmarks/out/quick_compile.json")
    args = ap.parse_args()
    names = [n for n in args.observers.split(",") if n]
    t0 = time.perf_counter()
    rows = []
    for quick in (False, True):
        r = single_run(quick)
        rows.append(dict(item="single closed-loop run", quick=quick, **r))
        for name in names:
            r = api(name, "auto", _env(quick), 600)
            rows.append(dict(item=f"equilibria {name}", quick=quick,
                             **{k: r.get(k) for k in ("first_s", "first_cpu_s", "second_s",
                                                      "status", "n", "theta")}))
    by = {(r["item"], r["quick"]): r for r in rows}
    print("| program | first call, default (s) | quick (s) | ratio | run, default (s) | "
          "quick (s) | ratio |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for item in dict.fromkeys(r["item"] for r in rows):
        a, b = by[(item, False)], by[(item, True)]
        print(f"| {item} | {a['first_s']:.2f} | {b['first_s']:.2f} | "
              f"{b['first_s'] / a['first_s']:.2f} | {a['second_s']:.4f} | "
              f"{b['second_s']:.4f} | {b['second_s'] / a['second_s']:.2f} |")
        if "theta" in a and a["theta"] != b["theta"]:
            d = max((abs(x - y) for x, y in zip(a["theta"], b["theta"])), default=0.0)
            print(f"|   (equilibrium angles differ by up to {d:.1e} rad) |||||||")
    print(f"Total {time.perf_counter() - t0:.0f} s; load average at the end "
          f"{os.getloadavg()[0]:.2f}.")
    write_report(args.out, rows, load_end=os.getloadavg())


if __name__ == "__main__":
    main()
