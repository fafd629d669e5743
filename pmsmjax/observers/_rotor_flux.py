r"""Rotor-flux-vector adaptive observer of morawiec2023 for interior PM machines.

Reference: M. Morawiec, A. Lewicki, I. C. Odeh, "Rotor-Flux Vector Based Observer of
Interior Permanent Synchronous Machine", IEEE Trans. Ind. Electron. 70(12), 2023,
doi:10.1109/TIE.2023.3250851.

**Machine model** morawiec2023 (1)-(6), stationary frame, with the functions of its
appendix (36)-(40):

$$\frac{di_{s}}{dt} = L_{ab}^{-1}(\theta)(u_s - R_s i_s) - \frac{\omega}{L_d} J\lambda,\qquad
L_{ab}^{-1} = \begin{bmatrix}L_1 & L_3\\ L_3 & L_4\end{bmatrix},$$

with the "rotor flux" $\lambda$ of (5)-(6). This is the flux-linkage model of the plant
($\psi_s = L_{ab}(\theta) i_s + \psi_f e^{\theta J}[1, 0]^T$, $d\psi_s/dt = u_s - R_s i_s$)
written for the current: $\frac{\omega}{L_d}J\lambda = \omega L_{ab}^{-1}
\partial\psi_s/\partial\theta$, so in rotor coordinates $\lambda_{dq} =
[\frac{L_d}{L_q}(\psi_f + (L_d - L_q) i_d),\ (L_q - L_d) i_q]$ (`rotor_flux_ab`,
`current_rhs_ab`; tested against `PMSM.vector_field`). The reluctance torque of (3)
must read $(L_d - L_q) i_d i_q$, not $i_\alpha i_\beta$ (`torque_ab`).

**Observer** (7)-(14): the model with the estimated angle $\hat\theta$ in $L_1, L_3,
L_4$ and in (10)-(14) (Remark 1; the printed left side of (7) lacks its hat), the
estimated current in $\hat\lambda$ and in the resistive drop, and the stabilising
functions (18)-(20):

$$v_\alpha = -c_\alpha R_s L_1 \tilde i_\alpha + c_\lambda \frac{\hat\omega}{L_d}
\hat\lambda_\beta\tilde i_\alpha,\quad v_\beta = -c_\alpha R_s L_4 \tilde i_\beta -
c_\lambda \frac{\hat\omega}{L_d}\hat\lambda_\alpha\tilde i_\beta,\quad
\frac{d\hat\theta}{dt} = \hat\omega - c_\theta\tilde\theta_\lambda,$$

$\tilde i = \hat i - i$ (the paper's estimate-minus-true). $v_\alpha$, $v_\beta$ act per
stationary-frame component (not as a vector), so the error dynamics depend on the rotor
angle itself: `error_rhs` returns them at `op.theta`, or averaged over one electrical
period without it; `analysis.floquet` gives the exact periodic stability.

*Position correction* (29)-(31): $\lambda$ is (5)-(6) with the measured current and
$\hat\theta$, $\hat\lambda$ (10)-(11) with $\hat i$ and $\hat\theta$; (30) is the angle
from $\lambda$ to $\hat\lambda$, $\tan\tilde\theta_\lambda = \varphi =
(\lambda\times\hat\lambda)/(\lambda\cdot\hat\lambda)$. The projection (31) as printed
($\mp\pi/2$ by the sign of $\varphi$) maps a perfect estimate ($\varphi = 0$) to
$-\pi/2$ and jumps by $\pi$ there, so no observer built on it can rest at zero error; it
is read as the quadrant correction of the arctangent (add $\pm\pi$ where
$\lambda\cdot\hat\lambda < 0$), i.e. $\tilde\theta_\lambda = \mathrm{atan2}(\lambda
\times\hat\lambda, \lambda\cdot\hat\lambda)$ in $(-\pi, \pi]$. Both fluxes use
$\hat\theta$, so $\lambda - \hat\lambda = L_d L'^{-1}(L - L')(i - \hat i)$ (in the
estimated frame $L = \mathrm{diag}(L_d, L_q)$, $L' = \mathrm{diag}(L_q, L_d)$): the
signal is the current error seen through the saliency ($\tilde\theta_\lambda \equiv 0$
for $L_d = L_q$). At no load and small errors $\tilde\theta_\lambda \approx
-(L_q - L_d)(i - \hat i)_q/\hat\lambda_d$, and the quasi-steady current error below gives
$(i - \hat i)_q \propto -\omega^2(\theta - \hat\theta)$: $\tilde\theta_\lambda$ has the
sign of $\theta - \hat\theta$, not of $\hat\theta - \theta$ as Remark 2 assumes, so (29)
with $-c_\theta$ pushes the angle away. `theta_sign="derived"` (default) uses
$v_\theta = +c_\theta\tilde\theta_\lambda$ (for $L_d < L_q$, every IPM preset);
`"printed"` keeps $-c_\theta$.

*Speed law* (22), with the scalar-product term (32)-(33), as printed:

$$\frac{d\hat\omega}{dt} = \frac{\gamma}{L_d}\left(\hat\lambda_\beta\tilde
i_\alpha - \hat\lambda_\alpha\tilde i_\beta - k_c s_\omega\right),\qquad
s_\omega = \hat\lambda_\alpha\tilde i_\alpha + \hat\lambda_\beta\tilde i_\beta.$$

Derivation of the sign (non-salient case, $L_d = L_q = L$, $\hat\lambda = \psi_f
e^{\hat\theta J}[1,0]^T$, estimated frame, $a = (1 + c_\alpha)R_s/L$, errors
$\tilde\theta = \hat\theta - \theta$, $\tilde\omega = \hat\omega - \omega$): the current
error obeys $\dot{\tilde i} = -(a + \omega J)\tilde i + b$, $b = \frac{\psi_f}{L}
[\omega\tilde\theta, -\tilde\omega]$, so quasi-statically $\tilde i = (a - \omega J)b/
(a^2 + \omega^2)$. For $\dot{\hat\omega} = \sigma\frac{\gamma}{L}(\hat\lambda_\beta
\tilde i_\alpha - \hat\lambda_\alpha\tilde i_\beta - \kappa k_c s_\omega)$ this gives
$\ddot{\tilde\theta} = \sigma k[(a + \kappa k_c\omega)\dot{\tilde\theta} + (\omega^2 -
\kappa k_c a\omega)\tilde\theta]$, $k = \gamma\psi_f^2/(L^2(a^2 + \omega^2))$. The
printed $\sigma = +1$ makes both coefficients of the characteristic polynomial negative
at $k_c = 0$: unstable at every speed. $\sigma = -1$ is stable, and $\kappa =
-\mathrm{sign}(\omega)$ (the printed minus at positive speed, reversed at negative
speed) turns the $k_c$ term into the extra angle stiffness $k k_c a|\omega|$ that the
paper credits it with near zero speed (with a fixed sign it destabilises one direction
below $|\omega| = k_c a$). `speed_sign="derived"` (default) is therefore

$$\frac{d\hat\omega}{dt} = -\frac{\gamma}{L_d}\left(\hat\lambda_\beta\tilde i_\alpha -
\hat\lambda_\alpha\tilde i_\beta + k_c\,\mathrm{sign}(\hat\omega)\, s_\omega\right);$$

`"printed"` is (32) as printed. For the salient machine the linearisation
(`analysis.linearization`, averaged, and `analysis.floquet`) confirms it: with the
printed sign an eigenvalue lies in the right half plane at every speed and load tested
(and a simulation from a small error diverges), with the derived one the paper's gains
(gamma 1.0 p.u.) are stable at every point tested from 0.2 to 1 p.u., both directions,
loads -0.9, 0, 0.9 p.u., and at 1.5 p.u. except under the motoring 0.9 p.u. load
(`test_rotor_flux.py`; "Choice of gamma" below). Below about 0.13 p.u. at light motoring
load the slowest exponent crosses zero (the angle is unobservable at standstill, and the
position correction, built from the current error, carries no angle information there).
The region of attraction is small: with a matched model at 0.2 p.u. and 0.35 p.u. load
(and gamma 2.0 p.u.) the generic analysis finds an unstable equilibrium at 0.082 rad.

**Saturated machines** (`with_magnetic`, docs/observers.md): the scheduled model takes
the map's apparent $L_d$, $L_q$, $\psi_f$ at the measured current (previous estimate's
frame) into the flux $L_{ab}(\theta) i + \psi_f e^{\theta J}[1, 0]^T$, its inverse,
$\lambda$ and every $1/L_d$: the flux-current relation is the map's at that current (the
$L_{ab}^{-1}$ of the current dynamics is apparent, not incremental: exact in steady
state). The gains are kept.

**Discretisation.** In flux form the rotation terms of (7)-(8) cancel exactly: with
$\hat\psi = L_{ab}(\hat\theta)\hat i + \psi_f e^{\hat\theta J}[1,0]^T$,
$d\hat\psi/dt = u - R_s\hat i + L_{ab}(\hat\theta) v + v_\theta\,\partial\hat\psi/
\partial\hat\theta$, and $\hat i$ is recovered from $\hat\psi$ and $\hat\theta$. The
state is $(\hat\psi_{ab}, \hat\theta, \hat\omega)$; between $t_{k-1}$ and $t_k$ the
voltage is integrated exactly for the zero-order hold, $-R_s\hat i = -R_s i + R_s(i -
\hat i)$ with the measured part by the trapezoid; the feedback explicitly at $t_{k-1}$,
held in the estimator frame while it turns (the sinc rule of the zhang2022 observers);
the speed by forward Euler and the angle with the mean of the old and new speed
estimates (semi-implicit: the Jacobian of a step stays $I + T_sA + O(T_s^2)$, and with
the paper's fast gains on a low-inductance machine a plain Euler angle drifted from the
continuous error dynamics by 6 % over 30 ms at 50 kHz, this rule by 2.8 %;
`test_contract.py`). A matched observer at zero error stays there exactly. At $k = 0$
the flux is initialised from the measured current and the initial angle ($\hat i_0 = i_0$).

**Choice of gamma** (not given with the paper's gains; Fig. 5(b) sweeps 0.01-2 p.u.),
measured on `morawiec_ipm3k5` at 6.6 kHz with the other gains as printed:

- *Spectra.* The slowest Floquet exponent at 0.2-1 p.u., both directions, MTPA currents
  for i_q = -1..1 p.u., is set by c_theta (about -0.15 p.u. = -47 1/s) and hardly moves
  with gamma from 0.5 to 2; it is -0.02 p.u. near i_q = 0.2 p.u. at 0.2 p.u. and crosses
  zero below 0.13 p.u. at light load whatever gamma. Small gamma loses the loaded high
  speeds: with gamma = 0.5 the exponent is +0.046 p.u. at 1 p.u. and i_q = 0.5 p.u.,
  with 0.75 +0.096 at 1.5 p.u.; 1.0 is stable to 1 p.u. at every load and at 1.5 p.u.
  up to i_q = 0.2 p.u. (+0.095 p.u. at 1.5 p.u., i_q = 0.5 p.u.).
- *Discretisation.* The speed state is advanced by forward Euler; its lightly damped
  pair grows with gamma / L. With the observer's L_q = 0.3 L_qN (Fig. 16(b)) at 0.2 p.u.
  and 0.33 p.u. current, gamma = 2.0 diverges at 6.6 kHz into a limit cycle (speed
  ripple 3.8 p.u.) but converges at 66 kHz, and 1.0-1.5 converge at 6.6 kHz
  (`test_rotor_flux.py`): 2.0 is beyond the sampling rate's limit for the paper's own
  mismatch test.
- *Closed loop* (`pmsmjax.papers.morawiec2023`): with gamma = 2.0 the load reversal of
  Fig. 14(a) loses the speed; with 1.0 it holds (angle error 0.028 rad).

So 1.0 p.u.: the middle of the interval that the high-speed spectra (>= ~0.8) and the
sampling rate (< 2) leave.

**Error coordinates** (true minus estimate, as everywhere in pmsmjax): the current error
$i - \hat i$ in the estimated frame, the angle error $\theta - \hat\theta$, the speed
error $\omega - \hat\omega$.

**Per unit.** The paper's gains are in its per unit ($\tau = \omega_b t$):
$c_\alpha$, $k_c$ dimensionless; $c_\lambda$ per current base; $c_\theta$ per time base;
$\gamma$ per (time base)$^2$ (current base)$^2$. `from_drive` converts them with the
drive's bases: $c_\lambda = c_{\lambda,pu}/I_b$ (1/A), $c_\theta = c_{\theta,pu}\omega_b$
(1/s), $\gamma = \gamma_{pu}\omega_b^2/I_b^2$ (1/(s^2 A^2)).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._frames import cos_sin, rotate, rotation_between, wrap_angle
from .._plant._params import Drive, PMSMParams
from .._validate import check_positive
from . import _rotor_flux_design as _design
from ._base import (
    AbstractObserver,
    ErrorCoordinates,
    Estimate,
    Measurement,
    OperatingPoint,
    PlantPoint,
)


_SIGNS = {"derived": -1.0, "printed": 1.0}
#: Rotor angles at which the angle-dependent error dynamics are averaged over one period:
#: they are a trigonometric polynomial of degree <= 4 in the rotor angle (harmonics 2 and
#: 4 from L1, L4, 1 and 3 from the c_lambda terms), so the mean of 8 equally spaced
#: angles is exact (tested against 64).
N_AVERAGE = 8

#: morawiec2023's gains (p.u., Sec. III end): c_alpha 3.0, c_lambda 0.001, k_c 0.1,
#: c_theta 0.15. gamma is not given with them: 1.0 p.u. is chosen here (the module
#: docstring, "Choice of gamma", gives the spectra and simulations behind it).
PAPER_GAINS_PU = {"c_alpha": 3.0, "c_lambda": 0.001, "k_c": 0.1, "c_theta": 0.15,
                  "gamma": 1.0}
#: $(\psi_f / L_d)^2$ (p.u.) of the machine gamma = 1.0 p.u. was chosen on
#: (morawiec2023 Table I: psi_f = 0.89 p.u., L_d = 0.28 p.u.).
PAPER_PSI_OVER_LD_PU2 = (0.89 / 0.28) ** 2


def gamma_pu_for(drive: Drive) -> float:
    r"""The default speed-law gain gamma (p.u.) for `drive`: the paper's 1.0 p.u. (see
    "Choice of gamma"), lowered in proportion where the machine's $(\psi_f / L_d)^2$ in
    p.u. exceeds that of morawiec2023's test machine (10.1), never raised.

    Why (derived, not from the paper): near the designed lock the speed loop's gain is
    $k = \gamma\psi_f^2 / (L_d^2(a^2 + \omega^2))$ (the derivation of the speed law's
    sign above), so gamma in p.u. alone does not fix the loop: on stumper_mt5
    ($(\psi_f/L_d)^2$ = 60.9 p.u.) gamma = 1.0 p.u. gives a loop six times as fast as on
    the paper's machine, and its forward-Euler speed update is unstable at 16 kHz (the
    largest pole of one real step over an electrical period, `analysis.discrete_poles`,
    is 1.008 at 62.5 us and 1.06 at 125 us: a replay from the true state runs away after
    0.1 s); with this rule (0.166 p.u.) it is 0.999 and 0.998 (`test_rotor_flux.py`).
    On the paper's machine the rule gives the paper's 1.0 p.u. exactly."""
    b, m = drive.base, drive.three_phase_motor
    L_b = float(b.U_b) / (float(b.w_b) * float(b.I_b))
    ratio = (float(m.psi_f) / (L_b * float(b.I_b)) / (float(m.L_d) / L_b)) ** 2
    factor = PAPER_PSI_OVER_LD_PU2 / ratio
    # the paper's machine's preset reproduces its p.u. values to rounding
    return PAPER_GAINS_PU["gamma"] * (1.0 if factor > 1.0 - 1e-6 else factor)


# ---------------------------------------------------------------------------------------
# The machine model of morawiec2023 (1)-(6), (36)-(40)
# ---------------------------------------------------------------------------------------

def l_functions(motor: PMSMParams, theta):
    """`(L1, L3, L4)` of morawiec2023 (12)-(13)/(36)-(38) at angle `theta` (rad), 1/H:
    the entries of the inverse stationary-frame inductance matrix."""
    c, s = cos_sin(theta)
    L1 = c * c / motor.L_d + s * s / motor.L_q
    L3 = 0.5 * (1.0 / motor.L_d - 1.0 / motor.L_q) * jnp.sin(2.0 * theta)
    L4 = s * s / motor.L_d + c * c / motor.L_q
    return L1, L3, L4


def rotor_flux_ab(motor: PMSMParams, theta, i_ab):
    """The rotor flux vector lambda of morawiec2023 (5)-(6) (or (10)-(11) with estimates)
    at angle `theta` (rad) and current `i_ab` (A, stationary frame) -> V s, `(2,)`."""
    L0 = 0.5 * (motor.L_d + motor.L_q)
    L2 = 0.5 * (motor.L_d - motor.L_q)
    r = motor.L_d / motor.L_q
    c2, s2 = cos_sin(2.0 * theta)
    i_a, i_b = i_ab[..., 0], i_ab[..., 1]
    i_a2 = i_a * c2 + i_b * s2                       # (39)
    i_b2 = -i_a * s2 + i_b * c2                      # (40)
    lam_a = r * motor.psi_f * jnp.cos(theta) - (1.0 - r) * (L0 * i_a2 + L2 * i_a)
    lam_b = r * motor.psi_f * jnp.sin(theta) + (1.0 - r) * (L0 * i_b2 - L2 * i_b)
    return jnp.stack([lam_a, lam_b], -1)


def current_rhs_ab(motor: PMSMParams, theta, w_m, i_ab, u_ab):
    """di_ab/dt of morawiec2023 (1)-(2) in SI (A/s): angle `theta` (rad), electrical
    speed `w_m` (rad/s), current `i_ab` (A), voltage `u_ab` (V), stationary frame."""
    L1, L3, L4 = l_functions(motor, theta)
    lam = rotor_flux_ab(motor, theta, i_ab)
    ea = u_ab[..., 0] - motor.R_s * i_ab[..., 0]
    eb = u_ab[..., 1] - motor.R_s * i_ab[..., 1]
    return jnp.stack([w_m / motor.L_d * lam[..., 1] + ea * L1 + eb * L3,
                      -w_m / motor.L_d * lam[..., 0] + ea * L3 + eb * L4], -1)


def torque_ab(motor: PMSMParams, theta, i_ab):
    """Electromagnetic torque of morawiec2023 (3) in SI (N m), with the reluctance term
    corrected to $(L_d - L_q) i_d i_q$ (the printed $i_\\alpha i_\\beta$ is not invariant
    under rotation): $\\tfrac32 n_p(\\psi_{f\\alpha} i_\\beta - \\psi_{f\\beta} i_\\alpha
    + (L_d - L_q) i_d i_q)$."""
    c, s = cos_sin(theta)
    i_a, i_b = i_ab[..., 0], i_ab[..., 1]
    i_d, i_q = c * i_a + s * i_b, c * i_b - s * i_a
    return 1.5 * motor.n_p * (motor.psi_f * (c * i_b - s * i_a)
                              + (motor.L_d - motor.L_q) * i_d * i_q)


def stator_flux_ab(motor: PMSMParams, theta, i_ab):
    """Stator flux $L_{ab}(\\theta) i + \\psi_f e^{\\theta J}[1,0]^T$ (V s, stationary)."""
    L0 = 0.5 * (motor.L_d + motor.L_q)
    L2 = 0.5 * (motor.L_d - motor.L_q)
    c2, s2 = cos_sin(2.0 * theta)
    i_a, i_b = i_ab[..., 0], i_ab[..., 1]
    return jnp.stack([(L0 + L2 * c2) * i_a + L2 * s2 * i_b + motor.psi_f * jnp.cos(theta),
                      L2 * s2 * i_a + (L0 - L2 * c2) * i_b + motor.psi_f * jnp.sin(theta)],
                     -1)


def current_from_flux_ab(motor: PMSMParams, theta, psi_ab):
    """Inverse of `stator_flux_ab`: the current (A) of flux `psi_ab` (V s) at `theta`."""
    L1, L3, L4 = l_functions(motor, theta)
    pa = psi_ab[..., 0] - motor.psi_f * jnp.cos(theta)
    pb = psi_ab[..., 1] - motor.psi_f * jnp.sin(theta)
    return jnp.stack([L1 * pa + L3 * pb, L3 * pa + L4 * pb], -1)


def _dflux_dtheta(motor: PMSMParams, theta, i_ab):
    """$\\partial\\psi_s/\\partial\\theta$ at constant current (V s/rad)."""
    L2 = 0.5 * (motor.L_d - motor.L_q)
    c2, s2 = cos_sin(2.0 * theta)
    i_a, i_b = i_ab[..., 0], i_ab[..., 1]
    return jnp.stack([2 * L2 * (-s2 * i_a + c2 * i_b) - motor.psi_f * jnp.sin(theta),
                      2 * L2 * (c2 * i_a + s2 * i_b) + motor.psi_f * jnp.cos(theta)], -1)


def _inductance_ab(motor: PMSMParams, theta):
    L0 = 0.5 * (motor.L_d + motor.L_q)
    L2 = 0.5 * (motor.L_d - motor.L_q)
    c2, s2 = cos_sin(2.0 * theta)
    return (L0 + L2 * c2, L2 * s2, L0 - L2 * c2)


def flux_angle_error(lam_ab, lam_hat_ab):
    """$\\tilde\\theta_\\lambda$ of morawiec2023 (30)-(31) (rad): the angle from `lam_ab`
    to `lam_hat_ab`, atan2 of their cross and dot products (the quadrant-corrected
    arctangent of $\\varphi$; see the module docstring on (31)): `rotation_between`."""
    return rotation_between(lam_ab, lam_hat_ab)


# ---------------------------------------------------------------------------------------
# The observer
# ---------------------------------------------------------------------------------------

class RotorFluxState(eqx.Module):
    """State of `RotorFluxObserver`.

    - `psi_ab`: the observer's stator flux $L_{ab}(\\hat\\theta)\\hat i + \\psi_f
      e^{\\hat\\theta J}[1,0]^T$ (V s, stationary frame), from which $\\hat i$ follows.
    - `theta`: estimated electrical angle, wrapped (rad).
    - `w`: estimated electrical speed $\\hat\\omega$ (rad/s).
    - `i_prev`: the current measured at the previous instant (A, stationary frame).
    - `started`: False until the first sample has been seen.
    """

    psi_ab: jnp.ndarray
    theta: jnp.ndarray
    w: jnp.ndarray
    i_prev: jnp.ndarray
    started: jnp.ndarray


_COORDS = ErrorCoordinates(
    names=("i_d", "i_q", "theta", "w"), units=("A", "A", "rad", "rad/s"), angle=2,
    doc=("current error i - i_hat, estimated frame d axis",
         "current error i - i_hat, estimated frame q axis",
         "angle error theta - theta_hat",
         "speed error w - w_hat"))

_DESIGN_UNITS = {
    "c_alpha": "-, current-error gain morawiec2023 (18)-(19)",
    "c_lambda": "1/A, rotor-flux gain morawiec2023 (18)-(19) (p.u. value / I_b)",
    "k_c": "-, scalar-product gain of the speed law morawiec2023 (32)-(33)",
    "c_theta": "1/s, position-correction gain morawiec2023 (20)/(29) (p.u. value x w_b)",
    "gamma": "1/(s^2 A^2), speed-adaptation gain morawiec2023 (22)/(32) "
             "(p.u. value x w_b^2 / I_b^2)",
}


class RotorFluxObserver(AbstractObserver):
    r"""Rotor-flux-vector adaptive observer, morawiec2023 (7)-(14), (18)-(20), (29)-(33).

    See the module docstring for the equations, the sign of the speed law, the
    projection (31) and the discretisation. Returns $\hat\theta$ and $\hat\omega$; extras
    `i_ab_hat` (A), `lambda_ab_hat` (V s), `s_omega` (A^2, (33) divided by $L_d$) and
    `theta_lambda` (rad, (30)-(31)).

    **Arguments:**

    - `motor`: the observer's machine model (`PMSMParams`).
    - `c_alpha` (-), `c_lambda` (1/A), `k_c` (-), `c_theta` (1/s), `gamma`
      (1/(s^2 A^2)): the gains in SI (`from_drive` converts the paper's p.u. values).
    - `speed_sign`: `"derived"` (default, stable) or `"printed"` (the sign of (22)/(32)
      as printed, unstable; kept for comparison).
    """

    paper_motor: ClassVar[str | None] = "morawiec_ipm3k5"
    paper_T_s: ClassVar[float | None] = 1 / 6600
    c_emitter: ClassVar[str | None] = "_morawiec2023:emit"
    motor: PMSMParams
    c_alpha: float
    c_lambda: float
    k_c: float
    c_theta: float
    gamma: float
    speed_sign: str = eqx.field(static=True, default="derived")
    theta_sign: str = eqx.field(static=True, default="derived")

    coordinates: ClassVar[ErrorCoordinates] = _COORDS
    design_units: ClassVar[dict[str, str]] = _DESIGN_UNITS
    #: the gains act per stationary-frame component: a 4 theta term in the linearisation
    angle_dependent: ClassVar[bool] = True
    #: two branches of the inner problem even with a matched model (morawiec_ipm3k5 at
    #: 0.5 and 0.8 p.u. under 0.4 p.u. load; tests/test_equilibria.py)
    equilibria_starts: ClassVar[bool] = True
    #: the inner problem is not affine (the flux estimate's magnitude and angle): with
    #: 3 steps the analysis missed 6 of the equilibria SciPy's root finder finds at 100
    #: points of the comparison grid on morawiec_ipm3k5 (every third, paper design),
    #: with 8 none (12-03)
    equilibria_gauss_newton: ClassVar[int] = 8
    extras: ClassVar[dict[str, str]] = {
        "i_ab_hat": "A, estimated stator current, stationary frame (2,)",
        "lambda_ab_hat": "V s, estimated rotor flux vector morawiec2023 (10)-(11) (2,)",
        "s_omega": "A^2, scalar product morawiec2023 (33) divided by L_d",
        "theta_lambda": "rad, flux angle deviation morawiec2023 (30)-(31)"}
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "c_alpha": (0.2, 5.0), "c_theta": (0.2, 5.0), "gamma": (0.1, 10.0), "k_c": (0.1, 10.)}
    tunable_kinds, tuning_spectral = {"c_theta": "explicit"}, True
    tuning_coordinates, tuning_replaces = _design.TUNING_COORDINATES, _design.TUNING_REPLACES
    # the tuner's coordinates, from the reduced spectrum (`_rotor_flux_design`)
    design_from_tuning, tuning_from_design = (_design.design_from_tuning,
                                              _design.tuning_from_design)

    def __check_init__(self):
        if not isinstance(self.motor, PMSMParams):
            raise ValueError(f"`RotorFluxObserver(motor=...)` must be a `PMSMParams`; got "
                             f"{type(self.motor).__name__}.")
        for name in ("speed_sign", "theta_sign"):
            if getattr(self, name) not in _SIGNS:
                raise ValueError(f"`RotorFluxObserver({name}=...)` must be one of "
                                 f"{', '.join(_SIGNS)}; got {getattr(self, name)!r}.")
        for name in ("c_alpha", "c_lambda", "k_c", "c_theta", "gamma"):
            check_positive("RotorFluxObserver", name, getattr(self, name),
                           _DESIGN_UNITS[name].split(",")[0], allow_zero=True)

    @classmethod  # --- design ---------------------------------------------------------
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None,
                   speed_sign: str = "derived", theta_sign: str = "derived", **design):
        """morawiec2023's gains (c_alpha 3.0, c_lambda 0.001, k_c 0.1, c_theta 0.15 p.u.)
        converted to SI with `drive.base` (see the module docstring). The paper gives no
        gamma with them (Figs. 3-5 sweep 0.01-2 p.u.); 1.0 p.u. is chosen on the paper's
        machine (module docstring, "Choice of gamma") and scaled to keep the speed loop's
        gain on machines of larger psi_f / L_d (`gamma_pu_for`).
        `design` overrides gains by name in SI (`design_units`)."""
        motor = drive.three_phase_motor if motor is None else motor
        b = drive.base
        pu = PAPER_GAINS_PU
        obs = cls(motor=motor, c_alpha=pu["c_alpha"], c_lambda=pu["c_lambda"] / b.I_b,
                  k_c=pu["k_c"], c_theta=pu["c_theta"] * b.w_b,
                  gamma=gamma_pu_for(drive) * b.w_b ** 2 / b.I_b ** 2, speed_sign=speed_sign,
                  theta_sign=theta_sign)
        return obs.with_design(**design) if design else obs

    @classmethod
    def from_pu(cls, drive: Drive, *, motor: PMSMParams | None = None,
                speed_sign: str = "derived", theta_sign: str = "derived", **gains_pu):
        """As `from_drive`, with the gains given in the paper's p.u. (`c_alpha`,
        `c_lambda`, `k_c`, `c_theta`, `gamma`)."""
        bad = sorted(set(gains_pu) - set(_DESIGN_UNITS))
        if bad:
            raise ValueError(f"`RotorFluxObserver.from_pu`: unknown gain(s) "
                             f"{', '.join(bad)}; it has {', '.join(_DESIGN_UNITS)}.")
        g = {**PAPER_GAINS_PU, **gains_pu}
        b = drive.base
        return cls.from_drive(drive, motor=motor, speed_sign=speed_sign,
                              theta_sign=theta_sign,
                              c_alpha=g["c_alpha"], c_lambda=g["c_lambda"] / b.I_b,
                              k_c=g["k_c"], c_theta=g["c_theta"] * b.w_b,
                              gamma=g["gamma"] * b.w_b ** 2 / b.I_b ** 2)

    def with_design(self, **values):
        self._check_design_names(values)
        if not values:
            return self
        for k, v in values.items():
            check_positive("RotorFluxObserver.with_design", k, v,
                           _DESIGN_UNITS[k].split(",")[0], allow_zero=True)
        return self._replace(**values)

    # --- the observer's right-hand side -----------------------------------------------
    def _feedback(self, theta_h, w_h, psi_h, i_meas):
        """Everything the observer computes from its state and the measured current:
        `(i_hat, lam_hat, v_ab, v_theta, dw_hat, s_omega, theta_lambda)`."""
        m = self.motor
        i_hat = current_from_flux_ab(m, theta_h, psi_h)
        e = i_hat - i_meas                                     # paper's i~ (16)
        lam_hat = rotor_flux_ab(m, theta_h, i_hat)             # (10)-(11)
        lam = rotor_flux_ab(m, theta_h, i_meas)                # (5)-(6) at theta_hat
        L1, _, L4 = l_functions(m, theta_h)
        v_a = -self.c_alpha * m.R_s * L1 * e[..., 0] \
            + self.c_lambda * w_h / m.L_d * lam_hat[..., 1] * e[..., 0]     # (18)
        v_b = -self.c_alpha * m.R_s * L4 * e[..., 1] \
            - self.c_lambda * w_h / m.L_d * lam_hat[..., 0] * e[..., 1]     # (19)
        th_lam = flux_angle_error(lam, lam_hat)                # (30)-(31)
        # (29): printed -c_theta theta_lambda; derived +c_theta theta_lambda
        v_theta = -_SIGNS[self.theta_sign] * self.c_theta * th_lam
        cross = (lam_hat[..., 1] * e[..., 0] - lam_hat[..., 0] * e[..., 1]) / m.L_d
        s_w = (lam_hat[..., 0] * e[..., 0] + lam_hat[..., 1] * e[..., 1]) / m.L_d  # (33)
        if self.speed_sign == "printed":                       # (32) as printed
            dw = self.gamma * (cross - self.k_c * s_w)
        else:                                                  # derived (module docstring)
            dw = -self.gamma * (cross + self.k_c * jnp.sign(w_h) * s_w)
        return i_hat, lam_hat, jnp.stack([v_a, v_b], -1), v_theta, dw, s_w, th_lam

    def _flux_correction(self, theta_h, i_hat, i_meas, v_ab, v_theta):
        """$d\\hat\\psi/dt - (u - R_s i)$: $R_s(i - \\hat i) + L_{ab}(\\hat\\theta) v +
        v_\\theta\\,\\partial\\hat\\psi/\\partial\\hat\\theta$ (V)."""
        m = self.motor
        La, Lab, Lb = _inductance_ab(m, theta_h)
        Lv = jnp.stack([La * v_ab[..., 0] + Lab * v_ab[..., 1],
                        Lab * v_ab[..., 0] + Lb * v_ab[..., 1]], -1)
        return m.R_s * (i_meas - i_hat) + Lv + v_theta * _dflux_dtheta(m, theta_h, i_hat)

    # --- running ----------------------------------------------------------------------
    def init(self, theta0=0.0, w0=0.0) -> RotorFluxState:
        theta0 = jnp.asarray(theta0)
        w0 = jnp.asarray(w0)
        dtype = jnp.result_type(theta0, w0, float)
        zero2 = jnp.zeros(2, dtype)
        return RotorFluxState(psi_ab=zero2, theta=wrap_angle(theta0.astype(dtype)),
                              w=w0.astype(dtype), i_prev=zero2,
                              started=jnp.asarray(False))

    def _rates(self, th, w, psi, i_meas):  # noqa: D401
        """`(flux correction (V), frame speed (rad/s), dw_hat/dt (rad/s^2))`."""
        i_hat, _, v_ab, v_th, dw, _, _ = self._feedback(th, w, psi, i_meas)
        return self._flux_correction(th, i_hat, i_meas, v_ab, v_th), w + v_th, dw

    def step(self, state: RotorFluxState, meas: Measurement, T_s):
        self = self._scheduled(state, meas)  # noqa: PLW0642 (the current-scheduled model)
        m = self.motor
        th, w, psi = state.theta, state.w, state.psi_ab
        i_k = jnp.asarray(meas.i_ab).astype(state.i_prev.dtype)
        # exact for the held voltage and the trapezoidal drop of the measured current
        psi_uR = psi + T_s * meas.u_ab - (0.5 * T_s * m.R_s) * (state.i_prev + i_k)
        # Heun (trapezoid) on the feedback: predictor with the current at t_{k-1},
        # corrector with the current at t_k
        c1, wf1, dw1 = self._rates(th, w, psi, state.i_prev)
        w_new = w + T_s * dw1
        dth = T_s * (wf1 - w + 0.5 * (w + w_new))
        # the correction held in the estimator frame, which turns by dth: exact integral
        half = 0.5 * dth
        psi_new = psi_uR + (T_s * jnp.sinc(half / jnp.pi)) * rotate(c1, half)
        th_new = wrap_angle(th + dth)
        go = state.started
        # a design beyond the sampling rate's limit runs away (see "Choice of gamma"):
        # the state is held where a step would leave it non-finite, so that the estimate
        # stays finite (frozen) and the run reports the lost lock instead of NaN
        finite = jnp.all(jnp.isfinite(psi_new)) & jnp.isfinite(w_new) & jnp.isfinite(dth)
        psi_new = jnp.where(finite, psi_new, psi)
        w_new = jnp.where(finite, w_new, w)
        th_new = jnp.where(finite, th_new, th)
        psi0 = stator_flux_ab(m, th, i_k)
        psi_new = jnp.where(go, psi_new, psi0).astype(state.psi_ab.dtype)
        th_new = jnp.where(go, th_new, th).astype(state.theta.dtype)
        w_new = jnp.where(go, w_new, w).astype(state.w.dtype)
        new = RotorFluxState(psi_ab=psi_new, theta=th_new, w=w_new, i_prev=i_k,
                             started=jnp.ones_like(state.started))
        i_h, lam_h, _, _, _, s_w, th_lam = self._feedback(th_new, w_new, psi_new, i_k)
        return new, Estimate(theta_hat=th_new, w_hat=w_new,
                             extras={"i_ab_hat": i_h, "lambda_ab_hat": lam_h,
                                     "s_omega": s_w, "theta_lambda": th_lam})

    # --- analysis ---------------------------------------------------------------------
    def _error_rhs_at(self, x, w, i0, theta, plant: PMSMParams):
        """Instantaneous error dynamics at true rotor angle `theta` (rad)."""
        th_h = theta - x[2]
        w_h = w - x[3]
        i_ab = rotate(i0, th_h)
        i_hat = i_ab - rotate(x[:2], th_h)
        psi_h = stator_flux_ab(self.motor, th_h, i_hat)
        _, _, v_ab, v_th, dw, _, _ = self._feedback(th_h, w_h, psi_h, i_ab)
        dth_h = w_h + v_th
        # the observer's flux: d psi_hat/dt = u - R_hat i + correction; the plant's flux
        # d psi/dt = u - R i with i held at i0 in the estimated frame (ideal current
        # control): the voltage cancels, d psi_hat/dt = d psi/dt + (R - R_hat) i + corr
        dpsi = _dflux_dtheta(plant, theta, i_ab) * w + \
            _inductance_apply(plant, theta, dth_h * jnp.stack([-i_ab[1], i_ab[0]]))
        i_hat_c = i_hat  # the correction uses the observer's current estimate
        dpsi_h = dpsi + (plant.R_s - self.motor.R_s) * i_ab + \
            self._flux_correction(th_h, i_hat_c, i_ab, v_ab, v_th)
        # i_hat = current_from_flux(theta_hat, psi_hat): its rate
        # L(theta_hat)^-1 (dpsi_hat/dt - dtheta_hat/dt d psi_hat/d theta_hat at const i_hat)
        L1, L3, L4 = l_functions(self.motor, th_h)
        r = dpsi_h - dth_h * _dflux_dtheta(self.motor, th_h, i_hat)
        di_hat = jnp.stack([L1 * r[0] + L3 * r[1], L3 * r[0] + L4 * r[1]])
        # e_dq = i0 - exp(-theta_hat J) i_hat
        ih_dq = rotate(i_hat, -th_h)
        de = dth_h * jnp.stack([-ih_dq[1], ih_dq[0]]) - rotate(di_hat, -th_h)
        return jnp.concatenate([de, jnp.stack([w - dth_h, -dw])])

    def error_rhs(self, x, op: OperatingPoint, plant: PMSMParams):
        """The error dynamics of (7)-(14), (18)-(20), (29)-(33) against the plant (1)-(6)
        (fundamental PM flux) with ideal current control at `op`: instantaneous at the
        true rotor angle `op.theta`, else averaged over one electrical period
        (`N_AVERAGE` angles; see the module docstring)."""
        x = jnp.asarray(x)
        dtype = x.dtype
        w = jnp.asarray(op.w_m, dtype)
        i0 = jnp.asarray(op.i_dq, dtype)
        if op.theta is not None:
            return self._error_rhs_at(x, w, i0, jnp.asarray(op.theta, dtype), plant)
        thetas = jnp.arange(N_AVERAGE, dtype=dtype) * (2 * jnp.pi / N_AVERAGE)
        f = jax.vmap(lambda t: self._error_rhs_at(x, w, i0, t, plant))(thetas)
        return jnp.mean(f, 0)

    def error_scale(self, op: OperatingPoint, plant: PMSMParams):
        del plant
        m = self.motor
        i_d, i_q = op.i_dq[..., 0], op.i_dq[..., 1]
        psi = jnp.sqrt((m.L_d * i_d + m.psi_f) ** 2 + (m.L_q * i_q) ** 2)
        i_s = psi / jnp.sqrt(m.L_d * m.L_q)
        i_s = jnp.where(i_s > 0, i_s, 1.0)
        aw = jnp.abs(op.w_m)
        return jnp.stack([i_s, i_s, jnp.ones_like(i_s), jnp.where(aw > 0, aw, 1.0)])

    def error_state(self, state: RotorFluxState, truth: PlantPoint, plant: PMSMParams):
        del plant
        i_hat = current_from_flux_ab(self.motor, state.theta, state.psi_ab)
        e_dq = rotate(truth.i_ab - i_hat, -state.theta)
        return jnp.concatenate([e_dq, jnp.stack([wrap_angle(truth.theta - state.theta),
                                                 truth.w_m - state.w])])

    def observer_state(self, x, truth: PlantPoint, plant: PMSMParams) -> RotorFluxState:
        del plant
        x = jnp.asarray(x)
        theta = wrap_angle(truth.theta - x[2])
        i_ab = jnp.asarray(truth.i_ab, x.dtype)
        i_hat = i_ab - rotate(x[:2], theta)
        return RotorFluxState(psi_ab=stator_flux_ab(self.motor, theta, i_hat), theta=theta,
                              w=truth.w_m - x[3], i_prev=i_ab, started=jnp.asarray(True))


def _inductance_apply(motor, theta, v):
    La, Lab, Lb = _inductance_ab(motor, theta)
    return jnp.stack([La * v[0] + Lab * v[1], Lab * v[0] + Lb * v[1]])
