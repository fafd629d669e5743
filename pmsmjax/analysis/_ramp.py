r"""Validation of the slowly-varying certificate (`pmsmjax.analysis._lyapunov`) by
simulation: the zhang2022 ESO/LESO error dynamics while the speed ramps between two
speeds (`simulate_ramp`), either zhang2022 (40) as the certificate sees it
(`model="paper"`) or the observer's true error dynamics, with the gains scheduled at the
estimated speed and the acceleration forcing (`model="observer"`), and the fastest ramp
that still converges (`fastest_converging_ramp`).
"""

from __future__ import annotations

import math

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._frames import wrap_angle
from .._plant._params import Drive
from .._sim._batching import values_as_arrays
from ..observers import AbstractFluxObserver
from ._linearize import check_frame, eso_rhs
from ._lyapunov import _as_observer, _ScaledDynamics, _state_scale


MODELS = ("paper", "observer")


class RampRun(eqx.Module):
    """A simulated speed ramp of the error dynamics.

    - `t` (s), `x` (`(n, 4)`, SI state), `w` (rad/s): saved trajectory.
    - `theta_err_max`: largest |theta_err| over the run (rad, not wrapped).
    - `final_norm`: ||z|| at the end (scaled state, angle wrapped).
    - `converged`: at the end the wrapped angle error is below `tol_deg` and the flux
      and speed errors below 1e-3 (scaled), i.e. the error is back at an equivalent of
      the origin (modulo 2 pi). `slipped`: the angle error went round by at least one
      turn on the way (the position estimate is still right modulo 2 pi).
    - `status`: 0, or -1 if the solver failed.
    """

    t: jnp.ndarray
    x: jnp.ndarray
    w: jnp.ndarray
    theta_err_max: jnp.ndarray
    final_norm: jnp.ndarray
    converged: jnp.ndarray
    slipped: jnp.ndarray
    status: jnp.ndarray


def _ramp_speed(t, w_start, w_end, rate):
    dur = jnp.abs(w_end - w_start) / rate
    s = jnp.clip(t / jnp.where(dur > 0, dur, 1.0), 0.0, 1.0)  # w_end = w_start: constant
    w = w_start + (w_end - w_start) * s
    wdot = jnp.where((t >= 0) & (t < dur), jnp.sign(w_end - w_start) * rate, 0.0)
    return w, wdot


@eqx.filter_jit
def _simulate_ramp(dyn: _ScaledDynamics, x0, w_start, w_end, rate, t_hold, model, n_save,
                   tol, max_steps):
    obs = dyn.observer
    a, eta = obs.feedback_parameters()
    dur = jnp.abs(w_end - w_start) / rate
    t1 = dur + t_hold

    def rhs(t, x, args):
        w, wdot = _ramp_speed(t, w_start, w_end, rate)
        if model == "observer":
            g = obs.linear_gains(w - x[3], dyn.i0)  # the observer schedules at w_hat
            f = eso_rhs(x, w, dyn.i0, g, dyn.plant, obs.motor, a, eta, dyn.frame)
            return f.at[3].add(wdot)
        return eso_rhs(x, w, dyn.i0, obs.linear_gains(w, dyn.i0), dyn.plant, obs.motor, a,
                       eta, dyn.frame)

    ts = jnp.linspace(0.0, t1, n_save)
    ctrl = dfx.ClipStepSizeController(dfx.PIDController(rtol=1e-7, atol=1e-9),
                                      jump_ts=jnp.reshape(dur, (1,)))
    sol = dfx.diffeqsolve(dfx.ODETerm(rhs), dfx.Tsit5(), 0.0, t1, None, x0,
                          saveat=dfx.SaveAt(ts=ts), stepsize_controller=ctrl,
                          max_steps=max_steps, throw=False)
    x = sol.ys
    w = jax.vmap(lambda t: _ramp_speed(t, w_start, w_end, rate)[0])(ts)
    th_max = jnp.max(jnp.abs(x[:, 2]))
    zf = (x[-1] * dyn.d).at[2].set(wrap_angle(x[-1, 2]))
    final = jnp.linalg.norm(zf)
    ok = (sol.result == dfx.RESULTS.successful) & jnp.all(jnp.isfinite(x))
    conv = ok & (jnp.abs(zf[2]) < tol) & (jnp.linalg.norm(zf[jnp.array([0, 1, 3])]) < 1e-3)
    return RampRun(t=ts, x=x, w=w, theta_err_max=th_max, final_norm=final, converged=conv,
                   slipped=jnp.abs(x[-1, 2]) > math.pi,
                   status=jnp.where(ok, 0, -1).astype(jnp.int32))


def simulate_ramp(drive: Drive, design, speeds=(0.2, 1.0), rate=1.0,
                  *, x0=None, theta0_deg=10.0, i_dq=(0.0, 0.0), model: str = "paper",
                  frame: str = "observer", a=1.0, eta=1.0, t_hold=None, n_save=2001,
                  tol_deg=0.05, max_steps=2_000_000, scale="pu") -> RampRun:
    r"""Simulate the error dynamics while the speed ramps from `speeds[0]` to `speeds[1]`
    (p.u.) at `rate` (rad/s^2), then holds for `t_hold` (s; default 20/sigma of the end
    speed, i.e. ample settling time). Equal speeds give a constant-speed run.

    `model="paper"`: zhang2022 (40), gains scheduled at the true speed, no acceleration forcing;
    `model="observer"`: the observer's true error dynamics, gains scheduled at
    $\hat\omega$ and $+\dot\omega$ in $\dot{\tilde\omega}$. `x0` (SI) or `theta0_deg`:
    the initial error. Convergence: see `RampRun` (modulo 2 pi; cycle slips are
    reported in `slipped`).
    """
    if model not in MODELS:
        raise ValueError(f"`simulate_ramp(model=...)` must be one of {MODELS}; got {model!r}.")
    check_frame("simulate_ramp", frame)
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"`simulate_ramp(rate=...)` (rad/s^2) must be finite and > 0; "
                         f"got {rate!r}.")
    dtype = jnp.float64
    i0 = jnp.asarray(i_dq, dtype) * drive.base.I_b
    observer = _as_observer("simulate_ramp", drive, design, a, eta)
    if not isinstance(observer, AbstractFluxObserver):
        raise ValueError("`simulate_ramp` simulates the zhang2022 ESO/LESO error dynamics "
                         f"(11)/(40); got {type(observer).__name__}.")
    dyn = _ScaledDynamics(observer=values_as_arrays(observer, dtype),
                          plant=values_as_arrays(drive.three_phase_motor, dtype), i0=i0,
                          d=_state_scale(drive, observer, scale, dtype), frame=frame)
    w_start, w_end = (float(s) * float(drive.w_rated) for s in speeds)
    if t_hold is None:
        A = dyn.A(jnp.asarray(w_end, dtype))
        sig = float(-jnp.max(jnp.real(jnp.linalg.eigvals(A))))
        t_hold = 20.0 / max(sig, 1e-3)
    x0 = jnp.array([0.0, 0.0, math.radians(theta0_deg), 0.0], dtype) if x0 is None else \
        jnp.asarray(x0, dtype)
    return _simulate_ramp(dyn, x0, jnp.asarray(w_start, dtype), jnp.asarray(w_end, dtype),
                          jnp.asarray(rate, dtype), jnp.asarray(t_hold, dtype), model,
                          n_save, math.radians(tol_deg), max_steps)


def fastest_converging_ramp(drive: Drive, design, speeds=(0.2, 1.0),
                            *, rate_lo=1.0, rate_hi=1e9, n_bisect=24, **kw):
    """Largest ramp rate (rad/s^2) in [rate_lo, rate_hi] for which `simulate_ramp`
    converges, by bisection in log(rate) (assumes convergence is monotone in the rate,
    which it is in every case we checked; the runs at both ends are returned too).

    Returns `(rate, runs)` where `runs` is a list of `(rate, RampRun)`; `rate` is
    `rate_hi` if even that converges (a speed step then converges too) and NaN if
    `rate_lo` does not.
    """
    runs = []

    def ok(rate):
        run = simulate_ramp(drive, design, speeds, rate, **kw)
        runs.append((rate, run))
        return bool(run.converged)

    if not ok(rate_lo):
        return float("nan"), runs
    if ok(rate_hi):
        return float(rate_hi), runs
    lo, hi = math.log(rate_lo), math.log(rate_hi)
    for _ in range(n_bisect):
        mid = 0.5 * (lo + hi)
        if ok(math.exp(mid)):
            lo = mid
        else:
            hi = mid
    return math.exp(lo), runs
