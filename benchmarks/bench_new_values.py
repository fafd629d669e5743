"""A second call with new parameter values: does it run the compiled program or compile
another?

Users loop over values in Python: a mismatched model (`scale_motor`,
`replace_params`), another design (`make_observer(..., zeta1=...)`,
`with_design(...)`). Those are Python floats, and `equinox.filter_jit` bakes Python
floats into the program; `pmsmjax._sim._batching.values_as_arrays` passes them as traced
values instead. Measured here, each case in a fresh process with the persistent
compilation cache off: the first call (trace, compile, run) and the second call with
new values, for

- `simulate`: a 50 ms sensorless closed loop on zhang750 (ESO), the observer's PM flux
  scaled by 0.9, then 1.1 (`with_motor(scale_motor(...))`);
- `simulate, plant`: the same with the plant's `L_q` changed by `replace_params`;
- `replay`: 4,000 samples through the LESO with `zeta1` 0.7, then 1.3;
- `harmonic_ripple`: the ESO at 0.5 p.u. with `w2` 200, then 400 rad/s;
- `certificate`: `slowly_varying_certificate` of the fixed-ratio LESO with `zeta1` 0.8,
  then 1.5.

`--pythonpath DIR` runs the children against another checkout (a `git worktree` of an
earlier commit) for a before/after on the same machine.

Usage:

    .venv/bin/python benchmarks/bench_new_values.py [--quick] [--pythonpath DIR]
        [--out FILE.json]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_trace import add_child_options, finish, run_child  # noqa: E402


CASES = ("simulate", "simulate, plant", "replay", "harmonic_ripple", "certificate")

CHILD = """
import json, sys, time
import numpy as np
import pmsmjax as pj
pj.runtime.configure(cache=False)
import jax
case = sys.argv[1]
d = pj.preset("zhang750")
mk = pj.observers.make_observer
foc = pj.FOC.from_drive(d)
sc = pj.Scenario(t_end=0.05, w_m_ref=pj.Profile.constant(300.0))
if case == "simulate":
    def call(v):
        o = mk("eso", d).with_motor(pj.scale_motor(d.motor, {"psi_f": v}))
        return pj.simulate(d, foc, o, sc, throw=False).theta_err
    values = (0.9, 1.1)
elif case == "simulate, plant":
    def call(v):
        dd = pj.replace_params(d, L_q=float(d.motor.L_q) * v)
        return pj.simulate(dd, foc, mk("eso", d), sc, throw=False).theta_err
    values = (0.9, 1.1)
elif case == "replay":
    tr = pj.simulate(d, foc, mk("eso", d), sc)
    u, i = np.asarray(tr.u_ab), np.asarray(tr.i_meas_ab)
    def call(v):
        return pj.replay(mk("leso", d, zeta1=v, ratio=1.0), u_ab=u, i_ab=i, T_s=125e-6,
                         theta0=0.0, w0=0.0)[0]
    values = (0.7, 1.3)
elif case == "harmonic_ripple":
    op = pj.analysis.OperatingPoint(0.5 * float(d.w_rated), (0.0, 1.0))
    def call(v):
        return pj.analysis.harmonic_ripple(mk("eso", d, w2=v), d, op, (-5, 7))
    values = (200.0, 400.0)
else:
    def call(v):
        return pj.analysis.slowly_varying_certificate(
            d, mk("leso", d, zeta1=v, ratio=1.0, w2=300.0), (0.1, 1.0)).eps
    values = (0.8, 1.5)
out = {}
for k, v in enumerate(values):
    t0 = time.perf_counter()
    r = jax.block_until_ready(call(v))
    out[f"call{k + 1}_s"] = time.perf_counter() - t0
    out[f"checksum{k + 1}"] = float(np.sum(np.asarray(r)))
print(json.dumps(out))
"""


def child(case: str, quick: bool, pythonpath: str | None) -> dict:
    return run_child(CHILD, [case], quick, pythonpath)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_child_options(ap)
    ap.add_argument("--out", default="benchmarks/out/new_values.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = []
    print("| case | first call (s) | second call, new values (s) | checksums |")
    print("|---|---:|---:|---|")
    for case in CASES:
        r = dict(case=case, quick=args.quick, **child(case, args.quick, args.pythonpath))
        rows.append(r)
        print(f"| {case} | {r['call1_s']:.2f} | {r['call2_s']:.2f} | "
              f"{r['checksum1']:.10e}, {r['checksum2']:.10e} |", flush=True)
    finish(args, rows, t0)


if __name__ == "__main__":
    main()
