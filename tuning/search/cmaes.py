"""CMA-ES (evosax) at the same budget of closed-loop simulations as the gradient search.

A generation of `population` designs is one vmapped batch of `population x n_train`
closed-loop runs (`Evaluator.values`). The search starts at `z0` with step size 0.5 in
the unconstrained coordinates (a factor of about 1.3-1.6 on a bandwidth across the
bounds used); evosax's default CMA-ES parameters otherwise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._base import SearchResult, Tracker, progress_bar


SIGMA0 = 0.5


def cmaes_search(ev, z0, *, budget: int, population: int = 8, key=None,
                 progress: bool = False, name: str = "cmaes", **_) -> SearchResult:
    """CMA-ES from `z0`: `z0` itself, then `(budget - ev.cost) // (population *
    ev.cost)` generations (at least one); returns the best design evaluated, `z0`
    included."""
    from evosax.algorithms import CMA_ES

    key = jax.random.PRNGKey(0) if key is None else key
    z0 = jnp.asarray(z0, dtype=float)
    es = CMA_ES(population_size=population, solution=z0)
    params = es.default_params.replace(std_init=SIGMA0)
    key, k = jax.random.split(key)
    state = es.init(k, z0, params)
    # the start is a candidate too: a search never returns a design worse on its own
    # objective than the one it started from (the paper's), which a generation drawn
    # around it may all be (one evaluation of the budget)
    tr = Tracker(name, z0)
    tr.record(z0, float(ev.value(z0)), ev.cost)
    gens = max(1, (budget - ev.cost) // (population * ev.cost))
    with progress_bar(gens * population * ev.cost, name, progress) as bar:
        for _ in range(gens):
            key, k_ask, k_tell = jax.random.split(key, 3)
            zs, state = es.ask(k_ask, state, params)
            f = ev.values(zs)
            tr.record(zs, f, ev.cost)
            bar.update(population * ev.cost)
            f = jnp.where(jnp.isfinite(f), f, jnp.max(jnp.where(jnp.isfinite(f), f, 0)) +
                          1e3)
            state, _ = es.tell(k_tell, zs, f, state, params)
    return tr.result()
