r"""The speed a drive takes from an observer's angle: a type-2 tracking loop on the angle
estimate (a drive's usual speed calculation; not part of any of the papers).

Several observers estimate the speed as a state of their own, adapted from a current or
flux error: zhang2022's AFO, morawiec2023's rotor-flux observer, Stumper's parallel-model
estimator. With the observer's model off (a saturated machine against its constant
model, or any parameter error), that speed estimate answers the q current: on the
saturated preset the rotor-flux observer's $|\partial(\hat\omega - \omega)/\partial i_q|$
reaches 7-24 rad/s per A near its own 55-60 Hz mode, and a speed PI on it closes a loop
that oscillates and loses lock from a tenth of rated load (docs/saturation.md,
`docs/figures/make_rotor_flux_speed_loop.py`). Its *angle* does not: the same runs with
the true speed given to the controller hold with the analysis's static error.

`SpeedFromAngle(observer)` hands the drive the speed of the observer's angle estimate
instead. Each period, with the tracker's angle $\vartheta$ and speed $\varpi$,

$$\vartheta^- = \vartheta_{k-1} + T_s\varpi_{k-1},\quad
\varepsilon = \mathrm{wrap}(\hat\theta_k - \vartheta^-),\quad
\varpi_k = \varpi_{k-1} + T_s k_i\varepsilon,\quad
\vartheta_k = \mathrm{wrap}(\vartheta^- + T_s k_p\varepsilon),$$

$k_p = 2\zeta\omega_t$, $k_i = \omega_t^2$: for small $T_s\omega_t$ the tracking error
obeys $\ddot\varepsilon + k_p\dot\varepsilon + k_i\varepsilon = \dot\omega$ (natural
frequency `w_track`, damping `zeta`), so a constant speed is tracked without error and a
speed ramp $a$ with a speed lag $k_p a/k_i = 2\zeta a/\omega_t$ (the tracker's own angle
lags by $a/k_i$; 33 rad/s at the default on zhang750 ramped from 0 to 0.5 p.u. in
0.2 s, 2.5 % of its rated speed, gone within about $5/\omega_t$ = 27 ms of the ramp's
end). The output angle is the observer's own $\hat\theta_k$ (no lag added); the output
speed is the integral state $\varpi_k$ (the proportional path would carry the angle's
noise). The wrapped observer runs unchanged, its own speed estimate in
`Estimate.extras["w_observer"]`.

**Bandwidth.** `w_track` sits between the speed loop and the observer's own modes: too
slow and its lag enters the speed loop (on the saturated preset, 60 rad/s against the
default 5 Hz = 31 rad/s speed loop still oscillates), too fast and the angle's response
to the current passes through (500 rad/s for the rotor-flux observer). The default,
2 pi 30 Hz = 188 rad/s, is six times the default speed loop; on the saturated preset at
0.5 p.u. 120-250 rad/s hold the rotor-flux observer and the parallel-model estimator
at 0.3 and 0.6 of rated load (measured in docs/saturation.md).

The angle is tracked through zero speed and reversals as it is estimated (the loop
tracks an angle, not a back-EMF, so it has no sign ambiguity of its own).
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._frames import wrap_angle
from .._plant._params import PMSMParams
from .._validate import check_positive
from ._base import AbstractObserver, Estimate, Measurement
from ._wrapper import WrappedObserver


#: The default natural frequency of the tracker (Hz, and in rad/s): 30 Hz (module
#: docstring).
W_TRACK_HZ = 30.0
W_TRACK = 2.0 * math.pi * W_TRACK_HZ


class TrackerState(eqx.Module):
    """State of `SpeedFromAngle`: the wrapped observer's `inner`, the tracker's angle
    `theta` (rad) and speed `w` (rad/s, electrical)."""

    inner: object
    theta: jnp.ndarray
    w: jnp.ndarray


class SpeedFromAngle(WrappedObserver):
    """`observer` whose speed output is the speed of its angle estimate, through a type-2
    tracking loop (see the module docstring).

    **Arguments:**

    - `observer`: any `AbstractObserver`.
    - `w_track`: the tracker's natural frequency (rad/s), > 0; default 2 pi 30 Hz.
    - `zeta`: its damping (-), > 0; default 1 (critically damped).
    """

    #: C code (`pmsmjax export-c`): the wrapped observer's, then the tracking loop.
    c_emitter: ClassVar[str | None] = "_tracker:emit"

    observer: AbstractObserver
    motor: PMSMParams | None
    w_track: float = W_TRACK
    zeta: float = 1.0

    def __init__(self, observer: AbstractObserver, w_track: float = W_TRACK,
                 zeta: float = 1.0):
        self._check_wrapped("SpeedFromAngle", observer, SpeedFromAngle)
        self.observer = observer
        self.motor = observer.motor
        self.w_track = w_track
        self.zeta = zeta

    def __check_init__(self):
        check_positive("SpeedFromAngle", "w_track", self.w_track, "rad/s")
        check_positive("SpeedFromAngle", "zeta", self.zeta, "-")

    def _rewrap(self, observer: AbstractObserver) -> SpeedFromAngle:
        return SpeedFromAngle(observer, self.w_track, self.zeta)

    def gains(self):
        """`(k_p, k_i)` (rad/s, rad/s^2): `2 zeta w_track`, `w_track^2` (the step and its
        generated C both take them from here)."""
        return 2.0 * self.zeta * self.w_track, self.w_track ** 2

    @property
    def extras(self):
        return {**self.observer.extras,
                "w_observer": "rad/s, the wrapped observer's own speed estimate"}

    def check_values(self, T_s) -> None:
        super().check_values(T_s)
        self._inner().check_values(T_s)

    def init(self, theta0=0.0, w0=0.0) -> TrackerState:
        inner = self._inner().init(theta0=theta0, w0=w0)
        dtype = jnp.result_type(jnp.asarray(theta0), jnp.asarray(w0), float)
        return TrackerState(inner=inner, theta=jnp.asarray(theta0, dtype),
                            w=jnp.asarray(w0, dtype))

    def step(self, state: TrackerState, meas: Measurement, T_s):
        inner, est = self._inner().step(state.inner, meas, T_s)
        k_p, k_i = self.gains()
        pred = state.theta + T_s * state.w
        eps = wrap_angle(est.theta_hat - pred)
        w = state.w + (T_s * k_i) * eps
        theta = wrap_angle(pred + (T_s * k_p) * eps)
        dtype = state.w.dtype
        new = TrackerState(inner=inner, theta=theta.astype(dtype), w=w.astype(dtype))
        return new, Estimate(theta_hat=est.theta_hat, w_hat=w.astype(est.w_hat.dtype),
                             extras={**est.extras, "w_observer": est.w_hat})
