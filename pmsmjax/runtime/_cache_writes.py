"""Whole-file writes for JAX's persistent compilation cache (`configure` installs them).

JAX's file cache (`jax._src.lru_cache.LRUCache`, jax 0.10) writes an entry in place
(`Path.write_bytes`) when the cache has no size limit, the default and pmsmjax's
setting. Processes that share the cache (the test suite's two workers, the command
line's worker beside a script, a sweep's processes) compile the same small programs at
the same moment when the cache is cold, and one of them then reads an entry the other
is still writing: JAX warns "Error reading persistent compilation cache entry ...
incomplete or truncated stream" and compiles the program itself. Measured: two
processes compiling the same 40 small programs on an empty cache read a half-written
entry in 1 of 12 starts (`python -m benchmarks.reproducers.cache_race`); a cold test
run failed its collection on it (warnings are errors there); a thread polling while one
32 MiB entry is written read it at 0, 2, 4, ... MiB (tests/test_runtime.py checks that
pmsmjax's write never shows a part). A process killed inside JAX's write leaves a
truncated entry that every later process warns about, since JAX never replaces an
existing entry.

`atomic_cache_writes()` makes the unlimited cache's `put` write through
`pmsmjax._files.atomic_write` (a temporary file in the cache folder, then `os.replace`):
a reader finds either no entry (and compiles) or the whole entry. JAX's own code
stays in charge of everything else (keys, the size-limited cache with its file lock,
eviction); where JAX's cache class is not the one described here, nothing is changed.
"""

from __future__ import annotations

from .._files import atomic_write


def _whole_file_put(original, suffix: str):
    """`LRUCache.put` that writes an entry of the unlimited cache (file `key + suffix`)
    through `atomic_write`, and leaves every other case to JAX's `original`."""

    def put(self, key: str, value: bytes, *args, **kwargs) -> None:
        if args or kwargs or getattr(self, "eviction_enabled", True) or not key:
            return original(self, key, value, *args, **kwargs)  # (extra arguments: a later JAX)
        path = self.path / f"{key}{suffix}"
        if not path.exists():  # (JAX's rule: an entry, once written, stays)
            atomic_write(path, value)

    put.__doc__ = (f"{original.__doc__ or ''}\n\n    pmsmjax: entries of the unlimited "
                   "cache are written to a temporary file and renamed into place "
                   "(`pmsmjax.runtime._cache_writes`).")
    put._pmsmjax_original = original
    return put


def atomic_cache_writes() -> bool:
    """Install the whole-file `put` on JAX's file cache class (idempotent); True if it is
    in place, False where this JAX's cache does not have the shape it expects (then
    JAX's own writes stay)."""
    try:
        from jax._src import lru_cache
    except ImportError:
        return False
    cls = getattr(lru_cache, "LRUCache", None)
    put, suffix = getattr(cls, "put", None), getattr(lru_cache, "_CACHE_SUFFIX", None)
    if put is None or not isinstance(suffix, str):
        return False
    if not hasattr(put, "_pmsmjax_original"):
        cls.put = _whole_file_put(put, suffix)
    return True
