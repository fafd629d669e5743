"""What the commands that run a drive or an observer over time share (`simulate`,
`plant`, `replay`): the timing of a compiled run (`compile_and_run`) and the lock status
of an estimate (`run_lock_status`)."""

from __future__ import annotations

import time

import jax
import numpy as np

import pmsmjax as pj


def compile_and_run(fn, *args, **kwargs):
    """Run the (internally jitted) function `fn` twice: the first call compiles and runs,
    the second only runs, so compile time = first - second.

    Returns `(result, compile_time_s, run_time_s)`; prints "compiling..." and timings.
    """
    print("compiling...", end=" ", flush=True)
    try:
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args, **kwargs))
        t1 = time.perf_counter()
        print(f"done in {t1 - t0:.2f} s (with one run); running...", end=" ", flush=True)
        out = jax.block_until_ready(fn(*args, **kwargs))
        t2 = time.perf_counter()
    except BaseException:
        print("failed", flush=True)
        raise
    print(f"done in {t2 - t1:.3f} s")
    return out, max(t1 - t0 - (t2 - t1), 0.0), t2 - t1


def run_lock_status(t, theta_err, ok: bool, w_m=None, startup=None, w_m_ref=None) -> dict:
    """The lock status of a run (`pmsmjax.lock_status`, the one definition) as plain data
    with the run's status: "successful", "lost lock at t = ... s", "never locked" or
    "diverged". With an I/f start-up the observer is judged from the first sample at
    which both the rotor and the speed reference (which the open-loop frame follows, so
    the handover cannot begin earlier) have reached the handover speed: before it the
    drive runs open loop, and a light rotor swinging about the open-loop current vector
    can pass the handover speed early (zhang750 in the reversal scenario does)."""
    t = np.asarray(t, float)
    start = 0
    if startup is not None and w_m is not None:
        for w in (w_m, w_m_ref):
            if w is None:
                continue
            fast = np.flatnonzero(np.abs(np.asarray(w)) >= float(startup.w_hand))
            start = max(start, int(fast[0]) if fast.size else len(t) - 1)
    st = {k: np.asarray(v).item() for k, v in pj.lock_status(
        t[start:], np.asarray(theta_err)[start:], ok=ok).items()}
    out = {"definition": f"mean |angle error| over {1e3 * pj.LOCK_DWELL_S:g} ms above "
                         f"{pj.LOCK_DEG:g} deg after lock was acquired (held for "
                         f"{1e3 * pj.LOCK_ACQUIRE_S:g} ms), or a diverged run "
                         f"(pmsmjax.lock_status)",
           "lock_deg": pj.LOCK_DEG, "dwell_s": pj.LOCK_DWELL_S,
           "acquire_s": pj.LOCK_ACQUIRE_S, "judged_from_s": float(t[start]),
           "acquired": bool(st["acquired"]), "lost": bool(st["lost"]),
           "t_acquired_s": None if np.isnan(st["t_acquired"]) else float(st["t_acquired"]),
           "t_lost_s": None if np.isnan(st["t_lost"]) else float(st["t_lost"])}
    if not ok:
        out["status"] = "diverged"
    elif out["lost"]:
        out["status"] = f"lost lock at t = {out['t_lost_s']:.4g} s"
    elif not out["acquired"]:
        out["status"] = "never locked"
    else:
        out["status"] = "successful"
    return out
