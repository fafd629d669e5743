r"""Stability of error dynamics that are periodic in the rotor angle (Floquet).

Some observers apply gains per stationary-frame component, so their error dynamics at a
constant-speed operating point depend on the true rotor angle $\theta = \theta_0 +
\omega_0 t$ itself (`OperatingPoint.theta`), not only on the errors: the linearisation
$A(\theta)$ is periodic with the electrical period $T = 2\pi/|\omega_0|$. Its exact
stability is given by the monodromy matrix $M = \Phi(T)$ of
$\dot\Phi = A(\theta_0 + \omega_0 t)\Phi$, $\Phi(0) = I$: the origin is asymptotically
stable iff every Floquet multiplier (eigenvalue of $M$) lies inside the unit circle.
`floquet` reports the exponents $\log\mu / T$ (1/s, comparable with eigenvalues of a
constant linearisation; the imaginary parts are defined modulo $2\pi/T$).
For an observer whose error dynamics do not depend on the angle, $M = e^{AT}$ and the
exponents are the eigenvalues of `linearization` (mod $2\pi j/T$): tested.
At standstill there is no period; `floquet` then returns the eigenvalues of the frozen
linearisation at `theta0`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._plant._params import PMSMParams
from ..observers import AbstractObserver, OperatingPoint
from ._args import _program_inputs, check_observer, check_plant


class Floquet(eqx.Module):
    """Floquet analysis of the periodic linearisation (any batch shape).

    - `multipliers`: eigenvalues of the monodromy matrix (complex, `(n,)`).
    - `exponents`: `log(multipliers) / T` (1/s, complex, `(n,)`).
    - `max_real`: largest real part of the exponents (1/s).
    - `stable`: every multiplier inside the unit circle.
    - `period`: T = 2 pi / |w_m| (s); inf at standstill.
    """

    multipliers: jnp.ndarray
    exponents: jnp.ndarray
    max_real: jnp.ndarray
    stable: jnp.ndarray
    period: jnp.ndarray


def floquet(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq=(0.0, 0.0), *,
            theta0=0.0, n_steps: int = 256) -> Floquet:
    """Floquet multipliers and exponents of `observer`'s error dynamics linearised at the
    origin, at electrical speed `w_m` (rad/s) and current `i_dq` (A, estimated frame),
    true machine `plant`, over one electrical period from rotor angle `theta0` (rad);
    `n_steps` exponential-midpoint steps per period (static; error
    O((2 pi / n_steps)^2) in the angle dependence, stable for any stiffness).
    Pure: vmap over any argument. Compiled once per observer structure and `n_steps`: a new
    speed, current, angle or design reuses the program (run op by op, every call compiled
    its loop over the period anew)."""
    check_observer("floquet", observer)
    check_plant("floquet", plant)
    if not isinstance(n_steps, int) or n_steps < 4:
        raise ValueError(f"`floquet(n_steps=...)` must be an int >= 4; got {n_steps!r}.")
    dtype = jnp.result_type(w_m, float)
    observer, plant = _program_inputs(observer, plant, dtype)
    return _floquet(observer, plant, jnp.asarray(w_m, dtype), jnp.asarray(i_dq, dtype),
                    jnp.asarray(theta0, dtype), n_steps)


@eqx.filter_jit
def _floquet(observer, plant, w_m, i_dq, theta0, n_steps):
    dtype = w_m.dtype
    w = jnp.asarray(w_m, dtype)
    i0 = jnp.asarray(i_dq, dtype)
    n = observer.coordinates.n
    x0 = jnp.zeros(n, dtype)
    th0 = jnp.asarray(theta0, dtype)

    def A(theta):
        op = OperatingPoint(w, i0, theta)
        return jax.jacfwd(lambda v: observer.error_rhs(v, op, plant))(x0)

    aw = jnp.abs(w)
    moving = aw > 0
    T = 2 * jnp.pi / jnp.where(moving, aw, 1.0)
    h = T / n_steps
    sgn = jnp.where(w >= 0, 1.0, -1.0)

    def body(Phi, k):
        # exponential midpoint rule (second-order Magnus): stable for stiff A at any h
        th = th0 + sgn * aw * (k + 0.5) * h
        return jax.scipy.linalg.expm(h * A(th)) @ Phi, None

    M, _ = jax.lax.scan(body, jnp.eye(n, dtype=dtype), jnp.arange(n_steps, dtype=dtype))
    mult = jnp.linalg.eigvals(M)
    expo = jnp.log(mult.astype(jnp.result_type(dtype, jnp.complex64))) / T
    frozen = jnp.linalg.eigvals(A(th0))
    expo = jnp.where(moving, expo, frozen)
    mult = jnp.where(moving, mult, jnp.exp(frozen))
    mr = jnp.max(jnp.real(expo), -1)
    return Floquet(multipliers=mult, exponents=expo, max_real=mr, stable=mr < 0,
                   period=jnp.where(moving, T, jnp.inf))
