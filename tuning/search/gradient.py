r"""Gradient search through the closed loops, and the measurement behind its settings.

**Adam with clipping.** The objective's gradient comes from reverse-mode differentiation
through every closed-loop run of the training batch (`Evaluator.value_and_grad`; a step
costs `n_train` simulations). Steps are Adam (optax) on the unconstrained coordinates,
after clipping the gradient's global norm to `clip_norm`: through a lock-loss transient
or a reversal the gradient can jump by orders of magnitude between neighbouring designs
(`gradient_vs_horizon` measures it) and an unclipped Adam step would then leave the
useful region for good.

**Why plain reverse mode, without truncation or multiple shooting.** `gradient_vs_horizon`
compares, at a design, the gradient with central finite differences for runs of growing
length. On zhang750's ESO with the default training runs it agrees within a few per cent
up to the 0.3 s runs used (docs/tuning.md gives the table); the error dynamics are
contracting (the observer forgets its past within a few of its time constants), so the
sensitivity of the loss to the gains does not grow with the horizon and nothing needs
cutting. A run that loses lock is where agreement fails (the loss is then
discontinuous in the design): the clipping bounds what such a step can do, and the
searches keep only the best design evaluated.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import optax

from ._base import SearchResult, Tracker, progress_bar


def gradient_search(ev, z0, *, budget: int, learning_rate: float = 0.08,
                    clip_norm: float = 1.0, progress: bool = False, key=None,
                    name: str = "gradient", tracker: Tracker | None = None, **_
                    ) -> SearchResult:
    """Adam on `ev.value_and_grad` from `z0` for `budget // ev.cost` steps (see the
    module docstring); returns the best design evaluated."""
    del key
    steps = max(1, budget // ev.cost)
    opt = optax.chain(optax.clip_by_global_norm(clip_norm), optax.adam(learning_rate))
    z = jnp.asarray(z0, dtype=float)
    state = opt.init(z)
    tr = tracker or Tracker(name, z0)
    with progress_bar(steps * ev.cost, name, progress) as bar:
        for _ in range(steps):
            v, g = ev.value_and_grad(z)
            v = float(v)
            tr.record(z, v, ev.cost)
            bar.update(ev.cost)
            g = jnp.where(jnp.isfinite(g), g, 0.0)
            upd, state = opt.update(g, state, z)
            z = optax.apply_updates(z, upd)
    res = tr.result()
    res.name = name
    return res


def hybrid_search(ev, z0, *, budget: int, population: int = 8, key=None,
                  progress: bool = False, learning_rate: float = 0.08,
                  clip_norm: float = 1.0, **_) -> SearchResult:
    """CMA-ES for half of `budget`, then `gradient_search` from its best design for the
    rest; simulations and wall time add up."""
    from .cmaes import cmaes_search

    first = cmaes_search(ev, z0, budget=budget // 2, population=population, key=key,
                         progress=progress)
    tr = Tracker("hybrid", first.z, first.value, first.sims)
    tr.history = list(first.history)
    tr.t0 -= first.wall_s
    res = gradient_search(ev, first.z, budget=budget - first.sims,
                          learning_rate=learning_rate, clip_norm=clip_norm,
                          progress=progress, tracker=tr, name="hybrid")
    return res


def gradient_vs_horizon(make_evaluator, z, horizons, *, eps: float = 1e-3) -> list[dict]:
    """Gradient norm and agreement with central finite differences against the run
    length: `make_evaluator(t_end)` gives an `Evaluator` whose runs last `t_end` (s);
    returns per horizon `{"t_end", "grad_norm", "fd_norm", "rel_error", "cos"}` where
    `rel_error` = |g - g_fd| / |g_fd| and `cos` the cosine between them."""
    out = []
    z = jnp.asarray(z, dtype=float)
    for t_end in horizons:
        ev = make_evaluator(float(t_end))
        _, g = ev.value_and_grad(z)
        g = np.asarray(g)
        fd = np.zeros_like(g)
        for i in range(g.size):
            e = np.zeros_like(g)
            e[i] = eps
            fd[i] = (float(ev.value(z + e)) - float(ev.value(z - e))) / (2 * eps)
        nf = float(np.linalg.norm(fd))
        out.append({"t_end": float(t_end), "grad_norm": float(np.linalg.norm(g)),
                    "fd_norm": nf,
                    "rel_error": float(np.linalg.norm(g - fd) / max(nf, 1e-300)),
                    "cos": float(g @ fd / max(np.linalg.norm(g) * nf, 1e-300))})
    return out
