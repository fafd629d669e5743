"""Offline replay: run an observer over recorded stator voltages and currents.

The recorded-data convention (`pmsmjax._data._recording`) stores at each sampling
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

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._plant._inverter import observer_voltage
from .._plant._params import Inverter, PMSMParams, scale_motor
from .._sim._batching import batched_like, values_as_arrays
from .._validate import NonFiniteInputError, is_concrete
from ..observers import AbstractObserver, Measurement
from ._flying_start import unknown_start


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


def _finite_scalar(name, unit, value, dtype):
    v = jnp.asarray(value, dtype)
    if is_concrete(v):
        if not bool(np.all(np.isfinite(np.asarray(v)))):
            raise NonFiniteInputError(f"`replay({name}=...)` ({unit}) must be finite; got "
                                      f"{float(v)!r}.")
        return v
    return eqx.error_if(v, ~jnp.isfinite(v), f"replay: {name} ({unit}) must be finite")


def _check_finite_samples(name, unit, a, t):
    """`a` (N, 2): a named error at its first non-finite sample (concrete arrays; traced
    ones are checked by `eqx.error_if`)."""
    if not is_concrete(a):
        return eqx.error_if(a, ~jnp.all(jnp.isfinite(a)),
                            f"replay: `{name}` ({unit}) holds NaN or inf")
    # numpy: inside a jit trace (a recording closed over) jnp would return tracers
    an = np.asarray(a)
    bad = ~np.all(np.isfinite(an), axis=-1)
    if bool(np.any(bad)):
        k = int(np.argmax(bad))
        when = ""
        if t is not None and is_concrete(t):
            when = f" (t = {float(np.asarray(t)[k]):.6g} s)"
        raise NonFiniteInputError(
            f"`replay`: `{name}` ({unit}) is not finite at sample {k}{when}: "
            f"{[float(x) for x in an[k]]}; {int(np.sum(bad))} of {a.shape[0]} samples are "
            "NaN or inf. Drop or fill those samples before replaying.")
    return a


def _checked(u_ab, i_ab, t, T_s):
    """The recording's arrays checked (shapes, finite values, sampling period):
    `(u_ab, i_ab, T_s)`."""
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
    u_ab = _check_finite_samples("u_ab", "V", u_ab, t)
    i_ab = _check_finite_samples("i_ab", "A", i_ab, t)
    return u_ab, i_ab, T_s


def _applied(u_ab, i_ab, inverter):
    """The voltage the observer sees: `u_ab` itself, or for commanded voltages the drive's
    compensation (as in simulate); the last row is never used."""
    if inverter is None:
        return u_ab
    u_ab = observer_voltage(u_ab[:-1], i_ab[:-1], i_ab[1:], inverter.u_dt, inverter.i_dt)
    return jnp.concatenate([u_ab, jnp.zeros((1, 2), u_ab.dtype)], 0)


def _unknown_start(observer, u_ab, i_ab, T_s):
    motor = getattr(observer, "motor", None)
    if not isinstance(motor, PMSMParams):
        zero = jnp.zeros((), jnp.result_type(u_ab.dtype, i_ab.dtype, float))
        return zero, zero, jnp.asarray(False)
    return unknown_start(motor, u_ab, i_ab, T_s)


def initial_estimate(observer: AbstractObserver, data=None, u_ab=None, i_ab=None, *,
                     t=None, T_s=None, inverter=None):
    """The initial estimate `replay` starts `observer` from when it is given none:
    `(theta0 (rad), w0 (rad/s), turning (bool))`, the flying start of the first samples
    read with the observer's own machine model where they show a turning rotor, else
    zero (`pmsmjax.unknown_start`). Arguments as `replay`."""
    t, u_ab, i_ab = _arrays(data, u_ab, i_ab, t)
    u_ab, i_ab, T_s = _checked(u_ab, i_ab, t, T_s)
    return _unknown_start(observer, _applied(u_ab, i_ab, inverter), i_ab, T_s)


@eqx.filter_jit
def _scan(observer, u_ab, i_ab, T_s, theta0, w0, scales, inverter=None):
    dtype = jnp.result_type(i_ab.dtype, u_ab.dtype)
    n = i_ab.shape[0]
    u_ab = _applied(u_ab, i_ab, inverter)
    if theta0 is None:  # unknown: caught from the first samples, or zero
        theta0, w0, _ = _unknown_start(observer, u_ab, i_ab, T_s)
    u_prev = jnp.concatenate([jnp.zeros((1, 2), u_ab.dtype), u_ab[:-1]], 0)
    nan = jnp.full((), jnp.nan, dtype)
    # every carry batched (under vmap) and differentiated (under jvp/grad) from the
    # start: one pass of the scan's fixpoints over the step (pmsmjax._sim._batching)
    state0 = batched_like(observer.init(theta0=theta0, w0=w0), observer, u_ab, i_ab, T_s,
                          theta0, w0, scales)

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
           T_s=None, theta0=None, w0=None, observer_scale=None, inverter=None):
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
    - `theta0`, `w0`: the observer's initial angle (rad) and speed (rad/s). Default
      (neither given): unknown, as for a drive that does not know its rotor's state: if
      the first samples show a turning rotor (their model back-EMF is more than a fifth
      of the voltage) the observer starts from their `flying_start` (a drive's
      catch-on-the-fly), otherwise from 0 rad and 0 rad/s (`initial_estimate` returns
      which). Give either to start from that value (the other then defaults to 0).
    - `observer_scale`: optional `{name: (N,) array}` factors on the observer's machine
      parameters (`R_s`, `L_d`, `L_q`, `psi_f`) at each sample, as
      `Scenario(observer_scale=...)` applies them in `simulate`.
    - `inverter`: for a recording of *commanded* voltages (what a drive's controller
      logs), the `Inverter` (e.g. `drive.inverter`) whose dead-time model (`u_dt` V,
      `i_dt` A) reconstructs the applied voltage: the observer sees the commanded voltage
      of each period less the model's error averaged over the currents at the period's two
      ends, as `simulate(..., observer_u_dt=...)` hands it in the loop. Default `None`:
      the voltages are the applied ones and are used as they are.

    **Returns:** `(theta_hat, w_hat)`, each (N,): the estimated electrical angle at t_k
    (rad, wrapped to (-pi, pi]) and speed (rad/s).
    """
    est = replay_estimates(observer, data, u_ab, i_ab, t=t, T_s=T_s, theta0=theta0, w0=w0,
                           observer_scale=observer_scale, inverter=inverter)
    return est.theta_hat, est.w_hat


def replay_estimates(observer: AbstractObserver, data=None, u_ab=None, i_ab=None, *,
                     t=None, T_s=None, theta0=None, w0=None, observer_scale=None,
                     inverter=None):
    """`replay`, returning the `Estimate` at every sample: `theta_hat` (N,), `w_hat`
    (N,) and every observer-specific estimate in `extras` (leading axis N; names and
    units in the observer class's `extras`)."""
    if not isinstance(observer, AbstractObserver):
        raise ValueError(
            f"`replay(observer=...)` must be an `AbstractObserver`; got "
            f"{type(observer).__name__}."
        )
    t, u_ab, i_ab = _arrays(data, u_ab, i_ab, t)
    u_ab, i_ab, T_s = _checked(u_ab, i_ab, t, T_s)
    n = i_ab.shape[0]
    scales = {}
    if observer_scale:
        scales = {k: jnp.broadcast_to(jnp.asarray(v), (n,)) for k, v in
                  observer_scale.items()}
    dtype = jnp.result_type(i_ab.dtype, u_ab.dtype)
    if theta0 is None and w0 is None:
        pass  # unknown: `_scan` catches a turning rotor from the first samples
    else:
        theta0 = _finite_scalar("theta0", "rad", 0.0 if theta0 is None else theta0, dtype)
        w0 = _finite_scalar("w0", "rad/s", 0.0 if w0 is None else w0, dtype)
    if inverter is not None and not isinstance(inverter, Inverter):
        raise ValueError(f"`replay(inverter=...)` must be a `pmsmjax.Inverter` (e.g. "
                         f"`drive.inverter`) or None; got {type(inverter).__name__}.")
    # the observer's and inverter's Python floats as traced values: another design or
    # model replays with the compiled program (pmsmjax._sim._batching.values_as_arrays);
    # checks that need the observer's concrete values run first
    observer.check_values(T_s)
    observer, inverter = values_as_arrays((observer, inverter), dtype)
    return _scan(observer, u_ab, i_ab, T_s, theta0, w0, scales, inverter)
