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
  or `clear_cache()`. Processes share it: its entries are written whole (a temporary
  file renamed into place), so one process never reads an entry that another is still
  writing (JAX writes them in place: `pmsmjax.runtime._cache_writes`).
- **Stored programs.** The compilation cache skips XLA's compile only: Python still
  traces and lowers the program, seconds for the generic equilibrium analysis and about
  ten for identification's Levenberg-Marquardt solve. So with the cache on, the
  equilibrium analysis of `pmsmjax equilibria` and the two programs of `identify` (the
  solve and the covariance at the solution) are also kept traced, as `jax.export`
  programs (StableHLO) in `cache_dir()/exported` (`stored_call`), keyed by the
  function, its static arguments (an observer's class and fields, the options), the
  shapes and dtypes of its array inputs, the pmsmjax version and a hash of its source,
  the jax/jaxlib versions and the backend: a repeated command reads the program instead
  of tracing, and its compile hits the compilation cache. LAPACK's custom calls (QR,
  eigensolvers), which `jax.export` does not guarantee across jaxlib versions, are
  allowed, since the key pins the jaxlib. A stored program that cannot be read or does
  not match is made again from a fresh trace. `PMSMJAX_CACHE=0` turns it off with the
  cache, and `pmsmjax cache --clear` removes it with the cache.

- **Quick compiles (opt-in, `PMSMJAX_QUICK_COMPILE=1`).** XLA's CPU backend spends most
  of a compile in LLVM, once per fused kernel; `QUICK_COMPILE_FLAGS` compile at LLVM's
  lowest optimisation level with XLA's older kernel emitters, one LLVM module per
  program (fewer memory mappings per compiled program), and JAX lowers them without
  Python tracebacks in their source locations (`QUICK_COMPILE_JAX_CONFIG`: what
  profilers and HLO dumps read; a user's `JAX_TRACEBACK_IN_LOCATIONS_LIMIT` wins).
  Programs then compile 2 to 3x faster and run 1.3 to 3x slower (BENCHMARKS.md, "Quick
  compiles"). It pays where thousands of programs each run once, as in the test suite,
  which turns it on for its workers (and the notebooks they run), their subprocesses
  and the notebook it runs in a Jupyter kernel (`tests/conftest.py`); the numbers are
  the same (`tests/test_runtime.py`). Off by default: a user's sweeps and replays run
  the compiled programs many times. A program that runs long even there (a batch of
  10,000 generic-route designs) passes `long_run_compiler_options()` to its
  `jit`: under quick compiles it is still compiled with full optimisation, and otherwise
  the option changes nothing.
- **Fewer garbage collections.** Tracing, lowering and compiling are allocation-heavy
  Python: a program's trace makes hundreds of thousands of short-lived containers, and a
  process that has compiled many programs holds millions of live objects (a test
  worker: 1.7 million), which every full collection scans. `configure` sets CPython's
  collector thresholds to `GC_THRESHOLDS` (a youngest generation of 50,000 instead of
  700): measured on two compile-bound test modules, collection time 6.5-6.9 s -> 0.9-1.0 s
  and the run 134-140 s -> 125-126 s. Garbage is still collected, only in larger
  batches. `PMSMJAX_GC=0` (or `configure(gc_thresholds=False)`) keeps Python's own.

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
fault in `backend_compile` (`benchmarks/reproducers/map_limit.py` shows it). The test suite's
workers did this (about 30,000 mappings halfway through a run, a worker killed in the
tuner's tests). `memory_maps()` tells where a process stands; `release_compiled()` drops
every compiled program (`jax.clear_caches()`) once the mappings pass a fraction of the
limit: programs still in use are compiled again when next called, nothing else changes.
The test suite calls it after every test; a long notebook session or a script that
compiles many designs in one process can call it between phases.
"""

from typing import TYPE_CHECKING

from .._lazy import lazy_exports


# Loaded on first use (`pmsmjax._lazy`): `import pmsmjax` sets the XLA flags from here
# before anything imports JAX, and the command line's client runs without JAX.
if TYPE_CHECKING:
    from ._lapack_pool import (
        LAPACK_MIN_WORK as LAPACK_MIN_WORK,
        LapackCall as LapackCall,
        concurrent_lapack_calls as concurrent_lapack_calls,
    )
    from ._memory import memory_maps as memory_maps, release_compiled as release_compiled
    from ._settings import (
        FAST_LOOP_FLAGS as FAST_LOOP_FLAGS,
        FULL_OPTIMISATION as FULL_OPTIMISATION,
        GC_THRESHOLDS as GC_THRESHOLDS,
        QUICK_COMPILE_FLAGS as QUICK_COMPILE_FLAGS,
        SAFE_FLAGS as SAFE_FLAGS,
        apply_xla_flags as apply_xla_flags,
        cache_dir as cache_dir,
        cache_size as cache_size,
        clear_cache as clear_cache,
        configure as configure,
        long_run_compiler_options as long_run_compiler_options,
    )
    from ._stored import (
        STORED_SUBDIR as STORED_SUBDIR,
        stored_call as stored_call,
        stored_programs_dir as stored_programs_dir,
    )

__getattr__, __dir__ = lazy_exports(__name__, __file__, globals())


__all__ = [
    "FAST_LOOP_FLAGS",
    "FULL_OPTIMISATION",
    "GC_THRESHOLDS",
    "LAPACK_MIN_WORK",
    "QUICK_COMPILE_FLAGS",
    "SAFE_FLAGS",
    "STORED_SUBDIR",
    "LapackCall",
    "apply_xla_flags",
    "cache_dir",
    "cache_size",
    "clear_cache",
    "concurrent_lapack_calls",
    "configure",
    "long_run_compiler_options",
    "memory_maps",
    "release_compiled",
    "stored_call",
    "stored_programs_dir",
]
