"""`pmsmjax cache`: where the persistent compilation cache is, how big, and clearing it."""

from __future__ import annotations

import argparse

from .. import runtime
from ._command import Command


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--clear", action="store_true",
                   help="delete the cache (the next run of each command compiles again)")


def _run(args: argparse.Namespace) -> int:
    d = runtime.cache_dir()
    if args.clear:
        n = runtime.clear_cache()
        print(f"removed {n} files from {d}")
        return 0
    n, size = runtime.cache_size()
    print(f"compilation cache: {d} ({n} files, {size / 2**20:.1f} MiB)")
    print("opt out: PMSMJAX_CACHE=0; elsewhere: PMSMJAX_CACHE_DIR=DIR; "
          "clear: pmsmjax cache --clear")
    return 0


COMMAND = Command(
    name="cache",
    help="show or clear the persistent compilation cache",
    description="JAX keeps compiled programs in a per-user cache directory so that a "
                "repeated command skips compilation. Shows its location and size, or clears "
                "it (--clear). Set PMSMJAX_CACHE=0 to run without it, PMSMJAX_CACHE_DIR to "
                "move it.",
    add_arguments=_arguments,
    run=_run,
)
