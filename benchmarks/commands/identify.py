"""Time of `pmsmjax identify` on a 1-second recording, cold and warm.

The recording: zhang750 with 3 V of dead time under current control (i_q reversing every
0.1 s, i_d steps), encoder angle and speed, 0.02 A current noise, 10 kHz (10,000
samples), commanded voltages. The fit: R_s, L_d, L_q, psi_f, J, B and u_dt from values
off by 30-40 %. Each case runs `pmsmjax identify` as a fresh process (start-up,
compilation and both Levenberg-Marquardt solves included) with the persistent
compilation cache empty ("cold") or filled by the previous run ("warm"), and reports the
wall time, the solver steps and the largest relative error of the fitted parameters.

Usage (from the repository root):

    python -m benchmarks.commands.identify [--repeat N] [--quick]
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

import pmsmjax as pj

from .. import _harness as h


MODULE = "benchmarks.commands.identify"


FIT = ("R_s", "L_d", "L_q", "psi_f", "J", "B", "u_dt")


def _value(d, n):
    if n in ("J", "B"):
        return float(getattr(d.mechanics, n))
    return float(d.inverter.u_dt) if n == "u_dt" else float(getattr(d.motor, n))


def _make(folder: Path):
    true = pj.replace_params(pj.preset("zhang750"), u_dt=3.0, B=2e-4)
    i_m, T = float(true.i_max), 1.0
    t_q = list(np.linspace(0, T, 11)[1:-1])
    sc = pj.Scenario(
        t_end=T,
        i_q_ref=pj.Profile.steps(t_q, [0.3 * i_m * (-1) ** k for k in range(1, 10)],
                                 initial=0.3 * i_m),
        i_d_ref=pj.Profile.steps([0.2, 0.45, 0.7], [-0.25 * i_m, -0.05 * i_m, -0.3 * i_m]))
    tr = pj.simulate(true, pj.FOC.from_drive(true), pj.SensoredObserver(), sc, T_s=1e-4,
                     w_m0=0.3 * float(true.w_rated), sensing=pj.Sensing(noise_std=0.02),
                     key=jax.random.PRNGKey(5))
    pj.save_recording(folder / "rec.npz", pj.RecordedData.from_trajectory(tr))
    start = pj.replace_params(true, R_s=_value(true, "R_s") * 1.4,
                              L_d=_value(true, "L_d") * 0.6, L_q=_value(true, "L_q") * 1.35,
                              psi_f=_value(true, "psi_f") * 0.7, J=_value(true, "J") * 1.4,
                              B=3e-4, u_dt=1.0)
    pj.save_motor_file(start, folder / "start.toml")
    return true


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="one warm run")
    h.size_option(ap, "--repeat", full=2, quick=1, help="warm runs")
    args = h.parse_args(ap, argv)
    repeat = args.repeat
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        true = _make(tmp)
        env = h.child_env(cache=str(tmp / "cache"))
        cmd = [sys.executable, "-m", "pmsmjax", "identify", "--motor-file",
               str(tmp / "start.toml"), "--data", str(tmp / "rec.npz"), "--voltage",
               "commanded", "--fit", *FIT, "--no-plot", "--out", str(tmp / "id")]
        rows = []
        for case in ["cold"] + ["warm"] * repeat:
            if case == "cold":
                shutil.rmtree(tmp / "cache", ignore_errors=True)
            c = h.run_child(cmd, env)
            rep = json.loads((tmp / "id" / "identify.json").read_text())
            errs = {n: abs(p["value"] / _value(true, n) - 1) for n, p in
                    rep["parameters"].items()}
            worst = max(errs, key=errs.get)
            rows.append({"case": case, "wall_s": c.wall_s, "cpu_s": c.cpu_s,
                         "solver_steps": rep["solver_steps"],
                         "max_rel_error_pct": 100 * errs[worst], "worst": worst})
    print(h.machine_line())
    h.table(rows, [("case", "case", ""), ("wall (s)", "wall_s", ".1f"),
                   ("CPU (s)", "cpu_s", ".1f"), ("LM steps (both solves)", "solver_steps", "d"),
                   ("largest parameter error",
                    lambda r: f"{r['max_rel_error_pct']:.2f} % ({r['worst']})", "")])
    h.write_report(args.json, rows, benchmark=MODULE, fit=FIT, samples=10000)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
