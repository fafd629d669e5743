r"""Nonlinear (gradient) flux observer with a phase-locked loop on the flux angle.

References: J. Lee, J. Hong, K. Nam, R. Ortega, L. Praly, A. Astolfi, "Sensorless
control of surface-mount permanent-magnet synchronous motors based on a nonlinear
observer", IEEE Trans. Power Electron. 25(2), 290-297, 2010 (Lee2010; the observer and
its experiments); R. Ortega, L. Praly, A. Astolfi, J. Lee, K. Nam, "Estimation of rotor
position and speed of permanent magnet synchronous motors with guaranteed stability",
IEEE Trans. Control Syst. Technol. 19(3), 601-614, 2011 (Ortega2011; the same observer
with its global-convergence analysis). Equation numbers are not quoted: only the
equations below, each checked here by linearisation and simulation, are used.

**Observer** (stationary frame, real 2-vectors). With $y = u - R_s i$ the stator flux
$x$ obeys $\dot x = y$, and for a surface-mount machine $\eta(x) = x - L i$ is the rotor
(PM) flux vector $\psi_f[\cos\theta, \sin\theta]$, of known magnitude. The observer is
the gradient search that pulls $|\eta|$ to $\psi_f$:

$$\dot{\hat x} = y + \frac{\gamma}{2}\,\eta(\hat x)\,\big(\psi_f^2 - |\eta(\hat x)|^2\big),
\qquad \theta_{obs} = \mathrm{atan2}(\eta_\beta, \eta_\alpha).$$

*Salient machines* (active flux, not in the papers). With $\eta = x - L_q i$ the true
$\eta$ is, in rotor coordinates, $[\psi_f + (L_d - L_q)i_d,\ 0]$ at every instant (the
linear flux model $\psi_{dq} = [L_d i_d + \psi_f, L_q i_q]$): along the d axis, of
magnitude $\psi_a = \psi_f + (L_d - L_q)i_d$ (`PMSMParams.extended_flux`). The target
magnitude is that, with $i_d$ the measured current in the PLL's frame. Assumed: a linear
(or current-scheduled, `with_magnetic`) flux model, and an angle estimate close enough
that $i_d$ in the estimated frame is the rotor's: the target is off by
$(L_d - L_q)(\hat i_d - i_d) \approx (L_d - L_q)i_q\tilde\theta$, which couples the angle
error into the magnitude. The determinant of the linearised error dynamics is exactly
$k_i\,\omega(\omega + \lambda\kappa)$, $\kappa = (L_d - L_q)i_q/\psi_a$ (with a fast
PLL the flux block is $s^2 + \lambda s + \omega^2 + \lambda\omega\kappa$): a real
eigenvalue crosses zero at $\omega = -\lambda\kappa$. For $L_d < L_q$ the designed
lock is therefore unstable while motoring ($\omega i_q > 0$) below $|\omega| =
\lambda|\kappa|$: 0.06 p.u. at half the base current on `morawiec_ipm3k5` (tested), a
slow divergence (about 1 1/s) that a reversal crosses in a few ms.

*Gain with a physical meaning.* In rotor coordinates the estimate-minus-true flux $z$
obeys, to first order, $\dot z = [[-\lambda, \omega], [-\omega, 0]]\,z$ with
$\lambda = \gamma\psi_a^2$: the linearised rate at which $|\eta|$ converges to its target.
Characteristic polynomial $s^2 + \lambda s + \omega^2$: natural frequency $|\omega|$,
damping $\lambda / (2|\omega|)$; the angle is not observable at standstill (a double
pole at 0 there: any point on the circle $|\eta| = \psi_a$ is at rest). The design
parameter is `lam` (1/s), $\gamma = \lambda/\hat\psi_f^2$ (1/(V^2 s^3)): exactly the rate
at $i_d = 0$ ($\lambda(\psi_a/\psi_f)^2$ otherwise). Default $\lambda = 0.2\,\omega_{rated}$:
critically damped at 0.1 p.u., the handover speed of the I/f start (`IfStartup`);
decay rate $\lambda/2$ above that speed, $\omega^2/\lambda$ below it.

**PLL** (speed and the filtered angle, a standard angle-tracking loop, not from the
papers, which build a speed observer of their own). Phase detector
$\varepsilon = (\cos\hat\theta\,\eta_\beta - \sin\hat\theta\,\eta_\alpha)/\psi_a =
(|\eta|/\psi_a)\sin(\theta_{obs} - \hat\theta)$ ($\psi_a$ from the model's $\psi_f$,
also for `"adaptive"`: normalised by the estimate, the detector's sign would flip with
$\hat\psi_f$ and make $\tilde\theta = \pi$, $\hat\psi_f = -\psi_f$ a stable lock),
$\dot{\hat\theta} = \hat\omega + k_p\varepsilon$, $\dot{\hat\omega} = k_i\varepsilon$,
$k_p = 2\zeta_{pll}\omega_{pll}$, $k_i = \omega_{pll}^2$. A flux (not a back-EMF) has the
same sign and size at every speed, so the loop needs no speed normalisation and tracks
through zero speed. With a matched model $\hat x = x$ is invariant at any speed profile,
so the flux angle has no lag; the PLL lags a speed ramp $a$ by $a/\omega_{pll}^2$.
Defaults: $\omega_{pll} = 2\pi\cdot 50$ rad/s (the bandwidth zhang2022 gives its
speed/angle loop, $\omega_2$; $\omega_{pll}T_s = 0.04$ at 8 kHz), $\zeta_{pll} = 1$. A
loop tied to the rated speed instead (0.4 $\omega_{rated}$, 126 rad/s on
`morawiec_ipm3k5`) left 0.12 deg of mean error from the speed loop's settling after a
load step there (measured; 0.014 deg with 2 pi 50). For a surface-mount model the
linearisation is block triangular: the flux block $s^2 + \lambda s + \omega^2$ drives
the PLL's $s^2 + k_p s + k_i$ (tested); saliency couples them (above).

**Variants** (`variant`, static):

- `"gradient"` (default): the equation above.
- `"clamped"`: the factor $\psi_a^2 - |\eta|^2$ clamped to $\ge 0$: the term only
  pushes $\eta$ outward. Not in Lee2010/Ortega2011, whose signed term makes $|\eta|$
  converge from both sides; it is a practice of motor-control firmware that guards
  against $|\eta|$ collapsing towards 0 (a point where the correction vanishes and the
  angle is undefined). Derived here (and tested): at speed a small offset $\tilde x$
  constant in the stationary frame decays on average at $\lambda/4$ instead of
  $\lambda/2$ (the radial projection acts on half of each turn). An offset never
  shrinks once $|\tilde x| \ge \psi_a$ ($d|\tilde x|^2/dt = q(|\eta|^2 +
  |\tilde x|^2 - \psi_a^2) \ge 0$ there), and every offset with $|\tilde x| \ge
  2\psi_a$ is at rest ($|\eta| \ge \psi_a$ at every rotor angle): from an estimate on
  the circle more than 60 deg off the term pushes the offset out towards $2\psi_a$ and
  the angle never locks (from 90 deg, tested). Drift outward is not corrected. The
  error dynamics are not differentiable at the equilibrium (the linearisation there is
  one-sided).
- `"adaptive"`: the PM flux is estimated from the same error,
  $\dot{\hat\psi}_f = -\kappa\,\psi_a(\psi_a^2 - |\eta|^2)$ ($\psi_a$ with
  $\hat\psi_f$), $\kappa = k_\psi/(2\psi_f^2)$ so that `k_psi` (1/s) is its linearised
  rate. With $p = \hat\psi_f - \psi_f$ the linearisation is
  $s^3 + (\lambda + k_\psi)s^2 + \omega^2 s + \omega^2 k_\psi$: Hurwitz for every
  $\lambda, k_\psi > 0$, $\omega \ne 0$ (the rotation makes the magnitude identifiable:
  a flux offset constant in the stationary frame cannot keep $|\eta|$ constant). One
  more error coordinate, `psi_f` (true minus estimate). `k_psi = 0` freezes
  $\hat\psi_f$ at the model's value. Default $k_\psi = \lambda/4$. The law is odd in
  $\psi_a$ and the flux term even, so every equilibrium has a mirror with $\psi_a \to
  -\psi_a$ of the same stability (the lock with $\hat\psi_f = -\psi_f$ is stable); for a
  surface-mount model $\hat\psi_f = 0$ is invariant, so from $\hat\psi_f > 0$ the
  mirrors are never reached.
- `"limited"`: a pure integrator with a magnitude limit (the limiting integrator of
  J. Hu, B. Wu, IEEE Trans. Power Electron. 13(5), 1998): no gradient term;
  after each step $\eta$ is scaled back onto the circle where $|\eta| > \psi_a$. It
  keeps $|\eta| \le \psi_a$; at speed an offset decays as the circle sweeps it, at
  standstill nothing corrects it. Its continuous error dynamics (`error_rhs`) are the
  projected ones (the outward radial rate of $\eta$ removed on the circle), not
  differentiable at the equilibrium. On a salient machine under load the limit circle
  is off by $(L_d - L_q)i_q\tilde\theta$ and nothing pulls $|\eta|$ back up: in a
  closed-loop run on `morawiec_ipm3k5` at 0.5 p.u. and half the rated torque it settled
  20 deg off (measured; the gradient variant 0.04 deg).

**Discretisation** (at $t_k$ with $i_k$ and the voltage held over $[t_{k-1}, t_k)$):
$\hat x_k = \hat x_{k-1} + T_s u - \tfrac12 T_sR_s(i_{k-1} + i_k) + c$: the voltage exact
for the zero-order hold, the resistive drop by the trapezoid; the gradient term by
forward Euler from $\eta_{k-1} = \hat x_{k-1} - L_q i_{k-1}$ (target from $i_{k-1}$ in
the frame $\hat\theta_{k-1}$), held constant in the frame turning at $\hat\omega_{k-1}$
over the interval (it points along $\eta$, which turns with the rotor):
$c = T_s\,\mathrm{sinc}(\hat\omega T_s/2)\,e^{(\hat\omega T_s/2)J}\,q\,\eta_{k-1}$,
$q = \max(\tfrac{\gamma}{2}(\psi_a^2 - |\eta_{k-1}|^2), -\tfrac{1}{2T_s})$ (the floor,
inactive near the target, keeps one step from shrinking $|\eta|$ by more than half:
forward Euler would overshoot once $|\eta|$ exceeds about $\psi_a/\sqrt{\lambda T_s}$);
$\hat\psi_f$ by forward Euler. The limit is applied to $\eta_k$ with the target at $t_k$.
The PLL as `QuadraturePLL`: $\hat\theta^- = \hat\theta_{k-1} + T_s\hat\omega_{k-1}$,
$\varepsilon_k$ from $\eta_k$ at $\hat\theta^-$, $\hat\theta_k = \hat\theta^- +
T_sk_p\varepsilon_k$, $\hat\omega_k = \hat\omega_{k-1} + T_sk_i\varepsilon_k$. A matched
observer at zero error stays there exactly at constant speed. At $k = 0$ the flux is
initialised at the initial angle, $\hat x_0 = L_q i_0 + \psi_a e^{\hat\theta_0J}[1, 0]$.

**Equilibria** (`fast_equilibria`): a scalar reduction (`"gradient"`, `"clamped"`).
With a matched surface-mount model they are the lock, the PLL's false lock at $\pi$ and,
below $|\omega| = \lambda/4$, four more where $\tfrac{\lambda}{4}\sin 2\tilde\theta =
\omega$ (unstable in the cases tested). The generic route misses some of these: its
inner problem is singular at $\tilde\theta = 0, \pi$, where the flux rows leave the
speed error free.

**Saturated machines** (`with_magnetic`): the map's apparent $L_d$, $L_q$, $\psi_f$ at
$i_{k-1}$ in the frame $\hat\theta_{k-1}$, where the gradient term is formed; with them
$\eta = \psi_s - L_q i$ is the map's active flux exactly in steady state (static error
0.014 deg at 0.8 p.u. load on `ipm3k5_sat`, 12 deg with the constant model;
`test_saturated_observers.py`). $\gamma$ and $\kappa$ follow the scheduled $\psi_f$;
for `"adaptive"` the estimate $\hat\psi_f$ replaces it in the target.

**Error coordinates** (true minus estimate): the stator-flux error in the PLL's frame,
the angle error, the speed error (and for `"adaptive"` the PM-flux error).

**Tuning** (`tunable`): `lam`, `w_pll`, `zeta_pll` within factors 1/5..5 of the
defaults (at 8 kHz on zhang750 `lam` T_s <= 0.16, `w_pll` T_s <= 0.2); `check_values`
refuses `lam` T_s >= 2 or $k_pT_s \ge 2$ (the forward-Euler stability limit of the
radial mode, $1 - \lambda T_s$ per step, and of the PLL's proportional path).
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._frames import cos_sin, jmul, park, rotate, wrap_angle
from .._plant._params import Drive, PMSMParams
from .._validate import check_positive, is_concrete
from ._base import (
    AbstractObserver,
    ErrorCoordinates,
    Estimate,
    Measurement,
    OperatingPoint,
    PlantPoint,
)
from ._flux_coordinates import (
    flux_error_scale,
    flux_errors,
    flux_estimates,
    previous_current_dq,
    true_flux_ab,
)


#: The variants (`NonlinearFluxObserver.variant`; the module docstring).
VARIANTS = ("gradient", "clamped", "adaptive", "limited")
#: Defaults (module docstring): lam and k_psi as fractions of the rated electrical speed
#: (flux poles critically damped at 0.1 p.u.; adaptation a quarter of lam), the PLL's
#: natural frequency (rad/s) and damping.
LAM_PU, K_PSI_PU, W_PLL, ZETA_PLL = 0.2, 0.05, 2.0 * math.pi * 50.0, 1.0

_NAMES = ("psi_d", "psi_q", "theta", "w")
_UNITS = ("V s", "V s", "rad", "rad/s")
_DOC = ("stator-flux error, PLL frame d axis (true minus estimate)",
        "stator-flux error, PLL frame q axis",
        "angle error theta - theta_hat (the PLL's angle)",
        "speed error w - w_hat (the PLL's speed)")
_COORDS = ErrorCoordinates(_NAMES, _UNITS, 2, _DOC)
_COORDS_ADAPTIVE = ErrorCoordinates(_NAMES + ("psi_f",), _UNITS + ("V s",), 2,
                                    _DOC + ("PM-flux error psi_f - psi_f_hat",))

_DESIGN_UNITS = {
    "lam": "1/s, linearised rate of |eta| to its target (gamma = lam / psi_f^2)",
    "w_pll": "rad/s, PLL natural frequency (k_i = w_pll^2)",
    "zeta_pll": "-, PLL damping (k_p = 2 zeta_pll w_pll)",
    "k_psi": "1/s, linearised rate of the PM-flux adaptation (variant 'adaptive' only; "
             "0 = frozen)",
}


class NonlinearFluxState(eqx.Module):
    """State of `NonlinearFluxObserver`.

    - `psi_ab`: estimated stator flux $\\hat x$, stationary frame (V s, (2,)).
    - `theta`: PLL angle, wrapped to (-pi, pi] (rad); `w`: PLL speed (rad/s).
    - `psi_f`: PM-flux estimate (V s; the model's value except for `"adaptive"`).
    - `i_prev`: current sampled at the previous instant (A, stationary frame).
    - `started`: False until the first sample has been seen.
    """

    psi_ab: jnp.ndarray
    theta: jnp.ndarray
    w: jnp.ndarray
    psi_f: jnp.ndarray
    i_prev: jnp.ndarray
    started: jnp.ndarray


class NonlinearFluxObserver(AbstractObserver):
    r"""Gradient flux observer of Lee2010/Ortega2011 with a PLL on the flux angle.

    See the module docstring for the equations, the variants and the discretisation.
    Returns the PLL's angle and speed; extras `psi_ab_hat` (V s), `eta_ab_hat` (V s),
    `theta_obs` (rad) and `psi_f_hat` (V s).

    **Arguments:**

    - `motor`: the observer's machine model (`PMSMParams`, `psi_f` > 0).
    - `lam` (1/s), `w_pll` (rad/s), `zeta_pll` (-), `k_psi` (1/s, >= 0): the design.
    - `variant`: `"gradient"` (default), `"clamped"`, `"adaptive"` or `"limited"`.
    """

    motor: PMSMParams
    lam: float
    w_pll: float
    zeta_pll: float = ZETA_PLL
    k_psi: float = 0.0
    variant: str = eqx.field(static=True, default="gradient")

    design_units: ClassVar[dict[str, str]] = _DESIGN_UNITS
    extras: ClassVar[dict[str, str]] = {
        "psi_ab_hat": "V s, estimated stator flux, stationary frame (2,)",
        "eta_ab_hat": "V s, estimated active (rotor) flux x - L_q i, stationary frame (2,)",
        "theta_obs": "rad, angle of eta_ab_hat (the observer's raw angle)",
        "psi_f_hat": "V s, PM-flux estimate (the model's value unless 'adaptive')",
    }
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "lam": (0.2, 5.0), "w_pll": (0.2, 5.0), "zeta_pll": (0.2, 5.0)}
    tunable_kinds: ClassVar[dict[str, str]] = {"lam": "estimator", "w_pll": "tracking",
                                               "zeta_pll": "damping"}
    paper_motor: ClassVar[str] = "zhang750"
    paper_T_s: ClassVar[float] = 125e-6
    c_emitter: ClassVar[str] = "_nonlinear_flux:emit"

    @property
    def coordinates(self) -> ErrorCoordinates:
        return _COORDS_ADAPTIVE if self.variant == "adaptive" else _COORDS

    def __check_init__(self):
        if not isinstance(self.motor, PMSMParams):
            raise ValueError(f"`NonlinearFluxObserver(motor=...)` must be a `PMSMParams`; "
                             f"got {type(self.motor).__name__}.")
        if self.variant not in VARIANTS:
            raise ValueError(f"`NonlinearFluxObserver(variant=...)` must be one of "
                             f"{', '.join(VARIANTS)}; got {self.variant!r}.")
        check_positive("NonlinearFluxObserver", "motor.psi_f", self.motor.psi_f, "V s")
        _check_design("NonlinearFluxObserver", self.design_parameters())

    # --- design -----------------------------------------------------------------------
    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None,
                   variant: str = "gradient", **design):
        """The default design for `drive` (module docstring): `lam` = 0.2 w_rated,
        `w_pll` = 2 pi 50 rad/s, `zeta_pll` = 1, `k_psi` = 0.05 w_rated (= lam / 4;
        used by `"adaptive"` only). `motor` replaces the observer's machine model,
        `variant` selects the variant, `design` overrides design parameters by name."""
        if not isinstance(drive, Drive):
            raise ValueError(f"`NonlinearFluxObserver.from_drive(drive=...)` must be a "
                             f"`Drive`; got {type(drive).__name__}.")
        motor = drive.three_phase_motor if motor is None else motor
        w_r = float(drive.w_rated)
        obs = cls(motor=motor, lam=LAM_PU * w_r, w_pll=W_PLL, zeta_pll=ZETA_PLL,
                  k_psi=K_PSI_PU * w_r, variant=variant)
        return obs.with_design(**design) if design else obs

    def with_design(self, **values):
        self._check_design_names(values)
        if not values:
            return self
        _check_design("NonlinearFluxObserver.with_design", values)
        return self._replace(**values)

    def gains(self):
        """`(gamma (1/(V^2 s^3)), k_p (rad/s), k_i (rad/s^2), kappa (1/(V^2 s)))`."""
        psi2 = self.motor.psi_f ** 2
        return (self.lam / psi2, 2.0 * self.zeta_pll * self.w_pll, self.w_pll ** 2,
                0.5 * self.k_psi / psi2)

    def check_values(self, T_s) -> None:
        super().check_values(T_s)
        if not is_concrete((T_s, self.lam, self.w_pll, self.zeta_pll)):
            return
        # forward Euler: the radial mode (1 - lam T_s per step at i_d = 0) and the PLL's
        # proportional path (1 - k_p T_s) within the step's stability limit
        for name, rate in (("lam", float(self.lam)),
                           ("w_pll", 2.0 * float(self.zeta_pll) * float(self.w_pll))):
            if not rate * float(T_s) < 2.0:
                raise ValueError(
                    f"`NonlinearFluxObserver({name}=...)`: "
                    f"{'lam' if name == 'lam' else '2 zeta_pll w_pll'} T_s must be below "
                    f"2 (forward Euler); got {rate!r} x {float(T_s)!r} s.")

    # --- the observer's right-hand side -----------------------------------------------
    def _target(self, psi_f, i_ab, theta):
        """Target magnitude $\\psi_f + (L_d - L_q)i_d$ (V s), $i_d$ of `i_ab` (A) in the
        frame at `theta` (rad)."""
        c, s = cos_sin(theta)
        i_d = i_ab[..., 0] * c + i_ab[..., 1] * s
        return psi_f + (self.motor.L_d - self.motor.L_q) * i_d

    def _psi_f(self, state_psi_f):
        """The PM flux the target is built on: the estimate for `"adaptive"`."""
        return state_psi_f if self.variant == "adaptive" else self.motor.psi_f

    def _radial(self, eta, ref):
        """`(q, g)`: the gradient term is `q * eta` (1/s), `g` = ref^2 - |eta|^2."""
        gamma = self.gains()[0]
        g = ref * ref - (eta[..., 0] ** 2 + eta[..., 1] ** 2)
        if self.variant == "limited":
            return jnp.zeros_like(g), g
        f = jnp.maximum(g, 0.0) if self.variant == "clamped" else g
        return 0.5 * gamma * f, g

    def _psi_f_rate(self, ref, g):
        """$d\\hat\\psi_f/dt$ (V): zero except for `"adaptive"`."""
        if self.variant != "adaptive":
            return jnp.zeros_like(g)
        return -self.gains()[3] * ref * g

    # --- running ----------------------------------------------------------------------
    def init(self, theta0=0.0, w0=0.0) -> NonlinearFluxState:
        theta0, w0 = jnp.asarray(theta0), jnp.asarray(w0)
        dtype = jnp.result_type(theta0, w0, float)
        zero2 = jnp.zeros(2, dtype)
        return NonlinearFluxState(psi_ab=zero2, theta=wrap_angle(theta0.astype(dtype)),
                                  w=w0.astype(dtype),
                                  psi_f=jnp.asarray(self.motor.psi_f, dtype),
                                  i_prev=zero2, started=jnp.asarray(False))

    # the step forms its correction at i_{k-1}: the scheduled model is the map's there
    _schedule_current = staticmethod(previous_current_dq)

    def step(self, state: NonlinearFluxState, meas: Measurement, T_s):
        self = self._scheduled(state, meas)  # noqa: PLW0642 (the current-scheduled model)
        m = self.motor
        dtype = state.psi_ab.dtype
        i_k = jnp.asarray(meas.i_ab).astype(dtype)
        u = jnp.asarray(meas.u_ab).astype(dtype)
        th, w, x, i0 = state.theta, state.w, state.psi_ab, state.i_prev
        _, k_p, k_i, _ = self.gains()
        # the gradient term from t_{k-1}, held in the frame turning at w over the period
        psi_f = self._psi_f(state.psi_f)
        ref0 = self._target(psi_f, i0, th)
        q, g = self._radial(x - m.L_q * i0, ref0)
        q = jnp.maximum(q, -0.5 / T_s)
        half = 0.5 * T_s * w
        corr = (T_s * jnp.sinc(half / jnp.pi) * q) * rotate(x - m.L_q * i0, half)
        x_new = x + T_s * u - (0.5 * T_s * m.R_s) * (i0 + i_k) + corr
        psi_f_new = state.psi_f + T_s * self._psi_f_rate(ref0, g)
        # the PLL's predicted angle, and the model's target at t_k in its frame
        th_p = th + T_s * w
        ref1 = self._target(m.psi_f, i_k, th_p)
        eta = x_new - m.L_q * i_k
        if self.variant == "limited":
            n = jnp.sqrt(eta[0] ** 2 + eta[1] ** 2)
            over = n > jnp.abs(ref1)
            eta = eta * jnp.where(over, jnp.abs(ref1) / jnp.where(over, n, 1.0), 1.0)
            x_new = m.L_q * i_k + eta
        eps = (jnp.cos(th_p) * eta[1] - jnp.sin(th_p) * eta[0]) / ref1
        th_new = wrap_angle(th_p + T_s * k_p * eps)
        w_new = w + T_s * k_i * eps
        # first sample: the flux at the initial angle, nothing else moves
        go = state.started
        ref_i = self._target(self._psi_f(state.psi_f), i_k, th)
        x0 = m.L_q * i_k + ref_i * jnp.stack([jnp.cos(th), jnp.sin(th)])
        x_new = jnp.where(go, x_new, x0).astype(dtype)
        th_new = jnp.where(go, th_new, th).astype(state.theta.dtype)
        w_new = jnp.where(go, w_new, w).astype(state.w.dtype)
        psi_f_new = jnp.where(go, psi_f_new, state.psi_f).astype(state.psi_f.dtype)
        eta = x_new - m.L_q * i_k
        new = NonlinearFluxState(psi_ab=x_new, theta=th_new, w=w_new, psi_f=psi_f_new,
                                 i_prev=i_k, started=jnp.ones_like(state.started))
        return new, Estimate(theta_hat=th_new, w_hat=w_new, extras={
            "psi_ab_hat": x_new, "eta_ab_hat": eta,
            "theta_obs": jnp.arctan2(eta[1], eta[0]), "psi_f_hat": psi_f_new})

    # --- analysis ---------------------------------------------------------------------
    def error_rhs(self, x, op: OperatingPoint, plant: PMSMParams):
        """The error dynamics at `op` with ideal current control ($i = e^{\\hat\\theta J}
        i_0$), in the PLL's frame (rotation invariant: it is taken at angle 0, the true
        rotor at the angle error)."""
        m = self.motor
        x = jnp.asarray(x)
        dtype = x.dtype
        w = jnp.asarray(op.w_m, dtype)
        i0 = jnp.asarray(op.i_dq, dtype)
        th = x[2]
        w_hat = w - x[3]
        psi_f = plant.psi_f - x[4] if self.variant == "adaptive" else m.psi_f
        psi_true = true_flux_ab(plant, th, i0)
        eta = psi_true - x[:2] - m.L_q * i0
        ref = self._target(psi_f, i0, jnp.zeros((), dtype))
        q, g = self._radial(eta, ref)
        _, k_p, k_i, _ = self.gains()
        eps = eta[1] / self._target(m.psi_f, i0, jnp.zeros((), dtype))
        dth_hat = w_hat + k_p * eps
        # stationary-frame rate of the flux error: (R_hat - R) i - correction
        de = (m.R_s - plant.R_s) * i0 - q * eta
        if self.variant == "limited":
            # the outward radial rate of eta removed on the circle (projected dynamics);
            # the plant's current is held in the estimated frame: di/dt = dth_hat J i
            i_dq = park(i0, th)
            di_dq = (dth_hat - w) * jmul(i_dq)
            dpsi = w * jmul(psi_true) + rotate(jnp.stack([plant.L_d * di_dq[0],
                                                          plant.L_q * di_dq[1]]), th)
            y = dpsi + (plant.R_s - m.R_s) * i0
            deta = y - m.L_q * dth_hat * jmul(i0)
            n = jnp.sqrt(eta[0] ** 2 + eta[1] ** 2)
            e_r = eta / n
            out = jnp.maximum(e_r[0] * deta[0] + e_r[1] * deta[1], 0.0)
            de = de + jnp.where(n >= jnp.abs(ref), out, 0.0) * e_r
        d_e = de - dth_hat * jmul(x[:2])
        rates = [d_e, jnp.stack([w - dth_hat, -k_i * eps])]
        if self.variant == "adaptive":
            rates.append(-self._psi_f_rate(ref, g)[None])
        return jnp.concatenate(rates)

    def fast_equilibria(self, plant: PMSMParams, op: OperatingPoint, n_grid=None):
        r"""The equilibria by a scalar reduction (every variant but `"limited"`, whose
        projected dynamics take the generic route). At an equilibrium the PLL rests:
        $\varepsilon = 0$, $\hat\omega = \omega$, so $\eta = [h, 0]$ in the PLL frame.
        With $P(\tilde\theta) = \psi(\tilde\theta) - \hat L_q i_0$ (the true stator
        flux in that frame less the model's $L_q$ term), $e = P - \eta$ and
        $\Delta R = \hat R_s - R_s$, the flux rows $-\omega Je + \Delta R\,i_0 - q\eta = 0$
        give $e_d = \Delta R\,i_{0q}/\omega$, so $h = P_d - \Delta R\,i_{0q}/\omega$, and
        leave one scalar equation
        $r(\tilde\theta) = \omega P_q + \Delta R\,i_{0d} - q(h)\,h = 0$. `"adaptive"`:
        its PM-flux row $\psi_a g = 0$ splits it into $g = 0$ ($q = 0$, $\psi_a = \pm h$:
        two equilibria per zero) and $\psi_a = 0$. Zeros are bracketed on a grid of
        `n_grid` angles (default 256, offset by half a step) and bisected; stability from
        the Jacobian of `error_rhs` (Routh-Hurwitz; one-sided for `"clamped"`). For a
        matched surface-mount model $r = \psi_f\sin\tilde\theta\,(\omega -
        \tfrac{\lambda}{4}\sin 2\tilde\theta)$: the designed lock, the PLL's false lock
        at $\pi$, and for $|\omega| < \lambda/4$ four more (`test_nonlinear_flux.py`)."""
        if self.variant == "limited":
            return None
        import jax

        from ..analysis._equilibria import Equilibria, _bisect, _tol
        from ..analysis._linearize import charpoly, routh_hurwitz

        n_grid, R = (256 if n_grid is None else int(n_grid)), 8
        m = self.motor
        dtype = jnp.result_type(op.w_m, float)
        w = jnp.asarray(op.w_m, dtype)
        i0 = jnp.asarray(op.i_dq, dtype)
        w_s = jnp.where(w != 0, w, 1.0)
        dR = m.R_s - plant.R_s
        dL_i = (m.L_d - m.L_q) * i0[0]
        ref = self._target(m.psi_f, i0, jnp.zeros((), dtype))
        norm = jnp.abs(w_s) * ref

        def flux(t):  # (e_d, e_q, h)
            P = true_flux_ab(plant, t, i0) - m.L_q * i0
            return dR * i0[1] / w_s, P[1], P[0] - dR * i0[1] / w_s

        def r_fixed(t):
            _, e_q, h = flux(t)
            q, _ = self._radial(jnp.stack([h, jnp.zeros_like(h)]), ref)
            return (w_s * e_q + dR * i0[0] - q * h) / norm

        def r_g0(t):
            return (w_s * flux(t)[1] + dR * i0[0]) / norm

        def r_ref0(t):
            h = flux(t)[2]
            return r_g0(t) + 0.5 * self.gains()[0] * h ** 3 / norm

        step = 2 * jnp.pi / n_grid
        grid = -jnp.pi + step * (jnp.arange(n_grid, dtype=dtype) + 0.5)

        def zeros(r):
            rv = jax.vmap(r)(grid)
            change = rv * jnp.roll(rv, -1) <= 0
            (k,) = jnp.nonzero(change, size=R, fill_value=0)
            valid = jnp.arange(R) < jnp.sum(change)
            th, conv = _bisect(r, grid[k], grid[k] + step, valid, _tol(dtype))
            return wrap_angle(th), valid & conv, jnp.sum(change) > R

        def state(t, psi_a):
            e_d, e_q, _ = flux(t)
            x = [e_d, e_q, t, jnp.zeros_like(t)]
            if self.variant == "adaptive":  # psi_a = psi_f_hat + (L_d - L_q) i_0d
                x.append(plant.psi_f - (psi_a - dL_i))
            return jnp.stack(x)

        if self.variant == "adaptive":
            (tA, okA, overA), (tB, okB, overB) = zeros(r_g0), zeros(r_ref0)
            hA = jax.vmap(lambda t: flux(t)[2])(tA)
            th = jnp.concatenate([tA, tA, tB])
            valid = jnp.concatenate([okA, okA & (hA != 0), okB])
            xs = jax.vmap(state)(th, jnp.concatenate([hA, -hA, jnp.zeros_like(tB)]))
            over = overA | overB
        else:
            th, valid, over = zeros(r_fixed)
            xs = jax.vmap(lambda t: state(t, ref))(th)
        op0 = OperatingPoint(w, i0)
        scale = self.error_scale(op0, plant)
        rhs = lambda v: self.error_rhs(v, op0, plant)  # noqa: E731
        rate = jnp.abs(w_s)
        res = jax.vmap(lambda v: jnp.max(jnp.abs(rhs(v) / (scale * rate))))(xs)
        ok = valid & (res < 1e3 * float(jnp.finfo(dtype).eps) ** 0.6)
        A = jax.vmap(jax.jacfwd(rhs))(xs)
        stable = ok & routh_hurwitz(charpoly(A / rate))
        order = jnp.argsort(jnp.where(ok, th, jnp.inf))
        th, xs, ok, stable, res, A = (a[order] for a in (th, xs, ok, stable, res, A))
        n = jnp.sum(ok)
        nan = jnp.nan
        status = jnp.where((w == 0) | over, -1, jnp.where(n == 0, 2, 0))
        return Equilibria(
            theta=jnp.where(ok, th, nan), x=jnp.where(ok[:, None], xs, nan), valid=ok,
            stable=stable, tangent=jnp.zeros_like(ok), residual=jnp.where(ok, res, nan),
            principal=jnp.argmin(jnp.where(ok, jnp.abs(th), jnp.inf)).astype(jnp.int32),
            n=n.astype(jnp.int32), status=status.astype(jnp.int32),
            jacobian=jnp.where(ok[:, None, None], A, nan))

    def error_scale(self, op: OperatingPoint, plant: PMSMParams):
        del plant
        m = self.motor
        i_dq = jnp.asarray(op.i_dq)
        pa = jnp.sqrt(m.extended_flux(i_dq[..., 0]) ** 2 + (m.L_q * i_dq[..., 1]) ** 2)
        scale = flux_error_scale(pa, op.w_m)
        if self.variant == "adaptive":
            scale = jnp.concatenate([scale, scale[:1]])
        return scale

    def error_state(self, state: NonlinearFluxState, truth: PlantPoint, plant: PMSMParams):
        x = flux_errors(state.psi_ab, state.theta, state.w, truth, plant)
        if self.variant == "adaptive":
            x = jnp.concatenate([x, jnp.stack([plant.psi_f - state.psi_f])])
        return x

    def observer_state(self, x, truth: PlantPoint, plant: PMSMParams) -> NonlinearFluxState:
        psi, theta, w = flux_estimates(x, truth, plant)
        psi_f = plant.psi_f - x[4] if self.variant == "adaptive" else self.motor.psi_f
        return NonlinearFluxState(psi_ab=psi, theta=theta, w=w,
                                  psi_f=jnp.asarray(psi_f, psi.dtype),
                                  i_prev=jnp.asarray(truth.i_ab, psi.dtype),
                                  started=jnp.asarray(True))


def _check_design(owner: str, values: dict) -> None:
    for k, v in values.items():
        check_positive(owner, k, v, _DESIGN_UNITS[k].split(",")[0],
                       allow_zero=(k == "k_psi"))
