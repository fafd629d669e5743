"""The process settings of the entry points: XLA flags (`apply_xla_flags`,
`configure`), the persistent compilation cache (`cache_dir`) and the compile options of
long-running programs (the package docstring says what each setting does and why)."""

from __future__ import annotations

import gc
import os
import shutil
import sys
import warnings
from pathlib import Path


# No JAX at module level: `import pmsmjax` sets the XLA flags (`apply_xla_flags`) before
# anything imports JAX, and the command line's client (`pmsmjax.runtime._worker`) starts
# without it.


#: XLA flags `configure` adds for fast single runs (see the module docstring).
#: 64 KiB: a single closed-loop run (a few KiB of loop buffers, just above XLA's default
#: threshold) becomes one kernel, while a large batch (1024 runs: hundreds of KiB) stays
#: split into kernels that XLA runs on several cores. With no upper bound (1e8, tried
#: first) batch 1024 ran 15 % slower than with XLA's default; with 64 KiB it runs as
#: fast as with the default (BENCHMARKS.md).
FAST_LOOP_FLAGS = ("--xla_backend_extra_options="
                   "xla_cpu_small_while_loop_byte_threshold=65536",)
#: XLA flags `configure` adds: XLA CPU's multi-threaded Eigen kernels (dot/convolution
#: only; pmsmjax's loops are element-wise fusions) run single-threaded. Public reports of
#: a wedged pool on vmapped graphs found this setting to avoid it; the hang that pmsmjax
#: met was another one (batched LAPACK calls, see the module docstring), which this flag
#: does not prevent. It costs nothing measurable here, so it stays on.
SAFE_FLAGS: tuple[str, ...] = ("--xla_cpu_multi_thread_eigen=false",)
#: XLA flags for quick compiles (opt-in, `PMSMJAX_QUICK_COMPILE=1`; module docstring):
#: LLVM's lowest optimisation level for every kernel, and XLA CPU's older (non-MLIR)
#: fusion emitters, which compile faster for the many small kernels of pmsmjax's programs;
#: and each program as one LLVM module instead of up to 32 compiled in parallel: the same
#: compile time for pmsmjax's small programs, about a third fewer memory mappings per
#: compiled program (a long-running process then reaches the limit of "Long-running
#: processes" later). It changes no run time, so `FULL_OPTIMISATION` leaves it.
QUICK_COMPILE_FLAGS: tuple[str, ...] = ("--xla_backend_optimization_level=0",
                                        "--xla_cpu_use_fusion_emitters=false",
                                        "--xla_cpu_parallel_codegen_split_count=1")
#: JAX settings of quick compiles: no Python traceback in the compiled programs' source
#: locations (JAX's default keeps up to 100 frames per operation, which lowering turns
#: into MLIR locations and XLA carries as metadata; only profilers and HLO dumps read
#: them). Lowering is then faster: a cold run of three compile-bound test modules 4-7 %
#: shorter (BENCHMARKS.md). The cache key leaves locations out, so the programs and
#: their cache entries are the same. A user's `JAX_TRACEBACK_IN_LOCATIONS_LIMIT` wins.
QUICK_COMPILE_JAX_CONFIG: dict[str, object] = {"jax_traceback_in_locations_limit": 0}

#: CPython's collector thresholds that `configure` sets (`gc.set_threshold`; module
#: docstring, "Fewer garbage collections"). Tracing and lowering a program allocate
#: hundreds of thousands of short-lived containers (jaxpr equations, MLIR operations);
#: at CPython's default (700, 10, 10) the youngest generation is collected every 700 of
#: them, and every tenth collection of the middle one may scan every live object (1.7
#: million in a test worker, 0.3 s each). With a youngest generation of 50,000 the
#: collections are a twelfth as many and the full ones a fifth.
GC_THRESHOLDS: tuple[int, int, int] = (50_000, 20, 10)

#: The compile options that undo `QUICK_COMPILE_FLAGS` for one program (XLA's defaults).
FULL_OPTIMISATION: dict[str, object] = {"xla_backend_optimization_level": 3,
                                        "xla_cpu_use_fusion_emitters": True}


def long_run_compiler_options() -> dict[str, object] | None:
    """`compiler_options` for `jax.jit` / `eqx.filter_jit` of a program that runs long
    (a large batch, a long loop): under quick compiles (`PMSMJAX_QUICK_COMPILE=1`) such a
    program is still compiled with full optimisation (`FULL_OPTIMISATION`), since its run
    costs more than its compile; otherwise None (the process's own settings)."""
    return dict(FULL_OPTIMISATION) if _env_flag("PMSMJAX_QUICK_COMPILE", False) else None


def _env_flag(name: str, default: bool) -> bool:
    v = os.environ.get(name)
    if v is None or v.strip() == "":
        return default
    if v.strip().lower() in ("0", "false", "no", "off"):
        return False
    if v.strip().lower() in ("1", "true", "yes", "on"):
        return True
    raise ValueError(f"environment variable {name}={v!r}: use 1/0 (or true/false)")


def cache_dir() -> Path:
    """The per-user directory of the persistent compilation cache (it may not exist)."""
    if os.environ.get("PMSMJAX_CACHE_DIR"):
        return Path(os.environ["PMSMJAX_CACHE_DIR"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "pmsmjax" / "jax"


def cache_size() -> tuple[int, int]:
    """(number of files, total bytes) in `cache_dir()`."""
    d = cache_dir()
    if not d.is_dir():
        return 0, 0
    files = [p for p in d.rglob("*") if p.is_file()]
    return len(files), sum(p.stat().st_size for p in files)


def clear_cache() -> int:
    """Delete the persistent compilation cache; return the number of files removed."""
    d = cache_dir()
    n, _ = cache_size()
    if d.is_dir():
        shutil.rmtree(d)
    return n


#: JAX options pmsmjax set through JAX's environment variables before JAX was imported
#: (JAX reads them when it is imported, so setting one imports nothing now): variable ->
#: (option, value, the variable's value before, None: unset). `settle_jax_env` puts the
#: variables back once JAX is in, so that child processes see the user's environment.
_JAX_ENV_SET: dict[str, tuple[str, object, str | None]] = {}
#: The environment as the process had it when pmsmjax was first imported (`start_environ`).
_START_ENVIRON: dict = {}


def start_environ() -> dict:
    """The environment variables as they were when pmsmjax was first imported, before
    pmsmjax or JAX set any (importing JAX sets `TF_CPP_MIN_LOG_LEVEL`, for one): what
    identifies a process's start-up settings (`pmsmjax.runtime._worker.worker_key`)."""
    return dict(_START_ENVIRON or os.environ)


def _set_jax_option(name: str, value: bool | int) -> None:
    """JAX's option `name` (e.g. `"jax_enable_x64"`) to `value`: through `jax.config`
    when JAX is imported, otherwise through its environment variable (`name` upper-case),
    which JAX reads when it is imported; `settle_jax_env` then restores the variable."""
    if "jax" in sys.modules:
        import jax

        jax.config.update(name, value)
        return
    var = name.upper()
    _JAX_ENV_SET[var] = (name, value, _user_jax_env(name))
    os.environ[var] = str(int(value))


def _user_jax_env(name: str) -> str | None:
    """The value the user gave JAX's environment variable of option `name` (None: unset),
    whether or not pmsmjax has set the variable since."""
    var = name.upper()
    return _JAX_ENV_SET[var][2] if var in _JAX_ENV_SET else os.environ.get(var)


def enable_x64() -> None:
    """What `import pmsmjax` does for float64 (and, the first time, it keeps the
    environment for `start_environ`): `jax_enable_x64` on, without importing JAX
    (`_set_jax_option`)."""
    if not _START_ENVIRON:
        _START_ENVIRON.update(os.environ)
    _set_jax_option("jax_enable_x64", True)


def settle_jax_env() -> None:
    """After JAX is imported: the options `_set_jax_option` set through environment
    variables in `jax.config`, and those variables as the user had them."""
    if not _JAX_ENV_SET or "jax" not in sys.modules:
        return
    import jax

    for var, (name, value, before) in list(_JAX_ENV_SET.items()):
        jax.config.update(name, value)
        if before is None:
            os.environ.pop(var, None)
        else:
            os.environ[var] = before
        del _JAX_ENV_SET[var]


def _backend_started() -> bool:
    if "jax" not in sys.modules:  # not imported: nothing can have started
        return False
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


_LATE_WARNED = False


def _apply_quick_jax_config() -> None:
    """`QUICK_COMPILE_JAX_CONFIG` under quick compiles, except a setting the user made
    through JAX's own environment variable."""
    if not _env_flag("PMSMJAX_QUICK_COMPILE", False):
        return
    settle_jax_env()  # with JAX in, the environment holds the user's variables again
    for name, value in QUICK_COMPILE_JAX_CONFIG.items():
        if _user_jax_env(name) is None:
            _set_jax_option(name, value)


def _process_flags(fast_loops: bool) -> tuple[list[str], list[str]]:
    """The XLA flags of this process's settings, and those of them not yet in `XLA_FLAGS`
    (a flag the user set, to any value, counts as set)."""
    flags = list(SAFE_FLAGS) + (list(FAST_LOOP_FLAGS) if fast_loops else [])
    if _env_flag("PMSMJAX_QUICK_COMPILE", False):
        flags += list(QUICK_COMPILE_FLAGS)
    current = os.environ.get("XLA_FLAGS", "")
    return flags, [f for f in flags if f.split("=")[0] not in current]


def apply_xla_flags(fast_loops: bool | None = None, *, stacklevel: int = 2) -> bool:
    """Put `SAFE_FLAGS` and (unless `fast_loops` is False, default from
    `PMSMJAX_FAST_LOOPS`) `FAST_LOOP_FLAGS`, and `QUICK_COMPILE_FLAGS` when
    `PMSMJAX_QUICK_COMPILE=1`, into `XLA_FLAGS` if JAX has not started its
    backend yet. `import pmsmjax` calls it, so that a plain script gets fast single runs
    without `configure()`. If the backend already runs (JAX computed something before
    pmsmjax was imported), the flags cannot take effect: a one-time warning says how to
    get them. Returns whether the flags are in effect."""
    global _LATE_WARNED
    _apply_quick_jax_config()
    if fast_loops is None:
        fast_loops = _env_flag("PMSMJAX_FAST_LOOPS", True)
    flags, missing = _process_flags(fast_loops)
    if not missing:
        return True
    if _backend_started():
        if fast_loops and not _LATE_WARNED:
            _LATE_WARNED = True
            warnings.warn(
                "pmsmjax: JAX started its backend before pmsmjax set its XLA flags, so "
                "single closed-loop runs are several times slower than they can be. "
                "Import pmsmjax before running any JAX computation, or start Python with "
                f"XLA_FLAGS='{' '.join(flags)}' (PMSMJAX_FAST_LOOPS=0 silences this).",
                RuntimeWarning, stacklevel=stacklevel)
        return False
    os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *missing]).strip()
    return True


def configure(*, cache: bool | None = None, fast_loops: bool | None = None,
              gc_thresholds: bool | None = None) -> dict:
    """Apply the entry points' process settings (see the module docstring); idempotent.

    **Arguments:**

    - `cache`: use the persistent compilation cache in `cache_dir()`; default from
      `PMSMJAX_CACHE` (on unless it is 0).
    - `fast_loops`: raise XLA's small-loop threshold; default from `PMSMJAX_FAST_LOOPS`
      (on unless it is 0).
    - `gc_thresholds`: set CPython's collector thresholds to `GC_THRESHOLDS`; default
      from `PMSMJAX_GC` (on unless it is 0). Off leaves them as they are.

    `QUICK_COMPILE_FLAGS` are added when `PMSMJAX_QUICK_COMPILE=1` (off by default).

    Returns what was applied: `{"xla_flags": [...], "cache_dir": str | None,
    "gc_thresholds": (int, int, int), "backend_was_started": bool}` (`gc_thresholds`:
    the collector's thresholds after the call).
    """
    import jax

    from ._cache_writes import atomic_cache_writes
    from ._stored import STORED_SUBDIR, set_stored_programs_dir

    cache = _env_flag("PMSMJAX_CACHE", True) if cache is None else bool(cache)
    fast_loops = _env_flag("PMSMJAX_FAST_LOOPS", True) if fast_loops is None else bool(fast_loops)
    gc_thresholds = (_env_flag("PMSMJAX_GC", True) if gc_thresholds is None
                     else bool(gc_thresholds))
    _apply_quick_jax_config()
    _, missing = _process_flags(fast_loops)
    started = _backend_started()
    current = os.environ.get("XLA_FLAGS", "")
    if missing:
        if started:
            warnings.warn("pmsmjax.runtime.configure() was called after JAX started its "
                          f"backend; XLA flags {missing} are not applied (call it first)",
                          RuntimeWarning, stacklevel=2)
        else:
            os.environ["XLA_FLAGS"] = " ".join([current, *missing]).strip()
    applied_dir = store_dir = None
    if cache:
        d = cache_dir()
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            warnings.warn(f"compilation cache disabled: cannot create {d}: {e}",
                          RuntimeWarning, stacklevel=2)
        else:
            jax.config.update("jax_compilation_cache_dir", str(d))
            # processes sharing the cache never read an entry another is still writing
            atomic_cache_writes()
            # cache every compiled program (JAX's default keeps those over 1 s): a
            # command's few dozen small eager programs (array set-up, unit conversions)
            # otherwise compile afresh in every process, about 1.5 s of a warm identify
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
            applied_dir = str(d)
            store_dir = d / STORED_SUBDIR
    set_stored_programs_dir(store_dir)
    if gc_thresholds:
        gc.set_threshold(*GC_THRESHOLDS)
    return dict(xla_flags=os.environ.get("XLA_FLAGS", "").split(), cache_dir=applied_dir,
                gc_thresholds=gc.get_threshold(), backend_was_started=started)
