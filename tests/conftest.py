import os


# Quick compiles (pmsmjax.runtime, QUICK_COMPILE_FLAGS): the suite compiles thousands of
# programs and runs most of them once, so it compiles at LLVM's lowest optimisation level
# with XLA's older kernel emitters, which halves its time. Set here, before pmsmjax is
# imported, so that the workers (and the notebooks they run), their subprocesses (the
# command-line tests) and the notebook run in a Jupyter kernel all inherit it;
# tests/test_runtime.py checks that both settings give the same numbers.
# PMSMJAX_QUICK_COMPILE=0 runs the suite with the users' default.
os.environ.setdefault("PMSMJAX_QUICK_COMPILE", "1")
# Every `pmsmjax` process the suite starts runs its command itself and leaves no resident
# worker behind (pmsmjax.runtime._worker); tests/test_worker.py turns it on for its own.
os.environ.setdefault("PMSMJAX_WORKER", "0")

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


#: Tests between two counts of the worker's memory mappings: counting reads
#: /proc/self/maps, about 2.7 ms per 5,000 mappings (a worker holds tens of thousands; in
#: two of three cold runs of 11-30 one worker passed half the limit once, late in the run).
MAPS_EVERY = 5
_tests_since_count = [0]


@pytest.fixture(autouse=True)
def _bounded_memory_maps():
    """A worker runs hundreds of tests and compiles thousands of programs, each holding
    memory mappings until dropped; at the system's limit (vm.max_map_count) the next
    compilation kills the worker (pmsmjax.runtime: "Long-running processes"). Drop the
    compiled programs whenever half of the limit is used, counted after every
    `MAPS_EVERY`-th test: a release costs 7 to 10 s, and the later tests compile their
    shared programs again. The other half is far more than `MAPS_EVERY` tests add (a
    whole worker's run reached about 30,000 mappings halfway, before releases
    existed)."""
    yield
    _tests_since_count[0] += 1
    if _tests_since_count[0] < MAPS_EVERY:
        return
    _tests_since_count[0] = 0
    if pmsmjax.runtime.release_compiled(1 / 2) and os.environ.get("PMSMJAX_RELEASE_LOG"):
        # where the suite's time goes: each release costs the later tests their programs
        with open(os.environ["PMSMJAX_RELEASE_LOG"], "a") as f:
            f.write(f"{os.getpid()} {os.environ.get('PYTEST_CURRENT_TEST', '')}\n")


@pytest.fixture
def getkey():
    counter = iter(range(10**9))

    def _getkey():
        return jr.PRNGKey(next(counter))

    return _getkey


# How the two workers share the work. pytest-xdist's default (`-n 2`, `--dist load`)
# hands out single tests, so the tests of one module land on both workers, and each
# worker sets up the module's fixtures and compiles the programs its tests share (the
# persistent compilation cache shares only XLA's part of the larger ones, not the
# tracing). Here the unit of work is a test module, and each notebook one of its own
# (`pytest_xdist_make_scheduler` below). xdist hands the units out in the order of their
# first test, so the longest go first (measured: `python -m benchmarks.compile.suite`
# prints the longest units; the order below is that of a cold run of 11-29): the run
# then does not end with one worker on a long module while the other has nothing left.
# Only the order and the grouping change: every test runs.
NOTEBOOK_TEST = "tests/test_notebooks.py::test_notebook_runs["  # + the notebook's file name
LONGEST_FIRST = (
    "tests/test_identify.py::",
    "tests/test_contract.py::",
    NOTEBOOK_TEST + "03_",
    "tests/test_runtime.py::",
    "tests/test_li_leso.py::",
    "tests/test_compare.py::",
    NOTEBOOK_TEST + "05_",
    "tests/test_main_job.py::",
    NOTEBOOK_TEST + "04_",
    "tests/test_saturated_analysis.py::",
    NOTEBOOK_TEST + "10_",
    "tests/test_harmonic_ripple.py::",
    "tests/test_equilibria.py::",
    "tests/test_firmware.py::",
    "tests/test_readme_commands.py::",
    "tests/test_cli_analysis.py::",
    "tests/test_rotor_flux.py::",
    NOTEBOOK_TEST + "02_",
    "tests/test_startup.py::",
    "tests/test_saturated_observers.py::",
    NOTEBOOK_TEST + "11_",
    "tests/test_tuning.py::",
    "tests/test_identify_saturation.py::",
    NOTEBOOK_TEST + "07_",
    "tests/test_feasibility.py::",
    "tests/test_reduced_order.py::",
    "tests/test_lyapunov.py::",
    "tests/test_docs.py::",
    NOTEBOOK_TEST + "09_",
    "tests/test_firmware_plots.py::",
    NOTEBOOK_TEST + "08_",
    "tests/test_replay_lock.py::",
    NOTEBOOK_TEST + "06_",
    "tests/test_nonlinear_flux.py::",
    "tests/test_flux_map_files.py::",
    "tests/test_saturated_control.py::",
    NOTEBOOK_TEST + "01_",
)


def pytest_xdist_make_scheduler(config, log):
    """Under `--dist load` (the default of `-n`), one test module per unit of work and
    one notebook per unit (see LONGEST_FIRST); any other `--dist` keeps xdist's own."""
    if config.getoption("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            if nodeid.startswith(NOTEBOOK_TEST):
                return nodeid
            return nodeid.split("::", 1)[0]

    config.option.loadscopereorder = False  # keep LONGEST_FIRST's order
    return ModuleScheduling(config, log)


def _rank(nodeid: str) -> int:
    for k, prefix in enumerate(LONGEST_FIRST):
        if nodeid.startswith(prefix):
            return k
    return len(LONGEST_FIRST)


def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda item: _rank(item.nodeid))  # stable: the rest keep their order
