"""Reproducer: a process that reaches the system's memory-mapping limit dies while
compiling (the native crashes of the test suite's workers), and
`pmsmjax.runtime.release_compiled` prevents it.

Each run is a fresh process: it compiles one JAX program, then occupies all but
`--headroom` of the mappings Linux allows it (`vm.max_map_count`; it splits one anonymous
region into alternating read-only / read-write pages), and then compiles `--programs`
distinct small programs, keeping every one (as JAX's jit caches do in a long-running
process). It runs twice: keeping every program, and calling `release_compiled()` after
each compilation. Prints a table (mappings before, programs compiled, exit status, what
the process died of) and writes JSON.

Usage (from the repository root):

    python -m benchmarks.reproducers.map_limit [--headroom 200] [--programs 100] [--quick]
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from .. import _harness as h


MODULE = "benchmarks.reproducers.map_limit"


CHILD = r"""
import ctypes, faulthandler, os, sys
faulthandler.enable()
headroom, programs, release = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1"
import jax, jax.numpy as jnp
import pmsmjax
jnp.ones(3).block_until_ready()
n, limit = pmsmjax.runtime.memory_maps()
libc = ctypes.CDLL(None, use_errno=True)
libc.mmap.restype = ctypes.c_void_p
libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                      ctypes.c_int, ctypes.c_long]
libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
pages = 2 * max(0, (limit - headroom - n) // 2) + 2
base = libc.mmap(None, pages * 4096, 3, 0x22, -1, 0)   # PROT_READ|WRITE, PRIVATE|ANON
for i in range(0, pages, 2):
    libc.mprotect(base + i * 4096, 4096, 1)          # every other page read-only
print("maps", pmsmjax.runtime.memory_maps()[0], "limit", limit, flush=True)
keep = []
for k in range(programs):
    f = jax.jit(lambda x, k=k: jnp.sin(x * k) + jax.lax.fori_loop(
        0, 10, lambda i, y: y * 1.01 + k, x))
    f(jnp.ones(8)).block_until_ready()
    keep.append(f)
    if release:
        pmsmjax.runtime.release_compiled(0.5)
    print("compiled", k + 1, "maps", pmsmjax.runtime.memory_maps()[0], flush=True)
print("done", flush=True)
"""


#: What a process at the mapping limit prints before it dies (LLVM's error, glibc's
#: failed mapping of a library, C++'s failed allocation).
_OOM_MESSAGES = ("Cannot allocate memory", "out of memory", "failed to map", "bad_alloc")


def run(headroom: int, programs: int, release: bool, timeout: float = 600) -> dict:
    """One fresh process (see the module docstring); returns what it did."""
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", CHILD, str(headroom), str(programs),
                        "1" if release else "0"], capture_output=True, text=True,
                       timeout=timeout, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    lines = p.stdout.splitlines()
    compiled = [int(ln.split()[1]) for ln in lines if ln.startswith("compiled")]
    return dict(release=release, headroom=headroom, programs=programs,
                returncode=p.returncode, compiled=max(compiled, default=0),
                finished="done" in lines,
                maps_before=int(lines[0].split()[1]) if lines and lines[0].startswith("maps")
                else None,
                llvm_out_of_memory="Cannot allocate memory" in p.stderr,
                out_of_memory=any(m in p.stderr for m in _OOM_MESSAGES),
                segfault=p.returncode == -11 or "Segmentation fault" in p.stderr,
                fatal_signal=p.returncode in (-6, -11),
                stderr_tail=p.stderr[-600:],
                seconds=round(time.perf_counter() - t0, 1))


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="60 mappings of headroom, 12 programs")
    h.size_option(ap, "--headroom", full=200, quick=60, help="mappings left")
    h.size_option(ap, "--programs", full=100, quick=12, help="programs compiled after")
    a = h.parse_args(ap, argv)
    rows = [run(a.headroom, a.programs, release) for release in (False, True)]
    h.table(rows, [("release", lambda r: str(r["release"]), ""),
                   ("maps before", "maps_before", "d"), ("compiled", "compiled", "d"),
                   ("exit", "returncode", "d"),
                   ("LLVM ENOMEM", lambda r: str(r["llvm_out_of_memory"]), ""),
                   ("segfault", lambda r: str(r["segfault"]), ""), ("s", "seconds", ".1f")])
    h.write_report(a.json, rows, benchmark=MODULE)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
