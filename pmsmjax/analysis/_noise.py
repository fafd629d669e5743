r"""What current-sensor noise does to an observer's estimates: the static angle error
against the noise, the trade an observer's bandwidth makes (li-fa-leso's C-LESO lags by
design, 11.4 deg on `li_dtp` at 0.5 p.u.; a faster one lags less and passes more noise).

**Setting** (a replay, `pmsmjax.replay`): the rotor turns at the constant electrical speed
$\omega$ (`op.w_m`), the current is the constant $i_{dq}$ (`op.i_dq`, in the *true* rotor
frame: the recorded currents do not follow the estimate) and the voltage over
$[t_k, t_{k+1})$ moves the true flux between the two samples with a trapezoidal
resistive drop, as in `discrete_error_map`. The sampled current carries white noise,
independent between the two axes and between samples, of standard deviation $\sigma$
per axis (`noise_std`, A); a current loop's response to the noise is not modelled.

**Linearisation.** One real `observer.step` is a map $x_{k+1} = F(x_k, v_k, v_{k+1})$ of
the observer's error coordinates, with the outputs $y_{k+1} = (\tilde\theta,
\hat\omega - \omega)$ of the same step; $v_k$ is the noise on the sample at $t_k$, which
the state remembers (`i_prev`: the observers' exact discretisations use both ends of the
period; without it the noise would count once where it acts twice, and the RMS came out
half the replays'), and $v_{k+1}$ the noise on the new sample, both in the rotor frame of
their sample. About the noise-free fixed point $x^*$ (Newton's method from the designed
equilibrium; the static error is $x^*$'s angle coordinate) the state $z_k = (x_k, v_k)$
obeys $z_{k+1} = \Phi_z z_k + \Gamma_z v_{k+1}$, $y_{k+1} = C_z z_k + D v_{k+1}$ with
$\Phi_z = [[\Phi, \Psi], [0, 0]]$, $\Gamma_z = [\Gamma; I]$, $C_z = [C, E]$, the
Jacobians of the running code (`jax.jacfwd`). For an observer whose error dynamics do not
depend on the rotor angle (the contract's `angle_dependent` False) a noise that is white
and isotropic in the stationary frame is white and isotropic in the rotor frame too, so
the steady-state covariance solves the discrete Lyapunov equation

$$P = \Phi_z P\Phi_z^T + \sigma^2\Gamma_z\Gamma_z^T,\qquad
\mathrm{Cov}(y) = C_z P C_z^T + \sigma^2 D D^T,$$

solved exactly as $(I - \Phi_z\otimes\Phi_z)\,\mathrm{vec}P = \sigma^2\,\mathrm{vec}\,
\Gamma_z\Gamma_z^T$. The RMS angle and speed-estimate noise are the square roots of its
diagonal: first order in $\sigma$, valid while the noise keeps the observer near $x^*$.
Measured against noisy replays (tests): the ESO, the C-LESO and the FA-LESO agree at
0.05 A and 0.5 p.u., and the C-LESO at 0.1 p.u. (its speed estimate biased by 0.29 of
the first-order speed noise there: second order). This analysis found the li
observers' PLL assist rectifying noise into a speed bias while it took its direction
from one sample's rotation (`pmsmjax.observers.QuadraturePLL`, "The gate's direction").
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .._frames import rotate, wrap_angle
from .._plant._params import Drive
from ..observers import AbstractObserver, Measurement, OperatingPoint, PlantPoint
from ._args import _program_inputs, check_observer
from ._discrete import _true_flux_ab


#: Newton steps from the designed equilibrium to the replay's noise-free fixed point.
_NEWTON_STEPS = 4


class SensorNoise(eqx.Module):
    """[`sensor_noise`][]'s result at one point (arrays broadcast under `vmap`).

    - `theta_static`: the static angle error (rad, true minus estimate) without noise.
    - `theta_rms`: the RMS angle-estimate noise (rad); `w_rms`: the RMS speed-estimate
      noise (rad/s, electrical); `noise_std`: the current noise they are for (A per axis).
    - `stable`: whether the linearised step is stable (spectral radius below 1); where
      it is not, the noise has no steady state and `theta_rms`, `w_rms` are NaN.
    - `spectral_radius`: the largest eigenvalue modulus of the linearised step (-).
    """

    theta_static: jax.Array
    theta_rms: jax.Array
    w_rms: jax.Array
    noise_std: jax.Array
    stable: jax.Array
    spectral_radius: jax.Array


def sensor_noise(observer: AbstractObserver, drive: Drive, op: OperatingPoint, T_s,
                 noise_std) -> SensorNoise:
    r"""The static angle error and the RMS angle and speed-estimate noise that white
    current-sensor noise causes, at a constant operating point (module docstring).

    **Arguments:**

    - `observer`: any observer of the contract whose error dynamics do not depend on the
      rotor angle (`angle_dependent` False: every observer but morawiec2023's rotor-flux
      one), with its own model and gains.
    - `drive`: the true machine (`drive.three_phase_motor`).
    - `op`: `OperatingPoint(w_m, i_dq)`: electrical speed (rad/s, nonzero) and the
      current (A) in the true rotor frame.
    - `T_s`: sampling period (s); `noise_std`: current noise per axis (A, >= 0).

    Every input may be traced: `jax.vmap` over a design parameter gives the trade
    between the static error and the noise (see `docs/tuning.md`). Returns a
    [`SensorNoise`][].
    """
    check_observer("sensor_noise", observer)
    if type(observer).angle_dependent:
        raise ValueError(
            f"`sensor_noise(observer=...)`: {type(observer).__name__}'s error dynamics "
            "depend on the rotor angle (a periodic system), where an isotropic noise does "
            "not give a constant covariance; the analysis covers observers with "
            "`angle_dependent = False`.")
    if not isinstance(op, OperatingPoint):
        raise ValueError(f"`sensor_noise(op=...)` must be an `OperatingPoint(w_m, i_dq)`; "
                         f"got {type(op).__name__}.")
    observer, plant = _program_inputs(observer, drive.three_phase_motor)
    w, i_dq = jnp.asarray(op.w_m, float), jnp.asarray(op.i_dq, float)
    T_s, sigma = jnp.asarray(T_s, float), jnp.asarray(noise_std, float)
    w = eqx.error_if(w, w == 0, "`sensor_noise`: `op.w_m` must be nonzero (rad/s).")
    T_s = eqx.error_if(T_s, ~(T_s > 0), "`sensor_noise`: `T_s` must be > 0 (s).")
    sigma = eqx.error_if(sigma, ~(sigma >= 0), "`sensor_noise`: `noise_std` must be >= 0 "
                         "(A).")
    return _sensor_noise(observer, plant, w, i_dq, T_s, sigma)


def _memory_fields(observer, state) -> bool:
    """Whether the observer's state remembers the last sampled current (`i_prev`, the
    contract's name for it); a state that remembers measurements otherwise is refused,
    since its noise would be lost between steps."""
    names = [f.name for f in dataclasses.fields(state)]
    other = [n for n in names if "prev" in n and n != "i_prev"]
    nested = [n for n in names if isinstance(getattr(state, n), eqx.Module)]
    if other or nested:
        raise ValueError(
            f"`sensor_noise`: {type(observer).__name__}'s state remembers its measurements "
            f"in {', '.join(other + nested)}; the analysis covers states that remember the "
            "last sampled current as `i_prev` (or nothing).")
    return "i_prev" in names


def _replay_step(observer, plant, w, i_dq, T_s):
    """`fn(x_k, v_k, v_{k+1}) -> (x_{k+1}, (angle error, speed-estimate error))`: one real
    step of the replay of the module docstring, with current noise `v` (A, rotor frame
    at its sample) on the sample at t_k (which the state remembers as `i_prev`) and on
    the one at t_{k+1}."""
    a = observer.coordinates.angle
    nan = jnp.full((), jnp.nan, w.dtype)
    th0, th1 = 0.0 * w, w * T_s
    i_k, i_next = rotate(i_dq, th0), rotate(i_dq, th1)
    u = (_true_flux_ab(plant, th1, i_next) - _true_flux_ab(plant, th0, i_k)) / T_s \
        + 0.5 * plant.R_s * (i_k + i_next)
    truth0 = PlantPoint(theta=th0, w_m=w, i_ab=i_k)

    def fn(x, v0, v1):
        state = observer.observer_state(x, truth0, plant)
        if _memory_fields(observer, state):
            state = eqx.tree_at(lambda s: s.i_prev, state, i_k + rotate(v0, th0))
        new, est = observer.step(state, Measurement(i_ab=i_next + rotate(v1, th1), u_ab=u,
                                                    theta=nan, w_m=nan), T_s)
        x1 = observer.error_state(new, PlantPoint(theta=th1, w_m=w, i_ab=i_next), plant)
        # the angle coordinate of x1 is the same error as the estimate's, wrapped alike
        return x1, jnp.stack([wrap_angle(x1[a]), est.w_hat - w])

    return fn


@eqx.filter_jit
def _sensor_noise(observer, plant, w, i_dq, T_s, sigma):
    fn = _replay_step(observer, plant, w, i_dq, T_s)
    v0 = jnp.zeros(2, w.dtype)
    x = jnp.asarray(observer.designed_error(OperatingPoint(w, i_dq), plant), w.dtype)
    n = x.shape[0]

    def newton(_, x):  # towards the fixed point x = F(x, 0, 0); one trace of the step
        def residual(v):
            r = fn(v, v0, v0)[0] - v
            return r, r

        J, r = jax.jacfwd(residual, has_aux=True)(x)
        return x - jnp.linalg.solve(J, r)

    x = jax.lax.fori_loop(0, _NEWTON_STEPS, newton, x)
    (Phi, Psi, Gam), (C, E, D) = jax.jacfwd(fn, argnums=(0, 1, 2))(x, v0, v0)
    # the state with the remembered noise: z_k = (x_k, v_k), z_{k+1} = (x_{k+1}, v_{k+1})
    zero = jnp.zeros((2, n + 2), w.dtype)
    Phi_z = jnp.concatenate([jnp.concatenate([Phi, Psi], 1), zero], 0)
    Gam_z = jnp.concatenate([Gam, jnp.eye(2, dtype=w.dtype)], 0)
    C_z = jnp.concatenate([C, E], 1)
    rho = jnp.max(jnp.abs(jnp.linalg.eigvals(Phi)))
    stable = rho < 1.0
    m = n + 2
    Q = sigma ** 2 * Gam_z @ Gam_z.T
    vecP = jnp.linalg.solve(jnp.eye(m * m, dtype=w.dtype) - jnp.kron(Phi_z, Phi_z),
                            Q.reshape(-1))
    P = vecP.reshape(m, m)
    cov = C_z @ P @ C_z.T + sigma ** 2 * D @ D.T
    rms = jnp.where(stable, jnp.sqrt(jnp.clip(jnp.diagonal(cov), 0.0)), jnp.nan)
    a = observer.coordinates.angle
    return SensorNoise(theta_static=wrap_angle(x[a]), theta_rms=rms[0], w_rms=rms[1],
                       noise_std=sigma, stable=stable, spectral_radius=rho)
