"""`pmsmjax feasibility` at scale: time, designs per second, and how the work splits over
1 vs 2 devices in one process and 1 vs 2 processes (jax.distributed) on one machine.

Two maps, each run as the command line runs it (fresh processes, `PMSMJAX_CACHE=0`, so
the compile time is the cold one and is reported apart):

- `closed form`: the matched LESO over (zeta1, w1/|w0|) (zhang2022 Fig. 1's axes) at 4
  speeds, 4 x 501 x 501 = 1,004,004 designs, the closed form zhang2022 (34)-(36);
- `general`: the same observer with its model's L_d at 0.9 of the plant's (mismatch: the
  ESO-specific general route, bracketing + bisection + Jacobian per design), 4 x 151 x
  151 = 91,204 designs.

Configurations: `1 proc x 1 dev` (the default), `1 proc x 2 dev`
(`XLA_FLAGS=--xla_force_host_platform_device_count=2`), `2 proc x 1 dev` (two processes,
`--coordinator localhost:PORT --num-processes 2 --process-id 0/1`, `JAX_PLATFORMS=cpu`).
Reported per run: the wall time of the whole command (start-up, compile, sweep, writing),
the map's time as the command prints it, the compile time (`sweep.json`), and designs per
second over the map time and over the chunks alone (sum of chunk wall times, compile
excluded).

Usage (from the repository root):

    python -m benchmarks.throughput.feasibility_sweep [--quick] [--maps general]
        [--configs "1 proc x 1 dev,2 proc x 1 dev"]

`--quick`: the closed-form map on a 4 x 201 x 201 grid, one and two devices in one
process.
"""

from __future__ import annotations

import json
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .. import _harness as h


MODULE = "benchmarks.throughput.feasibility_sweep"
MAPS = {
    "closed form": ["--set", "L_d=1e-3", "--set", "L_q=4.9e-3", "--i-q", "2",
                    "--zeta1", "0:5:501", "--ratio", "0:2:501",
                    "--speeds", "0.2", "0.5", "1", "-0.5", "--chunk-size", "65536"],
    "general": ["--i-q", "1", "--mismatch", "L_d=0.9", "--zeta1", "0.1:3:151",
                "--ratio", "0.1:2:151", "--speeds", "0.2", "0.5", "1", "-0.5",
                "--chunk-size", "4096"],
}
QUICK = {"closed form": ["--zeta1", "0:5:201", "--ratio", "0:2:201"],
         "general": ["--zeta1", "0.1:3:61", "--ratio", "0.1:2:61"]}
CONFIGS = ("1 proc x 1 dev", "1 proc x 2 dev", "2 proc x 1 dev")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _env(devices: int) -> dict:
    env = h.child_env(cache=False, JAX_PLATFORMS="cpu")
    flags = re.sub(r"--xla_force_host_platform_device_count=\d+", "",
                   env.get("XLA_FLAGS", "")).strip()
    if devices > 1:
        flags = f"{flags} --xla_force_host_platform_device_count={devices}".strip()
    env["XLA_FLAGS"] = flags
    return env


def run(name: str, args: list[str], config: str, workdir: Path) -> dict:
    out = workdir / f"{name.replace(' ', '_')}_{config.replace(' ', '')}"
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "pmsmjax", "feasibility", *args, "--no-plot",
           "--out", str(out)]
    procs = 2 if config.startswith("2 proc") else 1
    devices = 2 if config.endswith("2 dev") else 1
    t0 = time.perf_counter()
    if procs == 1:
        ps = [subprocess.Popen(cmd, env=_env(devices), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, cwd=h.ROOT)]
    else:
        port = _free_port()
        ps = [subprocess.Popen(cmd + ["--coordinator", f"localhost:{port}", "--num-processes",
                                      "2", "--process-id", str(i)],
                               env=_env(1), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, cwd=h.ROOT) for i in range(2)]
    outs = [p.communicate(timeout=1800) for p in ps]
    wall = time.perf_counter() - t0
    for p, (so, se) in zip(ps, outs):
        if p.returncode != 0:
            raise RuntimeError(f"{name} {config}: exit {p.returncode}\n{so[-2000:]}\n"
                               f"{se[-3000:]}")
    printed = outs[0][0]
    m = re.search(r"classified (\d+) designs in ([0-9.]+) s \(([^)]*)\)", printed)
    n, t_map, method = int(m.group(1)), float(m.group(2)), m.group(3)
    manifest = json.loads((out / "sweep" / "sweep.json").read_text())
    chunks = manifest["chunks"].values()
    t_chunks = sum(c["seconds"] for c in chunks)
    return dict(map=name, config=config, method=method, designs=n,
                chunks=manifest["n_chunks"], chunk_size=manifest["chunk_size"],
                devices=manifest["devices"]["count"], processes=procs,
                wall_s=wall, map_s=t_map, compile_s=manifest["compile_seconds"],
                chunks_s=t_chunks, designs_per_s=n / t_map,
                designs_per_s_chunks=n / t_chunks if t_chunks > 0 else None)


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="the closed-form map on a smaller grid, one "
                  "process with one and with two devices")
    ap.add_argument("--maps", default=None, help="comma-separated map names "
                    f"(default: {', '.join(MAPS)})")
    ap.add_argument("--configs", default=None, help="comma-separated configurations "
                    f"(default: {', '.join(CONFIGS)})")
    a = ap.parse_args(argv)
    maps = (a.maps or ("closed form" if a.quick else ",".join(MAPS))).split(",")
    configs = (a.configs or (",".join(CONFIGS[:2]) if a.quick else ",".join(CONFIGS)))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in maps:
            args = MAPS[name] + (QUICK[name] if a.quick else [])
            for config in configs.split(","):
                row = run(name, args, config, Path(tmp))
                rows.append(row)
                print(f"{name:12s} {config:15s} {row['designs']:>9d} designs: wall "
                      f"{row['wall_s']:6.1f} s, map {row['map_s']:6.1f} s (compile "
                      f"{row['compile_s']:5.1f} s), {row['designs_per_s']:9.3g} /s, "
                      f"chunks only {h.fmt(row['designs_per_s_chunks'], '9.3g')} /s",
                      flush=True)
    print(h.machine_line())
    h.table(rows, [
        ("map", lambda r: f"{r['map']} ({r['method']})", ""),
        ("processes x devices", "config", ""), ("designs", lambda r: f"{r['designs']:,}", ""),
        ("chunks", "chunks", "d"), ("wall (s)", "wall_s", ".1f"), ("map (s)", "map_s", ".1f"),
        ("compile (s)", "compile_s", ".1f"), ("designs/s (map)", "designs_per_s", ".3g"),
        ("designs/s (chunks)", "designs_per_s_chunks", ".3g")])
    h.write_report(a.json, rows, benchmark=MODULE, quick=a.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
