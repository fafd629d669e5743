"""Closed-loop throughput on a saturated machine against the same run with constant
inductances.

The same sensorless run on `morawiec_ipm3k5` (constant L_d, L_q, psi_f) and on
`ipm3k5_sat` (the same machine with a 26 x 41 flux map in the plant and in the
controller: references from the map's torque, gains from its incremental inductance,
decoupling from its flux): zhang2022's ESO in the loop (its constant small-current
model), `FOC.from_drive(drive)` (i_d = 0), speed reference ramping from 0 to w_final over
0.1 s (w_final 0.2 ... 0.8 p.u. across the batch), a load step of 1/3 of the rated
torque at 0.15 s; only the integrals and one sample kept (`save_every` = steps).
Reported: drive-steps per second (batch x steps / best time after compilation; also
per second of process CPU time, which a shared machine disturbs less), the saturated
rate over the constant one (the target: at least 0.5), the compile
time, and whether every run ended finite without divergence (float32 included).

Usage (from the repository root):

    python -m benchmarks.throughput.saturation                    # B = 1, 64; f64, f32
    python -m benchmarks.throughput.saturation --quick
"""

from __future__ import annotations

from .. import _harness as h
from . import observers


MODULE = "benchmarks.throughput.saturation"
DRIVES = ("morawiec_ipm3k5", "ipm3k5_sat")


def loop_row(preset, batch, steps, dtype, reps) -> dict:
    """The closed-loop row of the per-observer benchmark (the same runs), for the ESO on
    `preset` at the morawiec drive's sampling period."""
    import jax.numpy as jnp

    import pmsmjax as pj

    T_s = h.sampling_period("morawiec_ipm3k5")
    row = observers.loop_row("eso", pj.preset(preset), T_s, batch, steps, dtype, reps)
    return dict(drive=preset, dtype=jnp.dtype(dtype).name, batch=batch, steps=steps,
                T_s=T_s, **{k: row[k] for k in ("rate", "cpu_rate", "time_s", "compile_s",
                                                "finished")})


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="batch 1 and 8, 2000 steps, float64 and "
                  "float32, 3 repeats")
    ap.add_argument("--batches", default="1,64", help="batch sizes")
    ap.add_argument("--steps", type=int, default=8000,
                    help="steps at batch 1 (a quarter at larger batches)")
    ap.add_argument("--dtypes", default="float64,float32", help="float64 and/or float32")
    args = ap.parse_args(argv)
    batches = h.ints(args.batches)
    steps, reps = args.steps, dict(repeats=5, per_sample=0.2)
    if args.quick:
        batches, steps, reps = [1, 8], 2000, dict(repeats=3, per_sample=0.05)
    import jax.numpy as jnp

    import pmsmjax  # noqa: F401  (its XLA flags before JAX starts)

    print(h.machine_line())
    rows = []
    for dtype_name in args.dtypes.split(","):
        for batch in batches:
            n = steps if batch == 1 else max(200, steps // 4)
            for preset in DRIVES:
                r = loop_row(preset, batch, n, getattr(jnp, dtype_name), reps)
                rows.append(r)
                print(f"  {preset:16s} {dtype_name} B={batch:4d}: {r['rate']:10.3e} "
                      f"drive-steps/s (compile {r['compile_s']:.1f} s)", flush=True)
    ref = {(r["dtype"], r["batch"]): r for r in rows if r["drive"] == DRIVES[0]}
    for r in rows:
        r["vs_constant"] = r["rate"] / ref[(r["dtype"], r["batch"])]["rate"]
        r["cpu_vs_constant"] = r["cpu_rate"] / ref[(r["dtype"], r["batch"])]["cpu_rate"]
    print()
    h.table(rows, [("drive", "drive", ""), ("dtype", "dtype", ""), ("batch", "batch", "d"),
                   ("steps", "steps", "d"), ("steps/s", "rate", ".3g"),
                   ("vs constant", "vs_constant", ".2f"),
                   ("steps/CPU s", "cpu_rate", ".3g"), ("vs constant (CPU)", "cpu_vs_constant",
                                                        ".2f"),
                   ("compile s", "compile_s", ".1f"),
                   ("finished", "finished", ".2f")])
    h.write_report(args.json, rows, benchmark=MODULE,
                   config=dict(batches=batches, steps=steps, dtypes=args.dtypes))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
