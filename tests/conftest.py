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
    compiled programs whenever half of the limit is used: a release costs 7 to 10 s, and
    the later tests compile their shared programs again. The other half is far more than
    one test adds (a whole worker's run reached about 30,000 mappings halfway, before
    releases existed)."""
    yield
    pmsmjax.runtime.release_compiled(1 / 2)


@pytest.fixture
def getkey():
    counter = iter(range(10**9))

    def _getkey():
        return jr.PRNGKey(next(counter))

    return _getkey


# The longest tests first (measured wall times in BENCHMARKS.md, "The test suite's time").
# pytest-xdist hands tests to its workers in collection order, so a long test collected
# last keeps one worker busy while the other has nothing left: started first, the short
# tests fill in around it. Most of these wait on a subprocess or a notebook's kernel.
# Only the order changes: every test runs, each on its own (none of these has a
# module-scoped fixture that moving it would set up twice).
LONGEST_FIRST = (
    "tests/test_notebooks.py::test_notebook_runs[03_",
    "tests/test_notebooks.py::test_notebook_runs[04_",
    "tests/test_notebooks.py::test_notebook_runs[05_",
    "tests/test_readme_commands.py::test_readme_command_lines_run",
    "tests/test_main_job.py::test_main_job_quick",
    "tests/test_notebooks.py::test_notebook_runs[09_",
    "tests/test_notebooks.py::test_notebook_runs[02_",
    "tests/test_notebooks.py::test_notebook_runs[08_",
    "tests/test_notebooks.py::test_notebook_runs[07_",
    "tests/test_runtime.py::test_quick_compiles_give_the_same_numbers",
    "tests/test_runtime.py::test_cache_is_filled_reused_and_cleared",
    "tests/test_notebooks.py::test_notebook_runs[06_",
    "tests/test_docs.py::test_docs_build_strict",
    "tests/test_notebooks.py::test_notebook_runs[01_",
)


def _rank(nodeid: str) -> int:
    for k, prefix in enumerate(LONGEST_FIRST):
        if nodeid.startswith(prefix):
            return k
    return len(LONGEST_FIRST)


def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda item: _rank(item.nodeid))  # stable: the rest keep their order
