"""The figure of the saturated preset's flux map (docs/saturation.md): the flux contours
and the apparent and incremental inductances and PM flux along the q axis against the
constants the drive deploys (`pmsmjax.plotting.plot_flux_map`).

Run from the repository root: `python docs/figures/make_flux_map_figure.py`
(writes docs/figures/flux_map.png)."""

import os

import jax
import matplotlib


matplotlib.use("Agg")

import pmsmjax as pj  # noqa: E402
from pmsmjax.plotting import plot_flux_map  # noqa: E402


jax.config.update("jax_enable_x64", True)
HERE = os.path.dirname(os.path.abspath(__file__))

if __name__ == "__main__":
    drive = pj.preset("ipm3k5_sat")
    m = drive.motor
    fig = plot_flux_map(m.magnetic, drive.i_max, constants=(m.L_d, m.L_q, m.psi_f))
    fig.savefig(os.path.join(HERE, "flux_map.png"), dpi=90)
