r"""Equilibria of the zhang2022 ESO/LESO error dynamics (11) from the paper's closed form
zhang2022 (34)-(36): matched parameters and linear feedback (the quartic route; the general
route is `pmsmjax.analysis._equilibria`, and the two agree where both apply).

**Quartic route.** zhang2022 (34)-(35) with $G_1 = [g_1, g_2]^T[1, -\beta]$, $\beta =
-\psi_{aq0}/\psi_{ad0}$ ($g_1$, $g_2$ are the entries of $G_1$'s first column here, not
the speed gains) and $\hat\omega = \omega_0$. Our derivation from zhang2022 (31), (33)
gives
$A\Delta_d + B\Delta_q = 0$ with $A = \omega_0\beta + (1+\beta^2)g_1$,
$B = \omega_0 + (1+\beta^2)g_2$ and $\Delta = -e_0$, whose Fourier coefficients are
exactly the printed $p_1 \dots p_5$: zhang2022 (35) is correct as printed (checked numerically
against the general route in the tests). With zhang2022 (36),
$(1+t^2)^2 \cdot (34)$ is the quartic $c_4t^4 + c_3t^3 + c_2t^2 + c_1t + c_0$ with
$c_4 = p_1 - p_3 + p_5$, $c_3 = 2p_4 - 4p_2$, $c_2 = 2p_5 - 6p_1$, $c_1 = 4p_2 + 2p_4$,
$c_0 = p_1 + p_3 + p_5 = 0$. So $t = 0$ is always a root and the nonzero equilibria are
the real roots of the **cubic** $c_4t^3 + c_3t^2 + c_2t + c_1$: 1 or 3 of them, which is
the paper's "either 1 or 3" (counted with multiplicity; a root at $t = \infty$, i.e.
$\tilde\theta = \pi$, when $c_4 = -2p_3 = 0$). We solve it as the binary cubic form in
$(\cos x, \sin x)$, $x = \tilde\theta/2$, in closed form, so the root at infinity needs
no special case, and polish each root with Newton steps on the form.

The states, residuals and stability of the equilibria are computed as in the general
route (`eso_equilibria`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp

from .._plant._params import PMSMParams
from ..observers import ESOGains, psi_a
from ._args import as_arrays
from ._equilibria import Equilibria, _finish, _make_reduction
from ._linearize import check_frame


def quartic_coefficients(w0, i0, gains: ESOGains, motor: PMSMParams):
    r"""$p_1 \dots p_5$ of zhang2022 (35) exactly as printed (matched parameters, linear feedback).

    $\beta = -\psi_{aq0}/\psi_{ad0}$; $g_1$, $g_2$ are the entries of the first column of
    $G_1 = [g_1, g_2]^T[1, -\beta]$; $\hat\omega = \omega_0$ (the frame speed at an
    equilibrium); $i_d$, $i_q$ the current in the estimator frame; $\Delta L =
    (L_d - L_q)/2$. Returns `(5,)` (V; only their ratios matter).
    Singular when $\psi_{ad0} = 0$ (beta), which the general route is not.
    """
    pa = psi_a(motor, i0)
    beta = -pa[1] / pa[0]
    g1, g2 = gains.G1[0, 0], gains.G1[1, 0]
    i_d, i_q = i0[0], i0[1]
    dL = 0.5 * (motor.L_d - motor.L_q)
    b2 = beta ** 2 + 1.0
    p1 = dL * ((beta * i_d - i_q) * w0 + b2 * (g1 * i_d - g2 * i_q))
    p2 = dL * ((beta * i_q + i_d) * w0 + b2 * (g2 * i_d + g1 * i_q))
    p3 = motor.psi_f * (beta * w0 + b2 * g1)
    p4 = motor.psi_f * (w0 + b2 * g2)
    p5 = -p1 - p3
    return jnp.stack([p1, p2, p3, p4, p5])


def quartic_t_coefficients(p):
    r"""Quartic in $t = \tan(\tilde\theta/2)$ from zhang2022 (34) and (36): `[c4, c3, c2,
    c1, c0]`
    of $(1+t^2)^2\,(34)$ (highest power first, as `numpy.roots` expects)."""
    p1, p2, p3, p4, p5 = (p[..., k] for k in range(5))
    return jnp.stack([p1 - p3 + p5, 2 * p4 - 4 * p2, 2 * p5 - 6 * p1, 4 * p2 + 2 * p4,
                      p1 + p3 + p5], -1)


def trig_poly(p, theta):
    """Left side of zhang2022 (34): p1 cos 2th + p2 sin 2th + p3 cos th + p4 sin th + p5."""
    return (p[..., 0] * jnp.cos(2 * theta) + p[..., 1] * jnp.sin(2 * theta)
            + p[..., 2] * jnp.cos(theta) + p[..., 3] * jnp.sin(theta) + p[..., 4])


def _monic_cubic_real_roots(B, C, D):
    """Real roots of t^3 + B t^2 + C t + D (closed form). Returns (roots (..., 3), valid)."""
    p = C - B * B / 3.0
    q = 2.0 * B ** 3 / 27.0 - B * C / 3.0 + D
    disc = (0.5 * q) ** 2 + (p / 3.0) ** 3
    three = disc < 0
    # three real roots (p < 0 there): trigonometric form
    pn = jnp.where(three, p, -1.0)
    m = 2.0 * jnp.sqrt(-pn / 3.0)
    arg = jnp.clip(3.0 * q / (pn * m), -1.0, 1.0)
    phi = jnp.arccos(arg) / 3.0
    k = jnp.arange(3, dtype=B.dtype)
    y3 = m[..., None] * jnp.cos(phi[..., None] - 2.0 * math.pi * k / 3.0)
    # one real root: Cardano with the cancellation-free choice of cube root
    sq = jnp.sqrt(jnp.where(three, 0.0, disc))
    A = -jnp.sign(q) * jnp.cbrt(0.5 * jnp.abs(q) + sq)
    A = jnp.where(q == 0, jnp.cbrt(sq), A)
    y1 = jnp.where(A != 0, A - p / (3.0 * jnp.where(A != 0, A, 1.0)), 0.0)
    y = jnp.where(three[..., None], y3,
                  jnp.stack([y1, jnp.zeros_like(y1), jnp.zeros_like(y1)], -1))
    valid = jnp.where(three[..., None], True, k == 0)
    return y - B[..., None] / 3.0, valid


def _binary_cubic_angles(a0, a1, a2, a3, n_newton=3):
    r"""Zeros $x \in (-\pi/2, \pi/2]$ of $Q(x) = a_0c^3 + a_1c^2s + a_2cs^2 + a_3s^3$,
    $c = \cos x$, $s = \sin x$ (1 or 3 of them; closed form, then Newton on Q).

    Solves in $\tan x$ when $|a_3| \ge |a_0|$, else in $\cot x$, so roots near
    $x = \pm\pi/2$ need no special case. Returns (x (..., 3), valid (..., 3), ok) with
    `ok = False` when $a_0 = a_3 = 0$ (degenerate form).
    """
    use_tan = jnp.abs(a3) >= jnp.abs(a0)
    lead = jnp.where(use_tan, a3, a0)
    ok = lead != 0
    lead = jnp.where(ok, lead, 1.0)
    B = jnp.where(use_tan, a2, a1) / lead
    C = jnp.where(use_tan, a1, a2) / lead
    D = jnp.where(use_tan, a0, a3) / lead
    y, valid = _monic_cubic_real_roots(B, C, D)
    x_tan = jnp.arctan(y)
    x_cot = jnp.arctan2(jnp.ones_like(y), y)
    x_cot = jnp.where(x_cot > 0.5 * math.pi, x_cot - math.pi, x_cot)
    x = jnp.where(use_tan[..., None], x_tan, x_cot)
    A0, A1, A2, A3 = (v[..., None] for v in (a0, a1, a2, a3))
    for _ in range(n_newton):
        c, s = jnp.cos(x), jnp.sin(x)
        Q = A0 * c ** 3 + A1 * c * c * s + A2 * c * s * s + A3 * s ** 3
        dQ = (-3 * A0 * c * c * s + A1 * (c ** 3 - 2 * c * s * s)
              + A2 * (2 * c * c * s - s ** 3) + 3 * A3 * s * s * c)
        step = jnp.where(dQ != 0, Q / jnp.where(dQ != 0, dQ, 1.0), 0.0)
        x = x - jnp.clip(step, -0.1, 0.1)
    return x, valid, ok


def quartic_equilibria(w0, i0, gains: ESOGains, motor: PMSMParams, *,
                       frame: str = "observer") -> Equilibria:
    r"""Equilibria from the paper's quartic zhang2022 (34)-(36), matched parameters, linear
    feedback.

    $p$ from (35) as printed (`quartic_coefficients`); the root $t = 0$ of the quartic is
    divided out and the cubic is solved in closed form (see the module docstring).
    The full states, residuals and stability are computed exactly as in
    `eso_equilibria`. Returns an `Equilibria` with 4 slots (0 and up to 3 nonzero).
    """
    check_frame("quartic_equilibria", frame)
    dtype = jnp.result_type(w0, gains.G1, float)
    return _quartic_equilibria(*as_arrays((w0, i0, gains, motor), dtype), frame)


@eqx.filter_jit
def _quartic_equilibria(w0, i0, gains, motor, frame):
    dtype = w0.dtype
    p = quartic_coefficients(w0, i0, gains, motor)
    c4, c3, c2, c1, _ = (quartic_t_coefficients(p)[k] for k in range(5))
    # c4 t^3 + c3 t^2 + c2 t + c1 = 0, t = s/c: a binary cubic with a3 = c4, ..., a0 = c1
    x, valid, ok_form = _binary_cubic_angles(c1, c2, c3, c4)
    theta = jnp.concatenate([jnp.zeros(1, dtype), 2.0 * x])
    valid = jnp.concatenate([jnp.ones(1, bool), valid])
    red, ok = _make_reduction(w0, i0, gains, motor, motor, 1.0, 1.0, True)
    ok = ok & ok_form & jnp.all(jnp.isfinite(p))
    return _finish(red, theta, valid, jnp.zeros(4, bool), frame, 1.0, 1.0, ok)
