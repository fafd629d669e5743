"""Figures of the library's results (matplotlib only; never imported by `pmsmjax`).

`from pmsmjax.plotting import plot_trajectory`. Each function builds and returns a
`matplotlib.figure.Figure` (or draws into the axes it is given), so it works with any
backend, Agg on a machine without a display included. The figures of one paper's
experiments live with the paper (`pmsmjax.papers.stumper_plots`,
`pmsmjax.papers.morawiec2023_plots`).
"""

from ._analysis import (
    plot_feasibility as plot_feasibility,
    plot_lock_basin as plot_lock_basin,
    plot_ramp_runs as plot_ramp_runs,
    plot_response as plot_response,
    plot_saturated_map as plot_saturated_map,
    plot_static_error as plot_static_error,
)
from ._gains import (
    plot_gains_vs_speed as plot_gains_vs_speed,
    plot_poles_vs_speed as plot_poles_vs_speed,
)
from ._magnetic import plot_flux_map as plot_flux_map
from ._recording import plot_recording as plot_recording
from ._trajectory import (
    plot_identification as plot_identification,
    plot_plant_trace as plot_plant_trace,
    plot_trajectory as plot_trajectory,
)
