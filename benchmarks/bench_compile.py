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

Usage:

    .venv/bin/python benchmarks/bench_compile.py [--observers eso,c-leso] [--timeout 300]
        [--no-cli] [--no-api] [--no-generic] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import write_report  # noqa: E402


ROOT = Path(__file__).resolve().parents[1]

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
from pmsmjax.cli._options import current_from_args, drive_from_args, observer_from_args
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

_CPU = [0.0]  # CPU time of the finished child processes so far

FAST_ROUTE = ("eso", "parallel-model")  # observers with their own route under "auto"


def run(cmd, env, timeout):
    """(wall seconds or None on timeout, CompletedProcess or None)."""
    t0 = time.perf_counter()
    try:
        res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout,
                             cwd=ROOT)
    except subprocess.TimeoutExpired:
        ru = resource.getrusage(resource.RUSAGE_CHILDREN)
        _CPU[0] = ru.ru_utime + ru.ru_stime
        return None, None
    wall = time.perf_counter() - t0
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    res.cpu_s = ru.ru_utime + ru.ru_stime - _CPU[0]  # CPU time of this process
    _CPU[0] = ru.ru_utime + ru.ru_stime
    if res.returncode not in (0, 1):
        raise SystemExit(f"{' '.join(cmd)} failed ({res.returncode}):\n{res.stderr[-3000:]}")
    return wall, res


def api(name, method, env, timeout):
    wall, res = run([sys.executable, "-c", CHILD, name, method], dict(env, PMSMJAX_CACHE="0"),
                    timeout)
    if res is None:
        return dict(timeout=True, limit_s=timeout)
    out = json.loads(res.stdout.strip().splitlines()[-1])
    out["process_s"] = wall
    out["process_cpu_s"] = res.cpu_s
    return out


def cli(name, env, timeout, tmp):
    cmd = [sys.executable, "-m", "pmsmjax", "equilibria", "--observer", name, "--json"]
    cache = tmp / f"cache-{name}"
    shutil.rmtree(cache, ignore_errors=True)
    out = {}
    for key, e in (("cold", dict(env, PMSMJAX_CACHE="0")),
                   ("fill", dict(env, PMSMJAX_CACHE_DIR=str(cache))),
                   ("warm", dict(env, PMSMJAX_CACHE_DIR=str(cache))),
                   ("warm2", dict(env, PMSMJAX_CACHE_DIR=str(cache)))):
        out[f"{key}_s"], res = run(cmd, e, timeout)
        out[f"{key}_cpu_s"] = None if res is None else res.cpu_s
        if res is None:
            break
    for key in ("fill", "warm", "warm2"):
        out.setdefault(f"{key}_s", None)
        out.setdefault(f"{key}_cpu_s", None)
    return out


def fmt(v, limit):
    return f"> {limit:.0f}" if v is None else f"{v:.1f}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--observers", default=None,
                    help="comma-separated subset of the registry (default: all)")
    ap.add_argument("--timeout", type=float, default=300.0,
                    help="limit per process, s (default: %(default)s)")
    ap.add_argument("--no-cli", action="store_true", help="only the API measurements")
    ap.add_argument("--no-api", action="store_true", help="only the CLI measurements")
    ap.add_argument("--no-generic", action="store_true",
                    help="do not also force the generic route for observers with their own")
    ap.add_argument("--out", default="benchmarks/out/bench_compile.json")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from pmsmjax.observers import observer_names

    names = list(observer_names()) if args.observers is None else args.observers.split(",")
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=str(ROOT))
    env.pop("PMSMJAX_CACHE", None)
    env.pop("PMSMJAX_CACHE_DIR", None)
    tmp = Path(tempfile.mkdtemp(prefix="pmsmjax-compile-"))
    load0 = os.getloadavg()
    rows = []
    try:
        for name in names:
            row = dict(observer=name, api={})
            routes = [] if args.no_api else (
                ["auto"] + (["generic"] if name in FAST_ROUTE and not args.no_generic else []))
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
    load1 = os.getloadavg()
    t = args.timeout
    print("\n| observer | route | API first call (s) | its CPU (s) | API warm call (s) | CLI "
          "cold, no cache (s) | its CPU (s) | CLI warm (s) | its CPU (s) |\n"
          "|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        for route, a in (r["api"] or {"cli": {}}).items():  # {}: --no-api
            c = r.get("cli", {}) if route == "cli" else {}
            warm = min((v for v in (c.get("warm_s"), c.get("warm2_s")) if v is not None),
                       default=None)
            kw = "warm_cpu_s" if warm == c.get("warm_s") else "warm2_cpu_s"
            cpu = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
            print(f"| {r['observer']} | {route} | "
                  f"{fmt(a.get('first_s'), t) if a else '-'} | "
                  f"{cpu(a.get('first_cpu_s'))} | "
                  f"{'-' if a.get('timeout') or not a else format(a['second_s'], '.3f')} | "
                  f"{fmt(c.get('cold_s'), t) if c else '-'} | {cpu(c.get('cold_cpu_s'))} | "
                  f"{(fmt(warm, t) if c.get('fill_s') is not None else '-') if c else '-'} | "
                  f"{cpu(c.get(kw))} |")
    write_report(args.out, rows, loadavg_start=load0, loadavg_end=load1,
                 timeout_s=args.timeout)


if __name__ == "__main__":
    main()
