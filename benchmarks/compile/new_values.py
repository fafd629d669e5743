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
- `simulate_plant`: the same with the plant's `L_q` changed by `replace_params`;
- `replay`: 4,000 samples through the LESO with `zeta1` 0.7, then 1.3;
- `harmonic_ripple`: the ESO at 0.5 p.u. with `w2` 200, then 400 rad/s;
- `certificate`: `slowly_varying_certificate` of the fixed-ratio LESO with `zeta1` 0.8,
  then 1.5.

`--quick-compile` runs the children under quick compiles (the test suite's setting);
`--pythonpath DIR` against another checkout (a `git worktree` of an earlier commit) for
a before/after on the same machine.

Usage (from the repository root):

    python -m benchmarks.compile.new_values [--quick-compile] [--pythonpath DIR]
        [--cases simulate,replay] [--quick]
"""

from __future__ import annotations

import time

from .. import _harness as h
from .trace import finish, run_child


MODULE = "benchmarks.compile.new_values"


CASES = ("simulate", "simulate_plant", "replay", "harmonic_ripple", "certificate")

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
elif case == "simulate_plant":
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


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the `simulate` and `replay` cases only")
    ap.add_argument("--cases", default=None,
                    help=f"comma-separated cases (default: all: {','.join(CASES)})")
    h.add_child_options(ap)
    args = ap.parse_args(argv)
    cases = (args.cases.split(",") if args.cases else
             ["simulate", "replay"] if args.quick else list(CASES))
    for c in cases:
        if c not in CASES:
            ap.error(f"--cases: unknown case {c!r}; choose from {', '.join(CASES)}")
    t0 = time.perf_counter()
    rows = []
    for case in cases:
        rows.append(dict(case=case, quick_compile=args.quick_compile,
                         **run_child(CHILD, [case], args.quick_compile, args.pythonpath)))
        print(f"  {case}: done", flush=True)
    print(h.machine_line())
    h.table(rows, [("case", "case", ""), ("first call (s)", "call1_s", ".2f"),
                   ("second call, new values (s)", "call2_s", ".2f"),
                   ("checksums", lambda r: f"{r['checksum1']:.10e}, {r['checksum2']:.10e}",
                    "")])
    finish(args, rows, t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
