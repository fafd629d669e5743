"""Gradient-free baselines at the same budget: random search and a (1+1) evolution
strategy.

- `random_search`: designs uniform in the unconstrained cube [-3, 3]^n (through the
  logistic map, nearly uniform in the log of each physical coordinate within its
  bounds), evaluated in batches of `population`; the start is the first design.
- `local_search`: (1+1)-ES from the start: a Gaussian step of size `sigma` (0.5
  initially), kept if it improves; `sigma` grows by 1.5 after a success and shrinks by
  1.5^(-1/4) after a failure (the 1/5th success rule).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._base import SearchResult, Tracker, progress_bar


def random_search(ev, z0, *, budget: int, population: int = 8, key=None,
                  progress: bool = False, **_) -> SearchResult:
    key = jax.random.PRNGKey(1) if key is None else key
    n_designs = max(1, budget // ev.cost)
    z0 = jnp.asarray(z0, dtype=float)
    zs = jax.random.uniform(key, (n_designs, z0.size), minval=-3.0, maxval=3.0)
    zs = zs.at[0].set(z0)
    tr = Tracker("random", z0)
    with progress_bar(n_designs * ev.cost, "random", progress) as bar:
        for i in range(0, n_designs, population):
            batch = zs[i:i + population]
            m = batch.shape[0]
            if m < population:  # keep one compiled batch size
                batch = jnp.concatenate([batch, jnp.repeat(batch[-1:], population - m, 0)])
            f = ev.values(batch)[:m]
            tr.record(batch[:m], f, ev.cost)
            bar.update(m * ev.cost)
    return tr.result()


def local_search(ev, z0, *, budget: int, key=None, progress: bool = False,
                 **_) -> SearchResult:
    key = jax.random.PRNGKey(2) if key is None else key
    steps = max(1, budget // ev.cost)
    z = np.asarray(z0, dtype=float)
    f = float(ev.value(z))
    tr = Tracker("local", z)
    tr.record(z, f, ev.cost)
    sigma = 0.5
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)
                                           if hasattr(jax.random, "key_data") else key))
    with progress_bar(steps * ev.cost, "local", progress) as bar:
        bar.update(ev.cost)
        for _ in range(steps - 1):
            cand = z + sigma * rng.standard_normal(z.size)
            fc = float(ev.value(cand))
            tr.record(cand, fc, ev.cost)
            bar.update(ev.cost)
            if np.isfinite(fc) and fc < f:
                z, f, sigma = cand, fc, sigma * 1.5
            else:
                sigma *= 1.5 ** -0.25
    return tr.result()
