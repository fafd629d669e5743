"""Plots of a gains table for firmware engineers (matplotlib only): the gains versus
speed, tuned and paper, and the discrete observer's poles versus speed. `pmsmjax gains
--plot` writes them from `pmsmjax.cli._gains.gains_check`. Never imported by `pmsmjax`
itself."""

from __future__ import annotations

import math

import matplotlib.pyplot as plt
import numpy as np


def plot_gains_vs_speed(check: dict, *, title: str = ""):
    """One panel per gain (or design parameter of a constant design): the tuned value
    (solid) and the paper's (dashed) versus speed (p.u.), from `gains_check`. Returns the
    figure."""
    s = np.asarray(check["speed_pu"])
    names = list(check["gains"])
    n_col = min(4, len(names))
    n_row = math.ceil(len(names) / n_col)
    fig, axes = plt.subplots(n_row, n_col, figsize=(3.0 * n_col, 2.3 * n_row),
                             squeeze=False, sharex=True)
    for ax, name in zip(axes.flat, names):
        g = check["gains"][name]
        ax.plot(s, g["paper"], "--", color="0.4", lw=1.2, label="paper design")
        ax.plot(s, g["tuned"], "-", color="tab:blue", lw=1.2, label="tuned")
        ax.set_title(f"{name} ({g['unit'] or '-'})", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    for ax in axes.flat[len(names):]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("speed (p.u.)", fontsize=8)
    axes.flat[0].legend(fontsize=7)
    if title:
        fig.suptitle(f"gains versus speed: {title}", fontsize=9)
    fig.tight_layout()
    return fig


def plot_poles_vs_speed(check: dict, *, title: str = ""):
    """Left: the largest pole magnitude |z| of the discrete observer versus speed, tuned
    and paper (|z| < 1: stable; the closer to 1, the slower). Right: every pole in the
    z-plane near z = 1, coloured by speed, tuned (dots) and paper (crosses). Returns the
    figure."""
    s = np.asarray(check["speed_pu"])
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10.0, 4.0))
    a1.plot(s, check["max_abs_pole_paper"], "--", color="0.4", label="paper design")
    a1.plot(s, check["max_abs_pole_tuned"], "-", color="tab:blue", label="tuned")
    a1.axhline(1.0, color="tab:red", lw=0.8)
    a1.set_xlabel("speed (p.u.)")
    a1.set_ylabel("largest |z|")
    a1.grid(True, alpha=0.3)
    a1.legend(fontsize=8)
    for key, marker in (("poles_paper", "x"), ("poles_tuned", ".")):
        z = np.asarray(check[key])  # (speeds, n, 2)
        c = np.repeat(s, z.shape[1])
        sc = a2.scatter(z[..., 0].ravel(), z[..., 1].ravel(), c=c, cmap="coolwarm",
                        marker=marker, s=14, lw=0.8)
    t = np.linspace(-0.3, 0.3, 200)
    a2.plot(np.cos(t), np.sin(t), color="tab:red", lw=0.8)
    a2.set_xlabel("Re z")
    a2.set_ylabel("Im z")
    a2.set_title("poles (dots: tuned, crosses: paper)", fontsize=8)
    a2.grid(True, alpha=0.3)
    fig.colorbar(sc, ax=a2, label="speed (p.u.)")
    if title:
        fig.suptitle(f"discrete observer poles: {title}", fontsize=9)
    fig.tight_layout()
    return fig
