"""The stator-flux error coordinates that the flux observers share (zhang2022's ESO,
LESO and AFO, the reduced-order and the nonlinear flux observer): the flux error in the
observer's estimated frame, the angle error and the speed error, all true minus
estimate, against the true machine's stator flux."""

from __future__ import annotations

import jax.numpy as jnp

from .._frames import park, rotate, wrap_angle
from .._plant._params import PMSMParams
from ._base import PlantPoint


def model_flux_dq(motor: PMSMParams, i_dq, psi_f=None):
    """$[L_d i_d + \\psi_f,\\ L_q i_q]$ of `motor` (V s) at the current `i_dq` (A, the
    frame of the rotor or of an estimate of it); `psi_f` replaces `motor.psi_f` (V s,
    e.g. an adapted PM flux)."""
    psi_f = motor.psi_f if psi_f is None else psi_f
    return jnp.stack([motor.L_d * i_dq[..., 0] + psi_f, motor.L_q * i_dq[..., 1]], -1)


def true_flux_ab(plant: PMSMParams, theta, i_ab):
    """The true machine's stator flux (V s, stationary frame) at rotor angle `theta`
    (rad) and current `i_ab` (A): the fundamental PM flux, as in the error dynamics."""
    return rotate(model_flux_dq(plant, park(i_ab, theta)), theta)


def flux_errors(psi_ab, theta, w, truth: PlantPoint, plant: PMSMParams):
    """`(psi_d, psi_q, theta, w)` errors of a flux estimate `psi_ab` (V s, stationary),
    angle `theta` (rad) and speed `w` (rad/s) against `truth`: the flux error in the
    estimated frame."""
    e = park(true_flux_ab(plant, truth.theta, truth.i_ab) - psi_ab, theta)
    return jnp.concatenate([e, jnp.stack([wrap_angle(truth.theta - theta), truth.w_m - w])])


def flux_estimates(x, truth: PlantPoint, plant: PMSMParams):
    """The inverse of `flux_errors`: `(psi_ab, theta, w)` whose errors against `truth`
    are `x[:4]`."""
    x = jnp.asarray(x)
    theta = wrap_angle(truth.theta - x[2])
    i_ab = jnp.asarray(truth.i_ab, x.dtype)
    return true_flux_ab(plant, truth.theta, i_ab) - rotate(x[:2], theta), theta, \
        truth.w_m - x[3]


def flux_error_scale(flux, w_m):
    """Sizes of `(psi_d, psi_q, theta, w)` at an operating point: the flux magnitude
    `flux` (V s) for both flux errors, 1 rad, and |w_m| (rad/s; 1 where either is 0)."""
    flux = jnp.where(flux > 0, flux, 1.0)
    aw = jnp.abs(w_m)
    return jnp.stack([flux, flux, jnp.ones_like(flux), jnp.where(aw > 0, aw, 1.0)])


def previous_current_dq(state, meas):
    """The current a flux observer's step forms its correction at: $i_{k-1}$ (the state's
    `i_prev`; $i_k$ at the first sample, which initialises the flux) in the frame of the
    state's angle estimate. Its current-scheduled model is evaluated there
    (`AbstractObserver._schedule_current`)."""
    i_ab = jnp.where(state.started, state.i_prev, jnp.asarray(meas.i_ab))
    return park(i_ab, state.theta)
