"""Simulation: scenarios, integration, the closed loop, open-loop plant runs, run dtypes,
the solution and the metrics of a run. Private: the public names are re-exported by
`pmsmjax`."""
