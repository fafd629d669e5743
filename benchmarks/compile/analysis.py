"""Compile time of the equilibrium analysis, per observer, and of `pmsmjax equilibria`.

For each observer of the registry (`pmsmjax.observers.observer_names()`), on the drive and
operating point that `pmsmjax equilibria --observer NAME` uses by default (the CLI's
default motor, speed and current, parsed by the CLI's own parser), it measures

- **API, first call**: in a fresh process with the persistent compilation cache off
  (`PMSMJAX_CACHE=0`), the wall time of the first `pmsmjax.analysis.equilibria` call the
  command makes (trace + compile + run), then of a second call (the compiled program
  only). `route = cli` is the call as the command makes it (`method="auto"`: an observer
  family's own route where it declares one: the ESO with fal feedback and the
  parallel-model observer); `route = generic` forces the generic route
  (`method="generic"`), measured as well for the observers that have their own route.
- **CLI**: the whole process `python -m pmsmjax equilibria --observer NAME --json`
  (interpreter start-up, imports, compile, run), wall and CPU time (the machine may be
  shared: CPU time does not count waiting for a core): cold with the cache off
  (`PMSMJAX_CACHE=0`), then with a fresh, empty cache directory (fills it) and again
  (warm: the programs come from the cache).

Every measurement has a time limit (`--timeout`, default 300 s); a run that reaches it is
killed and recorded as "> LIMIT s".

`--quick-compile` measures under quick compiles (the test suite's setting) instead of the
users' flags; `benchmarks.compile.quick_compile` compares the two.

Usage (from the repository root):

    python -m benchmarks.compile.analysis                    # all eight, about 15 min
    python -m benchmarks.compile.analysis --observers leso,c-leso
    python -m benchmarks.compile.analysis --no-api           # the command only, about 5 min
    python -m benchmarks.compile.analysis --quick            # the ESO, about a minute
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

from .. import _harness as h


MODULE = "benchmarks.compile.analysis"

#: The child process: the CLI's defaults for `equilibria --observer NAME`, then two calls
#: of the analysis the command makes; prints one JSON line.
CHILD = r"""
import json, sys, time
t_start = time.perf_counter()
import numpy as np
import jax
import pmsmjax as pj
pj.runtime.configure()
from pmsmjax.cli.__main__ import build_parser
from pmsmjax.cli._drive_options import drive_from_args
from pmsmjax.cli._observer_options import observer_from_args
from pmsmjax.cli._operating_point import current_from_args
from pmsmjax.analysis import equilibria

name, method = sys.argv[1], sys.argv[2]
args = build_parser().parse_args(["equilibria", "--observer", name])
drive = drive_from_args(args)
choice = observer_from_args(args, drive)
i_pu, _ = current_from_args(args, drive)
w0 = float(args.speed) * float(drive.w_rated)
i0 = np.asarray(i_pu) * float(drive.base.I_b)
t_import = time.perf_counter() - t_start

def call():
    t0, c0 = time.perf_counter(), time.process_time()
    eq = equilibria(choice.observer, choice.plant, w0, i0, method=method)
    jax.block_until_ready(eq)
    cpu.append(time.process_time() - c0)
    return time.perf_counter() - t0, eq

cpu = []

first, eq = call()
second, eq2 = call()
third, _ = call()
valid = np.asarray(eq.valid)
print(json.dumps(dict(
    motor=drive.name, speed_pu=float(args.speed), i_pu=list(i_pu), import_s=t_import,
    first_s=first, second_s=min(second, third), first_cpu_s=cpu[0], status=int(eq.status),
    n=int(eq.n),
    theta=[float(t) for t in np.asarray(eq.theta)[valid]],
    x=[[float(v) for v in row] for row in np.asarray(eq.x)[valid]],
    stable=[bool(s) for s in np.asarray(eq.stable)[valid]])))
"""



def _own_route(name: str) -> bool:
    """Whether the observer's class declares its family's own route (`fast_equilibria`),
    which `method="auto"` takes: the generic route is then measured as well."""
    from pmsmjax.observers import AbstractObserver, observer_class

    return observer_class(name).fast_equilibria is not AbstractObserver.fast_equilibria


def api(name: str, method: str, env: dict, timeout: float) -> dict:
    """The analysis as `pmsmjax equilibria --observer NAME` calls it, in a fresh process
    with the compilation cache off: its first and later calls (`CHILD`)."""
    c = h.python_child(CHILD, name, method, env=dict(env, PMSMJAX_CACHE="0"),
                       timeout=timeout)
    if c.timed_out:
        return dict(timeout=True, limit_s=timeout)
    return dict(c.result, process_s=c.wall_s, process_cpu_s=c.cpu_s)


def cli(name: str, env: dict, timeout: float, tmp: Path) -> dict:
    """`python -m pmsmjax equilibria --observer NAME --json` in fresh processes: cold (the
    cache off), filling an empty cache, then warm twice."""
    cmd = [sys.executable, "-m", "pmsmjax", "equilibria", "--observer", name, "--json"]
    cache = tmp / f"cache-{name}"
    shutil.rmtree(cache, ignore_errors=True)
    out = {}
    for key, e in (("cold", dict(env, PMSMJAX_CACHE="0")),
                   ("fill", dict(env, PMSMJAX_CACHE_DIR=str(cache))),
                   ("warm", dict(env, PMSMJAX_CACHE_DIR=str(cache))),
                   ("warm2", dict(env, PMSMJAX_CACHE_DIR=str(cache)))):
        c = h.run_child(cmd, e, timeout=timeout, check=False)
        if c.returncode not in (0, 1, None):
            raise SystemExit(f"{' '.join(cmd)} failed ({c.returncode}):\n{c.stderr[-3000:]}")
        out[f"{key}_s"], out[f"{key}_cpu_s"] = c.wall_s, c.cpu_s
        if c.timed_out:
            break
    for key in ("fill", "warm", "warm2"):
        out.setdefault(f"{key}_s", None)
        out.setdefault(f"{key}_cpu_s", None)
    return out


def fmt(v, limit):
    return f"> {limit:.0f}" if v is None else f"{v:.1f}"


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the ESO only (its own route), API and command")
    ap.add_argument("--observers", default=None,
                    help="comma-separated subset of the registry (default: all)")
    ap.add_argument("--timeout", type=float, default=300.0,
                    help="limit per process, s (default: %(default)s)")
    ap.add_argument("--no-cli", action="store_true", help="only the API measurements")
    ap.add_argument("--no-api", action="store_true", help="only the CLI measurements")
    ap.add_argument("--no-generic", action="store_true",
                    help="do not also force the generic route for observers with their own")
    h.add_child_options(ap)
    args = ap.parse_args(argv)
    if args.quick:
        args.observers, args.no_generic = args.observers or "eso", True
    names = h.observer_names(args.observers)
    env = h.child_env(quick_compile=args.quick_compile, pythonpath=args.pythonpath,
                      PMSMJAX_CACHE=None, PMSMJAX_CACHE_DIR=None)
    tmp = Path(tempfile.mkdtemp(prefix="pmsmjax-compile-"))
    load0 = os.getloadavg()
    rows = []
    try:
        for name in names:
            row = dict(observer=name, api={})
            routes = [] if args.no_api else (
                ["auto"] + (["generic"] if _own_route(name) and not args.no_generic else []))
            for method in routes:
                r = api(name, method, env, args.timeout)
                row["api"]["cli" if method == "auto" else "generic"] = r
                print(f"{name:15s} {method:8s} first "
                      f"{fmt(r.get('first_s'), args.timeout):>7s} s  second "
                      f"{fmt(r.get('second_s'), args.timeout):>7s} s  n={r.get('n')}",
                      flush=True)
            if not args.no_cli:
                row["cli"] = c = cli(name, env, args.timeout, tmp)
                print(f"{name:15s} CLI      cold {fmt(c['cold_s'], args.timeout):>7s} s  "
                      f"fill {fmt(c['fill_s'], args.timeout):>7s} s  warm "
                      f"{fmt(c['warm_s'], args.timeout):>7s} s", flush=True)
            rows.append(row)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    t = args.timeout
    flat = []
    for r in rows:
        for route, a in (r["api"] or {"cli": {}}).items():  # {}: --no-api
            c = r.get("cli", {}) if route == "cli" else {}
            warm = [(c.get(k + "_s"), c.get(k + "_cpu_s")) for k in ("warm", "warm2")]
            warm = min((w for w in warm if w[0] is not None), default=(None, None))
            flat.append(dict(observer=r["observer"], route=route,
                             first=a and fmt(a.get("first_s"), t),
                             first_cpu=a.get("first_cpu_s"),
                             second=None if a.get("timeout") else a.get("second_s"),
                             cold=c and fmt(c.get("cold_s"), t), cold_cpu=c.get("cold_cpu_s"),
                             warm=c and c.get("fill_s") is not None and fmt(warm[0], t),
                             warm_cpu=warm[1]))
    print()
    print(h.machine_line())
    h.table(flat, [
        ("observer", "observer", ""), ("route", "route", ""),
        ("API first call (s)", lambda r: r["first"] or "-", ""),
        ("its CPU (s)", "first_cpu", ".1f"), ("API warm call (s)", "second", ".3f"),
        ("CLI cold, no cache (s)", lambda r: r["cold"] or "-", ""),
        ("its CPU (s)", "cold_cpu", ".1f"), ("CLI warm (s)", lambda r: r["warm"] or "-", ""),
        ("its CPU (s)", "warm_cpu", ".1f")])
    h.write_report(args.json, rows, benchmark=MODULE, loadavg_start=load0,
                   loadavg_end=os.getloadavg(), timeout_s=args.timeout,
                   quick_compile=args.quick_compile, pythonpath=args.pythonpath)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
