"""Figures of the observer comparison (`tuning.compare`), from a finished job folder.

- `robustness_maps.png`: per observer (columns) and design (rows), the static angle error
  $|\\tilde\\theta_{static}|$ (deg, worst over the loads) over signed speed (x) and
  mismatch case (y), all panels on one colour scale; a cross marks a point where a run
  lost lock.
- `metrics.png`: bar charts of the per-observer metrics, paper and tuned design.
- `traces.png`: angle error and speed-estimate error over time in the hardest scenario
  (the grid point with the largest median, over the observers' paper designs, of the
  run's RMS angle error), every observer.

matplotlib is imported inside the functions (nothing in `tuning` imports it at import
time).
"""

from __future__ import annotations

import pathlib

import numpy as np

from .config import DESIGNS, TRACE_SAMPLES, case_label


#: (key, label) of the bar charts.
BARS = (("static_worst_deg", "worst static error (deg)"),
        ("static_rms_deg", "RMS static error (deg)"),
        ("rms_worst_deg", "worst run RMS error (deg)"),
        ("settle_worst_s", "worst settling time (s)"),
        ("noise_median_rad_s", "median speed noise (rad/s)"),
        ("lost_lock", "runs that lost lock"),
        ("feasible_fraction", "feasible fraction (analysis)"))


def _runs(sweeps: pathlib.Path, name: str, design: str):
    path = sweeps / name / design / "runs" / "result.npz"
    if not path.is_file():
        return None
    with np.load(path) as f:
        return dict(f)


def hardest_point(summary: dict, out, sweeps=None) -> tuple[int, ...] | None:
    """Grid index (speed, load, case) of the hardest scenario (module docstring).
    `sweeps`: the job's sweep folder (default `out/sweeps`)."""
    sweeps = pathlib.Path(out) / "sweeps" if sweeps is None else pathlib.Path(sweeps)
    rms = [r["rms_deg"] for n in summary["observers"]
           if (r := _runs(sweeps, n, "paper")) is not None]
    if not rms:
        return None
    med = np.median(np.stack(rms), axis=0)
    return tuple(int(i) for i in np.unravel_index(int(np.argmax(med)), med.shape))


def plot_comparison(summary: dict, out, sweeps=None) -> list[pathlib.Path]:
    """Write the three figures into the job folder `out`; returns their paths.
    `sweeps`: the job's sweep folder (default `out/sweeps`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = pathlib.Path(out)
    sweeps = out / "sweeps" if sweeps is None else pathlib.Path(sweeps)
    paths = []
    for fn, name in ((_maps, "robustness_maps"), (_bars, "metrics"), (_traces, "traces")):
        fig = fn(summary, sweeps, plt)
        if fig is None:
            continue
        path = out / f"{name}.png"
        fig.savefig(path, dpi=110, bbox_inches="tight")
        plt.close(fig)
        paths.append(path)
    return paths


def _maps(summary, sweeps, plt):
    names = list(summary["observers"])
    designs = DESIGNS
    g = summary["grid"]
    data = {}
    for n in names:
        for d in designs:
            r = _runs(sweeps, n, d)
            if r is None:
                continue
            static = np.abs(r["static_deg"])  # (speed, load, case)
            lost = r["lost_lock"].astype(bool)
            worst = np.max(np.where(lost, -np.inf, static), axis=1)  # over loads kept
            worst = np.where(np.isfinite(worst), worst, np.nan)  # every load lost lock
            data[n, d] = (worst.T, np.any(lost, axis=1).T)  # (case, speed)
    if not data:
        return None
    designs = tuple(d for d in designs if any((n, d) in data for n in names))
    vals = np.concatenate([v[0][np.isfinite(v[0])].ravel() for v in data.values()])
    vmax = max(float(np.max(vals)) if vals.size else 1.0, 1e-3)
    fig, axes = plt.subplots(len(designs), len(names), squeeze=False, sharex=True,
                             sharey=True, figsize=(2.3 * len(names) + 1.5, 5.2))
    speeds = np.asarray(g["speeds_pu"])
    cases = [case_label(c) for c in g["cases"]]
    im = None
    cmap = plt.get_cmap("viridis").with_extremes(bad="0.85")
    for i, d in enumerate(designs):
        for j, n in enumerate(names):
            ax = axes[i, j]
            if (n, d) not in data:
                ax.set_axis_off()
                continue
            worst, lost = data[n, d]
            im = ax.imshow(np.ma.masked_invalid(worst), aspect="auto", origin="lower",
                           cmap=cmap, vmin=0.0, vmax=vmax, interpolation="nearest")
            yy, xx = np.nonzero(lost)
            ax.plot(xx, yy, "x", color="red", ms=6, mew=1.5)
            if i == 0:
                ax.set_title(n, fontsize=9)
            ax.set_xticks(range(len(speeds)))
            ax.set_xticklabels([f"{s:g}" for s in speeds], rotation=90, fontsize=7)
            ax.set_yticks(range(len(cases)))
            ax.set_yticklabels(cases, fontsize=7)
        axes[i, 0].set_ylabel(f"{d} design\nmismatch (observer / plant)", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("speed (p.u.)", fontsize=8)
    fig.colorbar(im, ax=axes, label="|static angle error| (deg, worst over loads)",
                 shrink=0.9)
    fig.suptitle(f"{summary['motor']}: static angle error over speed and mismatch "
                 f"(x: lost lock; grey: every load lost lock)", fontsize=10)
    return fig


def _bars(summary, sweeps, plt):
    del sweeps
    names = list(summary["observers"])
    fig, axes = plt.subplots(1, len(BARS), figsize=(2.6 * len(BARS), 3.4))
    x = np.arange(len(names))
    for ax, (key, label) in zip(axes, BARS):
        for k, d in enumerate(DESIGNS):
            color = f"C{k}"
            v = [summary["observers"][n]["designs"].get(d, {}).get(key) for n in names]
            h = [np.nan if a is None else a for a in v]
            ax.bar(x + (k - 0.5) * 0.38, h, width=0.38, color=color, label=d)
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=60, fontsize=7)
        ax.set_title(label, fontsize=8)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{summary['motor']}: per-observer metrics (paper and tuned design; a "
                 f"missing bar is n/a)", fontsize=10)
    fig.tight_layout()
    return fig


def _traces(summary, sweeps, plt):
    idx = hardest_point(summary, None, sweeps)
    if idx is None:
        return None
    c = summary["config"]
    g = summary["grid"]
    n_saved = int(round(c["t_end"] / c["T_s"])) // c["save_every"]
    fig, (a1, a2) = plt.subplots(2, 1, sharex=True, figsize=(8, 5))
    for k, n in enumerate(summary["observers"]):
        for d, ls in zip(DESIGNS, ("-", "--")):
            r = _runs(sweeps, n, d)
            if r is None:
                continue
            th = r["trace_theta_deg"][idx]
            stride = max(1, n_saved // TRACE_SAMPLES)  # as `points.run_point` keeps them
            t = np.arange(th.shape[-1]) * stride * c["T_s"] * c["save_every"]
            kw = dict(color=f"C{k % 10}", ls=ls, lw=1.0,
                      label=n if d == "paper" else None)
            a1.plot(t, th, **kw)
            a2.plot(t, r["trace_w_err"][idx], **kw)
    speed = sorted(g["speeds_pu"])[idx[0]]
    load = g["loads_pu"][idx[1]]
    case = case_label(g["cases"][idx[2]])
    a1.set_ylabel("angle error (deg)")
    a2.set_ylabel("speed-estimate error (rad/s)")
    a2.set_xlabel("t (s)")
    a1.legend(fontsize=7, ncol=4)
    a1.set_title(f"hardest scenario: {speed:g} p.u., load {load:g} p.u., {case} "
                 f"(solid: paper design, dashed: tuned)", fontsize=9)
    for a in (a1, a2):
        a.grid(alpha=0.3)
    fig.tight_layout()
    return fig

