"""Gradient-based tuning of sensorless-observer designs under inductance mismatch.

`python -m tuning` runs the whole job (see `tuning.__main__`); the pieces are public:
`TuningConfig` and the scenario grids (`tuning.scenarios`), the closed-loop validation
runs the tuner never sees (`tuning.validation`), the tunable designs
(`AbstractDesign`: the speed-scheduled zhang2022 `GainSchedule` and the generic
`ConstantDesign` for any registered observer that declares `tunable` design parameters;
unconstrained <-> physical, `filter_spec`), the objective (`tuning.objectives`), the
optimisers (`tuning.optimise`) and `run_tuning` / `write_report`. The side-by-side
comparison of every observer (`python -m tuning compare`) is `tuning.compare`
(`CompareConfig`, `run_comparison`, `plot_comparison`).
"""

from ._compare_plots import plot_comparison as plot_comparison
from ._export import gains_table as gains_table, table_speeds as table_speeds
from ._parametrise import (
    TUNABLE as TUNABLE,
    AbstractDesign as AbstractDesign,
    Bounds as Bounds,
    ConstantDesign as ConstantDesign,
    FactorBounds as FactorBounds,
    GainSchedule as GainSchedule,
    filter_spec as filter_spec,
    schedule_table as schedule_table,
    set_schedule as set_schedule,
    zhang38_schedule as zhang38_schedule,
)
from ._pipeline import (
    DESIGNS as DESIGNS,
    TuningReport as TuningReport,
    run_tuning as run_tuning,
    targets_reached as targets_reached,
    time_traces as time_traces,
)
from ._report import (
    REQUIRED_KEYS as REQUIRED_KEYS,
    accounting as accounting,
    config_from_summary as config_from_summary,
    load_schedule as load_schedule,
    plot_report as plot_report,
    report_figures as report_figures,
    summary as summary,
    tuned_design as tuned_design,
    write_report as write_report,
)
from .compare import CompareConfig as CompareConfig, run_comparison as run_comparison
from .objectives import (
    EquilibriumSet as EquilibriumSet,
    Metrics as Metrics,
    aggregate as aggregate,
    equilibria as equilibria,
    evaluate as evaluate,
    feasibility as feasibility,
    loss as loss,
    objective_value as objective_value,
    regression_penalty as regression_penalty,
    relative_change as relative_change,
    report_objective as report_objective,
    residuals as residuals,
    routh_margins as routh_margins,
    sampling_penalty as sampling_penalty,
    scenario_losses as scenario_losses,
    stability_penalty as stability_penalty,
    trajectory_metrics as trajectory_metrics,
    within_tolerance as within_tolerance,
)
from .optimise import (
    TuningResult as TuningResult,
    adam as adam,
    bfgs as bfgs,
    levenberg_marquardt as levenberg_marquardt,
    local_search as local_search,
    optimise as optimise,
    random_search as random_search,
)
from .scenarios import (
    MOTOR_DEFAULTS as MOTOR_DEFAULTS,
    OBJECTIVES as OBJECTIVES,
    PARAMETRISATIONS as PARAMETRISATIONS,
    ScenarioSet as ScenarioSet,
    TuningConfig as TuningConfig,
    apply_design as apply_design,
    design_quantities as design_quantities,
    heldout_scenarios as heldout_scenarios,
    make_observer as make_observer,
    make_scenarios as make_scenarios,
    observer_motor as observer_motor,
    parametrisation_of as parametrisation_of,
    simulate_scenarios as simulate_scenarios,
    training_scenarios as training_scenarios,
)
from .validation import (
    ValidationSet as ValidationSet,
    simulate_validation as simulate_validation,
    validate as validate,
    validation_metrics as validation_metrics,
    validation_scenario as validation_scenario,
    validation_scenarios as validation_scenarios,
)
