"""Plots for `pmsmjax.papers.morawiec2023` (matplotlib only).

Never imported by `pmsmjax`; import it explicitly:
`from pmsmjax.papers.morawiec2023_plots import plot_spectra`.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np


def plot_spectra(spectra, *, ax=None, which=("printed", "averaged", "floquet")):
    """The eigenvalues of one sweep of morawiec2023 Figs. 3-5 in the complex plane (p.u.):
    matrix (35) as printed, the implemented observer's averaged exact Jacobian and its
    Floquet exponents, coloured by the swept value (light to dark).

    **Arguments:** `spectra`: a `Spectra` from `spectrum_sweep`; `ax`: axes (default a
    new figure); `which`: the spectra to draw. Returns the axes.
    """
    if ax is None:
        _, ax = plt.subplots(figsize=(5.5, 4.5))
    markers = {"printed": ("x", "tab:red", "(35) as printed"),
               "averaged": ("o", "tab:blue", "exact, averaged"),
               "floquet": ("+", "tab:green", "exact, Floquet")}
    n = len(spectra.values)
    shade = np.linspace(0.35, 1.0, n)
    for key in which:
        mk, col, label = markers[key]
        ev = np.asarray(getattr(spectra, key))
        for k in range(n):
            ax.scatter(ev[k].real, ev[k].imag, marker=mk, color=col, alpha=float(shade[k]),
                       s=28, label=label if k == n - 1 else None,
                       facecolors="none" if mk == "o" else None)
    ax.axvline(0.0, color="k", lw=0.6)
    ax.axhline(0.0, color="k", lw=0.3)
    v = spectra.values
    ax.set_title(f"{spectra.name}: {spectra.parameter} = {v[0]:.3g} ... {v[-1]:.3g}")
    ax.set_xlabel("Re (p.u.)")
    ax.set_ylabel("Im (p.u.)")
    ax.legend(fontsize=8)
    return ax
