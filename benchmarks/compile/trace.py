"""Tracing, lowering and compiling the loops that users `vmap` and differentiate.

`vmap` and `jax.grad` of a `lax.scan` find which loop carries are batched (or have a
nonzero tangent) by a fixpoint that traces the loop body again for every carry it
finds late; `pmsmjax._sim._batching.batched_like` lets `simulate` and `replay` start with
every carry batched. Measured here, each in a fresh process with the persistent
compilation cache off:

- **vmapped closed loop**: `jax.jit(jax.vmap(one))` of 4 closed-loop runs (zhang750,
  speed control, 50 ms, a load and a noise key per run, `save_every=10`): trace and
  lowering (`.lower`), XLA's compile (`.compile`), the run, and a checksum of the
  angle errors (to compare trees);
- **gradient through a replay**: the first `jax.grad` of a replay's loss with respect to
  a design gain (120 samples of a rotating current on li_dtp for the LESOs, zhang750
  for the others; `tests/test_li_leso.py`'s case), which traces, linearises and
  compiles, and its value.

`--quick-compile` runs the children under quick compiles (the test suite's setting);
`--pythonpath DIR` against another checkout (e.g. a `git worktree` of an earlier commit)
for a before/after comparison on the same machine.

Usage (from the repository root):

    python -m benchmarks.compile.trace [--observers eso,c-leso] [--quick-compile]
        [--pythonpath DIR] [--quick]
"""

from __future__ import annotations

import os
import time

from .. import _harness as h


MODULE = "benchmarks.compile.trace"
OBSERVERS = ("eso", "parallel-model", "rotor-flux", "c-leso", "gi-leso", "fa-leso")
GAIN = {"eso": "w2", "parallel-model": "v1", "rotor-flux": "k_c", "c-leso": "w0",
        "gi-leso": "w0", "fa-leso": "k2"}

CHILD = """
import json, sys, time
import numpy as np
import pmsmjax as pj
pj.runtime.configure(cache=False)
import jax, jax.numpy as jnp
name, gain = sys.argv[1], sys.argv[2]
drive = pj.preset("zhang750")
foc = pj.FOC.from_drive(drive)
obs = pj.observers.make_observer(name, drive)

def one(load, key):
    sc = pj.Scenario(t_end=0.05, w_m_ref=pj.Profile.constant(100.0),
                     tau_L=pj.Profile.constant(load))
    tr = pj.simulate(drive, foc, obs, sc, sensing=pj.Sensing(noise_std=0.01), key=key,
                     save_every=10, throw=False)
    return tr.theta_err

loads = jnp.linspace(0.0, 1.0, 4)
keys = jax.random.split(jax.random.PRNGKey(0), 4)
f = jax.jit(jax.vmap(one))
t0 = time.perf_counter(); lo = f.lower(loads, keys)
t1 = time.perf_counter(); c = lo.compile()
t2 = time.perf_counter(); r = np.asarray(c(loads, keys)); t3 = time.perf_counter()
out = dict(lower_s=t1 - t0, compile_s=t2 - t1, run_s=t3 - t2, checksum=float(np.sum(r)))

dd = pj.preset("li_dtp") if "leso" in name else drive
o = pj.observers.make_observer(name, dd)
W = float(dd.w_rated)
n, T_s, w = 120, 1e-4, 0.8 * W
th = w * T_s * np.arange(n)
i_ab = 0.2 * float(dd.base.I_b) * np.stack([-np.sin(th), np.cos(th)], 1)
u_ab = 0.5 * float(dd.base.U_b) * np.stack([-np.sin(th + 0.1), np.cos(th + 0.1)], 1)

def loss(g):
    est = pj.replay_estimates(o.with_design(**{gain: g}), u_ab=u_ab, i_ab=i_ab, T_s=T_s,
                              theta0=0.3, w0=w)
    return jnp.sum(est.theta_hat)

g0 = float(o.design_parameters()[gain])
t0 = time.perf_counter(); g = float(jax.grad(loss)(g0))
out["grad_first_s"] = time.perf_counter() - t0
out["grad"] = g
print(json.dumps(out))
"""


def run_child(code: str, args: list[str], quick: bool, pythonpath: str | None) -> dict:
    """Run `code` with `args` in a fresh Python process (`XLA_FLAGS` cleared, the cache
    off, quick compiles or not; against the checkout `pythonpath` if given) and return the
    JSON object its last line prints."""
    env = h.child_env(quick_compile=quick, cache=False, clear_xla_flags=True,
                      pythonpath=pythonpath)
    return h.python_child(code, *args, env=env, timeout=900).result


def finish(args, rows: list[dict], t0: float) -> None:
    """Print the total time and load, and write the rows to `args.json`."""
    print(f"Total {time.perf_counter() - t0:.0f} s; load average at the end "
          f"{os.getloadavg()[0]:.2f}.")
    h.write_report(args.json, rows, quick_compile=args.quick_compile,
                   pythonpath=args.pythonpath)


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the ESO only")
    ap.add_argument("--observers", default=None,
                    help=f"comma-separated observers (default: {','.join(OBSERVERS)})")
    h.add_child_options(ap)
    args = ap.parse_args(argv)
    names = h.observer_names(args.observers or ("eso" if args.quick else OBSERVERS))
    for n in names:
        if n not in GAIN:
            ap.error(f"--observers: no gain to differentiate for {n!r}; choose from "
                     f"{', '.join(GAIN)}")
    t0 = time.perf_counter()
    rows = []
    for name in names:
        rows.append(dict(observer=name, quick_compile=args.quick_compile,
                         **run_child(CHILD, [name, GAIN[name]], args.quick_compile,
                                     args.pythonpath)))
        print(f"  {name}: done", flush=True)
    print(h.machine_line())
    h.table(rows, [("observer", "observer", ""),
                   ("vmapped run: trace + lower (s)", "lower_s", ".2f"),
                   ("compile (s)", "compile_s", ".2f"), ("run (s)", "run_s", ".3f"),
                   ("first grad of a replay (s)", "grad_first_s", ".2f"),
                   ("checksum", "checksum", ".12e"), ("gradient", "grad", ".12e")])
    finish(args, rows, t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
