"""A recording at a glance (`plot_recording`): what `pmsmjax convert` wrote, to check a
log's conversion by eye."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from ._trajectory import _axes, _legend


def plot_recording(data, *, title: str | None = None, t_window: float | None = None
                   ) -> Figure:
    """The arrays of a `RecordedData` in SI units over time: voltages and currents in the
    stationary frame, and where the recording has an angle, the currents in the rotor
    frame of that angle (constant in a steady state when angle, offset and direction are
    right; a ripple at the electrical frequency when they are not), the speed and the
    angle.

    **Arguments:**

    - `data`: the `RecordedData`.
    - `title`: the figure's title.
    - `t_window`: show only the first `t_window` seconds (default: all).

    **Returns:** the `matplotlib.figure.Figure`.
    """
    t = np.asarray(data.t, float)
    keep = slice(None) if t_window is None else t <= t[0] + t_window
    t = t[keep]
    panels = [p for p, name in (("u", "u_ab"), ("i", "i_ab"), ("dq", "theta"),
                                ("w", "w_m"), ("theta", "theta"))
              if getattr(data, name) is not None]
    fig, axes = _axes(None, len(panels))
    ax = dict(zip(panels, axes))
    for p, name, unit in (("u", "u_ab", "V"), ("i", "i_ab", "A")):
        if p in ax:
            x = np.asarray(getattr(data, name), float)[keep]
            ax[p].plot(t, x[:, 0], "C0", lw=0.8, label=rf"${p}_\alpha$")
            ax[p].plot(t, x[:, 1], "C1", lw=0.8, label=rf"${p}_\beta$")
            ax[p].set_ylabel(f"{'voltage' if p == 'u' else 'current'} ({unit})")
    if "dq" in ax and data.i_ab is not None:
        th = np.asarray(data.theta, float)[keep]
        i = np.asarray(data.i_ab, float)[keep]
        c, s = np.cos(th), np.sin(th)
        ax["dq"].plot(t, c * i[:, 0] + s * i[:, 1], "C0", lw=0.8, label=r"$i_d$")
        ax["dq"].plot(t, -s * i[:, 0] + c * i[:, 1], "C1", lw=0.8, label=r"$i_q$")
        ax["dq"].set_ylabel("rotor frame (A)")
    if "w" in ax:
        ax["w"].plot(t, np.asarray(data.w_m, float)[keep], "C0", label=r"$\omega_m$")
        ax["w"].set_ylabel("speed (rad/s el.)")
    if "theta" in ax:
        ax["theta"].plot(t, np.degrees(np.asarray(data.theta, float)[keep]), "C0", lw=0.8,
                         label=r"$\theta$")
        ax["theta"].set_ylabel("angle (deg el.)")
    for a in axes:
        _legend(a)
    axes[-1].set_xlabel("time (s)")
    axes[-1].set_xlim(float(t[0]), float(t[-1]))
    fig.suptitle(title if title is not None else "recording")
    return fig
