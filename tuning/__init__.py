"""Tuning sensorless-observer designs in the closed loop they will run in.

The pipeline, one module per stage (data flows one way):

- `TuningProblem` (`tuning.problem`): drive, observer family, scenario, design-space,
  objective and search settings, built once;
- scenario sets (`tuning.scenarios`): closed-loop sensorless training, held-out and
  validation runs, disjoint by construction;
- `DesignSpace` (`tuning.design_space`): bandwidths and damping in log space, bounds
  derived from the drive;
- `Evaluator` (`tuning.evaluate`) and the objective (`tuning.objective`): per-run
  metrics, a CVaR aggregate, per-metric no-regression constraints;
- searches (`tuning.search`): gradient, CMA-ES (evosax), hybrid, random, local, each at
  the same budget of closed-loop simulations;
- `tune` (`tuning.pipeline`) runs them and returns a `TuningReport`; `tuning.report`
  writes it (summary.json, figures, gains table); where the verdict fails, each blocking
  validation run's noise floor and the phase its change comes from, and for runs both
  designs lose, the analysis at the run's end (`tuning.blocking`).

`python -m tuning` runs the main job; `python -m tuning compare` the side-by-side
comparison of every observer (`tuning.compare`).
"""

from . import report as report
from .blocking import (
    END_VERDICTS as END_VERDICTS,
    NOISE_FLOOR_KEYS as NOISE_FLOOR_KEYS,
    PHASES as PHASES,
    end_analysis as end_analysis,
    noise_floor as noise_floor,
    phase_split as phase_split,
)
from .compare import (
    CompareConfig as CompareConfig,
    plot_comparison as plot_comparison,
    run_comparison as run_comparison,
)
from .design_space import Coordinate as Coordinate, DesignSpace as DesignSpace
from .evaluate import Evaluator as Evaluator
from .objective import (
    DEPRECATED_KEYS as DEPRECATED_KEYS,
    VOCABULARY as VOCABULARY,
    Metrics as Metrics,
    accounting as accounting,
    cvar as cvar,
    holds as holds,
    judged as judged,
    objective as objective,
    run_metrics as run_metrics,
)
from .pipeline import TuningReport as TuningReport, tune as tune
from .problem import (
    SEARCHES as SEARCHES,
    VALIDATION_CASES as VALIDATION_CASES,
    WIDE_CASES as WIDE_CASES,
    WIDE_MISMATCH_RANGE as WIDE_MISMATCH_RANGE,
    WIDE_N_TRAIN as WIDE_N_TRAIN,
    TuningProblem as TuningProblem,
    sampling_period as sampling_period,
)
from .report import (
    REQUIRED_KEYS as REQUIRED_KEYS,
    gains_table as gains_table,
    load_design as load_design,
    plot_report as plot_report,
    summary as summary,
    write_report as write_report,
)
from .scenarios import (
    ERROR_PATTERNS as ERROR_PATTERNS,
    ScenarioSet as ScenarioSet,
    apply_low_speed_rule as apply_low_speed_rule,
    check_disjoint as check_disjoint,
    heldout_set as heldout_set,
    judged_speeds as judged_speeds,
    low_speed_runs as low_speed_runs,
    simulate_set as simulate_set,
    training_set as training_set,
    validation_set as validation_set,
)
from .search import (
    STRATEGIES as STRATEGIES,
    SearchResult as SearchResult,
    cmaes_search as cmaes_search,
    gradient_search as gradient_search,
    gradient_vs_horizon as gradient_vs_horizon,
    hybrid_search as hybrid_search,
    local_search as local_search,
    random_search as random_search,
)
