"""What the sweep runner `run_sweep` costs on top of the work it runs.

Two workloads, each timed three ways in one process (start-up, imports and compilation
excluded: every timed call is warm, i.e. a second or later call with the same compiled
code):

- `feasibility`: the closed-form feasibility map of the matched LESO (zhang2022 (34)-(36))
  on a strongly salient variant of zhang750 (L_q = 12.3 mH), 0.5 p.u. speed, i_q = 1 p.u.,
  over a 2001 x 2001 grid of (zeta1, w1/|w0|) = 4,004,001 designs (`--quick`: 501 x 501).
  "API": `pmsmjax.analysis.feasibility_map` (one jitted, vmapped call, the map in memory);
  "command": `pmsmjax feasibility ... --no-plot --restart` called in this process (the
  sweep, its files, the command's own `feasibility.npz` and `feasibility.json`); "work":
  the command's own per-point function, `jit(vmap(point))` over the whole grid in memory;
  "runner": `run_sweep` of that function with its default chunk size (files written);
  "fresh process": the command as a user runs it, `python -m pmsmjax feasibility` with the
  persistent compilation cache filled by a first run, the map time it prints
  ("classified N designs in T s": tracing, loading the compiled code, the sweep; start-up
  and the command's own output files excluded) and its wall time, next to the API as a
  script calls it in a fresh process with the same cache (its first call: tracing,
  loading the compiled code, the map), the two run in turn; and "as a user times it":
  the whole command minus the same command on 11 x 11 (fresh output folders, medians),
  in a process of its own and through the resident worker.
- `simulation`: the comparison job's run sweep (`tuning.compare`: one closed-loop
  simulation per point, the ESO's paper design, the `--quick` grid of 60 runs, or of
  `--runs` repetitions of it). "work": `jit(vmap(point))` over the grid in memory;
  "runner": `run_sweep` with the job's chunk size.

Reported: points per second of each (median times), the command's rate over the API's and
the runner's overhead `runner / work - 1`, both as medians of the ratios within a round:
the calls are made in turn, `--repeats` rounds, so that the changing load of a shared
machine falls on all of them alike.

Usage (from the repository root):

    python -m benchmarks.throughput.sweep_overhead [--quick] [--repeats N]
"""

from __future__ import annotations

import contextlib
import inspect
import io
import json
import os
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from .. import _harness as h


MODULE = "benchmarks.throughput.sweep_overhead"


def _interleaved(fns: dict, repeats: int) -> dict:
    """Median wall time of each of `fns` (warm: each is called once first), called in
    turn `repeats` times, so that a change of the machine's load (shared with other jobs)
    falls on all of them alike; also the median of each one's ratio to the first within a
    round (`ratio/<name>`)."""
    for f in fns.values():
        f()
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, f in fns.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    first = next(iter(fns))
    out = {k: statistics.median(v) for k, v in times.items()}
    for k in fns:
        out[f"ratio/{k}"] = statistics.median(
            a / b for a, b in zip(times[k], times[first]))
    return out


def _in_memory(point, grid):
    """The work alone: `jit(vmap(point))` over the whole `grid` in memory, fetched."""
    flat = {k: jax.numpy.asarray(v) for k, v in grid.items()}
    vpoint = jax.jit(jax.vmap(point))

    def work():
        jax.tree_util.tree_map(np.asarray, jax.block_until_ready(vpoint(flat)))
    return work


def feasibility(n_axis, repeats, tmp):
    import pmsmjax as pj
    from pmsmjax import analysis
    from pmsmjax.analysis import grid_product, run_sweep
    from pmsmjax.cli import _feasibility as cf, main

    # the LESO, as `feasibility_map` maps it (the command's default observer is the ESO,
    # whose map takes the general route)
    args = ["--observer", "leso", "--set", "L_q=12.3e-3", "--i-q", "1", "--speed", "0.5",
            "--zeta1", f"0:5:{n_axis}", "--ratio", f"0:2:{n_axis}"]
    n = n_axis * n_axis
    z, r = np.linspace(0, 5, n_axis), np.linspace(0, 2, n_axis)
    drive = pj.replace_params(pj.preset("zhang750"), L_q=12.3e-3)

    def api():
        fm = analysis.feasibility_map(drive, [0.5], z, r, i_dq=(0.0, 1.0))
        jax.block_until_ready(fm.status)
        np.asarray(fm.status), np.asarray(fm.stable_theta_deg)

    out = os.path.join(tmp, "feas")
    printed = []

    def command():
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            assert main(["feasibility", *args, "--no-plot", "--restart", "--out", out]) == 0
        printed.append(buf.getvalue())

    command()  # compile (and make the command's per-point function)
    m = re.search(r"sweep: (\d+) chunks? of up to (\d+) points", printed[-1])
    manifest = json.loads(Path(out, "sweep", "sweep.json").read_text())

    # the command's own per-point function: the work alone, and through run_sweep
    (point, _method), = cf._POINT_FNS.values()
    w_r = float(drive.w_rated)
    grid = grid_product(w_m=np.array([0.5 * w_r]), x=z, y=r)
    work = _in_memory(point, grid)

    sweep_dir = os.path.join(tmp, "runner")

    kw = dict(out_dir=sweep_dir, resume=False, progress=False)
    if inspect.signature(run_sweep).parameters["chunk_size"].default is inspect.Parameter.empty:
        from pmsmjax.cli._sweep_options import DEFAULT_CHUNK_SIZE  # the command's default

        kw["chunk_size"] = DEFAULT_CHUNK_SIZE

    def runner():
        run_sweep(point, grid, **kw)

    t = _interleaved({"api": api, "command": command, "work": work, "runner": runner},
                     repeats)
    t_api, t_cmd, t_work, t_run = t["api"], t["command"], t["work"], t["runner"]
    files = sorted(os.listdir(sweep_dir))
    nbytes = sum(os.path.getsize(os.path.join(sweep_dir, f)) for f in files)
    # the command as a user runs it: a fresh process, the persistent compilation cache
    # warm (filled by a first run); its own printed time of the map ("classified N
    # designs in T s": tracing, loading the compiled code, the sweep) and its wall time
    env = h.child_env(cache=os.path.join(tmp, "cache"))
    cmd = [sys.executable, "-m", "pmsmjax", "feasibility", *args, "--no-plot", "--restart",
           "--out", os.path.join(tmp, "fresh")]
    # the API as a script runs it: a fresh process, the same cache, the time of the first
    # `feasibility_map` call (tracing, loading the compiled code, the map), made in turn
    # with the command's runs so that both see the same load
    api_script = _FRESH_API.format(n_axis=n_axis)
    fresh, fresh_api = [], []
    for k in range(repeats + 1):
        p = h.run_child(cmd, env, timeout=1800)
        t_map = float(re.search(r"classified \d+ designs in ([0-9.]+) s", p.stdout).group(1))
        q = h.python_child(api_script, env=env, timeout=1800)
        if k:  # the first run fills the cache
            fresh.append((t_map, p.wall_s))
            fresh_api.append(float(q.stdout.split()[-1]))
    user = {mode: _as_a_user_times_it(args, n_axis, repeats, tmp, worker=mode == "worker")
            for mode in ("own", "worker")}
    t_fresh = statistics.median(t for t, _ in fresh)
    wall_fresh = statistics.median(w for _, w in fresh)
    t_fresh_api = statistics.median(fresh_api)
    fresh_ratio = statistics.median(a / c for a, (c, _) in zip(fresh_api, fresh))
    return dict(workload="feasibility", points=n, api_s=t_api, command_s=t_cmd,
                command_over_api=t["ratio/command"],
                runner_over_work=t["ratio/runner"] / t["ratio/work"],
                fresh_map_s=t_fresh, fresh_wall_s=wall_fresh, fresh_api_s=t_fresh_api,
                fresh_command_over_api=fresh_ratio, work_s=t_work, runner_s=t_run,
                user_own_s=user["own"], user_worker_s=user["worker"],
                chunks=int(m.group(1)), chunk_size=int(m.group(2)),
                compile_s=manifest.get("compile_seconds"),
                runner_files=len(files), runner_bytes=nbytes)


def _as_a_user_times_it(args, n_axis, repeats, tmp, *, worker):
    """The map's time as a user measures it: the whole command (`python -m pmsmjax
    feasibility`, a fresh output folder each run, the compilation cache filled) minus the
    same command on an 11 x 11 grid, medians of `repeats` runs each, made in turn; in a
    process of its own (`PMSMJAX_WORKER=0`) or through the resident worker."""
    env = h.child_env(cache=os.path.join(tmp, "cache"), worker=worker,
                      PMSMJAX_WORKER_DIR=os.path.join(tmp, "sockets"))
    small = list(args)
    small[small.index("--zeta1") + 1], small[small.index("--ratio") + 1] = "0:5:11", "0:2:11"
    runs = {"big": [], "small": []}
    if worker:
        h.run_child([sys.executable, "-m", "pmsmjax", "worker", "--start"], env)
    try:
        for k in range(repeats + 1):
            for name, a in (("big", args), ("small", small)):
                out = os.path.join(tmp, f"user-{name}-{int(worker)}-{k}")
                p = h.run_child([sys.executable, "-m", "pmsmjax", "feasibility", *a,
                                 "--no-plot", "--out", out], env, timeout=1800)
                if k:  # the first run of each fills the cache (and the worker)
                    runs[name].append(p.wall_s)
    finally:
        if worker:
            h.run_child([sys.executable, "-m", "pmsmjax", "worker", "--stop"], env,
                        check=False)
    return statistics.median(runs["big"]) - statistics.median(runs["small"])


_FRESH_API = """
import time
import numpy as np
import pmsmjax as pj
pj.runtime.configure()
from pmsmjax import analysis
n = {n_axis}
z, r = np.linspace(0, 5, n), np.linspace(0, 2, n)
drive = pj.replace_params(pj.preset("zhang750"), L_q=12.3e-3)
t0 = time.perf_counter()
fm = analysis.feasibility_map(drive, [0.5], z, r, i_dq=(0.0, 1.0))
np.asarray(fm.status), np.asarray(fm.stable_theta_deg)
print(time.perf_counter() - t0)
"""


def simulation(runs, repeats, tmp):
    from pmsmjax.analysis import SweepGrid, run_sweep
    from tuning.compare import job as tc

    config = tc.CompareConfig.quick()
    base = config.grid(index=True)
    name = "eso"
    cols = tc._design_columns(None)  # the paper's design
    f_runs, _ = tc._sweep_fns(config, name, len(cols))
    n0 = len(base["case"])
    g = {k: np.tile(v, runs) for k, v in base.items()}
    g["index"] = np.arange(len(g["index"]))
    n = n0 * runs
    g.update({k: np.full(n, v) for k, v in cols.items()})
    grid = SweepGrid(g, shape=(n,), axes={"point": np.arange(n)})
    work = _in_memory(f_runs, grid)

    sweep_dir = os.path.join(tmp, "sim")
    kw = dict(out_dir=sweep_dir, resume=False, progress=False)
    if "chunk_size" in tc.CompareConfig.__dataclass_fields__:
        cs = getattr(config, "chunk_size")
        if cs is not None:
            kw["chunk_size"] = cs

    if "keep_chunks" in inspect.signature(run_sweep).parameters:
        kw["keep_chunks"] = False  # as the comparison job runs it

    def runner():
        run_sweep(f_runs, grid, **kw)

    t = _interleaved({"work": work, "runner": runner}, repeats)
    t_work, t_run = t["work"], t["runner"]
    manifest = json.loads(Path(sweep_dir, "sweep.json").read_text())
    return dict(workload="simulation", points=n, api_s=None, command_s=None,
                runner_over_work=t["ratio/runner"], work_s=t_work,
                runner_s=t_run, chunks=manifest["n_chunks"], chunk_size=manifest["chunk_size"],
                compile_s=manifest.get("compile_seconds"),
                runner_files=len(os.listdir(sweep_dir)),
                runner_bytes=sum(os.path.getsize(os.path.join(sweep_dir, f))
                                 for f in os.listdir(sweep_dir)))


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="501 x 501 designs and 60 runs, two repeats")
    ap.add_argument("--repeats", type=int, default=None,
                    help="warm calls per median (default 3; --quick: 2)")
    ap.add_argument("--runs", type=int, default=8,
                    help="repetitions of the comparison's quick grid (60 runs each)")
    ap.add_argument("--workloads", default="feasibility,simulation")
    ap.add_argument("--label", default="", help="a name for this code state (e.g. before)")
    a = ap.parse_args(argv)
    a.repeats = a.repeats or (2 if a.quick else 3)
    import pmsmjax as pj

    pj.runtime.configure()  # the command's process settings (XLA flags), before any work
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for w in a.workloads.split(","):
            if w == "feasibility":
                row = feasibility(501 if a.quick else 2001, a.repeats, tmp)
            else:
                row = simulation(1 if a.quick else a.runs, a.repeats, tmp)
            row["label"] = a.label
            rows.append(row)
            n = row["points"]
            line = (f"{a.label:8s} {w:12s} {n:>9d} points: work {n / row['work_s']:9.3g} /s, "
                    f"runner {n / row['runner_s']:9.3g} /s ({row['chunks']} chunks of "
                    f"{row['chunk_size']}, {row['runner_files']} files, "
                    f"{row['runner_bytes'] / 1e6:.1f} MB), runner overhead "
                    f"{row['runner_over_work'] - 1:+.1%}")
            if row["api_s"]:
                line += (f"; API {n / row['api_s']:9.3g} /s, command {n / row['command_s']:9.3g}"
                         f" /s, command/API rate {1 / row['command_over_api']:.2f}; fresh "
                         f"process (compile cache warm): map {n / row['fresh_map_s']:9.3g} /s "
                         f"({row['fresh_map_s']:.2f} s, wall {row['fresh_wall_s']:.1f} s), "
                         f"API's first call {n / row['fresh_api_s']:9.3g} /s "
                         f"({row['fresh_api_s']:.2f} s), "
                         f"command/API rate {row['fresh_command_over_api']:.2f}; as a user "
                         f"times it (whole command minus 11 x 11): own process "
                         f"{row['user_own_s']:.2f} s, {row['api_s'] / row['user_own_s']:.2f} "
                         f"of the API's warm rate; through the worker "
                         f"{row['user_worker_s']:.2f} s, "
                         f"{row['api_s'] / row['user_worker_s']:.2f}")
            print(line, flush=True)
    print(h.machine_line())

    def rate(key):
        return lambda r: r["points"] / r[key] if r.get(key) else None

    h.table(rows, [
        ("workload", "workload", ""), ("points", "points", ",d"),
        ("API (pt/s)", rate("api_s"), ".3g"),
        ("command in process (pt/s)", rate("command_s"), ".3g"),
        ("command / API", lambda r: r.get("command_over_api") and 1 / r["command_over_api"],
         ".2f"),
        ("fresh command: map (s)", "fresh_map_s", ".2f"),
        ("fresh API: first call (s)", "fresh_api_s", ".2f"),
        ("command / API, fresh", "fresh_command_over_api", ".2f"),
        ("as a user times it: own process / worker (s)",
         lambda r: r.get("user_own_s") and f"{r['user_own_s']:.2f} / {r['user_worker_s']:.2f}",
         ""),
        ("work (pt/s)", rate("work_s"), ".3g"), ("runner (pt/s)", rate("runner_s"), ".3g"),
        ("runner overhead", lambda r: f"{r['runner_over_work'] - 1:+.1%}", ""),
        ("chunks x size", lambda r: f"{r['chunks']} x {r['chunk_size']:,}", ""),
        ("files, MB", lambda r: f"{r['runner_files']}, {r['runner_bytes'] / 1e6:.1f}", "")])
    h.write_report(a.json, rows, benchmark=MODULE, quick=a.quick, repeats=a.repeats,
                   devices=jax.device_count())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
