import jax
import jax.random as jr
import pytest

import pmsmjax


# The test suite is an entry point: the same process settings as the command line
# (pmsmjax.runtime: XLA flags, compilation cache), applied before any computation.
pmsmjax.runtime.configure()
jax.config.update("jax_enable_x64", True)


@pytest.fixture
def getkey():
    counter = iter(range(10**9))

    def _getkey():
        return jr.PRNGKey(next(counter))

    return _getkey
