"""Memory mappings of a long-running process: how many it holds against the system's limit
(`memory_maps`), and dropping the compiled programs before it reaches it
(`release_compiled`; the package docstring says why)."""

from __future__ import annotations

import gc

import jax


def memory_maps() -> tuple[int, int] | None:
    """`(mappings, limit)`: the memory mappings of this process and the system's limit
    (`vm.max_map_count`); `None` where the system does not tell (not Linux)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            n = sum(1 for _ in f)
        with open("/proc/sys/vm/max_map_count") as f:
            limit = int(f.read())
    except (OSError, ValueError):
        return None
    return n, limit


def release_compiled(fraction: float = 1 / 3) -> bool:
    """Drop JAX's compiled programs (`jax.clear_caches()`) when this process's memory
    mappings exceed `fraction` of the system's limit (see the module docstring: at the
    limit the next compilation kills the process); return whether it did.

    `fraction` in [0, 1]: 0 always releases. Where the mappings cannot be counted (not
    Linux) it does nothing and returns False.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"release_compiled: fraction={fraction!r}; allowed: a number in "
                         "[0, 1] (a share of vm.max_map_count)")
    state = memory_maps()
    if state is None or state[0] <= fraction * state[1]:
        return False
    jax.clear_caches()
    gc.collect()
    return True
