"""Offline replay: run an observer over recorded stator voltages and currents.

The recorded-data convention (CONVENTIONS.md, `pmsmjax._io`) stores at each sampling
instant t_k the current `i_ab[k]` sampled at t_k and the voltage `u_ab[k]` applied over
[t_k, t_{k+1}). The observer interface (`observers._base`) hands the observer at t_k the
current at t_k and the voltage over the *previous* period, so replay feeds
`meas_k = (i_ab[k], u_ab[k-1])` with a zero voltage at k = 0 -- exactly what `simulate`
feeds the observer in the loop, so a replay of a simulated run reproduces the in-loop
estimates (`test_replay.py`).

`replay` is a pure `lax.scan` of `observer.step`: it jit-compiles, `vmap`s over a batch of
recordings or observers (any array leaf), and differentiates (e.g. a loss on the angle
error with respect to the observer's gains or model parameters).
"""

from __future__ import annotations

import json
import math
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._frames import wrap_angle
from ._simulate import scale_motor
from ._validate import is_concrete
from .observers import AbstractObserver, Measurement


def _arrays(data, u_ab, i_ab, t):
    """Accept a `RecordedData`, a `Trajectory` or explicit arrays."""
    if data is not None and hasattr(data, "i_meas_ab"):  # a Trajectory from simulate
        return data.t, data.u_ab, data.i_meas_ab
    if data is not None and hasattr(data, "u_ab"):  # RecordedData or similar
        if data.u_ab is None or data.i_ab is None:
            raise ValueError("`replay` needs recorded `u_ab` (V) and `i_ab` (A); "
                             "the data has " + ", ".join(getattr(data, "names", ())) + ".")
        return data.t, data.u_ab, data.i_ab
    return t if data is None else data, u_ab, i_ab


@eqx.filter_jit
def _scan(observer, u_ab, i_ab, T_s, theta0, w0, scales):
    dtype = jnp.result_type(i_ab.dtype, u_ab.dtype)
    n = i_ab.shape[0]
    u_prev = jnp.concatenate([jnp.zeros((1, 2), u_ab.dtype), u_ab[:-1]], 0)
    nan = jnp.full((), jnp.nan, dtype)
    state0 = observer.init(theta0=theta0, w0=w0)

    def step(state, x):
        i_k, u_k, sc = x
        obs = observer
        if sc:
            obs = eqx.tree_at(lambda o: o.motor, observer, scale_motor(observer.motor, sc))
        meas = Measurement(i_ab=i_k, u_ab=u_k, theta=nan, w_m=nan)
        state, est = obs.step(state, meas, T_s)
        return state, est

    del n
    _, est = jax.lax.scan(step, state0, (i_ab, u_prev, scales))
    return est


def replay(observer: AbstractObserver, data=None, u_ab=None, i_ab=None, *, t=None,
           T_s=None, theta0=0.0, w0=0.0, observer_scale=None):
    """Run `observer` over recorded voltages and currents; returns
    `(theta_hat, w_hat)`. `replay_estimates` (same arguments) returns the whole
    `Estimate` sequence, including the observer's `extras`.

    **Arguments:**

    - `observer`: any `AbstractObserver` (e.g. `ESOObserver`, `LESOObserver`,
      `AFOObserver`), with its own machine model and gains.
    - `data`: a `RecordedData` (`t`, `u_ab`, `i_ab`), or a `Trajectory` from `simulate`
      (then its *measured* current `i_meas_ab` is used, the one the in-loop observer saw),
      or the time array `t` (s) followed by `u_ab`, `i_ab`.
    - `u_ab`: voltage applied over [t_k, t_{k+1}) (V, (N, 2), stationary frame).
    - `i_ab`: current sampled at t_k (A, (N, 2), stationary frame).
    - `t`: sampling instants (s), if not given positionally.
    - `T_s`: sampling period (s); default `t[1] - t[0]`.
    - `theta0`, `w0`: the observer's initial angle (rad) and speed (rad/s); default 0
      (a drive that does not know its rotor position).
    - `observer_scale`: optional `{name: (N,) array}` factors on the observer's machine
      parameters (`R_s`, `L_d`, `L_q`, `psi_f`) at each sample, as
      `Scenario(observer_scale=...)` applies them in `simulate`.

    **Returns:** `(theta_hat, w_hat)`, each (N,): the estimated electrical angle at t_k
    (rad, wrapped to (-pi, pi]) and speed (rad/s).
    """
    est = replay_estimates(observer, data, u_ab, i_ab, t=t, T_s=T_s, theta0=theta0, w0=w0,
                           observer_scale=observer_scale)
    return est.theta_hat, est.w_hat


def replay_estimates(observer: AbstractObserver, data=None, u_ab=None, i_ab=None, *,
                     t=None, T_s=None, theta0=0.0, w0=0.0, observer_scale=None):
    """`replay`, returning the `Estimate` at every sample: `theta_hat` (N,), `w_hat`
    (N,) and every observer-specific estimate in `extras` (leading axis N; names and
    units in the observer class's `extras`)."""
    if not isinstance(observer, AbstractObserver):
        raise ValueError(
            f"`replay(observer=...)` must be an `AbstractObserver`; got "
            f"{type(observer).__name__}."
        )
    t, u_ab, i_ab = _arrays(data, u_ab, i_ab, t)
    if u_ab is None or i_ab is None:
        raise ValueError("`replay` needs `u_ab` (V, (N, 2)) and `i_ab` (A, (N, 2)).")
    u_ab = jnp.asarray(u_ab)
    i_ab = jnp.asarray(i_ab)
    n = i_ab.shape[0] if i_ab.ndim >= 1 else 0
    if i_ab.shape != (n, 2) or u_ab.shape != (n, 2) or n < 2:
        raise ValueError(
            f"`replay` needs `u_ab` and `i_ab` of shape (N, 2) with N >= 2; got "
            f"{tuple(u_ab.shape)} and {tuple(i_ab.shape)}."
        )
    if T_s is None:
        if t is None:
            raise ValueError("`replay` needs the time axis `t` (s) or `T_s` (s).")
        t = jnp.asarray(t)
        if t.shape != (n,):
            raise ValueError(f"`t` must have shape ({n},); got {tuple(t.shape)}.")
        T_s = t[1] - t[0]
        if is_concrete(T_s):
            T_s = float(T_s)
    if is_concrete(T_s) and not float(T_s) > 0:
        raise ValueError(f"`replay(T_s=...)` (s) must be > 0; got {float(T_s)!r}.")
    scales = {}
    if observer_scale:
        scales = {k: jnp.broadcast_to(jnp.asarray(v), (n,)) for k, v in
                  observer_scale.items()}
    dtype = jnp.result_type(i_ab.dtype, u_ab.dtype)
    theta0 = jnp.asarray(theta0, dtype)
    w0 = jnp.asarray(w0, dtype)
    return _scan(observer, u_ab, i_ab, T_s, theta0, w0, scales)


def settling_time(t, err, tol):
    """Time (s, from `t[0]`) after which `|err| <= tol` for good; `nan` if it never
    settles (the last sample is outside the band). Works under `vmap`."""
    t = jnp.asarray(t)
    err = jnp.asarray(err)
    out = jnp.abs(err) > tol
    idx = jnp.arange(t.shape[-1])
    last_out = jnp.max(jnp.where(out, idx, -1), axis=-1)
    n = t.shape[-1]
    k = jnp.clip(last_out + 1, 0, n - 1)
    ts = jnp.take(t, k, axis=-1) - t[..., 0]
    return jnp.where(last_out >= n - 1, jnp.nan, ts)


def replay_stats(t, theta_hat, w_hat, theta=None, w_m=None, *, t_settle=0.0,
                 tol_deg=2.0) -> dict:
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
        e = err[mask]
        out.update(
            theta_err_mean_deg=float(np.mean(e)), theta_err_std_deg=float(np.std(e)),
            theta_err_max_deg=float(np.max(np.abs(e))),
            theta_err_rms_deg=float(np.sqrt(np.mean(e ** 2))),
            t_converge_s=float(settling_time(t, err, tol_deg)), tol_deg=float(tol_deg),
        )
    if w_m is not None:
        we = (np.asarray(w_m, dtype=float) - np.asarray(w_hat, dtype=float))[mask]
        out.update(w_err_mean=float(np.mean(we)), w_err_std=float(np.std(we)),
                   w_err_max=float(np.max(np.abs(we))))
    return out


# ---------------------------------------------------------------------------------------
# Command line: `pmsmjax replay`
# ---------------------------------------------------------------------------------------

OBSERVER_NAMES = ("eso", "leso", "afo")


def make_observer(name: str, drive, *, bandwidth_hz=50.0, zeta2=1.0, schedule="zhang38",
                  zeta1=None, ratio=None, w1=None, w_min=None, a=0.5, eta=None,
                  fixed_at=None, motor=None):
    """An observer by name (`eso`, `leso`, `afo`) with gains from the design functions.

    **Arguments:**

    - `name`: `"eso"` (nonlinear ESO (10)), `"leso"` (linear ESO), `"afo"` (adaptive
      full-order observer with (53)).
    - `drive`: the `Drive` whose machine the observer models (or `motor` overrides it).
    - `bandwidth_hz`: w2 / (2 pi) (Hz); `zeta2` (-).
    - `schedule`, `zeta1`, `ratio`, `w1` (rad/s), `w_min` (rad/s): see `ESODesign`.
    - `a`, `eta` (V s): fal parameters of the ESO.
    - `fixed_at`: if given, freeze all gains at this speed (p.u. of `drive.w_rated`),
      zero current (`FixedGains`).
    - `motor`: the observer's `PMSMParams` (default `drive`'s).
    """
    from .observers import AFOObserver, ESODesign, ESOObserver, FixedGains, LESOObserver

    name = name.lower()
    if name not in OBSERVER_NAMES:
        raise ValueError(
            f"Unknown observer {name!r}; choose one of {', '.join(OBSERVER_NAMES)}."
        )
    motor = drive.three_phase_motor if motor is None else motor
    w2 = 2 * math.pi * float(bandwidth_hz)
    kw = {}
    if schedule == "zhang38":
        kw["w_rated"] = drive.w_rated
    if zeta1 is not None:
        kw["zeta1"] = zeta1
    if ratio is not None:
        kw["ratio"] = ratio
    if w1 is not None:
        kw["w1"] = w1
    if w_min is not None:
        kw["w_min"] = w_min
    design = ESODesign(w2, zeta2, schedule, **kw)
    if fixed_at is not None:
        design = FixedGains.at(design, motor, float(fixed_at) * float(drive.w_rated))
    if name == "eso":
        return ESOObserver(motor, design, a=a, eta=eta)
    if name == "leso":
        return LESOObserver(motor, design)
    return AFOObserver(motor, design)


def add_replay_arguments(parser) -> None:
    """Add the `replay` options other than `--motor`/`--set` and `--out`/`--no-plot`
    (the CLI's shared helpers add those) to an argparse parser."""
    parser.add_argument("--observer", default="eso", choices=OBSERVER_NAMES,
                        help="observer: eso (nonlinear ESO), leso (linear), afo "
                             "(adaptive full-order, PI speed law (53)); default eso")
    parser.add_argument("--data", required=True, metavar="FILE",
                        help="recorded drive data (.npz or .csv) with t, u_ab, i_ab "
                             "(and optionally theta, w_m to score)")
    parser.add_argument("--bandwidth", type=float, default=50.0,
                        help="observer bandwidth w2/(2 pi) in Hz (default 50)")
    parser.add_argument("--zeta2", type=float, default=1.0,
                        help="speed/angle damping ratio (default 1)")
    parser.add_argument("--schedule", default="zhang38",
                        choices=("zhang38", "fixed_ratio", "fixed_w1"),
                        help="flux-gain schedule (default zhang38 = eq. (38))")
    parser.add_argument("--zeta1", type=float, default=None,
                        help="flux damping ratio (fixed_ratio, fixed_w1)")
    parser.add_argument("--ratio", type=float, default=None,
                        help="w1/|w0| (fixed_ratio)")
    parser.add_argument("--w1", type=float, default=None,
                        help="flux natural frequency in rad/s (fixed_w1)")
    parser.add_argument("--w-min", type=float, default=None,
                        help="speed clamp in rad/s for fixed_w1")
    parser.add_argument("--fixed-at", type=float, default=None,
                        help="freeze all gains at this speed (p.u.), zero current")
    parser.add_argument("--a", type=float, default=0.5, help="fal exponent (eso)")
    parser.add_argument("--eta", type=float, default=None,
                        help="fal linear zone in V s (eso; default 0.05 psi_f)")
    parser.add_argument("--theta0", type=float, default=0.0,
                        help="initial angle estimate in degrees (default 0)")
    parser.add_argument("--w0", type=float, default=0.0,
                        help="initial speed estimate in rad/s (electrical, default 0)")
    parser.add_argument("--t-settle", type=float, default=None,
                        help="statistics after this time in s (default: half the record)")


def run_replay_cli(args, drive) -> dict:
    """The body of `pmsmjax replay`: load, replay, write `replay.npz` (the input arrays
    plus `theta_hat`, `w_hat`), `stats.json` and `replay.png` to `args.out`; returns the
    statistics dict. The observer models `drive`'s machine (so `--set` changes the
    observer's parameters); it starts from `--theta0` (deg, default 0) and `--w0`."""
    from ._io import RecordedData, load_recording, save_recording

    data = load_recording(args.data, require=("t", "u_ab", "i_ab"))
    observer = make_observer(
        args.observer, drive, bandwidth_hz=args.bandwidth, zeta2=args.zeta2,
        schedule=args.schedule, zeta1=args.zeta1, ratio=args.ratio, w1=args.w1,
        w_min=args.w_min, a=args.a, eta=args.eta, fixed_at=args.fixed_at)
    theta_hat, w_hat = replay(observer, data, theta0=math.radians(args.theta0),
                              w0=args.w0)
    theta_hat = np.asarray(theta_hat)
    w_hat = np.asarray(w_hat)
    os.makedirs(args.out, exist_ok=True)
    out = RecordedData(t=data.t, u_ab=data.u_ab, i_ab=data.i_ab, theta=data.theta,
                       w_m=data.w_m, tau_L=data.tau_L, theta_hat=theta_hat, w_hat=w_hat)
    save_recording(os.path.join(args.out, "replay.npz"), out)
    t_settle = 0.5 * float(data.t[-1] - data.t[0]) if args.t_settle is None \
        else args.t_settle
    stats = replay_stats(data.t, theta_hat, w_hat, data.theta, data.w_m,
                         t_settle=t_settle)
    stats = {"motor": drive.name, "observer": args.observer, "data": str(args.data),
             "T_s": data.T_s, "bandwidth_hz": args.bandwidth, **stats}
    with open(os.path.join(args.out, "stats.json"), "w") as f:
        json.dump(_json_safe(stats), f, indent=2, allow_nan=False)
        f.write("\n")
    if not args.no_plot:
        _plot(os.path.join(args.out, "replay.png"), data, theta_hat, w_hat, args.observer)
    return stats


def _json_safe(obj):
    """Non-finite floats -> None (strict JSON)."""
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _plot(path, data, theta_hat, w_hat, name):
    from matplotlib.figure import Figure

    t = np.asarray(data.t)
    rows = 3 if data.theta is not None else 2
    fig = Figure(figsize=(8, 2.4 * rows), layout="constrained")
    ax = fig.subplots(rows, 1, sharex=True)
    if data.w_m is not None:
        ax[0].plot(t, data.w_m, "k", lw=1, label="w_m")
    ax[0].plot(t, w_hat, "r", lw=1, label=f"w_hat ({name})")
    ax[0].set_ylabel("speed (rad/s, el.)")
    ax[0].legend(loc="best")
    if data.theta is not None:
        ax[1].plot(t, np.asarray(wrap_angle(jnp.asarray(data.theta))), "k", lw=1,
                   label="theta")
    ax[1].plot(t, theta_hat, "r", lw=0.8, label="theta_hat")
    ax[1].set_ylabel("angle (rad)")
    ax[1].legend(loc="best")
    if data.theta is not None:
        err = np.degrees(np.asarray(wrap_angle(jnp.asarray(data.theta - theta_hat))))
        ax[2].plot(t, err, "b", lw=1)
        ax[2].set_ylabel("theta error (deg)")
    ax[-1].set_xlabel("t (s)")
    fig.savefig(path, dpi=110)
