"""Throughput of li-fa-leso's back-EMF observers next to zhang2022's ESO.

Observer-only replay (`pmsmjax.replay_estimates`, a `lax.scan` of `observer.step`) of one
recorded run of the `li_dtp` drive (sensored, 600 rpm, half load, 0.02 A current noise),
batch 1 and 256 (`jax.vmap` over recordings with different noise), float64, for `eso`,
`c-leso`, `gi-leso`, `fa-leso`, each with its default design for `li_dtp`. Reported in
samples per second (batch x samples / best wall time after compilation) and the compile
time. The li-fa-leso observers integrate their internal dynamics exactly every step: the
exponential and two phi functions of their own matrix in complex form, shifted by the
speed estimate (2 x 2, pairs of complex numbers, for the C-LESO and FA-LESO; a 4 x 4
complex matrix for the GI-LESO), which is what they pay for.

Usage:

    .venv/bin/python benchmarks/bench_leso.py [--steps N] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

import pmsmjax as pj


sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_observers import _best_time  # noqa: E402

from pmsmjax.observers import make_observer  # noqa: E402


T_S = 1e-4
NAMES = ("eso", "c-leso", "gi-leso", "fa-leso")


def _record(n_steps: int, batch: int):
    drive = pj.preset("li_dtp")
    w = float(drive.w_rated)
    sc = pj.Scenario(t_end=n_steps * T_S, w_m_imposed=pj.Profile.constant(w),
                     i_d_ref=pj.Profile.constant(0.0),
                     i_q_ref=pj.Profile.constant(0.5 * float(drive.base.I_b)))
    tr = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver(), sc, T_s=T_S,
                     w_m0=w, sensing=pj.Sensing(noise_std=0.02), key=jax.random.PRNGKey(0))
    noise = 0.02 * jax.random.normal(jax.random.PRNGKey(1), (batch,) + tr.i_meas_ab.shape)
    return drive, tr.u_ab, tr.i_meas_ab[None] + noise


def _best(fn, repeats=3):
    """Best wall time of one call of `fn` over `repeats` calls."""
    return _best_time(fn, repeats, 0.0)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=4000)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    pj.runtime.configure()
    rows = []
    for batch in (1, 256):
        drive, u_ab, i_ab = _record(args.steps, batch)
        w = float(drive.w_rated)
        for name in NAMES:
            obs = make_observer(name, drive)

            @jax.jit
            def run(i_ab, obs=obs):
                f = lambda i: pj.replay_estimates(obs, u_ab=u_ab, i_ab=i, T_s=T_S,  # noqa: E731
                                                  theta0=0.0, w0=w).theta_hat
                return jax.vmap(f)(i_ab)

            t0 = time.perf_counter()
            jax.block_until_ready(run(i_ab))
            compile_s = time.perf_counter() - t0
            t = _best(lambda: run(i_ab))
            rows.append({"observer": name, "batch": batch, "samples_per_s":
                         batch * args.steps / t, "compile_s": compile_s})
            print(f"{name:>8} batch {batch:4d}: {batch * args.steps / t:12.4g} samples/s "
                  f"(compile {compile_s:.1f} s)", flush=True)
    out = {"platform": platform.platform(), "backend": jax.default_backend(),
           "steps": args.steps, "T_s": T_S, "dtype": str(jnp.zeros(()).dtype), "rows": rows}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
