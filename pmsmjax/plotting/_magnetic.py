"""Figures of a saturated machine's magnetic model."""

from __future__ import annotations

import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np


def plot_flux_map(model, i_max, *, constants=None, n=61, fig=None):
    """The flux map and the inductances it implies, over currents up to `i_max` (A).

    Left: contours of psi_d and psi_q (V s) over (i_d, i_q). Right: along the q axis
    (i_d = 0, i_q from 0 to `i_max`) the apparent L_q and the incremental dpsi_q/di_q, the
    apparent L_d and the PM flux psi_d(0, i_q) (cross-saturation), each relative to its
    value at zero current; `constants` `(L_d, L_q, psi_f)` (H, H, V s), e.g. the drive's
    deployed model, are drawn as horizontal lines at their ratio to those values.

    **Arguments:**

    - `model`: an `AbstractMagneticModel` (`FluxMap`, `AlgebraicSaturation`).
    - `i_max`: current range of the plot (A), > 0: i_d in [-i_max, 0], i_q in
      [-i_max, i_max] for the contours.
    - `constants`: optional `(L_d, L_q, psi_f)` to compare with.
    - `n`: grid points per axis.
    """
    i_max = float(i_max)
    if not i_max > 0:
        raise ValueError(f"`plot_flux_map(i_max=...)` (A) must be > 0; got {i_max!r}.")
    fig = fig or plt.figure(figsize=(11, 4.2))
    ax_d, ax_q, ax_l = fig.subplots(1, 3)
    i_d = np.linspace(-i_max, 0.0, n)
    i_q = np.linspace(-i_max, i_max, n)
    dd, qq = np.meshgrid(i_d, i_q, indexing="ij")
    psi = np.asarray(model.flux_dq(jnp.stack([dd, qq], -1)))
    for ax, k, name in ((ax_d, 0, r"$\psi_d$"), (ax_q, 1, r"$\psi_q$")):
        cs = ax.contourf(dd, qq, psi[..., k], levels=15, cmap="viridis")
        fig.colorbar(cs, ax=ax, label=f"{name} (V s)")
        ax.set_xlabel(r"$i_d$ (A)")
        ax.set_ylabel(r"$i_q$ (A)")
        ax.set_title(name)
    q = np.linspace(0.0, i_max, n)
    x = jnp.stack([jnp.zeros_like(q), q], -1)
    L_d, L_q, psi_f = (np.asarray(v) for v in model.apparent_inductance(x))
    L_inc = np.asarray(model.incremental_inductance(x))
    ax_l.plot(q, L_q / L_q[0], label=r"$L_q$ apparent")
    ax_l.plot(q, L_inc[:, 1, 1] / L_inc[0, 1, 1], "--", label=r"$\partial\psi_q/\partial i_q$")
    ax_l.plot(q, L_d / L_d[0], label=r"$L_d$ apparent")
    ax_l.plot(q, psi_f / psi_f[0], label=r"$\psi_d(0, i_q)$")
    if constants is not None:
        for value, ref, style, name in zip(constants, (L_d[0], L_q[0], psi_f[0]),
                                           (":", "-.", (0, (1, 3))),
                                           ("deployed L_d", "deployed L_q", "deployed psi_f")):
            ax_l.axhline(float(value) / ref, color="0.4", ls=style, lw=1, label=name)
    ax_l.set_xlabel(r"$i_q$ (A), $i_d = 0$")
    ax_l.set_ylabel("relative to zero current")
    ax_l.set_title("saturation along the q axis")
    ax_l.grid(True, alpha=0.3)
    ax_l.legend(fontsize=8)
    fig.tight_layout()
    return fig
