"""Options of the commands whose work is a large sweep run by
`pmsmjax.analysis.run_sweep` (chunked, resumable, sharded over every device, and over
several processes or hosts with `jax.distributed`), defined once.

- chunking and resume: `--chunk-size N`, `--batch-size N`, `--sweep-dir DIR` (default
  `OUT/sweep`; finished chunks there are reused), `--restart` (discard them);
- several processes or hosts: `--coordinator HOST:PORT` (or `auto`), `--num-processes P`,
  `--process-id I`, the arguments of `jax.distributed.initialize`.

A command adds them with `add_sweep_options(parser)`, reads them with
`sweep_settings(args)` (every inconsistency is a `CLIError` naming the option), starts
`jax.distributed` with `init_distributed(settings)` before any JAX computation (only when
`--coordinator` is given), and runs the sweep with `run_sweep_with(settings, fn, grid)`
(or passes `settings.run_sweep_kwargs()` to `run_sweep` itself).
"""

from __future__ import annotations

import argparse
import dataclasses
import os

import jax

from ._output import keep_on_failure
from ._values import CLIError, nonneg_int, positive_int


#: Default points per chunk: None, chosen by `run_sweep` from the measured cost of the
#: work (a chunk of a few seconds, within a memory bound).
DEFAULT_CHUNK_SIZE = None
#: `--coordinator auto`: let `jax.distributed.initialize` find the coordinator, the number
#: of processes and this process's id in the environment (SLURM, Open MPI, Kubernetes,
#: Cloud TPU, or `JAX_COORDINATOR_ADDRESS`).
AUTO = "auto"


def add_sweep_options(parser: argparse.ArgumentParser, *,
                      default_chunk_size: int | None = DEFAULT_CHUNK_SIZE) -> None:
    """Add the groups "sweep" (`--chunk-size`, `--batch-size`, `--sweep-dir`, `--restart`)
    and "several processes or hosts" (`--coordinator`, `--num-processes`, `--process-id`)
    to `parser`."""
    g = parser.add_argument_group(
        "sweep", "The work runs in chunks through pmsmjax.analysis.run_sweep: each chunk "
                 "sharded over every device (all of jax.devices(); on a CPU set "
                 "XLA_FLAGS=--xla_force_host_platform_device_count=N for N devices), "
                 "written to --sweep-dir as soon as it is done, so that an interrupted run "
                 "resumes where it stopped when the same command is run again.")
    g.add_argument("--chunk-size", type=positive_int, default=default_chunk_size,
                   metavar="N",
                   help="points per chunk: the unit of work lost on interruption and of the "
                        "progress bar; a multiple of the device count; with it the chunk "
                        "files stay in --sweep-dir after the sweep (default: "
                        + ("%(default)s" if default_chunk_size is not None else
                           "chosen from the measured cost of the work, chunks of a few "
                           "seconds, and the chunk files deleted once result.npz holds "
                           "them") + ")")
    g.add_argument("--batch-size", type=positive_int, default=None, metavar="N",
                   help="each device evaluates its share of a chunk N points at a time, "
                        "which makes the results bitwise independent of the device and "
                        "process count (default: the whole share at once)")
    g.add_argument("--sweep-dir", default=None, metavar="DIR",
                   help="folder of the chunk files, the manifest sweep.json and result.npz "
                        "(default: OUT/sweep); under several hosts it must be on a file "
                        "system that every host sees")
    g.add_argument("--restart", action="store_true",
                   help="discard the finished chunks in --sweep-dir and start over (default: "
                        "resume a sweep with the same inputs; a finished sweep of other "
                        "inputs there is replaced, an unfinished one refused)")
    d = parser.add_argument_group(
        "several processes or hosts (jax.distributed)",
        "Start the same command once per process, on one machine or on several hosts, "
        "with the same --coordinator and --num-processes and --process-id 0, 1, ..., P-1; "
        "the chunks are sharded over the devices of all processes, and process 0 writes the "
        "outputs.")
    d.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="address of process 0 and a free port there, e.g. node0:12345 "
                        "(localhost:12345 for processes on one machine); 'auto': "
                        "jax.distributed finds the coordinator, the process count and this "
                        "process's id itself under SLURM, Open MPI, Kubernetes or Cloud TPU, "
                        "or reads JAX_COORDINATOR_ADDRESS")
    d.add_argument("--num-processes", type=positive_int, default=None, metavar="P",
                   help="number of processes (needs --coordinator)")
    d.add_argument("--process-id", type=nonneg_int, default=None, metavar="I",
                   help="this process's id, 0 <= I < P; process 0 runs the coordinator "
                        "(needs --coordinator)")


@dataclasses.dataclass(frozen=True)
class SweepSettings:
    """The sweep options of one command, checked (`sweep_settings`).

    - `chunk_size` (None: automatic), `batch_size`: of `run_sweep`; `sweep_dir`: its
      `out_dir`; `resume`: False with `--restart`.
    - `coordinator`: `"HOST:PORT"`, `"auto"` or None (one process, no `jax.distributed`);
      `num_processes`, `process_id`: None where `jax.distributed` finds them itself.
    """

    chunk_size: int | None
    batch_size: int | None
    sweep_dir: str
    resume: bool
    coordinator: str | None = None
    num_processes: int | None = None
    process_id: int | None = None

    @property
    def distributed(self) -> bool:
        """Whether `jax.distributed` is asked for (`--coordinator`)."""
        return self.coordinator is not None

    def run_sweep_kwargs(self, *, progress: bool = True) -> dict:
        """The keyword arguments of `pmsmjax.analysis.run_sweep` these options set."""
        return dict(out_dir=self.sweep_dir, chunk_size=self.chunk_size,
                    batch_size=self.batch_size, resume=self.resume, progress=progress)


def _check_coordinator(text: str) -> str:
    if text == AUTO:
        return text
    host, sep, port = text.rpartition(":")
    ok = bool(sep) and bool(host) and port.isdigit() and 1 <= int(port) <= 65535
    if not ok:
        raise CLIError(f"--coordinator {text!r}: not HOST:PORT; allowed: the host of process "
                       f"0 and a free port there, e.g. localhost:12345 or node0:12345 (PORT "
                       f"1 to 65535), or 'auto' (found by jax.distributed under SLURM, Open "
                       f"MPI, Kubernetes, Cloud TPU or from JAX_COORDINATOR_ADDRESS)")
    return text


def sweep_settings(args: argparse.Namespace, *, out: str | None = None) -> SweepSettings:
    """The checked sweep options of `args` (from `add_sweep_options`). `out`: the folder
    under which the default `--sweep-dir` (`OUT/sweep`) lies; default `args.out`.

    Raises `CLIError` naming the option for: `--num-processes`/`--process-id` without
    `--coordinator`; `--coordinator HOST:PORT` without both of them; `--process-id I`
    not below `--num-processes P`; a malformed `--coordinator`; `--batch-size` larger
    than `--chunk-size`; no `--sweep-dir` and no output folder.
    """
    chunk_size = None if args.chunk_size is None else int(args.chunk_size)
    batch_size = args.batch_size
    if chunk_size is not None and chunk_size < 1:  # argparse checks this; direct callers
        raise CLIError(f"--chunk-size {chunk_size}: allowed: an integer >= 1")
    if batch_size is not None and batch_size < 1:
        raise CLIError(f"--batch-size {batch_size}: allowed: an integer >= 1")
    if batch_size is not None and chunk_size is not None and batch_size > chunk_size:
        raise CLIError(f"--batch-size {batch_size} with --chunk-size {chunk_size}: allowed: "
                       f"1 <= batch size <= chunk size (a divisor of the chunk size per "
                       f"device avoids padding)")
    coordinator, P, pid = args.coordinator, args.num_processes, args.process_id
    if coordinator is None:
        given = [f"{o} {v}" for o, v in (("--num-processes", P), ("--process-id", pid))
                 if v is not None]
        if given:
            raise CLIError(f"{' and '.join(given)}: needs --coordinator HOST:PORT (the "
                           f"address of process 0, the same for every process) or "
                           f"--coordinator auto; without --coordinator the command runs as "
                           f"one process")
    else:
        coordinator = _check_coordinator(coordinator)
        if coordinator != AUTO and (P is None or pid is None):
            missing = " and ".join(o for o, v in (("--num-processes P", P),
                                                   ("--process-id I", pid)) if v is None)
            raise CLIError(f"--coordinator {coordinator} needs {missing} as well (or "
                           f"--coordinator auto, where jax.distributed finds them under "
                           f"SLURM, Open MPI, Kubernetes or Cloud TPU)")
        if P is not None and pid is not None and pid >= P:
            raise CLIError(f"--process-id {pid} with --num-processes {P}: allowed: 0 <= "
                           f"process id <= {P - 1}")
    sweep_dir = args.sweep_dir
    if sweep_dir is None:
        out = getattr(args, "out", None) if out is None else out
        if not out:
            raise CLIError("--sweep-dir: needed when the command has no output folder "
                           "(--out)")
        sweep_dir = os.path.join(out, "sweep")
    elif os.path.exists(sweep_dir) and not os.path.isdir(sweep_dir):
        raise CLIError(f"--sweep-dir {sweep_dir!r} exists and is not a directory")
    return SweepSettings(chunk_size=chunk_size, batch_size=batch_size, sweep_dir=sweep_dir,
                         resume=not args.restart, coordinator=coordinator,
                         num_processes=P, process_id=pid)


def init_distributed(settings: SweepSettings) -> SweepSettings:
    """Start `jax.distributed` as `settings` ask (`--coordinator`), before any JAX
    computation; nothing without `--coordinator`. Returns `settings`.

    Every process blocks here until all `--num-processes` have connected to the
    coordinator (`jax.distributed` gives up after 5 minutes). On CPU, JAX's default
    cross-process collectives (gloo) are used; nothing needs to be set.
    """
    if not settings.distributed:
        return settings
    spelled = f"--coordinator {settings.coordinator}"
    if jax.distributed.is_initialized():
        if settings.num_processes is not None and \
                jax.process_count() != settings.num_processes:
            raise CLIError(f"{spelled} --num-processes {settings.num_processes}: this "
                           f"process already runs jax.distributed with "
                           f"{jax.process_count()} processes")
        return settings
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise CLIError(f"{spelled}: jax.distributed must start before any JAX computation, "
                       f"but this process has already started JAX's backend (call "
                       f"init_distributed first)")
    address = None if settings.coordinator == AUTO else settings.coordinator
    try:
        jax.distributed.initialize(coordinator_address=address,
                                   num_processes=settings.num_processes,
                                   process_id=settings.process_id)
    except (RuntimeError, ValueError, TypeError) as e:
        raise CLIError(f"{spelled}: jax.distributed.initialize failed: {e}") from None
    return settings


def run_sweep_with(settings: SweepSettings, fn, grid, *, metadata=None,
                   on_chunk_done=None, progress: bool = True, keep_result: bool = True):
    """`pmsmjax.analysis.run_sweep(fn, grid, ...)` with the options of `settings`; the
    progress bar on process 0 only; `keep_result=False` for a command that stores the
    outputs in its own file (a finished sweep then keeps its manifest alone). The
    finished chunks in `--sweep-dir` survive a failing or interrupted command
    (`keep_on_failure`), so that running it again resumes.

    `--sweep-dir` holding another sweep: a *finished* one is replaced (its outputs are
    the command's previous outputs, which the command overwrites anyway: running a
    command again with other inputs keeps working as before), an *unfinished* one is a
    `CLIError` naming `--restart` (resuming it was probably meant, with an option
    changed by mistake).
    """
    import json

    from pmsmjax.analysis import run_sweep

    keep_on_failure(settings.sweep_dir)
    kw = dict(metadata=metadata, on_chunk_done=on_chunk_done, keep_result=keep_result,
              **settings.run_sweep_kwargs(progress=progress and is_writer()))
    try:
        return run_sweep(fn, grid, **kw)
    except ValueError as e:
        text = str(e)
        if "holds a different sweep" not in text and "refused to resume" not in text:
            raise
        error = e
    try:
        with open(os.path.join(settings.sweep_dir, "sweep.json")) as f:
            complete = bool(json.load(f).get("complete"))
    except (OSError, ValueError):
        complete = False
    if not complete:
        raise CLIError(f"--sweep-dir {settings.sweep_dir}: {error} From the command line: "
                       f"run the same command to resume it, give another --sweep-dir (or "
                       f"--out), or --restart to discard its chunks") from None
    if is_writer():
        print(f"--sweep-dir {settings.sweep_dir}: replacing the finished sweep of other "
              f"inputs there")
    return run_sweep(fn, grid, **{**kw, "resume": False})


def is_writer() -> bool:
    """True in the process that writes the outputs: process 0 (the only one without
    `jax.distributed`)."""
    return jax.process_index() == 0
