r"""The one place errors, settling and noise are measured.

Replay (`pmsmjax replay`), the command line, the paper reproductions (`pmsmjax.papers`)
and the gain tuner (`tuning`) all measure their runs with these functions, so a number
called "settling time" or "angle error RMS" means the same everywhere. Errors are *true
minus estimate* (or reference minus actual), angles wrapped to (-pi, pi].

Two kinds:

- **Reporting** (`error_stats`, `settled_mask`, `replay_stats`): NumPy, concrete arrays,
  plain floats out (JSON-ready).
- **Differentiable** (`settling_time`, `run_errors`, `run_metrics`,
  `trajectory_metrics`): JAX, pure, jit/vmap/grad safe, any leading batch axes.

**The static window** (`STATIC_WINDOW`, `static_window`): the static angle error and the
speed-estimate noise of a run are measured over its last 20 %, by time: the samples at
$t \ge t_0 + 0.8\,(t_{end} - t_0)$, with the run's end $t_{end}$ one sample spacing after
its last sample (as `simulate` saves them, the first sample of every `save_every` steps).
A time, not a count of samples: the same part of the run whatever the sampling period
`T_s` and `save_every`; the samples in it are derived from it.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._frames import wrap_angle


_EPS = 1e-12  # added under the square roots of the metrics (finite gradient at 0)

#: The static window: the last fraction of a run's duration over which the static angle
#: error and the speed-estimate noise are measured (`static_window`).
STATIC_WINDOW = 0.2
#: Settling band of the angle error (deg) of `run_metrics` and `replay_stats`.
SETTLE_BAND_DEG = 2.0

#: Loss of lock: the angle error's magnitude above this (deg) ...
LOCK_DEG = 45.0
#: ... for longer than this (s).
LOCK_DWELL_S = 10e-3
#: Lock is acquired where it then holds for this long (s): five dwells.
LOCK_ACQUIRE_S = 50e-3


# The array metrics below are jitted: outside a trace (on a finished run's arrays) each
# of their operations would otherwise compile a program of its own for every new shape.
@functools.partial(jax.jit, static_argnames="start_locked")
def lock_status(t, theta_err, *, ok=True, lock_deg: float = LOCK_DEG,
                dwell_s: float = LOCK_DWELL_S, acquire_s: float = LOCK_ACQUIRE_S,
                start_locked: bool = False) -> dict:
    r"""Whether an observer acquired and kept lock: **the one definition of loss of lock**
    (`simulate` and `replay` summaries, the tuner, the comparison job).

    Over a window of `dwell_s`, the observer is *in lock* where the mean magnitude of the
    wrapped angle error (true minus estimate) is at most `lock_deg`. It *acquired lock*
    at the start of the first such window from which every window starting within the
    next `acquire_s` (or up to the last whole window, near the end of the run) is in lock
    too: an acquisition's overshoot that passes through the band and out again (the ESO
    catching a rotor that starts to turn does) is not a lock. It *lost lock* at the
    start of the first later window whose mean exceeds `lock_deg`, or when the run
    diverged or produced a non-finite error (`ok` False: lost at the first non-finite
    sample, or at the end for a diverged run; a non-finite sample counts as 180 deg). A
    mean, not "every sample above": an estimate that spins through every angle is out of
    lock although some of its samples pass near the true angle.

    *A run that starts in lock* (`start_locked` True: the observer starts on the true
    angle and speed, as every run of the tuner and of the comparison does) acquired lock
    at its first sample by construction: there is nothing to acquire, and a slip in its
    first window is a loss, not an acquisition's overshoot. Judged as an acquisition
    instead, such a run that slipped at once and settled back only after a long slip
    (the li observers at 0.1 p.u.: out of lock from 12 ms to 0.34 s) would count as
    acquired late and never lost.

    Why these numbers: at 45 deg the current control, which runs in the estimated frame,
    produces cos 45 = 71 % of the torque per ampere it intends and as much again in the
    wrong axis; beyond that a speed loop pushes the error further (at 90 deg the torque
    vanishes). 10 ms is longer than the current loop's response (0.3 ms at the default
    500 Hz bandwidth), so a spike through a load step or a reversal does not count, and
    shorter than the speed loop's time constant (32 ms at 5 Hz), so a slip is caught
    before the speed controller has reacted to it.

    **Arguments:** `t` (s), `theta_err` (rad, wrapped or not), samples on the last axis,
    any leading batch axes (NumPy or JAX arrays; jit and vmap safe); `ok`: the run did
    not diverge (a bool or an array of the batch shape); `start_locked`: the run starts
    in lock (above; a Python bool).

    **Returns:** a dict of arrays with the batch shape: `acquired` (bool), `t_acquired`
    (s; NaN if never), `lost` (bool), `t_lost` (s; NaN if not lost).
    """
    t = jnp.asarray(t)
    th = jnp.asarray(theta_err)
    fin = jnp.isfinite(th)
    err = jnp.abs(wrap_angle(jnp.where(fin, th, jnp.pi)))
    n = th.shape[-1]
    dt = (t[..., -1] - t[..., 0]) / max(n - 1, 1)
    k = jnp.maximum(1, jnp.round(dwell_s / jnp.maximum(dt, 1e-300))).astype(jnp.int32)
    k = jnp.minimum(k, n)
    lim = jnp.deg2rad(lock_deg)
    # mean |error| over the window of k samples that starts at each sample
    c = jnp.concatenate([jnp.zeros(err.shape[:-1] + (1,), err.dtype),
                         jnp.cumsum(err, -1)], -1)
    idx = jnp.arange(n)
    end = jnp.minimum(idx + k[..., None], n)
    mean = (jnp.take_along_axis(c, end, -1) - c[..., :n]) / k[..., None]
    whole = idx + k[..., None] <= n
    big = jnp.int32(n)
    # in lock at every window start of [j, min(j + m, n_whole)): a count over that range
    inside = (whole & (mean <= lim)).astype(jnp.int32)
    m = jnp.maximum(1, jnp.round(acquire_s / jnp.maximum(dt, 1e-300))).astype(jnp.int32)
    n_whole = n - k + 1
    ci = jnp.concatenate([jnp.zeros(inside.shape[:-1] + (1,), jnp.int32),
                          jnp.cumsum(inside, -1)], -1)
    stop = jnp.minimum(idx + m[..., None], n_whole[..., None])
    held = (jnp.take_along_axis(ci, jnp.clip(stop, 0, n), -1) - ci[..., :n]) == stop - idx
    if start_locked:
        j_acq = jnp.zeros(th.shape[:-1], jnp.int32)
        after = idx >= 0
    else:
        j_acq = jnp.min(jnp.where(whole & (inside > 0) & held, idx, big), -1)
        after = idx > j_acq[..., None]
    j_lost = jnp.min(jnp.where(whole & (mean > lim) & after, idx, big), -1)
    j_bad = jnp.min(jnp.where(~fin, idx, big), -1)
    ok = jnp.asarray(ok) & (j_bad == big)
    j_lost = jnp.where(ok, j_lost, jnp.minimum(j_lost, jnp.where(j_bad < big, j_bad,
                                                                  n - 1)))
    acquired = j_acq < big
    lost = (acquired & (j_lost < big)) | ~ok
    tt = jnp.broadcast_to(t, th.shape)
    at = lambda j: jnp.take_along_axis(tt, jnp.minimum(j, n - 1)[..., None], -1)[..., 0]  # noqa
    return {"acquired": acquired, "t_acquired": jnp.where(acquired, at(j_acq), jnp.nan),
            "lost": lost, "t_lost": jnp.where(lost, at(jnp.minimum(j_lost, n - 1)),
                                               jnp.nan)}


def _spacing(t):
    """Sample spacing (s) of equally spaced times `t` (samples on the last axis), shape
    `(..., 1)`; 0 for a single sample."""
    n = t.shape[-1]
    return (t[..., -1:] - t[..., :1]) / max(n - 1, 1)


def _at_or_after(t, t_from):
    """True at the samples `t >= t_from`, up to a thousandth of the sample spacing (the
    rounding of computed times, never a whole sample)."""
    return t >= jnp.asarray(t_from)[..., None] - 1e-3 * _spacing(t)


@jax.jit
def settling_time(t, err, tol, t_from=None):
    """Time after which `|err| <= tol` for good; `nan` if it never settles (the last
    sample is outside the band). Works under `vmap`.

    **Arguments:**

    - `t`: sample times (s), `(..., N)`, equally spaced.
    - `err`: the error on `t` (any unit), `(..., N)`.
    - `tol`: the band (unit of `err`).
    - `t_from`: the samples before this time (s; a scalar or the batch shape) are
      ignored, and the time is measured from it (0 if no later sample is outside the
      band); default `t[..., 0]`.

    **Returns:** the settling time (s), measured from `t_from`.
    """
    shape = jnp.broadcast_shapes(jnp.shape(t), jnp.shape(err))
    t = jnp.broadcast_to(jnp.asarray(t), shape)
    err = jnp.broadcast_to(jnp.asarray(err), shape)
    out = jnp.abs(err) > tol
    if t_from is None:
        t_from = t[..., 0]
    else:
        out = out & _at_or_after(t, t_from)
    idx = jnp.arange(t.shape[-1])
    last_out = jnp.max(jnp.where(out, idx, -1), axis=-1)
    n = t.shape[-1]
    k = jnp.clip(last_out + 1, 0, n - 1)
    t_set = jnp.take_along_axis(t, k[..., None], -1)[..., 0]
    ts = jnp.where(last_out < 0, 0.0, t_set - t_from)
    return jnp.where(last_out >= n - 1, jnp.nan, ts)


def error_stats(err) -> dict:
    """Mean, standard deviation, RMS and largest magnitude of the error samples `err`
    (1-D, non-empty; any unit, the results are in the same unit).

    **Returns:** a dict of floats `mean`, `std`, `rms`, `max_abs`.
    """
    e = np.asarray(err, dtype=float)
    if e.size == 0:
        raise ValueError("`error_stats(err=...)` needs at least one sample.")
    return {"mean": float(np.mean(e)), "std": float(np.std(e)),
            "rms": float(np.sqrt(np.mean(e ** 2))), "max_abs": float(np.max(np.abs(e)))}


def settled_mask(t, *references, t_settle: float) -> np.ndarray:
    """True at the samples where every reference signal has been constant for at least
    `t_settle`.

    **Arguments:**

    - `t`: sample times (s), `(N,)`.
    - `references`: reference signals on `t` (e.g. the speed reference in rad/s and the
      load torque in N m), each `(N,)`; a change is a step above 1e-12 of the signal's
      largest magnitude (at least 1e-12).
    - `t_settle`: the time since the last change (s).

    **Returns:** a boolean array `(N,)`.
    """
    t = np.asarray(t, dtype=float)

    def changed(x):
        x = np.asarray(x, dtype=float)
        tol = 1e-12 * max(1.0, float(np.max(np.abs(x))))
        return np.r_[True, np.abs(np.diff(x)) > tol]

    step = np.zeros(len(t), dtype=bool)
    step[0] = True
    for x in references:
        step = step | changed(x)
    idx = np.arange(len(t))
    last = np.maximum.accumulate(np.where(step, idx, 0))
    return (t - t[last]) >= t_settle - 1e-12


def replay_stats(t, theta_hat, w_hat, theta=None, w_m=None, *, t_settle=0.0,
                 tol_deg=SETTLE_BAND_DEG) -> dict:
    """Error statistics of estimates against the true angle and speed.

    **Arguments:**

    - `t` (s), `theta_hat` (rad), `w_hat` (rad/s): estimates at t_k, (N,).
    - `theta` (rad), `w_m` (rad/s): true electrical angle and speed at t_k, (N,).
    - `t_settle`: statistics use samples with `t - t[0] >= t_settle` (s).
    - `tol_deg`: band for the settling time of the angle error (deg).

    **Returns:** a dict of floats (JSON-ready): `n_samples`, `t_settle`, and when `theta`
    is given `theta_err_mean_deg`, `theta_err_std_deg`, `theta_err_max_deg` (max of
    the absolute error), `theta_err_rms_deg`, `t_converge_s` (time after which
    |theta_err| <= `tol_deg` for good, measured from t[0]; NaN if never) and
    `tol_deg`; when `w_m` is given `w_err_mean`, `w_err_std`, `w_err_max` (rad/s, true
    minus estimate, max absolute). Errors are true minus estimate, angles wrapped.
    """
    t = np.asarray(t, dtype=float)
    mask = (t - t[0]) >= t_settle
    if not np.any(mask):
        raise ValueError(
            f"`replay_stats(t_settle={t_settle!r})` (s) leaves no samples: the record "
            f"lasts {float(t[-1] - t[0]):.6g} s."
        )
    out = {"n_samples": int(np.sum(mask)), "t_settle": float(t_settle)}
    if theta is not None:
        err = np.degrees(np.asarray(wrap_angle(jnp.asarray(theta) - jnp.asarray(theta_hat))))
        s = error_stats(err[mask])
        out.update(
            theta_err_mean_deg=s["mean"], theta_err_std_deg=s["std"],
            theta_err_max_deg=s["max_abs"], theta_err_rms_deg=s["rms"],
            t_converge_s=float(settling_time(t, err, tol_deg)), tol_deg=float(tol_deg),
        )
    if w_m is not None:
        s = error_stats((np.asarray(w_m, dtype=float) - np.asarray(w_hat, dtype=float))[mask])
        out.update(w_err_mean=s["mean"], w_err_std=s["std"], w_err_max=s["max_abs"])
    return out


def _safe_sqrt(x):
    return jnp.sqrt(jnp.maximum(x, 0.0) + _EPS)


def _window_mean(x, mask):
    """Mean of `x` over the samples where `mask` (last axis; at least one counted)."""
    mask = mask.astype(x.dtype)
    return jnp.sum(x * mask, -1) / jnp.maximum(jnp.sum(mask, -1), 1.0)


def _window_std(x, mask):
    """`(std, mean)` of `x` over the samples where `mask` (the std with 1e-12 under its
    square root: a finite gradient at 0)."""
    mean = _window_mean(x, mask)
    return _safe_sqrt(_window_mean((x - mean[..., None]) ** 2, mask)), mean


def static_window(t):
    """The static window of a run (`STATIC_WINDOW`, module docstring): True at the
    samples of its last 20 % by time.

    **Arguments:** `t`: sample times (s), equally spaced, samples on the last axis (any
    leading batch axes), the run's end one spacing after the last sample.

    **Returns:** a boolean array of the shape of `t`.
    """
    t = jnp.asarray(t)
    n = t.shape[-1]
    t0 = t[..., 0]
    t_end = t0 + n * _spacing(t)[..., 0]
    return _at_or_after(t, t0 + (1.0 - STATIC_WINDOW) * (t_end - t0))


def run_errors(traj):
    r"""The errors of a (batched) closed-loop `Trajectory` that its metrics are made of:
    `(theta_err_deg, w_err, ok)`, the angle error $\tilde\theta$ (deg, true minus
    estimate, wrapped), the speed-estimate error $\tilde\omega = \omega - \hat\omega$
    (rad/s, electrical) and whether the run did not diverge and every sample is finite.
    A non-finite sample counts as 180 deg and 0 rad/s (as in `lock_status`), replaced
    before any arithmetic, so no NaN reaches a gradient.

    **Arguments:** `traj`: a `Trajectory` (any leading batch axes; samples on the last
    axis).
    """
    return _run_errors(traj.theta_err, traj.w_m, traj.w_hat, traj.ok)


def _run_errors(theta_err, w_m, w_hat, ok):
    th, w_err = theta_err, w_m - w_hat
    fin = jnp.isfinite(th) & jnp.isfinite(w_err)
    ok = ok & jnp.all(fin, axis=-1)
    return (jnp.rad2deg(jnp.where(fin, th, jnp.pi)), jnp.where(fin, w_err, 0.0), ok)


def run_metrics(traj, *, lock_deg: float = LOCK_DEG, settle_from=None,
                settle_band_deg: float = SETTLE_BAND_DEG) -> dict:
    r"""The per-run metrics of a (batched) closed-loop `Trajectory`: **the one
    definition** of the tuner's (`tuning.run_metrics`) and the observer comparison's
    (`tuning.compare`) run metrics. On `run_errors`' $\tilde\theta$ (deg) and
    $\tilde\omega$ (rad/s):

    - `static_deg`: the static angle error, the mean of $\tilde\theta$ over the static
      window (`static_window`, the last 20 % of the run);
    - `noise_rad_s`: the speed-estimate noise, the standard deviation of $\tilde\omega$
      over the static window;
    - `rms_deg`: RMS of $\tilde\theta$ over the whole run;
    - `max_abs_deg`: largest $|\tilde\theta|$ over the run;
    - `settle_s`: settling time (`settling_time`), from `settle_from` until
      the angle error stays within `settle_band_deg` of `static_deg` for good (0 if it never
      leaves the band; NaN if the last sample is outside it);
    - `lost_lock`: the run lost lock (`lock_status` with `lock_deg`; a run that starts
      in lock, `start_locked`, as the tuner's and the comparison's runs do: the observer
      starts on the true angle and speed);
    - `t_lost`: when it lost lock (s; `lock_status`'s `t_lost`, NaN if it did not);
    - `ok`: the run did not diverge and every sample is finite.

    The square roots carry 1e-12 (a finite gradient at 0); jit, vmap and grad safe.

    **Arguments:**

    - `traj`: a `Trajectory` (any leading batch axes; samples on the last axis).
    - `lock_deg`: the loss-of-lock threshold (deg).
    - `settle_from`: start of the settling time (s; default the first sample).
    - `settle_band_deg`: the settling band (deg).

    **Returns:** a dict of arrays with the batch shape of `traj`.
    """
    return _run_metrics(traj.t, traj.theta_err, traj.w_m, traj.w_hat, traj.ok, lock_deg,
                        settle_from, settle_band_deg)


@jax.jit
def _run_metrics(t, theta_err, w_m, w_hat, ok, lock_deg, settle_from, settle_band_deg):
    t = jnp.asarray(t)
    th, w_err, ok = _run_errors(theta_err, w_m, w_hat, ok)
    win = jnp.broadcast_to(static_window(t), th.shape)
    static = _window_mean(th, win)
    noise, _ = _window_std(w_err, win)
    settle = settling_time(t, th - static[..., None], settle_band_deg, settle_from)
    lock = lock_status(t, theta_err, ok=ok, lock_deg=lock_deg, start_locked=True)
    return dict(static_deg=static, rms_deg=_safe_sqrt(jnp.mean(th ** 2, -1)),
                max_abs_deg=jnp.max(jnp.abs(th), -1), settle_s=settle, noise_rad_s=noise,
                lost_lock=lock["lost"], t_lost=lock["t_lost"], ok=ok)


def trajectory_metrics(traj, *, t_transient, T_s, save_every=1, theta_err0) -> dict:
    r"""Differentiable error metrics of a (batched) closed-loop `Trajectory`.

    With the angle error $\tilde\theta$ (`traj.theta_err`, true minus estimate) and the
    speed-estimate error $\tilde\omega = \omega - \hat\omega$ on the saved samples, and
    "after the transient" meaning $t \ge t_{tr} - T_s/2$:

    - `pos_rms_deg`: RMS of $\tilde\theta$ after the transient (deg);
    - `theta_ss_deg`: mean of $\tilde\theta$ after the transient, the static error (deg);
    - `settle_s`: settling-time surrogate (s), $\sqrt{4\sum_k t_k(\tilde\theta_k -
      \tilde\theta_\infty)^2\,\Delta t / \tilde\theta_0^2}$ with $\tilde\theta_\infty$ the
      static error and $\Delta t$ = `T_s * save_every`: exactly the time constant $\tau$
      of a decay $\tilde\theta_0 e^{-t/\tau}$;
    - `noise_rad_s`: standard deviation of $\tilde\omega$ after the transient (rad/s);
    - `w_bias_rad_s`: its mean (rad/s);
    - `ok`: the run did not diverge and every sample is finite.

    Non-finite samples are replaced by 0 (their gradient is dropped); the square roots
    carry 1e-12 so that their gradient stays finite at 0.

    **Arguments:**

    - `traj`: a `Trajectory` (any leading batch axes; samples on the last axis).
    - `t_transient`: start of the averaging window (s).
    - `T_s`: sampling period of the run (s).
    - `save_every`: sampling periods per saved sample.
    - `theta_err0`: initial angle error $\tilde\theta_0$ (rad) that normalises the
      settling surrogate; 0 means 1 rad.

    **Returns:** a dict of arrays with the batch shape of `traj`.
    """
    return _trajectory_metrics(traj.t, traj.theta_err, traj.w_m, traj.w_hat, traj.ok,
                               t_transient, T_s, save_every, theta_err0)


@jax.jit
def _trajectory_metrics(t, th, w_m, w_hat, ok, t_transient, T_s, save_every, theta_err0):
    w_err = w_m - w_hat
    fin = jnp.isfinite(th) & jnp.isfinite(w_err)
    ok = ok & jnp.all(fin, axis=-1)
    # keep non-finite samples out of the arithmetic (their gradient is dropped anyway)
    th = jnp.where(fin, th, 0.0)
    w_err = jnp.where(fin, w_err, 0.0)
    dt = T_s * save_every
    mask = jnp.broadcast_to(t >= t_transient - 0.5 * T_s, th.shape)
    pos_ms = _window_mean(th ** 2, mask)
    th_ss = _window_mean(th, mask)
    dev = th - th_ss[..., None]
    th0 = jnp.where(theta_err0 == 0, 1.0, theta_err0)
    itse = jnp.sum(t * dev ** 2, -1) * dt
    noise, w_mean = _window_std(w_err, mask)
    return dict(pos_rms_deg=jnp.degrees(_safe_sqrt(pos_ms)), theta_ss_deg=jnp.degrees(th_ss),
                settle_s=_safe_sqrt(4.0 * itse / th0 ** 2), noise_rad_s=noise,
                w_bias_rad_s=w_mean, ok=ok)
