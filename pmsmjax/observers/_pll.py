r"""Quadrature phase-locked loop: rotor angle and speed from an estimated back-EMF.

Shared by the back-EMF observer families (li-fa-leso's C-LESO, GI-LESO and FA-LESO; any
observer whose output is an equivalent back-EMF
$\hat e_{ab} \approx \omega\psi_{ex}[-\sin\theta, \cos\theta]^T$, li-fa-leso (5)).
li-fa-leso names a PLL in its Fig. 3 but its section IV (the PLL and the gain design) is
missing from the available text, so this is a standard design, documented here.

**Phase detector.** The component of $\hat e$ along the estimated d axis,

$$\hat e_\perp = -\hat e_\alpha\cos\hat\theta - \hat e_\beta\sin\hat\theta
= \omega\psi_{ex}\sin(\theta - \hat\theta)\quad(\text{for } \hat e = e),$$

is normalised by the model back-EMF amplitude at the estimated speed,

$$\varepsilon = \frac{\hat e_\perp\,\hat\omega}{\hat\psi_{ex}\max(\hat\omega^2,
\omega_{min}^2)},\qquad \hat\psi_{ex} = \hat\psi_f + (\hat L_d - \hat L_q)\hat i_d,$$

so that $\varepsilon = (\omega/\hat\omega)\sin\tilde\theta \approx \tilde\theta$ above
$\omega_{min}$ at either sign of speed (the factor $\hat\omega$ carries the sign of the
back-EMF, so the loop is stable in both directions).

**Loop.** A PI law on $\varepsilon$:

$$\dot{\hat\theta} = \hat\omega + k_p\varepsilon,\qquad \dot{\hat\omega} = k_i\varepsilon,
\qquad k_p = 2\zeta_{pll}\omega_{pll},\quad k_i = \omega_{pll}^2,$$

so that for a fast observer ($\hat e = e$) the angle error obeys
$\ddot{\tilde\theta} + k_p\dot{\tilde\theta} + k_i\tilde\theta = \dot\omega$: natural
frequency `w_pll`, damping `zeta_pll`; a constant speed gives no steady-state angle
error and a speed ramp $a$ an error $a/k_i$. The speed estimate is the integral state
$\hat\omega$ (not the PI output, which carries the observer's noise).

**Low speed and zero speed.** Below $\omega_{min}$ the normaliser is frozen at
$\hat\psi_{ex}\omega_{min}^2$: the loop gain falls as $|\omega\hat\omega|/\omega_{min}^2$,
so at standstill (no back-EMF, the angle is not observable from it) the PLL coasts on
its integral state instead of amplifying noise by $1/\hat\omega$; passing through zero
speed, the angle is integrated open loop from $\hat\omega$ until the back-EMF is large
enough again. The lock at $\tilde\theta = \pi$ is the other equilibrium of any
back-EMF PLL (the back-EMF of $-\omega$ at $\theta + \pi$ is the same): it is unstable
while $\hat\omega$ and $\omega$ have the same sign.

*Reversals* (a standard design choice, not from the paper). With the factor
$\hat\omega$ alone, the loop gain changes sign whenever the speed passes through zero
before its estimate does: the angle error then grows (positive feedback) and the drive
stalls near zero speed with up to 180 deg error (every back-EMF PLL observer did, in
the closed-loop reversal). Below $\omega_{min}$ the detector is therefore

$$\varepsilon = \frac{\hat e_\perp}{\hat\psi_{ex}\omega_{min}}\Big[
\frac{\hat\omega}{\omega_{min}} + \Big(1 - \frac{|\hat\omega|}{\omega_{min}}\Big)
\big(\mathrm{sign}\,\hat e_q - \mathrm{sign}\,\hat\omega\big)\Big],$$

$\hat e_q$ the back-EMF's component along the estimated q axis ($= \omega\psi_{ex}
\cos\tilde\theta$). Where the signs agree (at the designed lock, and everywhere near it)
the bracket is $\hat\omega/\omega_{min}$: the detector above, so its equilibria and its
linearisation at the designed lock are unchanged at every speed. Where they disagree
(the speed has reversed and its estimate has not yet, or the false lock) the bracket
is $3|\hat\omega|/\omega_{min} - 2$ times $\mathrm{sign}\,\hat\omega$: for
$|\hat\omega| < 2\omega_{min}/3$ the loop follows the back-EMF's axis instead, which
turns with the rotor whichever the sign of the speed, so the angle estimate passes
through the reversal continuously and the speed estimate follows the speed to the new
sign; at $\hat\omega = 0$ the gain is $|\omega|/\omega_{min}$ instead of zero. The
price: below $2\omega_{min}/3$ the false lock $\tilde\theta = \pi$ is stable too (the
back-EMF's axis cannot tell $\theta$ from $\theta + \pi$); above it, it is not, and
the assist below pulls the speed estimate out of it.

**Discretisation** (at $t_k$, from the state at $t_{k-1}$): the angle is predicted with
the speed estimate, $\hat\theta^- = \hat\theta_{k-1} + T_s\hat\omega_{k-1}$, the phase
detector is evaluated at $\hat\theta^-$ with $\hat e_k$, and both integrators take a
forward step: $\hat\theta_k = \hat\theta^- + T_s k_p\varepsilon_k$,
$\hat\omega_k = \hat\omega_{k-1} + T_s k_i\varepsilon_k$. At constant speed with
$\hat e_k$ on the true back-EMF direction this is exact ($\varepsilon_k = 0$).

**Acquisition: the frequency-locked-loop assist.** The phase detector above carries the
factor $\hat\omega$ (it sets the sign of the loop gain): a speed estimate of exactly 0 is
a fixed point of the PI loop whatever the back-EMF does, and from a small or wrong-signed
$\hat\omega$ the loop gain $\omega\hat\omega/\omega_{min}^2$ is small or negative. A
drive started on a turning rotor, or a replay of a log that starts mid-run, never leaves
$\hat\omega = 0$. The usual remedy (a standard PLL design, not from the paper) is a
frequency discriminator: the rotation of the estimated back-EMF vector between two
samples,

$$\omega_e = \frac{1}{T_s}\,\mathrm{atan2}(s\,\hat e_{k-1}\times\hat e_k,\;
|\hat e_{k-1}\cdot\hat e_k|),\qquad s = \mathrm{sign}(\hat e_{k-1}\cdot\hat e_k)$$

($= \omega$ for a back-EMF turning with the rotor, either sign, independent of the
angle estimate: the exact increment, where $\hat e_{k-1}\times\hat e_k/(T_s
|\hat e|^2)$ would be $\sin(\omega T_s)/T_s$; taken modulo $\pi$, so that a back-EMF
that flips through zero in a speed reversal, a jump of $\pi$, does not read as a speed
of $\pi/T_s$; valid for $|\omega| T_s < \pi/2$), pulls the speed estimate towards it,

$$\hat\omega_k \mathrel{+}= T_s\,k_f\,g_k\,(\omega_e - \hat\omega_{k-1}),\qquad
g = \frac{m}{2}\Big(1 - \sigma\frac{\hat e_q}{|\hat e|}\Big),\quad
m = \frac{|\hat e_{k-1}||\hat e_k|}{|\hat e_{k-1}||\hat e_k| + (\hat\psi_{ex}
\omega_{min})^2},\quad \sigma = \tanh(\hat\omega_{k-1}/\omega_{min}),$$

$k_f$ = `fll` $\cdot\,\omega_{pll}$ (`fll = 0` switches it off), $\hat e_q = -\hat
e_\alpha\sin\hat\theta^- + \hat e_\beta\cos\hat\theta^-$ the component along the
estimated q axis ($= \omega\psi_{ex}\cos\tilde\theta$). The gate $g$ is
$\approx(1 - \cos\tilde\theta)/2$ at speed: 0 at lock, 1 at the false lock
$\tilde\theta = \pi$, 1/2 on average while the angle slips; $m$ fades it out where the
back-EMF (and so $\omega_e$) is too small to be trusted. From $\hat\omega = 0$ (or any
sign) the speed estimate is pulled to $\omega$ within a few $1/k_f$, and then the PI
loop locks the phase at $\tilde\theta = 0$ (the false lock at $\pi$ is unstable once
$\hat\omega$ has the sign of $\omega$).

*The gate's direction* $\sigma$ is the sense in which the PLL believes the rotor
turns, from its speed estimate before the step. The gate opens where the back-EMF's
q component disagrees with it: at the false lock, where the speed has reversed and its
estimate has not yet, and, from a speed estimate of the wrong sign, at every angle but
$\tilde\theta = \pi$, which such an estimate does not hold (the angle error then turns
at $\omega - \hat\omega$, so the gate averages $m/2$ and pulls the estimate over).
Earlier versions took the direction from one sample's rotation,
$\tanh(\omega_e/\omega_{min})$. That rotation is the difference of two noisy back-EMF
angles divided by $T_s$: with current-sensor noise its sign flips from sample to sample,
and the gate opened exactly on the samples whose $\omega_e$ read against the rotation and
pulled the speed estimate towards them, a rectifier. On `li_dtp` with 0.05 A of noise it
biased the FA-LESO's speed estimate by -9.4 rad/s (3.7 deg) at 0.5 p.u. and cost the
C-LESO the angle at 0.1 p.u.; in the closed-loop validation runs (0.02 A) the li
observers slipped within 12 ms of the start of most 0.1 p.u. runs and the FA-LESO lost
0.4 and 0.5 p.u. runs. The speed estimate before the step holds none of the new
sample's noise: measured at 0.1 p.u. with 0.05 A, the bias left is 0.29 of the
first-order speed noise (`analysis.sensor_noise`'s tests), and no closed-loop
validation run above 0.1 p.u. is lost (docs/tuning.md, "The low-speed limit").

*What the analysis sees.* At every equilibrium of the error dynamics $\hat\omega =
\omega$ and $\hat e$ turns at $\omega$, so $\omega_e - \hat\omega = 0$: the assist
adds nothing there, and the equilibria of `pmsmjax.analysis` are those of the PI loop.
At an equilibrium with the lock in the direction of rotation (the designed branch,
$\hat e$ along $\mathrm{sign}\,\omega$ times the estimated q axis) $g$ is
$\frac{m}{2}(1 - \tanh(|\omega|/\omega_{min}))$ plus terms quadratic in the deviation
(the factor $1 - \tanh$ is $4\cdot 10^{-9}$ at $|\omega| = 10\,\omega_{min}$, 0.036 at
$2\,\omega_{min}$). Above a
few $\omega_{min}$ the assist's term is therefore of third order and the linearised
error dynamics are those of the PI loop (`rates`); the error model (`error_rhs` of the
observers) leaves it out at every speed (the replay's linearisation,
`analysis.sensor_noise`, keeps it). Only at the unstable false lock
($\tilde\theta = \pi$, $g = 1$) does it change the linearisation (it adds damping to
$\hat\omega$; the lock stays a saddle, $\det = -k_pk_f - k_i < 0$).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._frames import cos_sin, wrap_angle
from .._validate import check_positive


#: Design parameters of the PLL (names shared by every observer that uses it).
PLL_UNITS = {
    "w_pll": "rad/s, PLL natural frequency (k_i = w_pll^2)",
    "zeta_pll": "-, PLL damping (k_p = 2 zeta_pll w_pll)",
    "w_min": "rad/s, speed below which the PLL's normalisation is frozen (low-speed "
             "fade-out of the loop gain)",
}
#: The frequency-locked-loop assist's gain, k_f = fll * w_pll (see the module docstring).
DEFAULT_FLL = 2.0
#: The default design's normalisation floor `w_min`, as a fraction of the rated speed.
W_MIN_PU = 0.05


class QuadraturePLL(eqx.Module):
    """Quadrature PLL on an estimated back-EMF (see the module docstring).

    **Arguments:**

    - `w_pll`: natural frequency (rad/s), > 0.
    - `zeta_pll`: damping (-), > 0.
    - `w_min`: normalisation floor (rad/s, electrical), > 0.
    - `fll`: gain of the acquisition assist, $k_f$ = `fll` $\\omega_{pll}$ (-), >= 0;
      0 switches it off (the bare PI loop, which cannot leave $\\hat\\omega = 0$).
    """

    w_pll: float
    zeta_pll: float = 1.0
    w_min: float = 10.0
    fll: float = DEFAULT_FLL

    def __check_init__(self):
        check_positive("QuadraturePLL", "w_pll", self.w_pll, "rad/s")
        check_positive("QuadraturePLL", "zeta_pll", self.zeta_pll, "-")
        check_positive("QuadraturePLL", "w_min", self.w_min, "rad/s")
        check_positive("QuadraturePLL", "fll", self.fll, "-", allow_zero=True)

    @classmethod
    def for_speed(cls, w_rated, w_pll_pu=0.4, zeta_pll=1.0, w_min_pu=W_MIN_PU):
        """The default design for a drive of rated electrical speed `w_rated` (rad/s):
        `w_pll = 0.4 w_rated` (126 rad/s = 20 Hz on `li_dtp`, well below the observers'
        bandwidths there), critically damped, `w_min = 0.05 w_rated`."""
        return cls(w_pll_pu * w_rated, zeta_pll, w_min_pu * w_rated)

    def gains(self):
        """`(k_p, k_i)` (rad/s, rad/s^2)."""
        return 2.0 * self.zeta_pll * self.w_pll, self.w_pll ** 2

    def error(self, e_ab_hat, theta_hat, w_hat, psi_ex_hat):
        """Normalised phase-detector output (rad, ~ sin of the angle error) for the
        estimated back-EMF `e_ab_hat` (V), angle `theta_hat` (rad), speed `w_hat` (rad/s)
        and model extended flux `psi_ex_hat` (V s)."""
        e_perp, e_q = _components(e_ab_hat, *cos_sin(theta_hat))
        return self._detector(e_perp, e_q, w_hat, psi_ex_hat)

    def _detector(self, e_perp, e_q, w_hat, psi_ex_hat):
        """`error` from the back-EMF's components along the estimated d and q axes."""
        psi = jnp.where(jnp.abs(psi_ex_hat) > 1e-12, psi_ex_hat, 1e-12)
        # below w_min: the sign of the back-EMF's q component where it disagrees with
        # the speed estimate's (see "Low speed and zero speed"); one division by psi for
        # both terms (a division is an expensive operation for XLA: two would each be a
        # kernel of their own)
        inv_min = 1.0 / self.w_min
        fade = jnp.maximum(1.0 - jnp.abs(w_hat) * inv_min, 0.0)
        gain = (w_hat / jnp.maximum(w_hat ** 2, self.w_min ** 2)
                + (fade * inv_min) * (jnp.sign(e_q) - jnp.sign(w_hat)))
        return e_perp * gain / psi

    def rates(self, w_hat, eps):
        """Continuous-time `(d theta_hat/dt, d w_hat/dt)` for phase error `eps`."""
        k_p, k_i = self.gains()
        return w_hat + k_p * eps, k_i * eps

    def _gate(self, e_prev, e_ab_hat, e_q, psi_ex_hat, T_s, w_hat):
        """The assist's gate `g` in [0, 1], the back-EMF's rotation rate `w_e` (rad/s)
        between the estimated back-EMFs `e_prev` and `e_ab_hat` (V) one period `T_s` (s)
        apart, for the back-EMF's component `e_q` (V) along the estimated q axis, the
        model extended flux `psi_ex_hat` (V s) and the speed estimate `w_hat` (rad/s)
        (see "Acquisition" in the module docstring); the two-element sums written out (a
        reduction is a kernel of its own on the CPU)."""
        a0, a1, b0, b1 = e_prev[..., 0], e_prev[..., 1], e_ab_hat[..., 0], e_ab_hat[..., 1]
        dot = a0 * b0 + a1 * b1
        cross = a0 * b1 - a1 * b0
        n2_prev = a0 * a0 + a1 * a1
        n2 = b0 * b0 + b1 * b1
        tiny = jnp.finfo(jnp.result_type(n2, float)).tiny
        # the increment modulo pi: a back-EMF that passes through zero (a speed reversal)
        # flips by pi in one sample, which is no rotation (the rotation from e_prev to
        # sign(dot) e_ab_hat: cross and dot times that sign); atan2 of (0, 0) has an
        # infinite gradient: 0 there with a finite one (as `rotation_between`), and the
        # square roots' arguments nudged (m ~ 0 then)
        sgn = jnp.where(dot < 0, -1.0, 1.0)
        cross, dot = sgn * cross, sgn * dot
        w_e = jnp.arctan2(cross, jnp.where((cross == 0) & (dot == 0), 1.0, dot)) / T_s
        e_min2 = (psi_ex_hat * self.w_min) ** 2
        prod = jnp.sqrt(n2_prev * n2 + tiny)
        m = prod / (prod + e_min2)
        sigma = jnp.tanh(w_hat / self.w_min)
        g = 0.5 * m * (1.0 - sigma * e_q / jnp.sqrt(n2 + tiny))
        return g, w_e

    def step(self, theta_prev, w_prev, e_ab_hat, psi_ex_fn, T_s, e_prev=None):
        """One sampling period (see "Discretisation" and "Acquisition"):
        `psi_ex_fn(theta)` gives the model extended flux at the predicted angle,
        `e_prev` is the estimated back-EMF one period earlier (V; None or zero: no
        assist this step). Returns `(theta_k, w_k)`."""
        k_p, k_i = self.gains()
        theta_pred = theta_prev + T_s * w_prev
        psi = psi_ex_fn(theta_pred)
        # the angle's cosine and sine once, for the detector and the gate
        e_perp, e_q = _components(e_ab_hat, *cos_sin(theta_pred))
        eps = self._detector(e_perp, e_q, w_prev, psi)
        w_k = w_prev + T_s * k_i * eps
        if e_prev is not None:
            g, w_e = self._gate(e_prev, e_ab_hat, e_q, psi, T_s, w_prev)
            w_k = w_k + (T_s * self.fll * self.w_pll) * g * (w_e - w_prev)
        return wrap_angle(theta_pred + T_s * k_p * eps), w_k


def _components(e_ab, c, s):
    """The components of `e_ab` along the d and q axes at the angle of cosine `c`, sine
    `s`: `(e_perp, e_q)` (the phase detector's `e_perp` is minus the d component)."""
    e0, e1 = e_ab[..., 0], e_ab[..., 1]
    return -(e0 * c + e1 * s), -e0 * s + e1 * c


