import os

import jax
import jax.random as jr
import pytest

import pmsmjax


# The test suite is an entry point: the same process settings as the command line
# (pmsmjax.runtime: XLA flags), applied before any computation. The persistent
# compilation cache is off for the suite (and the commands and kernels it starts, which
# inherit the variable; tests/test_runtime.py sets its own): in two full runs on the
# 2-core machine a worker died natively inside JAX's cache code (a segfault reading an
# entry under heavy load, an abort writing one from a cold run), so the suite must not
# depend on it. Set PMSMJAX_CACHE=1 to use it anyway.
os.environ.setdefault("PMSMJAX_CACHE", "0")
pmsmjax.runtime.configure()
jax.config.update("jax_enable_x64", True)


@pytest.fixture
def getkey():
    counter = iter(range(10**9))

    def _getkey():
        return jr.PRNGKey(next(counter))

    return _getkey
