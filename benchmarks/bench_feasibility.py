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

The NumPy references are independent of pmsmjax (everything written out here); their
classification is compared with pmsmjax's on every point before timing is trusted.

Every measurement runs in a fresh subprocess. "one core": `taskset -c 0`,
`XLA_FLAGS=--xla_cpu_multi_thread_eigen=false`, `OMP/OPENBLAS/MKL_NUM_THREADS=1`; "all
cores": no pinning. Reported: points per second from the best of several repeats, by
process CPU time (one core: insensitive to other load on a shared machine) and by wall
time; the first compile (trace + lower + XLA compile) separately.

Usage:

    .venv/bin/python benchmarks/bench_feasibility.py [--quick] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


HERE = Path(__file__).resolve().parent
OUT = HERE / "out"
ONE_CORE_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false"
B = 100_000
W2 = 2 * math.pi * 50.0
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
# NumPy references (the paper's route, written out)
# ---------------------------------------------------------------------------------------

J2 = np.array([[0.0, -1.0], [1.0, 0.0]])


def _gains(w0, i_d, i_q, zeta1, ratio, L_d, L_q, psi_f):
    psi = np.array([(L_d - L_q) * i_d + psi_f, -(L_d - L_q) * i_q])
    n2 = psi @ psi
    w1 = ratio * abs(w0)
    c = w1 ** 2 / w0 - w0
    G1 = (2 * zeta1 * w1 * np.outer(psi, psi) + c * np.outer(J2 @ psi, psi)) / n2
    row = np.array([psi[1], -psi[0]]) / n2
    return psi, G1, 2 * W2 * row, W2 ** 2 * row  # zeta2 = 1


def _p35(w0, i_d, i_q, psi, G1, L_d, L_q, psi_f):
    beta = -psi[1] / psi[0]
    g1, g2 = G1[0, 0], G1[1, 0]
    dL, b2 = 0.5 * (L_d - L_q), beta ** 2 + 1
    p1 = dL * ((beta * i_d - i_q) * w0 + b2 * (g1 * i_d - g2 * i_q))
    p2 = dL * ((beta * i_q + i_d) * w0 + b2 * (g2 * i_d + g1 * i_q))
    p3 = psi_f * (beta * w0 + b2 * g1)
    p4 = psi_f * (w0 + b2 * g2)
    return p1, p2, p3, p4, -p1 - p3


def _rot(t):
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


def numpy_point(w0, i_d, i_q, zeta1, ratio, L_d, L_q, psi_f):
    """(status, n_nonzero) of one design: (35), numpy.roots of (36), (37), eigvals."""
    i0 = np.array([i_d, i_q])
    psi, G1, g2, g3 = _gains(w0, i_d, i_q, zeta1, ratio, L_d, L_q, psi_f)
    p1, p2, p3, p4, p5 = _p35(w0, i_d, i_q, psi, G1, L_d, L_q, psi_f)
    t = np.roots([p1 - p3 + p5, 2 * p4 - 4 * p2, 2 * p5 - 6 * p1, 4 * p2 + 2 * p4,
                  p1 + p3 + p5])
    L = np.diag([L_d, L_q])
    pf = np.array([psi_f, 0.0])
    M = w0 * J2 + G1
    n, stable = 0, False
    for root in t:
        if abs(root.imag) > 1e-7 * (1 + abs(root)):
            continue
        th = 2 * np.arctan(root.real)
        if abs(th) < 1e-6:
            continue
        n += 1
        R = _rot(th)
        e0 = L @ i0 + pf - R @ (L @ R.T @ i0 + pf)
        de0 = -(J2 @ R @ L @ R.T @ i0 - R @ L @ R.T @ J2 @ i0 + J2 @ R @ pf)
        x = -np.linalg.solve(M, G1 @ e0)
        e = e0 + x
        wf = w0 - g2 @ e + g2 @ e
        Jx = J2 @ x
        A = np.zeros((4, 4))
        A[:2, :2] = -wf * J2 - np.outer(Jx, g2) - G1
        A[:2, 2] = -Jx * (g2 @ de0) - G1 @ de0
        A[:2, 3] = Jx
        A[2] = [-g2[0], -g2[1], -g2 @ de0, 1.0]
        A[3] = [-g3[0], -g3[1], -g3 @ de0, 0.0]
        stable |= bool(np.max(np.linalg.eigvals(A).real) < 0)
    return int(stable), n


def numpy_batched(w0, i_d, i_q, zeta1, ratio, L_d, L_q, psi_f):
    """The same, vectorised over points; returns (status, n_nonzero) arrays."""
    nb = w0.shape[0]
    dL = L_d - L_q
    pd, pq = dL * i_d + psi_f, -dL * i_q
    n2 = pd ** 2 + pq ** 2
    w1 = ratio * np.abs(w0)
    c = w1 ** 2 / w0 - w0
    k = 2 * zeta1 * w1
    # G1 = (k psi psi^T + c (J psi) psi^T) / n2, J psi = (-pq, pd)
    G1 = np.empty((nb, 2, 2))
    G1[:, 0, 0] = (k * pd - c * pq) * pd / n2
    G1[:, 0, 1] = (k * pd - c * pq) * pq / n2
    G1[:, 1, 0] = (k * pq + c * pd) * pd / n2
    G1[:, 1, 1] = (k * pq + c * pd) * pq / n2
    row = np.stack([pq, -pd], -1) / n2[:, None]
    g2, g3 = 2 * W2 * row, W2 ** 2 * row
    beta = -pq / pd
    g1c, g2c = G1[:, 0, 0], G1[:, 1, 0]
    h, b2 = 0.5 * dL, beta ** 2 + 1
    p1 = h * ((beta * i_d - i_q) * w0 + b2 * (g1c * i_d - g2c * i_q))
    p2 = h * ((beta * i_q + i_d) * w0 + b2 * (g2c * i_d + g1c * i_q))
    p3 = psi_f * (beta * w0 + b2 * g1c)
    p4 = psi_f * (w0 + b2 * g2c)
    p5 = -p1 - p3
    coef = np.stack([p1 - p3 + p5, 2 * p4 - 4 * p2, 2 * p5 - 6 * p1, 4 * p2 + 2 * p4,
                     p1 + p3 + p5], -1)
    comp = np.zeros((nb, 4, 4))  # companion matrices of the quartic
    comp[:, 0, :] = -coef[:, 1:] / coef[:, :1]
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    t = np.linalg.eigvals(comp)  # (nb, 4)
    real = np.abs(t.imag) <= 1e-7 * (1 + np.abs(t))
    th = 2 * np.arctan(t.real)
    ok = real & (np.abs(th) >= 1e-6)
    # equilibrium states and Jacobians for all 4 candidate roots at once
    ct, st = np.cos(th), np.sin(th)
    c2, s2 = np.cos(2 * th), np.sin(2 * th)
    hi = 0.5 * dL
    Id, Iq = i_d[:, None], i_q[:, None]
    e0 = np.stack([hi * (Id - c2 * Id - s2 * Iq) + psi_f * (1 - ct),
                   hi * (-Iq - s2 * Id + c2 * Iq) - psi_f * st], -1)
    de0 = np.stack([hi * (2 * s2 * Id - 2 * c2 * Iq) + psi_f * st,
                    hi * (-2 * c2 * Id - 2 * s2 * Iq) - psi_f * ct], -1)
    M = G1 + w0[:, None, None] * J2
    G1e = np.einsum("bij,bkj->bki", G1, e0)
    x = -np.linalg.solve(M[:, None], G1e[..., None])[..., 0]
    Jx = np.stack([-x[..., 1], x[..., 0]], -1)
    gd = np.einsum("bj,bkj->bk", g2, de0)
    hd = np.einsum("bj,bkj->bk", g3, de0)
    Gd = np.einsum("bij,bkj->bki", G1, de0)
    A = np.zeros((nb, 4, 4, 4))
    w = w0[:, None]
    A[..., 0, 0] = -Jx[..., 0] * g2[:, None, 0] - G1[:, None, 0, 0]
    A[..., 0, 1] = w - Jx[..., 0] * g2[:, None, 1] - G1[:, None, 0, 1]
    A[..., 1, 0] = -w - Jx[..., 1] * g2[:, None, 0] - G1[:, None, 1, 0]
    A[..., 1, 1] = -Jx[..., 1] * g2[:, None, 1] - G1[:, None, 1, 1]
    A[..., :2, 2] = -Jx * gd[..., None] - Gd
    A[..., :2, 3] = Jx
    A[..., 2, 0], A[..., 2, 1] = -g2[:, None, 0], -g2[:, None, 1]
    A[..., 2, 2], A[..., 2, 3] = -gd, 1.0
    A[..., 3, 0], A[..., 3, 1] = -g3[:, None, 0], -g3[:, None, 1]
    A[..., 3, 2] = -hd
    stab = np.max(np.linalg.eigvals(A).real, -1) < 0
    return np.any(stab & ok, -1).astype(np.int32), np.sum(ok, -1)


# ---------------------------------------------------------------------------------------
# Workers (one subprocess per measurement)
# ---------------------------------------------------------------------------------------

def _best(fn, repeats, min_time):
    best_cpu = best_wall = math.inf
    for _ in range(repeats):
        n_rep, c0, w0 = 0, time.process_time(), time.perf_counter()
        while True:
            fn()
            n_rep += 1
            wall = time.perf_counter() - w0
            if wall >= min_time:
                break
        best_cpu = min(best_cpu, (time.process_time() - c0) / n_rep)
        best_wall = min(best_wall, wall / n_rep)
    return best_cpu, best_wall


def worker(impl, dtype, n, repeats, min_time, status_file, sharded=False):
    pts = {k: v[:n] for k, v in design_points(B).items()}  # the same points for every n
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
            from pmsmjax.analysis._feasibility import _closed_form_classify

            cargs = [args[0], i_dq[:, 0], i_dq[:, 1], args[1], args[2],
                     jnp.asarray(1.0, dt), jnp.asarray(W2, dt)] + [
                jnp.asarray(MOTOR[k], dt) for k in ("L_d", "L_q", "psi_f")]
            if sharded:  # split the batch over one XLA host device per core
                from jax.sharding import Mesh, NamedSharding, PartitionSpec

                mesh = Mesh(np.array(jax.devices()), ("b",))
                sh = NamedSharding(mesh, PartitionSpec("b"))
                cargs = [jax.device_put(v, sh) if v.ndim else v for v in cargs]
                res["devices"] = len(jax.devices())
            f = jax.jit(lambda *a: _closed_form_classify(*a))
            t0 = time.perf_counter()
            lowered = f.lower(*cargs)
            t1 = time.perf_counter()
            comp = lowered.compile()
            t2 = time.perf_counter()
            res.update(trace_s=t1 - t0, compile_s=t2 - t1)
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

            t0 = time.perf_counter()
            out = jax.block_until_ready(generic(args[0], i_dq, args[1], args[2]))
            res.update(first_call_s=time.perf_counter() - t0)
            run = lambda: jax.block_until_ready(  # noqa: E731
                generic(args[0], i_dq, args[1], args[2]))
        else:
            t0 = time.perf_counter()
            out = analysis.classify_designs(motor, args[0], i_dq, args[1], args[2], w2=W2,
                                            method="general", n_grid=128, dtype=dt)
            jax.block_until_ready(out)
            res.update(first_call_s=time.perf_counter() - t0)
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
    cpu, wall = _best(run, repeats, min_time)
    res.update(cpu_s=cpu, wall_s=wall, pts_per_s_cpu=n / cpu, pts_per_s_wall=n / wall,
               infeasible=float(np.mean(status == 1)))
    np.savez(status_file, status=status, n_nonzero=nnz)
    return res


def run_subprocess(impl, dtype, n, mode, repeats, min_time):
    env = dict(os.environ)
    cmd = [sys.executable, __file__, "--worker", impl, "--dtype", dtype, "--n", str(n),
           "--repeats", str(repeats), "--min-time", str(min_time)]
    if mode == "one":
        env.update(XLA_FLAGS=ONE_CORE_XLA_FLAGS, OMP_NUM_THREADS="1",
                   OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
        cmd = ["taskset", "-c", "0"] + cmd
    elif mode == "sharded":
        env.update(XLA_FLAGS=f"--xla_force_host_platform_device_count={os.cpu_count()} "
                             f"{ONE_CORE_XLA_FLAGS}")
        cmd += ["--sharded"]
    status_file = f"/tmp/bench_feas_{impl}_{dtype}_{mode}_{os.getpid()}.npz"
    cmd += ["--status-file", status_file]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-3000:])
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["mode"] = mode
    st = np.load(status_file)
    os.remove(status_file)
    return res, st


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(OUT / "bench_feasibility.json"))
    ap.add_argument("--worker")
    ap.add_argument("--dtype", default="float64")
    ap.add_argument("--n", type=int, default=B)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--min-time", type=float, default=1.0)
    ap.add_argument("--status-file")
    ap.add_argument("--sharded", action="store_true")
    a = ap.parse_args()
    if a.worker:
        print(json.dumps(worker(a.worker, a.dtype, a.n, a.repeats, a.min_time,
                                a.status_file, a.sharded)))
        return

    rep, mt = (2, 0.2) if a.quick else (7, 1.0)
    n_loop = 500 if a.quick else 3000
    n_general = 2000 if a.quick else 10000
    plan = [
        ("pmsmjax_closed", "float64", B, "one"),
        ("pmsmjax_closed", "float32", B, "one"),
        ("pmsmjax_closed", "float64", B, "all"),
        ("pmsmjax_closed", "float32", B, "all"),
        ("pmsmjax_closed", "float64", B, "sharded"),
        ("pmsmjax_closed", "float32", B, "sharded"),
        ("pmsmjax_general", "float64", n_general, "one"),
        ("pmsmjax_generic", "float64", n_general, "one"),
        ("numpy_batched", "float64", B, "one"),
        ("numpy_batched", "float64", B, "all"),
        ("numpy_loop", "float64", n_loop, "one"),
    ]
    rows, statuses = [], {}
    for impl, dtype, n, mode in plan:
        print(f"  running {impl} {dtype} n={n} ({mode})",
              flush=True)
        res, st = run_subprocess(impl, dtype, n, mode, rep, mt)
        rows.append(res)
        statuses[(impl, dtype, mode)] = st
    # agreement with the float64 closed form (on the common leading points)
    ref = statuses[("pmsmjax_closed", "float64", "one")]
    for r in rows:
        st = statuses[(r["impl"], r["dtype"], r["mode"])]
        m = len(st["status"])
        r["agree_status"] = float(np.mean(st["status"] == ref["status"][:m]))
        r["agree_n_nonzero"] = float(np.mean(st["n_nonzero"] == ref["n_nonzero"][:m]))
    base = {m: next(r for r in rows if r["impl"] == "numpy_batched" and r["mode"] == m)
            for m in ("one", "all")}
    base["sharded"] = base["all"]
    loop = next(r for r in rows if r["impl"] == "numpy_loop")
    lines = ["| implementation | dtype | cores | points/s (CPU time) | points/s (wall) | "
             "vs NumPy batched | vs NumPy loop | first compile (s) | agrees with f64 |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rate = r["pts_per_s_cpu"] if r["mode"] == "one" else r["pts_per_s_wall"]
        b = base[r["mode"]]
        b_rate = b["pts_per_s_cpu"] if r["mode"] == "one" else b["pts_per_s_wall"]
        comp = r.get("compile_s")
        comp = f"{r['trace_s'] + comp:.2f}" if comp is not None else (
            f"{r['first_call_s']:.1f} (1st call)" if "first_call_s" in r else "-")
        n_note = "" if r["n"] == B else f" (n={r['n']}, extrapolated)"
        lines.append(
            f"| {r['impl']}{n_note} | {r['dtype']} | {r['mode']} | {r['pts_per_s_cpu']:.3g} | "
            f"{r['pts_per_s_wall']:.3g} | {rate / b_rate:.1f}x | "
            f"{rate / loop['pts_per_s_cpu']:.0f}x | {comp} | "
            f"{r['agree_status']:.4%} |")
    table = "\n".join(lines)
    print(table)
    meta = dict(
        date=datetime.datetime.now().isoformat(timespec="seconds"),
        machine=platform.processor() or platform.machine(), platform=platform.platform(),
        cpu=_cpu_name(), n_cpus=os.cpu_count(), python=sys.version.split()[0],
        numpy=np.__version__, batch=B, motor=MOTOR, quick=a.quick,
        load_average=os.getloadavg())
    try:
        import jax

        meta["jax"] = jax.__version__
    except ImportError:  # pragma: no cover
        pass
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(dict(meta=meta, rows=rows, table=table), indent=1))
    print(f"wrote {a.out}")


def _cpu_name():
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:  # pragma: no cover
        pass
    return platform.processor()


if __name__ == "__main__":
    main()
