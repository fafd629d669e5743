"""Throughput of the feasibility classification (zhang2022 Fig. 1) in pmsmjax vs NumPy.

Task: for B = 100,000 random design points (speed, d/q current, zeta1, w1/w0), find every
equilibrium of the ESO error dynamics (11) and classify the design (feasible: every
nonzero equilibrium unstable). Machine: a strongly salient variant of the zhang750 preset
(L_d = 1.0 mH, L_q = 4.9 mH), so that 1 and 3 nonzero equilibria and stable ones all
occur (with Table I itself every design is feasible; the kernels are branch-free, so
the cost is the same).

Implementations:

- `pmsmjax closed form`: `analysis.classify_designs(method="closed_form")`, one jitted
  element-wise XLA computation (float64 and float32);
- `pmsmjax general`: `method="general"` (bracketing + optimistix bisection + jacfwd);
- `pmsmjax generic`: the observer-generic route `analysis.classify(observer, ...,
  method="generic")` on the LESO (constrained least-squares reduction, bracketing,
  Illinois, Newton polish; works for any observer of the contract);
- `NumPy loop`: the paper's route point by point, as one would write it with NumPy/SciPy:
  (35) as printed, `numpy.roots` of the quartic (36), the Jacobian (37) written out, and
  `numpy.linalg.eigvals` (on a subsample, extrapolated);
- `NumPy batched`: the same, vectorised over points (batched companion-matrix and
  Jacobian eigenvalues with `numpy.linalg.eigvals` on stacks).

The NumPy references (`benchmarks/reference/feasibility_numpy.py`) are independent of
pmsmjax; their classification is compared with pmsmjax's on every point.

Every measurement runs in a fresh subprocess. "one core": `taskset -c 0`,
`XLA_FLAGS=--xla_cpu_multi_thread_eigen=false`, `OMP/OPENBLAS/MKL_NUM_THREADS=1`; "all
cores": no pinning. Reported: points per second from the best of several repeats, by
process CPU time (one core: insensitive to other load on a shared machine) and by wall
time; the first compile (trace + lower + XLA compile) separately.

Usage (from the repository root):

    python -m benchmarks.throughput.feasibility            # full run, about 3 min
    python -m benchmarks.throughput.feasibility --quick    # 20,000 points, one core
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile

import numpy as np

from .. import _harness as h
from ..reference.feasibility_numpy import W2, numpy_batched, numpy_point


MODULE = "benchmarks.throughput.feasibility"
B = 100_000
MOTOR = dict(L_d=1.0e-3, L_q=4.9e-3, psi_f=0.056)  # salient variant of zhang750


def design_points(n, seed=0):
    """Random designs: |w0| in [0.01, 1] p.u. (both signs), |i_d|, |i_q| <= 1 p.u.,
    zeta1 in [0, 5], w1/w0 in [0.02, 2]. SI units."""
    w_r = 5 * 2 * math.pi * 2400 / 60
    I_b = math.sqrt(2) * 4.8
    rng = np.random.default_rng(seed)
    w0 = rng.choice([-1.0, 1.0], n) * rng.uniform(0.01, 1.0, n) * w_r
    i = rng.uniform(-1.0, 1.0, (n, 2)) * I_b
    return dict(w0=w0, i_d=i[:, 0], i_q=i[:, 1], zeta1=rng.uniform(0.0, 5.0, n),
                ratio=rng.uniform(0.02, 2.0, n))


# ---------------------------------------------------------------------------------------
# Workers (one subprocess per measurement)
# ---------------------------------------------------------------------------------------

def worker(impl, dtype, n, repeats, min_time, status_file, sharded=False):
    """One implementation's measurement (in a fresh process): its rate by CPU and wall
    time, and its classification saved to `status_file`."""
    pts = {k: v[:n] for k, v in design_points(max(n, B)).items()}  # the same points for every n
    res = dict(impl=impl, dtype=dtype, n=n)
    if impl.startswith("pmsmjax"):
        import jax
        import jax.numpy as jnp

        import pmsmjax as pj
        from pmsmjax import analysis

        dt = jnp.float32 if dtype == "float32" else jnp.float64
        motor = pj.PMSMParams(R_s=0.78, n_p=5.0, **MOTOR)
        method = "closed_form" if impl == "pmsmjax_closed" else "general"
        args = [jnp.asarray(pts[k], dt) for k in ("w0", "zeta1", "ratio")]
        i_dq = jnp.stack([jnp.asarray(pts["i_d"], dt), jnp.asarray(pts["i_q"], dt)], -1)
        if method == "closed_form":
            from pmsmjax.analysis._closed_form import _closed_form_classify

            cargs = [args[0], i_dq[:, 0], i_dq[:, 1], args[1], args[2],
                     jnp.asarray(1.0, dt), jnp.asarray(W2, dt)] + [
                jnp.asarray(MOTOR[k], dt) for k in ("L_d", "L_q", "psi_f")]
            if sharded:  # split the batch over one XLA host device per core
                from jax.sharding import Mesh, NamedSharding, PartitionSpec

                mesh = Mesh(np.array(jax.devices()), ("b",))
                sh = NamedSharding(mesh, PartitionSpec("b"))
                cargs = [jax.device_put(v, sh) if v.ndim else v for v in cargs]
                res["devices"] = len(jax.devices())
            stages, comp = h.lower_compile(jax.jit(lambda *a: _closed_form_classify(*a)),
                                           *cargs)
            res.update(trace_s=stages["trace_lower_s"], compile_s=stages["compile_s"])
            run = lambda: jax.block_until_ready(comp(*cargs))  # noqa: E731
            # the public entry point gives the same answer (checked below)
            out = analysis.classify_designs(motor, args[0], i_dq, args[1], args[2],
                                            w2=W2, dtype=dt)
        elif impl == "pmsmjax_generic":
            # the observer-generic route (any observer): the LESO with the same designs
            @jax.jit
            def generic(w0, i0, z1, r):
                def one(w, i, a, b):
                    obs = pj.LESOObserver(motor, pj.ESODesign.fixed_ratio(a, b, w2=W2))
                    return analysis.classify(obs, motor, w, i, method="generic")
                return jax.vmap(one)(w0, i0, z1, r)

            first_s, out = h.first_call(lambda: generic(args[0], i_dq, args[1], args[2]))
            res.update(first_call_s=first_s)
            run = lambda: jax.block_until_ready(  # noqa: E731
                generic(args[0], i_dq, args[1], args[2]))
        else:
            first_s, out = h.first_call(lambda: analysis.classify_designs(
                motor, args[0], i_dq, args[1], args[2], w2=W2, method="general", n_grid=128,
                dtype=dt))
            res.update(first_call_s=first_s)
            run = lambda: jax.block_until_ready(analysis.classify_designs(  # noqa: E731
                motor, args[0], i_dq, args[1], args[2], w2=W2, method="general",
                n_grid=128, dtype=dt))
        first = run()
        if method == "closed_form":
            assert np.array_equal(np.asarray(first.status), np.asarray(out.status))
        status, nnz = np.asarray(out.status), np.asarray(out.n_nonzero)
    elif impl == "numpy_loop":
        def run():
            return [numpy_point(pts["w0"][k], pts["i_d"][k], pts["i_q"][k], pts["zeta1"][k],
                                pts["ratio"][k], **MOTOR) for k in range(n)]
        out = run()
        status = np.array([o[0] for o in out])
        nnz = np.array([o[1] for o in out])
    else:
        def run():
            return numpy_batched(pts["w0"], pts["i_d"], pts["i_q"], pts["zeta1"],
                                 pts["ratio"], **MOTOR)
        status, nnz = run()
    t = h.steady(run, repeats=repeats, per_sample=min_time)
    cpu, wall = t.cpu_s, t.best_s
    res.update(cpu_s=cpu, wall_s=wall, pts_per_s_cpu=n / cpu, pts_per_s_wall=n / wall,
               infeasible=float(np.mean(status == 1)))
    np.savez(status_file, status=status, n_nonzero=nnz)
    return res


def run_subprocess(impl, dtype, n, mode, repeats, min_time):
    """`worker` in a fresh process under `mode` ("one": pinned, single-threaded; "all";
    "sharded": one XLA host device per core); returns (its row, its classification)."""
    env = h.mode_env(mode)
    with tempfile.TemporaryDirectory() as tmp:
        status_file = os.path.join(tmp, "status.npz")
        args = ["--worker", impl, "--dtype", dtype, "--n", str(n), "--repeats", str(repeats),
                "--min-time", str(min_time), "--status-file", status_file]
        child = h.module_child(MODULE, *args, *(["--sharded"] if mode == "sharded" else []),
                               env=env, pinned=mode == "one")
        with np.load(status_file) as f:
            st = dict(f)
    return dict(child.result, mode=mode), st


def main(argv=None) -> int:
    ap = h.parser(__doc__, MODULE, quick_help="20,000 points on one core (and fewer for "
                  "the slow routes), two repeats")
    for name, kw in (("--worker", {}), ("--dtype", dict(default="float64")),
                     ("--n", dict(type=int, default=B)),
                     ("--repeats", dict(type=int, default=5)),
                     ("--min-time", dict(type=float, default=1.0)), ("--status-file", {}),
                     ("--sharded", dict(action="store_true"))):
        ap.add_argument(name, help=argparse.SUPPRESS, **kw)
    a = ap.parse_args(argv)
    if a.worker:
        h.worker_result(worker(a.worker, a.dtype, a.n, a.repeats, a.min_time,
                               a.status_file, a.sharded))
        return 0

    n = 20_000 if a.quick else B
    rep, mt = (2, 0.2) if a.quick else (7, 1.0)
    n_loop = 300 if a.quick else 3000
    n_general = 1000 if a.quick else 10000
    plan = [("pmsmjax_closed", "float64", n, "one"), ("pmsmjax_closed", "float32", n, "one")]
    if not a.quick:
        plan += [("pmsmjax_closed", "float64", n, "all"), ("pmsmjax_closed", "float32", n, "all"),
                 ("pmsmjax_closed", "float64", n, "sharded"),
                 ("pmsmjax_closed", "float32", n, "sharded")]
    plan += [("pmsmjax_general", "float64", n_general, "one")]
    if not a.quick:
        plan += [("pmsmjax_generic", "float64", n_general, "one")]
    plan += [("numpy_batched", "float64", n, "one")]
    if not a.quick:
        plan += [("numpy_batched", "float64", n, "all")]
    plan += [("numpy_loop", "float64", n_loop, "one")]
    print(h.machine_line())
    rows, statuses = [], {}
    for impl, dtype, m, mode in plan:
        print(f"  running {impl} {dtype} n={m} ({mode})", flush=True)
        res, st = run_subprocess(impl, dtype, m, mode, rep, mt)
        rows.append(res)
        statuses[(impl, dtype, mode)] = st
    # agreement with the float64 closed form (on the common leading points)
    ref = statuses[("pmsmjax_closed", "float64", "one")]
    for r in rows:
        st = statuses[(r["impl"], r["dtype"], r["mode"])]
        m = len(st["status"])
        r["agree_status"] = float(np.mean(st["status"] == ref["status"][:m]))
        r["agree_n_nonzero"] = float(np.mean(st["n_nonzero"] == ref["n_nonzero"][:m]))
    base = {m: next((r for r in rows if r["impl"] == "numpy_batched" and r["mode"] == m),
                    None) for m in ("one", "all")}
    base["sharded"] = base["all"]
    loop = next(r for r in rows if r["impl"] == "numpy_loop")

    def rate(r):
        return r["pts_per_s_cpu"] if r["mode"] == "one" else r["pts_per_s_wall"]

    def first(r):
        if r.get("compile_s") is not None:
            return f"{r['trace_s'] + r['compile_s']:.2f}"
        return f"{r['first_call_s']:.1f} (1st call)" if "first_call_s" in r else "-"

    print()
    h.table(rows, [
        ("implementation", lambda r: r["impl"] + ("" if r["n"] == n else f" (n={r['n']})"),
         ""), ("dtype", "dtype", ""), ("cores", "mode", ""),
        ("points/s (CPU time)", "pts_per_s_cpu", ".3g"),
        ("points/s (wall)", "pts_per_s_wall", ".3g"),
        ("vs NumPy batched",
         lambda r: base[r["mode"]] and f"{rate(r) / rate(base[r['mode']]):.1f}x", ""),
        ("vs NumPy loop", lambda r: f"{rate(r) / loop['pts_per_s_cpu']:.0f}x", ""),
        ("first compile (s)", first, ""),
        ("agrees with f64", lambda r: f"{r['agree_status']:.4%}", "")])
    h.write_report(a.json, rows, benchmark=MODULE, batch=n, motor=MOTOR)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
