"""Search strategies: each takes the objective (an `Evaluator`), a start and a budget of
closed-loop simulations, and returns a `SearchResult`; none knows of reports.

- `gradient_search`: Adam (optax) on the reverse-mode gradient through the closed loops,
  with global-norm clipping (`tuning.search.gradient`);
- `cmaes_search`: CMA-ES (evosax), a generation as one vmapped batch
  (`tuning.search.cmaes`);
- `random_search`, `local_search`: uniform random designs in the bounds and a (1+1)
  evolution strategy with the 1/5th success rule (`tuning.search.baselines`);
- `hybrid_search`: CMA-ES for half the budget, then the gradient polish from its best.
"""

from ._base import SearchResult as SearchResult
from .baselines import local_search as local_search, random_search as random_search
from .cmaes import cmaes_search as cmaes_search
from .gradient import (
    gradient_search as gradient_search,
    gradient_vs_horizon as gradient_vs_horizon,
    hybrid_search as hybrid_search,
)


#: The strategies by name (`TuningProblem.search`).
STRATEGIES = {"hybrid": hybrid_search, "gradient": gradient_search, "cmaes": cmaes_search,
              "random": random_search, "local": local_search}
