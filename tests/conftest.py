import os

# Quick compiles (pmsmjax.runtime, QUICK_COMPILE_FLAGS): the suite compiles thousands of
# programs and runs most of them once, so it compiles at LLVM's lowest optimisation level
# with XLA's older kernel emitters, which halves its time. Set here, before pmsmjax is
# imported, so that the workers, their subprocesses (the command-line tests) and the
# notebooks' kernels all inherit it; tests/test_runtime.py checks that both settings give
# the same numbers. PMSMJAX_QUICK_COMPILE=0 runs the suite with the users' default.
os.environ.setdefault("PMSMJAX_QUICK_COMPILE", "1")

import jax  # noqa: E402
import jax.random as jr  # noqa: E402
import pytest  # noqa: E402

import pmsmjax  # noqa: E402


# The test suite is an entry point: the same process settings as the command line
# (pmsmjax.runtime: XLA flags, the persistent compilation cache), applied before any
# computation. The native crashes that killed workers in earlier full runs (inside
# compilation, and inside the cache's reading and writing of executables, which maps code
# too) were the workers reaching the system's limit of memory mappings; the fixture below
# keeps them away from it (pmsmjax.runtime, "Long-running processes").
pmsmjax.runtime.configure()
jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True)
def _bounded_memory_maps():
    """A worker runs hundreds of tests and compiles thousands of programs, each holding
    memory mappings until dropped; at the system's limit (vm.max_map_count) the next
    compilation kills the worker (pmsmjax.runtime: "Long-running processes"). Drop the
    compiled programs whenever a third of the limit is used."""
    yield
    pmsmjax.runtime.release_compiled(1 / 3)


@pytest.fixture
def getkey():
    counter = iter(range(10**9))

    def _getkey():
        return jr.PRNGKey(next(counter))

    return _getkey
