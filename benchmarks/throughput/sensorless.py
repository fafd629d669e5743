"""Batched sensorless closed loops against the same loop in C, on all cores.

The scenario of `benchmarks.throughput.simulate` (zhang750, T_s = 125 us, RK4, a speed
ramp to 0.2-0.8 of rated speed over 0.1 s and a 1 N m load step at 0.15 s, B drives that
differ in the final speed) with an observer in the loop instead of the sensor: by default
zhang2022's ESO with its default design (`make_observer("eso", drive)`), the current
controller and the speed controller on the estimated angle and speed.

The C reference is `benchmarks/reference/closed_loop.c` built with `-DPMSM_SENSORLESS`:
the same loop around the observer step that `pmsmjax.firmware.export_c` generates (in
float64 and in float32, `gcc -O3 -march=native`, with OpenMP over the drives for the
all-cores rows). Before timing, C and pmsmjax are checked to agree (float64: final
currents, speed and ISE to 1e-9 relative after 2000 steps).

Rows, each in a fresh process: "all" (no pinning; XLA's own threads, C with OpenMP), the
batch "sharded" over one XLA host device per core (pmsmjax only, compared with the C of
"all"), and "one" (pinned to one core, single-threaded; rated by CPU time). Rates are
drive-steps per second = B x steps / time (best of the repeats; medians in the JSON).

    python -m benchmarks.throughput.sensorless            # batch 1024, both precisions
    python -m benchmarks.throughput.sensorless --quick    # batch 256, fewer repeats
"""

from __future__ import annotations

import os
import time

from .. import _harness as h
from ..reference import build_c
from . import simulate as S


MODULE = "benchmarks.throughput.sensorless"
MODES = ("all", "sharded", "one")


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE)
    ap.add_argument("--observer", default="eso",
                    help="observer of the loop (a registry name with a C emitter; default eso)")
    h.size_option(ap, "--batch", full=1024, quick=256, help="drives per run")
    ap.add_argument("--steps", type=int, default=2000, help="sampling periods per run")
    ap.add_argument("--modes", default=",".join(MODES), help="of " + ", ".join(MODES))
    args = h.parse_args(ap, argv)
    B = args.batch
    modes = [m for m in args.modes.split(",") if m]
    bad = sorted(set(modes) - set(MODES))
    if bad:
        ap.error(f"--modes: {', '.join(bad)} unknown; use {', '.join(MODES)}")
    t0 = time.perf_counter()
    print(h.machine_line())
    print(f"Building the C loop around the generated `{args.observer}` step:")
    libs = build_c(observer=(args.observer, S.make_observer(args.observer), S.T_S))
    print("Verifying C against pmsmjax:")
    verification = S.verify(libs, observer=args.observer)
    if verification["float64"]["max_rel_err_c"] > 1e-9:
        raise SystemExit(f"C and pmsmjax differ: {verification['float64']}")
    base = dict(jax_steps={str(B): args.steps}, numpy_steps={}, c_steps={str(B): args.steps},
                batches=[B], min_time=0.3 if args.quick else 1.0,
                repeats=3 if args.quick else 5, observer=args.observer)
    rows = []
    for dtype_name in ("float64", "float32"):
        c_all = (None, None)
        for mode in modes:
            print(f"{dtype_name}, {h.MODES[mode]}:")
            lib = libs[dtype_name if mode == "one" else dtype_name + "_omp"]
            res = S.run_worker("throughput", dict(base, dtype=dtype_name, c_lib=lib,
                                                  sharded=mode == "sharded"), mode)
            for r in res["rows"]:
                rate = "steps_per_cpu_s" if mode == "one" else "steps_per_s"
                c = r.get("c", {}).get(rate) or c_all[0]
                c_med = (B * args.steps / r["c"]["run_median_s"] if "c" in r
                         else c_all[1])
                if mode == "all":
                    c_all = (c, c_med)
                med = B * args.steps / r["pmsmjax"]["run_median_s"]
                rows.append(dict(dtype=dtype_name, mode=mode, batch=r["batch"],
                                 steps=args.steps, pmsmjax=r["pmsmjax"][rate],
                                 pmsmjax_median=med, c=c, c_median=c_med,
                                 ratio=r["pmsmjax"][rate] / c if c else None,
                                 ratio_median=med / c_med if c_med else None,
                                 compile_s=r["pmsmjax"]["trace_lower_s"]
                                 + r["pmsmjax"]["compile_s"],
                                 devices=r.get("devices"), rated_by=rate))
    print()
    table = h.table(rows, [
        ("dtype", "dtype", ""), ("mode", "mode", ""), ("batch", "batch", "d"),
        ("pmsmjax M/s", lambda r: r["pmsmjax"] / 1e6, ".3f"),
        ("median M/s", lambda r: r["pmsmjax_median"] / 1e6, ".3f"),
        ("C M/s", lambda r: r["c"] and r["c"] / 1e6, ".3f"),
        ("C median", lambda r: r["c_median"] and r["c_median"] / 1e6, ".3f"),
        ("pmsmjax/C", "ratio", ".2f"), ("of medians", "ratio_median", ".2f"),
        ("compile s", "compile_s", ".1f")],
        title=f"Sensorless loop ({args.observer}), drive-steps/s (best and median of the "
              f"repeats): all cores and sharded by wall time (sharded against C with "
              f"OpenMP), one core by CPU time (medians by wall time).")
    h.write_report(args.json, rows, benchmark=MODULE, observer=args.observer,
                   verification=verification, table=table, cpus=os.cpu_count(),
                   total_s=time.perf_counter() - t0)
    print(f"Total {time.perf_counter() - t0:.0f} s.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
