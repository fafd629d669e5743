r"""Catching a turning rotor in the loop: any observer, re-started from the back-EMF of the
first samples (a drive's catch-on-the-fly; not part of any of the papers).

`pmsmjax.flying_start` reads a turning rotor's angle and speed off a recording's first
samples, so that `replay` can start an observer near its lock. A drive switched on while
its rotor turns needs the same in the loop, where the samples arrive one at a time:
`FlyingCatch(observer)` runs `observer` as it is and, from the same samples, accumulates
the model back-EMF

$$\hat e_{k-1/2} = u_{k-1} - \hat R_s\frac{i_{k-1} + i_k}{2} - \hat L_q\frac{i_k -
i_{k-1}}{T_s}$$

(the voltage held over the period that ended at $t_k$; any current, the drive's current
loop may run meanwhile) and its rotation between successive periods (the exact increment
$\mathrm{atan2}(\hat e_{k-3/2}\times\hat e_{k-1/2}, \hat e_{k-3/2}\cdot\hat e_{k-1/2})$).
At $k = n$ (`n` periods, default 64) the mean increment over $T_s$ is the speed
$\hat\omega_c$ and the direction of the last $\hat e$, advanced by half a period, the angle
($\theta = \mathrm{atan2}(-\sigma\hat e_\alpha, \sigma\hat e_\beta)$, $\sigma =
\mathrm{sign}\,\hat\omega_c$: `back_emf_angle`, as `flying_start`). If these show a
turning rotor, the observer's state is replaced by `observer.init(theta, w)` at that
sample; otherwise it runs on untouched (a rotor at rest or too slow: nothing to catch,
and the drive's start-up, e.g. `IfStartup`, takes over).

*Turning* means: the back-EMF is more than `TURNING_FRACTION` (a fifth) of the voltage
on average over the window and it agrees with the speed it turns at, $\frac12 <
\overline{|\hat e|}/(|\hat\omega_c|\hat\psi_f) < 2$ (differentiated current noise at
standstill can be as large as the resistive drop, but its increments are random, so the
speed it implies is far from the one its magnitude implies).

The wrapper is pure and scan friendly (every decision a `jnp.where`); its analysis
(error dynamics, equilibria, design) is the wrapped observer's: after the catch it is
that observer (`WrappedObserver`). Its `motor` is the wrapped observer's machine model
(replace it with `with_motor`, or scale it in `simulate`, and both use the new one).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._data._flying_start import model_back_emf
from .._frames import back_emf_angle, rotation_between, wrap_angle
from .._plant._params import PMSMParams
from ._base import AbstractObserver, Estimate, Measurement
from ._wrapper import WrappedObserver


#: A window is taken to show a turning rotor when its mean model back-EMF exceeds this
#: fraction of its mean voltage (the same threshold as `pmsmjax.unknown_start`).
TURNING_FRACTION = 0.2


class CatchState(eqx.Module):
    """State of `FlyingCatch`: the wrapped observer's `inner`, the sample count `k`, the
    previous current `i_prev` (A) and model back-EMF `e_prev` (V), the summed rotation
    `turn` (rad) and the summed magnitudes of the back-EMF `e_sum` and of the voltage
    `u_sum` (V)."""

    inner: object
    k: jnp.ndarray
    i_prev: jnp.ndarray
    e_prev: jnp.ndarray
    turn: jnp.ndarray
    e_sum: jnp.ndarray
    u_sum: jnp.ndarray


class FlyingCatch(WrappedObserver):
    """`observer` re-started from the back-EMF of the first `n` periods where they show a
    turning rotor (see the module docstring).

    **Arguments:**

    - `observer`: any `AbstractObserver` with a `PMSMParams` machine model.
    - `n`: periods in the window (int, >= 3): 64 (8 ms at 125 us) by default.
    """

    observer: AbstractObserver
    motor: PMSMParams
    n: int = eqx.field(static=True, default=64)

    def __init__(self, observer: AbstractObserver, n: int = 64):
        self._check_wrapped("FlyingCatch", observer, FlyingCatch)
        if not isinstance(getattr(observer, "motor", None), PMSMParams):
            raise ValueError(f"`FlyingCatch`: {type(observer).__name__} has no machine "
                             "model (`motor`, a PMSMParams) to read the back-EMF with.")
        if isinstance(n, bool) or not isinstance(n, int) or n < 3:
            raise ValueError(f"`FlyingCatch(n=...)` must be an int >= 3 (periods); got "
                             f"{n!r}.")
        self.observer = observer
        self.motor = observer.motor
        self.n = n

    def _rewrap(self, observer: AbstractObserver) -> FlyingCatch:
        return FlyingCatch(observer, self.n)

    def init(self, theta0=0.0, w0=0.0) -> CatchState:
        inner = self._inner().init(theta0=theta0, w0=w0)
        dtype = jnp.result_type(jnp.asarray(theta0), jnp.asarray(w0), float)
        zero = jnp.zeros((), dtype)
        return CatchState(inner=inner, k=jnp.zeros((), jnp.int32),
                          i_prev=jnp.zeros(2, dtype), e_prev=jnp.zeros(2, dtype),
                          turn=zero, e_sum=zero, u_sum=zero)

    def step(self, state: CatchState, meas: Measurement, T_s):
        obs = self._inner()
        m = self.motor
        dtype = state.turn.dtype
        i_k = jnp.asarray(meas.i_ab).astype(dtype)
        u = jnp.asarray(meas.u_ab).astype(dtype)
        k = state.k
        # the model back-EMF of the period that ended now (from k = 1 on)
        e = model_back_emf(m, u, state.i_prev, i_k, T_s)
        inc = rotation_between(state.e_prev, e)
        window = (k >= 1) & (k <= self.n)
        turn = state.turn + jnp.where(window & (k >= 2), inc, 0.0)
        e_sum = state.e_sum + jnp.where(window, jnp.sqrt(jnp.sum(e ** 2)), 0.0)
        u_sum = state.u_sum + jnp.where(window, jnp.sqrt(jnp.sum(u ** 2)), 0.0)
        inner, est = obs.step(state.inner, meas, T_s)
        # at k = n: the catch
        w_c = turn / ((self.n - 1) * T_s)
        sg = jnp.where(w_c < 0, -1.0, 1.0)
        th_c = wrap_angle(back_emf_angle(e, sg) + 0.5 * w_c * T_s)
        e_mean = e_sum / self.n
        psi = jnp.abs(m.psi_f)
        ratio = e_mean / jnp.maximum(jnp.abs(w_c) * psi, jnp.finfo(dtype).tiny)
        turning = (e_sum > TURNING_FRACTION * u_sum) & (ratio > 0.5) & (ratio < 2.0) & \
            jnp.isfinite(w_c) & jnp.isfinite(th_c)
        catch = (k == self.n) & turning
        fresh = obs.init(theta0=th_c, w0=w_c)
        # a started observer: one step from the caught estimate at the present sample, so
        # that its internal "previous sample" is this one
        # (a branch: the restarted state is computed at the catch sample only, except
        # under vmap, where both are)
        inner = jax.lax.cond(catch, lambda: _started(obs, fresh, meas, T_s), lambda: inner)
        est = _select(catch, Estimate(theta_hat=th_c.astype(est.theta_hat.dtype),
                                      w_hat=w_c.astype(est.w_hat.dtype),
                                      extras=est.extras), est)
        new = CatchState(inner=inner, k=jnp.minimum(k + 1, self.n + 1), i_prev=i_k, e_prev=e,
                         turn=turn, e_sum=e_sum, u_sum=u_sum)
        return new, est


def _select(pred, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(pred, x, y), a, b)


def _started(obs, fresh, meas, T_s):
    """The state `fresh` (from `init`) as after its first sample `meas`: observers set
    their "previous sample" memory on the first step and hold their estimate there."""
    state, _ = obs.step(fresh, meas, T_s)
    return state
