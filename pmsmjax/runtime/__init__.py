"""Process-wide settings for the programs that use pmsmjax: the entry points call
`configure()` once at start-up (the `pmsmjax` command line, `python -m tuning`, the test
suite and the notebooks' first cell). A plain `import pmsmjax` enables `jax_enable_x64`
and puts the XLA flags below into `XLA_FLAGS` (`apply_xla_flags`) when JAX has not
started its backend yet, so a script that only imports pmsmjax gets fast single runs;
if JAX already computed something, it warns once and says how. The compilation cache is
the entry points' (`configure`) alone.

What `configure()` sets, and why (measurements in BENCHMARKS.md):

- **Fast single runs.** XLA's CPU backend compiles a `while` loop (a `lax.scan` over
  time) into one kernel only while its buffers stay below a small byte threshold;
  above it every fusion of the loop body is dispatched on its own, about 1 us per time
  step. A closed-loop drive step is just above the default threshold, so `configure`
  raises it (`--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=...`):
  single runs become about 8x faster, batched runs are unchanged (see `FAST_LOOP_FLAGS`).
- **No hangs.** The hang that the Lyapunov certificate showed on 2-core machines is a
  deadlock of XLA's CPU thread pool in jaxlib's batched LAPACK calls (`solve`, `eigvals`,
  `eigvalsh`, `expm` over a batch of matrices): a call with enough work splits its batch
  over the pool and blocks its own pool thread until the pieces have run, so two such
  calls that XLA runs at the same time take both threads of a 2-core pool and wait for
  each other forever. No setting avoids it short of a pool of one thread (`PJRT_NPROC=1`
  before JAX starts; it costs the in-program parallelism, about 30 % on a batch of
  10,000 generic-route designs on 2 cores), so pmsmjax's programs are written without
  such a pair (the certificate solves one speed at a time), and
  `concurrent_lapack_calls(compiled)` finds the pairs in any compiled program, yours
  included (`jax.jit(f).lower(*args).compile()`); the tests run it on the library's
  programs. `--xla_cpu_multi_thread_eigen=false` (`SAFE_FLAGS`) stays on: it did not
  cause the hang but costs nothing. Asynchronous CPU dispatch stays on. Public reports
  of hangs with it need a host callback inside a `while` loop; `simulate` calls the host
  only after its time loop (`throw=True`) and the analyses not at all. Code that calls
  the host inside a loop can turn it off first:
  `jax.config.update("jax_cpu_enable_async_dispatch", False)` (no measurable cost on the
  closed loop).
- **Persistent compilation cache.** Compiled programs are kept in a per-user directory
  (`cache_dir()`: `$PMSMJAX_CACHE_DIR`, else `$XDG_CACHE_HOME/pmsmjax/jax`, else
  `~/.cache/pmsmjax/jax`), so a repeated command skips XLA compilation. Opt out with
  `PMSMJAX_CACHE=0` (or `configure(cache=False)`); clear it with `pmsmjax cache --clear`
  or `clear_cache()`.
- **Stored programs.** The compilation cache skips XLA's compile only: Python still
  traces and lowers the program, seconds for the generic equilibrium analysis. So with
  the cache on, `pmsmjax equilibria` also keeps its traced analysis as a `jax.export`
  program (StableHLO) in `cache_dir()/exported` (`stored_call`), keyed by the observer's
  class and static fields, the shapes and dtypes of the inputs, the options, the
  pmsmjax version and a hash of its source, and the jax/jaxlib versions: a repeated
  command reads it instead of tracing, and its compile hits the compilation cache. A
  stored program that cannot be read or does not match is made again from a fresh trace.
  `PMSMJAX_CACHE=0` turns it off with the cache, and `pmsmjax cache --clear` removes it
  with the cache.

- **Quick compiles (opt-in, `PMSMJAX_QUICK_COMPILE=1`).** XLA's CPU backend spends most
  of a compile in LLVM, once per fused kernel; `QUICK_COMPILE_FLAGS` compile at LLVM's
  lowest optimisation level with XLA's older kernel emitters. Programs then compile
  2 to 3x faster and run 1.3 to 3x slower (BENCHMARKS.md, "Quick compiles"). It pays where
  thousands of programs each run once, as in the test suite, which turns it on for its
  workers, their subprocesses and the notebooks' kernels (`tests/conftest.py`); the
  numbers are the same (`tests/test_runtime.py`). Off by default: a user's sweeps and
  replays run the compiled programs many times. A program that runs long even there (a
  batch of 10,000 generic-route designs) passes `long_run_compiler_options()` to its
  `jit`: under quick compiles it is still compiled with full optimisation, and otherwise
  the option changes nothing.

XLA reads its flags when the first computation starts the backend, so `configure` must
run before any JAX computation; called later it keeps the backend as it is and warns.
Set `PMSMJAX_FAST_LOOPS=0` to keep XLA's default loop threshold.

**Long-running processes: memory mappings.** Every program XLA compiles for the CPU keeps
its machine code in memory mappings of its own (about 6-10 for a small program, more for
a large one), released only when JAX drops the program. Linux limits the mappings of one
process (`vm.max_map_count`, 65,530 by default). A process that compiles thousands of
distinct programs and keeps them (JAX keeps every compiled program of every jitted
function) reaches the limit, and then the next compilation fails inside LLVM ("LLVM
compilation error: Cannot allocate memory") and the process dies with a segmentation
fault in `backend_compile` (`benchmarks/map_limit.py` shows it). The test suite's
workers did this (about 30,000 mappings halfway through a run, a worker killed in the
tuner's tests). `memory_maps()` tells where a process stands; `release_compiled()` drops
every compiled program (`jax.clear_caches()`) once the mappings pass a fraction of the
limit: programs still in use are compiled again when next called, nothing else changes.
The test suite calls it after every test; a long notebook session or a script that
compiles many designs in one process can call it between phases.
"""

from __future__ import annotations

import gc
import os
import shutil
import warnings
from pathlib import Path

import jax

from pmsmjax.runtime._lapack_pool import LAPACK_MIN_WORK, LapackCall, concurrent_lapack_calls  # noqa: F401 (public, see below)


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
#: fusion emitters, which compile faster for the many small kernels of pmsmjax's programs.
QUICK_COMPILE_FLAGS: tuple[str, ...] = ("--xla_backend_optimization_level=0",
                                        "--xla_cpu_use_fusion_emitters=false")

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


def _backend_started() -> bool:
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


_LATE_WARNED = False


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


def configure(*, cache: bool | None = None, fast_loops: bool | None = None) -> dict:
    """Apply the entry points' process settings (see the module docstring); idempotent.

    **Arguments:**

    - `cache`: use the persistent compilation cache in `cache_dir()`; default from
      `PMSMJAX_CACHE` (on unless it is 0).
    - `fast_loops`: raise XLA's small-loop threshold; default from `PMSMJAX_FAST_LOOPS`
      (on unless it is 0).

    `QUICK_COMPILE_FLAGS` are added when `PMSMJAX_QUICK_COMPILE=1` (off by default).

    Returns what was applied: `{"xla_flags": [...], "cache_dir": str | None,
    "backend_was_started": bool}`.
    """
    cache = _env_flag("PMSMJAX_CACHE", True) if cache is None else bool(cache)
    fast_loops = _env_flag("PMSMJAX_FAST_LOOPS", True) if fast_loops is None else bool(fast_loops)
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
    global _STORE_DIR
    applied_dir = None
    _STORE_DIR = None
    if cache:
        d = cache_dir()
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            warnings.warn(f"compilation cache disabled: cannot create {d}: {e}",
                          RuntimeWarning, stacklevel=2)
        else:
            jax.config.update("jax_compilation_cache_dir", str(d))
            # cache every compiled program that took noticeable time (default 1 s)
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
            applied_dir = str(d)
            _STORE_DIR = d / STORED_SUBDIR
    return dict(xla_flags=os.environ.get("XLA_FLAGS", "").split(), cache_dir=applied_dir,
                backend_was_started=started)


# ---------------------------------------------------------------------------------------
# Stored programs: a traced program kept with `jax.export`, so that a repeated command
# skips Python's tracing and lowering as well as XLA's compile (module docstring).
# ---------------------------------------------------------------------------------------

#: Sub-directory of `cache_dir()` with the stored (exported) programs.
STORED_SUBDIR = "exported"
_STORE_DIR: Path | None = None  # set by `configure` when the cache is on
_SOURCE_HASH: str | None = None


class _Unkeyable(Exception):
    """A static value whose identity cannot be written down stably (a lambda, a closure,
    an object whose repr is its address): such a call is not stored."""


def stored_programs_dir() -> Path | None:
    """Where `stored_call` keeps its programs (`cache_dir()/exported`), or None when
    `configure` did not turn the compilation cache on in this process."""
    return _STORE_DIR


def _can_serialize() -> bool:
    """`jax.export`'s serialisation needs the `flatbuffers` package (a dependency of
    pmsmjax); without it nothing is stored and every call traces as before."""
    import importlib.util

    return importlib.util.find_spec("flatbuffers") is not None


def _source_hash() -> str:
    """SHA-256 of every Python source file of the pmsmjax package (paths and contents):
    any change of the code invalidates every stored program."""
    global _SOURCE_HASH
    if _SOURCE_HASH is None:
        import hashlib

        root = Path(__file__).resolve().parents[1]
        h = hashlib.sha256()
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(b"\0")
            h.update(p.read_bytes())
            h.update(b"\0")
        _SOURCE_HASH = h.hexdigest()
    return _SOURCE_HASH


def _describe(x, depth: int = 0):
    """A stable, hashable description of `x` for the key of a stored program: arrays by
    shape, dtype and weak type (their values are the program's inputs), every other value
    (the static part, baked into the program) by type and value; dataclasses (equinox
    modules) field by field with their class's module and name. Raises `_Unkeyable` for
    anything else (lambdas, closures, objects without a stable repr)."""
    import dataclasses
    import enum
    import types

    import numpy as np

    if depth > 64:
        raise _Unkeyable("nested too deeply")
    if isinstance(x, jax.Array | np.ndarray | np.generic):
        return ("array", tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False)))
    if x is None or isinstance(x, bool | int | float | complex | str | bytes):
        return (type(x).__name__, repr(x))
    if isinstance(x, enum.Enum):
        return ("enum", type(x).__module__, type(x).__qualname__, x.name)
    if isinstance(x, tuple | list):
        return (type(x).__name__, tuple(_describe(v, depth + 1) for v in x))
    if isinstance(x, dict):
        return ("dict", tuple(sorted((repr(k), _describe(v, depth + 1))
                                     for k, v in x.items())))
    if isinstance(x, types.FunctionType):
        if x.__closure__ or "<" in x.__qualname__:
            raise _Unkeyable(f"function {x.__qualname__}")
        return ("function", x.__module__, x.__qualname__)
    if isinstance(x, types.MethodType):
        return ("method", _describe(x.__self__, depth + 1), x.__func__.__qualname__)
    if isinstance(x, type):
        return ("type", x.__module__, x.__qualname__)
    if dataclasses.is_dataclass(x):
        cls = type(x)
        return ("dataclass", cls.__module__, cls.__qualname__,
                tuple((f.name, _describe(getattr(x, f.name, None), depth + 1))
                      for f in dataclasses.fields(x)))
    raise _Unkeyable(f"value of type {type(x).__qualname__}")


def _program_key(tag: str, fn, args) -> str | None:
    import hashlib

    import jaxlib

    from .. import __version__

    try:
        desc = (tag, _describe(fn), _describe(args))
    except _Unkeyable:
        return None
    parts = (repr(desc), __version__, _source_hash(), jax.__version__, jaxlib.__version__,
             repr(jax.config.jax_enable_x64), jax.default_backend())
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


_LOADED: dict = {}  # key -> the jitted call of a program read in this process


def _call_exported(key: str, blob: bytes | None, leaves, out_type):
    call = _LOADED.get(key)
    if call is None:
        exp = jax.export.deserialize(bytearray(blob))
        if [(tuple(a.shape), a.dtype) for a in exp.in_avals] != [(tuple(v.shape), v.dtype)
                                                                 for v in leaves]:
            raise ValueError("stored program: its inputs differ from the call's")
        call = jax.jit(exp.call)
    out = call(*leaves)
    _LOADED[key] = call
    import dataclasses

    names = [f.name for f in dataclasses.fields(out_type)]
    if len(out) != len(names):
        raise ValueError("stored program: its outputs differ from the result type's")
    return out_type(**dict(zip(names, out)))


def stored_call(tag: str, fn, args: tuple, out_type):
    """`fn(*args)` through a stored program, or None (the caller then runs `fn` its own
    way): None when `configure` did not turn the cache on, when a static value in `args`
    has no stable description, or when exporting fails.

    `fn` must be a pure function, traceable by JAX, whose result is an instance of the
    dataclass `out_type` (an equinox module) with array fields; the array leaves of `args`
    are its inputs and every other leaf is static (as `equinox.filter_jit` treats them).
    The program is stored (`jax.export`, StableHLO) under a key made of `tag`, `fn`, the
    static leaves and the shapes and dtypes of the array leaves, the pmsmjax version and a
    hash of its source, the jax/jaxlib versions, `jax_enable_x64` and the backend; a
    stored program that cannot be read, does not match or fails is deleted and made
    again from a fresh trace. XLA's compile of the stored program then hits the persistent
    compilation cache like any other program.
    """
    d = _STORE_DIR
    if d is None or not _can_serialize():
        return None
    import equinox as eqx

    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dyn)
    if any(isinstance(v, jax.core.Tracer) for v in leaves):
        return None  # called inside a transformation: trace as usual
    key = _program_key(tag, fn, args)
    if key is None:
        return None
    # the source hash in the name: programs of an older pmsmjax are removed (below)
    stem = f"{tag}-{_source_hash()[:12]}-"
    path = d / f"{stem}{key}.jaxexport"
    if key in _LOADED:
        return _call_exported(key, None, leaves, out_type)
    if path.is_file():
        try:
            return _call_exported(key, path.read_bytes(), leaves, out_type)
        except Exception:  # noqa: BLE001 - corrupt or stale: make it again
            try:
                path.unlink()
            except OSError:
                pass
    import dataclasses

    names = [f.name for f in dataclasses.fields(out_type)]

    def flat(*xs):
        out = fn(*eqx.combine(jax.tree_util.tree_unflatten(treedef, list(xs)), static))
        if not isinstance(out, out_type):
            raise TypeError(f"stored_call: {tag} returned {type(out).__name__}, not "
                            f"{out_type.__name__}")
        return tuple(getattr(out, n) for n in names)

    try:
        blob = bytes(jax.export.export(jax.jit(flat))(*leaves).serialize())
    except Exception:  # noqa: BLE001 - not exportable: the caller traces as usual
        return None
    try:
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / f".{path.name}.{os.getpid()}.tmp"
        tmp.write_bytes(blob)
        os.replace(tmp, path)
        for old in d.glob(f"{tag}-*.jaxexport"):  # stored by another version of the code
            if not old.name.startswith(stem):
                old.unlink(missing_ok=True)
    except OSError:
        pass  # read-only or full: still run the program just made
    # the same route as a later process (deserialise, call): same compiled program
    try:
        return _call_exported(key, blob, leaves, out_type)
    except Exception:  # noqa: BLE001
        return None
