"""Start-up of every command: cold (empty compilation cache) and warm (second run).

Each command runs as a user runs it, in a fresh process (`python -m pmsmjax ...`,
`python -m tuning ...`), with `PMSMJAX_CACHE_DIR` pointing at a fresh directory: the first
run compiles and fills the cache ("cold"), the second finds its programs there ("warm").
A third configuration runs with the cache switched off (`PMSMJAX_CACHE=0`), which is what
every run cost before the cache. Wall time of the whole process, best of `--repeats`.

Usage (from the repository root):

    python -m benchmarks.commands.startup            # every command, the main job's --quick
    python -m benchmarks.commands.startup --full-job # ... and the full main job (make run)
    python -m benchmarks.commands.startup --readme   # the README's quick start
    python -m benchmarks.commands.startup --quick    # the same as --readme

`--readme` (and `--quick`) runs only the README's three quick-start commands
(`README_QUICK_START`, in the README's order), which the README says take a few seconds.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

from .. import _harness as h


MODULE = "benchmarks.commands.startup"


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


def commands(tmp: Path, full_job: bool) -> dict[str, list[str]]:
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
    if full_job:
        cmds["main job (make run)"] = ["-m", "tuning", "--no-progress", "--out",
                                       str(tmp / "tune")]
    else:
        cmds["main job --quick"] = ["-m", "tuning", "--quick", "--no-progress", "--no-plot",
                                    "--out", str(tmp / "tune")]
    return cmds


def timed(args, env) -> float:
    """Wall time of `python ARGS` in a fresh process (exit 0 or 1: a verdict, not a failure)."""
    c = h.run_child([sys.executable, *args], env, check=False)
    if c.returncode not in (0, 1):
        raise SystemExit(f"{' '.join(args)} failed ({c.returncode}):\n{c.stderr[-2000:]}")
    return c.wall_s


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the README's quick start (as --readme)")
    ap.add_argument("--readme", action="store_true",
                    help="only the README's quick-start commands")
    ap.add_argument("--full-job", action="store_true",
                    help="the full main job (make run, minutes) instead of its --quick")
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="pmsmjax-startup-"))
    rows = []
    try:
        readme = args.readme or args.quick
        cmds = readme_commands(tmp) if readme else commands(tmp, args.full_job)
        for name, cmd in cmds.items():
            cache = tmp / "cache"
            shutil.rmtree(cache, ignore_errors=True)
            env = h.child_env(cache=str(cache))
            off = min(timed(cmd, dict(env, PMSMJAX_CACHE="0")) for _ in range(args.repeats))
            cold = timed(cmd, env)
            warm = min(timed(cmd, env) for _ in range(args.repeats))
            rows.append(dict(command=name, no_cache_s=off, cold_s=cold, warm_s=warm))
            print(f"{name:28s} no cache {off:7.1f} s  cold {cold:7.1f} s  warm {warm:7.1f} s",
                  flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(h.machine_line())
    h.table(rows, [("command", "command", ""), ("no cache (s)", "no_cache_s", ".1f"),
                   ("cold (s)", "cold_s", ".1f"), ("warm (s)", "warm_s", ".1f")])
    h.write_report(args.json, rows, benchmark=MODULE, repeats=args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
