"""The figure of the saturated analysis (docs/observers.md, "Analysis on a saturated
machine"): maps over (speed, load) of the static angle error and the verdict for the ESO
and the parallel-model estimator on the saturated preset `ipm3k5_sat`, each keeping the
drive's constant (small-current) model (`pmsmjax.analysis.saturated_map`).

Run from the repository root: `python docs/figures/make_saturated_map_figure.py`
(writes docs/figures/saturated_map.png and saturated_map.json)."""

import json
import os
import time

import jax
import matplotlib


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import pmsmjax as pj  # noqa: E402
from pmsmjax.analysis import saturated_map  # noqa: E402
from pmsmjax.plotting import plot_saturated_map  # noqa: E402


jax.config.update("jax_enable_x64", True)
HERE = os.path.dirname(os.path.abspath(__file__))
SPEEDS = np.linspace(0.2, 1.0, 9)
LOADS = np.linspace(0.05, 0.9, 18)


def main():
    drive = pj.preset("ipm3k5_sat")
    w_r, t_r = float(drive.w_rated), float(drive.tau_rated)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), constrained_layout=True)
    out = {"speeds_pu": SPEEDS.tolist(), "loads_pu": LOADS.tolist()}
    for row, name in zip(axes, ("eso", "parallel-model")):
        obs = pj.observers.make_observer(name, drive)
        t0 = time.perf_counter()
        m = jax.device_get(saturated_map(obs, drive, SPEEDS * w_r, LOADS * t_r))
        print(f"{name}: {time.perf_counter() - t0:.1f} s")
        plot_saturated_map(m, w_base=w_r, tau_base=t_r, axes=row)
        row[0].set_title(f"{name}: static angle error (deg)")
        row[1].set_title(f"{name}: verdict")
        out[name] = {"theta_deg": np.where(np.isfinite(m.theta), np.degrees(m.theta),
                                           None).tolist(),
                     "verdict": np.asarray(m.verdict).tolist()}
    fig.suptitle("ipm3k5_sat, observers with the drive's constant model, FOC i_d = 0")
    fig.savefig(os.path.join(HERE, "saturated_map.png"), dpi=100)
    with open(os.path.join(HERE, "saturated_map.json"), "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main()
