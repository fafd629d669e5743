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


#: Test files that start first (`make test`: `pytest -n 2 --dist loadgroup
#: --no-loadscope-reorder`): the longest single tests, so that no worker ends the run
#: alone on one of them.
_FIRST = ("test_notebooks.py", "test_main_job.py", "test_readme_commands.py",
          "test_compare.py")


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist every test file but the notebooks' runs in one worker (an
    `xdist_group` per file): its module fixtures (a comparison job, closed-loop runs,
    stability maps) are computed once instead of once per worker, and its tests reuse
    each other's compiled programs. The notebooks (each in its own kernel process) stay
    single tests, spread over the workers; they and the other long runs go first."""
    rank = {name: k for k, name in enumerate(_FIRST)}
    items.sort(key=lambda it: rank.get(it.path.name, len(rank)))  # stable: file order kept
    for item in items:
        if item.path.name != "test_notebooks.py":
            item.add_marker(pytest.mark.xdist_group(item.path.stem))
