"""Standard per-unit plots of simulation results (matplotlib only).

Not imported by `pmsmjax/__init__.py`: use `from pmsmjax.plotting import plot_trajectory`.
The functions build a `matplotlib.figure.Figure` directly, without pyplot, so they work
with any backend (including Agg on a machine without a display) and leave no global
state behind. Save with `fig.savefig("file.png")`; in Jupyter, `%matplotlib inline` and a
bare `fig` as the last expression of a cell display it.

Per-unit scaling: speeds are fractions of the rated speed `drive.w_rated`, torques of the
rated torque `drive.tau_rated`, currents of `drive.base.I_b` and voltages of
`drive.base.U_b` (docs/conventions.md, "Per unit"). Angles are in degrees, time in s.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from .._frames import wrap_angle


_TRAJ_FIELDS = ("t", "w_m", "w_hat", "w_m_ref", "tau_M", "tau_L", "tau_ref", "i_dq", "i_ref",
                "u_ab", "u_dq", "theta_err")


def _f(x) -> float:
    a = np.asarray(x, dtype=float)
    if a.size != 1:
        raise ValueError(
            "plotting needs a single (unbatched) `Drive` for the per-unit bases; got an array "
            f"of shape {a.shape}. Pass the nominal drive."
        )
    return float(a.reshape(()))


def _axes(fig: Figure | None, n: int, width: float = 9.0, height: float = 1.9):
    """`n` stacked axes sharing the time axis, on a new figure or reused from `fig`."""
    if fig is None:
        fig = Figure(figsize=(width, height * n + 0.6), layout="constrained")
    if len(fig.axes) >= n:
        return fig, fig.axes[:n]
    if fig.axes:
        raise ValueError(
            f"`fig` has {len(fig.axes)} axes; pass an empty figure or one made by this "
            f"function ({n} axes)."
        )
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    for ax in axes:
        ax.grid(True, alpha=0.3)
    return fig, list(axes)


def _legend(ax, extra=(), x: float = 1.01):
    """Legend outside the axes on the right (at `x` in axes units: beyond a twin axis'
    ticks), one entry per label."""
    handles, labels = ax.get_legend_handles_labels()
    seen = {}
    for h, lab in list(zip(handles, labels)) + list(extra):
        if lab and not lab.startswith("_") and lab not in seen:
            seen[lab] = h
    if seen:
        ax.legend(list(seen.values()), list(seen), loc="upper left",
                  bbox_to_anchor=(x, 1.0), fontsize="small", frameon=False)


def _split_runs(obj, fields):
    """Numpy arrays of `fields` as a list of single runs (leading batch axes flattened)."""
    t = np.asarray(obj.t)
    batch = t.shape[:-1]
    runs = []
    arrays = {}
    for f in fields:
        a = np.asarray(getattr(obj, f), dtype=float)
        arrays[f] = a.reshape((-1,) + a.shape[len(batch):])
    n = int(np.prod(batch, dtype=int)) if batch else 1
    for i in range(n):
        runs.append({f: a[i] for f, a in arrays.items()})
    return runs


def plot_trajectory(traj, drive, *, title: str | None = None, fig: Figure | None = None,
                    labels=None) -> Figure:
    """The standard stacked per-unit plot of a closed-loop `Trajectory`.

    Panels, top to bottom (time axis in s):

    1. speed: `w_m`, `w_hat` and `w_m_ref` (p.u. of `drive.w_rated`);
    2. torque: `tau_M`, `tau_L` and `tau_ref` (p.u. of `drive.tau_rated`);
    3. currents: `i_dq` and the references `i_ref` (p.u. of `drive.base.I_b`);
    4. voltage: `|u|`, `u_dq` and the inverter limit (p.u. of `drive.base.U_b`);
    5. angle error `theta - theta_hat` (degrees).

    **Arguments:**

    - `traj`: a `Trajectory` from `simulate`, or a batch of them (leading `vmap` axes):
      runs of a batch are overlaid, one colour per run, with fewer lines per run
      (no current/voltage references or components).
    - `drive`: the (unbatched) `Drive` whose ratings and bases define the per unit.
    - `title`: figure title; default the drive's name.
    - `fig`: draw into this figure (empty, or one returned by this function, to overlay);
      default a new one.
    - `labels`: one legend label per run of a batch (e.g. the swept parameter values).

    **Returns:** the `matplotlib.figure.Figure`.
    """
    w_b, tau_b = _f(drive.w_rated), _f(drive.tau_rated)
    I_b, U_b = _f(drive.base.I_b), _f(drive.base.U_b)
    u_lim = _f(drive.inverter.u_lim)
    runs = _split_runs(traj, _TRAJ_FIELDS)
    batched = np.ndim(traj.t) > 1
    if labels is not None and len(labels) != len(runs):
        raise ValueError(f"`labels` needs one label per run ({len(runs)}); got {len(labels)}.")
    fig, (ax_w, ax_tau, ax_i, ax_u, ax_th) = _axes(fig, 5)

    for k, r in enumerate(runs):
        t = r["t"]
        c = f"C{k % 10}"
        i_dq, i_ref = r["i_dq"] / I_b, r["i_ref"] / I_b
        u_dq = r["u_dq"] / U_b
        u_abs = np.hypot(r["u_ab"][:, 0], r["u_ab"][:, 1]) / U_b
        th_err = np.degrees(r["theta_err"])
        if not batched:
            ax_w.plot(t, r["w_m_ref"] / w_b, "k--", lw=1, zorder=3, label=r"$\omega_{m,ref}$")
            ax_w.plot(t, r["w_m"] / w_b, "C0", label=r"$\omega_m$")
            ax_w.plot(t, r["w_hat"] / w_b, "C1:", label=r"$\hat\omega_m$")
            ax_tau.plot(t, r["tau_ref"] / tau_b, "k--", lw=1, zorder=3, label=r"$\tau_{ref}$")
            ax_tau.plot(t, r["tau_M"] / tau_b, "C0", label=r"$\tau_M$")
            ax_tau.plot(t, r["tau_L"] / tau_b, "C3-.", label=r"$\tau_L$")
            ax_i.plot(t, i_ref[:, 0], "k--", lw=1, zorder=3, label=r"$i_{d,ref}$")
            ax_i.plot(t, i_ref[:, 1], "k:", lw=1, zorder=3, label=r"$i_{q,ref}$")
            ax_i.plot(t, i_dq[:, 0], "C0", label=r"$i_d$")
            ax_i.plot(t, i_dq[:, 1], "C1", label=r"$i_q$")
            ax_u.plot(t, u_abs, "k--", lw=1, zorder=3, label=r"$|u|$")
            ax_u.plot(t, u_dq[:, 0], "C0", label=r"$u_d$")
            ax_u.plot(t, u_dq[:, 1], "C1", label=r"$u_q$")
            ax_th.plot(t, th_err, "C0", label=r"$\tilde\theta$")
        else:
            lab = str(labels[k]) if labels is not None else f"run {k}"
            ax_w.plot(t, r["w_m_ref"] / w_b, "--", color=c, lw=1, alpha=0.7)
            ax_w.plot(t, r["w_m"] / w_b, color=c, label=lab)
            ax_w.plot(t, r["w_hat"] / w_b, ":", color=c)
            ax_tau.plot(t, r["tau_M"] / tau_b, color=c)
            ax_tau.plot(t, r["tau_L"] / tau_b, "-.", color=c, lw=1)
            ax_i.plot(t, i_dq[:, 1], color=c)
            ax_i.plot(t, i_dq[:, 0], "-.", color=c, lw=1)
            ax_u.plot(t, u_abs, color=c)
            ax_th.plot(t, th_err, color=c)
    ax_u.axhline(u_lim / U_b, color="0.5", ls=":", lw=1, label=r"$u_{max}$")

    if batched:
        def proxy(ls, lab):
            return Line2D([], [], color="k", ls=ls), lab

        _legend(ax_w, [proxy("-", r"$\omega_m$"), proxy(":", r"$\hat\omega_m$"),
                       proxy("--", r"$\omega_{m,ref}$")])
        _legend(ax_tau, [proxy("-", r"$\tau_M$"), proxy("-.", r"$\tau_L$")])
        _legend(ax_i, [proxy("-", r"$i_q$"), proxy("-.", r"$i_d$")])
        _legend(ax_u, [proxy("-", r"$|u|$")])
        _legend(ax_th)
    else:
        for ax in (ax_w, ax_tau, ax_i, ax_u, ax_th):
            _legend(ax)
    ax_w.set_ylabel("speed (p.u.)")
    ax_tau.set_ylabel("torque (p.u.)")
    ax_i.set_ylabel("current (p.u.)")
    ax_u.set_ylabel("voltage (p.u.)")
    ax_th.set_ylabel("angle error (deg)")
    # Sensored runs have angle errors at rounding level: show at least +-1 deg.
    lo, hi = ax_th.get_ylim()
    ax_th.set_ylim(min(lo, -1.0), max(hi, 1.0))
    ax_th.set_xlabel("time (s)")
    ax_th.set_xlim(float(np.min(np.asarray(traj.t))), float(np.max(np.asarray(traj.t))))
    fig.suptitle(title if title is not None else f"{drive.name}: closed-loop simulation")
    return fig


def plot_plant_trace(trace, drive, *, data=None, title: str | None = None,
                     fig: Figure | None = None) -> Figure:
    """Per-unit plot of an open-loop plant run (`PlantTrace` from `run_plant`).

    Panels (time axis in s): applied voltage `u_ab` (if `data` has it, p.u. of
    `base.U_b`); stationary currents `i_ab` and rotor-frame currents `i_dq` (p.u. of
    `base.I_b`); speed `w_m` (p.u. of `drive.w_rated`); torque `tau_M` and load `tau_L`
    (p.u. of `drive.tau_rated`); and, if `data` has a recorded angle, the angle difference
    simulated minus recorded (degrees). Recorded values in `data` are drawn dashed for
    comparison.

    **Arguments:**

    - `trace`: the `PlantTrace` of one run.
    - `drive`: the (unbatched) `Drive` whose ratings and bases define the per unit.
    - `data`: optional `RecordedData` that drove the plant (its `u_ab`, `tau_L`) and holds
      recorded `i_ab`, `w_m`, `theta` to compare with.
    - `title`: figure title; default the drive's name.
    - `fig`: draw into this (empty) figure; default a new one.

    **Returns:** the `matplotlib.figure.Figure`.
    """
    if np.ndim(trace.t) != 1:
        raise ValueError("`plot_plant_trace` needs one run (an unbatched `PlantTrace`).")
    w_b, tau_b = _f(drive.w_rated), _f(drive.tau_rated)
    I_b, U_b = _f(drive.base.I_b), _f(drive.base.U_b)
    t = np.asarray(trace.t, dtype=float)
    i_ab = np.asarray(trace.i_ab, dtype=float) / I_b
    i_dq = np.asarray(trace.i_dq, dtype=float) / I_b
    w_m = np.asarray(trace.w_m, dtype=float) / w_b
    tau_M = np.asarray(trace.tau_M, dtype=float) / tau_b
    theta = np.asarray(trace.theta, dtype=float)

    def rec(name):
        return None if data is None else getattr(data, name)

    panels = (["voltage"] if rec("u_ab") is not None else []) + \
        ["i_ab", "i_dq", "speed", "torque"] + (["angle"] if rec("theta") is not None else [])
    fig, axes = _axes(fig, len(panels))
    ax = dict(zip(panels, axes))
    if "voltage" in ax:
        u = rec("u_ab") / U_b
        ax["voltage"].plot(t, u[:, 0], "C0", label=r"$u_\alpha$")
        ax["voltage"].plot(t, u[:, 1], "C1", label=r"$u_\beta$")
        ax["voltage"].set_ylabel("voltage (p.u.)")
    a = ax["i_ab"]
    a.plot(t, i_ab[:, 0], "C0", label=r"$i_\alpha$")
    a.plot(t, i_ab[:, 1], "C1", label=r"$i_\beta$")
    if rec("i_ab") is not None:
        a.plot(t, rec("i_ab")[:, 0] / I_b, "k--", lw=1, label="recorded")
        a.plot(t, rec("i_ab")[:, 1] / I_b, "k--", lw=1)
    a.set_ylabel("current (p.u.)")
    a = ax["i_dq"]
    a.plot(t, i_dq[:, 0], "C0", label=r"$i_d$")
    a.plot(t, i_dq[:, 1], "C1", label=r"$i_q$")
    a.set_ylabel("current (p.u.)")
    a = ax["speed"]
    a.plot(t, w_m, "C0", label=r"$\omega_m$")
    if rec("w_m") is not None:
        a.plot(t, rec("w_m") / w_b, "k--", lw=1, label="recorded")
    a.set_ylabel("speed (p.u.)")
    a = ax["torque"]
    a.plot(t, tau_M, "C0", label=r"$\tau_M$")
    if rec("tau_L") is not None:
        a.plot(t, rec("tau_L") / tau_b, "C3-.", label=r"$\tau_L$")
    a.set_ylabel("torque (p.u.)")
    if "angle" in ax:
        d = np.degrees(np.asarray(wrap_angle(theta - rec("theta"))))
        ax["angle"].plot(t, d, "C0", label=r"$\theta - \theta_{rec}$")
        ax["angle"].set_ylabel("angle diff. (deg)")
        lo, hi = ax["angle"].get_ylim()
        ax["angle"].set_ylim(min(lo, -1.0), max(hi, 1.0))
    for a in axes:
        _legend(a)
    axes[-1].set_xlabel("time (s)")
    axes[-1].set_xlim(float(t[0]), float(t[-1]))
    fig.suptitle(title if title is not None else f"{drive.name}: open-loop plant run")
    return fig


def _worst_window(tr, segment_s: float, span: int = 3) -> tuple[np.ndarray, float, float]:
    """Sample mask of the `span` segments around the segment of `tr` whose current
    residual RMS is largest, that RMS and the whole trace's (A)."""
    t = np.asarray(tr["t"])
    err = np.sum((np.asarray(tr["i_model"]) - np.asarray(tr["i_ab"])) ** 2, axis=1)
    seg = ((t - t[0]) / segment_s + 1e-9).astype(int)
    n_seg = int(seg.max()) + 1
    rms = np.sqrt(np.bincount(seg, err, n_seg) / np.maximum(np.bincount(seg, None, n_seg), 1))
    worst = int(np.argmax(rms))
    lo = min(max(worst - span // 2, 0), max(n_seg - span, 0))
    return (seg >= lo) & (seg < lo + span), float(rms[worst]), float(np.sqrt(np.mean(err)))


def plot_identification(result, *, recording: int | None = None,
                        t_window: float | None = None, title: str | None = None) -> Figure:
    """Measured against model signals of a `pmsmjax.identify` result: the alpha and beta
    currents (A), the speed (rad/s, electrical) and the current residual, the model
    restarted at each segment start (multiple shooting: the logged angle and speed, the
    fitted current); a load torque fitted per segment (N m) on the speed panel's right
    axis.

    **Arguments:**

    - `recording`: the recording to show (index); default every recording, one column
      each (the eight with the largest residual).
    - `t_window`: show the first `t_window` seconds; default the three segments around
      each recording's worst one (largest current residual RMS), which the column's title
      names with its residual and the whole recording's.
    - `title`: the figure's title (default: the fitted values).
    """
    which = range(len(result.traces)) if recording is None else [recording]
    cols = []
    for r in which:
        tr = result.traces[r]
        t = np.asarray(tr["t"])
        if t_window is None:
            k, worst, whole = _worst_window(tr, result.segment_s)
            label = (f"recording {r}: worst segments {t[k][0]:.3g}-{t[k][-1]:.3g} s, "
                     f"residual {worst:.3g} A (whole recording {whole:.3g} A)")
        else:
            k = t - t[0] <= float(t_window)
            label = f"recording {r}: first {float(t_window):g} s"
        cols.append((tr, k, label, worst if t_window is None else 0.0, r))
    if recording is None and len(cols) > 8:
        cols = sorted(cols, key=lambda c: -c[3])[:8]
    fig = Figure(figsize=(6.0 * len(cols) + 1.5, 7.4), layout="constrained")
    grid = fig.subplots(4, len(cols), sharex="col", squeeze=False)
    loads = getattr(result, "loads", None) or [None] * len(result.traces)
    for j, (tr, k, label, _, r) in enumerate(cols):
        ax = grid[:, j]
        t = np.asarray(tr["t"])[k]
        for row, name in enumerate(("alpha", "beta")):
            ax[row].plot(t, tr["i_ab"][k, row], "k", lw=0.8, label=f"i_{name} measured")
            ax[row].plot(t, tr["i_model"][k, row], "r--", lw=1.0, label="model")
            ax[row].set_ylabel(f"i_{name} (A)")
        ax[2].plot(t, tr["w_m"][k], "k", lw=0.8, label="w_m measured")
        ax[2].plot(t, tr["w_model"][k], "r--", lw=1.0, label="model")
        ax[2].set_ylabel("speed (rad/s)")
        extra = ()
        if loads[r] is not None:
            ld, tw = loads[r], ax[2].twinx()
            t0 = np.asarray(ld["t_start"])  # the segments in the window, to its ends
            sel = np.flatnonzero((t0 + result.segment_s > t[0]) & (t0 < t[-1]))
            xs = np.clip(np.append(t0[sel], t0[sel[-1]] + result.segment_s), t[0], t[-1])
            extra = tw.step(xs, np.append(ld["value"][sel], ld["value"][sel[-1]]),
                            where="post", color="C2", lw=1.0,
                            label="load fitted per segment (N m, right)")
            extra = [(h, h.get_label()) for h in extra]
            tw.tick_params(axis="y", colors="C2")
        for row in (0, 1):
            ax[3].plot(t, tr["i_model"][k, row] - tr["i_ab"][k, row], lw=0.6,
                       color=f"C{row}", label=f"i_{('alpha', 'beta')[row]} model - measured")
        ax[3].set_ylabel("residual (A)")
        ax[3].set_xlabel("t (s)")
        ax[0].set_title(label, fontsize=8)
        for a in ax:
            a.grid(True, alpha=0.3)
            if j == len(cols) - 1:
                _legend(a, extra if a is ax[2] else (), 1.1 if extra and a is ax[2] else 1.01)
    fit = ", ".join(f"{n} {p['value']:.4g} {p['unit']}" for n, p in result.parameters.items())
    fig.suptitle(title or f"identified: {fit}", fontsize=9)
    return fig
