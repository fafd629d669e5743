"""Closed-loop throughput benchmark of `pmsmjax.simulate`, side by side with NumPy and C.

Scenario (the same for every implementation): the `zhang750` preset under sensored speed
control (`FOC.from_drive`, `SensoredObserver`), T_s = 125 us, RK4 plant with one substep,
ZOH. Speed reference ramps from 0 to `w_final` over [0, 0.1] s, load torque steps from 0
to 1 N m at 0.15 s. A batch of B drives differs in `w_final` (0.2 ... 0.8 x rated), so
`jax.vmap` runs B closed loops at once. Throughput runs keep one sample of the trajectory
(`save_every` = number of steps) and the ISE integral; memory does not grow with the run.

The references implement the identical discrete algorithm:

- `benchmarks/reference/closed_loop_numpy.py`: batched NumPy arrays, Python loop over time;
- `benchmarks/reference/closed_loop.c`: scalar C, loop over drives and time, `gcc -O3
  -march=native` (float64 and float32 builds, plus an OpenMP build for the all-cores
  rows).

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

Usage (from the repository root; `make bench` runs the full benchmark):

    python -m benchmarks.throughput.simulate            # full run, about 4 min
    python -m benchmarks.throughput.simulate --quick    # under a minute
"""


from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from .. import _harness as h
from ..reference import build_c, c_simulate


T_S = 125e-6
T_RAMP, T_LOAD, TAU_LOAD = 0.1, 0.15, 1.0
W_LO, W_HI = 0.2, 0.8  # w_final range, fraction of rated speed
BATCHES = (1, 64, 1024, 4096)
# jaxlib 0.10 parses --xla_cpu_multi_thread_eigen; "intra_op_parallelism_threads=1" is not
# an XLA flag: XLA_FLAGS parsing stops at the first token without "--" (it is taken for a
# file name) and silently drops every flag after it. The pinning (taskset) is what
# restricts a run to one core.

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
MODULE = "benchmarks.throughput.simulate"


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


def make_observer(name: str | None):
    """The loop's observer: sensored (`None`) or the registry's observer `name` with its
    default design on the scenario's drive (a sensorless loop)."""
    import pmsmjax as pj
    from pmsmjax.observers import make_observer as make

    return pj.SensoredObserver() if name is None else make(name, drive_and_controller()[0])


def make_pmsmjax_run(dtype_name: str, n_steps: int, save_every: int | None = None,
                     params=None, observer: str | None = None):
    """`f(w_final[B]) -> (ise_w, w_m, i_dq, status)` for a batch, not yet jitted.

    `params(foc, gain) -> foc` may replace controller fields (for the gradient);
    `observer`: see `make_observer`."""
    import jax.numpy as jnp

    import pmsmjax as pj

    drive, foc = drive_and_controller()
    obs = make_observer(observer)
    dt = jnp.float32 if dtype_name == "float32" else jnp.float64
    if dt == jnp.float32:
        drive, foc, obs = pj.astype(drive, dt), pj.astype(foc, dt), pj.astype(obs, dt)
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


def c_rate(steps: int, dtype_name: str = "float64") -> float:
    """Steps per second of one drive of the scalar C reference (best of five)."""
    lib = build_c(verbose=False)[dtype_name]
    drive, foc = drive_and_controller()
    p, w = reference_params(drive, foc), w_finals(1)
    c_simulate(lib, p, w, steps)
    return h.steady(lambda: c_simulate(lib, p, w, steps), repeats=5).rate(steps)


# ---------------------------------------------------------------------------------------
# Verification of the references against pmsmjax
# ---------------------------------------------------------------------------------------

def verify(libs: dict, n_steps=2000, B=4, verbose=True, observer: str | None = None
           ) -> dict:
    """Final (i_d, i_q, w_m) and ISE of pmsmjax, NumPy and C for a few drives (the
    sensorless loop of `observer`: pmsmjax and C)."""
    import jax

    from ..reference import closed_loop_numpy

    drive, foc = drive_and_controller()
    p = reference_params(drive, foc)
    res = {}
    for dtype_name in ("float64", "float32"):
        dt = np.float32 if dtype_name == "float32" else np.float64
        w = w_finals(B, dt)
        # pmsmjax records the state at t_k before the step: run one step more and take
        # the last sample = the state after n_steps periods.
        one_long = make_pmsmjax_run(dtype_name, n_steps + 1, save_every=1,
                                    observer=observer)
        one = make_pmsmjax_run(dtype_name, n_steps, observer=observer)
        _, w_m, i_dq, _ = jax.jit(jax.vmap(one_long))(w)
        ise, _, _, status = jax.jit(jax.vmap(one))(w)
        jx = np.stack([np.asarray(i_dq[:, -1, 0]), np.asarray(i_dq[:, -1, 1]),
                       np.asarray(w_m[:, -1]), np.asarray(ise)], -1).astype(np.float64)
        c_out = c_simulate(libs[dtype_name], p, w, n_steps)[:, [0, 1, 3, 4]]
        scale = np.maximum(np.abs(jx), 1.0)
        # None: the NumPy reference has no observer, so it checks the sensored loop only
        err_np = None if observer else float(np.max(np.abs(
            closed_loop_numpy.simulate(p, w, n_steps, dtype=dt)[:, [0, 1, 3, 4]] - jx) / scale))
        err_c = float(np.max(np.abs(c_out - jx) / scale))
        res[dtype_name] = dict(
            n_steps=n_steps, batch=B, jax_dtype=str(w_m.dtype), ok=bool(np.all(status == 0)),
            max_rel_err_numpy=err_np, max_rel_err_c=err_c, pmsmjax_final=jx.tolist())
        if verbose:
            print(f"  {dtype_name}: pmsmjax output dtype {w_m.dtype}; max relative "
                  f"difference of final (i_d, i_q, w_m, ISE_w) over {B} drives after "
                  f"{n_steps} steps: NumPy "
                  f"{'not run (no observer)' if err_np is None else f'{err_np:.2e}'}, "
                  f"C {err_c:.2e}")
    tol = 1e-9
    if (res["float64"]["max_rel_err_numpy"] or 0.0) > tol or res["float64"]["max_rel_err_c"] > tol:
        raise SystemExit(f"Verification failed: the references differ from pmsmjax by more "
                         f"than {tol} in float64: {res['float64']}")
    if res["float32"]["jax_dtype"] != "float32":
        raise SystemExit("pmsmjax did not run in float32 with float32 inputs.")
    return res


# ---------------------------------------------------------------------------------------
# Workers (each in a fresh process)
# ---------------------------------------------------------------------------------------

def _timing(t: h.Timing, work: float) -> dict:
    return dict(run_s=t.best_s, run_median_s=t.median_s, cpu_s=t.cpu_s, repeats=t.samples,
                steps_per_s=t.rate(work), steps_per_cpu_s=t.cpu_rate(work))


def worker_throughput(cfg: dict) -> dict:
    import jax

    from ..reference import closed_loop_numpy

    dtype_name = cfg["dtype"]
    dt = np.float32 if dtype_name == "float32" else np.float64
    drive, foc = drive_and_controller()
    p = reference_params(drive, foc)
    rows = []
    sharded = cfg.get("sharded", False)
    reps = dict(repeats=cfg["repeats"], min_time=cfg["min_time"])
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
        stages, compiled = h.lower_compile(jax.jit(jax.vmap(make_pmsmjax_run(
            dtype_name, N, observer=cfg.get("observer")))), w)
        first_s, out = h.first_call(lambda: compiled(w))
        assert str(out[1].dtype) == dtype_name, out[1].dtype
        assert bool(np.all(np.asarray(out[3]) == 0)), "a benchmark run diverged"
        t = h.steady(lambda: compiled(w), **reps)
        row["pmsmjax"] = dict(steps=N, save_every=N, first_run_s=first_s,
                              out_dtype=str(out[1].dtype), **stages, **_timing(t, B * N))
        if sharded:
            rows.append(row)
            print(f"    B={B:5d}: pmsmjax {row['pmsmjax']['steps_per_s'] / 1e6:7.3f} M/s "
                  f"on {row['devices']} devices", flush=True)
            continue
        # --- NumPy (the sensored loop only)
        Nn = cfg["numpy_steps"].get(str(B))
        if Nn:
            closed_loop_numpy.simulate(p, w, 2, dtype=dt)
            t = h.steady(lambda: closed_loop_numpy.simulate(p, w, Nn, dtype=dt),
                         repeats=max(1, cfg["repeats"] // 2), min_time=cfg["min_time"])
            row["numpy"] = dict(steps=Nn, **_timing(t, B * Nn))
        # --- C
        Nc = cfg["c_steps"][str(B)]
        lib = cfg["c_lib"]
        c_simulate(lib, p, w, 2)
        t = h.steady(lambda: c_simulate(lib, p, w, Nc), **reps)
        row["c"] = dict(steps=Nc, lib=os.path.basename(lib), **_timing(t, B * Nc))
        rows.append(row)
        numpy = f"NumPy {row['numpy']['steps_per_s'] / 1e6:7.3f} M/s, " if Nn else ""
        print(f"    B={B:5d}: pmsmjax {row['pmsmjax']['steps_per_s'] / 1e6:7.3f} M/s, "
              f"{numpy}C {row['c']['steps_per_s'] / 1e6:7.3f} M/s", flush=True)
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
            stages, compiled = h.lower_compile(jax.jit(fn), a0, w)
            _, val = h.first_call(lambda: compiled(a0, w))
            t = h.steady(lambda: compiled(a0, w), repeats=cfg["repeats"],
                         min_time=cfg["min_time"])
            res[name] = dict(compile_s=stages["trace_lower_s"] + stages["compile_s"],
                             run_s=t.best_s, run_median_s=t.median_s, cpu_s=t.cpu_s,
                             repeats=t.samples, temp_bytes=stages["temp_bytes"],
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
              f"{res['grad_over_forward']:.2f})", flush=True)
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


def worker_single(cfg: dict) -> dict:
    """One drive's closed loop as a plain script runs it (`import pmsmjax`, `jax.jit`):
    the first call and the best of five, in steps per second."""
    import jax

    steps = cfg.get("steps", 8000)
    run = jax.jit(make_pmsmjax_run("float64", steps))
    w = float(w_finals(1)[0])
    first_s, _ = h.first_call(lambda: run(w))
    t = h.steady(lambda: run(w), repeats=5)
    return dict(steps=steps, first_s=first_s, second_s=t.best_s, steps_per_s=t.rate(steps))


WORKERS = dict(throughput=worker_throughput, grad=worker_grad,
               first_compile=worker_first_compile, single=worker_single)


def run_worker(kind: str, cfg: dict, mode: str = "one", env: dict | None = None) -> dict:
    """Run worker `kind` with `cfg` in a fresh process under `mode` (`harness.MODES`; "one"
    pins it to core 0), or with the environment `env` as given."""
    env = h.mode_env(mode) if env is None else env
    load0 = os.getloadavg()[0]
    child = h.module_child(MODULE, "--worker", kind, json.dumps(cfg), env=env,
                           pinned=mode == "one")
    for line in child.stdout.splitlines()[:-1]:
        print(line)
    res = child.result
    if isinstance(res, dict):
        res["loadavg_before_after"] = [load0, os.getloadavg()[0]]
    return res


# ---------------------------------------------------------------------------------------
# Tables, targets, driver
# ---------------------------------------------------------------------------------------

def _m(x):
    return f"{x / 1e6:.3f}"


def print_tables(results: dict) -> str:
    thr, ncores = results["throughput"], os.cpu_count()
    texts = []
    rows = [dict(dtype=dt, **r) for dt in ("float64", "float32")
            for r in thr.get(f"{dt}/one", {}).get("rows", [])]
    texts.append(h.table(rows, [
        ("dtype", "dtype", ""), ("batch", "batch", "d"),
        ("pmsmjax M/s", lambda r: _m(r["pmsmjax"]["steps_per_cpu_s"]), ""),
        ("NumPy M/s", lambda r: _m(r["numpy"]["steps_per_cpu_s"]), ""),
        ("C M/s", lambda r: _m(r["c"]["steps_per_cpu_s"]), ""),
        ("pmsmjax/NumPy", lambda r: r["pmsmjax"]["steps_per_cpu_s"]
         / r["numpy"]["steps_per_cpu_s"], ".1f"),
        ("pmsmjax/C", lambda r: r["pmsmjax"]["steps_per_cpu_s"]
         / r["c"]["steps_per_cpu_s"], ".2f"),
        ("pmsmjax wall M/s", lambda r: _m(r["pmsmjax"]["steps_per_s"]), ""),
        ("C wall M/s", lambda r: _m(r["c"]["steps_per_s"]), ""),
        ("compile s", lambda r: r["pmsmjax"]["trace_lower_s"] + r["pmsmjax"]["compile_s"],
         ".2f"),
        ("temp MiB", lambda r: r["pmsmjax"]["temp_bytes"] / 2**20, ".1f")],
        title="One core (pinned): drive-steps per second from the process CPU time (best "
              "of the repeats); wall time alongside."))
    rows = []
    for dt in ("float64", "float32"):
        refs = {r["batch"]: r for r in thr.get(f"{dt}/all", {}).get("rows", [])}
        for mode in ("all", "sharded"):
            for r in thr.get(f"{dt}/{mode}", {}).get("rows", []):
                ref = refs.get(r["batch"], {})
                rows.append(dict(
                    dtype=dt, batch=r["batch"], rate=r["pmsmjax"]["steps_per_s"],
                    mode="XLA threads" if mode == "all" else f"sharded x{r['devices']}",
                    numpy=ref.get("numpy", {}).get("steps_per_s"),
                    c=ref.get("c", {}).get("steps_per_s")))
    if rows:
        print()
        texts.append(h.table(rows, [
            ("dtype", "dtype", ""), ("pmsmjax mode", "mode", ""), ("batch", "batch", "d"),
            ("pmsmjax M/s", lambda r: _m(r["rate"]), ""),
            ("per core", lambda r: _m(r["rate"] / ncores), ""),
            ("NumPy M/s", lambda r: r["numpy"] and _m(r["numpy"]), ""),
            ("C M/s", lambda r: r["c"] and _m(r["c"]), ""),
            ("pmsmjax/NumPy", lambda r: r["numpy"] and r["rate"] / r["numpy"], ".1f"),
            ("pmsmjax/C", lambda r: r["c"] and r["rate"] / r["c"], ".2f")],
            title=f"All {ncores} cores (no pinning): wall time; C with OpenMP over the "
                  f"drives, NumPy single-threaded."))
    g = results.get("grad") or {}
    rows = [dict(batch=k.split("_")[1], **r) for k, r in g.items() if k.startswith("batch_")]
    if rows:
        print()
        texts.append(h.table(rows, [
            ("batch", "batch", ""), ("steps", "steps", "d"),
            ("forward ms (CPU)", lambda r: r["forward"]["cpu_s"] * 1e3, ".1f"),
            ("grad ms (CPU)", lambda r: r["grad"]["cpu_s"] * 1e3, ".1f"),
            ("grad/forward (CPU)", "grad_over_forward_cpu", ".2f"),
            ("grad/forward (wall)", "grad_over_forward", ".2f"),
            ("value_and_grad/forward (CPU)", "value_and_grad_over_forward_cpu", ".2f"),
            ("grad compile s", lambda r: r["grad"]["compile_s"], ".2f"),
            ("grad temp MiB", lambda r: r["grad"]["temp_bytes"] / 2**20, ".1f")],
            title="Gradient of the ISE of the speed error w.r.t. `alpha_s` (one core, "
                  "float64), against the forward run of the same loss:"))
    fc = results.get("first_compile")
    if fc:
        line = (f"First call of `simulate` in a fresh process (one core, 2000 steps, "
                f"save_every=1): {fc['first_call_s']:.2f} s, of which compile "
                f"{fc['first_compile_s']:.2f} s (import pmsmjax {fc['import_s']:.2f} s).")
        print("\n" + line)
        texts.append(line)
    return "\n\n".join(texts)


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
    j1, c1 = one64[1]["pmsmjax"], one64[1]["c"]
    out["single_run_steps_per_s"] = dict(value=j1["steps_per_cpu_s"],
                                         value_wall=j1["steps_per_s"], target=1e5,
                                         met=j1["steps_per_cpu_s"] >= 1e5)
    out["single_run_vs_scalar_c"] = dict(ratio=j1["steps_per_cpu_s"] / c1["steps_per_cpu_s"],
                                         ratio_wall=j1["steps_per_s"] / c1["steps_per_s"])
    for key, r in results["grad"].items():
        if key.startswith("batch_"):
            out[f"grad_over_forward_{key}"] = dict(
                value=r["grad_over_forward_cpu"], value_wall=r["grad_over_forward"],
                target=5.0, met=r["grad_over_forward_cpu"] <= 5.0)
    fc = results["first_compile"]["first_compile_s"]
    out["first_compile_s"] = dict(value=fc, target=5.0, met=fc < 5.0)
    return out


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE)
    ap.add_argument("--worker", nargs=2, metavar=("KIND", "CONFIG"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        kind, cfg = args.worker[0], json.loads(args.worker[1])
        h.worker_result(WORKERS[kind](cfg))
        return 0

    t_start = time.perf_counter()
    plan = QUICK if args.quick else FULL
    print(h.machine_line())
    print("Building the C reference:")
    libs = build_c()
    print("Verifying the references against pmsmjax:")
    results = dict(quick=args.quick, verification=verify(libs),
                   scenario=dict(preset="zhang750", T_s=T_S, t_ramp=T_RAMP, t_load=T_LOAD,
                                 tau_load=TAU_LOAD, w_final_range_pu=[W_LO, W_HI],
                                 solver="RK4", n_substeps=1, save_every="steps (1 sample)"))
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
            print(f"Throughput {dtype_name}, {h.MODES[mode]}:")
            cfg = dict(base, dtype=dtype_name, sharded=(mode == "sharded"),
                       c_lib=libs[dtype_name if mode == "one" else dtype_name + "_omp"])
            results["throughput"][f"{dtype_name}/{mode}"] = run_worker(
                "throughput", cfg, mode)
    print("Gradient (one core, float64):")
    results["grad"] = run_worker("grad", dict(base, dtype="float64"), "one")
    results["targets"] = targets(results)
    results["total_s"] = time.perf_counter() - t_start
    print()
    results["table"] = print_tables(results)
    print("\nTargets (one core; judged on CPU time, wall time alongside):")
    for k, v in results["targets"].items():
        state = "" if "met" not in v else ("MET  " if v["met"] else "MISS ")
        print(f"  {state}{k}: " + ", ".join(
            f"{a}={b:.4g}" if isinstance(b, float) else f"{a}={b}"
            for a, b in v.items() if a != "met"))
    print(f"Total benchmark time {results['total_s']:.0f} s; load average at the end "
          f"{os.getloadavg()[0]:.2f}.")
    h.write_report(args.json, results.pop("throughput"), benchmark=MODULE, **results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
