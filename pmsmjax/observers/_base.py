"""The observer interface shared by every position/speed estimator.

Timing (the same for the closed loop and for offline replay): at sampling instant t_k
an observer receives a `Measurement` with the currents sampled at t_k and the stator
voltage that was applied over the previous period [t_{k-1}, t_k) (zero at k = 0). It
returns the `Estimate` valid at t_k and its state for the next instant. Everything it
needs from the past (e.g. i_{k-1} for an integration rule) lives in its state, so the
step is a pure function of `(state, measurement, T_s)`.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp

from .._frames import wrap_angle


class Measurement(eqx.Module):
    """What an observer sees at one sampling instant.

    - `i_ab`: stator current sampled at t_k, stationary frame (A, shape (2,)).
    - `u_ab`: stator voltage applied over [t_{k-1}, t_k), stationary frame (V, (2,)).
    - `theta`: encoder angle at t_k (rad, electrical); NaN when no encoder is present.
      Only sensored observers may use it.
    - `w_m`: encoder speed at t_k (rad/s, electrical); NaN when absent.
    """

    i_ab: jnp.ndarray
    u_ab: jnp.ndarray
    theta: jnp.ndarray
    w_m: jnp.ndarray


class Estimate(eqx.Module):
    """Observer output at one sampling instant.

    - `theta_hat`: estimated electrical rotor angle, wrapped to (-pi, pi] (rad).
    - `w_hat`: estimated electrical speed (rad/s).
    """

    theta_hat: jnp.ndarray
    w_hat: jnp.ndarray


class AbstractObserver(eqx.Module):
    """Base class of all observers: pure `init` and `step`.

    Subclasses implement

    - `init(theta0=0.0, w0=0.0) -> state`: the state at k = 0, with the initial angle
      estimate `theta0` (rad) and speed estimate `w0` (rad/s).
    - `step(state, meas, T_s) -> (state, Estimate)`: see the module docstring for timing.

    Observers that model the machine keep their own `PMSMParams` in a field `motor`, so
    that observer parameters can differ from the plant's (mismatch studies).
    """

    @abc.abstractmethod
    def init(self, theta0=0.0, w0=0.0):
        ...

    @abc.abstractmethod
    def step(self, state, meas: Measurement, T_s) -> tuple[object, Estimate]:
        ...


class SensoredObserver(AbstractObserver):
    """Passes the encoder angle and speed through (sensored control).

    The state is empty; `init`'s arguments are ignored.
    """

    def init(self, theta0=0.0, w0=0.0):
        del theta0, w0
        return ()

    def step(self, state, meas: Measurement, T_s):
        del T_s
        return state, Estimate(theta_hat=wrap_angle(meas.theta), w_hat=meas.w_m)
