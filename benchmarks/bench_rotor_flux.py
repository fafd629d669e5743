"""Replay throughput of the rotor-flux observer (morawiec2023) next to the zhang2022
observers, on one recording of the `morawiec_ipm3k5` drive.

The recording: the drive under sensored speed control at 0.5 p.u. with 0.3 p.u. load,
T_s = 150 us (the paper's 6.6 kHz). Each observer (its default design for this drive)
replays it with `pmsmjax.replay` at batch 1 (8000 samples) and batch 256 (`jax.vmap` over
copies with different current noise, 800 samples), float64. Reported: samples per
second (batch x samples / best wall time after compilation) and the compile time.

Usage:

    .venv/bin/python benchmarks/bench_rotor_flux.py [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

import pmsmjax as pj


sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_observers import _best_time  # noqa: E402


NAMES = ("rotor-flux", "eso", "leso", "afo")


def _best(fn, repeats=3):
    """Best wall time of one call of `fn` over `repeats` calls."""
    return _best_time(fn, repeats, 0.0)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    pj.runtime.configure()
    drive = pj.preset("morawiec_ipm3k5")
    T_s = 1 / 6600
    w = 0.5 * drive.w_rated
    sc = pj.Scenario(t_end=8000 * T_s, w_m_ref=pj.Profile.constant(w),
                     tau_L=pj.Profile.constant(0.3 * drive.tau_rated))
    traj = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver(), sc, T_s=T_s,
                       w_m0=w)
    u, i = jnp.asarray(traj.u_ab), jnp.asarray(traj.i_meas_ab)
    key = jax.random.PRNGKey(0)
    noise = 0.02 * jax.random.normal(key, (256, 800, 2))
    rows = []
    for name in NAMES:
        obs = pj.observers.make_observer(name, drive)
        one = jax.jit(lambda u, i, o=obs: pj.replay(o, u_ab=u, i_ab=i, T_s=T_s, w0=w)[0])
        batch = jax.jit(jax.vmap(lambda n, o=obs: pj.replay(
            o, u_ab=u[:800], i_ab=i[:800] + n, T_s=T_s, w0=w)[0]))
        t0 = time.perf_counter()
        jax.block_until_ready(one(u, i))
        c1 = time.perf_counter() - t0
        t0 = time.perf_counter()
        jax.block_until_ready(batch(noise))
        c2 = time.perf_counter() - t0
        r1 = 8000 / _best(lambda: one(u, i))
        r2 = 256 * 800 / _best(lambda: batch(noise))
        rows.append(dict(observer=name, batch1_samples_per_s=r1, batch256_samples_per_s=r2,
                         compile_s=c1 + c2))
        print(f"{name:10s} batch 1: {r1 / 1e6:7.3f} M samples/s, batch 256: "
              f"{r2 / 1e6:7.3f} M samples/s, compile {c1 + c2:5.1f} s", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
