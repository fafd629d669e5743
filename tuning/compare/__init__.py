"""The observer comparison job (`python -m tuning compare`): every registered observer,
paper design and tuned (by the closed-loop tuner), on one common grid of closed-loop
runs. `config` defines it (the grid, the designs), `points` computes one grid point (a
run, the analysis), `report` aggregates and tabulates, `job` runs it, `worker` is its
worker process, `plots` draws it, `cli` parses its command line."""

from .config import (
    CASE_NAMES as CASE_NAMES,
    CASES as CASES,
    DESIGNS as DESIGNS,
    TUNERS as TUNERS,
    CompareConfig as CompareConfig,
    tuned_designs_from as tuned_designs_from,
)
from .job import CompareInterrupted as CompareInterrupted, run_comparison as run_comparison
from .plots import plot_comparison as plot_comparison
from .points import operating_current as operating_current
from .report import (
    aggregate as aggregate,
    beyond_points as beyond_points,
    lock_comparison as lock_comparison,
    markdown as markdown,
)
