"""Figures for stumper's parallel-model estimator (matplotlib only, like `plotting`).

Not imported by `pmsmjax/__init__.py`: `from pmsmjax.papers.stumper_plots import
plot_sensitivity`. Angles in degrees.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure


def plot_sensitivity(sens, *, fig: Figure | None = None, printed: bool = True) -> Figure:
    """stumper Fig. 1 from a `pmsmjax.papers.stumper.Sensitivity`: the angle offset
    (deg, estimate minus true) against the resistance error (Ohm, top) and the
    inductance error (mH, bottom). Lines: the closed forms (open loop, current in rotor
    coordinates: solid; closed loop, current in the estimated frame: dashed); markers:
    the estimator replayed over simulated open-loop data (circles), the stable
    equilibrium of the generic analysis (squares) and the sensorless closed loop
    (crosses); dotted: the printed (32)/(31) (`printed=False` leaves them out)."""
    if fig is None:
        fig = Figure(figsize=(6.5, 6.0), layout="constrained")
    axes = fig.subplots(2, 1, squeeze=False)[:, 0] if not fig.axes else fig.axes[:2]
    for ax, (name, unit, k) in zip(axes, (("R", "Ohm", 1.0), ("L", "mH", 1e3))):
        a = sens.axes[name]
        x, xc = np.asarray(a["x"]) * k, np.asarray(a["x_closed"]) * k
        ax.plot(x, a["formula_open"], "b-", label="closed form, open loop")
        ax.plot(x, a["simulated_open"], "ko", mfc="none", label="simulated, open loop")
        ax.plot(x, a["formula_closed"], "b--", label="closed form, closed loop")
        ax.plot(x, a["equilibria"], "gs", mfc="none", ms=8, label="equilibrium (analysis)")
        ax.plot(xc, a["simulated_closed"], "rx", ms=9, label="simulated, closed loop")
        if printed:
            ax.plot(x, a["printed"], "m:", label=f"printed ({'32' if name == 'R' else '31'})")
        ax.set_xlabel(f"d{name} = {name}_hat - {name} ({unit})")
        ax.set_ylabel("angle offset (deg)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small", frameon=False)
    fig.suptitle(f"{sens.rpm:g} rpm, (i_d, i_q) = {tuple(sens.i_dq)} p.u.")
    return fig
