"""A plain script's single closed-loop run against scalar C (issue: fast settings on a
plain `import pmsmjax`).

Runs, each in a fresh process with XLA_FLAGS cleared and pinned to one core
(`taskset -c 0` where available): (a) a script that only does `import pmsmjax` and calls
`pmsmjax.simulate` (the scenario of `bench_simulate.py`: zhang750, sensored speed
control, 125 us, 8000 steps, B = 1); (b) the same with `PMSMJAX_FAST_LOOPS=0` (what a
plain import gave before it set the flags); and the scalar C reference of
`bench_simulate.py` (`ref_c.c`, float64, one drive). Reported: steps/s (best of five
after compilation, wall time) and the ratio to C.

Usage:

    .venv/bin/python benchmarks/bench_plain_script.py [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

N_STEPS = 8000
SCRIPT = f"""
import time, sys
sys.path.insert(0, {str(HERE)!r})
import pmsmjax as pj
import bench_simulate as b
import numpy as np
run = b.make_pmsmjax_run("float64", {N_STEPS})
w = float(b.w_finals(1)[0])
import jax
f = jax.jit(run)
jax.block_until_ready(f(w))
best = 1e9
for _ in range(5):
    t = time.perf_counter(); jax.block_until_ready(f(w)); best = min(best, time.perf_counter() - t)
print({N_STEPS} / best)
"""


def _pinned(cmd):
    return (["taskset", "-c", "0"] + cmd) if shutil.which("taskset") else cmd


def plain(fast: bool) -> float:
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    env["PMSMJAX_FAST_LOOPS"] = "1" if fast else "0"
    out = subprocess.run(_pinned([sys.executable, "-c", SCRIPT]), env=env, check=True,
                         capture_output=True, text=True)
    return float(out.stdout.strip().splitlines()[-1])


def c_rate() -> float:
    import bench_simulate as b

    libs = b.build_c(verbose=False)
    drive, foc = b.drive_and_controller()
    p = b.reference_params(drive, foc)
    w = b.w_finals(1)
    b.c_simulate(libs["float64"], p, w, N_STEPS)
    best = 1e9
    for _ in range(5):
        t = time.perf_counter()
        b.c_simulate(libs["float64"], p, w, N_STEPS)
        best = min(best, time.perf_counter() - t)
    return N_STEPS / best


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(HERE / "out" / "bench_plain_script.json"))
    args = ap.parse_args()
    rows = {"plain import (flags set on import)": plain(True),
            "plain import, PMSMJAX_FAST_LOOPS=0 (before)": plain(False),
            "scalar C (ref_c.c, float64)": c_rate()}
    c = rows["scalar C (ref_c.c, float64)"]
    print(f"{'single closed-loop run, B = 1':<46}{'steps/s':>12}{'x C':>8}")
    for k, v in rows.items():
        print(f"{k:<46}{v:>12.3g}{v / c:>8.2f}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": platform.machine(), "cpus": os.cpu_count(),
                               "steps": N_STEPS, "steps_per_s": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
