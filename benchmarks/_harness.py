"""The one harness every benchmark uses: options, timing, child processes, the observer
registry, tables and the JSON report.

- `parser(doc, module)`: an `argparse` parser with `--quick` (a run of under a minute on
  2 cores) and `--json PATH` (default `results/benchmarks/KIND.NAME.json`; `results/` is
  ignored by git).
- `steady(fn)`: steady-state time of a warm callable (best and median over repeats,
  wall and process CPU time); `first_call(fn)`: the first call (trace, compile, run);
  `lower_compile(jitted, *args)`: tracing and lowering apart from XLA's compile.
- `child_env(...)`, `run_child(argv, env)`, `python_child(code, *args, env=...)`: a
  measurement in a fresh process (wall and CPU time, a time limit, the JSON object its
  last line prints), with the settings the benchmarks vary (quick compiles, the
  compilation cache, another checkout, XLA flags, one core).
- `observer_names(selection)`, `paper_drive(name)`, `sampling_period(preset)`: the
  observers of the registry (`pmsmjax.observers.observer_names()`), the motor of each
  one's paper and its sampling period, for the benchmarks that loop over observers.
- `table(rows, columns)`: a Markdown table, printed; `write_report(path, rows, **meta)`:
  `{"meta": machine_info() + meta, "rows": rows}` as strict JSON.

Run the benchmarks as modules from the repository root, e.g.
`python -m benchmarks.throughput.simulate --quick`.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results" / "benchmarks"


# ------------------------------------------------------------------------------ options

def parser(doc: str | None, module: str, *, quick_help: str = "a short run (under a "
           "minute on 2 cores)") -> argparse.ArgumentParser:
    """The parser of benchmark `module` (`benchmarks.KIND.NAME`): its description from the
    module docstring `doc`, `--quick` and `--json` (default
    `results/benchmarks/KIND.NAME.json`)."""
    name = module.removeprefix("benchmarks.")
    ap = argparse.ArgumentParser(
        prog=f"python -m {module}", description=(doc or "").split("\n\n")[0],
        epilog="\n\n".join((doc or "").split("\n\n")[1:]) or None,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--json", default=str(RESULTS / f"{name}.json"), metavar="PATH",
                    help=f"write the results here (default: results/benchmarks/{name}.json)")
    return ap


def size_option(ap: argparse.ArgumentParser, flag: str, *, full: int, quick: int,
                help: str) -> None:
    """An integer option `flag` of `ap` whose default is `full`, or `quick` under `--quick`
    (`parse_args` fills it in)."""
    action = ap.add_argument(flag, type=int, default=None,
                             help=f"{help} (default {full}; {quick} with --quick)")
    ap.set_defaults(**{f"_size_{action.dest}": (full, quick)})


def parse_args(ap: argparse.ArgumentParser, argv=None) -> argparse.Namespace:
    """`ap.parse_args(argv)` with every `size_option` not given set to its default."""
    a = ap.parse_args(argv)
    for key, sizes in list(vars(a).items()):
        if key.startswith("_size_"):
            (full, quick), dest = sizes, key.removeprefix("_size_")
            if getattr(a, dest) is None:
                setattr(a, dest, quick if a.quick else full)
            delattr(a, key)
    return a


def add_child_options(ap: argparse.ArgumentParser) -> None:
    """`--quick-compile` and `--pythonpath`, the settings of `child_env` that the
    fresh-process benchmarks expose."""
    ap.add_argument("--quick-compile", action="store_true",
                    help="quick compiles in the children (PMSMJAX_QUICK_COMPILE=1, the test "
                         "suite's setting); default: the users' flags")
    ap.add_argument("--pythonpath", default=None, metavar="DIR",
                    help="run the children against the pmsmjax of this checkout (a "
                         "before/after on one machine); default: this one")


# ------------------------------------------------------------------------------ machine

def cpu_model() -> str:
    """The processor's model name (`/proc/cpuinfo`), else `platform.processor()`."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """Where and when a measurement was made: CPU model, cores, platform, Python, NumPy,
    jax/jaxlib and the default backend, the date (UTC) and the load average. (pmsmjax is
    imported first, so that JAX's backend starts with the flags it sets on import.)"""
    import jax
    import jaxlib
    import numpy as np

    import pmsmjax  # noqa: F401  (before JAX starts its backend)

    return dict(
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        cpu=cpu_model(), cores=os.cpu_count(),
        cores_usable=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
        else os.cpu_count(),
        platform=platform.platform(), python=platform.python_version(),
        numpy=np.__version__, jax=jax.__version__, jaxlib=jaxlib.__version__,
        backend=jax.default_backend(), devices=[str(d) for d in jax.devices()],
        loadavg=list(os.getloadavg()))


def machine_line() -> str:
    """One line naming the machine, printed before a benchmark's table."""
    m = machine_info()
    return (f"{m['cpu']}, {m['cores']} cores; jax/jaxlib {m['jax']}/{m['jaxlib']} "
            f"({m['backend']}); Python {m['python']}; load average {m['loadavg'][0]:.2f}")


# ------------------------------------------------------------------------------ timing

@dataclasses.dataclass
class Timing:
    """Steady-state time of one call (s): best and median wall time, best process CPU
    time, and how many samples they come from."""
    best_s: float
    median_s: float
    cpu_s: float
    samples: int

    def rate(self, work: float) -> float:
        """`work` per second of the best wall time (e.g. drive-steps/s)."""
        return work / self.best_s

    def cpu_rate(self, work: float) -> float:
        """`work` per second of process CPU time (insensitive to waiting for a core)."""
        return work / self.cpu_s


def _block(out):
    import jax

    return jax.block_until_ready(out)


def steady(fn: Callable[[], object], *, repeats: int = 5, min_time: float = 0.0,
           per_sample: float = 0.0, max_samples: int = 50) -> Timing:
    """Time `fn` (already warm; its result is waited for): at least `repeats` samples and
    at least `min_time` seconds in all (at most `max_samples` samples); each sample calls
    `fn` until `per_sample` seconds have passed (at least once) and takes the time per
    call."""
    walls, cpus = [], []
    t_start = time.perf_counter()
    while len(walls) < repeats or (time.perf_counter() - t_start < min_time
                                   and len(walls) < max_samples):
        n, c0, t0 = 0, time.process_time(), time.perf_counter()
        while True:
            _block(fn())
            n += 1
            el = time.perf_counter() - t0
            if el >= per_sample:
                break
        walls.append(el / n)
        cpus.append((time.process_time() - c0) / n)
    return Timing(min(walls), statistics.median(walls), min(cpus), len(walls))


def first_call(fn: Callable[[], object]) -> tuple[float, object]:
    """(wall seconds, result) of a first call: tracing, compiling and running."""
    t0 = time.perf_counter()
    out = _block(fn())
    return time.perf_counter() - t0, out


def lower_compile(jitted, *args) -> tuple[dict, object]:
    """Trace and lower `jitted` (a `jax.jit` function) for `args`, then compile it:
    `({"trace_lower_s", "compile_s", "temp_bytes"}, compiled)`."""
    t0 = time.perf_counter()
    lowered = jitted.lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    mem = compiled.memory_analysis()
    return dict(trace_lower_s=t1 - t0, compile_s=t2 - t1,
                temp_bytes=int(getattr(mem, "temp_size_in_bytes", -1))), compiled


# ------------------------------------------------------------------------------ children

ONE_CORE_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false"


def child_env(*, quick_compile: bool | None = None, cache: bool | str | None = None,
              pythonpath: str | None = None, xla_flags: str | None = None,
              clear_xla_flags: bool = False, one_core: bool = False, worker: bool = False,
              **extra) -> dict:
    """The environment of a fresh measurement process.

    **Arguments:**

    - `quick_compile`: `PMSMJAX_QUICK_COMPILE` 1 / 0 (None: inherited).
    - `cache`: False turns the persistent compilation cache off (`PMSMJAX_CACHE=0`), a
      path uses that cache folder (`PMSMJAX_CACHE_DIR`), None leaves it as it is.
    - `pythonpath`: import pmsmjax from this checkout (`PYTHONSAFEPATH`: not from the
      working folder).
    - `xla_flags`: appended to `XLA_FLAGS` (after clearing it with `clear_xla_flags`).
    - `one_core`: single-threaded XLA and BLAS (pin the process with `run_child(...,
      pinned=True)`).
    - `worker`: let `pmsmjax` commands use a resident worker (`PMSMJAX_WORKER`); off by
      default, so that every command measured is a process of its own.
    - `extra`: further variables (a value None removes the variable).
    """
    env = dict(os.environ)
    env.setdefault("MPLBACKEND", "Agg")
    env["PMSMJAX_WORKER"] = "1" if worker else "0"
    if quick_compile is not None:
        env["PMSMJAX_QUICK_COMPILE"] = "1" if quick_compile else "0"
    if cache is False:
        env["PMSMJAX_CACHE"] = "0"
        env.pop("PMSMJAX_CACHE_DIR", None)
    elif isinstance(cache, (str, Path)):
        env.pop("PMSMJAX_CACHE", None)
        env["PMSMJAX_CACHE_DIR"] = str(cache)
    if pythonpath:
        env["PYTHONPATH"] = str(pythonpath)
        env["PYTHONSAFEPATH"] = "1"
    flags = "" if clear_xla_flags else env.get("XLA_FLAGS", "")
    if one_core:
        flags = f"{flags} {ONE_CORE_XLA_FLAGS}"
        env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if xla_flags:
        flags = f"{flags} {xla_flags}"
    if flags.strip():
        env["XLA_FLAGS"] = flags.strip()
    else:
        env.pop("XLA_FLAGS", None)
    for k, v in extra.items():
        if v is None:
            env.pop(k, None)
        else:
            env[k] = str(v)
    return env


MODES = dict(one="one core (pinned, single-threaded XLA and BLAS)",
             all="all cores (XLA's default threading)",
             sharded="all cores (the batch split over one XLA host device per core)")


def mode_env(mode: str) -> dict:
    """The environment of a measurement under `mode` (`MODES`); "one" also needs
    `run_child(..., pinned=True)`."""
    if mode == "one":
        return child_env(one_core=True)
    if mode == "sharded":
        return child_env(xla_flags=f"{ONE_CORE_XLA_FLAGS} "
                         f"--xla_force_host_platform_device_count={os.cpu_count()}")
    return child_env(OMP_NUM_THREADS=None)


@dataclasses.dataclass
class Child:
    """A finished (or timed-out) child process: wall and CPU seconds (None on timeout),
    exit code, output, and the JSON object of its last output line if it printed one."""
    wall_s: float | None
    cpu_s: float | None
    returncode: int | None
    stdout: str
    stderr: str
    result: dict | None

    @property
    def timed_out(self) -> bool:
        return self.wall_s is None


def children_cpu() -> float:
    """CPU seconds (user + system) of this process's finished children so far."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_child(argv: Sequence[str], env: dict | None = None, *, timeout: float | None = None,
              pinned: bool = False, cwd: str | Path = ROOT, check: bool = True) -> Child:
    """Run `argv` (e.g. `[sys.executable, "-m", "pmsmjax", ...]`) to completion in a fresh
    process, pinned to core 0 with `pinned` (where `taskset` exists). CPU time counts the
    process and its own children (user + system). A run past `timeout` is killed and
    returned with `wall_s=None`; a non-zero exit raises with `check` (its stderr's tail)."""
    cmd = list(argv)
    if pinned and shutil.which("taskset"):
        cmd = ["taskset", "-c", "0", *cmd]
    cpu0, t0 = children_cpu(), time.perf_counter()
    try:
        p = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True,
                           timeout=timeout)
    except subprocess.TimeoutExpired as e:
        def text(s):
            return s.decode(errors="replace") if isinstance(s, bytes) else (s or "")

        return Child(None, None, None, text(e.stdout), text(e.stderr), None)
    wall, cpu = time.perf_counter() - t0, children_cpu() - cpu0
    if check and p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {p.returncode}):\n"
                           f"{p.stderr[-3000:]}")
    result = None
    lines = p.stdout.strip().splitlines()
    if lines:
        try:
            result = json.loads(lines[-1])
        except ValueError:
            result = None
    return Child(wall, cpu, p.returncode, p.stdout, p.stderr, result)


def python_child(code: str, *args: str, env: dict | None = None,
                 timeout: float | None = None, pinned: bool = False) -> Child:
    """`run_child` of `python -c code args...` (the interpreter running this one)."""
    return run_child([sys.executable, "-c", code, *args], env, timeout=timeout,
                     pinned=pinned)


def module_child(module: str, *args: str, env: dict | None = None,
                 timeout: float | None = None, pinned: bool = False) -> Child:
    """`run_child` of `python -m module args...` from the repository root (a benchmark's
    own worker: `module_child("benchmarks.throughput.simulate", "--worker", ...)`)."""
    return run_child([sys.executable, "-m", module, *args], env, timeout=timeout,
                     pinned=pinned)


def worker_result(payload: object) -> None:
    """A worker's answer to `run_child`: one JSON line, last."""
    from pmsmjax._files import json_text

    print(json_text(payload, indent=None), flush=True)


# ------------------------------------------------------------------------------ observers

def observer_names(selection: str | Sequence[str] | None = None) -> list[str]:
    """The observers to measure: the whole registry (`pmsmjax.observers.observer_names()`,
    in registration order) or the comma-separated `selection`, checked against it."""
    from pmsmjax.observers import observer_names as registry

    names = list(registry())
    if selection is None:
        return names
    chosen = [n for n in (selection.split(",") if isinstance(selection, str) else selection)
              if n]
    unknown = [n for n in chosen if n not in names]
    if unknown:
        raise SystemExit(f"unknown observer(s) {', '.join(unknown)}; the registry has "
                         f"{', '.join(names)}")
    return chosen


def paper_drive(name: str) -> str:
    """The motor preset of observer `name`'s paper (its class's `paper_motor`:
    `pmsmjax.observers.paper_drive`), the drive the tuner uses for it."""
    from pmsmjax.observers import paper_drive as drive_of

    return drive_of(name)[0]


def sampling_period(preset: str) -> float:
    """The sampling period (s) of motor `preset`'s drive (`tuning.sampling_period`)."""
    from tuning import sampling_period as period

    return period(preset)


# ------------------------------------------------------------------------------ output

def ints(text: str) -> list[int]:
    """A comma-separated list of whole numbers (an option such as `--batches 1,64`)."""
    return [int(x) for x in text.split(",") if x]


def fmt(value, spec: str = ".3g", missing: str = "-") -> str:
    """`value` formatted with `spec`, or `missing` for None (a timeout, a case not run)."""
    return missing if value is None else format(value, spec)


def table(rows: Sequence[dict], columns: Sequence[tuple[str, object, str]], *,
          title: str | None = None, echo: bool = True) -> str:
    """A Markdown table of `rows`: `columns` are `(header, key or function of the row,
    format spec)`; a missing value prints as "-". Printed unless `echo=False`."""
    def cell(row, get, spec):
        v = get(row) if callable(get) else row.get(get)
        return v if isinstance(v, str) else fmt(v, spec)

    lines = [] if title is None else [title, ""]
    lines.append("| " + " | ".join(h for h, _, _ in columns) + " |")
    lines.append("|" + "|".join("---" if s == "" else "---:" for _, _, s in columns) + "|")
    for r in rows:
        lines.append("| " + " | ".join(cell(r, g, s) for _, g, s in columns) + " |")
    text = "\n".join(lines)
    if echo:
        print(text, flush=True)
    return text


def write_report(path: str | Path, rows, **meta) -> Path:
    """Write `{"meta": machine_info() + meta, "rows": rows}` to `path` (folders made) as
    strict JSON and say where."""
    from pmsmjax._files import write_json

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, dict(meta=dict(machine_info(), **meta), rows=rows))
    print(f"wrote {path}")
    return path
