"""The static error against the noise of the li observers (docs/tuning.md, "The trade a
LESO's bandwidth makes"): on `li_dtp` at 0.5 p.u. and i_q = 0.5 p.u., each LESO's
bandwidth w0 at 0.5x to 2x the paper's (the tuner's box is 0.3x to 3x), the static angle
error and the first-order RMS angle and speed-estimate noise per 0.01 A of white
current-sensor noise (`analysis.sensor_noise`). Under a minute.

    .venv/bin/python docs/figures/make_lag_noise_table.py
"""

import numpy as np

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import make_observer


if __name__ == "__main__":
    pj.runtime.configure()
    drive = pj.preset("li_dtp")
    op = analysis.OperatingPoint(0.5 * float(drive.w_rated),
                                 np.array([0.0, 0.5 * float(drive.base.I_b)]))
    print("| observer | w0 / paper | static error (deg) | angle noise (deg) | "
          "speed noise (rad/s) |")
    print("|---|---:|---:|---:|---:|")
    for name in ("c-leso", "gi-leso", "fa-leso"):
        obs = make_observer(name, drive)
        for f in (0.5, 1.0, 2.0):
            if name == "fa-leso":  # k1 f^2, k2 f: the roots of (22) f times faster
                d = obs.design_parameters()
                o = obs.with_design(k1=float(d["k1"]) * f * f, k2=float(d["k2"]) * f)
            else:
                o = obs.with_design(w0=float(obs.design_parameters()["w0"]) * f)
            r = analysis.sensor_noise(o, drive, op, 1e-4, 0.01)
            print(f"| {name} | {f:g} | {np.degrees(float(r.theta_static)):.2f} | "
                  f"{np.degrees(float(r.theta_rms)):.4f} | {float(r.w_rms):.4f} |",
                  flush=True)
