import jax
import jax.random as jr
import pytest

import pmsmjax


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
