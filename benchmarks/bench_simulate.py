"""Closed-loop throughput benchmark of `pmsmjax.simulate`, side by side with NumPy and C.

Scenario (the same for every implementation): the `zhang750` preset under sensored speed
control (`FOC.from_drive`, `SensoredObserver`), T_s = 125 us, RK4 plant with one substep,
ZOH. Speed reference ramps from 0 to `w_final` over [0, 0.1] s, load torque steps from 0
to 1 N m at 0.15 s. A batch of B drives differs in `w_final` (0.2 ... 0.8 x rated), so
`jax.vmap` runs B closed loops at once. Throughput runs keep one sample of the trajectory
(`save_every` = number of steps) and the ISE integral; memory does not grow with the run.

The references implement the identical discrete algorithm:

- `ref_numpy.py`: batched NumPy arrays, Python loop over time;
- `ref_c.c`: scalar C, loop over drives and time, `gcc -O3 -march=native` (float64 and
  float32 builds, plus an OpenMP build for the all-cores rows).

They are checked against pmsmjax (float64, final state and ISE to 1e-9) before timing.

Every measurement runs in a fresh subprocess: "one core" pins it with `taskset -c 0` and
sets `XLA_FLAGS=--xla_cpu_multi_thread_eigen=false` (and OMP_NUM_THREADS=1); "all cores"
uses neither (XLA's default threading; C with OpenMP); "sharded" splits the batch over
one XLA host device per core (`--xla_force_host_platform_device_count`, pmsmjax only).

Reported: drive-steps per second = B x steps / time, from the best of several repeats,
both by the process CPU time (for the pinned one-core runs: insensitive to other load on
a shared machine; the targets are judged on it) and by wall time; compile time (trace +
lower, and XLA compile) separately from run time, and the compiled temporary memory; the
cost of `jax.grad` of a scalar loss (ISE of the speed error) w.r.t. the speed-loop
bandwidth `alpha_s` relative to the forward run of the same loss.

Usage:

    .venv/bin/python benchmarks/bench_simulate.py [--quick] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import ctypes
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


HERE = Path(__file__).resolve().parent
BUILD = HERE / "build"
sys.path.insert(0, str(HERE))

T_S = 125e-6
T_RAMP, T_LOAD, TAU_LOAD = 0.1, 0.15, 1.0
W_LO, W_HI = 0.2, 0.8  # w_final range, fraction of rated speed
# XLA (jaxlib 0.10) parses --xla_cpu_multi_thread_eigen; "intra_op_parallelism_threads=1"
# is not an XLA flag: XLA_FLAGS parsing stops at the first token without "--" (it is taken
# for a file name) and silently drops every flag after it. The pinning (taskset) is what
# restricts a run to one core.
ONE_CORE_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false"
BATCHES = (1, 64, 1024, 4096)

# Steps per run: long enough that the timings are stable (>= 0.25 s of drive time).
FULL = dict(jax_steps={1: 16000, 64: 8000, 1024: 2000, 4096: 2000},
            numpy_steps={1: 2000, 64: 2000, 1024: 500, 4096: 250},
            c_steps={1: 16000, 64: 8000, 1024: 2000, 4096: 2000},
            grad_steps=8000, grad_batch=64, value_and_grad=True, min_time=1.0, repeats=5,
            batches=BATCHES, modes=("one", "all", "sharded"))
QUICK = dict(jax_steps={1: 4000, 1024: 1000},
             numpy_steps={1: 300, 1024: 60},
             c_steps={1: 4000, 1024: 1000},
             grad_steps=2000, grad_batch=16, value_and_grad=False, min_time=0.1,
             repeats=2, batches=(1, 1024), modes=("one",))
# "one": one core (taskset -c 0, XLA single-threaded); "all": no pinning, XLA's default
# threading, C with OpenMP over the drives; "sharded": no pinning, one XLA host device per
# core (single-threaded each) and the batch split over them (pmsmjax only).


# ---------------------------------------------------------------------------------------
# The scenario and the parameters the references need
# ---------------------------------------------------------------------------------------

def drive_and_controller():
    import pmsmjax as pj

    drive = pj.preset("zhang750")
    return drive, pj.FOC.from_drive(drive)


def w_finals(B, dtype=np.float64):
    drive, _ = drive_and_controller()
    return (np.linspace(W_LO, W_HI, B) * float(drive.w_rated)).astype(dtype)


def reference_params(drive, foc, n_sub=1) -> dict:
    """Plain numbers for the references, read from the pmsmjax objects."""
    m, cm = drive.motor, foc.current.motor
    assert not drive.dual and m.harmonics is None and cm.harmonics is None
    assert foc.refs.strategy == "id_const" and foc.angle_advance
    assert not drive.inverter.delay
    f = float
    return dict(
        R_s=f(m.R_s), L_d=f(m.L_d), L_q=f(m.L_q), psi_f=f(m.psi_f), n_p=f(m.n_p),
        J=f(drive.mechanics.J), B=f(drive.mechanics.B),
        cR_s=f(cm.R_s), cL_d=f(cm.L_d), cL_q=f(cm.L_q), cpsi_f=f(cm.psi_f),
        alpha_c=f(foc.current.alpha_c), u_max=f(foc.current.u_max),
        J_over_np=f(foc.speed.J_over_np), alpha_s=f(foc.speed.alpha_s),
        tau_max=f(foc.speed.tau_max), i_d_ref=f(foc.refs.i_d), i_max=f(foc.refs.i_max),
        k_tau=f(foc.k_tau),
        T_s=T_S, t_ramp=T_RAMP, t_load=T_LOAD, tau_load=TAU_LOAD,
        i_bound=20.0 * f(drive.i_max), w_bound=20.0 * f(drive.w_rated), n_sub=int(n_sub),
    )


def make_pmsmjax_run(dtype_name: str, n_steps: int, save_every: int | None = None,
                     params=None):
    """`f(w_final[B]) -> (ise_w, w_m, i_dq, status)` for a batch, not yet jitted.

    `params(foc) -> foc` may replace controller fields (for the gradient)."""
    import jax.numpy as jnp

    import pmsmjax as pj

    drive, foc = drive_and_controller()
    obs = pj.SensoredObserver()
    dt = jnp.float32 if dtype_name == "float32" else jnp.float64
    if dt == jnp.float32:
        drive, foc = pj.astype(drive, dt), pj.astype(foc, dt)
    save_every = n_steps if save_every is None else save_every

    def one(w_final, gain=None):
        sc = pj.Scenario(
            t_end=n_steps * T_S,
            w_m_ref=pj.astype(pj.Profile.ramp(0.0, T_RAMP, 0.0, w_final), dt),
            tau_L=pj.astype(pj.Profile.steps([T_LOAD], [TAU_LOAD]), dt))
        c = foc if gain is None else params(foc, gain)
        tr = pj.simulate(drive, c, obs, sc, T_s=T_S, save_every=save_every, throw=False)
        return tr.ise_w, tr.w_m, tr.i_dq, tr.status._value

    return one


# ---------------------------------------------------------------------------------------
# C reference: build and call through ctypes
# ---------------------------------------------------------------------------------------

class _CParams(ctypes.Structure):
    _fields_ = [(n, ctypes.c_double) for n in (
        "R_s", "L_d", "L_q", "psi_f", "n_p", "J", "B",
        "cR_s", "cL_d", "cL_q", "cpsi_f", "alpha_c", "u_max", "J_over_np", "alpha_s",
        "tau_max", "i_d_ref", "i_max", "k_tau",
        "T_s", "t_ramp", "t_load", "tau_load", "i_bound", "w_bound")] + [
        ("n_sub", ctypes.c_int)]


C_BUILDS = {  # name: extra gcc flags
    "float64": ["-DREAL=double"],
    "float32": ["-DREAL=float"],
    "float64_omp": ["-DREAL=double", "-fopenmp"],
    "float32_omp": ["-DREAL=float", "-fopenmp"],
}


def build_c(verbose=True) -> dict:
    """Compile ref_c.c into benchmarks/build/ (shared libraries for ctypes)."""
    BUILD.mkdir(exist_ok=True)
    src = HERE / "ref_c.c"
    out = {}
    for name, extra in C_BUILDS.items():
        lib = BUILD / f"ref_c_{name}.so"
        cmd = ["gcc", "-O3", "-march=native", "-shared", "-fPIC", *extra, str(src), "-o",
               str(lib), "-lm"]
        if not lib.exists() or lib.stat().st_mtime < src.stat().st_mtime:
            if verbose:
                print("  $", " ".join(cmd))
            subprocess.run(cmd, check=True)
        out[name] = str(lib)
    return out


def c_simulate(lib_path: str, p: dict, w_final: np.ndarray, n_steps: int):
    dt = np.float32 if "float32" in lib_path else np.float64
    lib = ctypes.CDLL(lib_path)
    w = np.ascontiguousarray(w_final, dtype=dt)
    out = np.zeros((w.shape[0], 6), dt)
    lib.simulate_batch(ctypes.byref(_CParams(**p)), ctypes.c_int(w.shape[0]),
                       ctypes.c_int(n_steps), w.ctypes.data_as(ctypes.c_void_p),
                       out.ctypes.data_as(ctypes.c_void_p))
    return out


# ---------------------------------------------------------------------------------------
# Verification of the references against pmsmjax
# ---------------------------------------------------------------------------------------

def verify(libs: dict, n_steps=2000, B=4, verbose=True) -> dict:
    """Final (i_d, i_q, w_m) and ISE of pmsmjax, NumPy and C for a few drives."""
    import jax
    import ref_numpy

    drive, foc = drive_and_controller()
    p = reference_params(drive, foc)
    res = {}
    for dtype_name in ("float64", "float32"):
        dt = np.float32 if dtype_name == "float32" else np.float64
        w = w_finals(B, dt)
        # pmsmjax records the state at t_k before the step: run one step more and take
        # the last sample = the state after n_steps periods.
        one_long = make_pmsmjax_run(dtype_name, n_steps + 1, save_every=1)
        one = make_pmsmjax_run(dtype_name, n_steps)
        _, w_m, i_dq, _ = jax.jit(jax.vmap(one_long))(w)
        ise, _, _, status = jax.jit(jax.vmap(one))(w)
        jx = np.stack([np.asarray(i_dq[:, -1, 0]), np.asarray(i_dq[:, -1, 1]),
                       np.asarray(w_m[:, -1]), np.asarray(ise)], -1).astype(np.float64)
        np_out = ref_numpy.simulate(p, w, n_steps, dtype=dt)[:, [0, 1, 3, 4]]
        c_out = c_simulate(libs[dtype_name], p, w, n_steps)[:, [0, 1, 3, 4]]
        scale = np.maximum(np.abs(jx), 1.0)
        err_np = float(np.max(np.abs(np_out - jx) / scale))
        err_c = float(np.max(np.abs(c_out - jx) / scale))
        res[dtype_name] = dict(
            n_steps=n_steps, batch=B, jax_dtype=str(w_m.dtype), ok=bool(np.all(status == 0)),
            max_rel_err_numpy=err_np, max_rel_err_c=err_c,
            pmsmjax_final=jx.tolist(),
        )
        if verbose:
            print(f"  {dtype_name}: pmsmjax output dtype {w_m.dtype}; max relative "
                  f"difference of final (i_d, i_q, w_m, ISE_w) over {B} drives after "
                  f"{n_steps} steps: NumPy {err_np:.2e}, C {err_c:.2e}")
    tol = 1e-9
    if res["float64"]["max_rel_err_numpy"] > tol or res["float64"]["max_rel_err_c"] > tol:
        raise SystemExit(f"Verification failed: the references differ from pmsmjax by more "
                         f"than {tol} in float64: {res['float64']}")
    if res["float32"]["jax_dtype"] != "float32":
        raise SystemExit("pmsmjax did not run in float32 with float32 inputs.")
    return res


# ---------------------------------------------------------------------------------------
# Timing (inside a worker subprocess)
# ---------------------------------------------------------------------------------------

def _timeit(fn, min_time, repeats):
    """Call `fn` (already warm) at least `repeats` times and for at least `min_time` s;
    return (best wall, median wall, best process-CPU) seconds."""
    walls, cpus = [], []
    t_start = time.perf_counter()
    while len(walls) < repeats or (time.perf_counter() - t_start < min_time
                                   and len(walls) < 50):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return min(walls), float(np.median(walls)), min(cpus), len(walls)


def worker_throughput(cfg: dict) -> dict:
    import jax
    import ref_numpy

    dtype_name = cfg["dtype"]
    dt = np.float32 if dtype_name == "float32" else np.float64
    drive, foc = drive_and_controller()
    p = reference_params(drive, foc)
    rows = []
    sharded = cfg.get("sharded", False)
    for B in cfg["batches"]:
        row = dict(batch=B)
        w = w_finals(B, dt)
        if sharded:
            devs = jax.devices()
            if B % len(devs):
                continue
            mesh = jax.sharding.Mesh(np.array(devs), ("batch",))
            w = jax.device_put(w, jax.sharding.NamedSharding(
                mesh, jax.sharding.PartitionSpec("batch")))
            row["devices"] = len(devs)
        # --- pmsmjax
        N = cfg["jax_steps"][str(B)]
        fn = jax.jit(jax.vmap(make_pmsmjax_run(dtype_name, N)))
        t0 = time.perf_counter()
        lowered = fn.lower(w)
        t1 = time.perf_counter()
        compiled = lowered.compile()
        t2 = time.perf_counter()
        out = jax.block_until_ready(compiled(w))
        t3 = time.perf_counter()
        assert str(out[1].dtype) == dtype_name, out[1].dtype
        assert bool(np.all(np.asarray(out[3]) == 0)), "a benchmark run diverged"
        best, med, cpu, n = _timeit(lambda: jax.block_until_ready(compiled(w)),
                                    cfg["min_time"], cfg["repeats"])
        mem = compiled.memory_analysis()
        row["pmsmjax"] = dict(
            steps=N, save_every=N, trace_lower_s=t1 - t0, compile_s=t2 - t1,
            first_run_s=t3 - t2, run_s=best, run_median_s=med, cpu_s=cpu, repeats=n,
            steps_per_s=B * N / best, steps_per_cpu_s=B * N / cpu,
            out_dtype=str(out[1].dtype),
            temp_bytes=int(getattr(mem, "temp_size_in_bytes", -1)),
        )
        if sharded:
            rows.append(row)
            print(f"    B={B:5d}: pmsmjax {row['pmsmjax']['steps_per_s'] / 1e6:7.3f} M/s "
                  f"on {row['devices']} devices", file=sys.stderr, flush=True)
            continue
        # --- NumPy
        Nn = cfg["numpy_steps"][str(B)]
        ref_numpy.simulate(p, w, 2, dtype=dt)
        best, med, cpu, n = _timeit(lambda: ref_numpy.simulate(p, w, Nn, dtype=dt),
                                    cfg["min_time"], max(1, cfg["repeats"] // 2))
        row["numpy"] = dict(steps=Nn, run_s=best, run_median_s=med, cpu_s=cpu, repeats=n,
                            steps_per_s=B * Nn / best, steps_per_cpu_s=B * Nn / cpu)
        # --- C
        Nc = cfg["c_steps"][str(B)]
        lib = cfg["c_lib"]
        c_simulate(lib, p, w, 2)
        best, med, cpu, n = _timeit(lambda: c_simulate(lib, p, w, Nc), cfg["min_time"],
                                    cfg["repeats"])
        row["c"] = dict(steps=Nc, run_s=best, run_median_s=med, cpu_s=cpu, repeats=n,
                        steps_per_s=B * Nc / best, steps_per_cpu_s=B * Nc / cpu,
                        lib=os.path.basename(lib))
        rows.append(row)
        print(f"    B={B:5d}: pmsmjax {row['pmsmjax']['steps_per_s'] / 1e6:7.3f} M/s, "
              f"NumPy {row['numpy']['steps_per_s'] / 1e6:7.3f} M/s, "
              f"C {row['c']['steps_per_s'] / 1e6:7.3f} M/s", file=sys.stderr, flush=True)
    return dict(rows=rows)


def worker_grad(cfg: dict) -> dict:
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    N = cfg["grad_steps"]
    dtype_name = cfg["dtype"]
    dt = jnp.float32 if dtype_name == "float32" else jnp.float64

    def set_gain(foc, a):
        return eqx.tree_at(lambda c: c.speed.alpha_s, foc, a)

    one = make_pmsmjax_run(dtype_name, N, params=set_gain)
    _, foc = drive_and_controller()
    a0 = jnp.asarray(float(foc.speed.alpha_s), dt)

    def loss(a, w_final):
        return one(w_final, a)[0] * 1e-3  # ISE of the speed error

    out = {}
    for B in (1, cfg["grad_batch"]):
        w = jnp.asarray(w_finals(B, np.dtype(dtype_name)))
        if B == 1:
            fns = dict(forward=lambda a, w: loss(a, w[0]),
                       grad=lambda a, w: jax.grad(loss)(a, w[0]),
                       value_and_grad=lambda a, w: jax.value_and_grad(loss)(a, w[0])[1])
        else:
            fns = dict(forward=jax.vmap(loss, (None, 0)),
                       grad=jax.vmap(jax.grad(loss), (None, 0)),
                       value_and_grad=jax.vmap(lambda a, w: jax.value_and_grad(loss)(a, w)[1],
                                               (None, 0)))
        if not cfg["value_and_grad"]:
            del fns["value_and_grad"]
        res = {}
        for name, fn in fns.items():
            t0 = time.perf_counter()
            compiled = jax.jit(fn).lower(a0, w).compile()
            tc = time.perf_counter() - t0
            val = jax.block_until_ready(compiled(a0, w))
            best, med, cpu, n = _timeit(lambda: jax.block_until_ready(compiled(a0, w)),
                                        cfg["min_time"], cfg["repeats"])
            mem = compiled.memory_analysis()
            res[name] = dict(compile_s=tc, run_s=best, run_median_s=med, cpu_s=cpu,
                             repeats=n, temp_bytes=int(getattr(mem, "temp_size_in_bytes", -1)),
                             value=np.asarray(val).reshape(-1)[:2].tolist())
        for name in fns:
            if name != "forward":
                res[f"{name}_over_forward"] = res[name]["run_s"] / res["forward"]["run_s"]
                res[f"{name}_over_forward_cpu"] = res[name]["cpu_s"] / res["forward"]["cpu_s"]
        res["steps"] = N
        out[f"batch_{B}"] = res
        print(f"    grad B={B}: forward {res['forward']['cpu_s'] * 1e3:.1f} ms, grad "
              f"{res['grad']['cpu_s'] * 1e3:.1f} ms CPU time (x"
              f"{res['grad_over_forward_cpu']:.2f}; by wall time x"
              f"{res['grad_over_forward']:.2f})", file=sys.stderr, flush=True)
    return out


def worker_first_compile(cfg: dict) -> dict:
    """Wall time from a cold `import pmsmjax` to the first result of one `simulate` call."""
    t0 = time.perf_counter()
    import jax

    import pmsmjax as pj

    t1 = time.perf_counter()
    drive, foc = drive_and_controller()
    sc = pj.Scenario(t_end=0.25, w_m_ref=pj.Profile.ramp(0.0, T_RAMP, 0.0, 600.0),
                     tau_L=pj.Profile.steps([T_LOAD], [TAU_LOAD]))
    t2 = time.perf_counter()
    tr = pj.simulate(drive, foc, pj.SensoredObserver(), sc, T_s=T_S)
    jax.block_until_ready(tr.w_m)
    t3 = time.perf_counter()
    tr = pj.simulate(drive, foc, pj.SensoredObserver(), sc, T_s=T_S)
    jax.block_until_ready(tr.w_m)
    t4 = time.perf_counter()
    return dict(import_s=t1 - t0, first_call_s=t3 - t2, second_call_s=t4 - t3,
                first_compile_s=(t3 - t2) - (t4 - t3))


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------

def run_worker(kind: str, cfg: dict, mode: str) -> dict:
    env = dict(os.environ)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", kind, json.dumps(cfg)]
    if mode == "one":
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + ONE_CORE_XLA_FLAGS).strip()
        env["OMP_NUM_THREADS"] = "1"
        if shutil.which("taskset"):
            cmd = ["taskset", "-c", "0", *cmd]
    elif mode == "sharded":
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + ONE_CORE_XLA_FLAGS +
                            f" --xla_force_host_platform_device_count={os.cpu_count()}"
                            ).strip()
    else:
        env.pop("OMP_NUM_THREADS", None)
    load0 = os.getloadavg()[0]
    proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, text=True, check=True)
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    res["loadavg_before_after"] = [load0, os.getloadavg()[0]]
    return res


def machine_info() -> dict:
    import jax
    import jaxlib

    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gcc = subprocess.run(["gcc", "--version"], stdout=subprocess.PIPE, text=True)
    return dict(
        cpu_model=model, cpu_count=os.cpu_count(),
        cpu_affinity=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
        else None,
        jax=jax.__version__, jaxlib=jaxlib.__version__, numpy=np.__version__,
        python=platform.python_version(), platform=platform.platform(),
        gcc=gcc.stdout.splitlines()[0] if gcc.stdout else "unknown",
        date=datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        loadavg=os.getloadavg(),
    )


MODE_NAMES = dict(one="one core", all="all cores (XLA default threading)",
                  sharded="all cores (batch sharded over one XLA device per core)")


def _fmt_rate(x):
    return f"{x / 1e6:.3f}"


def print_table(results: dict) -> str:
    thr = results["throughput"]
    ncores = results["machine"]["cpu_count"]
    lines = ["One core (pinned). Drive-steps per second from the process CPU time (best of "
             "the repeats); wall-clock figures alongside.", ""]
    hdr = ("| dtype | batch | pmsmjax M/s | NumPy M/s | C M/s | pmsmjax/NumPy | pmsmjax/C | "
           "pmsmjax wall M/s | C wall M/s | compile s | temp MiB |")
    lines += [hdr, "|" + "---|" * (hdr.count("|") - 1)]
    for dtype_name in ("float64", "float32"):
        for row in thr.get(f"{dtype_name}/one", {}).get("rows", []):
            j, n, c = row["pmsmjax"], row["numpy"], row["c"]
            lines.append(
                f"| {dtype_name} | {row['batch']} | {_fmt_rate(j['steps_per_cpu_s'])} | "
                f"{_fmt_rate(n['steps_per_cpu_s'])} | {_fmt_rate(c['steps_per_cpu_s'])} | "
                f"{j['steps_per_cpu_s'] / n['steps_per_cpu_s']:.1f} | "
                f"{j['steps_per_cpu_s'] / c['steps_per_cpu_s']:.2f} | "
                f"{_fmt_rate(j['steps_per_s'])} | {_fmt_rate(c['steps_per_s'])} | "
                f"{j['trace_lower_s'] + j['compile_s']:.2f} | {j['temp_bytes'] / 2**20:.1f} |")
    if any(k.split("/")[1] != "one" for k in thr):
        lines += ["", f"All {ncores} cores (no pinning). Drive-steps per second from the "
                  "wall time (best of the repeats); C uses OpenMP over the drives, NumPy is "
                  "single-threaded.", ""]
        hdr = ("| dtype | pmsmjax mode | batch | pmsmjax M/s | per core | NumPy M/s | "
               "C M/s | pmsmjax/NumPy | pmsmjax/C |")
        lines += [hdr, "|" + "---|" * (hdr.count("|") - 1)]
        for dtype_name in ("float64", "float32"):
            refs = {r["batch"]: r for r in thr.get(f"{dtype_name}/all", {}).get("rows", [])}
            for mode in ("all", "sharded"):
                for row in thr.get(f"{dtype_name}/{mode}", {}).get("rows", []):
                    j = row["pmsmjax"]
                    ref = refs.get(row["batch"], {})
                    nr = ref["numpy"]["steps_per_s"] if "numpy" in ref else float("nan")
                    cr = ref["c"]["steps_per_s"] if "c" in ref else float("nan")
                    name = "XLA threads" if mode == "all" else f"sharded x{row['devices']}"
                    lines.append(
                        f"| {dtype_name} | {name} | {row['batch']} | "
                        f"{_fmt_rate(j['steps_per_s'])} | "
                        f"{_fmt_rate(j['steps_per_s'] / ncores)} | {_fmt_rate(nr)} | "
                        f"{_fmt_rate(cr)} | {j['steps_per_s'] / nr:.1f} | "
                        f"{j['steps_per_s'] / cr:.2f} |")
    g = results.get("grad")
    if g:
        lines += ["", "Gradient of the ISE of the speed error w.r.t. `alpha_s` (one core, "
                  "float64), relative to the forward run of the same loss:", ""]
        hdr = ("| batch | steps | forward ms (CPU) | grad ms (CPU) | grad/forward (CPU) | "
               "grad/forward (wall) | value_and_grad/forward (CPU) | grad compile s | "
               "grad temp MiB |")
        lines += [hdr, "|" + "---|" * (hdr.count("|") - 1)]
        for key, r in g.items():
            if not key.startswith("batch_"):
                continue
            vg = r.get("value_and_grad_over_forward_cpu")
            lines.append(
                f"| {key.split('_')[1]} | {r['steps']} | {r['forward']['cpu_s'] * 1e3:.1f} | "
                f"{r['grad']['cpu_s'] * 1e3:.1f} | {r['grad_over_forward_cpu']:.2f} | "
                f"{r['grad_over_forward']:.2f} | "
                f"{'-' if vg is None else f'{vg:.2f}'} | "
                f"{r['grad']['compile_s']:.2f} | {r['grad']['temp_bytes'] / 2**20:.1f} |")
    fc = results.get("first_compile")
    if fc:
        lines += ["", f"First call of `simulate` in a fresh process (one core, 2000 steps, "
                  f"save_every=1): {fc['first_call_s']:.2f} s, of which compile "
                  f"{fc['first_compile_s']:.2f} s (import pmsmjax {fc['import_s']:.2f} s)."]
    text = "\n".join(lines)
    print(text)
    return text


def targets(results: dict) -> dict:
    """The targets, on one core, judged on CPU time (wall-clock figures alongside)."""
    one64 = {r["batch"]: r for r in results["throughput"]["float64/one"]["rows"]}
    big = max(one64)
    j, c = one64[big]["pmsmjax"], one64[big]["c"]
    out = {}
    out["batch_max_float64_steps_per_s"] = dict(
        batch=big, value=j["steps_per_cpu_s"], value_wall=j["steps_per_s"], target=2e6,
        met=j["steps_per_cpu_s"] >= 2e6)
    out["batch_max_float64_vs_scalar_c"] = dict(
        batch=big, ratio=j["steps_per_cpu_s"] / c["steps_per_cpu_s"],
        ratio_wall=j["steps_per_s"] / c["steps_per_s"], target=1.0,
        met=j["steps_per_cpu_s"] >= c["steps_per_cpu_s"])
    j1 = one64[1]["pmsmjax"]
    out["single_run_steps_per_s"] = dict(value=j1["steps_per_cpu_s"],
                                         value_wall=j1["steps_per_s"], target=1e5,
                                         met=j1["steps_per_cpu_s"] >= 1e5)
    for key, r in results["grad"].items():
        if key.startswith("batch_"):
            out[f"grad_over_forward_{key}"] = dict(
                value=r["grad_over_forward_cpu"], value_wall=r["grad_over_forward"],
                target=5.0, met=r["grad_over_forward_cpu"] <= 5.0)
    fc = results["first_compile"]["first_compile_s"]
    out["first_compile_s"] = dict(value=fc, target=5.0, met=fc < 5.0)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short runs (< 1 min)")
    ap.add_argument("--out", default=None, help="write the results as JSON here")
    ap.add_argument("--worker", nargs=2, metavar=("KIND", "CONFIG"), help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.worker:
        kind, cfg = args.worker[0], json.loads(args.worker[1])
        fn = dict(throughput=worker_throughput, grad=worker_grad,
                  first_compile=worker_first_compile)[kind]
        print(json.dumps(fn(cfg)))
        return

    t_start = time.perf_counter()
    plan = QUICK if args.quick else FULL
    results = dict(machine=machine_info(), quick=args.quick,
                   scenario=dict(preset="zhang750", T_s=T_S, t_ramp=T_RAMP, t_load=T_LOAD,
                                 tau_load=TAU_LOAD, w_final_range_pu=[W_LO, W_HI],
                                 solver="RK4", n_substeps=1, save_every="steps (1 sample)"))
    m = results["machine"]
    print(f"Machine: {m['cpu_model']}, {m['cpu_count']} cores; jax {m['jax']}, jaxlib "
          f"{m['jaxlib']}, numpy {m['numpy']}, Python {m['python']}; {m['gcc']}")
    print(f"Load average at start: {m['loadavg'][0]:.2f}")
    print("Building the C reference:")
    libs = build_c()
    print("Verifying the references against pmsmjax:")
    results["verification"] = verify(libs)

    base = dict(jax_steps={str(k): v for k, v in plan["jax_steps"].items()},
                numpy_steps={str(k): v for k, v in plan["numpy_steps"].items()},
                c_steps={str(k): v for k, v in plan["c_steps"].items()},
                batches=list(plan["batches"]), min_time=plan["min_time"],
                repeats=plan["repeats"], grad_steps=plan["grad_steps"],
                grad_batch=plan["grad_batch"], value_and_grad=plan["value_and_grad"])
    print("First compile (fresh process, one core):")
    results["first_compile"] = run_worker("first_compile", base, "one")
    print(f"    {results['first_compile']['first_compile_s']:.2f} s")
    results["throughput"] = {}
    for dtype_name in ("float64", "float32"):
        for mode in plan["modes"]:
            print(f"Throughput {dtype_name}, {MODE_NAMES[mode]}:")
            cfg = dict(base, dtype=dtype_name, sharded=(mode == "sharded"),
                       c_lib=libs[dtype_name if mode == "one" else dtype_name + "_omp"])
            results["throughput"][f"{dtype_name}/{mode}"] = run_worker(
                "throughput", cfg, mode)
    print("Gradient (one core, float64):")
    results["grad"] = run_worker("grad", dict(base, dtype="float64"), "one")
    results["targets"] = targets(results)
    results["machine"]["loadavg_end"] = os.getloadavg()
    results["total_s"] = time.perf_counter() - t_start
    print()
    results["table"] = print_table(results)
    print()
    print("Targets (one core; judged on CPU time, wall time alongside):")
    for k, v in results["targets"].items():
        print(f"  {'MET ' if v['met'] else 'MISS'} {k}: "
              + ", ".join(f"{a}={b:.4g}" if isinstance(b, float) else f"{a}={b}"
                          for a, b in v.items() if a != "met"))
    print(f"Total benchmark time {results['total_s']:.0f} s; load average at the end "
          f"{results['machine']['loadavg_end'][0]:.2f}.")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(results, indent=1))
        print(f"Wrote {args.out}")


if __name__ == "__main__":
    main()
