"""The library's bulk work on whatever backend JAX starts (a GPU where there is one): how
far a batch of closed loops, a feasibility map and a saturated-machine map scale.

Every row runs the public API on JAX's default device, compiled once, timed after
compilation (best of the repeats, results waited for):

1. **Closed loops** (`pmsmjax.simulate`, the per-observer benchmark's run,
   `benchmarks.throughput.observers.loop_row`): zhang2022's ESO in the sensorless loop of
   the 750 W drive, speed ramp and load step, `--batches` runs vmapped, float64 and
   float32. Drive-steps per second, and the share of runs that ended without divergence.
2. **Saturated machine**: the same loop on `ipm3k5_sat` (flux map in plant and controller)
   and on `morawiec_ipm3k5` (its constants), the rate ratio at each batch.
3. **Feasibility map**: `pmsmjax.analysis.feasibility_map` of the 750 W drive over an N x N
   (zeta1, ratio) grid at one speed (the closed form zhang2022 (34)-(36)), and the
   general route (`method="general"`) on a smaller grid. Points per second.
4. **Saturated map**: `pmsmjax.analysis.saturated_map` of the ESO on `ipm3k5_sat` over
   speeds x loads (the static angle error at every point). Points per second.

A row that fails prints its error and is kept in the JSON with `error`; the others run.

Usage (from the repository root):

    python -m benchmarks.throughput.accelerator                   # the full set
    python -m benchmarks.throughput.accelerator --quick           # small, on any machine
"""

from __future__ import annotations

import time
import traceback

import numpy as np

from .. import _harness as h
from . import observers


MODULE = "benchmarks.throughput.accelerator"


def _guard(rows: list, kind: str, fn, **labels) -> None:
    t0 = time.perf_counter()
    try:
        row = fn()
    except Exception as exc:  # a failed row is reported, the others still run
        traceback.print_exc()
        row = dict(error=f"{type(exc).__name__}: {exc}"[:300])
    row = dict(kind=kind, **labels, **row, wall_s=time.perf_counter() - t0)
    rows.append(row)
    shown = {k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in row.items()}
    print("  " + ", ".join(f"{k}={v}" for k, v in shown.items()), flush=True)


def loop(preset: str, batch: int, steps: int, dtype, reps) -> dict:
    import jax.numpy as jnp

    import pmsmjax as pj

    T_s = h.sampling_period(preset if preset != "ipm3k5_sat" else "morawiec_ipm3k5")
    r = observers.loop_row("eso", pj.preset(preset), T_s, batch, steps, dtype, reps)
    return dict(drive=preset, dtype=jnp.dtype(dtype).name, batch=batch, steps=steps,
                rate=r["rate"], unit="drive-steps/s", compile_s=r["compile_s"],
                finished=r["finished"])


def feasibility(n: int, method: str, dtype, reps) -> dict:
    import jax.numpy as jnp

    import pmsmjax as pj
    from pmsmjax import analysis

    drive = pj.preset("zhang750")
    if dtype == jnp.float32:
        drive = pj.astype(drive, dtype)
    z1 = np.linspace(0.0, 5.0, n)
    ratio = np.linspace(0.02, 2.0, n)
    w = np.array([0.5 * float(drive.w_rated)])
    kw = dict(i_dq=(0.0, 0.4 * float(drive.base.I_b)), method=method, dtype=dtype)
    first_s, out = h.first_call(lambda: analysis.feasibility_map(drive, w, z1, ratio, **kw))
    t = h.steady(lambda: analysis.feasibility_map(drive, w, z1, ratio, **kw), **reps)
    status = np.asarray(out.status)
    return dict(points=n * n, method=method, dtype=jnp.dtype(dtype).name,
                rate=t.rate(n * n), unit="points/s", compile_s=first_s - t.best_s,
                feasible=float(np.mean(status == 0)))


def saturated(n_speed: int, n_load: int, reps) -> dict:
    import pmsmjax as pj
    from pmsmjax import analysis
    from pmsmjax.observers import make_observer

    drive = pj.preset("ipm3k5_sat")
    obs = make_observer("eso", drive)
    speeds = np.linspace(0.1, 1.0, n_speed) * float(drive.w_rated)
    loads = np.linspace(0.0, 1.0, n_load) * float(drive.tau_rated)
    first_s, out = h.first_call(lambda: analysis.saturated_map(obs, drive, speeds, loads))
    t = h.steady(lambda: analysis.saturated_map(obs, drive, speeds, loads), **reps)
    v = np.asarray(out.verdict)
    return dict(points=n_speed * n_load, rate=t.rate(n_speed * n_load), unit="points/s",
                compile_s=first_s - t.best_s, feasible=float(np.mean(v == 0)))


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="batches 1 and 16, 1000 steps, a 64 x 64 map")
    ap.add_argument("--batches", default="1,1024,16384,131072",
                    help="closed-loop batch sizes")
    ap.add_argument("--sat-batches", default="1,1024,16384",
                    help="batch sizes of the saturated/constant pair")
    ap.add_argument("--steps", type=int, default=4000, help="steps per closed loop")
    ap.add_argument("--map", type=int, default=2048, help="N of the N x N feasibility map")
    ap.add_argument("--general-map", type=int, default=256,
                    help="N of the general route's N x N map")
    ap.add_argument("--sat-map", default="64,64", help="speeds,loads of the saturated map")
    args = ap.parse_args(argv)
    batches, sat_batches = h.ints(args.batches), h.ints(args.sat_batches)
    steps, N, NG = args.steps, args.map, args.general_map
    n_speed, n_load = h.ints(args.sat_map)
    reps = dict(repeats=3, per_sample=0.0)
    if args.quick:
        batches, sat_batches, steps, N, NG = [1, 16], [1, 16], 1000, 64, 16
        n_speed, n_load = 4, 4
    import jax.numpy as jnp

    import pmsmjax  # noqa: F401  (its XLA flags before JAX starts)

    print(h.machine_line())
    import jax

    print("devices:", jax.devices(), flush=True)
    rows: list[dict] = []
    for dt in (jnp.float32, jnp.float64):
        for b in batches:
            _guard(rows, "closed loop", lambda: loop("zhang750", b, steps, dt, reps))
    for b in sat_batches:
        for preset in ("morawiec_ipm3k5", "ipm3k5_sat"):
            _guard(rows, "saturated pair", lambda: loop(preset, b, steps, jnp.float32, reps))
    for dt in (jnp.float32, jnp.float64):
        _guard(rows, "feasibility", lambda: feasibility(N, "closed_form", dt, reps))
    _guard(rows, "feasibility", lambda: feasibility(NG, "general", jnp.float64, reps))
    _guard(rows, "saturated map", lambda: saturated(n_speed, n_load, reps))
    pairs = {(r.get("batch"), r.get("drive")): r for r in rows if r["kind"] == "saturated pair"}
    for (b, d), r in pairs.items():
        ref = pairs.get((b, "morawiec_ipm3k5"))
        if d == "ipm3k5_sat" and ref and "rate" in r and "rate" in ref:
            r["vs_constant"] = r["rate"] / ref["rate"]
    print()
    h.table(rows, [("kind", "kind", ""), ("drive", "drive", ""), ("dtype", "dtype", ""),
                   ("batch/points", lambda r: r.get("batch", r.get("points")), "d"),
                   ("rate", "rate", ".3g"), ("unit", "unit", ""),
                   ("vs constant", "vs_constant", ".2f"), ("compile s", "compile_s", ".1f"),
                   ("finished/feasible", lambda r: r.get("finished", r.get("feasible")),
                    ".3f")])
    h.write_report(args.json, rows, benchmark=MODULE,
                   config=dict(batches=batches, sat_batches=sat_batches, steps=steps,
                               map=N, general_map=NG, sat_map=[n_speed, n_load]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
