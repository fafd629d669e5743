"""What every search returns, and the budget bookkeeping they share."""

from __future__ import annotations

import dataclasses
import time

import numpy as np


@dataclasses.dataclass
class SearchResult:
    """The outcome of one search.

    - `name`: the strategy; `z`: the best design found (unconstrained) by the training
      objective; `value`: its objective.
    - `sims`: closed-loop simulations run; `wall_s`: wall time (s), compilation included.
    - `history`: one `(sims, best value so far, wall s)` per evaluation step.
    """

    name: str
    z: np.ndarray
    value: float
    sims: int
    wall_s: float
    history: list = dataclasses.field(default_factory=list)

    def to_reach(self, target: float) -> tuple[int | None, float | None]:
        """Simulations and wall time until the best value first reached `target`
        (None, None: never)."""
        for sims, best, wall in self.history:
            if best <= target:
                return sims, wall
        return None, None


class Tracker:
    """Counts simulations and keeps the best design (finite values only)."""

    def __init__(self, name: str, z0, value0: float | None = None, sims0: int = 0):
        self.name = name
        self.t0 = time.perf_counter()
        self.sims = sims0
        self.best_z = np.asarray(z0, dtype=float)
        self.best = float("inf") if value0 is None else float(value0)
        self.history = []

    def record(self, zs, values, cost: int) -> None:
        zs = np.atleast_2d(np.asarray(zs, dtype=float))
        values = np.atleast_1d(np.asarray(values, dtype=float))
        self.sims += cost * len(values)
        ok = np.isfinite(values)
        if ok.any():
            j = int(np.argmin(np.where(ok, values, np.inf)))
            if values[j] < self.best:
                self.best, self.best_z = float(values[j]), zs[j].copy()
        self.history.append((self.sims, self.best, time.perf_counter() - self.t0))

    def result(self) -> SearchResult:
        return SearchResult(self.name, self.best_z, self.best, self.sims,
                            time.perf_counter() - self.t0, self.history)


def progress_bar(total: int, desc: str, enabled: bool):
    """A tqdm bar counting simulations (disabled: a no-op object)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="sim", disable=not enabled, leave=False)
