"""Regenerate `docs/figures/lock_basins.png` and `lock_basins.json`: the basin of
attraction of every registered observer's designed lock (`pmsmjax.analysis.lock_basin`,
replay of a recording turning at half the rated speed), each with its default design on
its own paper's motor preset (about a minute on 2 CPU cores).

    .venv/bin/python docs/figures/make_lock_basin_figure.py
"""

import json
import math
import pathlib

import matplotlib


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import pmsmjax as pj  # noqa: E402
from pmsmjax import analysis  # noqa: E402
from pmsmjax.observers import make_observer, observer_names, paper_drive  # noqa: E402
from pmsmjax.plotting import plot_lock_basin  # noqa: E402


HERE = pathlib.Path(__file__).resolve().parent

if __name__ == "__main__":
    pj.runtime.configure()
    theta = np.linspace(-math.pi, math.pi, 16, endpoint=False)
    ratios = np.array([-1.0, -0.5, 0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5])
    names = observer_names()  # each on its paper's drive, at its sampling period
    cols = math.ceil(len(names) / 2)
    fig, axes = plt.subplots(2, cols, figsize=(4.5 * cols, 8), constrained_layout=True)
    table = {}
    for ax, name in zip(axes.ravel(), names):
        preset, T_s = paper_drive(name)
        drive = pj.preset(preset)
        w_m = 0.5 * float(drive.w_rated)
        b = analysis.lock_basin(make_observer(name, drive), drive, w_m=w_m,
                                theta_err0=theta, w_hat0=ratios * w_m, t_end=0.4,
                                T_s=T_s)
        plot_lock_basin(b, ax=ax, title=f"{name} on {preset}: "
                                        f"{100 * b.fraction_locked:.0f} % locked")
        zero = b.locked[:, ratios == 0.0].ravel()
        table[name] = {
            "preset": preset, "w_m_rad_s": w_m, "fraction_locked": b.fraction_locked,
            "fraction_locked_from_zero_speed": float(np.mean(zero)),
            "T_s": T_s,
            "worst_t_lock_s": b.worst_t_lock if math.isfinite(b.worst_t_lock) else None,
            "tol_rad": b.tol, "t_end_s": b.t_end}
        print(name, table[name])
    fig.savefig(HERE / "lock_basins.png", dpi=80)
    (HERE / "lock_basins.json").write_text(json.dumps(table, indent=1) + "\n")
