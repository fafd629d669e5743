"""`python -m tuning compare`: every observer, paper design and tuned, on one common grid
(`tuning.compare`). Writes `comparison.json`, `comparison.md`, `timing.json` and the
figures into `--out`; resumable (run the same command again after an interruption).
Exit status 0 on success, 2 for a bad configuration (one-line message), 3 when the job
was interrupted on purpose (`PMSMJAX_COMPARE_STOP_AFTER`)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import pmsmjax as pj
from pmsmjax.cli import (
    CLIError,
    ListOption,
    add_drive_options,
    add_speed_from_angle_option,
    add_sweep_options,
    init_distributed,
    sweep_settings,
)
from pmsmjax.observers import observer_names


def build_parser(prog: str = "python -m tuning compare") -> argparse.ArgumentParser:
    from .config import TUNERS, CompareConfig

    p = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Which observer for my drive? Runs every registered observer that applies to "
            "the motor (or --observers), with its paper design and the design tuned by "
            "the closed-loop tuner (python -m tuning), on one common grid of closed-loop "
            "speed-controlled sensorless runs (speeds in both directions, no load to "
            "rated load, a speed ramp and a load step, observer-model mismatch of L_d, "
            "L_q, R_s and psi_f, current noise), checks the same grid with the generic "
            "equilibrium analysis, and writes one table (comparison.md), the numbers "
            "(comparison.json) and figures. Interrupted runs continue where they stopped."),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_drive_options(p)  # --motor, --motor-file, --set: as every pmsmjax command
    p.add_argument("--observers", action=ListOption, default=None, metavar="NAME",
                   help=f"registered observers, separated by spaces (default: every one "
                        f"that applies to the motor: {' '.join(observer_names())})")
    p.add_argument("--out", default="results/compare", metavar="DIR",
                   help="job folder (outputs, and the state that makes the job resumable)")
    p.add_argument("--quick", action="store_true",
                   help="a first look, about 80 s on a 2-core CPU from an empty "
                        "compilation cache (CompareConfig.quick; BENCHMARKS.md): a small "
                        "grid, the paper designs only, no equilibrium analysis (add "
                        "--tuner hybrid and --analysis for the tuned designs and the "
                        "feasible fraction)")
    p.add_argument("--tuner", default=None, choices=TUNERS,
                   help="search strategy of the closed-loop tuner for the 'tuned' design "
                        "(default: hybrid, CMA-ES then the gradient polish, as python -m "
                        "tuning; none: the paper designs only)")
    p.add_argument("--tuned-from", nargs="+", default=None, metavar="DIR",
                   help="output folders of `python -m tuning` runs on this motor: each "
                        "one's deployed design is its observer's 'tuned' design here "
                        "(nothing is tuned for those observers; the others are tuned as "
                        "--tuner says)")
    p.add_argument("--analysis", action=argparse.BooleanOptionalAction, default=None,
                   help="run the generic equilibrium analysis of the grid (the feasible "
                        "fraction; default: on, off with --quick)")
    p.add_argument("--tune-steps", type=int, default=None, metavar="N",
                   help="the tuner's budget in evaluations of its training batch")
    p.add_argument("--jobs", type=_jobs, default="auto", metavar="N",
                   help="observers computed side by side in N worker processes (each "
                        "compiles its own observer's programs; the results do not depend "
                        "on N); 'auto': one per CPU core, at most 4; 1 under "
                        "--num-processes")
    # the field's default, not `CompareConfig()`: building a configuration computes,
    # and under --coordinator nothing may start JAX's backend before jax.distributed
    add_speed_from_angle_option(p, "; every run's speed loop takes it, and the tuner "
                                   "tunes with it")
    add_sweep_options(p, default_chunk_size=CompareConfig.__dataclass_fields__[
        "chunk_size"].default)
    p.add_argument("--no-plot", action="store_true", help="do not write the figures")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def _jobs(text: str):
    if text == "auto":
        return text
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be 'auto' or an integer >= 1; got {text!r}")
    return v


def jobs_for(value, distributed: bool) -> int:
    """`--jobs`: 'auto' is one worker per CPU core, at most 4 (each worker holds its own
    compiled programs, about 1.5 GB), and 1 when the job runs under jax.distributed."""
    if distributed:
        return 1
    if value == "auto":
        return max(1, min(os.cpu_count() or 1, 4))
    return value


def main(argv=None, prog: str = "python -m tuning compare") -> int:
    pj.runtime.configure()
    args = build_parser(prog).parse_args(argv)
    from .config import CompareConfig, tuned_designs_from
    from .job import CompareInterrupted, run_comparison
    from .report import markdown

    kw = {"motor": args.motor or "zhang750"}
    if args.motor_file is not None:
        if args.motor is not None:
            print(f"{prog}: error: --motor {args.motor} and --motor-file "
                  f"{args.motor_file}: give one of the two", file=sys.stderr)
            return 2
        kw["motor_file"] = args.motor_file
    if args.set_params:
        kw["set_params"] = tuple(args.set_params)
    if args.observers is not None:
        kw["observers"] = tuple(args.observers)
    kw["chunk_size"] = args.chunk_size
    for opt, field in (("tuner", "tuner"), ("tune_steps", "tune_steps"),
                       ("analysis", "analysis"), ("speed_from_angle", "speed_from_angle")):
        v = getattr(args, opt)
        if v is not None:
            kw[field] = v
    try:
        # `--sweep-dir` given: the sweeps go there (NAME/DESIGN/runs, .../analysis)
        settings = sweep_settings(args, out=args.out)
        sweep_dir = args.sweep_dir
        init_distributed(settings)
        config = CompareConfig.quick(**kw) if args.quick else CompareConfig(**kw)
        if args.tuned_from:
            config = dataclasses.replace(config, tuned_designs=tuned_designs_from(
                args.tuned_from, config.motor))
    except (ValueError, CLIError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    try:
        s = run_comparison(config, args.out, progress=not args.no_progress, log=print,
                           restart=args.restart, plot=not args.no_plot,
                           sweep_dir=sweep_dir, batch_size=settings.batch_size,
                           jobs=jobs_for(args.jobs, settings.distributed))
    except CompareInterrupted as e:
        print(f"{prog}: interrupted: {e}; run again to continue",
              file=sys.stderr)
        return 3
    except ValueError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    import jax

    if jax.process_index() != 0:  # process 0 writes the outputs (perhaps not yet)
        print(f"process {jax.process_index()} done after {time.perf_counter() - t0:.1f} s; "
              f"process 0 writes {args.out}/comparison.json")
        return 0
    print()
    print(markdown(s).split("\n\n## Definitions")[0])
    print(f"wall time {time.perf_counter() - t0:.1f} s "
          f"({s['timing']['runs_per_design']} runs per observer and design); wrote "
          f"{args.out}/comparison.json")
    return 0
