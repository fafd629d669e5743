"""Throughput of every observer of the registry: offline replay and the sensorless closed
loop, each on its paper's drive, side by side with zhang2022's ESO on the same drive.

1. **Replay** (`pmsmjax.replay_estimates`, a `lax.scan` of `observer.step`) of a recording
   of the drive (its paper's motor and sampling period, `pmsmjax.observers.paper_drive`; `--drive`
   puts every observer on one): sensored current control at `--speed` p.u. (default 1.0,
   imposed), i_d = 0, i_q = 0.5 p.u., 0.02 A current noise; each observer with its default
   design for the drive (`make_observer`), started at the true angle and speed. Batch B
   is `jax.vmap` over copies with another 0.02 A of noise each. Reported: samples per
   second (B x samples / best time after compilation), the ratio to the ESO's rate in
   the same run, and the compile time.
2. **Closed loop** (`pmsmjax.simulate` with the observer in the loop, `--loop-batches`):
   speed control on the estimate, the reference ramping from 0 to w_final over 0.1 s
   (w_final 0.2 ... 0.8 p.u. across the batch), a load step of 1/3 of the rated torque at
   0.15 s; only the integrals and one sample kept (`save_every` = steps). The runs are
   timed, not checked for convergence (a back-EMF observer starting from standstill may
   lose them): the share of runs that ended without divergence is in the JSON. Reported
   in drive-steps per second.

The observers come from the registry in registration order (`--observers` picks some);
the ESO is measured on every drive that is used. Timings run in this process with the
flags `import pmsmjax` sets; `--xla-defaults` adds a pass in a fresh process with XLA's
defaults (`PMSMJAX_FAST_LOOPS=0`), the setting before pmsmjax set its flags.

Usage (from the repository root):

    python -m benchmarks.throughput.observers                     # every observer
    python -m benchmarks.throughput.observers --observers c-leso,gi-leso,fa-leso
    python -m benchmarks.throughput.observers --drive zhang750 --batches 1,1024 \\
        --dtypes float64,float32 --loop-batches 1,64,1024       # zhang2022's observers
    python -m benchmarks.throughput.observers --quick
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from .. import _harness as h


MODULE = "benchmarks.throughput.observers"
REFERENCE = "eso"
LOAD_PU = 1 / 3  # load step of the closed loop (fraction of the rated torque)


def recording(drive, T_s: float, steps: int, batch: int, speed_pu: float, dtype):
    """(u_ab [steps, 2], i_ab [batch, steps, 2], w) of a sensored run of `drive` at an
    imposed `speed_pu`, i_q = 0.5 p.u., with current noise, `batch` noisy copies."""
    import jax
    import jax.numpy as jnp

    import pmsmjax as pj

    w = speed_pu * float(drive.w_rated)
    sc = pj.Scenario(t_end=steps * T_s, w_m_imposed=pj.Profile.constant(w),
                     i_d_ref=pj.Profile.constant(0.0),
                     i_q_ref=pj.Profile.constant(0.5 * float(drive.base.I_b)))
    tr = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver(), sc, T_s=T_s,
                     w_m0=w, sensing=pj.Sensing(noise_std=0.02), key=jax.random.PRNGKey(0))
    noise = 0.02 * jax.random.normal(jax.random.PRNGKey(1), (batch,) + tr.i_meas_ab.shape)
    return (jnp.asarray(tr.u_ab, dtype), jnp.asarray(tr.i_meas_ab[None] + noise, dtype),
            w)


def _cast(tree, dtype):
    """`tree` in `dtype` (`pmsmjax.astype`); float64 as made (pmsmjax's default)."""
    import jax.numpy as jnp

    import pmsmjax as pj

    return tree if jnp.dtype(dtype) == jnp.float64 else pj.astype(tree, dtype)


def _try(fn, *args) -> dict:
    """`fn(*args)`, or the row of a measurement that failed (its error named)."""
    try:
        return fn(*args)
    except Exception as e:  # one observer's failure does not stop the others
        print(f"  FAILED: {type(e).__name__}: {str(e).splitlines()[0][:200]}", flush=True)
        return dict(rate=None, compile_s=None, error=f"{type(e).__name__}: "
                    f"{str(e).splitlines()[0][:500]}")


def replay_row(name, drive, T_s, data, dtype, reps) -> dict:
    """Compile and time the vmapped replay of `name` on `data` (`recording`)."""
    import jax
    import jax.numpy as jnp

    import pmsmjax as pj
    from pmsmjax.observers import make_observer

    u_ab, i_ab, w = data
    batch, steps = i_ab.shape[:2]
    obs = _cast(make_observer(name, drive), dtype)

    @jax.jit
    def run(i_ab):
        def one(i):
            return pj.replay_estimates(obs, u_ab=u_ab, i_ab=i, T_s=T_s, theta0=0.0,
                                       w0=w).theta_hat
        return jax.vmap(one)(i_ab)

    compile_s, out = h.first_call(lambda: run(i_ab))
    assert out.dtype == jnp.dtype(dtype), (name, out.dtype)
    t = h.steady(lambda: run(i_ab), **reps)
    return dict(kind="replay", unit="samples/s", observer=name, batch=batch, steps=steps,
                rate=t.rate(batch * steps), time_s=t.best_s, compile_s=compile_s,
                finite=float(jnp.mean(jnp.isfinite(out[:, -1]))))


def loop_row(name, drive, T_s, batch, steps, dtype, reps) -> dict:
    """Compile and time `batch` vmapped sensorless closed loops of `steps` steps (the
    runs count as finished when none diverged and their results are finite)."""
    import jax
    import jax.numpy as jnp

    import pmsmjax as pj
    from pmsmjax.observers import make_observer

    foc = _cast(pj.FOC.from_drive(drive), dtype)
    obs = _cast(make_observer(name, drive), dtype)
    plant = _cast(drive, dtype)
    w_final = jnp.asarray(np.linspace(0.2, 0.8, batch) * float(drive.w_rated), dtype)
    load = LOAD_PU * float(drive.tau_rated)

    def one(w):
        sc = pj.Scenario(t_end=steps * T_s,
                         w_m_ref=pj.astype(pj.Profile.ramp(0.0, 0.1, 0.0, w), dtype),
                         tau_L=pj.astype(pj.Profile.steps([0.15], [load]), dtype))
        tr = pj.simulate(plant, foc, obs, sc, T_s=T_s, save_every=steps, throw=False)
        return tr.ise_theta, tr.status._value, tr.w_m[-1]

    run = jax.jit(jax.vmap(one))
    compile_s, out = h.first_call(lambda: run(w_final))
    assert out[0].dtype == jnp.dtype(dtype), (name, out[0].dtype)
    t = h.steady(lambda: run(w_final), **reps)
    ok = (np.asarray(out[1]) == 0) & np.isfinite(np.asarray(out[0])) & np.isfinite(
        np.asarray(out[2]))
    return dict(kind="closed loop", unit="drive-steps/s", observer=name, batch=batch,
                steps=steps, rate=t.rate(batch * steps), cpu_rate=t.cpu_rate(batch * steps),
                time_s=t.best_s, compile_s=compile_s, finished=float(np.mean(ok)))


def measure(cfg: dict) -> list[dict]:
    """Every row of one pass (this process's XLA settings)."""
    import jax.numpy as jnp

    import pmsmjax as pj

    reps = dict(repeats=cfg["repeats"], per_sample=cfg["per_sample"])
    groups: dict[str, list[str]] = {}
    for name in cfg["observers"]:
        groups.setdefault(cfg["drive"] or h.paper_drive(name), []).append(name)
    rows = []
    for preset, names in groups.items():
        names = [REFERENCE] + [n for n in names if n != REFERENCE]
        drive, T_s = pj.preset(preset), h.sampling_period(preset)
        for dtype_name in cfg["dtypes"]:
            dt = getattr(jnp, dtype_name)
            for batch in cfg["batches"]:
                data = recording(drive, T_s, cfg["steps"], batch, cfg["speed"], dt)
                for name in names:
                    r = _try(replay_row, name, drive, T_s, data, dt, reps)
                    rows.append(dict(dict(kind="replay", unit="samples/s", observer=name,
                                          batch=batch, steps=cfg["steps"]), **r,
                                     drive=preset, T_s=T_s, dtype=dtype_name))
                    _progress(rows[-1])
            for batch in cfg["loop_batches"]:
                steps = cfg["loop_steps"] if batch == 1 else max(200, cfg["loop_steps"] // 4)
                for name in names:
                    r = _try(loop_row, name, drive, T_s, batch, steps, dt, reps)
                    rows.append(dict(dict(kind="closed loop", unit="drive-steps/s",
                                          observer=name, batch=batch, steps=steps), **r,
                                     drive=preset, T_s=T_s, dtype=dtype_name))
                    _progress(rows[-1])
    return rows


def _progress(r: dict) -> None:
    if r["rate"] is None:
        return
    print(f"  {r['kind']:11s} {r['observer']:15s} {r['drive']:16s} {r['dtype']} "
          f"B={r['batch']:5d}: {r['rate']:10.3e} {r['unit']} (compile {r['compile_s']:.1f} s)",
          flush=True)


def _with_ratios(rows: list[dict]) -> list[dict]:
    ref = {(r["kind"], r["drive"], r["dtype"], r["batch"], r.get("xla")): r["rate"]
           for r in rows if r["observer"] == REFERENCE}
    for r in rows:
        base = ref.get((r["kind"], r["drive"], r["dtype"], r["batch"], r.get("xla")))
        r["vs_eso"] = r["rate"] / base if r["rate"] and base else None
    return rows


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="batch 1, no closed loop, "
                  "fewer repeats: every observer in under a minute")
    ap.add_argument("--observers", default=None,
                    help="comma-separated observers of the registry (default: all)")
    ap.add_argument("--drive", default=None,
                    help="one motor preset for every observer (default: each one's paper's)")
    ap.add_argument("--speed", type=float, default=1.0, help="replay speed, p.u.")
    ap.add_argument("--batches", default="1,256", help="replay batch sizes")
    ap.add_argument("--steps", type=int, default=4000, help="replay samples")
    ap.add_argument("--dtypes", default="float64", help="float64 and/or float32")
    ap.add_argument("--loop-batches", default="1,64",
                    help="closed-loop batch sizes ('' for none)")
    ap.add_argument("--loop-steps", type=int, default=8000,
                    help="closed-loop steps at batch 1 (a quarter at larger batches)")
    ap.add_argument("--xla-defaults", action="store_true",
                    help="also measure in a fresh process with XLA's defaults "
                         "(PMSMJAX_FAST_LOOPS=0)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        h.worker_result(measure(json.loads(args.worker)))
        return 0
    cfg = dict(observers=h.observer_names(args.observers), drive=args.drive,
               speed=args.speed, batches=h.ints(args.batches), steps=args.steps,
               dtypes=args.dtypes.split(","), loop_batches=h.ints(args.loop_batches),
               loop_steps=args.loop_steps, repeats=5, per_sample=0.2)
    if args.quick:
        cfg.update(batches=[1], loop_batches=[], repeats=3, per_sample=0.05)
    import pmsmjax  # noqa: F401  (its XLA flags before JAX starts)

    print(h.machine_line())
    rows = [dict(r, xla="pmsmjax") for r in measure(cfg)]
    if args.xla_defaults:
        print("XLA's defaults (PMSMJAX_FAST_LOOPS=0), in a fresh process:", flush=True)
        env = h.child_env(clear_xla_flags=True, PMSMJAX_FAST_LOOPS="0")
        child = h.module_child(MODULE, "--worker", json.dumps(cfg), env=env)
        rows += [dict(r, xla="XLA defaults") for r in child.result]
    _with_ratios(rows)
    cols = [("kind", "kind", ""), ("observer", "observer", ""), ("drive", "drive", ""),
            ("dtype", "dtype", ""), ("batch", "batch", "d"), ("steps", "steps", "d"),
            ("rate /s", lambda r: "failed" if r.get("error") else r["rate"], ".3g"),
            ("vs ESO", "vs_eso", ".2f"),
            ("compile s", "compile_s", ".1f")]
    if args.xla_defaults:
        cols.insert(5, ("XLA", "xla", ""))
    print()
    h.table(rows, cols)
    h.write_report(args.json, rows, benchmark=MODULE, config=cfg)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
