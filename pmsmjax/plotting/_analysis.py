"""Plots for `pmsmjax.analysis` (matplotlib only).

Never imported by `pmsmjax` or `pmsmjax.analysis`; import it explicitly:
`from pmsmjax.plotting import plot_feasibility`.
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D
from matplotlib.patches import Patch


_SPEED_COLOURS = ("tab:red", "gold", "tab:green", "tab:purple", "tab:orange", "tab:cyan")


def plot_feasibility(result, *, load: int = 0, speeds=None, ax=None, show_degenerate=True):
    """Feasibility map in the style of zhang2022 Fig. 1.

    For every speed of `result` (a `FeasibilityMap`), or the indices in `speeds`, the
    infeasible designs (a stable nonzero equilibrium) are shaded in the speed's colour
    and the boundary of the feasible region is drawn; the design (38) at that speed is
    marked with a star (in these coordinates it is the single point
    `zeta1 = 1.5 + w0/w_r`, `w1/w0 = 1.5/zeta1`). Designs with `status = -1` (e.g.
    `w1 = 0`) are hatched grey, `status = 2` (no equilibrium) dotted.

    **Arguments:** `result`; `load`: index into `result.i_dq`; `speeds`: speed indices
    (default all); `ax`: axes to draw into. Returns the axes.
    """
    if ax is None:
        _, ax = plt.subplots(figsize=(6.0, 4.5))
    z = np.asarray(result.zeta1)
    r = np.asarray(result.ratio)
    st = np.asarray(result.status)[:, load]
    idx = range(st.shape[0]) if speeds is None else speeds
    Z, R = np.meshgrid(z, r, indexing="ij")
    handles = []
    z38, r38 = result.schedule38()
    for n, i in enumerate(idx):
        col = _SPEED_COLOURS[n % len(_SPEED_COLOURS)]
        inf = (st[i] == 1).astype(float)
        frac = inf.mean()
        if frac > 0:
            ax.contourf(Z, R, inf, levels=[0.5, 1.5], colors=[col], alpha=0.25)
            ax.contour(Z, R, inf, levels=[0.5], colors=[col], linewidths=1.8)
        label = (f"w0 = {result.speeds[i]:g} p.u.: infeasible {frac:.1%}"
                 + ("" if frac > 0 else " (all feasible)"))
        handles.append(Patch(facecolor=col, alpha=0.4, edgecolor=col, label=label))
        ax.plot(z38[i], r38[i], marker="*", ms=13, color=col, mec="k", zorder=5)
    if show_degenerate:
        deg = np.any(st[list(idx)] == -1, axis=0).astype(float)
        if deg.any():
            ax.contourf(Z, R, deg, levels=[0.5, 1.5], colors="none", hatches=["////"])
            handles.append(Patch(facecolor="none", hatch="////", edgecolor="grey",
                                 label="degenerate (e.g. w1 = 0)"))
        none = np.any(st[list(idx)] == 2, axis=0).astype(float)
        if none.any():
            ax.contourf(Z, R, none, levels=[0.5, 1.5], colors="none", hatches=[".."])
            handles.append(Patch(facecolor="none", hatch="..", edgecolor="grey",
                                 label="no equilibrium"))
    handles.append(Line2D([], [], marker="*", ms=12, ls="", color="w", mec="k",
                          label="design (38)"))
    cur = result.i_dq[load]
    ax.set_title(f"Feasible designs, i_dq = ({cur[0]:g}, {cur[1]:g}) p.u. "
                 f"[{result.method}, frame {result.frame}]", fontsize=10)
    ax.set_xlabel("damping ratio zeta1")
    ax.set_ylabel("w1 / w0")
    ax.set_xlim(z[0], z[-1])
    ax.set_ylim(r[0], r[-1])
    ax.legend(handles=handles, fontsize=8, loc="upper right")
    return ax


def plot_static_error(result, *, speed: int = 0, load: int = 0, ax=None):
    """Static position error (deg) of the infeasible designs at one speed and load, as a
    colour map over (zeta1, w1/w0); feasible designs are left blank."""
    if ax is None:
        _, ax = plt.subplots(figsize=(6.0, 4.5))
    th = np.asarray(result.stable_theta_deg)[speed, load]
    m = ax.pcolormesh(result.zeta1, result.ratio, th.T, shading="nearest", cmap="twilight",
                      vmin=-180, vmax=180)
    plt.colorbar(m, ax=ax, label="static error (deg)")
    ax.set_xlabel("damping ratio zeta1")
    ax.set_ylabel("w1 / w0")
    ax.set_title(f"Stable nonzero equilibrium, w0 = {result.speeds[speed]:g} p.u.",
                 fontsize=10)
    return ax


def plot_ramp_runs(runs, *, ax=None, label_fmt="{:.3g} rad/s^2"):
    """Angle error (deg) of `simulate_ramp` runs, given as `[(rate, RampRun), ...]`
    (as returned by `fastest_converging_ramp`), against time normalised by the run
    length. Converged runs solid, failed ones dashed."""
    if ax is None:
        _, ax = plt.subplots(figsize=(6.0, 4.0))
    for rate, run in sorted(runs, key=lambda p: p[0]):
        t = np.asarray(run.t)
        th = np.degrees(np.asarray(run.x)[:, 2])
        ok = bool(run.converged)
        ax.plot(t / t[-1], th, ls="-" if ok else "--", lw=1.2,
                label=label_fmt.format(rate) + ("" if ok else " (fails)"))
    ax.set_xlabel("t / t_end")
    ax.set_ylabel("angle error (deg)")
    ax.legend(fontsize=7, ncol=2)
    return ax


def plot_response(curves: dict, *, title: str = ""):
    """The frequency response of an observer from `pmsmjax response --plot`.

    `curves` (from `pmsmjax.cli._response.response_curves`): `orders` and `ripple_deg`,
    the peak angle-error ripple per 1 % back-EMF harmonic of each signed order (every
    observer); for a back-EMF observer also the Bode data `bode` (`f_hz` signed, `mag_db`,
    `phase_deg`, and `mag_db_discrete`, `phase_deg_discrete` at the sampling period) of
    its estimate's gain from the back-EMF component; `marked`: the orders asked for,
    `f_electrical_hz`. Returns the figure (1 panel, or 3 with the Bode plot)."""
    bode = curves.get("bode")
    n = 3 if bode is not None else 1
    fig, axes = plt.subplots(n, 1, figsize=(7.0, 2.6 + 2.4 * (n - 1)), squeeze=False)
    ax = axes[0, 0]
    h = np.asarray(curves["orders"])
    r = np.asarray(curves["ripple_deg"])
    # an order the observer rejects exactly (ripple at rounding level) is left out
    ax.semilogy(h, np.where(r > 1e-9 * np.nanmax(r), r, np.nan), "o-", ms=3,
                color="tab:blue")
    for m in curves.get("marked", ()):
        ax.axvline(m, color="0.6", lw=0.8, ls=":")
    ax.set_xlabel("signed harmonic order h (negative: negative sequence)")
    ax.set_ylabel("angle ripple\n(deg per 1 %)")
    ax.grid(True, which="both", alpha=0.3)
    if bode is not None:
        f = np.asarray(bode["f_hz"])
        for sign, style in ((1, "-"), (-1, "--")):
            sel = np.sign(f) == sign
            lab = "positive sequence" if sign > 0 else "negative sequence"
            for key, ax_i in (("mag_db", 1), ("phase_deg", 2)):
                a = axes[ax_i, 0]
                a.semilogx(np.abs(f[sel]), np.asarray(bode[key])[sel], style,
                           color="tab:orange", label=f"continuous, {lab}")
                if f"{key}_discrete" in bode:
                    a.semilogx(np.abs(f[sel]), np.asarray(bode[f"{key}_discrete"])[sel],
                               style, color="tab:blue", lw=1.0,
                               label=f"discrete (T_s), {lab}")
        fe = float(curves["f_electrical_hz"])
        for a, lab in ((axes[1, 0], "|G| (dB)"), (axes[2, 0], "phase (deg)")):
            for m in curves.get("marked", ()):
                a.axvline(abs(m) * abs(fe), color="0.6", lw=0.8, ls=":")
            a.set_ylabel(lab)
            a.grid(True, which="both", alpha=0.3)
        axes[2, 0].set_xlabel("|frequency| of the back-EMF component (Hz)")
        axes[1, 0].legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return fig


def plot_lock_basin(basin, *, ax=None, title=None, t_max=None):
    """Basin of attraction from `analysis.lock_basin`: time to lock (ms, colour) over
    the initial angle error (deg) x initial speed estimate (relative to the rotor speed);
    starts that never locked (or did not keep the lock) are crossed out in grey."""
    if ax is None:
        _, ax = plt.subplots(figsize=(5.0, 4.0))
    th = np.degrees(np.asarray(basin.theta_err0))
    wr = np.asarray(basin.w_hat0) / float(basin.w_m)
    t_ms = 1e3 * np.asarray(basin.t_lock, float)
    vmax = 1e3 * float(basin.t_end) if t_max is None else 1e3 * float(t_max)
    m = ax.pcolormesh(wr, th, np.ma.masked_invalid(t_ms), shading="nearest",
                      cmap="viridis", vmin=0.0, vmax=vmax)
    bad = ~np.asarray(basin.locked, bool)
    if bad.any():
        W, T = np.meshgrid(wr, th)
        ax.scatter(W[bad], T[bad], marker="x", color="0.5", s=25, label="no lock")
        ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
    plt.colorbar(m, ax=ax, label="time to lock (ms)")
    ax.set_xlabel("initial speed estimate / rotor speed")
    ax.set_ylabel("initial angle error (deg)")
    ax.set_title(title or f"lock basin ({basin.mode}), {100 * basin.fraction_locked:.0f} % "
                          f"locked", fontsize=10)
    return ax


def plot_saturated_map(point, *, w_base=1.0, tau_base=1.0, axes=None, title=None):
    """Maps over (speed, load) of a saturated machine with a constant-model observer
    (`pmsmjax.analysis.saturated_map`): the static angle error (deg, colour, with
    contours) on the left and the verdict per point on the right (feasible,
    infeasible, no equilibrium, degenerate, cannot hold).

    **Arguments:** `point`: the `SaturatedPoint` of `saturated_map` (arrays of shape
    `(n_speeds, n_loads)`); `w_base` (rad/s) and `tau_base` (N m): the axes' units
    (e.g. the drive's `w_rated` and `tau_rated` for p.u.; default SI); `axes`: two axes
    to draw into; `title`: the figure's title. Returns the figure.
    """
    from matplotlib.colors import BoundaryNorm, ListedColormap

    w = np.asarray(point.w_m)[:, 0] / w_base
    t = np.asarray(point.tau_L)[0, :] / tau_base
    th = np.degrees(np.asarray(point.theta))
    verdict = np.asarray(point.verdict)
    if axes is None:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    else:
        fig = axes[0].figure
    ax0, ax1 = axes
    unit_w = "p.u." if w_base != 1.0 else "rad/s el."
    unit_t = "p.u." if tau_base != 1.0 else "N m"
    m = ax0.pcolormesh(t, w, th, shading="nearest", cmap="viridis")
    if np.isfinite(th).sum() > 3 and th.shape[0] > 1 and th.shape[1] > 1:
        cs = ax0.contour(t, w, np.where(np.isfinite(th), th, np.nan), colors="w",
                         linewidths=0.7, levels=[1, 2, 5, 10, 20, 30])
        ax0.clabel(cs, fmt="%g", fontsize=7)
    fig.colorbar(m, ax=ax0, label="static angle error (deg, true - estimate)")
    ax0.set_xlabel(f"load torque ({unit_t})")
    ax0.set_ylabel(f"speed ({unit_w})")
    ax0.set_title("static angle error (blank: no steady state)")
    codes = [-1, 0, 1, 2, 3]
    names = ["degenerate", "feasible", "infeasible", "no equilibrium", "cannot hold"]
    colours = ["0.6", "tab:green", "tab:orange", "tab:purple", "tab:red"]
    cmap = ListedColormap(colours)
    norm = BoundaryNorm(np.arange(-1.5, 4.0, 1.0), cmap.N)
    ax1.pcolormesh(t, w, verdict, shading="nearest", cmap=cmap, norm=norm)
    ax1.legend(handles=[Patch(color=c, label=n) for c, n, k in zip(colours, names, codes)
                        if np.any(verdict == k)], loc="upper right", fontsize=8)
    ax1.set_xlabel(f"load torque ({unit_t})")
    ax1.set_ylabel(f"speed ({unit_w})")
    ax1.set_title("verdict at the steady state")
    if title:
        fig.suptitle(title)
    return fig
