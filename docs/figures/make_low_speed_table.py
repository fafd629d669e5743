"""The low-speed table of docs/lock-and-startup.md: for every registered observer on
zhang750 (default design, matched model, no noise), whether it keeps the lock from the
correct start and from 0.5 rad off (`lock_basin`, replay, 0.4 s, i_q = 0.3 i_max) at
0.01 ... 0.2 p.u. speed, and its largest final angle error (deg). About a minute.

    .venv/bin/python docs/figures/make_low_speed_table.py
"""

import numpy as np

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import make_observer, observer_names


if __name__ == "__main__":
    pj.runtime.configure()
    drive = pj.preset("zhang750")
    for name in observer_names():
        if name == "sensored":
            continue
        obs = make_observer(name, drive)
        cells = []
        for s in (0.01, 0.02, 0.05, 0.1, 0.2):
            w = s * float(drive.w_rated)
            b = analysis.lock_basin(obs, drive, w_m=w, theta_err0=[0.0, 0.5], w_hat0=[w],
                                    t_end=0.4, progress=False)
            err = float(np.degrees(np.abs(b.final_err).max()))
            cells.append(f"{s:g}: {'lock' if b.locked.all() else 'NO'} ({err:.3g} deg)")
        print(name, "  ".join(cells), flush=True)
