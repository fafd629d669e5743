r"""The discrete observer in error coordinates: one real `observer.step` as a map of the
error state (`discrete_error_map`), its Jacobian and poles, and runs of it, for the
consistency of the discrete observer with its continuous error dynamics (any observer)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._frames import rotate
from .._plant._params import PMSMParams
from ..observers import AbstractObserver, Measurement, OperatingPoint, PlantPoint
from ._args import _program_inputs, check_observer, check_plant


def _true_flux_ab(plant: PMSMParams, theta, i_ab):
    """The true machine's stator flux (V s, stator frame) at rotor angle `theta` (rad)
    and stator current `i_ab` (A)."""
    i_dq = rotate(i_ab, -theta)
    psi = jnp.stack([plant.L_d * i_dq[0] + plant.psi_f, plant.L_q * i_dq[1]])
    return rotate(psi, theta)


def discrete_error_map(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq, T_s, *,
                       theta_k=0.0, n_fixed_point: int = 3):
    r"""One real `observer.step` as a map of error coordinates $x_k \mapsto x_{k+1}$.

    The plant turns at constant electrical speed `w_m` (rad/s); ideal current control
    holds the current at `i_dq` (A) in the observer's estimated frame, so the sampled
    current at $t_{k+1}$ is $e^{\hat\theta_{k+1}J} i_{dq}$ (a fixed point with the
    observer's own estimate, solved by `n_fixed_point` iterations); the voltage held over
    $[t_k, t_{k+1})$ is the one that moves the true flux between the two samples with a
    trapezoidal resistive drop. At $t_k$ the rotor is at `theta_k` (rad).

    Returns `fn(x_k) -> x_{k+1}` (pure; `jax.jacfwd(fn)(x)` is the Jacobian of the
    discrete observer, which agrees with $I + T_s A$ of `linearization` to $O(T_s^2)$).
    """
    check_observer("discrete_error_map", observer)
    check_plant("discrete_error_map", plant)
    a = observer.coordinates.angle
    i0 = jnp.asarray(i_dq, float)

    def fn(x):
        x = jnp.asarray(x)
        dtype = x.dtype
        th0 = jnp.asarray(theta_k, dtype)
        th1 = th0 + w_m * T_s
        w = jnp.asarray(w_m, dtype)
        i_k = rotate(i0, th0 - x[a]).astype(dtype)
        truth0 = PlantPoint(theta=th0, w_m=w, i_ab=i_k)
        state = observer.observer_state(x, truth0, plant)
        psi0 = _true_flux_ab(plant, th0, i_k)
        i_next = rotate(i0, th1 - x[a])
        nan = jnp.full((), jnp.nan, dtype)
        for _ in range(n_fixed_point):
            u = (_true_flux_ab(plant, th1, i_next) - psi0) / T_s \
                + 0.5 * plant.R_s * (i_k + i_next)
            new, est = observer.step(state, Measurement(i_ab=i_next, u_ab=u, theta=nan,
                                                        w_m=nan), T_s)
            i_next = rotate(i0, est.theta_hat)
        return observer.error_state(new, PlantPoint(theta=th1, w_m=w, i_ab=i_next), plant)

    return fn


def discrete_jacobian(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq, T_s, *,
                      x=None, theta_k=0.0):
    r"""The Jacobian $\partial x_{k+1} / \partial x_k$ of one real `observer.step` in
    error coordinates (`discrete_error_map`), at the error state `x` (SI units; default
    the designed equilibrium, `observer.designed_error`).

    `w_m` (rad/s), `i_dq` (A, estimated frame), `T_s` (s) and `theta_k` (rad) as in
    `discrete_error_map`. It agrees with $I + T_s A$ of `linearization` to $O(T_s^2)$
    (tested). Compiled once per observer structure: the speed, current, period, angle and
    state are the program's inputs, so a sweep over any of them, or `jax.vmap` over them,
    reuses one program (run op by op, one Jacobian of a LESO took seconds). Returns
    `(n, n)`."""
    observer, plant = _program_inputs(observer, plant)
    return _discrete_jacobian(observer, plant, jnp.asarray(w_m, float),
                              jnp.asarray(i_dq, float), jnp.asarray(T_s, float),
                              jnp.asarray(theta_k, float),
                              None if x is None else jnp.asarray(x, float))


@eqx.filter_jit
def _discrete_jacobian(observer, plant, w_m, i_dq, T_s, theta_k, x):
    if x is None:
        x = observer.designed_error(OperatingPoint(w_m, i_dq), plant)
    fn = discrete_error_map(observer, plant, w_m, i_dq, T_s, theta_k=theta_k)
    return jax.jacfwd(fn)(x)


def discrete_poles(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq, T_s, *,
                   theta_k=0.0):
    r"""The poles of the discrete observer: the eigenvalues $z$ of the Jacobian of one
    real `observer.step` (`discrete_jacobian`) at its designed equilibrium
    (`observer.designed_error`; with a mismatched model pass the equilibrium of
    `equilibria` to `discrete_jacobian` instead).

    $|z| < 1$ for every pole: locally stable at sampling period `T_s` (s). For small
    `T_s` they approach $e^{T_s\lambda}$ of the continuous `linearization`'s
    eigenvalues $\lambda$ (tested); at the firmware's `T_s` they say how far the real
    observer is from its continuous design. `w_m` (rad/s) and `i_dq` (A, estimated
    frame) as in `discrete_error_map`; pure, so `jax.vmap` it over speeds. Returns the
    `(n,)` complex eigenvalues, unordered."""
    return jnp.linalg.eigvals(discrete_jacobian(observer, plant, w_m, i_dq, T_s,
                                                theta_k=theta_k))


def discrete_error_run(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq, T_s,
                       x0, n_steps: int):
    """Iterate `discrete_error_map` `n_steps` times from `x0` (the discrete observer in a
    closed loop with ideal current control at constant speed). Returns the error
    coordinates `(n_steps + 1, n)` at t_0 ... t_N (SI units). Compiled once per observer
    structure and `n_steps` (static), as `discrete_jacobian`: a new speed, current, period,
    start or design reuses the program (run op by op, every call compiled its loop anew)."""
    check_observer("discrete_error_run", observer)
    check_plant("discrete_error_run", plant)
    if not isinstance(n_steps, int) or n_steps < 1:
        raise ValueError(f"`discrete_error_run(n_steps=...)` must be an int >= 1; got "
                         f"{n_steps!r}.")
    observer, plant = _program_inputs(observer, plant)
    return _discrete_error_run(observer, plant, jnp.asarray(w_m, float),
                               jnp.asarray(i_dq, float), jnp.asarray(T_s, float),
                               jnp.asarray(x0, float), n_steps)


@eqx.filter_jit
def _discrete_error_run(observer, plant, w_m, i_dq, T_s, x0, n_steps):
    def body(carry, k):
        x = carry
        fn = discrete_error_map(observer, plant, w_m, i_dq, T_s, theta_k=k * w_m * T_s)
        x1 = fn(x)
        return x1, x1

    _, xs = jax.lax.scan(body, x0, jnp.arange(n_steps, dtype=x0.dtype))
    return jnp.concatenate([x0[None], xs], 0)
