"""C99 code generation for the observers: the discrete step exactly as `pmsmjax.replay`
computes it, for firmware.

`export_c(observer, T_s, out_dir, float32=False, inverter=None)` writes `pmsm_observer.h`
(state, inputs, units, sampling period), `pmsm_observer.c` (the step, no allocation, libm
only) and `replay_main.c` (reads a CSV recording `t,u_a,u_b,i_a,i_b` in the stationary
alpha-beta frame on standard input and prints `theta_hat,w_hat` per sample). With an
`inverter` whose dead-time model is set (`u_dt`, `i_dt`), the step takes commanded
voltages and compensates them as `replay(..., inverter=...)` does (`_dead_time`).

One module per observer family; `render` picks it by the observer's class (the class's own
`c_emitter` attribute; a class without one raises `UnsupportedObserverError`, never another
family's code; `supported_observers()` lists the registered names with one). Supported: the
zhang2022 flux observers (`eso`, `leso`, `afo`; `_zhang2022`) with any of their gain
schedules (`ESODesign`: zhang38, fixed_ratio, fixed_w1; `FixedGains`; a tuned
`TabulatedDesign`), morawiec2023's rotor-flux observer (`rotor-flux`;
`_morawiec2023`), stumper's parallel-model estimator (`parallel-model`; `_stumper`) and
the li-fa-leso back-EMF observers (`c-leso`, `gi-leso`, `fa-leso`; `_li`, the exact ZOH
discretisation in the closed form of the JAX step, `_li_transition`).
"""

from __future__ import annotations

from ._emit import (
    UnsupportedObserverError,
    emitter_for,
    export_c,
    render,
    supported_observers,
)


__all__ = ["UnsupportedObserverError", "emitter_for", "export_c", "render",
           "supported_observers"]
