"""Throughput of stumper's parallel-model estimator next to zhang2022's ESO.

The same two measurements as `bench_observers.py`, on the same data and drive, with the
ESO measured in the same process for a side-by-side figure on a shared machine:

1. replay (`pmsmjax.replay`) of a recorded sensored run of `zhang750` at 0.5 p.u. with
   0.02 A current noise, batch 1 and 1024 (vmap over noisy copies), float64 and float32,
   in samples per second;
2. the sensorless closed loop (`pmsmjax.simulate`, the observer in the loop), speed ramp
   and load step as in `bench_observers.py`, batch 1 and 64, float64, in drive-steps per
   second.

Timings: best of `repeats` after compilation, XLA's defaults plus the process settings of
`pmsmjax.runtime.configure()`.

Usage:

    .venv/bin/python benchmarks/bench_parallel_model.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj


sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_observers import T_S, _best_time, recorded_data  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    pj.runtime.configure()
    jax.config.update("jax_enable_x64", True)
    replay_steps = {1: 4000, 1024: 400} if args.quick else {1: 40000, 1024: 4000}
    loop_steps = {1: 2000, 64: 400} if args.quick else {1: 8000, 64: 2000}
    reps = dict(repeats=2 if args.quick else 5, min_time=0.1 if args.quick else 0.5)
    drive, t, u, i = recorded_data(max(replay_steps.values()))
    makers = {"parallel-model": pj.ParallelModelObserver.from_drive,
              "eso": pj.ESOObserver.from_drive}
    for name, make in makers.items():
        for dt in (jnp.float64, jnp.float32):
            obs = pj.astype(make(drive), dt)
            for B, n in replay_steps.items():
                u_b = jnp.asarray(u[:n], dt)
                i_b = jnp.asarray(i[:n], dt)[None] + 0.01 * jax.random.normal(
                    jax.random.PRNGKey(1), (B, n, 2), dt)

                @jax.jit
                def run(i_b, u_b=u_b, obs=obs):
                    f = lambda i1: pj.replay(obs, None, u_b, i1, T_s=T_S)  # noqa: E731
                    th, w = jax.vmap(f)(i_b)
                    return th[:, -1], w[:, -1]

                t0 = time.perf_counter()
                out = jax.block_until_ready(run(i_b))
                tc = time.perf_counter() - t0
                assert out[0].dtype == dt and bool(jnp.all(jnp.isfinite(out[1])))
                best = _best_time(lambda: run(i_b), **reps)
                print(f"replay {name:14s} {jnp.dtype(dt).name} B={B:5d}: "
                      f"{B * n / best:10.3e} samples/s (compile {tc:.1f} s)", flush=True)
    wr = float(drive.w_rated)
    foc = pj.FOC.from_drive(drive)
    for name, make in makers.items():
        obs = make(drive)
        for B, n in loop_steps.items():
            w_final = jnp.asarray(np.linspace(0.2, 0.8, B) * wr)

            def one(w, n=n, obs=obs):
                sc = pj.Scenario(t_end=n * T_S, w_m_ref=pj.Profile.ramp(0.0, 0.1, 0.0, w),
                                 tau_L=pj.Profile.steps([0.15], [1.0]))
                tr = pj.simulate(drive, foc, obs, sc, T_s=T_S, save_every=n, throw=False)
                return tr.ise_theta, tr.status._value

            run = jax.jit(jax.vmap(one))
            t0 = time.perf_counter()
            jax.block_until_ready(run(w_final))
            tc = time.perf_counter() - t0
            best = _best_time(lambda: run(w_final), **reps)
            print(f"loop   {name:14s} float64 B={B:5d}: {B * n / best:10.3e} drive-steps/s "
                  f"(compile {tc:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
