r"""Lock acquisition: the basin of attraction of an observer's designed lock, measured.

The local analysis (`linearization`, `equilibria`) says whether the designed equilibrium
is stable; it does not say from how far away an observer finds it. A drive switched on
while the rotor turns (a flying start), or a replay of a log that starts mid-run, starts
the observer at an unknown angle and a wrong speed estimate (usually zero). `lock_basin`
runs the real discrete observer from a grid of such starts, all at once (`vmap`), while
the rotor turns at a constant speed, and reports for each start whether it locked and
when.

**The runs.** The rotor turns at the constant electrical speed `w_m` (a load machine
imposes it: `Scenario(w_m_imposed=...)`), the current controller holds
$i_{dq} = (0, i_q)$ in its frame.

- `mode="replay"`: one sensored run gives the recording (the current controller works
  in the true frame); the observer runs over it open loop (`replay`) from each start.
  This is what replaying a drive log does.
- `mode="closed_loop"`: the observer is in the loop: the current controller works in the
  estimated frame from the first sample, so the currents (and the observer's input) are
  wrong until the observer locks; one `simulate` per start.

**Lock.** The angle error $\tilde\theta = \theta - \hat\theta$ is compared with the
observer's designed steady-state error at the operating point (`designed_error`, e.g. the
C-LESO's phase lag; zero for most): the run has locked at the first sample after which
$|\tilde\theta - \tilde\theta_{design}|$ stays below `tol` to the end of the run, and
$t_{lock}$ is that sample's time (NaN where it never locks, or where the run diverged).
A run counts as locked only if that happens before the last `hold` fraction of the run,
so that a lock is seen to be kept.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._frames import wrap_angle
from .._plant._params import Drive
from .._validate import check_positive, check_range
from ..observers import AbstractObserver, OperatingPoint


class LockBasin(eqx.Module):
    """Result of `lock_basin`.

    - `theta_err0`: initial angle errors $\\theta - \\hat\\theta_0$ (rad), `(n_theta,)`.
    - `w_hat0`: initial speed estimates (rad/s, electrical), `(n_w,)`.
    - `w_m`: the rotor's electrical speed (rad/s); `i_q`: the q current held (A).
    - `locked`: bool `(n_theta, n_w)`, the run locked and kept the lock (see the module
      docstring).
    - `t_lock`: time to lock (s), `(n_theta, n_w)`, NaN where not locked.
    - `final_err`: $\\tilde\\theta - \\tilde\\theta_{design}$ at the end of the run
      (rad, wrapped), `(n_theta, n_w)`.
    - `theta_design`: the designed steady-state angle error (rad).
    - `tol`: the lock tolerance (rad); `t_end`: the run length (s); `mode`: "replay" or
      "closed_loop".
    """

    theta_err0: np.ndarray
    w_hat0: np.ndarray
    w_m: float
    i_q: float
    locked: np.ndarray
    t_lock: np.ndarray
    final_err: np.ndarray
    theta_design: float
    tol: float
    t_end: float
    mode: str = eqx.field(static=True)

    @property
    def fraction_locked(self) -> float:
        """Share of the grid that locked."""
        return float(np.mean(self.locked))

    @property
    def worst_t_lock(self) -> float:
        """The longest time to lock over the locked starts (s; NaN if none locked)."""
        t = np.asarray(self.t_lock)
        return float(np.nanmax(t)) if np.any(np.isfinite(t)) else math.nan


def lock_time(t, err, tol, hold: float = 0.2):
    """`(locked, t_lock)` of one run from its samples `t` (s) and angle error relative
    to the designed one `err` (rad, wrapped): the time of the first sample after which
    `|err| < tol` holds to the end (NaN if never, or only in the last `hold` fraction of
    the run). Works on traced arrays (under `vmap`)."""
    bad = ~(jnp.abs(err) < tol)  # NaN counts as outside
    n = err.shape[-1]
    idx = jnp.arange(n)
    last_bad = jnp.max(jnp.where(bad, idx, -1), axis=-1)
    first_good = last_bad + 1
    locked = first_good <= jnp.floor((1.0 - hold) * (n - 1))
    t_l = jnp.where(locked, t[jnp.clip(first_good, 0, n - 1)], jnp.nan)
    return locked, t_l


def lock_basin(observer: AbstractObserver, drive: Drive, *, w_m=None, i_q=None,
               theta_err0=None, w_hat0=None, mode: str = "replay", t_end: float = 0.4,
               T_s: float = 125e-6, tol: float = math.radians(5.0), batch: int = 64,
               progress: bool = True) -> LockBasin:
    """Basin of attraction of `observer`'s designed lock and its time to lock, on a grid
    of initial angle errors x initial speed estimates (see the module docstring).

    **Arguments:**

    - `observer`: any sensorless observer (its own design and machine model).
    - `drive`: the plant (`Drive`); the current controller is `FOC.from_drive(drive)`.
    - `w_m`: rotor electrical speed (rad/s; default half the rated speed), != 0.
    - `i_q`: the q current held (A; default 0.3 `drive.i_max`).
    - `theta_err0`: initial angle errors $\\theta_0 - \\hat\\theta_0$ (rad); default 12
      values over $[-\\pi, \\pi)$.
    - `w_hat0`: initial speed estimates (rad/s); default $w_m\\cdot$(-1, -0.5, 0, 0.5,
      1, 1.5) (zero included: a drive that knows nothing).
    - `mode`: `"replay"` (observer open loop on a sensored recording) or
      `"closed_loop"` (observer in the current loop).
    - `t_end`: length of each run (s), `T_s`: sampling period (s).
    - `tol`: lock tolerance on the angle error about its designed value (rad).
    - `batch`: starts run per vectorised call (one compilation; a progress bar counts
      the calls); `progress`: show the bar.

    **Returns:** `LockBasin`.
    """
    from .._control._foc import FOC
    from .._data._replay import _scan
    from .._sim._scenario import Profile, Scenario
    from .._sim._simulate import simulate
    from ..observers import SensoredObserver

    if not isinstance(observer, AbstractObserver) or isinstance(observer, SensoredObserver):
        raise ValueError(f"`lock_basin(observer=...)` must be a sensorless observer; got "
                         f"{type(observer).__name__}.")
    if not isinstance(drive, Drive):
        raise ValueError(f"`lock_basin(drive=...)` must be a `Drive`; got "
                         f"{type(drive).__name__}.")
    if mode not in ("replay", "closed_loop"):
        raise ValueError(f"`lock_basin(mode=...)` must be 'replay' or 'closed_loop'; got "
                         f"{mode!r}.")
    check_positive("lock_basin", "t_end", t_end, "s")
    check_positive("lock_basin", "T_s", T_s, "s")
    check_positive("lock_basin", "tol", tol, "rad")
    check_range("lock_basin", "batch", batch, 1, 1e6)
    w_m = 0.5 * float(drive.w_rated) if w_m is None else float(w_m)
    if not (math.isfinite(w_m) and w_m != 0.0):
        raise ValueError(f"`lock_basin(w_m=...)` (rad/s) must be finite and non-zero (the "
                         f"rotor turns); got {w_m!r}.")
    i_q = 0.3 * float(drive.i_max) if i_q is None else float(i_q)
    if theta_err0 is None:
        theta_err0 = np.linspace(-math.pi, math.pi, 12, endpoint=False)
    if w_hat0 is None:
        w_hat0 = w_m * np.array([-1.0, -0.5, 0.0, 0.5, 1.0, 1.5])
    theta_err0 = np.atleast_1d(np.asarray(theta_err0, float))
    w_hat0 = np.atleast_1d(np.asarray(w_hat0, float))
    for name, v in (("theta_err0", theta_err0), ("w_hat0", w_hat0)):
        if v.ndim != 1 or v.size == 0 or not np.all(np.isfinite(v)):
            raise ValueError(f"`lock_basin({name}=...)` must be a non-empty 1-D array of "
                             f"finite values; got shape {v.shape}.")

    controller = FOC.from_drive(drive)
    scenario = Scenario(t_end=t_end, i_d_ref=Profile.constant(0.0),
                        i_q_ref=Profile.constant(i_q),
                        w_m_imposed=Profile.constant(w_m))
    theta0 = 0.0
    op = OperatingPoint(w_m, (0.0, i_q))
    th_design = float(observer.designed_error(op, drive.three_phase_motor)
                      [observer.coordinates.angle])

    TH, WH = np.meshgrid(theta_err0, w_hat0, indexing="ij")
    th_flat, w_flat = TH.reshape(-1), WH.reshape(-1)
    n = th_flat.size
    n_pad = -(-n // batch) * batch
    th_flat = np.concatenate([th_flat, np.full(n_pad - n, th_flat[-1])])
    w_flat = np.concatenate([w_flat, np.full(n_pad - n, w_flat[-1])])

    if mode == "replay":
        ref = simulate(drive, controller, SensoredObserver(drive.motor), scenario, T_s=T_s,
                       theta0=theta0, w_m0=w_m)
        t, theta = ref.t, ref.theta
        u_ab, i_ab = ref.u_ab, ref.i_meas_ab

        @jax.jit
        def run(th0, wh0):
            def one(a, b):
                est = _scan(observer, u_ab, i_ab, T_s, theta0 - a, b, {})
                err = wrap_angle(theta - est.theta_hat - th_design)
                locked, t_l = lock_time(t, err, tol)
                return locked, t_l, err[-1]
            return jax.vmap(one)(th0, wh0)
    else:
        @eqx.filter_jit
        def run(th0, wh0):
            def one(a, b):
                tr = simulate(drive, controller, observer, scenario, T_s=T_s,
                              theta0=theta0, w_m0=w_m, theta_hat0=theta0 - a, w_hat0=b,
                              throw=False)
                err = wrap_angle(tr.theta_err - th_design)
                locked, t_l = lock_time(tr.t, err, tol)
                ok = tr.status._value == 0
                return locked & ok, jnp.where(ok, t_l, jnp.nan), err[-1]
            return jax.vmap(one)(th0, wh0)

    from tqdm import tqdm

    out = []
    for k in tqdm(range(0, n_pad, batch), desc=f"lock basin ({mode})", unit="batch",
                  disable=not progress, dynamic_ncols=True):
        res = run(jnp.asarray(th_flat[k:k + batch]), jnp.asarray(w_flat[k:k + batch]))
        out.append([np.asarray(r) for r in res])
    locked, t_l, fin = (np.concatenate([o[j] for o in out])[:n].reshape(TH.shape)
                        for j in range(3))
    return LockBasin(theta_err0=theta_err0, w_hat0=w_hat0, w_m=w_m, i_q=i_q,
                     locked=locked.astype(bool), t_lock=t_l, final_err=fin,
                     theta_design=th_design, tol=float(tol), t_end=float(t_end),
                     mode=mode)
