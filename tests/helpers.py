"""Independent reference models and small utilities for the tests.

Nothing here calls the library's models: the equations are written out by hand from the
textbook PMSM model (docs/conventions.md) so that they can serve as a reference.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np

import pmsmjax as pj


def rot(theta):
    """exp(theta J) as a numpy 2x2 matrix."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def motor_numbers(motor):
    """(R_s, L_d, L_q, psi_f, n_p) of a three-phase `PMSMParams` as Python floats."""
    return tuple(float(getattr(motor, n)) for n in ("R_s", "L_d", "L_q", "psi_f", "n_p"))


def steady_u_dq(motor, i_dq, w_m):
    """Steady-state voltage u_dq = R i + w J (L i + psi_f) written out per axis (V)."""
    R, Ld, Lq, psi_f, _ = motor_numbers(motor)
    i_d, i_q = i_dq
    return np.array([R * i_d - w_m * Lq * i_q, R * i_q + w_m * (Ld * i_d + psi_f)])


def dq_rhs(motor, J, B, x, u_ab, tau_L, free=True):
    """Right-hand side of the three-phase dq model without harmonics (numpy).

    State x = [i_d, i_q, theta, w_m]; u_ab is the stationary-frame voltage.

        L_d di_d/dt = u_d - R i_d + w L_q i_q
        L_q di_q/dt = u_q - R i_q - w (L_d i_d + psi_f)
        dtheta/dt = w
        (J / n_p) dw/dt = 1.5 n_p (psi_f i_q + (L_d - L_q) i_d i_q) - B w / n_p - tau_L
    """
    R, Ld, Lq, psi_f, n_p = motor_numbers(motor)
    i_d, i_q, th, w = x
    c, s = np.cos(th), np.sin(th)
    u_d = c * u_ab[0] + s * u_ab[1]
    u_q = -s * u_ab[0] + c * u_ab[1]
    did = (u_d - R * i_d + w * Lq * i_q) / Ld
    diq = (u_q - R * i_q - w * (Ld * i_d + psi_f)) / Lq
    tau = 1.5 * n_p * (psi_f * i_q + (Ld - Lq) * i_d * i_q)
    dw = n_p * (tau - B * w / n_p - tau_L) / J if free else 0.0
    return np.array([did, diq, w, dw])


def with_harmonics(drive, order, amplitude, phase=None):
    """`drive` with its (alpha-beta) machine given the PM-flux harmonics."""
    harm = pj.EMFHarmonics(order=order, amplitude=amplitude, phase=phase)
    if drive.dual:
        return eqx.tree_at(lambda d: d.motor.ab.harmonics, drive, harm,
                           is_leaf=lambda x: x is None)
    return eqx.tree_at(lambda d: d.motor.harmonics, drive, harm,
                       is_leaf=lambda x: x is None)


def simpson(f, h):
    """Composite Simpson rule of samples `f` (odd count) with spacing `h`."""
    f = np.asarray(f)
    n = f.shape[0] - 1
    assert n % 2 == 0
    return h / 3.0 * (f[0] + f[-1] + 4.0 * f[1:-1:2].sum(0) + 2.0 * f[2:-1:2].sum(0))


def tree_max_abs_diff(a, b):
    """Largest absolute difference over all array leaves of two PyTrees."""
    import jax

    la = [np.asarray(x) for x in jax.tree_util.tree_leaves(eqx.filter(a, eqx.is_array))]
    lb = [np.asarray(x) for x in jax.tree_util.tree_leaves(eqx.filter(b, eqx.is_array))]
    assert len(la) == len(lb)
    return max(float(np.max(np.abs(x - y))) if x.size else 0.0 for x, y in zip(la, lb))


def scheduled_gains_table(drive, T_s, *, w2_factor=1.2, zeta2=1.1, verdict=None):
    """A speed-scheduled ESO gains table (`pmsmjax.gains_table_scheduled`) of zhang2022's
    flux schedule (38) with w2 = `w2_factor` x 2 pi 50 rad/s and `zeta2`, rows every
    0.025 p.u. up to 1.5 p.u., and the observer it tabulates (`make_observer("eso",
    drive, w2=..., zeta2=...)`, whose schedule the observer evaluates exactly)."""
    import math

    import jax.numpy as jnp

    import pmsmjax as pj
    from pmsmjax.observers import make_observer
    from pmsmjax.observers._eso_design import zhang38

    w_r = float(drive.w_rated)
    w = pj.gains_speed_grid(w_r, 1.5, 60)
    zeta1, w1 = zhang38(jnp.asarray(w), w_r)
    n = len(w)
    w2 = w2_factor * 2 * math.pi * 50.0
    sched = pj.TabulatedDesign(w_m=jnp.asarray(w), zeta1=zeta1, w1=w1,
                               zeta2=jnp.full(n, zeta2), w2=jnp.full(n, w2),
                               nu2=jnp.zeros(n), nu3=jnp.zeros(n))
    table = pj.gains_table_scheduled("eso", sched, drive.three_phase_motor,
                                     drive=drive.name, notes=["test schedule"], T_s=T_s,
                                     objective="cvar", verdict=verdict)
    return table, make_observer("eso", drive, w2=w2, zeta2=zeta2)


def lock_status_loop(t, theta_err, *, ok=True, lock_deg=45.0, dwell_s=10e-3,
                     acquire_s=50e-3, start_locked=False):
    """`pmsmjax.lock_status` of one run by a plain loop over the samples (an independent
    reference): `(acquired, t_acquired, lost, t_lost)`; `start_locked`: the run starts in
    lock (acquired at its first sample, any window out of lock is a loss)."""
    import math

    import numpy as np

    t = np.asarray(t, float)
    e = np.asarray(theta_err, float)
    n = len(t)
    k = max(1, min(n, int(round(dwell_s / ((t[-1] - t[0]) / max(n - 1, 1))))))
    bad = ~np.isfinite(e)
    mag = [math.pi if bad[j] else abs(math.remainder(e[j], 2 * math.pi)) for j in range(n)]
    lim = math.radians(lock_deg)
    means = [sum(mag[j:j + k]) / k for j in range(n - k + 1)]
    dt = (t[-1] - t[0]) / max(n - 1, 1)
    m = max(1, int(round(acquire_s / dt)))
    acq = next((j for j in range(len(means))
                if all(means[i] <= lim for i in range(j, min(j + m, len(means))))), None)
    first = acq + 1 if acq is not None else None
    if start_locked:
        acq, first = 0, 0
    lost_j = None
    if acq is not None:
        lost_j = next((j for j in range(first, len(means)) if means[j] > lim), None)
    first_bad = next((j for j in range(n) if bad[j]), None)
    if first_bad is not None or not ok:
        end = first_bad if first_bad is not None else n - 1
        lost_j = end if lost_j is None else min(lost_j, end)
        return acq is not None, (t[acq] if acq is not None else math.nan), True, t[lost_j]
    lost = acq is not None and lost_j is not None
    return (acq is not None, t[acq] if acq is not None else math.nan, lost,
            t[lost_j] if lost else math.nan)


def read_npz(path) -> dict:
    """Every array of the NPZ archive at `path`, read, with the archive closed. An archive
    left open (`np.load` without `with`) is closed by the garbage collector whenever it
    runs, and pytest then fails the test running at that moment with the
    `ResourceWarning`. No archive the package writes holds a pickled (object) array."""
    with np.load(path, allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def start_load_reversal_run(drive, observer, *, T_s=125e-6, theta_hat0=2.0):
    """The closed loop of a new observer's lock test: I/f start from standstill
    (`IfStartup.from_drive`), speed held at 0 for 50 ms, ramped to 0.5 p.u. by 0.3 s, held,
    reversed to -0.5 p.u. over 0.6-0.85 s; half the rated load from 0.4 s, reversed at
    1.0 s; 1.3 s in all. Returns the trajectory (`throw=False`) and `pj.lock_status` of its
    angle error from the handover on (the first sample at which both the speed and its
    reference reach the start-up's handover speed)."""
    W = 0.5 * float(drive.w_rated)
    tau = float(drive.tau_rated)
    sc = pj.Scenario(t_end=1.3,
                     w_m_ref=pj.Profile([0.0, 0.05, 0.3, 0.6, 0.85], [0.0, 0.0, W, W, -W]),
                     tau_L=pj.Profile.steps([0.4, 1.0], [0.5 * tau, -0.5 * tau]))
    su = pj.IfStartup.from_drive(drive)
    tr = pj.simulate(drive, pj.FOC.from_drive(drive, startup=su), observer, sc, T_s=T_s,
                     theta_hat0=theta_hat0, throw=False)
    k = max(int(np.flatnonzero(np.abs(np.asarray(w)) >= su.w_hand)[0])
            for w in (tr.w_m, tr.w_m_ref))
    return tr, pj.lock_status(np.asarray(tr.t)[k:], np.asarray(tr.theta_err)[k:])
