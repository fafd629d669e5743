"""A plain script's single closed-loop run against scalar C.

Runs, each in a fresh process with `XLA_FLAGS` cleared and pinned to one core (`taskset
-c 0` where available): (a) a script that only does `import pmsmjax` and calls
`pmsmjax.simulate` under `jax.jit` (the scenario of `benchmarks.throughput.simulate`:
zhang750, sensored speed control, 125 us, 8000 steps, one drive); (b) the same with
`PMSMJAX_FAST_LOOPS=0` (XLA's defaults: what a plain import gave before it set its flags);
and the scalar C reference (`benchmarks/reference/closed_loop.c`, float64, one drive).
Reported: steps/s (best of five after compilation, wall time) and the ratio to C.

Usage (from the repository root):

    python -m benchmarks.throughput.plain_script [--quick] [--json FILE]
"""

from __future__ import annotations

from .. import _harness as h
from . import simulate


MODULE = "benchmarks.throughput.plain_script"


def plain(fast: bool, steps: int) -> dict:
    """`simulate`'s single-run worker in a fresh pinned process, with pmsmjax's flags on
    import (`fast`) or XLA's defaults."""
    env = h.child_env(clear_xla_flags=True, PMSMJAX_FAST_LOOPS="1" if fast else "0")
    return simulate.run_worker("single", dict(steps=steps), "one", env=env)


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="2000 steps instead of 8000")
    args = ap.parse_args(argv)
    steps = 2000 if args.quick else 8000
    rows = [dict(run="plain import (flags set on import)", **plain(True, steps)),
            dict(run="plain import, PMSMJAX_FAST_LOOPS=0 (XLA's defaults)",
                 **plain(False, steps)),
            dict(run="scalar C (closed_loop.c, float64)",
                 steps_per_s=simulate.c_rate(steps))]
    c = rows[-1]["steps_per_s"]
    for r in rows:
        r["vs_c"] = r["steps_per_s"] / c
    print(h.machine_line())
    h.table(rows, [("single closed-loop run, B = 1", "run", ""),
                   ("steps/s", "steps_per_s", ".3g"), ("x scalar C", "vs_c", ".2f"),
                   ("first call s", "first_s", ".2f")])
    h.write_report(args.json, rows, benchmark=MODULE, steps=steps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
