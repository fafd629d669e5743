"""`python -m tuning compare`: wall time of the job, simulations per second, and how the
work splits over worker processes (`--jobs`), devices and `jax.distributed` processes.

Each case runs the command as a user runs it, in fresh processes, with its own
persistent compilation cache directory (`PMSMJAX_CACHE_DIR`): "cold" starts from an empty
one (the first run on a machine), "warm" repeats the same command with the cache the cold
run filled (a new job folder, so nothing but compiled programs is reused). Reported per
case: the wall time of the command, the CPU time of the command and its worker processes
(user + system), and from the job's `timing.json`/sweep manifests: the runs simulated
(observers x designs x grid points), drive-steps per second of the run sweeps' chunks
(compilation excluded) and the compile seconds of the sweeps.

Cases (`--cases`, comma-separated; default all):

- `eso-quick`: `--quick --observers eso --jobs 1`, cold (the `--quick` run of this
  benchmark);
- `quick-1`, `quick-2`: `--quick` (8 observers, paper designs), `--jobs 1` / `--jobs 2`, cold;
- `quick-warm`: `--quick --jobs 2` again with the cache of `quick-2`;
- `default-2`: the default job (8 observers, paper and tuned designs, equilibrium
  analysis, 300 runs each), `--jobs 2`, cold;
- `eso-1dev`, `eso-2dev`: the default grid for the ESO alone, `--jobs 1`, one device /
  two CPU devices (`XLA_FLAGS=--xla_force_host_platform_device_count=2`), cold;
- `eso-2proc`: the same on two `jax.distributed` processes (`--coordinator
  localhost:PORT --num-processes 2 --process-id 0/1`), cold.

Usage (from the repository root):

    python -m benchmarks.commands.compare [--cases quick-2,quick-warm] [--quick]

Without `--cases` every case but `eso-quick` runs (about 15 minutes on 2 cores).
"""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .. import _harness as h


MODULE = "benchmarks.commands.compare"
CASES = {
    "eso-quick": dict(args=["--quick", "--observers", "eso", "--jobs", "1"],
                      cache="eso-quick"),
    "quick-1": dict(args=["--quick", "--jobs", "1"], cache="quick-1"),
    "quick-2": dict(args=["--quick", "--jobs", "2"], cache="quick-2"),
    "quick-warm": dict(args=["--quick", "--jobs", "2"], cache="quick-2", warm=True),
    "default-2": dict(args=["--jobs", "2"], cache="default-2"),
    "eso-1dev": dict(args=["--observers", "eso", "--jobs", "1"], cache="eso-1dev"),
    "eso-2dev": dict(args=["--observers", "eso", "--jobs", "1"], cache="eso-2dev",
                     env={"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}),
    "eso-2proc": dict(args=["--observers", "eso", "--jobs", "1"], cache="eso-2proc",
                      procs=2),
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def run_case(name: str, work: Path) -> dict:
    spec = CASES[name]
    cache = work / "cache" / spec["cache"]
    if not spec.get("warm"):
        shutil.rmtree(cache, ignore_errors=True)
    out = work / "jobs" / name
    shutil.rmtree(out, ignore_errors=True)
    env = h.child_env(cache=str(cache), **spec.get("env", {}))
    base = [sys.executable, "-m", "tuning", "compare", "--out", str(out), "--no-plot",
            "--no-progress", *spec["args"]]
    procs = spec.get("procs", 1)
    cpu0, t0 = h.children_cpu(), time.perf_counter()
    if procs == 1:
        p = subprocess.run(base, env=env, cwd=h.ROOT, capture_output=True, text=True)
        codes = [p.returncode]
        tail = p.stderr[-2000:]
    else:
        port = _free_port()
        ps = [subprocess.Popen(base + ["--coordinator", f"localhost:{port}",
                                       "--num-processes", str(procs), "--process-id",
                                       str(i)], env=dict(env, JAX_PLATFORMS="cpu"),
                               cwd=h.ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True) for i in range(procs)]
        outs = [q.communicate() for q in ps]
        codes = [q.returncode for q in ps]
        tail = outs[0][1][-2000:]
    wall = time.perf_counter() - t0
    cpu = h.children_cpu() - cpu0
    if any(codes):
        raise RuntimeError(f"case {name}: exit {codes}\n{tail}")
    timing = json.loads((out / "timing.json").read_text())
    summary = json.loads((out / "comparison.json").read_text())
    steps_per_run = timing["steps_per_run"]
    n_runs, chunk_s, compile_s, devices = 0, 0.0, 0.0, set()
    for man in (out / "sweeps").glob("*/*/*/sweep.json"):
        m = json.loads(man.read_text())
        compile_s += m.get("compile_seconds") or 0.0
        devices.add(m["devices"]["count"])  # over all processes
        if man.parent.name == "runs":
            n_runs += m["n_points"]
            chunk_s += sum(c.get("seconds") or 0.0 for c in m["chunks"].values())
    return dict(case=name, args=spec["args"], warm=bool(spec.get("warm")),
                processes=procs, env=spec.get("env", {}), wall_s=wall, cpu_s=cpu,
                observers=len(summary["observers"]), runs=n_runs,
                steps_per_s=n_runs * steps_per_run / chunk_s if chunk_s else None,
                sweep_compile_s=compile_s, devices=sorted(devices),
                job_wall_s=timing.get("wall_s"))


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the case eso-quick only")
    ap.add_argument("--cases", default=None,
                    help=f"comma-separated cases of {', '.join(CASES)}")
    ap.add_argument("--work", default=None, help="work folder (default: a temporary one)")
    args = ap.parse_args(argv)
    names = [c for c in (args.cases or ("eso-quick" if args.quick else ",".join(
        c for c in CASES if c != "eso-quick"))).split(",") if c]
    unknown = [c for c in names if c not in CASES]
    if unknown:
        ap.error(f"unknown cases {unknown}; choose from {', '.join(CASES)}")
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_compare"))
    rows = []
    for n in names:
        rows.append(run_case(n, work))
        print(f"  {n}: {rows[-1]['wall_s']:.1f} s", flush=True)
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)
    print(h.machine_line())
    h.table(rows, [("case", "case", ""), ("wall s", "wall_s", ".1f"), ("CPU s", "cpu_s", ".1f"),
                   ("observers", "observers", "d"), ("runs", "runs", "d"),
                   ("drive-steps/s", "steps_per_s", ".3g"),
                   ("sweep compile s", "sweep_compile_s", ".1f"),
                   ("devices", lambda r: ",".join(map(str, r["devices"])), "")])
    h.write_report(args.json, rows, benchmark=MODULE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
