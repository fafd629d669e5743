"""The observer comparison job (`python -m tuning compare`): every registered observer,
paper design and tuned (by the closed-loop tuner), on one common grid of closed-loop
runs. `job` runs it, `worker` is its worker process, `plots` draws it, `cli` parses its
command line."""

from .job import (
    CASES as CASES,
    TUNERS as TUNERS,
    CompareConfig as CompareConfig,
    CompareInterrupted as CompareInterrupted,
    run_comparison as run_comparison,
)
from .plots import plot_comparison as plot_comparison
