r"""Gain design and error dynamics of the extended-state flux observer of zhang2022.

Reference: M. Zhang, B. Xia, J. Zhang, "Parameter Design and Convergence Analysis of Flux
Observer for Sensorless PMSM Drives", IEEE Trans. Energy Convers., 37(4), 2022,
doi:10.1109/TEC.2022.3177707.

Notation (estimator frame, no suffix): $\tilde x = x - \hat x$ (true minus estimate),
auxiliary flux zhang2022 (7) $\psi_{a0} = [(L_d - L_q) i_{d0} + \psi_f,\; -(L_d - L_q) i_{q0}]$,
error signal zhang2022 (10d) $e = \hat L (i - \hat i) = \hat L i - \hat\psi + \hat\psi_f$.

Gains (all functions are pure and vmappable):

- zhang2022 (17) $G_1 = [2\zeta_1\omega_1 I + (\omega_1^2/\omega_0 - \omega_0) J]\,
  \psi_{a0}\psi_{a0}^T / \|\psi_{a0}\|^2$ places the flux-error poles at
  $s^2 + 2\zeta_1\omega_1 s + \omega_1^2$ (16) and gives $G_1 J \psi_{a0} = 0$.
- zhang2022 (25) minimum-norm $g_2 = 2\zeta_2\omega_2 \psi_{a0}^T J / \|\psi_{a0}\|^2$,
  $g_3 = \omega_2^2 \psi_{a0}^T J / \|\psi_{a0}\|^2$; any other solution of zhang2022 (19) adds
  multiples of $\psi_{a0}^T$ (the null space of $v \mapsto v J\psi_{a0}$).
- zhang2022 (38) schedule $\zeta_1 = 1.5 + |\omega_0|/\omega_r$, $\omega_1 = 1.5|\omega_0|/\zeta_1$.

$\omega_0 \to 0$: (17) contains $\omega_1^2/\omega_0$. With $\omega_1$ proportional to
$|\omega_0|$ (the schedule (38), or a fixed ratio $\omega_1/|\omega_0|$ as in Fig. 1) the
term is $r^2 \omega_0 \to 0$ and $G_1 \to 0$: at standstill the flux error is not
observable and the observer integrates open loop. With a fixed $\omega_1$ the term is
singular; `gain_G1` then evaluates it at $\omega_0$ clamped to `w_min` in magnitude
(sign kept), which bounds the gain and is documented as a design choice, not physics.

Erratum handled here: zhang2022 (9) prints the linear branch of fal as $e/\eta^{a-1}$, which is
discontinuous at $|e| = \eta$ for $a < 1$; the continuous (Han) form is
$e / \eta^{1-a}$, whose slope is $\eta^{a-1}$. Footnote 1 of the paper says the gains of
zhang2022 (10) and (15) differ by that factor: the nonlinear observer uses
$G^{(10)} = G^{(15)} \eta^{1-a}$ so its linearisation has the designed poles.

Frame speed: the observer is implemented with the estimator frame rotating at
$\dot{\hat\theta} = \hat\omega + g_2 \mathrm{fal}(e)$ (the frame it actually lives in),
so that the exact error dynamics are
$\dot{\tilde\psi} = -(\omega_0 - \tilde\omega + g_2\mathrm{fal}(e)) J\tilde\psi
- G_1 \mathrm{fal}(e) - (R_s - \hat R_s) i$. (11) prints $-(\omega_0 -
  \tilde\omega)J\tilde\psi$;
the extra term is of second order, so both give the same linearisation zhang2022 (15), and at an
equilibrium with the min-norm gains ($g_2 \parallel g_3$) it vanishes, so both have the
same equilibria; zhang2022 (31a) is written with the frame speed $\omega_0$, as here.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._frames import J, jmul, rotate
from .._plant._params import PMSMParams
from .._validate import check_positive, check_range, is_concrete


def check_design(owner: str, *, zeta1=None, w1=None, ratio=None, zeta2=None, w2=None,
                 a=None, eta=None) -> None:
    """Raise `ValueError` naming the argument for a bad (concrete) design parameter.

    Damping ratios `zeta1`, `zeta2` (-) and natural frequencies `w1`, `w2` (rad/s) and the
    ratio `w1 / |w0|` must be finite and > 0; fal's exponent `a` must lie in (0, 1] and its
    linear-zone half-width `eta` (V s) must be > 0. Traced values are not checked.
    """
    check_positive(owner, "zeta1", zeta1)
    check_positive(owner, "w1", w1, "rad/s")
    check_positive(owner, "ratio", ratio, "-")
    check_positive(owner, "zeta2", zeta2)
    check_positive(owner, "w2", w2, "rad/s")
    check_range(owner, "a", a, 0.0, 1.0, "-", lo_open=True)
    check_positive(owner, "eta", eta, "V s")


def fal(e, a, eta):
    r"""Han's fal function zhang2022 (9), element-wise, continuous at $|e| = \eta$.

    $\mathrm{fal}(e) = e\,\eta^{a-1}$ for $|e| \le \eta$, $|e|^a \mathrm{sign}(e)$
    otherwise. Smooth at $e = 0$ (linear there), so gradients are finite everywhere.
    `a` in (0, 1], `eta` > 0 (same unit as `e`).
    """
    check_design("fal", a=a, eta=eta)
    e = jnp.asarray(e)
    abs_e = jnp.abs(e)
    big = abs_e > eta
    safe = jnp.where(big, abs_e, eta)  # avoid |e|^a at 0 (infinite derivative) in AD
    return jnp.where(big, jnp.sign(e) * safe ** a, e * eta ** (a - 1.0))


def psi_a(motor: PMSMParams, i_dq):
    """Auxiliary flux zhang2022 (7) at current `i_dq` (A, estimator frame) -> (V s, (2,))."""
    dL = motor.L_d - motor.L_q
    i_dq = jnp.asarray(i_dq)
    return jnp.stack([motor.extended_flux(i_dq[..., 0]), -dL * i_dq[..., 1]], -1)


def zhang38(w0, w_rated, zeta1_scale=1.0, decay_scale=1.0):
    """Suggested design zhang2022 (38): `(zeta1, w1)` for speed `w0` (rad/s), rated speed (rad/s).

    `zeta1 = 1.5 + |w0|/w_rated`, `w1 = 1.5 |w0| / zeta1`, so `zeta1 w1 = 1.5 |w0|` and
    `w1 -> 0` (hence G1 -> 0 in zhang2022 (17)) as `w0 -> 0`.

    `zeta1_scale` (-) multiplies the damping and `decay_scale` (-) the decay rate
    `zeta1 w1` (the flux error's envelope, per radian of rotation 1.5 in (38)), each
    keeping (38)'s shape over speed: `zeta1 = zeta1_scale (1.5 + |w0|/w_rated)`,
    `zeta1 w1 = decay_scale 1.5 |w0|`. Both 1 is (38).
    """
    check_positive("zhang38", "w_rated", w_rated, "rad/s")
    check_positive("zhang38", "zeta1_scale", zeta1_scale, "-")
    check_positive("zhang38", "decay_scale", decay_scale, "-")
    zeta1 = zeta1_scale * (1.5 + jnp.abs(w0) / w_rated)
    return zeta1, decay_scale * 1.5 * jnp.abs(w0) / zeta1


def gain_G1(psi_a0, w0, zeta1, w1, w_min=0.0):
    r"""Flux gain zhang2022 (17): poles of $-(\omega_0 J + G_1)$ at $s^2 + 2\zeta_1\omega_1 s +
    \omega_1^2$.

    - `psi_a0`: auxiliary flux (V s, (2,)); `w0`: speed (rad/s, any sign, nonzero unless
      `w1` is proportional to `|w0|`); `zeta1` (-), `w1` (rad/s).
    - `w_min`: the magnitude below which `w0` is clamped in `w1**2 / w0` (rad/s); 0 = none.

    Written as $(2\zeta_1\omega_1\,\psi_{a0}\psi_{a0}^T + c\,J\psi_{a0}\psi_{a0}^T)
    / \|\psi_{a0}\|^2$, $c = \omega_1^2/\omega_0 - \omega_0$, with no constant arrays,
    so float32 inputs give float32 gains.
    """
    check_design("gain_G1", zeta1=zeta1)
    # w1 = 0 is legitimate here: proportional schedules give w1 -> 0 at standstill.
    check_positive("gain_G1", "w1", w1, "rad/s", allow_zero=True)
    check_positive("gain_G1", "w_min", w_min, "rad/s", allow_zero=True)
    w0c = jnp.where(jnp.abs(w0) < w_min, jnp.where(w0 < 0, -w_min, w_min), w0) \
        if (not is_concrete(w_min) or w_min) else w0
    # w1^2/w0 - w0, written so that w1 = r |w0| stays finite at w0 = 0 when w_min = 0.
    c = jnp.where(w0c == 0, 0.0, w1 ** 2 / jnp.where(w0c == 0, 1.0, w0c)) - w0
    psi_a0 = jnp.asarray(psi_a0)
    nrm2 = jnp.sum(psi_a0 ** 2)
    return (2.0 * zeta1 * w1 * jnp.outer(psi_a0, psi_a0)
            + c * jnp.outer(jmul(psi_a0), psi_a0)) / nrm2


def gains_g23(psi_a0, zeta2, w2, n2=0.0, n3=0.0):
    r"""Speed/position gains solving zhang2022 (19).

    `n2 = n3 = 0` gives the minimum-norm solution zhang2022 (25), which attains the lower bound
    $\sigma_1 = \|v_2\| / \|v_1\|$ of zhang2022 (27). Nonzero `n2`, `n3` (rad/s per V s and
    rad/s^2 per V s) add $n\,\psi_{a0}^T/\|\psi_{a0}\|$, the null space of zhang2022 (19), giving
    any other solution for comparison.
    """
    check_design("gains_g23", zeta2=zeta2, w2=w2)
    psi_a0 = jnp.asarray(psi_a0)
    nrm2 = jnp.sum(psi_a0 ** 2)
    row = jnp.stack([psi_a0[1], -psi_a0[0]]) / nrm2  # psi_a0^T J / |psi_a0|^2
    null = psi_a0 / jnp.sqrt(nrm2)
    g2 = 2.0 * zeta2 * w2 * row + n2 * null
    g3 = w2 ** 2 * row + n3 * null
    return g2, g3


def sigma1(psi_a0, zeta2, w2):
    r"""Lower bound zhang2022 (27) of $\|[g_2; g_3]\|_{2,i}$ over all solutions of zhang2022 (19):
    $\sigma_1 = \|v_2\|/\|v_1\| = \sqrt{4\zeta_2^2\omega_2^2 + \omega_2^4}/\|\psi_{a0}\|$."""
    return jnp.sqrt(4.0 * zeta2 ** 2 * w2 ** 2 + w2 ** 4) / jnp.sqrt(jnp.sum(
        jnp.asarray(psi_a0) ** 2))


def gains_pi(psi_a0, zeta2, w2):
    r"""Speed-law gains of the adaptive full-order observer, zhang2022 (53):
    $k_p = 2\zeta_2\omega_2/\psi_{ad0}$ (rad/s per V s), $k_i = \omega_2^2/\psi_{ad0}$
    (rad/s^2 per V s). The paper prints $\zeta_2 = 1$. See `AFOObserver` for the sign.
    """
    check_design("gains_pi", zeta2=zeta2, w2=w2)
    psi_ad0 = jnp.asarray(psi_a0)[0]
    return 2.0 * zeta2 * w2 / psi_ad0, w2 ** 2 / psi_ad0


class ESOGains(eqx.Module):
    """Linear-design gains of zhang2022 (15): `G1` (1/s, (2, 2)), `g2` (rad/(V s^2), (2,)),
    `g3` (rad/(V s^3), (2,)).

    `g2 @ e` is an angular speed (rad/s) and `g3 @ e` an angular acceleration (rad/s^2)
    for a flux error `e` (V s).
    """

    G1: jnp.ndarray
    g2: jnp.ndarray
    g3: jnp.ndarray


def eso_gains(psi_a0, w0, zeta1, w1, zeta2, w2, *, w_min=0.0, n2=0.0, n3=0.0) -> ESOGains:
    """All gains at one operating point: zhang2022 (17) and (19)/(25). Units as in
    `gain_G1`."""
    g2, g3 = gains_g23(psi_a0, zeta2, w2, n2, n3)
    return ESOGains(G1=gain_G1(psi_a0, w0, zeta1, w1, w_min), g2=g2, g3=g3)


def error_matrix(w0, psi_a0, gains: ESOGains):
    r"""The 4x4 linearised error matrix A of zhang2022 (15), state $[\tilde\psi_d, \tilde\psi_q,
    \tilde\theta, \tilde\omega]$."""
    Jp = jmul(psi_a0)
    G1, g2, g3 = gains.G1, gains.g2, gains.g3
    Jw = w0 * jnp.asarray(J, dtype=jnp.result_type(G1))
    zero, one = jnp.zeros((), G1.dtype), jnp.ones((), G1.dtype)
    top = jnp.concatenate([-(Jw + G1), (G1 @ Jp)[:, None],
                           jnp.zeros((2, 1), G1.dtype)], 1)
    mid = jnp.concatenate([-g2, jnp.stack([g2 @ Jp, one])])[None]
    bot = jnp.concatenate([-g3, jnp.stack([g3 @ Jp, zero])])[None]
    return jnp.concatenate([top, mid, bot], 0)


def error_signal(psi_err, theta_err, i0, motor: PMSMParams, motor_hat: PMSMParams):
    r"""Error signal $e = \hat L i - \hat\psi + \hat\psi_f$ (V s) in the estimator frame.

    The true flux in the estimator frame is zhang2022 (5)
    $\psi = e^{\tilde\theta J}(L e^{-\tilde\theta J} i + \psi_f)$ and
    $\hat\psi = \psi - \tilde\psi$, with the controlled current `i0` (A, estimator frame);
    `motor` holds the true parameters and `motor_hat` the observer's.
    """
    i_dq = rotate(i0, -theta_err)
    psi_s = jnp.stack([motor.L_d * i_dq[0] + motor.psi_f, motor.L_q * i_dq[1]])
    psi = rotate(psi_s, theta_err)
    L_hat_i = jnp.stack([motor_hat.L_d * i0[0], motor_hat.L_q * i0[1]])
    return L_hat_i + jnp.stack([motor_hat.psi_f, 0.0 * motor_hat.psi_f]) - psi + psi_err


def error_dynamics(x, w0, i0, gains: ESOGains, motor: PMSMParams,
                   motor_hat: PMSMParams | None = None, a=1.0, eta=1.0):
    r"""Right-hand side of the error dynamics zhang2022 (11) at constant speed `w0` (rad/s).

    State `x = [psi_err_d, psi_err_q, theta_err, w_err]` (V s, V s, rad, rad/s), errors
    true minus estimate; `i0` is the controlled current in the estimator frame (A).
    `motor_hat` (default `motor`) is the observer's model (parameter mismatch).
    With `a = 1` the feedback is linear (LESO); with `a < 1` the fal feedback uses the
    gains scaled by $\eta^{1-a}$ (footnote 1), so the linearisation is zhang2022 (15) either way.
    """
    motor_hat = motor if motor_hat is None else motor_hat
    psi_err, theta_err, w_err = x[:2], x[2], x[3]
    e = error_signal(psi_err, theta_err, i0, motor, motor_hat)
    f = fal(e, a, eta) * eta ** (1.0 - a)  # = e exactly when a = 1
    frame_speed = w0 - w_err + gains.g2 @ f
    dR = motor.R_s - motor_hat.R_s
    d_psi = -frame_speed * jmul(psi_err) - gains.G1 @ f - dR * jnp.asarray(i0)
    d_theta = w_err - gains.g2 @ f
    d_w = -gains.g3 @ f
    return jnp.concatenate([d_psi, jnp.stack([d_theta, d_w])])
