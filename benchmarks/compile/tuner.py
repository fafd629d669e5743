"""Compile work of one whole tuning run: `python -m tuning --quick` in a fresh process.

The run's wall and CPU time, and what XLA compiled on the way (JAX's compile events,
counted in the child process): the number of programs, how many took at least one
second to compile, and the seconds spent in XLA's compiler, in lowering and in tracing.
The persistent compilation cache is off (`PMSMJAX_CACHE=0`), so every program compiles,
as on a machine that runs the job for the first time. `--repeat N` runs the job N times
(fresh processes) and reports each.

`--quick` runs a smaller job: `--quick --peers local --search local` (the local search
alone, no gradient program), which compiles the closed-loop batches but not the tuner's
gradient.

Usage (from the repository root):

    python -m benchmarks.compile.tuner [--repeat 1] [--timeout 900] [--quick]
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .. import _harness as h


MODULE = "benchmarks.compile.tuner"

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
sys.argv = ["tuning", "--quick", "--no-plot", "--no-progress", "--out", *sys.argv[1:]]
runpy.run_module("tuning", run_name="__main__")
"""


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the local search alone (no gradient program)")
    ap.add_argument("--repeat", type=int, default=1, help="runs, each a fresh process")
    ap.add_argument("--timeout", type=float, default=900.0, help="limit per run, s")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error(f"--repeat must be >= 1; got {args.repeat}")
    extra = ["--peers", "local", "--search", "local"] if args.quick else []
    env = h.child_env(cache=False)
    rows = []
    for k in range(args.repeat):
        with tempfile.TemporaryDirectory() as d:
            c = h.python_child(CHILD, str(Path(d) / "out"), *extra, env=env,
                               timeout=args.timeout)
        if c.timed_out:
            raise SystemExit(f"run {k + 1}: the tuning job ran past {args.timeout} s")
        r = c.result
        verdict = [ln for ln in c.stdout.splitlines() if ln.startswith("verdict:")]
        r["verdict"] = verdict[-1] if verdict else None
        rows.append(dict(run=k + 1, **r))
    print(h.machine_line())
    h.table(rows, [("run", "run", "d"), ("wall s", "wall_s", ".1f"), ("CPU s", "cpu_s", ".1f"),
                   ("programs", "programs", "d"), (">= 1 s", "programs_over_1s", "d"),
                   ("XLA compile s", "backend_compile_s", ".1f"),
                   ("lowering s", "lowering_s", ".1f"), ("tracing s", "tracing_s", ".1f")])
    print("largest programs (s):", ", ".join(f"{n} {s:.1f}" for n, s in rows[0]["largest"]))
    print(rows[0]["verdict"])
    h.write_report(args.json, rows, benchmark=MODULE, job_args=["--quick", *extra],
                   loadavg=os.getloadavg())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
