"""The report: accounting, figures, gains tables and `summary.json` of a `TuningReport`;
it knows nothing of how the designs were found."""

from .corners import (
    MISMATCHES as MISMATCHES,
    heldout_simulate as heldout_simulate,
    heldout_text as heldout_text,
)
from .export import gains_table as gains_table
from .figures import BLOCKING_PLOT as BLOCKING_PLOT, PLOTS as PLOTS, plot_report as plot_report
from .summary import (
    REQUIRED_KEYS as REQUIRED_KEYS,
    load_design as load_design,
    summary as summary,
    write_report as write_report,
)
