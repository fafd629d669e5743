r"""Catching a turning rotor: an initial angle and speed estimate from the first samples.

A drive's practice (a "flying start"), not part of any of the papers: before an
observer runs, the rotor angle and speed of a turning machine are read off its back-EMF
over a short window of samples. `replay(..., theta0=..., w0=...)` then starts the
observer near its lock; zhang2022's flux observers (ESO, LESO, AFO), which do not find
their lock from a zero speed estimate (`analysis.lock_basin`), need it to replay a log
that starts mid-run.

**The estimate.** With the voltage $u_k$ held over $[t_k, t_{k+1})$, the model's
extended back-EMF at the midpoint of each period is

$$\hat e_{k+1/2} = u_k - \hat R_s\,\frac{i_k + i_{k+1}}{2} - \hat L_q\,\frac{i_{k+1} -
i_k}{T_s} \;\approx\; \omega\,\psi_{ex}\,[-\sin\theta, \cos\theta]^T$$

($\psi_{ex} = \psi_f + (L_d - L_q)i_d$ plus a term in $di_q/dt$: its direction is the
rotor's q axis for either saliency). Its rotation between successive periods (the exact
increment, $\mathrm{atan2}$ of the cross and dot products) summed over the window and
divided by its length gives $\hat\omega$, with its sign; its direction gives the angle,
$\theta_{k+1/2} = \mathrm{atan2}(-\sigma\hat e_\alpha, \sigma\hat e_\beta)$ with
$\sigma = \mathrm{sign}\,\hat\omega$ (`back_emf_angle`), and the circular mean of
$\theta_{k+1/2} - \hat\omega(k + \tfrac12)T_s$ over the window is the angle at $t_0$.
Both are least-squares-free and exact for noise-free data at constant speed (up to the
hold of the current between samples, $O(\omega T_s)^2$).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._frames import back_emf_angle, rotation_between, wrap_angle
from .._plant._params import PMSMParams
from .._validate import is_concrete


#: `replay` with no initial estimate takes a recording to start with the rotor turning
#: when the model back-EMF of its first samples (`FlyingStart.e_mag`) exceeds this
#: fraction of the mean voltage magnitude over the same samples: at standstill the
#: voltage is the resistive drop and the inductive one, which the model takes off
#: (`e_mag` ~ the model error), while on a turning rotor the back-EMF is most of it.
TURNING_FRACTION = 0.2
#: ... and its angles, referred to the first sample with the estimated speed, agree
#: (`FlyingStart.coherence` above this): the current's noise, differentiated, can be as
#: large as the resistive drop at standstill, but it does not turn at one speed.
TURNING_COHERENCE = 0.9
#: Samples of the flying start's window in `replay` (fewer in a shorter recording).
WINDOW = 64


class FlyingStart(eqx.Module):
    """Result of `flying_start`.

    - `theta0`: electrical rotor angle at the first sample (rad, wrapped).
    - `w0`: electrical speed (rad/s), mean over the window.
    - `e_mag`: mean magnitude of the model back-EMF over the window (V): compare it with
      the noise on the voltage; near standstill the estimate is meaningless.
    - `coherence`: the length of the circular mean of the window's angles referred to
      `t_0` (-, 0..1): 1 for a back-EMF that turns at the estimated speed, small for one
      made of noise (the differentiated current's, at standstill).
    """

    theta0: jnp.ndarray
    w0: jnp.ndarray
    e_mag: jnp.ndarray
    coherence: jnp.ndarray


def model_back_emf(motor: PMSMParams, u_ab, i0_ab, i1_ab, T_s):
    r"""The model back-EMF (V) of the period from the current `i0_ab` to `i1_ab` (A, `T_s`
    (s) apart) with the voltage `u_ab` (V) held over it:
    $u - \hat R_s(i_0 + i_1)/2 - \hat L_q(i_1 - i_0)/T_s$ (the q-axis model: for a
    salient machine it is the extended back-EMF, along the q axis)."""
    return u_ab - motor.R_s * 0.5 * (i0_ab + i1_ab) - motor.L_q * (i1_ab - i0_ab) / T_s


def flying_start(motor: PMSMParams, u_ab, i_ab, T_s, n: int = 64) -> FlyingStart:
    """Initial angle and speed of a turning rotor from the first `n` + 1 samples (see the
    module docstring).

    **Arguments:**

    - `motor`: the model (`PMSMParams`; uses $R_s$ and $L_q$).
    - `u_ab`: voltage held over $[t_k, t_{k+1})$ (V, `(N, 2)`, stationary frame).
    - `i_ab`: current sampled at $t_k$ (A, `(N, 2)`).
    - `T_s`: sampling period (s), > 0.
    - `n`: periods in the window (2 <= n < N).

    **Returns:** `FlyingStart`.
    """
    if not isinstance(motor, PMSMParams):
        raise ValueError(f"`flying_start(motor=...)` must be a `PMSMParams`; got "
                         f"{type(motor).__name__}.")
    u_ab, i_ab = jnp.asarray(u_ab), jnp.asarray(i_ab)
    if u_ab.ndim != 2 or u_ab.shape[-1] != 2 or i_ab.shape != u_ab.shape:
        raise ValueError(f"`flying_start` needs `u_ab` and `i_ab` of the same shape (N, 2); "
                         f"got {tuple(u_ab.shape)} and {tuple(i_ab.shape)}.")
    if not (isinstance(n, int) and 2 <= n < u_ab.shape[0]):
        raise ValueError(f"`flying_start(n=...)` must be an integer with 2 <= n < N = "
                         f"{u_ab.shape[0]}; got {n!r}.")
    if is_concrete(T_s) and not float(T_s) > 0:
        raise ValueError(f"`flying_start(T_s=...)` (s) must be > 0; got {T_s!r}.")
    u = u_ab[:n]
    i0, i1 = i_ab[:n], i_ab[1:n + 1]
    e = model_back_emf(motor, u, i0, i1, T_s)
    w0 = jnp.sum(rotation_between(e[:-1], e[1:])) / ((n - 1) * T_s)
    sg = jnp.where(w0 < 0, -1.0, 1.0)
    th_mid = back_emf_angle(e, sg)
    k = jnp.arange(n) + 0.5
    d = th_mid - w0 * k * T_s
    s_, c_ = jnp.mean(jnp.sin(d)), jnp.mean(jnp.cos(d))
    theta0 = jnp.arctan2(s_, c_)
    return FlyingStart(theta0=wrap_angle(theta0), w0=w0,
                       e_mag=jnp.mean(jnp.sqrt(jnp.sum(e ** 2, -1))),
                       coherence=jnp.sqrt(s_ ** 2 + c_ ** 2))


def unknown_start(motor: PMSMParams, u_ab, i_ab, T_s):
    """The initial estimate `(theta0, w0, turning)` of a drive that does not know its
    rotor's state (what `replay` uses when it is given none): the `flying_start` of the
    first `WINDOW` samples where they show a turning rotor (back-EMF above
    `TURNING_FRACTION` of the voltage, turning at one speed: coherence above
    `TURNING_COHERENCE`), else 0 rad and 0 rad/s (a rotor at rest, or
    too slow for its back-EMF to be read: every observer starts from zero speed there).
    `u_ab`: the applied voltage held over each period (V, (N, 2)); `i_ab` (A, (N, 2));
    `T_s` (s). Traceable (`jnp.where`, no Python branch on values)."""
    u_ab, i_ab = jnp.asarray(u_ab), jnp.asarray(i_ab)
    n = min(WINDOW, u_ab.shape[0] - 1)
    dtype = jnp.result_type(u_ab.dtype, i_ab.dtype, float)
    if n < 2:
        zero = jnp.zeros((), dtype)
        return zero, zero, jnp.asarray(False)
    fs = flying_start(motor, u_ab, i_ab, T_s, n=n)
    u_mag = jnp.mean(jnp.sqrt(jnp.sum(u_ab[:n] ** 2, -1)))
    turning = (fs.e_mag > TURNING_FRACTION * u_mag) & \
        (fs.coherence > TURNING_COHERENCE) & jnp.isfinite(fs.w0) & jnp.isfinite(fs.theta0)
    zero = jnp.zeros((), dtype)
    return (jnp.where(turning, fs.theta0, zero).astype(dtype),
            jnp.where(turning, fs.w0, zero).astype(dtype), turning)
