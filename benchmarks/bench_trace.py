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

`--pythonpath DIR` runs the children against another checkout (e.g. a `git worktree`
of an earlier commit) for a before/after comparison on the same machine.

Usage:

    .venv/bin/python benchmarks/bench_trace.py [--observers eso,c-leso] [--quick]
        [--pythonpath DIR] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _report import write_report  # noqa: E402
from bench_quick_compile import _env  # noqa: E402


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
    """Run `code` with `args` in a fresh Python process (XLA_FLAGS cleared, the cache off,
    quick compiles or not; against the checkout `pythonpath` if given) and return the
    JSON object its last line prints."""
    env = _env(quick)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
        env["PYTHONSAFEPATH"] = "1"  # the checkout named, not this one's current folder
    res = subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True,
                         text=True, timeout=900, cwd="/")
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(args)}: {res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def add_child_options(ap: argparse.ArgumentParser) -> None:
    """`--quick` and `--pythonpath`, the options of `run_child`."""
    ap.add_argument("--quick", action="store_true",
                    help="quick compiles (PMSMJAX_QUICK_COMPILE=1, as the test suite)")
    ap.add_argument("--pythonpath", default=None,
                    help="run the children against this checkout (default: this one)")


def finish(args, rows: list[dict], t0: float) -> None:
    """Print the total time and load, and write the rows to `args.out`."""
    print(f"Total {time.perf_counter() - t0:.0f} s; load average at the end "
          f"{os.getloadavg()[0]:.2f}.")
    write_report(args.out, rows, quick=args.quick, pythonpath=args.pythonpath,
                 load_end=os.getloadavg())


def child(name: str, quick: bool, pythonpath: str | None) -> dict:
    return run_child(CHILD, [name, GAIN[name]], quick, pythonpath)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--observers", default=",".join(OBSERVERS),
                    help="comma-separated observers (default: %(default)s)")
    add_child_options(ap)
    ap.add_argument("--out", default="benchmarks/out/trace.json")
    args = ap.parse_args()
    names = [n for n in args.observers.split(",") if n]
    for n in names:
        if n not in GAIN:
            ap.error(f"--observers: unknown observer {n!r}; choose from {', '.join(GAIN)}")
    t0 = time.perf_counter()
    rows = []
    print("| observer | vmapped run: trace + lower (s) | compile (s) | run (s) | "
          "first grad of a replay (s) | checksum | gradient |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name in names:
        r = dict(observer=name, quick=args.quick, **child(name, args.quick, args.pythonpath))
        rows.append(r)
        print(f"| {name} | {r['lower_s']:.2f} | {r['compile_s']:.2f} | {r['run_s']:.3f} | "
              f"{r['grad_first_s']:.2f} | {r['checksum']:.12e} | {r['grad']:.12e} |",
              flush=True)
    finish(args, rows, t0)


if __name__ == "__main__":
    main()
