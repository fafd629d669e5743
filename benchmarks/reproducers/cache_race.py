"""Reproducer: two processes that share an empty compilation cache and compile the same
programs at the same moment, with JAX's in-place cache writes and with pmsmjax's
whole-file writes (`pmsmjax.runtime._cache_writes`).

Each start is a fresh cache folder and two fresh processes started together; each runs
`pmsmjax.runtime.configure()` and compiles the same `--programs` small programs (array
set-up as at a test module's import, and a few eager operations), with every warning
an error. With JAX's writes, a process sometimes reads an entry the other is still
writing ("Error reading persistent compilation cache entry ... truncated stream");
with pmsmjax's, never. Prints a table (writes, starts, starts with a failed process,
seconds) and writes JSON.

Usage (from the repository root):

    python -m benchmarks.reproducers.cache_race [--starts 10] [--programs 40] [--quick]
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time

from .. import _harness as h


MODULE = "benchmarks.reproducers.cache_race"


CHILD = r"""
import sys, warnings
warnings.simplefilter("error")
programs, jax_writes = int(sys.argv[1]), sys.argv[2] == "1"
import pmsmjax
pmsmjax.runtime.configure()
if jax_writes:  # JAX's own in-place writes back
    from jax._src.lru_cache import LRUCache
    LRUCache.put = LRUCache.put._pmsmjax_original
import jax, jax.numpy as jnp
for n in range(2, programs + 2):
    jax.block_until_ready(jnp.eye(n) * 2.0 + jnp.ones((n, n)))
print("done", flush=True)
"""


def start(cache: str, programs: int, jax_writes: bool) -> list[str]:
    """Two processes on `cache` at once; the stderr of each that did not finish."""
    env = h.child_env(cache=cache, quick_compile=True)
    procs = [subprocess.Popen([sys.executable, "-c", CHILD, str(programs),
                               "1" if jax_writes else "0"], env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for _ in range(2)]
    failed = []
    for p in procs:
        out, err = p.communicate(timeout=600)
        if p.returncode != 0 or "done" not in out:
            failed.append(err[-2000:])
    return failed


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="4 starts of 20 programs each")
    h.size_option(ap, "--starts", full=10, quick=4, help="starts per kind of write")
    h.size_option(ap, "--programs", full=40, quick=20, help="programs each process compiles")
    a = h.parse_args(ap, argv)
    starts, programs = a.starts, a.programs
    rows = []
    for jax_writes in (True, False):
        t0, failed, messages = time.perf_counter(), 0, []
        for _ in range(starts):
            with tempfile.TemporaryDirectory(prefix="pmsmjax-race-") as cache:
                errs = start(cache, programs, jax_writes)
            failed += bool(errs)
            messages += [next((ln for ln in e.splitlines() if "Error reading" in ln),
                              e.strip()[-200:]) for e in errs]
        rows.append(dict(writes="JAX in place" if jax_writes else "pmsmjax whole file",
                         starts=starts, programs=programs, failed_starts=failed,
                         messages=messages[:3],
                         seconds=round(time.perf_counter() - t0, 1)))
    h.table(rows, [("writes", "writes", ""), ("starts", "starts", "d"),
                   ("programs", "programs", "d"), ("failed starts", "failed_starts", "d"),
                   ("s", "seconds", ".1f")])
    for r in rows:
        for m in r["messages"]:
            print(f"  {r['writes']}: {m}")
    h.write_report(a.json, rows, benchmark=MODULE)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
