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

- `quick-1`, `quick-2`: `--quick` (8 observers, paper designs), `--jobs 1` / `--jobs 2`, cold;
- `quick-warm`: `--quick --jobs 2` again with the cache of `quick-2`;
- `default-2`: the default job (8 observers, paper and tuned designs, equilibrium
  analysis, 300 runs each), `--jobs 2`, cold;
- `eso-1dev`, `eso-2dev`: the default grid for the ESO alone, `--jobs 1`, one device /
  two CPU devices (`XLA_FLAGS=--xla_force_host_platform_device_count=2`), cold;
- `eso-2proc`: the same on two `jax.distributed` processes (`--coordinator
  localhost:PORT --num-processes 2 --process-id 0/1`), cold.

Usage:

    .venv/bin/python benchmarks/bench_compare.py [--cases quick-2,quick-warm] [--out F.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
REPO = HERE.parent

CASES = {
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


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_case(name: str, work: Path) -> dict:
    spec = CASES[name]
    cache = work / "cache" / spec["cache"]
    if not spec.get("warm"):
        shutil.rmtree(cache, ignore_errors=True)
    out = work / "jobs" / name
    shutil.rmtree(out, ignore_errors=True)
    env = dict(os.environ, PMSMJAX_CACHE_DIR=str(cache), **spec.get("env", {}))
    base = [sys.executable, "-m", "tuning", "compare", "--out", str(out), "--no-plot",
            "--no-progress", *spec["args"]]
    procs = spec.get("procs", 1)
    cpu0, t0 = _children_cpu(), time.perf_counter()
    if procs == 1:
        p = subprocess.run(base, env=env, cwd=REPO, capture_output=True, text=True)
        codes = [p.returncode]
        tail = p.stderr[-2000:]
    else:
        port = _free_port()
        ps = [subprocess.Popen(base + ["--coordinator", f"localhost:{port}",
                                       "--num-processes", str(procs), "--process-id",
                                       str(i)], env=dict(env, JAX_PLATFORMS="cpu"),
                               cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True) for i in range(procs)]
        outs = [q.communicate() for q in ps]
        codes = [q.returncode for q in ps]
        tail = outs[0][1][-2000:]
    wall = time.perf_counter() - t0
    cpu = _children_cpu() - cpu0
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
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--out", default=str(HERE / "out" / "bench_compare.json"))
    ap.add_argument("--work", default=None, help="work folder (default: a temporary one)")
    args = ap.parse_args(argv)
    names = [c for c in args.cases.split(",") if c]
    unknown = [c for c in names if c not in CASES]
    if unknown:
        ap.error(f"unknown cases {unknown}; choose from {', '.join(CASES)}")
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_compare"))
    rows = []
    print(f"{'case':<11} {'wall s':>8} {'CPU s':>8} {'obs':>4} {'runs':>6} "
          f"{'steps/s':>10} {'compile s':>10} devices")
    for n in names:
        r = run_case(n, work)
        rows.append(r)
        sps = f"{r['steps_per_s']:.3g}" if r["steps_per_s"] else "-"
        print(f"{n:<11} {r['wall_s']:8.1f} {r['cpu_s']:8.1f} {r['observers']:4d} "
              f"{r['runs']:6d} {sps:>10} {r['sweep_compile_s']:10.1f} {r['devices']}",
              flush=True)
    res = dict(benchmark="bench_compare", date=datetime.datetime.now().isoformat(
        timespec="seconds"), machine=dict(node=platform.node(), cpus=os.cpu_count(),
                                          python=platform.python_version(),
                                          processor=platform.processor()),
               load_average=os.getloadavg(), rows=rows)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
