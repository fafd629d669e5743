"""Warm commands, every observer: `equilibria`, `response`, `replay` and `simulate` with
the compilation cache filled, each a fresh `pmsmjax` process as a user runs it, with and
without the resident worker (`pmsmjax.runtime._worker`).

For each observer of the registry, on its paper's drive (`--motor`), the four commands
first run once on their own (filling a fresh cache folder) and once through a worker
(`pmsmjax worker --start`); then each is timed `--repeats` times through the worker and
`--repeats` times in a process of its own (`PMSMJAX_WORKER=0`). Wall time of the whole
process (`python -m pmsmjax ...`); medians with the range. The workers live in a
temporary socket folder and are stopped at the end.

Usage (from the repository root):

    python -m benchmarks.commands.warm                         # every observer, ~10 min
    python -m benchmarks.commands.warm --observers eso,gi-leso
    python -m benchmarks.commands.warm --quick                 # the ESO, 3 repeats
"""

from __future__ import annotations

import shutil
import statistics
import sys
import tempfile
from pathlib import Path

from .. import _harness as h
from .startup import timed


MODULE = "benchmarks.commands.warm"
COMMANDS = ("equilibria", "response", "replay", "simulate")


def command(name: str, observer: str, motor: str, tmp: Path) -> list[str]:
    """`python ARGS` of command `name` for `observer` on `motor` (outputs under `tmp`)."""
    common = ["--motor", motor, "--observer", observer]
    folder = tmp / observer
    return {
        "equilibria": ["equilibria", *common, "--json"],
        "response": ["response", *common, "--json"],
        "simulate": ["simulate", *common, "--t-end", "0.2", "--out", str(folder / "sim"),
                     "--no-plot"],
        "replay": ["replay", *common, "--data", str(folder / "rec" / "recording.npz"),
                   "--out", str(folder / "rep"), "--no-plot"],
    }[name]


def _wall(args: list[str], env: dict) -> float:
    """Wall time of `pmsmjax ARGS` in a fresh process (`startup.timed`)."""
    return timed(["-m", "pmsmjax", *args], env)


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the ESO only, 3 repeats")
    ap.add_argument("--observers", default=None, metavar="A,B",
                    help="observers to measure (default: the whole registry)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    names = h.observer_names("eso" if args.quick else args.observers)
    repeats = 3 if args.quick else args.repeats
    tmp = Path(tempfile.mkdtemp(prefix="pmsmjax-warm-"))
    env = h.child_env(cache=str(tmp / "cache"), worker=True,
                      PMSMJAX_WORKER_DIR=str(tmp / "sockets"))
    alone = dict(env, PMSMJAX_WORKER="0")
    rows = []
    try:
        for name in names:
            motor = h.paper_drive(name)
            # the recording the replay reads: a sensored run of the paper's drive
            rec = ["simulate", "--motor", motor, "--t-end", "0.2", "--out",
                   str(tmp / name / "rec"), "--no-plot"]
            _wall(rec, alone)
            _wall(["worker", "--start"], env)
            for cmd in COMMANDS:
                a = command(cmd, name, motor, tmp)
                _wall(a, alone)  # fills the cache
                _wall(a, env)  # the worker loads its programs
                worker = [_wall(a, env) for _ in range(repeats)]
                own = [_wall(a, alone) for _ in range(repeats)]
                row = dict(observer=name, motor=motor, command=cmd,
                           worker_s=statistics.median(worker), worker_min_s=min(worker),
                           worker_max_s=max(worker), own_s=statistics.median(own),
                           own_min_s=min(own), own_max_s=max(own))
                rows.append(row)
                print(f"{name:15s} {cmd:11s} worker {row['worker_s']:5.2f} s "
                      f"({min(worker):.2f}-{max(worker):.2f})   own process "
                      f"{row['own_s']:5.2f} s ({min(own):.2f}-{max(own):.2f})", flush=True)
    finally:
        h.run_child([sys.executable, "-m", "pmsmjax", "worker", "--stop"], env, check=False)
        shutil.rmtree(tmp, ignore_errors=True)
    print(h.machine_line())

    def span(lo, hi):
        return lambda r: f"{r[lo]:.2f}-{r[hi]:.2f}"

    h.table(rows, [("observer", "observer", ""), ("command", "command", ""),
                   ("worker, median (s)", "worker_s", ".2f"),
                   ("range", span("worker_min_s", "worker_max_s"), ""),
                   ("own process, median (s)", "own_s", ".2f"),
                   ("range", span("own_min_s", "own_max_s"), "")])
    h.write_report(args.json, rows, benchmark=MODULE, repeats=repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
