"""The test suite's time, cold, and where it goes: `pytest -n 2` (the README's test
command) with an empty compilation cache, profiled per test and per compiled function.

The suite runs in a child process (this checkout's tests, `-p no:cacheprovider`), with
the plugin `benchmarks.compile._suite_plugin` in every worker and a fresh cache folder
(`PMSMJAX_CACHE_DIR`), so every program is compiled as on a clean checkout. Printed and
written:

- wall time, the CPU time of the run and its children (user + system) and the sum of
  the tests' durations (setup, call and teardown, from `--durations=0`);
- the workers' own compile time: tracing, lowering and XLA's backend compile, and the
  part of it in eager operations (one JAX primitive compiled on its own, outside any
  `jit`: each new shape is a program of its own);
- the workers' garbage collection (seconds and collections per generation), how
  often they dropped their compiled programs (the suite's memory-mapping guard) and
  the persistent compilation cache's hits and misses;
- the modules and notebooks that take longest, and the functions whose compiles cost
  most (count and seconds); the JSON also lists every test with its duration and its
  compile time in the worker (`tests`), longest first.

`--quick` runs three small test modules. Other pytest arguments follow `--`:
`python -m benchmarks.compile.suite -- tests/test_eso.py -k fal`.
"""

from __future__ import annotations

import collections
import json
import re
import sys
import tempfile
from pathlib import Path

from .. import _harness as h


MODULE = "benchmarks.compile.suite"
QUICK_TESTS = ("tests/test_frames.py", "tests/test_metrics.py", "tests/test_lock_status.py")
_DURATION = re.compile(r"^\s*([\d.]+)s (call|setup|teardown)\s+(\S+)")
_SUMMARY = re.compile(r"(\d+) passed")


def _is_eager(name: str) -> bool:
    """A compile of one JAX primitive or `jax.numpy` function outside `jit`:
    `jit(multiply)`, `jit(_where)`."""
    import jax
    import jax.numpy as jnp

    if not (name.startswith("jit(") and name.endswith(")")):
        return False
    inner = name[4:-1]
    return hasattr(jax.lax, inner) or hasattr(jnp, inner.lstrip("_")) or inner in (
        "convert_element_type", "broadcast_in_dim", "dynamic_slice", "true_divide")


def profile(paths: list[str], workers: int) -> dict:
    """Run the suite (or `paths`) cold with the plugin; the measured figures."""
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as tmp:  # a late writer
        prof = Path(tmp) / "profile"
        prof.mkdir()
        env = h.child_env(cache=str(Path(tmp) / "cache"),
                          PMSMJAX_SUITE_PROFILE_DIR=str(prof))
        argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p",
                "benchmarks.compile._suite_plugin", "--durations=0", *paths]
        if workers > 0:
            argv += ["-n", str(workers)]
        child = h.run_child(argv, env, check=False)
        if child.returncode != 0 and _SUMMARY.search(child.stdout) is None:
            raise SystemExit(f"the suite did not run (exit {child.returncode}):\n"
                             f"{child.stdout[-3000:]}\n{child.stderr[-2000:]}")
        if child.returncode != 0:  # failures: shown, and the profile of the run all the same
            failures = child.stdout.split("= FAILURES =", 1)[-1].split("slowest durations")[0]
            print(f"the suite failed (exit {child.returncode}):\n{failures[-20000:]}",
                  file=sys.stderr)
        durations = collections.defaultdict(float)
        for line in child.stdout.splitlines():
            m = _DURATION.match(line)
            if m:
                durations[m.group(3)] += float(m.group(1))
        tests: dict = collections.defaultdict(dict)
        functions = collections.defaultdict(lambda: [0, 0.0, 0.0, 0.0])
        gc_s, gc_n, releases, cache = [0.0] * 3, [0] * 3, 0, collections.Counter()
        for f in prof.glob("worker-*.json"):
            data = json.loads(f.read_text())
            tests.update(data["tests"])
            gc_s = [a + b for a, b in zip(gc_s, data["gc"]["s"])]
            gc_n = [a + b for a, b in zip(gc_n, data["gc"]["n"])]
            releases += data["releases"]
            cache.update(data.get("cache", {}))
            for name, row in data["functions"].items():
                functions[name] = [a + b for a, b in zip(functions[name], row)]
    passed = _SUMMARY.search(child.stdout)
    return dict(wall_s=child.wall_s, cpu_s=child.cpu_s, durations=dict(durations),
                returncode=child.returncode,
                tests=dict(tests), functions=dict(functions), gc_s=gc_s, gc_n=gc_n,
                releases=releases, cache=dict(cache),
                passed=int(passed.group(1)) if passed else None)


def summarise(p: dict) -> tuple[list[dict], list[dict], list[dict], list[dict]]:
    """(totals, the longest modules and notebooks, the costliest compiled functions,
    every test with its duration and its compile time in the worker, longest first)."""
    fun = p["functions"]
    eager = [r for n, r in fun.items() if _is_eager(n)]
    total = [sum(r[k] for r in fun.values()) for k in range(4)]
    eager_t = [sum(r[k] for r in eager) for k in range(4)]

    def compile_s(test: str) -> float:
        return sum(p["tests"].get(test, {}).values())

    by_unit = collections.defaultdict(lambda: [0.0, 0.0])
    for test, s in p["durations"].items():
        unit = test if "test_notebook_runs[" in test else test.split("::")[0]
        by_unit[unit][0] += s
        by_unit[unit][1] += compile_s(test)
    totals = [
        dict(item="wall (s)", value=p["wall_s"]),
        dict(item="CPU, user + system (s)", value=p["cpu_s"]),
        dict(item="tests passed", value=str(p["passed"])),
        dict(item="sum of test durations (s)", value=sum(p["durations"].values())),
        dict(item="workers' XLA backend compile (s)", value=total[1]),
        dict(item="workers' tracing (s)", value=total[2]),
        dict(item="workers' lowering (s)", value=total[3]),
        dict(item="programs compiled", value=str(int(total[0]))),
        dict(item="of them eager operations", value=str(int(eager_t[0]))),
        dict(item="eager operations' compile + lowering (s)",
             value=eager_t[1] + eager_t[3]),
        dict(item="workers' garbage collection (s), generations 0/1/2",
             value=" / ".join(f"{v:.1f}" for v in p["gc_s"])),
        dict(item="collections, generations 0/1/2",
             value=" / ".join(str(v) for v in p["gc_n"])),
        dict(item="compiled programs dropped (memory-mapping guard)",
             value=str(p["releases"])),
        dict(item="persistent cache: hits / misses",
             value=f"{p['cache'].get('hits', 0)} / {p['cache'].get('misses', 0)}"),
    ]
    units = [dict(unit=u, s=v[0], compile_s=v[1])
             for u, v in sorted(by_unit.items(), key=lambda x: -x[1][0])[:15]]
    funcs = [dict(function=n, compiles=r[0], backend_s=r[1], lower_s=r[3],
                  trace_s=fun.get(n[4:-1], [0, 0, 0, 0])[2] if n.startswith("jit(") else r[2])
             for n, r in sorted(fun.items(), key=lambda x: -(x[1][1] + x[1][3]))[:15]]
    tests = [dict(test=t, s=s, compile_s=compile_s(t))
             for t, s in sorted(p["durations"].items(), key=lambda x: -x[1])]
    return totals, units, funcs, tests


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    ap = h.parser(__doc__, MODULE, quick_help=f"only {', '.join(QUICK_TESTS)}")
    ap.add_argument("--workers", type=int, default=2,
                    help="pytest-xdist workers (default 2, the README's test command; 0: "
                         "no xdist)")
    args = ap.parse_args(own)
    paths = extra or (list(QUICK_TESTS) if args.quick else [])
    print(h.machine_line())
    p = profile(paths, args.workers)
    totals, units, funcs, tests = summarise(p)
    h.table(totals, [("", "item", ""), ("value", "value", ".1f")],
            title="The suite, cold (" + (" ".join(paths) or "every test") + ")")
    print()
    h.table(units, [("module or notebook", "unit", ""), ("s", "s", ".1f"),
                    ("of it compiling in the worker (s)", "compile_s", ".1f")],
            title="Longest units of work")
    print()
    h.table(funcs, [("function", "function", ""), ("compiles", "compiles", "d"),
                    ("backend s", "backend_s", ".1f"), ("lowering s", "lower_s", ".1f"),
                    ("tracing s", "trace_s", ".1f")],
            title="Costliest compiled functions")
    h.write_report(args.json, dict(totals=totals, units=units, functions=funcs, tests=tests),
                   paths=paths, workers=args.workers)
    return 1 if p["returncode"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
