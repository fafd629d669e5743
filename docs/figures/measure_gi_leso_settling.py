"""The li observers under load steps (docs/tuning.md, "The li observers under load
steps"): the command line's load-step run (`pmsmjax simulate --motor morawiec_ipm3k5 --scenario
load-step`, 0.5 p.u., a 0.5 p.u. load step at 0.5 s and back at 1 s) with the li observers
and zhang2022's ESO, the li observers with the PLL's bandwidth w_pll scaled from the
default's, and the GI-LESO with its resonator's gain K_r and attenuation w_c scaled from
Table II's. Per design: the static lag of the analysis (`analysis.equilibria` at 0.5 p.u.
and 0.5 p.u. of i_q, the principal equilibrium), for the GI-LESO the two slowest decay
rates of its linearised error dynamics there (-Re of the eigenvalues, a complex pair
once), and the run's RMS angle error (deg), over the whole run and from 0.5 s on (after
the start). Each run is a fresh `pmsmjax`
process, as a user runs it; about a minute. Writes the table between the page's
`<!-- gi-leso settling -->` markers.

    .venv/bin/python docs/figures/measure_gi_leso_settling.py
"""

import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np
from _page import markdown_table, write_block

import pmsmjax as pj
from pmsmjax import analysis
from pmsmjax.observers import make_observer


HERE = os.path.dirname(os.path.abspath(__file__))
PAGE = os.path.join(HERE, os.pardir, "tuning.md")
BEGIN, END = "<!-- gi-leso settling -->", "<!-- /gi-leso settling -->"
MOTOR = "morawiec_ipm3k5"
#: (observer, {design parameter: factor on its default}), each run in this order
CASES = (("eso", {}), ("c-leso", {}), ("fa-leso", {}), ("fa-leso", {"w_pll": 4}),
         ("gi-leso", {}), ("gi-leso", {"w_pll": 4}), ("gi-leso", {"w_c": 4}),
         ("gi-leso", {"K_r": 4}), ("gi-leso", {"K_r": 4, "w_c": 4}),
         ("gi-leso", {"K_r": 4, "w_c": 4, "w_pll": 4}))


def run(name: str, gains: dict, out: str) -> tuple[np.ndarray, np.ndarray]:
    """The command line's load-step run; returns (t, angle error in deg)."""
    cmd = [sys.executable, "-m", "pmsmjax", "simulate", "--motor", MOTOR, "--observer", name,
           "--scenario", "load-step", "--no-plot", "--out", out]
    for k, v in gains.items():
        cmd += ["--gain", f"{k}={v!r}"]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{p.stderr}")
    with np.load(os.path.join(out, "trajectory.npz")) as f:
        return np.asarray(f["t"]), np.degrees(np.angle(np.exp(1j * f["theta_err"])))


if __name__ == "__main__":
    pj.runtime.configure()
    drive = pj.preset(MOTOR)
    w, i_q = 0.5 * float(drive.w_rated), 0.5 * float(drive.base.I_b)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, (name, factors) in enumerate(CASES):
            obs = make_observer(name, drive)
            paper = obs.design_parameters()
            gains = {g: f * float(paper[g]) for g, f in factors.items()}
            obs = obs.with_design(**gains)
            eq = analysis.equilibria(obs, drive.three_phase_motor, w, np.array([0.0, i_q]))
            if int(eq.status) != 0:
                raise SystemExit(f"{name} {factors}: analysis.equilibria status "
                                 f"{int(eq.status)} at 0.5 p.u.; no static lag to report")
            principal = int(eq.principal)
            # decay rates, each complex pair once
            ev = np.linalg.eigvals(np.asarray(eq.jacobian)[principal])
            rates = np.unique(np.round(-ev.real, 6))[:2]
            t, e = run(name, gains, os.path.join(tmp, str(k)))
            after = t >= 0.5
            design = ", ".join(f"{g} x{f:g}" for g, f in factors.items()) or "default"
            rows.append([name, design, f"{math.degrees(float(eq.theta[principal])):.2f}",
                         " / ".join(f"{r:.1f}" for r in rates) if name == "gi-leso"
                         else "-",
                         f"{np.sqrt(np.mean(e ** 2)):.2f}",
                         f"{np.sqrt(np.mean(e[after] ** 2)):.2f}"])
            print(" | ".join(rows[-1]), flush=True)
    table = markdown_table(
        [("observer", "l"), ("design", "l"), ("static lag (deg)", "r"),
         ("slowest decay rates (1/s)", "r"), ("RMS, whole run (deg)", "r"),
         ("RMS from 0.5 s (deg)", "r")], rows)
    stamp = (f"(`docs/figures/measure_gi_leso_settling.py`, {time.strftime('%Y-%m-%d')}, "
             f"{platform.machine()}, Python {platform.python_version()}):")
    write_block(PAGE, BEGIN, END, f"{stamp}\n\n{table}")
    with open(os.path.join(HERE, "gi_leso_settling.json"), "w") as f:
        json.dump({"rows": rows}, f, indent=1)
    print(f"wrote {PAGE} and gi_leso_settling.json")
