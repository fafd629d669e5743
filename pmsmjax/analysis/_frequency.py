r"""Frequency response of back-EMF observers (li-fa-leso Figs. 1, 2, 4 and Table I).

**Discrete response from the running code.** `bemf_response` linearises the observer's
own `step` (the code that runs in `simulate` and `replay`) about its started zero state
with the speed estimate at $\omega$, and evaluates the resulting linear system
$x_k = A x_{k-1} + B m_k$, $y_k = C x_{k-1} + D m_k$ (measurement $m$, estimate
$y = \hat e_{ab}$) at $z = e^{jh\omega T_s}$. The input is the sampled current that the
back-EMF component $e_{ab} = \mathrm{Re}\{E e^{jh\omega t}[1, -j]^T\}$ drives through the
observer's own machine model li-fa-leso (4) with zero voltage,
$i = -e/(\hat R_s + jh\omega\hat L_q)$ (exact at the samples). The gain at order $h$ is
the positive-rotating part of the output, $G_h = (y_\alpha + jy_\beta)/(2E)$. For an
observer that is linear in its measurements at a fixed speed estimate (the li-fa-leso
observers) the PLL states do not act back at first order, so this is the observer's
transfer function at the fixed speed estimate, as (14) assumes.

**Continuous transfer functions as printed**: (17), (26), (29)-(30) (`g_c_leso`,
`g_fa_leso`, `g_gi_leso`); every observer's own `transfer_function` must agree with them
(tested), and the discrete response with both at the fundamental.

**Generalised Routh test** (Table I, after Xie 1985): $\lambda(s) = s^2 + (a_1 + jb_1)s
+ (a_2 + jb_2)$ is Hurwitz iff $a_1 > 0$ and
$a_2^{(2)} = a_1^2a_2 + a_1b_1b_2 - b_2^2 > 0$. For the FA-LESO (22) ($a_1 = k_2$,
$b_1 = -\hat\omega$, $a_2 = k_1$, $b_2 = 0$) this is $a_2^{(2)} = k_1k_2^2$: the printed
(23) gives $k_1k_2$ (a factor $a_1$ is missing); the condition $k_1, k_2 > 0$ is the same.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..observers import AbstractObserver, Measurement
from ._args import as_arrays


def _has_bemf(observer) -> None:
    if not isinstance(observer, AbstractObserver):
        raise ValueError(f"`bemf_response(observer=...)` must be an `AbstractObserver`; got "
                         f"{type(observer).__name__}.")
    if "e_ab_hat" not in type(observer).extras:
        raise ValueError(
            f"`{type(observer).__name__}` has no back-EMF estimate (`e_ab_hat` in its "
            f"`extras`: {', '.join(type(observer).extras) or 'none'}); the back-EMF "
            f"frequency response applies to back-EMF observers only.")


def discrete_bemf_system(observer: AbstractObserver, w_m, T_s):
    """The observer's `step` linearised about its started zero state with speed estimate
    `w_m` (rad/s): `(A, B, C, D)` with the state flattened (its floating leaves), the
    measurement `[i_a, i_b, u_a, u_b]` (A, V) and the output `e_ab_hat` (V)."""
    _has_bemf(observer)
    dtype = jnp.result_type(w_m, float)
    # one compiled program per observer family (op by op it took seconds for a LESO)
    # (the observer's float values as inputs of that dtype, as in `discrete_jacobian`)
    return _discrete_bemf_system(as_arrays(observer, dtype, ints=False), jnp.asarray(w_m, dtype),
                                 jnp.asarray(T_s, dtype))


@eqx.filter_jit
def _discrete_bemf_system(observer, w_m, T_s):
    dtype = w_m.dtype
    nan = jnp.full((), jnp.nan, dtype)
    z2 = jnp.zeros(2, dtype)
    st, _ = observer.step(observer.init(theta0=0.0, w0=jnp.asarray(w_m, dtype)),
                          Measurement(i_ab=z2, u_ab=z2, theta=nan, w_m=nan), T_s)
    dyn, static = eqx.partition(st, eqx.is_inexact_array)
    x0, unravel = ravel_pytree(dyn)

    def f(x, m):
        s = eqx.combine(unravel(x), static)
        new, est = observer.step(s, Measurement(i_ab=m[:2], u_ab=m[2:], theta=nan,
                                                w_m=nan), T_s)
        return ravel_pytree(eqx.partition(new, eqx.is_inexact_array)[0])[0], \
            est.extras["e_ab_hat"]

    m0 = jnp.zeros(4, dtype)
    (A, B), (C, D) = jax.jacfwd(f, argnums=(0, 1))(x0, m0)
    return A, B, C, D


def bemf_response(observer: AbstractObserver, w_m, orders, T_s):
    """Complex gains $\\hat e/e$ of the discrete observer at the signed harmonic orders
    `orders` (e.g. `(1, -5, 7)`) of the electrical speed `w_m` (rad/s, nonzero), sampling
    period `T_s` (s) (see the module docstring). Returns a complex numpy array."""
    A, B, C, D = (np.asarray(M) for M in discrete_bemf_system(observer, w_m, T_s))
    m = observer.motor
    R, L = float(m.R_s), float(m.L_q)
    out = []
    for h in np.atleast_1d(orders):
        wh = float(h) * float(w_m)
        z = np.exp(1j * wh * T_s)
        v_i = -np.array([1.0, -1j]) / (R + 1j * wh * L)
        v = np.concatenate([v_i, [0.0, 0.0]])
        y = C @ np.linalg.solve(z * np.eye(A.shape[0]) - A, B @ v) + D @ v
        out.append((y[0] + 1j * y[1]) / 2.0)
    return np.asarray(out)


def g_c_leso(s, w0):
    """li-fa-leso (17): $\\omega_0^2/(s^2 + 2\\omega_0 s + \\omega_0^2)$."""
    s = np.asarray(s, complex)
    return w0 ** 2 / (s ** 2 + 2 * w0 * s + w0 ** 2)


def g_gi_leso(s, w0, K_r, w_c, w_e):
    """li-fa-leso (29) with the generalised integrator (30) resonant at `w_e` (rad/s)."""
    s = np.asarray(s, complex)
    G = 2 * K_r * w_c * s / (s ** 2 + 2 * w_c * s + w_e ** 2)
    return (G + w0 ** 2) / (s ** 2 + 2 * w0 * s + G + w0 ** 2)


def g_fa_leso(s, k1, k2, w_e):
    """li-fa-leso (26): $(k_1 + k_2 s)/(s^2 - j\\hat\\omega_e s + k_1 + k_2 s)$."""
    s = np.asarray(s, complex)
    return (k1 + k2 * s) / (s ** 2 - 1j * w_e * s + k1 + k2 * s)


def routh_complex2(c1, c2):
    """Generalised Routh conditions for $s^2 + c_1 s + c_2$ with complex `c1`, `c2`:
    `(a1, a2_2)`; the polynomial is Hurwitz iff both are > 0 (Table I; see the module
    docstring for the corrected $a_2^{(2)}$)."""
    c1, c2 = np.asarray(c1, complex), np.asarray(c2, complex)
    a1, b1, a2, b2 = c1.real, c1.imag, c2.real, c2.imag
    return a1, a1 ** 2 * a2 + a1 * b1 * b2 - b2 ** 2


def bode_data(observer: AbstractObserver, w_hat, freqs_hz, T_s=None):
    """Magnitude (dB) and phase (deg) of the observer's continuous `transfer_function`
    at speed estimate `w_hat` (rad/s) over signed frequencies `freqs_hz` (Hz, negative =
    negative sequence); with `T_s` also those of the discrete `bemf_response` (same
    frequencies, as orders of `w_hat`). Returns a dict of numpy arrays."""
    f = np.asarray(freqs_hz, float)
    G = np.asarray(observer.transfer_function(2j * np.pi * f, w_hat))
    out = {"f_hz": f, "mag_db": 20 * np.log10(np.abs(G)),
           "phase_deg": np.degrees(np.angle(G))}
    if T_s is not None:
        Gd = bemf_response(observer, w_hat, 2 * np.pi * f / float(w_hat), T_s)
        out.update(mag_db_discrete=20 * np.log10(np.abs(Gd)),
                   phase_deg_discrete=np.degrees(np.angle(Gd)))
    return out
