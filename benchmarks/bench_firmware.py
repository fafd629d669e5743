"""Cost of one step of the generated C observers (`pmsmjax export-c`).

For every registered observer: generate the code (double and float), compile it with
`gcc -std=c99 -O2` together with a small driver that feeds a rotating current and
voltage (held in memory, no I/O) to `pmsm_obs_step` N times, and time the loop with
`clock_gettime`. Prints a table (ns per step, and the share of a 125 us period) and
writes JSON.

    .venv/bin/python benchmarks/bench_firmware.py [--steps 200000] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile

import pmsmjax as pj
from pmsmjax.firmware import SUPPORTED, export_c
from pmsmjax.observers import make_observer


T_S = 125e-6
DRIVES = {"rotor-flux": "morawiec_ipm3k5", "parallel-model": "stumper_mt5",
          "c-leso": "li_dtp", "gi-leso": "li_dtp", "fa-leso": "li_dtp"}

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=200000)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in SUPPORTED:
            drive = pj.preset(DRIVES.get(name, "zhang750"))
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
                out = subprocess.run([exe, str(args.steps), repr(w), repr(u)], check=True,
                                     capture_output=True, text=True).stdout.split()
                row[f"ns_per_step_{prec}"] = float(out[0])
            rows.append(row)
    print(f"{'observer':16s} {'double ns/step':>15s} {'float ns/step':>14s} "
          f"{'% of 125 us (double)':>21s}")
    for r in rows:
        print(f"{r['observer']:16s} {r['ns_per_step_double']:15.0f} "
              f"{r['ns_per_step_float']:14.0f} "
              f"{100 * r['ns_per_step_double'] * 1e-9 / T_S:21.2f}")
    result = {"machine": platform.machine(), "cpus": os.cpu_count(),
              "gcc": subprocess.run(["gcc", "--version"], capture_output=True,
                                    text=True).stdout.splitlines()[0],
              "steps": args.steps, "T_s": T_S, "rows": rows}
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
