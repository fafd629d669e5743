"""Cost of one step of the generated C observers (`pmsmjax export-c`).

For every observer of the registry that the C export supports
(`pmsmjax.firmware.supported_observers()`), on its paper's motor with its default design at
T_s = 125 us: generate the code (double and float), compile it with `gcc -std=c99 -O2`
together with a small driver that feeds a rotating current and voltage (held in memory,
no I/O; the driver's own two `sin`/`cos` per step are included) to `pmsm_obs_step` N
times at 0.5 p.u. speed, and time the loop with `clock_gettime`. Prints a table (ns per
step, and the share of a 125 us period) and writes JSON.

Usage (from the repository root):

    python -m benchmarks.throughput.firmware [--steps 200000] [--observers eso,c-leso]
"""

from __future__ import annotations

import os
import subprocess
import tempfile

from .. import _harness as h


MODULE = "benchmarks.throughput.firmware"
T_S = 125e-6

BENCH_MAIN = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <math.h>
#include <time.h>
#include "pmsm_observer.h"

int main(int argc, char **argv)
{
    long n = argc > 1 ? atol(argv[1]) : 100000, k;
    double w = atof(argv[2]), amp_i = 3.0, amp_u = atof(argv[3]);
    pmsm_obs_state s;
    pmsm_real i_ab[2], u_ab[2] = {0, 0}, th, wh;
    double acc = 0.0;
    struct timespec t0, t1;
    pmsm_obs_init(&s, (pmsm_real)0.1, (pmsm_real)w);
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (k = 0; k < n; k++) {
        double a = w * (double)PMSM_OBS_T_S * (double)k;
        i_ab[0] = (pmsm_real)(amp_i * -sin(a));
        i_ab[1] = (pmsm_real)(amp_i * cos(a));
        pmsm_obs_step(&s, i_ab, u_ab, &th, &wh);
        u_ab[0] = (pmsm_real)(amp_u * -sin(a + 0.3));
        u_ab[1] = (pmsm_real)(amp_u * cos(a + 0.3));
        acc += (double)th;
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    printf("%.6g %g\n", ((t1.tv_sec - t0.tv_sec) * 1e9 + (t1.tv_nsec - t0.tv_nsec)) / n,
           acc);
    return 0;
}
"""


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="20,000 steps instead of 200,000")
    h.size_option(ap, "--steps", full=200_000, quick=20_000, help="steps per timed loop")
    ap.add_argument("--observers", default=None,
                    help="comma-separated observers (default: every one the export supports)")
    args = h.parse_args(ap, argv)
    steps = args.steps
    import pmsmjax as pj
    from pmsmjax.firmware import export_c, supported_observers
    from pmsmjax.observers import make_observer

    names = [n for n in h.observer_names(args.observers) if n in supported_observers()]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            drive = pj.preset(h.paper_drive(name))
            obs = make_observer(name, drive)
            w = 0.5 * float(drive.w_rated)
            u = w * float(drive.three_phase_motor.psi_f)
            row = {"observer": name, "drive": drive.name}
            for prec, f32 in (("double", False), ("float", True)):
                d = os.path.join(tmp, f"{name}-{prec}")
                export_c(obs, T_S, d, float32=f32)
                with open(os.path.join(d, "bench_main.c"), "w") as f:
                    f.write(BENCH_MAIN)
                exe = os.path.join(d, "bench")
                subprocess.run(["gcc", "-std=c99", "-O2", "-o", exe,
                                os.path.join(d, "bench_main.c"),
                                os.path.join(d, "pmsm_observer.c"), "-lm"], check=True)
                out = subprocess.run([exe, str(steps), repr(w), repr(u)], check=True,
                                     capture_output=True, text=True).stdout.split()
                row[f"ns_per_step_{prec}"] = float(out[0])
            row["period_share_double"] = row["ns_per_step_double"] * 1e-9 / T_S
            rows.append(row)
            print(f"  {name}: {row['ns_per_step_double']:.0f} ns/step", flush=True)
    gcc = subprocess.run(["gcc", "--version"], capture_output=True, text=True)
    print(h.machine_line())
    h.table(rows, [("observer", "observer", ""), ("drive", "drive", ""),
                   ("double (ns/step)", "ns_per_step_double", ".0f"),
                   ("float (ns/step)", "ns_per_step_float", ".0f"),
                   ("share of a 125 us period (double)",
                    lambda r: f"{100 * r['period_share_double']:.2f} %", "")])
    h.write_report(args.json, rows, benchmark=MODULE, steps=steps, T_s=T_S,
                   gcc=gcc.stdout.splitlines()[0])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
