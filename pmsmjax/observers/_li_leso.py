r"""Back-EMF linear extended-state observers of li-fa-leso: C-LESO, GI-LESO and FA-LESO.

Reference: Y. Li, Y. Hu, X. Ma, L. Liu, "Sensorless Control of Dual Three-Phase IPMSM
Based on Frequency Adaptive Linear Extended State Observer" (li-fa-leso).

**Model.** The equivalent back-EMF model li-fa-leso (4)-(6) in the stationary frame (for a
dual three-phase machine: its alpha-beta subspace),
$L_q\,di_{ab}/dt = u_{ab} - R_s i_{ab} - e_{ab}$, $e_{ab} = \omega[\psi_f + (L_d - L_q)
i_d][-\sin\theta, \cos\theta]^T$, with $x_1 = i_{ab}$, $x_2 = -e_{ab}/L_q$ (7)-(8). The
LESO with gain functions $l_1(t)$, $l_2(t)$ (9) estimates $\hat e_{ab} = -\hat L_q\hat x_2$
(10); its transfer function is li-fa-leso (14),
$\hat e/e = L_2(s)/(s^2 + (\mu + L_1(s))s + L_2(s))$. Each observer here is that LESO in
the form of `AbstractBackEMFLESO` (`_back_emf_leso`: the exact discretisation, the
steady state and the error coordinates), $\dot s = A_s s + B_s\varepsilon_1$,
$\hat x_2 = C_s s + D_x\varepsilon_1$, with:

- C-LESO (15)-(17): $l_1 = 2\omega_0 - \mu$, $l_2 = \omega_0^2$: $s = \hat x_2$,
  $\dot{\hat x}_2 = -\omega_0^2\varepsilon_1$, $D_1 = -2\omega_0$.
- GI-LESO (29)-(30): $L_2(s) = \omega_0^2 + G(s)$, $G(s) = 2K_r\omega_c s/(s^2 +
  2\omega_c s + \omega_r^2)$: $s = (\hat x_2, r, q)$ with $\dot r = q$, $\dot q = \varepsilon_1 -
  \omega_r^2 r - 2\omega_c q$, $\dot{\hat x}_2 = -\omega_0^2\varepsilon_1 - 2K_r\omega_c q$;
  $\omega_r$ is the estimated speed (`resonance="estimated"`, the default) or fixed
  (`"fixed"`, Table II's $\hat\omega_e = 100\pi$ on `li_dtp`).
- FA-LESO (25)-(28): $L_1 = -j\hat\omega - \mu$, $L_2 = k_1 + k_2 s$: $s = z$ with
  $\hat x_2 = -k_2\varepsilon_1 - z$, $\dot z = k_1\varepsilon_1$, $D_1 = \hat\omega J$.

A `QuadraturePLL` (`_pll.py`) turns $\hat e_{ab}$ into $\hat\theta$, $\hat\omega$; the
FA-LESO (and the GI-LESO with `resonance="estimated"`) adapt to that $\hat\omega$.

**Lock, low speed, reversals** (measured, not from the paper; docs "Lock acquisition,
start-up and reversals"): with the PLL's acquisition assist all three lock from any
initial angle and speed estimate (zero and the wrong sign included) on a turning rotor,
within 0.1 s on `li_dtp` at 0.5 p.u. (`analysis.lock_basin`); they keep the lock down to
0.01 p.u. on zhang750 (matched model, ideal sensing); below the PLL's `w_min`
(0.05 p.u.) its loop gain fades. They reverse through zero speed in the closed loop at
about 1700 rad/s^2 (zhang750, 0.5 p.u.); the GI-LESO not at 2500 rad/s^2. At
standstill they cannot see the angle: a drive starts them with `pmsmjax.IfStartup`.
"""

from __future__ import annotations

import functools
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._plant._params import Drive, PMSMParams
from .._validate import check_positive
from ._back_emf_leso import AbstractBackEMFLESO, _real, blk
from ._base import ErrorCoordinates, OperatingPoint
from ._matrix_functions import ACTION_NORMS, phi2_action, phi_matrix, switched, taylor_degree
from ._pll import PLL_UNITS, QuadraturePLL


#: Table II of li-fa-leso is given for `li_dtp`, whose rated electrical speed is 100 pi
#: rad/s; `from_drive` scales every rate by w_rated / (100 pi) on other machines.
_W_REF = 100.0 * math.pi


def _coords(s_names, s_units, s_doc):
    return ErrorCoordinates(
        names=("eps_d", "eps_q", *s_names, "theta", "w"),
        units=("A", "A", *s_units, "rad", "rad/s"), angle=2 + len(s_names),
        doc=("current-estimate error x1_hat - i, rotor frame d axis, minus its designed "
             "steady state", "the same, q axis", *s_doc,
             "angle error theta - theta_hat", "speed error w - w_hat (PLL speed)"))


def _check_motor(owner, motor):
    if not isinstance(motor, PMSMParams):
        raise ValueError(f"`{owner}(motor=...)` must be a `PMSMParams` (the observer's "
                         f"machine model, alpha-beta subspace); got {type(motor).__name__}.")


def _check_pll(owner, pll):
    if not isinstance(pll, QuadraturePLL):
        raise ValueError(f"`{owner}(pll=...)` must be a `QuadraturePLL`; got "
                         f"{type(pll).__name__}.")


def _scale(drive: Drive) -> float:
    return float(drive.w_rated) / _W_REF


class CLESOObserver(AbstractBackEMFLESO):
    r"""Conventional LESO, li-fa-leso (9), (15)-(17), with a quadrature PLL.

    $l_1 = 2\omega_0 - \mu$, $l_2 = \omega_0^2$ (16): $\hat e/e = \omega_0^2/(s^2 +
    2\omega_0 s + \omega_0^2)$ (17), a low-pass whose phase lag
    $2\arctan(\omega/\omega_0)$ becomes the steady-state angle error.

    **Arguments:**

    - `motor`: the observer's machine model (`PMSMParams`; uses $R_s$, $L_q$, and $L_d$,
      $\psi_f$ in the PLL's normalisation).
    - `w0`: observer bandwidth $\omega_0$ (rad/s), > 0.
    - `pll`: `QuadraturePLL`.
    """

    paper_motor: ClassVar[str | None] = "li_dtp"
    paper_T_s: ClassVar[float | None] = 1e-4
    c_emitter: ClassVar[str | None] = "_li:emit"
    motor: PMSMParams
    w0: float
    pll: QuadraturePLL

    coordinates: ClassVar[ErrorCoordinates] = _coords(
        ("x2_d", "x2_q"), ("A/s", "A/s"),
        ("extended state x2_hat (= -e_hat/L_q) minus its steady state, rotor frame d",
         "the same, q"))
    design_units: ClassVar[dict[str, str]] = {
        "w0": "rad/s, C-LESO bandwidth li-fa-leso (16)", **PLL_UNITS}
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "w0": (0.3, 3.0), "w_pll": (0.25, 4.0), "zeta_pll": (0.5, 2.0)}

    def __init__(self, motor: PMSMParams, w0, pll: QuadraturePLL, *, magnetic=None):
        _check_motor("CLESOObserver", motor)
        _check_pll("CLESOObserver", pll)
        self.motor, self.w0, self.pll, self.magnetic = motor, w0, pll, magnetic

    def __check_init__(self):
        check_positive("CLESOObserver", "w0", self.w0, "rad/s")

    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None, **design):
        """Table II of li-fa-leso on `li_dtp` ($\\omega_0 = 500\\pi$), scaled by
        `w_rated / (100 pi)` elsewhere; PLL `QuadraturePLL.for_speed(w_rated)`."""
        motor = drive.three_phase_motor if motor is None else motor
        obs = cls(motor, 500.0 * math.pi * _scale(drive),
                  QuadraturePLL.for_speed(float(drive.w_rated)))
        return obs.with_design(**design) if design else obs

    def _own_design(self):
        return {"w0": self.w0}

    def _matrices(self, w_hat):
        w0 = jnp.asarray(self.w0) + 0.0 * w_hat
        z = 0.0 * w0
        return (blk(z), blk(-w0 ** 2), blk(1.0 + z), blk(z), blk(-2.0 * w0))

    def _complex_system(self, w_hat):
        w0 = jnp.asarray(self.w0, jnp.result_type(w_hat, float))
        k, b = -2.0 * w0, -w0 ** 2
        return ((k, 1.0), (b, 0.0)), (-k, -b), 1.0, 0.0


class GILESOObserver(AbstractBackEMFLESO):
    r"""LESO with a generalised integrator, li-fa-leso (29)-(30), with a quadrature PLL.

    $L_1 = 2\omega_0 - \mu$, $L_2(s) = \omega_0^2 + G(s)$,
    $G(s) = 2K_r\omega_c s/(s^2 + 2\omega_c s + \omega_r^2)$ (30): $\hat e/e =
    (G + \omega_0^2)/(s^2 + 2\omega_0 s + G + \omega_0^2)$ (29), order 4 per axis.
    At $s = j\omega_r$ the integrator's gain is $K_r$, finite: (37)'s
    "$|G(j\hat\omega_e)| \to \infty$" does not hold, and with Table II's
    $K_r = 2\omega_0^2$ the GI-LESO keeps a lag $\arg(3\omega_0^2/(3\omega_0^2 - \omega^2 +
    2j\omega_0\omega))$ at its resonance.

    **Arguments:**

    - `motor`, `pll`: as `CLESOObserver`.
    - `w0`: bandwidth $\omega_0$ (rad/s); `K_r`: integrator gain (rad^2/s^2);
      `w_c`: its attenuation coefficient $\omega_c$ (rad/s); all > 0.
    - `w_r`: fixed resonant frequency (rad/s, used when `resonance="fixed"`), > 0.
    - `resonance`: `"estimated"` ($\omega_r = |\hat\omega|$, the PLL's speed; default)
      or `"fixed"` ($\omega_r$ = `w_r`). The resonance is floored at $\omega_c$ so that
      the integrator stays a damped band-pass at standstill.
    """

    paper_motor: ClassVar[str | None] = "li_dtp"
    paper_T_s: ClassVar[float | None] = 1e-4
    c_emitter: ClassVar[str | None] = "_li:emit"
    motor: PMSMParams
    w0: float
    K_r: float
    w_c: float
    w_r: float
    pll: QuadraturePLL
    resonance: str = eqx.field(static=True)

    n_s: ClassVar[int] = 6
    coordinates: ClassVar[ErrorCoordinates] = _coords(
        ("x2_d", "x2_q", "r_d", "r_q", "q_d", "q_q"),
        ("A/s", "A/s", "A s^2", "A s^2", "A s", "A s"),
        ("extended state x2_hat minus its steady state, rotor frame d", "the same, q",
         "generalised-integrator state r (dr/dt = q) minus steady state, d", "same, q",
         "generalised-integrator state q minus steady state, d", "same, q"))
    design_units: ClassVar[dict[str, str]] = {
        "w0": "rad/s, LESO bandwidth li-fa-leso (16), (29)",
        "K_r": "rad^2/s^2, generalised-integrator gain li-fa-leso (30)",
        "w_c": "rad/s, generalised-integrator attenuation coefficient li-fa-leso (30)",
        "w_r": "rad/s, fixed resonant frequency (resonance='fixed'; Table II 100 pi)",
        **PLL_UNITS}
    #: K_r alone sets the lag at resonance and w_c, with K_r, the two slow real modes
    #: that follow a start or a speed change (about -9 and -10 1/s with Table II's at
    #: 0.5 p.u.; docs/tuning.md, "The li observers under load steps"): both are tuned,
    #: in the contract's box around Table II's values
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "w0": (0.3, 3.0), "K_r": (0.5, 8.0), "w_c": (0.5, 16.0), "w_pll": (0.25, 4.0),
        "zeta_pll": (0.5, 2.0)}

    def __init__(self, motor: PMSMParams, w0, K_r, w_c, w_r, pll: QuadraturePLL,
                 resonance: str = "estimated", *, magnetic=None):
        _check_motor("GILESOObserver", motor)
        _check_pll("GILESOObserver", pll)
        if resonance not in ("estimated", "fixed"):
            raise ValueError(f"`GILESOObserver(resonance=...)` must be 'estimated' or "
                             f"'fixed'; got {resonance!r}.")
        self.motor, self.w0, self.K_r, self.w_c, self.w_r = motor, w0, K_r, w_c, w_r
        self.magnetic = magnetic
        self.pll, self.resonance = pll, resonance

    def __check_init__(self):
        for k, u in (("w0", "rad/s"), ("K_r", "rad^2/s^2"), ("w_c", "rad/s"),
                     ("w_r", "rad/s")):
            check_positive("GILESOObserver", k, getattr(self, k), u)

    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None,
                   resonance: str = "estimated", **design):
        """Table II on `li_dtp`: $\\omega_0 = 500\\pi$, $K_r = 2\\omega_0^2$,
        $\\omega_c = \\pi$, $\\omega_r = 100\\pi$ (used with `resonance="fixed"`); every
        rate scaled by `w_rated / (100 pi)` on other machines."""
        motor = drive.three_phase_motor if motor is None else motor
        a = _scale(drive)
        w0 = 500.0 * math.pi * a
        obs = cls(motor, w0, 2.0 * w0 ** 2, math.pi * a, 100.0 * math.pi * a,
                  QuadraturePLL.for_speed(float(drive.w_rated)), resonance=resonance)
        return obs.with_design(**design) if design else obs

    def _own_design(self):
        return {"w0": self.w0, "K_r": self.K_r, "w_c": self.w_c, "w_r": self.w_r}

    def fast_equilibria(self, plant: PMSMParams, op: OperatingPoint, n_grid=None):
        r"""With the resonance at the estimated speed (`resonance="estimated"`): the
        equilibria located on this observer's twin with the resonance fixed at
        $\max(|\omega|, \omega_c)$, their stability from this observer's own Jacobian.
        None with a fixed resonance (the generic route).

        Why the twin has the same equilibria: at an equilibrium the PLL's integrator is at
        rest and the estimated frame turns at the true speed, so $\hat\omega = \omega$,
        and the resonance $\max(|\hat\omega|, \omega_c)$ takes the twin's value there;
        every other equation is the same. The Jacobians differ in the speed-error column
        (the resonance moves with $\hat\omega$), so stability is read from this
        observer's. Why not the generic route directly: its inner least-squares solve at
        fixed angle errors away from the equilibria oscillates for this observer (the
        resonator's gain $K_r$ makes the residual strongly curved in the speed error:
        undamped Gauss-Newton steps then never settle, and every point was reported
        degenerate), while on the twin it converges as for the C-LESO. `n_grid`: the
        generic route's grid (None: its default)."""
        if self.resonance != "estimated":
            return None
        return _gi_twin_equilibria(self, plant, op, n_grid)


    def _matrices(self, w_hat):
        w0 = jnp.asarray(self.w0) + 0.0 * w_hat
        z = 0.0 * w0
        wr = (jnp.abs(w_hat) if self.resonance == "estimated"
              else jnp.asarray(self.w_r) + z)
        wr2 = jnp.maximum(wr ** 2, jnp.asarray(self.w_c) ** 2)
        O, I2 = blk(z), blk(1.0 + z)
        A = jnp.block([[O, O, blk(-2.0 * self.K_r * self.w_c + z)],
                       [O, O, I2],
                       [O, blk(-wr2), blk(-2.0 * self.w_c + z)]])
        B = jnp.concatenate([blk(-w0 ** 2), O, I2], 0)
        C = jnp.concatenate([I2, O, O], 1)
        return A, B, C, O, blk(-2.0 * w0)

    def _complex_system(self, w_hat):
        # constant patterns times the coefficients (one elementwise expression, no
        # assembly); rows and columns [x1, x2_hat, r, q]
        dt = jnp.result_type(w_hat, float)
        w0 = jnp.asarray(self.w0, dt)
        wr = (jnp.abs(w_hat) if self.resonance == "estimated" else jnp.asarray(self.w_r, dt))
        wr2 = jnp.maximum(wr ** 2, jnp.asarray(self.w_c, dt) ** 2)
        P = _GI_PATTERNS.astype(dt)
        Ao = (P[0] - 2.0 * w0 * P[1] - w0 ** 2 * P[2] - (2.0 * self.K_r * self.w_c) * P[3]
              - wr2 * P[4] - (2.0 * self.w_c) * P[5])
        g_i = 2.0 * w0 * P[1, :, 0] + w0 ** 2 * P[2, :, 0] - P[0, :, 0]
        return Ao, g_i, (1.0, 0.0, 0.0), 0.0

    def _complex_scale(self, w_hat):
        r"""$[1, \omega_0, d_q/\omega_r, d_q]$, $d_q = \sqrt{\omega_0/(2K_r\omega_c)}$:
        scales the cycles $x_1 \leftrightarrow \hat x_2$ ($\omega_0T_s$ each way),
        $r \leftrightarrow q$ ($\omega_rT_s$) and $x_1 \to q \to \hat x_2$ to equal
        entries, so the row-sum norm is about $3\omega_0T_s$ (0.47 at 100 us on
        `li_dtp`)."""
        w0 = jnp.asarray(self.w0) + 0.0 * w_hat
        wr = (jnp.abs(w_hat) if self.resonance == "estimated"
              else jnp.asarray(self.w_r) + 0.0 * w0)
        wr = jnp.sqrt(jnp.maximum(wr ** 2, jnp.asarray(self.w_c) ** 2))
        dq = jnp.sqrt(w0 / (2.0 * self.K_r * self.w_c))
        return jnp.stack([jnp.ones_like(w0), w0, dq / wr, dq])

    def _entries(self, w_hat, T):
        r"""The non-zero entries of $A_oT_s$ (`_complex_system`, rows and columns
        $[x_1, \hat x_2, r, q]$), as `(a00, a10, a13, a32, a33, T, theta)`:
        $a_{00} = -2\omega_0T_s$, $a_{10} = -\omega_0^2T_s$, $a_{13} = -2K_r\omega_cT_s$,
        $a_{32} = -\omega_r^2T_s$, $a_{33} = -2\omega_cT_s$, the three ones times $T_s$
        ($a_{01} = a_{23} = a_{30} = T_s$), and $\theta = \hat\omega T_s$."""
        w_hat = jnp.asarray(w_hat, T.dtype)
        w0, K_r, w_c = (jnp.asarray(v, T.dtype) for v in (self.w0, self.K_r, self.w_c))
        wr = jnp.abs(w_hat) if self.resonance == "estimated" else jnp.asarray(self.w_r, T.dtype)
        wr2 = jnp.maximum(wr ** 2, w_c ** 2)
        return (-2.0 * w0 * T, -(w0 * w0) * T, -(2.0 * K_r * w_c) * T, -wr2 * T,
                -(2.0 * w_c) * T, T, w_hat * T)

    def _norm_bound(self, k):
        r"""The row-sum norm of $X = A_oT_s - j\theta I$ in the units `_complex_scale`
        (entries $|X_{ik}|d_k/d_i$), written out from the entries `k` (`_entries`): rows
        $x_1$: $|a_{00} - j\theta| + \omega_0T_s$; $\hat x_2$: $\omega_0T_s + |\theta| +
        \kappa$; $r$: $|\theta| + \omega_rT_s$; $q$: $\kappa + \omega_rT_s + |a_{33} -
        j\theta|$, with $\kappa = T_s\sqrt{2K_r\omega_c/\omega_0}$ (the cycle
        $x_1 \to q \to \hat x_2 \to x_1$ in equal parts); held constant."""
        a00, a10, a13, a32, a33, T, th = jax.lax.stop_gradient(k)
        w0T, wrT = -0.5 * a00, jnp.sqrt(-a32 * T)
        kap = T * jnp.sqrt(2.0 * a13 / a00)
        ath = jnp.abs(th)
        return jnp.maximum(
            jnp.maximum(jnp.sqrt(a00 * a00 + th * th) + w0T, w0T + ath + kap),
            jnp.maximum(ath + wrT, kap + wrT + jnp.sqrt(a33 * a33 + th * th)))

    def _transition_c(self, w_hat, T_s, y, i0, dl, c, rot=None):
        r"""`AbstractBackEMFLESO._transition_c` from the structure of li-fa-leso
        (29)-(30)'s $A_o$: the complex state `y` = $[x_1, \hat x_2, r, q]$ one period on,
        $e^{j\theta}[e^Xy + \varphi_1(X)g_0 + \varphi_2(X)g_1]$ with $X = A_oT_s -
        j\theta I$, $\theta = \hat\omega T_s$, $g_0 = T_s(g_ii_0 + g_cc)$,
        $g_1 = T_s^2g_i\delta$.

        **One action.** The series $e^X = I + X + X^2\varphi_2(X)$ and $\varphi_1(X) = I +
        X\varphi_2(X)$ turn the bracket into
        $$e^Xy + \varphi_1(X)g_0 + \varphi_2(X)g_1 = y + u + \varphi_2(X)v,\qquad
        u = Xy + g_0,\quad v = Xu + g_1,$$
        one function of $X$ applied to one vector (three before; exact, the same power
        series regrouped). **Sparse, real $A_o$.** Of its 16 entries eight are non-zero
        and all real (`_entries`: the resonator's $r \leftrightarrow q$ rotation, the
        plant's $x_1 \leftrightarrow \hat x_2$ pair, coupled by $q \to \hat x_2$ and
        $x_1 \to q$), so $Xt = A_oT_st - j\theta t$ costs eight real-by-complex products
        and the shift, on the real and imaginary parts apart (`_gi_matvec`).
        $\varphi_2(X)v$ is its Taylor series by Horner's rule (`phi2_action`) of the
        degree that puts the truncation below the unit round-off at the branch's bound on
        the row-sum norm $\rho$ of $X$ in the observer's units (`_norm_bound`,
        $\approx 3\omega_0T_s$: 0.47 on `li_dtp` at 100 us, 2.4 on `zhang750` at 125 us):
        degree 12 for $\rho \le 0.5$, 24 for $\rho \le 3$ (float32: 6, 14); beyond, the
        balanced matrix function (`phi_matrix`). **No closed form in blocks:** the
        resonator and the plant pair feed each other ($q \to \hat x_2$ with
        $2K_r\omega_c$, $x_1 \to q$), so $A_o$ is not block-triangular; its
        characteristic polynomial is (29)'s denominator $(s + \omega_0)^2(s^2 +
        2\omega_cs + \omega_r^2) + 2K_r\omega_cs$, whose double root at $-\omega_0$ the
        coupling splits only slightly (an eigen-decomposition would divide by that gap).

        The same numbers to round-off as the three matrix functions of the complex
        $4\times4$ $X$ (tests against `expm` of the real augmented system). `y` may be
        given in the real layout (`step` does); the result is returned in it."""
        dt = jnp.real(i0).dtype
        T = jnp.asarray(T_s, dt)
        k = self._entries(w_hat, T)
        w0, inv_lq = jnp.asarray(self.w0, dt), 1.0 / self.motor.L_q
        z = jnp.zeros_like(T)
        # g_i = [2 w0, w0^2, 0, -1] (`_complex_system`), g_c = [1/L_q, 0, 0, 0]; all
        # vectors in the real layout [Re x1, Im x1, Re x2_hat, ..., Im q] (`_real`)
        g00 = T * (2.0 * w0 * i0 + inv_lq * c)
        g0 = jnp.stack([jnp.real(g00), jnp.imag(g00), (T * w0 * w0) * jnp.real(i0),
                        (T * w0 * w0) * jnp.imag(i0), z, z, -T * jnp.real(i0),
                        -T * jnp.imag(i0)])
        g1 = jnp.stack([f * p(dl) for f in (2.0 * w0 * T * T, w0 * w0 * T * T, z, -T * T)
                        for p in (jnp.real, jnp.imag)])
        yr = _real(y) if jnp.iscomplexobj(y) else y
        u = _gi_matvec(k, yr) + g0
        v = _gi_matvec(k, u) + g1
        w = yr + u + _gi_phi2(jnp.dtype(dt).name)(k, v, self._norm_bound(k))
        rot = jnp.exp(jax.lax.complex(z, k[6])) if rot is None else rot
        cr, ci, wr, wi = jnp.real(rot), jnp.imag(rot), w[0::2], w[1::2]
        return jnp.stack([cr * wr - ci * wi, cr * wi + ci * wr], -1).reshape(-1)


def _unit(i, j, n=4):
    return np.eye(n)[i][:, None] * np.eye(n)[j][None, :]


#: The GI-LESO's complex observer matrix as constant patterns (`_complex_system`): the
#: ones, then the entries of -2 w0, -w0^2, -2 K_r w_c, -w_r^2, -2 w_c.
_GI_PATTERNS = np.stack([_unit(0, 1) + _unit(2, 3) + _unit(3, 0), _unit(0, 0), _unit(1, 0),
                         _unit(1, 3), _unit(3, 2), _unit(3, 3)])


def _gi_matvec(k, t):
    r"""$Xt = A_oT_st - j\theta t$ for the GI-LESO's entries `k` (`_entries`), `t` in the
    real layout $[\mathrm{Re}\,x_1, \mathrm{Im}\,x_1, \mathrm{Re}\,\hat x_2, \dots,
    \mathrm{Im}\,q]$ (one array: one kernel a product, under `vmap` as well)."""
    a00, a10, a13, a32, a33, T, th = k

    def A(v):
        return (a00 * v[0] + T * v[1], a10 * v[0] + a13 * v[3], T * v[3],
                T * v[0] + a32 * v[2] + a33 * v[3])

    re, im = [t[2 * j] for j in range(4)], [t[2 * j + 1] for j in range(4)]
    ar, ai = A(re), A(im)
    return jnp.stack([e for j in range(4) for e in (ar[j] + th * im[j], ai[j] - th * re[j])])


def _gi_dense(k):
    """The complex $4\\times4$ $X$ of the entries `k` (`_entries`)."""
    a00, a10, a13, a32, a33, T, th = k
    z = jnp.zeros_like(T)
    A = jnp.stack([jnp.stack(r) for r in ((a00, T, z, z), (a10, z, z, a13), (z, z, z, T),
                                          (T, z, a32, a33))])
    return jax.lax.complex(A, -th * jnp.eye(4, dtype=A.dtype))


#: The GI-LESO's Taylor loop runs a batch in chunks whose state (8 components) holds at
#: most this many bytes: a degree reads and writes about five times the state, and
#: pmsmjax's loop setting (`runtime`'s `FAST_LOOP_FLAGS`) compiles a loop whose body
#: accesses under 64 KiB as one kernel; above, every degree runs kernel by kernel (about
#: a third slower at batch 256 in float64).
_GI_CHUNK_BYTES = 8192


def _gi_taylor(k, v, order: int):
    r"""$\varphi_2(X)v$ by `phi2_action` on `_gi_matvec` of degree `order`, `v` (the real
    layout) with an optional batch axis first (`switched`'s `native`; the entries `k`
    batched alike or scalars): inside, the components first, each product a vector
    operation over the batch per component; a batch over `_GI_CHUNK_BYTES` in chunks
    (`lax.map`, the last padded with zeros). Two degrees a pass: replay on `li_dtp`
    (float64, EPYC) 2.7 -> 3.9 M samples/s at batch 1, 4.2 -> 4.3 M at batch 256; three or
    more a pass fall to 2.8 M at batch 256 (XLA fuses across the degrees)."""
    def run(k, v):
        return phi2_action(functools.partial(_gi_matvec, k), v.T, order, unroll=2).T

    c = _GI_CHUNK_BYTES // (8 * v.dtype.itemsize)
    if v.ndim < 2 or v.shape[0] <= c:
        return run(k, v)
    n, m = v.shape[0], -(-v.shape[0] // c)

    def split(x):
        x = jnp.pad(x, [(0, m * c - n)] + [(0, 0)] * (x.ndim - 1))
        return x.reshape((m, c) + x.shape[1:])

    batched = [jnp.ndim(x) > 0 for x in k]

    def chunk(args):
        kb, vb = args
        kb = iter(kb)
        return run(tuple(next(kb) if b else x for x, b in zip(k, batched)), vb)

    out = jax.lax.map(chunk, (tuple(split(x) for x, b in zip(k, batched) if b), split(v)))
    return out.reshape((m * c,) + out.shape[2:])[:n]


@functools.lru_cache
def _gi_phi2(dtype: str):
    r"""$\varphi_2(X)v$ for the GI-LESO (`GILESOObserver._transition_c`): `f(k, v, rho)`
    for the entries `k`, the vector `v` (the real layout) and the norm bound
    `rho`: Horner's rule on `_gi_matvec` at the degree of each bound in `ACTION_NORMS`
    for `dtype` (`_gi_taylor`), the balanced matrix function beyond (`switched`)."""

    def taylor(norm):
        return functools.partial(_gi_taylor, order=taylor_degree(norm, dtype))

    def full(k, v):
        return _real(phi_matrix(_gi_dense(k))[2] @ jax.lax.complex(v[0::2], v[1::2]))

    return switched([taylor(x) for x in ACTION_NORMS] + [full], ACTION_NORMS,
                    native=range(len(ACTION_NORMS)))


class FALESOObserver(AbstractBackEMFLESO):
    r"""Frequency-adaptive LESO, li-fa-leso (25)-(28), with a quadrature PLL.

    $L_1(s) = -j\hat\omega - \mu$, $L_2(s) = k_1 + k_2 s$ (25): $\hat e/e = (k_1 + k_2 s)/
    (s^2 - j\hat\omega s + k_1 + k_2 s)$ (26), unity gain and zero phase at
    $s = j\hat\omega$ (19): no steady-state angle error at any constant speed, of either
    sign, with a matched model. Stable for $k_1, k_2 > 0$ at every $\hat\omega$ (22)-(24);
    the generalised Routh array's last entry is $a_2^{(2)} = k_1k_2^2$ (the printed
    (23) drops a factor $k_2$, the sign is the same: `pmsmjax.analysis.routh_complex2`).

    The price of (26) passing DC ($G(0) = 1$): one root of (22) sits near
    $s \approx -k_1/(k_2 - j\hat\omega)$, real part $-k_1k_2/(k_2^2 + \hat\omega^2)$, about
    $-0.08$ 1/s at 25 Hz with Table II's gains: a constant (stationary-frame) error in the
    estimate, e.g. left by a start-up transient, decays with a time constant of about
    10 s. It shows in the linearised error dynamics as a pair at $-0.08 \pm j\omega$
    (`pmsmjax equilibria`), and the tuner's Hurwitz margin penalises it.

    **Arguments:**

    - `motor`, `pll`: as `CLESOObserver`.
    - `k1` (1/s^2), `k2` (1/s): the gains of (25), > 0.
    """

    paper_motor: ClassVar[str | None] = "li_dtp"
    paper_T_s: ClassVar[float | None] = 1e-4
    c_emitter: ClassVar[str | None] = "_li:emit"
    #: (25)'s $-j\hat\omega$ multiplies the resonator's states by the speed estimate,
    #: itself a coordinate of the error: the inner solve of the equilibrium analysis is
    #: not affine, and three steps leave most angles unsettled at low speed (measured on
    #: the comparison grids, 300 points each: paper design on `li_dtp` 22 points without
    #: a verdict, 2 with 8 steps; a tuned design on `zhang750`, k1 = 208 1/s^2, 138 and
    #: 0; 12 steps change no verdict of either). The steps are a scan: run time only
    #: (+45 % for the analysis), no compile time.
    equilibria_gauss_newton: ClassVar[int] = 8
    motor: PMSMParams
    k1: float
    k2: float
    pll: QuadraturePLL

    coordinates: ClassVar[ErrorCoordinates] = _coords(
        ("z_d", "z_q"), ("A/s", "A/s"),
        ("integral state z (x2_hat = -k2 eps - z) minus its steady state, rotor frame d",
         "the same, q"))
    design_units: ClassVar[dict[str, str]] = {
        "k1": "1/s^2, FA-LESO gain k1 li-fa-leso (25)",
        "k2": "1/s, FA-LESO gain k2 li-fa-leso (25)", **PLL_UNITS}
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "k1": (0.1, 10.0), "k2": (0.3, 3.0), "w_pll": (0.25, 4.0), "zeta_pll": (0.5, 2.0)}

    def __init__(self, motor: PMSMParams, k1, k2, pll: QuadraturePLL, *, magnetic=None):
        _check_motor("FALESOObserver", motor)
        _check_pll("FALESOObserver", pll)
        self.motor, self.k1, self.k2, self.pll, self.magnetic = motor, k1, k2, pll, magnetic

    def __check_init__(self):
        check_positive("FALESOObserver", "k1", self.k1, "1/s^2")
        check_positive("FALESOObserver", "k2", self.k2, "1/s")

    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None, **design):
        """Table II on `li_dtp`: $k_1 = 10\\pi$, $k_2 = 100\\pi$; scaled as time is
        ($k_1$ by the square, $k_2$ by the ratio `w_rated / (100 pi)`) elsewhere."""
        motor = drive.three_phase_motor if motor is None else motor
        a = _scale(drive)
        obs = cls(motor, 10.0 * math.pi * a ** 2, 100.0 * math.pi * a,
                  QuadraturePLL.for_speed(float(drive.w_rated)))
        return obs.with_design(**design) if design else obs

    def _own_design(self):
        return {"k1": self.k1, "k2": self.k2}

    def _matrices(self, w_hat):
        w_hat = jnp.asarray(w_hat)
        z = 0.0 * w_hat
        return (blk(z), blk(self.k1 + z), blk(-1.0 + z), blk(-self.k2 + z),
                blk(z, w_hat))

    def _complex_system(self, w_hat):
        w_hat = jnp.asarray(w_hat)
        dt = jnp.result_type(w_hat, float)
        k2 = jnp.asarray(self.k2, dt)
        k = jax.lax.complex(-k2, w_hat.astype(dt))
        b = jnp.asarray(self.k1, dt)
        return ((k, -1.0), (b, 0.0)), (-k, -b), -1.0, -k2


#: Gauss-Newton steps per grid point of the twin's continuation (the generic route's
#: default is 3). The resonator's states make the inner least squares stiff: with 3, of
#: the 81 designs with w0, K_r, w_c and w_pll each at a bound of the tuning box or at
#: Table II's value, at 0.1, 0.5 and 1 p.u., 22 of 243 points on li_dtp and 25 on
#: morawiec_ipm3k5 had fewer than half the grid settled and were reported degenerate,
#: among them designs whose closed loop runs well (e.g. K_r, w_c and w_pll at 4x Table
#: II's: 1.65 deg RMS on morawiec_ipm3k5's load-step run); with 10, none. The steps are
#: a scan: more cost run time, not compile time.
GI_TWIN_GAUSS_NEWTON = 10


@eqx.filter_jit
def _gi_twin_equilibria(obs, plant, op, n_grid):
    # `GILESOObserver.fast_equilibria`, one compiled program (inlined under an outer
    # jit): run op by op, the twin's generic route traced its loops anew at every call
    # (about 25 s per operating point)
    from ..analysis._generic import _make_scaled, equilibria_traced, jacobian_readout

    dtype = jnp.result_type(op.w_m, float)
    wr = jnp.maximum(jnp.abs(jnp.asarray(op.w_m, dtype)), jnp.asarray(obs.w_c, dtype))
    twin = GILESOObserver(obs.motor, obs.w0, obs.K_r, obs.w_c, wr, obs.pll,
                          resonance="fixed")
    grid = {} if n_grid is None else {"n_grid": n_grid}
    eq = equilibria_traced(twin, plant, op, method="generic",
                           n_gauss_newton=GI_TWIN_GAUSS_NEWTON, **grid)
    sys = _make_scaled(obs, plant, op, 1.0)
    z = jnp.where(eq.valid[:, None], eq.x, 0.0) / sys.scale
    A = jax.vmap(jax.jacfwd(sys.F))(z)  # scaled, as the generic route's test
    _, hurwitz, A_si = jacobian_readout(sys, A)
    stable = eq.valid & hurwitz & ~eq.tangent
    return eqx.tree_at(lambda e: (e.stable, e.jacobian), eq,
                       (stable, jnp.where(eq.valid[:, None, None], A_si, jnp.nan)))
