"""Analysis entry points called outside `jit`, as a notebook or a script calls them: the
first call (compilation included) and later calls with new values.

Entry points whose body is a `lax` loop or a long chain of small operations cost a compile
per call, or one per operation, when they are not compiled as one program. Measured here,
each in a fresh process (the users' flags unless `--quick-compile`, no compilation
cache):

- `equilibria`: the parallel-model estimator's closed form (`fast_equilibria`), stumper_mt5
  with a mismatched model; zhang2022's ESO with fal feedback (the reduction
  `eso_equilibria`, which `method="auto"` takes for fal), zhang750 made salient
  (L_q = 4 L_d) with a model 20 % off in R_s, L_q and psi_f;
- `designed_error`: the C-LESO's designed equilibrium (a fixed-point loop), li_dtp;
- `floquet`: the rotor-flux observer's Floquet multipliers (a loop over one period),
  morawiec_ipm3k5;
- `discrete_error_run`: 200 steps of the rotor-flux observer's discrete error map;
- `slowly_varying_certificate`: zhang2022 §V's certificate of the LESO with the (38)
  schedule over 0.1-1 p.u., zhang750; the later calls with other w2 (its default
  resolution: 101 speeds, about 200,000 small matrix exponentials).

Each row: the first call (s), the median of five later calls at other speeds (s), and the
number of XLA compilations in each (JAX's compile events).

Usage (from the repository root; an older tree: `--pythonpath <its checkout>`):

    python -m benchmarks.compile.analysis_calls [--quick-compile] [--case CASE] [--quick]
"""

from __future__ import annotations

from .. import _harness as h


MODULE = "benchmarks.compile.analysis_calls"

CASES = ("equilibria/parallel-model", "equilibria/eso", "designed_error/c-leso",
         "floquet/rotor-flux", "discrete_error_run/rotor-flux",
         "slowly_varying_certificate/leso")

CHILD = r"""
import json, math, statistics, sys, time
import pmsmjax as pj
pj.runtime.configure(cache=False)
import jax, jax.numpy as jnp
import jax.monitoring as mon
from pmsmjax import analysis
from pmsmjax.observers import OperatingPoint, make_observer, paper_drive

n_comp = [0]
mon.register_event_duration_secs_listener(
    lambda e, d, **k: n_comp.__setitem__(0, n_comp[0] + 1)
    if e == "/jax/core/compile/backend_compile_duration" else None)
case = sys.argv[1]
fn_name, obs_name = case.split("/")
preset = paper_drive(obs_name)[0]
drive = pj.preset(preset)
if obs_name == "eso":
    drive = pj.replace_params(drive, L_d=1.5e-3, L_q=6.0e-3)
plant = drive.three_phase_motor
obs = make_observer(obs_name, drive)
if obs_name == "parallel-model":
    obs = obs.with_motor(pj.PMSMParams(R_s=1.5, L_d=4.0e-3, L_q=9.0e-3, psi_f=0.25,
                                       n_p=3.0))
if obs_name == "eso":
    obs = obs.with_motor(pj.scale_motor(plant, {"R_s": 1.2, "L_q": 0.8, "psi_f": 0.8}))
i0 = jnp.array([0.3, -3.0]) if obs_name == "parallel-model" else jnp.array([0.0, 2.0])
w_r = float(drive.w_rated)


def call(s):
    w = s * w_r
    if fn_name == "equilibria":
        return analysis.equilibria(obs, plant, w, i0).theta
    if fn_name == "designed_error":
        return obs.designed_error(OperatingPoint(w, i0), plant)
    if fn_name == "floquet":
        return analysis.floquet(obs, plant, w, i0).max_real
    if fn_name == "slowly_varying_certificate":
        w2 = jnp.asarray(2 * math.pi * 50 * (1 + abs(s)))  # a value: one program
        design = make_observer("leso", drive, w2=w2)
        return analysis.slowly_varying_certificate(drive, design, (0.1, 1.0)).eps
    return analysis.discrete_error_run(obs, plant, w, i0, 1 / 6600, jnp.zeros(4), 200)


t0 = time.perf_counter()
jax.block_until_ready(call(0.3))
first, c_first = time.perf_counter() - t0, n_comp[0]
times = []
for s in (-0.4, 0.5, 0.6, -0.7, 0.8):
    t0 = time.perf_counter()
    jax.block_until_ready(call(s))
    times.append(time.perf_counter() - t0)
print(json.dumps(dict(case=case, first_s=first, first_compiles=c_first,
                      later_s=statistics.median(times),
                      later_compiles=(n_comp[0] - c_first) / len(times))))
"""


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the C-LESO's designed equilibrium only")
    ap.add_argument("--case", action="append", choices=CASES,
                    help="only this case (repeatable; default: all)")
    h.add_child_options(ap)
    args = ap.parse_args(argv)
    env = h.child_env(quick_compile=args.quick_compile, cache=False,
                      pythonpath=args.pythonpath)
    cases = args.case or (["designed_error/c-leso"] if args.quick else CASES)
    rows = []
    for case in cases:
        rows.append(h.python_child(CHILD, case, env=env).result)
        print(f"  {case}: done", flush=True)
    print(h.machine_line())
    h.table(rows, [("entry point / observer", "case", ""), ("first call (s)", "first_s", ".2f"),
                   ("its compiles", "first_compiles", "d"),
                   ("later call (s)", "later_s", ".4f"),
                   ("compiles per later call", "later_compiles", ".1f")])
    h.write_report(args.json, rows, benchmark=MODULE, quick_compile=args.quick_compile,
                   pythonpath=args.pythonpath)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
