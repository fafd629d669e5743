"""Throughput of the zhang2022 observers: offline replay and the sensorless closed loop.

1. Observer-only replay (`pmsmjax.replay`, a `lax.scan` of `observer.step`) of recorded
   voltages and currents, for `ESOObserver`, `LESOObserver` and `AFOObserver` (design (38)/
   (25), 50 Hz), batch 1 and 1024 (`jax.vmap` over recordings that differ in their current
   noise), float64 and float32. Reported in samples per second (batch x samples / time).
2. The sensorless closed loop (`pmsmjax.simulate` with the ESO in the loop): the
   `zhang750` drive under speed control, T_s = 125 us, speed ramp 0 -> w_final over 0.1 s
   and a 1 N m load step at 0.15 s, w_final in 0.2 ... 0.8 p.u. across the batch, batch
   1, 64 and 1024, float64 and float32. Reported in drive-steps per second. Only the ISE
   integrals and one sample are kept (`save_every` = number of steps).

Timings are the best of `repeats` runs after compilation (compile time is reported
separately), on whatever the default JAX backend is. Every configuration is measured
twice, each time in a fresh subprocess: with XLA's defaults, and with
`XLA_FLAGS=--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000`.
On CPU, XLA compiles a `while` loop whose buffers are below that threshold into one
kernel ("small call"); above it, every fusion of the loop body is dispatched separately,
which costs about 1 us per step. The float64 observer loop is just above the default
threshold and the float32 one just below it, hence the flag.

Usage:

    .venv/bin/python benchmarks/bench_observers.py [--quick] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import pmsmjax as pj


HERE = Path(__file__).resolve().parent
T_S = 125e-6

FULL = dict(replay_steps={1: 40000, 1024: 4000}, loop_steps={1: 8000, 64: 2000, 1024: 800},
            repeats=5, min_time=0.5)
QUICK = dict(replay_steps={1: 8000, 1024: 800}, loop_steps={1: 2000, 64: 800, 1024: 200},
             repeats=2, min_time=0.1)


def _best_time(fn, repeats, min_time):
    """Best wall time of one call of `fn` (each sample averages >= min_time of calls)."""
    best = math.inf
    for _ in range(repeats):
        n, t0 = 0, time.perf_counter()
        while True:
            jax.block_until_ready(fn())
            n += 1
            el = time.perf_counter() - t0
            if el >= min_time:
                break
        best = min(best, el / n)
    return best


def recorded_data(n_steps: int):
    """A recorded run: sensored drive at 0.5 p.u. with 0.02 A current noise."""
    drive = pj.preset("zhang750")
    wr = float(drive.w_rated)
    sc = pj.Scenario(t_end=n_steps * T_S, w_m_ref=pj.Profile.constant(0.5 * wr),
                     tau_L=pj.Profile.constant(0.5 * float(drive.tau_rated)))
    tr = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver(), sc,
                     w_m0=0.5 * wr, sensing=pj.Sensing(noise_std=0.02),
                     key=jax.random.PRNGKey(0))
    return drive, np.asarray(tr.t), np.asarray(tr.u_ab), np.asarray(tr.i_meas_ab)


def bench_replay(cfg) -> list:
    rows = []
    n_max = max(cfg["replay_steps"].values())
    drive, t, u, i = recorded_data(n_max)
    makers = {"eso": pj.ESOObserver.from_drive, "leso": pj.LESOObserver.from_drive,
              "afo": pj.AFOObserver.from_drive}
    for name, make in makers.items():
        for dtype_name in ("float64", "float32"):
            dt = jnp.float32 if dtype_name == "float32" else jnp.float64
            obs = pj.astype(make(drive), dt)
            for B, n in cfg["replay_steps"].items():
                u_b = jnp.asarray(u[:n], dt)
                noise = 0.01 * jax.random.normal(jax.random.PRNGKey(1), (B, n, 2), dt)
                i_b = jnp.asarray(i[:n], dt)[None] + noise

                @jax.jit
                def run(i_b, u_b=u_b, obs=obs, n=n):
                    f = lambda i_one: pj.replay(obs, None, u_b, i_one, T_s=T_S)  # noqa: E731
                    th, w = jax.vmap(f)(i_b)
                    return th[:, -1], w[:, -1]

                t0 = time.perf_counter()
                out = jax.block_until_ready(run(i_b))
                t_compile = time.perf_counter() - t0
                assert out[0].dtype == dt, (name, dtype_name, out[0].dtype)
                assert bool(jnp.all(jnp.isfinite(out[1])))
                best = _best_time(lambda: run(i_b), cfg["repeats"], cfg["min_time"])
                rows.append(dict(kind="replay", observer=name, dtype=dtype_name, batch=B,
                                 steps=n, time_s=best, compile_s=t_compile,
                                 rate=B * n / best))
                print(f"replay {name:4s} {dtype_name} B={B:5d}: {B * n / best:10.3e} "
                      f"samples/s (compile {t_compile:.1f} s)", flush=True)
    return rows


def bench_loop(cfg) -> list:
    rows = []
    drive0 = pj.preset("zhang750")
    wr = float(drive0.w_rated)
    for dtype_name in ("float64", "float32"):
        dt = jnp.float32 if dtype_name == "float32" else jnp.float64
        drive = pj.astype(drive0, dt) if dt == jnp.float32 else drive0
        foc = pj.astype(pj.FOC.from_drive(drive0), dt)
        obs = pj.astype(pj.ESOObserver.from_drive(drive0), dt)
        for B, n in cfg["loop_steps"].items():
            w_final = jnp.asarray(np.linspace(0.2, 0.8, B) * wr, dt)

            def one(w, n=n, drive=drive, foc=foc, obs=obs, dt=dt):
                sc = pj.Scenario(t_end=n * T_S,
                                 w_m_ref=pj.astype(pj.Profile.ramp(0.0, 0.1, 0.0, w), dt),
                                 tau_L=pj.astype(pj.Profile.steps([0.15], [1.0]), dt))
                tr = pj.simulate(drive, foc, obs, sc, T_s=T_S, save_every=n, throw=False)
                return tr.ise_theta, tr.ise_w, tr.w_m[-1], tr.status._value

            run = jax.jit(jax.vmap(one))
            t0 = time.perf_counter()
            out = jax.block_until_ready(run(w_final))
            t_compile = time.perf_counter() - t0
            assert out[0].dtype == dt, (dtype_name, out[0].dtype)
            assert bool(jnp.all(out[3] == 0)), "a benchmark run diverged"
            best = _best_time(lambda: run(w_final), cfg["repeats"], cfg["min_time"])
            rows.append(dict(kind="sensorless_loop", observer="eso", dtype=dtype_name,
                             batch=B, steps=n, time_s=best, compile_s=t_compile,
                             rate=B * n / best))
            print(f"loop   eso  {dtype_name} B={B:5d}: {B * n / best:10.3e} drive-steps/s "
                  f"(compile {t_compile:.1f} s)", flush=True)
    return rows


def machine_info() -> dict:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return dict(cpu=cpu, cores=os.cpu_count(), platform=platform.platform(),
                python=platform.python_version(), jax=jax.__version__,
                backend=jax.default_backend(), devices=[str(d) for d in jax.devices()],
                date=datetime.datetime.now().isoformat(timespec="seconds"))


def table(rows) -> str:
    """Markdown table: one row per configuration, default and small-loop-flag rates."""
    keys = []
    by = {}
    for r in rows:
        k = (r["kind"], r["observer"], r["dtype"], r["batch"], r["steps"])
        if k not in by:
            keys.append(k)
            by[k] = {}
        by[k][r.get("xla", "default")] = r
    lines = ["| benchmark | observer | dtype | batch | steps | rate, XLA defaults | "
             "rate, small-loop flag | compile (s) |",
             "|---|---|---|---|---|---|---|---|"]
    for k in keys:
        kind, obs, dt, B, n = k
        unit = "samples/s" if kind == "replay" else "drive-steps/s"
        d, f = by[k].get("default"), by[k].get("small-loop flag")
        fmt = lambda r: "-" if r is None else f"{r['rate']:.3g}"  # noqa: E731
        comp = (d or f)["compile_s"]
        lines.append(f"| {kind} ({unit}) | {obs} | {dt} | {B} | {n} | {fmt(d)} | {fmt(f)} | "
                     f"{comp:.1f} |")
    return "\n".join(lines)


SMALL_LOOP_FLAG = ("--xla_backend_extra_options="
                   "xla_cpu_small_while_loop_byte_threshold=100000000")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="short runs (smoke test)")
    p.add_argument("--out", default=str(HERE / "out" / "bench_observers.json"),
                   help="JSON output file (default benchmarks/out/bench_observers.json)")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    cfg = QUICK if args.quick else FULL
    if args.worker:  # one measurement pass, in this process
        rows = bench_replay(cfg) + bench_loop(cfg)
        Path(args.worker).write_text(json.dumps(rows))
        return
    info = machine_info()
    print(f"{info['cpu']}, {info['cores']} cores, jax {info['jax']} ({info['backend']})")
    rows = []
    for label, flags in (("default", ""), ("small-loop flag", SMALL_LOOP_FLAG)):
        print(f"\n--- XLA {label}: XLA_FLAGS={flags!r}", flush=True)
        env = dict(os.environ)
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + flags).strip()
        env.pop("PMSMJAX_XLA_SMALL_LOOPS", None)  # the flag only via XLA_FLAGS above
        with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
            tmp = f.name
        cmd = [sys.executable, __file__, "--worker", tmp] + (["--quick"] if args.quick else [])
        subprocess.run(cmd, env=env, check=True)
        for r in json.loads(Path(tmp).read_text()):
            rows.append(dict(r, xla=label))
        os.unlink(tmp)
    text = table(rows)
    print()
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(machine=info, quick=args.quick, T_s=T_S,
                                   small_loop_flag=SMALL_LOOP_FLAG, results=rows),
                              indent=2) + "\n")
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
