"""A pytest plugin for `benchmarks.compile.suite`: where each worker's compile time goes.

It listens to JAX's compile events (`jax.monitoring`: tracing, lowering to MLIR and XLA's
backend compile, each with the name of the function compiled) and, when the session
ends, writes `worker-PID.json` into `$PMSMJAX_SUITE_PROFILE_DIR`:

- `tests`: per test id, the seconds of each event while it ran (setup, call, teardown);
- `functions`: per compiled function name, `[compiles, backend_s, trace_s, lower_s]`;
- `gc`: the seconds Python's garbage collector ran, per generation, and how many
  collections; `releases`: how many times the worker dropped its compiled programs
  (`jax.clear_caches`, the suite's guard against the memory-mapping limit);
- `cache`: the persistent compilation cache's hits and misses (a hit is a program
  compiled before: by the other worker, a child process, or this worker before it
  dropped its programs or from another function object with the same program; its
  tracing and lowering still run here, XLA's compile does not).

Only the workers' own compiles are seen: a test's child processes are not (their time
is in the test's duration).
"""

from __future__ import annotations

import collections
import gc
import json
import os
import time
from pathlib import Path

import pytest


_EVENTS = {"/jax/core/compile/backend_compile_duration": 1,
           "/jax/core/compile/jaxpr_trace_duration": 2,
           "/jax/core/compile/jaxpr_to_mlir_module_duration": 3}
_current: list[str | None] = [None]
_tests: dict = collections.defaultdict(lambda: collections.defaultdict(float))
_functions: dict = collections.defaultdict(lambda: [0, 0.0, 0.0, 0.0])
_gc = {"s": [0.0, 0.0, 0.0], "n": [0, 0, 0], "start": 0.0}
_releases = [0]
_CACHE_EVENTS = {"/jax/compilation_cache/cache_hits": "hits",
                 "/jax/compilation_cache/cache_misses": "misses"}
_cache = {"hits": 0, "misses": 0}


def _gc_timer(phase: str, info: dict) -> None:
    if phase == "start":
        _gc["start"] = time.perf_counter()
        return
    g = info["generation"]
    _gc["s"][g] += time.perf_counter() - _gc["start"]
    _gc["n"][g] += 1


def _listener(event: str, duration: float, **kwargs) -> None:
    k = _EVENTS.get(event)
    if k is None:
        return
    if _current[0] is not None:
        _tests[_current[0]][event.rsplit("/", 1)[1]] += duration
    row = _functions[str(kwargs.get("fun_name"))]
    row[0] += k == 1
    row[k] += duration


def _cache_listener(event: str, **kwargs) -> None:
    k = _CACHE_EVENTS.get(event)
    if k is not None:
        _cache[k] += 1


def pytest_configure(config):
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_listener)
    jax.monitoring.register_event_listener(_cache_listener)
    gc.callbacks.append(_gc_timer)
    clear = jax.clear_caches

    def counted_clear():
        _releases[0] += 1
        clear()

    jax.clear_caches = counted_clear


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _current[0] = item.nodeid
    yield
    _current[0] = None


def pytest_sessionfinish(session):
    folder = os.environ.get("PMSMJAX_SUITE_PROFILE_DIR")
    if not folder:
        return
    path = Path(folder) / f"worker-{os.getpid()}.json"
    path.write_text(json.dumps({"tests": {k: dict(v) for k, v in _tests.items()},
                                "functions": dict(_functions),
                                "gc": {"s": _gc["s"], "n": _gc["n"]},
                                "releases": _releases[0], "cache": _cache}))
