"""Compile work of one whole tuning run: `python -m tuning --quick` in a fresh process.

The run's wall and CPU time, and what XLA compiled on the way (JAX's compile events,
counted in the child process): the number of programs, how many took at least one
second to compile, and the seconds spent in XLA's compiler, in lowering and in tracing.
The persistent compilation cache is off (`PMSMJAX_CACHE=0`), so every program compiles,
as on a machine that runs the job for the first time. `--repeat N` runs the job N times
(fresh processes) and reports each.

Usage:

    .venv/bin/python benchmarks/bench_tuner_compile.py [--repeat 1] [--timeout 900]
        [--out results/bench_tuner_compile.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import write_report  # noqa: E402


ROOT = Path(__file__).resolve().parents[1]

#: The child: count JAX's compile events, run the quick job, print one JSON line last.
CHILD = r"""
import atexit, collections, json, logging, re, runpy, sys, time
import jax.monitoring as mon
t0 = time.perf_counter()
acc = collections.Counter()
mon.register_event_duration_secs_listener(lambda e, d, **kw: acc.update({e: d}))
per = []
class H(logging.Handler):
    def emit(self, rec):
        m = re.match(r"Finished XLA compilation of (.*) in ([0-9.]+) sec", rec.getMessage())
        if m:
            per.append((m.group(1), float(m.group(2))))
log = logging.getLogger("jax._src.dispatch")
log.setLevel(logging.DEBUG)
log.addHandler(H())
log.propagate = False
def report():
    ev = "/jax/core/compile/"
    print(json.dumps(dict(
        wall_s=time.perf_counter() - t0, cpu_s=time.process_time(),
        programs=len(per), programs_over_1s=sum(1 for _, s in per if s >= 1.0),
        backend_compile_s=acc[ev + "backend_compile_duration"],
        lowering_s=acc[ev + "jaxpr_to_mlir_module_duration"],
        tracing_s=acc[ev + "jaxpr_trace_duration"],
        largest=sorted(per, key=lambda p: -p[1])[:8])))
atexit.register(report)
sys.argv = ["tuning", "--quick", "--no-plot", "--no-progress", "--out", sys.argv[1]]
runpy.run_module("tuning", run_name="__main__")
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--out", default=str(ROOT / "results" / "bench_tuner_compile.json"))
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error(f"--repeat must be >= 1; got {args.repeat}")
    env = dict(os.environ, PMSMJAX_CACHE="0")
    rows = []
    for k in range(args.repeat):
        with tempfile.TemporaryDirectory() as d:
            p = subprocess.run([sys.executable, "-c", CHILD, str(Path(d) / "out")],
                               capture_output=True, text=True, timeout=args.timeout,
                               env=env, cwd=ROOT)
        if p.returncode != 0:
            sys.exit(f"run {k + 1}: the tuning job failed:\n{p.stderr[-3000:]}")
        r = json.loads(p.stdout.strip().splitlines()[-1])
        verdict = [ln for ln in p.stdout.splitlines() if ln.startswith("verdict:")]
        r["verdict"] = verdict[-1] if verdict else None
        rows.append(r)
    print("| run | wall s | CPU s | programs | >= 1 s | XLA compile s | lowering s | "
          "tracing s |\n|---:|---:|---:|---:|---:|---:|---:|---:|")
    for k, r in enumerate(rows, 1):
        print(f"| {k} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['programs']} | "
              f"{r['programs_over_1s']} | {r['backend_compile_s']:.1f} | "
              f"{r['lowering_s']:.1f} | {r['tracing_s']:.1f} |")
    print("largest programs (s):", ", ".join(f"{n} {s:.1f}" for n, s in rows[0]["largest"]))
    print(rows[0]["verdict"])
    write_report(args.out, rows, loadavg=os.getloadavg())


if __name__ == "__main__":
    main()
