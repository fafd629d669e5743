"""Stress reproducer for the intermittent hang of jitted, vmapped computations on CPU.

Symptom seen twice (a vmapped `slowly_varying_certificate` inside a Jupyter kernel, and
earlier any computation with XLA's small-while-loop flag on a loaded 2-core machine): the
caller blocks on its output buffers while XLA's worker threads sit idle.

This script repeats the affected computations many times in several concurrent worker
processes, with extra CPU load beside them, under a set of process configurations
("variants"), and counts hangs. A watchdog declares a hang when a worker makes no
progress for `--timeout` seconds; it then dumps the native and Python stacks of every
thread of the worker with py-spy (`py-spy dump --native`) and, where gdb is installed, the native
stacks of every thread (`gdb -batch -ex "thread apply all bt"`) into the output folder, kills
the worker and starts a fresh one, so one hang does not stop the count.

Workloads (each iteration uses new inputs, so nothing is served from a cache):

- `certificate`: `jax.vmap` of `analysis.slowly_varying_certificate` over 4 LESO designs
  (reduced resolution), the computation that hung in the notebook;
- `certificate_eager`: the same `jax.vmap` without an outer `jit` (as the notebook
  called it: many small dispatched computations);
- `certificate_full`: one `slowly_varying_certificate` at its default resolution (101
  speeds), one of 4 LESO designs per iteration, as notebook 03 calls it. The reduced
  resolution above stays below jaxlib's threshold for splitting a batched LAPACK call
  over the thread pool, so it cannot show the deadlock that this one showed
  (`pmsmjax/_lapack_pool.py`);
- `lapack_pair`: the deadlock's mechanism alone: a jitted program with two independent
  batched solves (200 matrices of 16 x 16 each, above the threshold), 50 calls per
  iteration;
- `loop`: one sensorless closed-loop run (ESO, 4000 steps) and a vmapped batch of 16;
- `equilibria`: the generic equilibria route vmapped over 256 operating points;
- `callback_loop`: the minimal program of the public reports of a hang with asynchronous
  CPU dispatch: a jitted `lax.while_loop` whose body calls the host (`jax.debug.callback`
  and a `jax.pure_callback` inside a `lax.cond`, as `equinox.error_if` lowers), single and
  vmapped, 100 chained dispatches per iteration; `callback_loop_jax`: the same with a
  host function that itself runs a JAX computation; `callback_print`: the same with a
  `debug.callback` that prints a line; `callback_random`: 100 independent dispatches
  (no chain, nothing blocks between them) of a 30-step loop with a printing
  `debug.callback` and a data-dependent stop, each on a new random input.

Variants (process settings, applied before JAX starts):

- `default`: XLA's defaults;
- `small_loops`: `--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=...`;
- `small_loops_sync`: the same with `jax_cpu_enable_async_dispatch=False`;
- `small_loops_no_eigen_mt`: the same with `--xla_cpu_multi_thread_eigen=false`;
- `pmsmjax`: whatever `pmsmjax.runtime.configure()` chooses (the entry points' default);
- `sync`: XLA's defaults with `jax_cpu_enable_async_dispatch=False`;
- `no_eigen_mt`: XLA's defaults with `--xla_cpu_multi_thread_eigen=false`;
- `pmsmjax_sync`: `configure()` with `jax_cpu_enable_async_dispatch=False`.

`--mode kernel` runs the iterations inside Jupyter kernels driven by jupyter_client
(the notebook condition); the watchdog then dumps the kernel's stacks.

`--count-callbacks` runs nothing under load: it compiles the affected programs and counts
the custom calls to the Python CPU callback in their HLO, and how many of them a `while`
body reaches (the ingredient of the public reports of hangs with asynchronous dispatch).

Usage (from the repository root; `make stress` runs the defaults):

    python -m benchmarks.reproducers.stress_hang [--runs 100] [--procs 3] [--load 2]
        [--variants default,small_loops,...] [--workloads certificate,loop]
        [--timeout 120] [--out results/benchmarks/stress]
    python -m benchmarks.reproducers.stress_hang --count-callbacks
    python -m benchmarks.reproducers.stress_hang --quick   # 2 closed-loop iterations

Stack dumps of hangs go to `--out`, the counts to `--json`.
"""

from __future__ import annotations

import argparse
import math
import os
import queue
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

from .. import _harness as h


MODULE = "benchmarks.reproducers.stress_hang"


SMALL_LOOPS = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000"
VARIANTS = {
    "default": dict(xla_flags="", sync=False, configure=False),
    "small_loops": dict(xla_flags=SMALL_LOOPS, sync=False, configure=False),
    "small_loops_sync": dict(xla_flags=SMALL_LOOPS, sync=True, configure=False),
    "small_loops_no_eigen_mt": dict(
        xla_flags=SMALL_LOOPS + " --xla_cpu_multi_thread_eigen=false", sync=False,
        configure=False),
    "pmsmjax": dict(xla_flags="", sync=False, configure=True),
    "sync": dict(xla_flags="", sync=True, configure=False),
    "no_eigen_mt": dict(xla_flags="--xla_cpu_multi_thread_eigen=false", sync=False,
                        configure=False),
    "pmsmjax_sync": dict(xla_flags="", sync=True, configure=True),
}
WORKLOADS = ("certificate", "certificate_eager", "certificate_full", "lapack_pair", "loop",
             "equilibria", "callback_loop", "callback_loop_jax", "callback_print",
             "callback_random")


# ----------------------------------------------------------------------------- worker

def _callback_random(n_dispatch: int = 100):
    """`callback_random` (see the module docstring)."""
    import jax
    import jax.numpy as jnp
    from jax import lax

    def solve(x):
        def body(c):
            x, k = c
            jax.debug.callback(lambda k: print("step", int(k)), k)
            return 0.9 * x + jnp.sin(x), k + 1
        return lax.while_loop(lambda c: (c[1] < 30) & (jnp.max(jnp.abs(c[0])) < 1e6),
                              body, (x, 0))[0]

    f = jax.jit(solve)

    def run(i):
        key = jax.random.PRNGKey(i)
        out = []
        for _ in range(n_dispatch):
            key, sub = jax.random.split(key)
            out.append(f(jax.random.normal(sub, (64,))))
        return out
    return run


def _workload(name):
    """A function `f(i)` that runs iteration `i` of the workload to completion."""
    import jax
    import jax.numpy as jnp

    import pmsmjax as pj
    from pmsmjax import analysis

    drive = pj.preset("zhang750")
    wr = float(drive.w_rated)
    if name in ("certificate", "certificate_eager"):
        base = pj.observers.make_observer("leso", drive)

        def cert(zeta1):
            obs = base.with_design(zeta1=zeta1, ratio=0.5)
            c = analysis.slowly_varying_certificate(
                drive, obs, (0.2, 1.0), n_speed=21, n_time=60, n_dirs=64, n_refine=10,
                n_k1_speeds=5)
            return c.eps

        f = jax.vmap(cert) if name.endswith("eager") else jax.jit(jax.vmap(cert))
        return lambda i: f(jnp.linspace(0.6, 1.2, 4) + 1e-3 * (i % 7))
    if name == "certificate_full":
        base = pj.observers.make_observer("leso", drive)
        w2s = 2 * math.pi * jnp.array([25.0, 50.0, 100.0, 200.0])
        return lambda i: analysis.slowly_varying_certificate(
            drive, base.with_design(w2=w2s[i % 4]), (0.1, 1.0)).eps
    if name == "lapack_pair":
        a = jax.random.normal(jax.random.PRNGKey(0), (200, 16, 16)) + 16.0 * jnp.eye(16)
        x = jnp.ones((200, 16, 1))
        f = jax.jit(lambda a, b: (jnp.linalg.solve(a, x), jnp.linalg.solve(b, x)))

        def run(i):
            for k in range(50):
                jax.block_until_ready(f(a + 1e-3 * (i + k), a - 1e-3 * (i + k)))
        return run
    if name == "loop":
        foc = pj.FOC.from_drive(drive)
        obs = pj.ESOObserver.from_drive(drive)

        def one(w):
            sc = pj.Scenario(t_end=4000 * 125e-6, w_m_ref=pj.Profile.ramp(0.0, 0.1, 0.0, w),
                             tau_L=pj.Profile.steps([0.3], [1.0]))
            tr = pj.simulate(drive, foc, obs, sc, T_s=125e-6, save_every=4000, throw=False)
            return tr.ise_theta

        single = jax.jit(one)
        batch = jax.jit(jax.vmap(one))

        def run(i):
            w = (0.3 + 0.01 * (i % 11)) * wr
            jax.block_until_ready(single(w))
            return batch(w * jnp.linspace(0.8, 1.2, 16))
        return run
    if name == "equilibria":
        obs = pj.observers.make_observer("leso", drive)
        f = jax.jit(jax.vmap(lambda w, iq: analysis.equilibria(
            obs, drive.motor, w, jnp.stack([0.0, iq]), method="generic").status))
        w = jnp.linspace(0.1, 1.0, 256) * wr
        return lambda i: f(w * (1 + 1e-3 * (i % 5)), jnp.full(256, 0.5 + 0.01 * (i % 3)))
    if name in ("callback_loop", "callback_loop_jax", "callback_print"):
        return _callback_loop(name.endswith("_jax"), printing=name.endswith("_print"))
    if name == "callback_random":
        return _callback_random()
    raise ValueError(f"unknown workload {name!r}")


def _callback_loop(jax_in_callback: bool, printing: bool = False, n_loop: int = 20,
                   n_chain: int = 50):
    """The minimal workload of the public reports: a jitted `lax.while_loop` whose body
    calls the host twice per step (a `jax.debug.callback`, and a `jax.pure_callback`
    inside a `lax.cond` as `equinox.error_if` lowers), single and vmapped over 8, each
    dispatched `n_chain` times in a chain (each call's input is the previous output) before
    the caller blocks. With `jax_in_callback` the host function itself runs a JAX
    computation (the `pure_callback` report); with `printing` the `debug.callback` prints
    a line (to the worker's pipe, or a Jupyter kernel's output stream), as in the report of
    a hang with asynchronous dispatch."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax import lax

    def host(v):
        if jax_in_callback:
            return np.asarray(jnp.asarray(v) * 1.0)
        return np.asarray(v)

    def body(c):
        k, x = c
        jax.debug.callback((lambda v: print("step", v.shape)) if printing
                           else (lambda v: None), x)
        x = lax.cond(jnp.any(x > 1e9),
                     lambda x: jax.pure_callback(host, jax.ShapeDtypeStruct(x.shape, x.dtype),
                                                 x, vmap_method="broadcast_all"),
                     lambda x: x, x)
        x = jax.pure_callback(host, jax.ShapeDtypeStruct(x.shape, x.dtype), x,
                              vmap_method="broadcast_all")
        return k + 1, 0.99 * x + 1.0

    def loop(x):
        return lax.while_loop(lambda c: c[0] < n_loop, body, (0, x))[1]

    single = jax.jit(loop)
    batch = jax.jit(jax.vmap(loop))

    def run(i):
        x, xb = jnp.asarray(1.0 + 1e-3 * i), jnp.linspace(0.0, 1.0, 8) + 1e-3 * i
        for _ in range(n_chain):
            x, xb = 0.5 * single(x), 0.5 * batch(xb)
        return x, xb
    return run


def kernel_worker(args):
    """The same iterations inside a Jupyter kernel (the notebook condition): this process
    drives an ipykernel with jupyter_client and reports its pid for the stack dump."""
    from jupyter_client.manager import start_new_kernel

    variant = VARIANTS[args.variant]
    env = dict(os.environ)
    if variant["xla_flags"]:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + variant["xla_flags"]).strip()
    # the kernel imports this module from the repository root
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(h.ROOT), env.get("PYTHONPATH")) if p)
    km, kc = start_new_kernel(kernel_name="python3", env=env)
    try:
        pid = km.provisioner.process.pid
        print(f"kernel_pid {pid}", flush=True)
        setup = ("import time\n"
                 "import jax\n"
                 f"if {variant['sync']}: jax.config.update("
                 "'jax_cpu_enable_async_dispatch', False)\n"
                 f"if {variant['configure']}:\n"
                 "    import pmsmjax as pj; pj.runtime.configure(cache=False)\n"
                 "from benchmarks.reproducers import stress_hang as sh\n"
                 f"fns = {{w: sh._workload(w) for w in {args.workloads.split(',')!r}}}\n")
        kc.execute_interactive(setup, timeout=None, store_history=False)
        print("ready", flush=True)
        for i in range(args.runs):
            for w in args.workloads.split(","):
                t0 = time.perf_counter()
                r = kc.execute_interactive(f"jax.block_until_ready(fns[{w!r}]({i}))",
                                           timeout=None, store_history=False,
                                           output_hook=lambda msg: None)
                if r["content"]["status"] != "ok":
                    print("error", r["content"].get("ename"), r["content"].get("evalue"),
                          flush=True)
                    raise SystemExit(1)
                print(f"done {i} {w} {time.perf_counter() - t0:.3f}", flush=True)
    finally:
        kc.stop_channels()
        km.shutdown_kernel(now=True)


def worker(args):
    if args.mode == "kernel":
        return kernel_worker(args)
    variant = VARIANTS[args.variant]
    if variant["xla_flags"]:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " "
                                   + variant["xla_flags"]).strip()
    import jax

    if variant["sync"]:
        jax.config.update("jax_cpu_enable_async_dispatch", False)
    if variant["configure"]:
        import pmsmjax as pj

        pj.runtime.configure(cache=False)
    fns = {w: _workload(w) for w in args.workloads.split(",")}
    print("ready", flush=True)
    for i in range(args.runs):
        for w, f in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f(i))
            print(f"done {i} {w} {time.perf_counter() - t0:.3f}", flush=True)


# ----------------------------------------------------------------------------- callbacks

def _hlo_callbacks(text: str) -> tuple[int, int, int]:
    """(while loops, host callbacks, host callbacks reachable from a while body) of an
    optimized HLO module's text."""
    import re

    comps: dict[str, list[str]] = {}
    cur = None
    for line in text.splitlines():
        m = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
        if m:
            cur = m.group(1)
            comps[cur] = []
        elif cur is not None:
            comps[cur].append(line)
    edges: dict[str, set] = {}
    bodies: list[str] = []
    for c, lines in comps.items():
        e = set()
        for line in lines:
            for key in ("condition", "body", "to_apply", "calls", "true_computation",
                        "false_computation"):
                e.update(re.findall(key + r"=%?([\w.\-]+)", line))
            m = re.search(r"branch_computations=\{([^}]*)\}", line)
            if m:
                e.update(x.strip().lstrip("%") for x in m.group(1).split(","))
            if " while(" in line:
                bodies += re.findall(r"body=%?([\w.\-]+)", line)
        edges[c] = e
    in_loop: set = set()
    todo = list(bodies)
    while todo:
        c = todo.pop()
        if c not in in_loop:
            in_loop.add(c)
            todo += edges.get(c, ())
    n_cb = {c: sum("custom_call_target=" in x and "callback" in x for x in lines)
            for c, lines in comps.items()}
    return (len(bodies), sum(n_cb.values()),
            sum(n for c, n in n_cb.items() if c in in_loop))


def count_callbacks():
    import jax
    import jax.numpy as jnp

    import pmsmjax as pj
    from pmsmjax import analysis

    pj.runtime.configure(cache=False)
    drive = pj.preset("zhang750")
    wr = float(drive.w_rated)
    leso = pj.observers.make_observer("leso", drive)
    foc, eso = pj.FOC.from_drive(drive), pj.ESOObserver.from_drive(drive)

    def cert(zeta1):
        return analysis.slowly_varying_certificate(
            drive, leso.with_design(zeta1=zeta1, ratio=0.5), (0.2, 1.0), n_speed=21,
            n_time=60, n_dirs=64, n_refine=10, n_k1_speeds=5).eps

    def sim(w, throw):
        sc = pj.Scenario(t_end=4000 * 125e-6, w_m_ref=pj.Profile.ramp(0.0, 0.1, 0.0, w),
                         tau_L=pj.Profile.steps([0.3], [1.0]))
        return pj.simulate(drive, foc, eso, sc, T_s=125e-6, save_every=4000,
                           throw=throw).ise_theta

    cases = {
        "slowly_varying_certificate, vmapped over 4 LESO designs":
            (jax.vmap(cert), (jnp.linspace(0.6, 1.2, 4),)),
        "generic equilibria, vmapped over 256 points":
            (jax.vmap(lambda w, iq: analysis.equilibria(
                leso, drive.motor, w, jnp.stack([0.0, iq]), method="generic").status),
             (jnp.linspace(0.1, 1.0, 256) * wr, jnp.full(256, 0.5))),
        "simulate (ESO closed loop), throw=True": (lambda w: sim(w, True), (0.3 * wr,)),
        "simulate, throw=False": (lambda w: sim(w, False), (0.3 * wr,)),
    }
    print("| program | while loops | host callbacks | inside a loop |")
    print("|---|---:|---:|---:|")
    for name, (f, args) in cases.items():
        n_while, n_cb, n_in = _hlo_callbacks(jax.jit(f).lower(*args).compile().as_text())
        print(f"| {name} | {n_while} | {n_cb} | {n_in} |", flush=True)


# ----------------------------------------------------------------------------- parent

def _load_proc():
    """A busy process (NumPy matrix products) as concurrent CPU load."""
    code = ("import numpy as np\n"
            "a = np.random.rand(300, 300)\n"
            "while True:\n    a = np.tanh(a @ a.T / 300.0)\n")
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def _dump_stacks(pid, path: Path):
    """Python threads with py-spy; then, where gdb is installed, every native thread
    (py-spy shows only the threads that run Python, not XLA's pool threads)."""
    spy = shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy")
    try:
        res = subprocess.run([spy, "dump", "--native", "--pid", str(pid)],
                             capture_output=True, text=True, timeout=60)
        text = res.stdout + res.stderr
    except (OSError, subprocess.TimeoutExpired) as e:
        text = f"py-spy failed: {e}\n"
    gdb = shutil.which("gdb")
    if gdb:
        try:
            res = subprocess.run([gdb, "-p", str(pid), "-batch", "-ex", "thread apply all bt 30"],
                                 capture_output=True, text=True, timeout=120)
            text += "\n# gdb: every thread\n" + res.stdout
        except (OSError, subprocess.TimeoutExpired) as e:
            text += f"\ngdb failed: {e}\n"
    path.write_text(text)


def _reader(proc, q):
    for line in proc.stdout:
        q.put(line)
    q.put(None)


def run_variant(variant, args, out: Path) -> dict:
    """Run `args.runs` iterations of each workload split over `args.procs` workers."""
    per = max(1, args.runs // args.procs)
    todo = [per] * args.procs
    stats = dict(variant=variant, mode=args.mode, iterations=0, hangs=0, crashes=0, times=[],
                 dumps=[])
    slots: list = [None] * args.procs
    t_start = time.perf_counter()

    def start(k):
        cmd = [sys.executable, "-m", MODULE, "--child", "--variant", variant, "--mode",
               args.mode, "--workloads", args.workloads, "--runs", str(todo[k])]
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             text=True, cwd=h.ROOT)
        q: queue.Queue = queue.Queue()
        threading.Thread(target=_reader, args=(p, q), daemon=True).start()
        slots[k] = dict(proc=p, q=q, last=time.monotonic(), ready=False, done=0, tail=[])

    for k in range(args.procs):
        start(k)
    while any(s is not None for s in slots):
        time.sleep(0.2)
        for k, s in enumerate(slots):
            if s is None:
                continue
            while True:
                try:
                    line = s["q"].get_nowait()
                except queue.Empty:
                    break
                if line is None:
                    s["eof"] = True
                    break
                s["last"] = time.monotonic()
                s["tail"] = (s["tail"] + [line])[-30:]
                if line.startswith("kernel_pid"):
                    s["dump_pid"] = int(line.split()[1])
                elif line.startswith("ready"):
                    s["ready"] = True
                elif line.startswith("done"):
                    _, i, w, dt = line.split()
                    stats["iterations"] += 1
                    s["done"] += 1
                    stats["times"].append(float(dt))
                    if w == args.workloads.split(",")[-1]:  # an iteration is complete
                        todo[k] -= 1
            limit = args.timeout if s["ready"] else max(args.timeout, 600)
            if s.get("eof"):
                rc = s["proc"].wait()
                if rc != 0:
                    stats["crashes"] += 1
                    if s["done"] == 0:  # a broken workload, not an intermittent failure
                        raise SystemExit(f"worker of {variant} failed (exit {rc}):\n"
                                         + "".join(s["tail"]))
                slots[k] = None
                if rc != 0 and todo[k] > 0:
                    start(k)
            elif time.monotonic() - s["last"] > limit:
                stats["hangs"] += 1
                dump = out / f"hang_{variant}_{stats['hangs']}.txt"
                _dump_stacks(s.get("dump_pid", s["proc"].pid), dump)
                if "dump_pid" in s:
                    try:
                        os.kill(s["dump_pid"], 9)
                    except OSError:
                        pass
                stats["dumps"].append(dump.name)
                print(f"  HANG in {variant} (pid {s['proc'].pid}); stacks in {dump}",
                      flush=True)
                s["proc"].kill()
                s["proc"].wait()
                slots[k] = None
                if todo[k] > 0:
                    start(k)
    stats["wall_s"] = time.perf_counter() - t_start
    ts = sorted(stats.pop("times"))
    stats["median_iteration_s"] = ts[len(ts) // 2] if ts else None
    stats["max_iteration_s"] = ts[-1] if ts else None
    stats["hangs_per_100"] = 100.0 * stats["hangs"] / max(1, stats["iterations"])
    return stats


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="2 iterations of the closed loop in one "
                  "worker beside one busy process, configure()'s settings")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--variant", default="default")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--workloads", default="certificate_full,loop")
    ap.add_argument("--mode", choices=("process", "kernel"), default="process",
                    help="run the workloads in plain worker processes or inside Jupyter "
                         "kernels driven by jupyter_client (the notebook condition)")
    ap.add_argument("--runs", type=int, default=100,
                    help="iterations of each workload per variant, over all workers")
    ap.add_argument("--procs", type=int, default=3, help="concurrent worker processes")
    ap.add_argument("--load", type=int, default=2, help="extra busy processes")
    ap.add_argument("--timeout", type=float, default=120.0,
                    help="seconds without progress that count as a hang")
    ap.add_argument("--out", default=str(h.RESULTS / "stress"),
                    help="folder for the stack dumps of hangs")
    ap.add_argument("--count-callbacks", action="store_true",
                    help="count the host callbacks in the affected programs' compiled HLO")
    args = ap.parse_args(argv)
    if args.child:
        worker(args)
        return 0
    if args.count_callbacks:
        count_callbacks()
        return 0
    if args.quick:
        args.variants, args.workloads, args.runs, args.procs, args.load = (
            "pmsmjax", "loop", 2, 1, 1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    loads = [_load_proc() for _ in range(args.load)]
    results = []
    try:
        for v in args.variants.split(","):
            if v not in VARIANTS:
                raise SystemExit(f"--variants: unknown variant {v!r}; "
                                 f"choose from {', '.join(VARIANTS)}")
            print(f"variant {v} ({args.mode}): {args.runs} x ({args.workloads}) on "
                  f"{args.procs} workers "
                  f"+ {args.load} load processes", flush=True)
            r = run_variant(v, args, out)
            print(f"  {r['iterations']} iterations, {r['hangs']} hangs, {r['crashes']} "
                  f"crashes, median {r['median_iteration_s']} s, wall {r['wall_s']:.0f} s",
                  flush=True)
            results.append(r)
    finally:
        for p in loads:
            p.kill()
            p.wait()
    print()
    h.table(results, [("variant", "variant", ""), ("mode", "mode", ""),
                      ("iterations", "iterations", "d"), ("hangs", "hangs", "d"),
                      ("hangs per 100", "hangs_per_100", ".1f"),
                      ("median s", "median_iteration_s", ".3f"),
                      ("max s", "max_iteration_s", ".3f")])
    h.write_report(args.json, results, benchmark=MODULE, args=vars(args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
