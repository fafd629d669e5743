"""The figure of the I/f start's stabiliser (docs/lock-and-startup.md): the ESO drive on
morawiec_ipm3k5 started 2 rad off (the rotor at 0, the observer at 2 rad), speed reference
0 for 50 ms, then a ramp to 0.5 p.u. by 0.3 s; the rotor's speed and the angle error
with the plain I/f start and with the stabiliser (`IfStartup.from_drive(drive,
zeta=0.7)`).

Run from the repository root: `python docs/figures/make_startup_figure.py`
(writes docs/figures/if_stabiliser.png)."""

import os

import jax
import matplotlib
import numpy as np


matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402

import pmsmjax as pj  # noqa: E402
from pmsmjax.observers import make_observer  # noqa: E402


jax.config.update("jax_enable_x64", True)
HERE = os.path.dirname(os.path.abspath(__file__))

if __name__ == "__main__":
    drive = pj.preset("morawiec_ipm3k5")
    w = 0.5 * float(drive.w_rated)
    sc = pj.Scenario(t_end=0.6, w_m_ref=pj.Profile([0.0, 0.05, 0.3], [0.0, 0.0, w]))
    fig, (ax_w, ax_e) = plt.subplots(2, 1, figsize=(7.5, 5.0), sharex=True)
    for zeta, label, colour in ((0.0, "plain I/f start", "C3"),
                                (0.7, "with the stabiliser (zeta = 0.7)", "C0")):
        ctrl = pj.FOC.from_drive(drive, startup=pj.IfStartup.from_drive(drive, zeta=zeta))
        tr = pj.simulate(drive, ctrl, make_observer("eso", drive), sc, theta_hat0=2.0,
                         throw=False)
        t = np.asarray(tr.t)
        ax_w.plot(t, np.asarray(tr.w_m) / float(drive.w_rated), colour, label=label)
        ax_e.plot(t, np.degrees(np.asarray(tr.theta_err)), colour, lw=0.8)
    ax_w.plot(t, np.asarray(tr.w_m_ref) / float(drive.w_rated), "k--", lw=0.8,
              label="speed reference")
    ax_w.axvspan(0.0, 0.1, color="0.92", zorder=0)
    ax_w.text(0.005, 0.55, "alignment", fontsize=8)
    ax_w.set_ylabel("rotor speed (p.u.)")
    ax_e.legend(*ax_w.get_legend_handles_labels(), fontsize=8, loc="lower right")
    ax_e.set_ylabel("angle error (deg)")
    ax_e.set_xlabel("t (s)")
    ax_e.set_ylim(-185, 185)
    for ax in (ax_w, ax_e):
        ax.grid(alpha=0.3)
    fig.suptitle("morawiec_ipm3k5, ESO, started 2 rad off", fontsize=10)
    fig.tight_layout()
    fig.savefig(os.path.join(HERE, "if_stabiliser.png"), dpi=90)
