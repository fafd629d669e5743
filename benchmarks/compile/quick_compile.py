"""Quick compiles (`PMSMJAX_QUICK_COMPILE=1`, `pmsmjax.runtime.QUICK_COMPILE_FLAGS`)
against the default build: what a program saves in compile time and pays in run time.

Each measurement runs in a fresh process with the persistent compilation cache off and
`XLA_FLAGS` cleared, once with the default settings and once with quick compiles:

- the generic equilibrium analysis as `pmsmjax equilibria --observer NAME` calls it
  (`benchmarks.compile.analysis`'s child: the CLI's default drive and operating point):
  the first call (trace, compile, run) and the better of two further calls (the run
  alone);
- a single closed-loop run (`benchmarks.throughput.simulate`'s scenario: zhang750,
  sensored speed control, 125 us, 8000 steps, one drive): the first call and the best of
  five runs, in drive-steps per second.

Usage (from the repository root):

    python -m benchmarks.compile.quick_compile [--observers eso,leso] [--quick]
"""

from __future__ import annotations

import os
import time

from .. import _harness as h
from ..throughput import simulate
from .analysis import api


MODULE = "benchmarks.compile.quick_compile"
OBSERVERS = ("eso", "leso", "parallel-model", "rotor-flux", "c-leso", "gi-leso")


def _env(quick: bool) -> dict:
    return h.child_env(quick_compile=quick, cache=False, clear_xla_flags=True)


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the single run and the ESO's analysis only")
    ap.add_argument("--observers", default=None,
                    help=f"comma-separated observers (default: {','.join(OBSERVERS)})")
    args = ap.parse_args(argv)
    names = h.observer_names(args.observers or ("eso" if args.quick else OBSERVERS))
    t0 = time.perf_counter()
    rows = []
    for quick in (False, True):
        r = simulate.run_worker("single", dict(steps=8000), "all", env=_env(quick))
        rows.append(dict(item="single closed-loop run", quick=quick, **r))
        for name in names:
            r = api(name, "auto", _env(quick), 600)
            rows.append(dict(item=f"equilibria {name}", quick=quick,
                             **{k: r.get(k) for k in ("first_s", "first_cpu_s", "second_s",
                                                      "status", "n", "theta")}))
    by = {(r["item"], r["quick"]): r for r in rows}
    pairs = []
    for item in dict.fromkeys(r["item"] for r in rows):
        a, b = by[(item, False)], by[(item, True)]
        d = max((abs(x - y) for x, y in zip(a.get("theta") or [], b.get("theta") or [])),
                default=None)
        pairs.append(dict(item=item, first=a["first_s"], first_q=b["first_s"],
                          run=a["second_s"], run_q=b["second_s"], dtheta=d))
    print(h.machine_line())
    h.table(pairs, [
        ("program", "item", ""), ("first call, default (s)", "first", ".2f"),
        ("quick (s)", "first_q", ".2f"),
        ("ratio", lambda r: r["first_q"] / r["first"], ".2f"),
        ("run, default (s)", "run", ".4f"), ("quick (s)", "run_q", ".4f"),
        ("ratio", lambda r: r["run_q"] / r["run"], ".2f"),
        ("equilibrium angles differ by (rad)", "dtheta", ".1e")])
    print(f"Total {time.perf_counter() - t0:.0f} s; load average at the end "
          f"{os.getloadavg()[0]:.2f}.")
    h.write_report(args.json, rows, benchmark=MODULE)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
