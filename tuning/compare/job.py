"""Which observer for my drive? Every registered observer, paper design and tuned, on one
common grid (`python -m tuning compare`): the job that runs it.

The comparison in four modules:

- `tuning.compare.config`: `CompareConfig`, the common grid (speeds in both directions,
  loads, observer-model mismatch cases, current noise), the designs ("paper" and
  "tuned") and which observers apply;
- `tuning.compare.points`: what the sweeps compute at one grid point (a closed-loop run
  and its per-run metrics, `pmsmjax.run_metrics`; the equilibrium analysis) and the
  harmonic sensitivity of a design;
- `tuning.compare.report`: the per-observer metrics (`aggregate`) and `comparison.md`;
- this module: the job, `run_comparison`. Per observer (`observer_entry`): tune the
  "tuned" design (or read it from the job folder), measure the cost of one observer
  step, run both designs' sweeps (`pmsmjax.analysis.run_sweep`, resumable chunk by
  chunk), aggregate; where an observer class compared declares a low-speed limit, one
  sweep of the sensored drive over the grid (`points.sensored_point`: the low-speed
  rule's lowest speeds, `SWEEPS/sensored`); then `comparison.json`, `comparison.md`,
  `timing.json` and the figures (`tuning.compare.plots`). Everything is kept in the job
  folder, so an interrupted job continues where it stopped; `jobs` > 1 computes
  observers side by side in worker processes (`tuning.compare.worker`).
"""

from __future__ import annotations

import functools
import json
import math
import os
import pathlib
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import pmsmjax as pj
from pmsmjax.analysis import SweepGrid, run_sweep
from pmsmjax.cli import atomic_write, json_safe, write_json
from pmsmjax.observers import make_observer as registry_observer, observer_class

from ..evaluate import Evaluator
from ..objective import objective
from ..scenarios import search_set
from ..search import STRATEGIES
from .config import CASE_NAMES, DESIGNS, CompareConfig, applicable_observers
from .points import (
    _design_columns,
    _space,
    _sweep_fns,
    harmonic_sensitivity,
    sensored_point,
)
from .report import aggregate, beyond_points, lock_comparison, markdown


FORMAT = "pmsmjax-compare/1"
#: Environment variable (tests): stop the job with `CompareInterrupted` after this many
#: units of work (a tuning, a sweep chunk, a cost measurement).
STOP_ENV = "PMSMJAX_COMPARE_STOP_AFTER"
#: Keys of comparison.json that hold measurements of the machine (they differ between any
#: two runs, a resumed one included); the last column of comparison.md is one of them.
TIMING_KEYS = ("observer_us_per_step",)


class CompareInterrupted(RuntimeError):
    """Raised when the job stops after `STOP_ENV` units (a simulated interruption)."""


class _Units:
    """Counts finished units of work and stops after `STOP_ENV` of them (tests)."""

    def __init__(self):
        v = os.environ.get(STOP_ENV)
        self.stop = int(v) if v else None
        self.done = 0

    def tick(self, *_):
        self.done += 1
        if self.stop is not None and self.done >= self.stop:
            raise CompareInterrupted(f"stopped after {self.done} units ({STOP_ENV})")


def _tuned(config: CompareConfig, name: str, folder: pathlib.Path, units, progress, log):
    """The tuned design of `name` (physical coordinates of the tuner's design space) and
    its record, from the cache or tuned now."""
    meta_path = folder / f"{name}.json"
    if meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        return (np.asarray(meta["x"], dtype=float) if meta["tuned"] else None), meta
    given = dict(config.tuned_designs)
    if name in given:  # a design tuned elsewhere (`python -m tuning`): nothing to tune
        space = _space(config, name)
        coords = dict(zip(space.names, np.asarray(space.paper_point(), float).tolist()))
        coords.update(dict(given[name]))
        x = np.asarray([coords[k] for k in space.names])
        meta = dict(tuned=True, tuner="given", source="CompareConfig.tuned_designs "
                    "(the design a `python -m tuning` run deployed, `--tuned-from`)",
                    x=x.tolist(), coordinates=space.as_dict(x),
                    design={k: float(v) for k, v in space.design(x).items()}, seconds=0.0)
        folder.mkdir(parents=True, exist_ok=True)
        write_json(meta_path, meta, indent=1)
        return x, meta
    if config.tuner == "none":
        return None, dict(tuned=False, reason="no tuner (tuner = none)")
    folder.mkdir(parents=True, exist_ok=True)
    problem = config.tuning_problem(name)
    space = _space(config, name)
    log(f"tuning {name} ({config.tuner}, {problem.budget} closed-loop simulations) ...")
    t = time.perf_counter()
    # the tuner's low-speed rule: training runs beyond the observer's class left out (and
    # drawn anew), those a load step alone takes below it unloaded
    kept, rule = search_set(problem, "train")
    ev = Evaluator(problem, space, kept)
    z0 = space.to_unconstrained(space.paper_point())
    res = STRATEGIES[config.tuner](ev, z0, budget=problem.budget,
                                   population=problem.population,
                                   key=jr.PRNGKey(config.seed),
                                   learning_rate=problem.learning_rate,
                                   clip_norm=problem.clip_norm, progress=progress)
    x = np.asarray(space.to_physical(jnp.asarray(res.z)))
    meta = dict(tuned=True, tuner=config.tuner, budget=problem.budget, sims=res.sims,
                objective="cvar (tuning.objective)",
                train_runs=kept.n, train_runs_left_out=rule["left_out"],
                train_runs_unloaded=rule["unloaded"],
                low_speed_limit_pu=problem.low_speed_limit_pu,
                train_objective_paper=float(objective(ev.reference, ev.reference,
                                                      problem)[0]),
                train_objective_tuned=float(res.value), x=x.tolist(),
                coordinates=space.as_dict(x),
                design={k: float(v) for k, v in space.design(x).items()},
                seconds=time.perf_counter() - t)
    write_json(meta_path, meta, indent=1)
    units.tick()
    return x, meta


@eqx.filter_jit
def _replay(obs, u_ab, i_ab, T_s):
    return pj.replay(obs, u_ab=u_ab, i_ab=i_ab, T_s=T_s, theta0=0.0, w0=0.0)


def _cost(config: CompareConfig, name: str, folder: pathlib.Path, units) -> dict:
    """Compute cost of one observer step (us, replay at batch 1), cached."""
    path = folder / f"{name}.json"
    if path.is_file():
        return json.loads(path.read_text())
    drive = config.drive()
    obs = registry_observer(name, drive)
    n = int(round(config.t_end / config.T_s))
    t = np.arange(n) * config.T_s
    w = 0.5 * float(drive.w_rated)
    psi = float(drive.three_phase_motor.psi_f)
    u_ab = np.stack([-w * psi * np.sin(w * t), w * psi * np.cos(w * t)], -1)
    i_ab = np.zeros((n, 2))
    jax.block_until_ready(_replay(obs, u_ab, i_ab, config.T_s))
    best = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(_replay(obs, u_ab, i_ab, config.T_s))
        best = min(best, time.perf_counter() - t0)
    out = dict(observer_us_per_step=1e6 * best / n, steps=n)
    folder.mkdir(parents=True, exist_ok=True)
    write_json(path, out, indent=None)
    units.tick()
    return out


def _sweep(fn, grid, out_dir, config, metadata, progress, units, batch_size):
    return run_sweep(fn, grid, out_dir=out_dir, chunk_size=config.chunk_size,
                     batch_size=batch_size, metadata=metadata,
                     progress=progress and jax.process_index() == 0, resume=True,
                     on_chunk_done=units.tick, keep_chunks=False)


class _Context:
    """What every observer's part of the job shares (see `observer_entry`)."""

    def __init__(self, config, out, sweeps, grid, progress, log, batch_size):
        self.config, self.out, self.sweeps, self.grid = config, out, sweeps, grid
        self.progress, self.log, self.batch_size = progress, log, batch_size

    def entry_path(self, name: str) -> pathlib.Path:
        return self.out / "observers" / f"{name}.json"


def observer_entry(ctx: _Context, name: str, units, *, class_name: str | None = None):
    """One observer's part of the job: tune (or load the tuned design), measure the cost
    per step, run both designs' sweeps and aggregate. Returns `(entry, timing)` and keeps
    both in `OUT/observers/NAME.json`, so that a resumed job (or the parent of worker
    processes, `jobs`) reads them instead of computing them again."""
    path = ctx.entry_path(name)
    if path.is_file():
        rec = json.loads(path.read_text())
        return rec["entry"], rec["timing"]
    config, out, sweeps, grid = ctx.config, ctx.out, ctx.sweeps, ctx.grid
    progress, log, batch_size = ctx.progress, ctx.log, ctx.batch_size
    n_runs = len(grid["case"])
    tim = {}
    design_t, meta = _tuned(config, name, out / "tuned", units, progress, log)
    tim["tuning_s"] = meta.pop("seconds", None)
    tim.update(_cost(config, name, out / "cost", units))
    # measured on this machine: differs between any two runs (`TIMING_KEYS`)
    entry = {"class": class_name or observer_class(name).__name__, "designs": {},
             "tuning": meta, "observer_us_per_step": tim["observer_us_per_step"]}
    for dname, design in (("paper", None), ("tuned", design_t)):
        if dname == "tuned" and design is None:
            entry["designs"][dname] = dict(flags={"all": "tuned design not available: "
                                                  + meta.get("reason", "")})
            continue
        cols = _design_columns(design)
        f_runs, f_feas = _sweep_fns(config, name, len(cols))
        sweep_dir = sweeps / name / dname
        md = dict(observer=name, design=dname, config=config.fingerprint())
        log(f"{name}, {dname} design: {n_runs} runs ...")
        t = time.perf_counter()
        g = SweepGrid({**grid, **{k: np.full(n_runs, v) for k, v in cols.items()}},
                      shape=grid.shape, axes=grid.axes)
        runs = _sweep(f_runs, g, sweep_dir / "runs", config, md, progress, units,
                      batch_size)
        tim[f"{dname}_runs_s"] = time.perf_counter() - t
        t = time.perf_counter()
        agrid = {k: v for k, v in g.items() if k != "index"}
        feas = (_sweep(f_feas, agrid, sweep_dir / "analysis", config, md, progress,
                       units, batch_size) if config.analysis else None)
        tim[f"{dname}_analysis_s"] = time.perf_counter() - t
        m = aggregate(runs, feas, config, grid)
        t = time.perf_counter()
        h, why = harmonic_sensitivity(design, config, name)
        tim[f"{dname}_harmonic_s"] = time.perf_counter() - t
        m["harmonic_deg_per_pct"] = h
        if why:
            m["flags"]["harmonic_deg_per_pct"] = why
        entry["designs"][dname] = m
    entry, tim = json_safe(entry), json_safe(tim)
    if jax.process_index() == 0:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_json(path, dict(entry=entry, timing=tim), indent=1)
    return entry, tim


@functools.lru_cache(maxsize=8)
def _sensored_fn(config: CompareConfig):
    """The per-point function of the sensored sweep (one object per configuration, so
    that a resumed job in the same process compiles nothing)."""
    return lambda p: sensored_point(config, p)


def _lowest_speeds(ctx: _Context, limits: dict, units):
    """Per grid point, the lowest speed (p.u.) of the sensored drive on that run
    (`sensored_point`, one sweep for every observer, kept in `SWEEPS/sensored`), where an
    observer class compared declares a low-speed limit (`limits`, p.u. by observer);
    else None (nothing to measure)."""
    if not any(v > 0 for v in limits.values()):
        return None
    ctx.log(f"sensored drive: {len(ctx.grid['case'])} runs (the low-speed rule) ...")
    md = dict(observer="sensored", design="sensored", config=ctx.config.fingerprint())
    r = _sweep(_sensored_fn(ctx.config), ctx.grid, ctx.sweeps / "sensored" / "runs",
               ctx.config, md, ctx.progress, units, ctx.batch_size)
    return np.asarray(r["lowest_speed_pu"]).reshape(-1)


def _run_workers(ctx: _Context, names: list, jobs: int):
    """Run `observer_entry` for `names` in `jobs` worker processes at a time (`python -m
    tuning.compare.worker`); each writes `OUT/observers/NAME.json` and its log to
    `OUT/logs/NAME.log`. Compilation, which dominates a small comparison, is per observer
    and runs on one or two cores per process, so the observers compile side by side."""
    import subprocess
    import sys

    if not names:
        return
    logs = ctx.out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "tuning.compare.worker", "--out", str(ctx.out),
           "--sweep-dir", str(ctx.sweeps)]
    if ctx.batch_size:
        cmd += ["--batch-size", str(ctx.batch_size)]
    ctx.log(f"{len(names)} observers in {min(jobs, len(names))} worker processes (logs: "
            f"{logs}) ...")
    bar = _observer_bar(len(names), ctx.progress)
    queue, running, failed = list(names), {}, []
    try:
        while queue or running:
            while queue and len(running) < jobs:
                n = queue.pop(0)
                f = open(logs / f"{n}.log", "w")
                running[n] = (subprocess.Popen(cmd + ["--observer", n], stdout=f,
                                               stderr=subprocess.STDOUT), f)
            time.sleep(0.2)
            for n, (proc, f) in list(running.items()):
                if proc.poll() is None:
                    continue
                f.close()
                del running[n]
                if proc.returncode != 0:
                    failed.append(n)
                bar.update(1)
                bar.set_postfix_str(n)
    finally:
        for proc, f in running.values():
            proc.kill()
            f.close()
        bar.close()
    if failed:
        raise RuntimeError(f"worker processes failed for {', '.join(failed)}; see "
                           f"{logs}/<observer>.log (the other observers' results are kept: "
                           f"run the job again to continue)")


def _observer_bar(n, progress):
    from tqdm.auto import tqdm

    return tqdm(total=n, desc="observers", unit="obs", disable=not progress)


def run_comparison(config: CompareConfig, out, *, progress: bool = True, log=print,
                   restart: bool = False, plot: bool = False, sweep_dir=None,
                   batch_size: int | None = None, jobs: int = 1) -> dict:
    """Run the comparison into the job folder `out` and return the summary (the content
    of `comparison.json`). Resumable: tuned designs, cost measurements and every sweep
    chunk are kept in `out`, and a second call continues where the first stopped.
    `restart`: start over (`ValueError` if `out` holds a job of another configuration
    unless `restart`). `plot`: also write the figures (`tuning.compare.plots`).
    `sweep_dir`: folder of the sweeps (default `out/sweeps`: one sweep of the runs and
    one of the analysis per observer and design, `NAME/DESIGN/runs`, `.../analysis`);
    `batch_size`: of `run_sweep` (bitwise the same results on any device count).
    `jobs`: observers computed side by side in this many worker processes (1: all in
    this process; not with `jax.distributed`). The results do not depend on it.

    Under `jax.distributed` every process runs this function (the sweeps are sharded
    over the devices of all processes, the tuning is repeated in each, deterministic);
    only process 0 writes the outputs."""
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"`run_comparison(jobs=...)` must be an int >= 1; got {jobs!r}.")
    if jobs > 1 and jax.process_count() > 1:
        raise ValueError("`run_comparison(jobs=...)` > 1 cannot be combined with "
                         "jax.distributed (several processes already share the work); "
                         "give jobs=1.")
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    job = out / "job.json"
    fp = config.fingerprint()
    if job.is_file() and not restart:
        old = json.loads(job.read_text())
        if old.get("fingerprint") != fp:
            raise ValueError(f"{out} holds a comparison with another configuration; give "
                             f"another --out or --restart.")
    sweeps = out / "sweeps" if sweep_dir is None else pathlib.Path(sweep_dir)
    if restart:
        import shutil

        for sub in (out / "tuned", out / "cost", out / "observers", out / "logs", sweeps):
            shutil.rmtree(sub, ignore_errors=True)
    write_json(job, dict(format=FORMAT, fingerprint=fp, config=config.to_dict()), indent=1)
    log = log or (lambda msg: None)
    units = _Units()
    t_start = time.perf_counter()
    ok, skipped = applicable_observers(config)
    grid = config.grid(index=True)
    n_runs = len(grid["case"])
    steps = int(round(config.t_end / config.T_s))
    log(f"comparison on {config.motor}: {len(ok)} observers x {len(DESIGNS)} designs x "
        f"{n_runs} runs ({2 * len(config.speeds_pu)} speeds x {len(config.loads_pu)} loads "
        f"x {len(config.cases)} mismatch cases) of {steps} steps")
    observers, timing = {}, {"observers": {}}
    ctx = _Context(config, out, sweeps, grid, progress, log, batch_size)
    if jobs > 1:
        _run_workers(ctx, [n for n in ok if not ctx.entry_path(n).is_file()], jobs)
    limits = {n: float(observer_class(n).low_speed_limit_pu) for n in ok}
    lowest = _lowest_speeds(ctx, limits, units)
    for name in ok:
        entry, tim = observer_entry(ctx, name, units, class_name=ok[name])
        entry["lock_comparison"] = lock_comparison(
            entry, beyond_points(lowest, limits[name], grid, config))
        observers[name] = entry
        timing["observers"][name] = tim
    timing["wall_s"] = time.perf_counter() - t_start
    timing["runs_per_design"] = n_runs
    timing["steps_per_run"] = steps
    timing["devices"] = [str(d) for d in jax.devices()]
    timing["processes"] = jax.process_count()
    summary = dict(format=FORMAT, motor=config.motor, config=config.to_dict(),
                   grid=dict(speeds_pu=sorted(set(grid.axes["speed_pu"].tolist())),
                             loads_pu=list(config.loads_pu),
                             cases=[dict(zip(CASE_NAMES, c)) for c in config.cases],
                             n_runs=n_runs),
                   observers=observers, skipped=skipped)
    summary = json_safe(summary)
    writer = jax.process_index() == 0
    if writer:
        write_json(out / "comparison.json", summary, indent=1)
        atomic_write(out / "comparison.md", markdown(summary))
        write_json(out / "timing.json", timing, indent=1)
    summary["timing"] = json_safe(timing)
    if plot and writer:
        from .plots import plot_comparison

        plot_comparison(summary, out, sweeps)
    return summary


__all__ = ["CompareInterrupted", "run_comparison"]
