r"""The rotor-flux observer's design in physical terms (morawiec2023), for the tuner.

morawiec2023 tunes $c_\alpha$, $k_c$, $c_\theta$ and $\gamma$ by looking at the spectrum of
its linearisation (35) (Figs. 3-5); it states no rule that ties them to the drive. A
reduction of that spectrum gives one. Non-salient machine ($L_d = L_q = L$), estimated
frame, errors estimate minus true, current-error rate $a = (1 + c_\alpha)R_s/L$: the
current error obeys $\dot{\tilde i} = -(a + \omega J)\tilde i + b$ with
$b = \frac{\psi_f}{L}[\omega\tilde\theta, -\tilde\omega]$, and the speed law with its
derived sign (`RotorFluxObserver`, module docstring) reads it. Expanding
$(s + a + \omega J)^{-1} = M^{-1} - sM^{-2} + \dots$ ($M = a + \omega J$) to first order
in $s$, the angle error obeys

$$m s^2 + c_1 s + c_0 = 0,\qquad k = \frac{\gamma\psi_f^2}{L^2(a^2 + \omega^2)},\quad
q = a^2 - \omega^2 - 2ak_c|\omega|,$$
$$m = 1 - \frac{kq}{a^2 + \omega^2},\quad c_1 = \frac{kaq}{a^2 + \omega^2},\quad
c_0 = k(\omega^2 + k_c a|\omega|).$$

The quasi-static step alone ($m = 1$, $c_1 = k(a - k_c|\omega|)$, `RotorFluxObserver`'s
derivation of the sign) gets the frequency but not the damping, which is small and set
by the current error's lag: the speed law damps itself only while $q > 0$, i.e. below
$|\omega| = a(\sqrt{1 + k_c^2} - k_c)$; above it (the paper's design: $a$ = 54 1/s in
the q axis, rated 314 rad/s on `morawiec_ipm3k5`) the loop is held by the position correction
$c_\theta$, which needs the saliency ($\tilde\theta_\lambda \equiv 0$ for $L_d = L_q$).
`tests/test_rotor_flux_design.py` checks the reduction against
`analysis.linearization` on a non-salient variant (frequency and real part of the slow
pair, and the speed at which the real part changes sign).

With saliency the speed law reads the q-axis current error through
$\hat\lambda_d = \frac{L_d}{L_q}\psi_f$ and its own $1/L_d$, and that error is driven
through $L_q$: the loop's gain becomes $\gamma\psi_f^2/L_q^2$, so $L_q$ takes the place
of $L$ below (the same for $L_d = L_q$). On `morawiec_ipm3k5` ($L_q$ = 2.9 $L_d$), no
load, with $\gamma$ small enough for the quasi-static step, the slow pair's modulus in
`analysis.linearization` is $\omega_\gamma$ to within 0.7 % (tested); under load
and at the paper's $\gamma$ the current modes and $c_\theta$ move it.

Read off it, the coordinates the tuner searches instead of $\gamma$ and $c_\alpha$
(`design_from_tuning`, `tuning_from_design`, with the drive's $L_d$, $L_q$, $R_s$,
$\psi_f$):

- $\omega_\gamma = \sqrt\gamma\,\psi_f / L_q$ (rad/s): $c_0/m \to \omega_\gamma^2$ for
  $|\omega| \gg a$, the speed law's natural frequency at speed, so a type-2 tracking
  bandwidth, bounded like the others by the ramp lag it allows and by the sampling
  period (the speed state is advanced by forward Euler);
- $a_i = (1 + c_\alpha)R_s / L_d$ (1/s), (35)'s $a_1(1 + c_\alpha)$: the faster of the two
  current-error rates (the speed law reads the q-axis one, $a = a_i L_d/L_q$). The
  feedback acts explicitly, once per sampling period, so $a_i T_s$ is bounded like a
  tracking bandwidth's (at $a_i T_s = 1$ the discrete poles reach 1.93). Below
  $R_s/L_d$ ($c_\alpha < 0$) it is held at $c_\alpha = 0$.

$c_\theta$ (1/s) stays as it is: the rate at which the position correction pulls the
angle (at standstill the slow roots are $-c_\theta$ and $-\omega_\gamma^2/a$ in the paper's
row 4 of (35); the slowest Floquet exponent of the paper's design), applied once per
sampling period like $a_i$. $k_c$ keeps the contract's box: it adds the stiffness
$k k_c a|\omega|$ near zero speed, the paper's purpose for it, and costs the damping
$2ak_c|\omega|$ in $q$; the drive alone gives no bound on that trade.

The stable region is narrower than these rules. With the others at the paper's values,
the averaged linearisation at +-0.2, 0.5 and 1 p.u. and q-currents -0.5 to 1 p.u. is
stable only for $c_\theta$ up to 60 1/s (47 in the paper's design), $a_i$ up to 264 1/s
(157), $\omega_\gamma$ from 284 rad/s (341) and $k_c$ up to 0.56 (0.1); at
$c_\theta$ = 990 1/s ($c_\theta T_s$ = 0.15) the discrete poles reach 1.05-1.11. So the
class sets `tuning_spectral`, and `tuning.DesignSpace` narrows each bound to that
region.
"""

from __future__ import annotations

import jax.numpy as jnp


#: The tuner's coordinates: name -> (unit, kind of bound, `tuning.design_space`).
TUNING_COORDINATES = {"w_gamma": ("rad/s", "tracking"), "a_i": ("1/s", "explicit")}
TUNING_REPLACES = ("gamma", "c_alpha")


def _rate(c_alpha, R_s, L):
    """The current-error rate (1 + c_alpha) R_s / L (1/s) of the feedback c_alpha."""
    return (1.0 + c_alpha) * R_s / L


def _constants(drive):
    if drive is None:
        raise ValueError("RotorFluxObserver's tuning coordinates (w_gamma, a_i) are scaled "
                         "with the drive's L_d, L_q, R_s and psi_f: pass `drive=` (a `Drive`).")
    m = drive.three_phase_motor
    return m.L_d, m.L_q, m.R_s, m.psi_f


@classmethod
def design_from_tuning(cls, coords: dict, drive=None) -> dict:
    """gamma and c_alpha of `w_gamma` (rad/s) and `a_i` (1/s) on `drive` (module
    docstring; other names pass through; values may be traced): the observer class's
    `design_from_tuning`."""
    d = dict(coords)
    if "w_gamma" not in d:
        return d
    L_d, L_q, R_s, psi_f = _constants(drive)
    w_g, a_i = d.pop("w_gamma"), d.pop("a_i")
    d["gamma"] = (w_g * L_q / psi_f) ** 2
    d["c_alpha"] = jnp.maximum(a_i * L_d / R_s - 1.0, 0.0)
    return d


@classmethod
def tuning_from_design(cls, design: dict, drive=None) -> dict:
    """`design_from_tuning` inverted."""
    d = dict(design)
    if "gamma" not in d:
        return d
    L_d, L_q, R_s, psi_f = _constants(drive)
    gamma, c_alpha = d.pop("gamma"), d.pop("c_alpha")
    d["w_gamma"] = gamma ** 0.5 * psi_f / L_q
    d["a_i"] = _rate(c_alpha, R_s, L_d)
    return d


def reduced_poles(gamma, c_alpha, k_c, motor, w):
    """The two roots of the module docstring's polynomial $m s^2 + c_1 s + c_0$ at
    electrical speed `w` (rad/s) for the non-salient reduction of `motor` (its `L_q`,
    `R_s`, `psi_f`), complex (2,)."""
    L, a, aw = motor.L_q, _rate(c_alpha, motor.R_s, motor.L_q), jnp.abs(w)
    D = a ** 2 + w ** 2
    k = gamma * motor.psi_f ** 2 / (L ** 2 * D)
    q = a ** 2 - w ** 2 - 2.0 * a * k_c * aw
    m, c1, c0 = 1.0 - k * q / D, k * a * q / D, k * (w ** 2 + k_c * a * aw)
    disc = jnp.sqrt(jnp.asarray(c1 * c1 - 4.0 * m * c0, complex))
    return jnp.stack([(-c1 + disc) / (2.0 * m), (-c1 - disc) / (2.0 * m)])


def self_damped_below(c_alpha, k_c, motor):
    """The electrical speed (rad/s) below which the speed law damps itself on the
    non-salient reduction: $a(\\sqrt{1 + k_c^2} - k_c)$ (module docstring)."""
    a = _rate(c_alpha, motor.R_s, motor.L_q)
    return a * (jnp.sqrt(1.0 + k_c ** 2) - k_c)
