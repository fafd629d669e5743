"""Start-up of every command: cold (empty compilation cache) and warm (second run).

Each command runs as a user runs it, in a fresh process (`python -m pmsmjax ...`,
`python -m tuning ...`), with `PMSMJAX_CACHE_DIR` pointing at a fresh directory: the first
run compiles and fills the cache ("cold"), the second finds its programs there ("warm").
A third configuration runs with the cache switched off (`PMSMJAX_CACHE=0`), which is what
every run cost before the cache. Wall time of the whole process, best of `--repeats`.

Usage:

    .venv/bin/python benchmarks/bench_startup.py [--quick | --readme] [--out FILE.json]

`--quick` leaves out the full main job (`python -m tuning`, about 2 minutes) and runs its
`--quick` variant instead. `--readme` runs only the README's three quick-start commands
(`README_QUICK_START`, in the README's order), which the README says take a few seconds.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import write_report  # noqa: E402


#: The README's quick start (keep in step with README.md; `--readme` times it).
README_QUICK_START = {
    "quick start: simulate (sensorless)": [
        "simulate", "--observer", "eso", "--scenario", "load-step", "--t-end", "0.5",
        "--out", "{tmp}/sim"],
    "quick start: replay (leso)": [
        "replay", "--observer", "leso", "--data", "{tmp}/sim/recording.npz", "--theta0",
        "30", "--speed0", "0.5", "--out", "{tmp}/replay"],
    "quick start: equilibria": [
        "equilibria", "--observer", "eso", "--speed", "0.5", "--i-q", "0.5", "--mismatch",
        "L_q=1.3"],
}


def readme_commands(tmp: Path) -> dict[str, list[str]]:
    return {name: ["-m", "pmsmjax", *(a.format(tmp=tmp) for a in cmd)]
            for name, cmd in README_QUICK_START.items()}


def commands(tmp: Path, quick: bool) -> dict[str, list[str]]:
    data = tmp / "sim" / "recording.npz"  # written by the simulate run
    cmds = {
        "simulate (default run)": ["-m", "pmsmjax", "simulate", "--out", str(tmp / "sim"),
                                   "--no-plot"],
        "replay": ["-m", "pmsmjax", "replay", "--data", str(data), "--out",
                   str(tmp / "rep"), "--no-plot"],
        "plant": ["-m", "pmsmjax", "plant", "--data", str(data), "--out",
                  str(tmp / "plant"), "--no-plot"],
        "feasibility (11 x 11)": ["-m", "pmsmjax", "feasibility", "--zeta1", "0:5:11",
                                  "--ratio", "0:2:11", "--out", str(tmp / "feas"),
                                  "--no-plot"],
        "equilibria": ["-m", "pmsmjax", "equilibria", "--speed", "0.5", "--json"],
        "certify --quick": ["-m", "pmsmjax", "certify", "--quick", "--json"],
    }
    if quick:
        cmds["main job --quick"] = ["-m", "tuning", "--quick", "--no-progress", "--no-plot",
                                    "--out", str(tmp / "tune")]
    else:
        cmds["main job (make run)"] = ["-m", "tuning", "--no-progress", "--out",
                                       str(tmp / "tune")]
    return cmds


def timed(args, env) -> float:
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode not in (0, 1):
        raise SystemExit(f"{' '.join(args)} failed ({res.returncode}):\n{res.stderr[-2000:]}")
    return wall


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--readme", action="store_true",
                    help="only the README's quick-start commands")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--out", default="results/bench_startup.json")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="pmsmjax-startup-"))
    rows = []
    try:
        cmds = readme_commands(tmp) if args.readme else commands(tmp, args.quick)
        for name, cmd in cmds.items():
            cache = tmp / "cache"
            shutil.rmtree(cache, ignore_errors=True)
            env = dict(os.environ, PMSMJAX_CACHE_DIR=str(cache), MPLBACKEND="Agg")
            env.pop("PMSMJAX_CACHE", None)
            off = min(timed(cmd, dict(env, PMSMJAX_CACHE="0")) for _ in range(args.repeats))
            cold = timed(cmd, env)
            warm = min(timed(cmd, env) for _ in range(args.repeats))
            rows.append(dict(command=name, no_cache_s=off, cold_s=cold, warm_s=warm))
            print(f"{name:28s} no cache {off:7.1f} s  cold {cold:7.1f} s  warm {warm:7.1f} s",
                  flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print("\n| command | no cache (s) | cold (s) | warm (s) |\n|---|---:|---:|---:|")
    for r in rows:
        print(f"| {r['command']} | {r['no_cache_s']:.1f} | {r['cold_s']:.1f} | "
              f"{r['warm_s']:.1f} |")
    write_report(args.out, rows)


if __name__ == "__main__":
    main()
