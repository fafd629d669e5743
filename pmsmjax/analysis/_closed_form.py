r"""zhang2022's closed-form classification of ESO/LESO flux-gain designs (matched
parameters, linear feedback; `method="closed_form"` of `classify_designs`, and
`LESOObserver.fast_classify`).

The quartic route zhang2022 (34)-(36) with its root $t = 0$ divided out, as a closed-form
cubic, then the Jacobian zhang2022 (37) written out by hand and the exact Routh-Hurwitz
test, all element-wise in dimensionless variables (flux / $|\psi_{a0}|$, speed error /
$|\omega_0|$, time $\times|\omega_0|$). It is one fused, vectorised XLA computation:
millions of designs per second on one CPU core.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ._classify import DesignClass


# ---------------------------------------------------------------------------------------
# Closed-form kernel (matched parameters, linear feedback)
# ---------------------------------------------------------------------------------------
# Written for speed: everything is element-wise over the batch (one fused XLA loop), no
# trigonometric function of the equilibrium angle is evaluated (double-angle formulas on
# the unit vector (cos x, sin x), x = theta/2), and the structural zeros and ones of the
# Jacobian are removed at trace time (`_mul`, `_add` below), so that the characteristic
# polynomial costs about a hundred flops.

def _is_const(a, v):
    return isinstance(a, float) and a == v


def _mul(a, b):
    if _is_const(a, 0.0) or _is_const(b, 0.0):
        return 0.0
    if _is_const(a, 1.0):
        return b
    if _is_const(b, 1.0):
        return a
    return a * b


def _add(a, b):
    if _is_const(a, 0.0):
        return b
    if _is_const(b, 0.0):
        return a
    return a + b


def _det(A, rows, cols):
    """Laplace expansion along the first row (trace-time recursion; sparse-aware)."""
    if len(rows) == 1:
        return A[rows[0]][cols[0]]
    out = 0.0
    for k, c in enumerate(cols):
        a = A[rows[0]][c]
        if _is_const(a, 0.0):
            continue
        minor = _det(A, rows[1:], cols[:k] + cols[k + 1:])
        term = _mul(a, minor)
        out = _add(out, term if k % 2 == 0 else -term)
    return out


def _charpoly4(A):
    """det(sI - A) = s^4 + c1 s^3 + c2 s^2 + c3 s + c4 from principal minors."""
    idx = range(4)
    c1 = 0.0
    for i in idx:
        c1 = _add(c1, -A[i][i])
    c2 = c3 = 0.0
    for i in idx:
        for j in range(i + 1, 4):
            c2 = _add(c2, _det(A, (i, j), (i, j)))
            for k in range(j + 1, 4):
                c3 = _add(c3, -_det(A, (i, j, k), (i, j, k)))
    c4 = _det(A, (0, 1, 2, 3), (0, 1, 2, 3))
    return c1, c2, c3, c4


def _hurwitz4(c1, c2, c3, c4):
    """Routh-Hurwitz for the monic quartic: c1, c3, c4 > 0, c1 c2 - c3 > 0,
    (c1 c2 - c3) c3 - c1^2 c4 > 0."""
    d2 = c1 * c2 - c3
    return (c1 > 0) & (c3 > 0) & (c4 > 0) & (d2 > 0) & (d2 * c3 - c1 * c1 * c4 > 0)


def _cubic_cs(a0, a1, a2, a3, n_newton):
    r"""Zeros of the binary cubic $a_0c^3 + a_1c^2s + a_2cs^2 + a_3s^3$ as unit vectors
    $(c, s) = (\cos x, \sin x)$ (up to sign, which does not change $\theta = 2x$).

    Closed form in $\tan x$ (if $|a_3| \ge |a_0|$) or $\cot x$, then Newton steps in $x$
    applied as small rotations of $(c, s)$. Returns three `(c, s, valid)` and `ok`
    (False if $a_0 = a_3 = 0$).
    """
    use_tan = jnp.abs(a3) >= jnp.abs(a0)
    lead = jnp.where(use_tan, a3, a0)
    ok = lead != 0
    inv = 1.0 / jnp.where(ok, lead, 1.0)
    B = jnp.where(use_tan, a2, a1) * inv
    C = jnp.where(use_tan, a1, a2) * inv
    D = jnp.where(use_tan, a0, a3) * inv
    p = C - B * B * (1.0 / 3.0)
    q = B * (2.0 / 27.0 * B * B - C / 3.0) + D
    disc = (0.5 * q) ** 2 + (p * (1.0 / 3.0)) ** 3
    three = disc < 0
    pn = jnp.where(three, p, -1.0)
    m = 2.0 * jnp.sqrt(pn * (-1.0 / 3.0))
    phi = jnp.arccos(jnp.clip(3.0 * q / (pn * m), -1.0, 1.0)) * (1.0 / 3.0)
    cp, sp = m * jnp.cos(phi), m * jnp.sin(phi)
    h = 0.5 * math.sqrt(3.0)
    sq = jnp.sqrt(jnp.where(three, 0.0, disc))
    Acb = -jnp.sign(q) * jnp.cbrt(0.5 * jnp.abs(q) + sq)
    Acb = jnp.where(q == 0, jnp.cbrt(sq), Acb)
    y1 = jnp.where(Acb != 0, Acb - p / (3.0 * jnp.where(Acb != 0, Acb, 1.0)), 0.0)
    shift = B * (1.0 / 3.0)
    ys = [jnp.where(three, cp, y1) - shift, -0.5 * cp + h * sp - shift,
          -0.5 * cp - h * sp - shift]
    valids = [jnp.ones_like(three), three, three]
    out = []
    for y, valid in zip(ys, valids):
        r = jax.lax.rsqrt(1.0 + y * y)
        c = jnp.where(use_tan, r, y * r)
        s = jnp.where(use_tan, y * r, r)
        for _ in range(n_newton):
            c2, s2 = c * c, s * s
            Q = c * (a0 * c2 + a2 * s2) + s * (a1 * c2 + a3 * s2)
            dQ = (-3.0 * a0 * c2 * s + a1 * c * (c2 - 2.0 * s2) + a2 * s * (2.0 * c2 - s2)
                  + 3.0 * a3 * s2 * c)
            d = jnp.clip(Q / jnp.where(dQ != 0, dQ, 1.0), -0.1, 0.1)
            cd, sd = 1.0 - 0.5 * d * d, d * (1.0 - d * d * (1.0 / 6.0))
            c, s = c * cd + s * sd, s * cd - c * sd  # rotate by -d: x <- x - d
            r = jax.lax.rsqrt(c * c + s * s)
            c, s = c * r, s * r
        out.append((c, s, valid))
    return out, ok


def _closed_form_classify(w0, i_d, i_q, zeta1, ratio, zeta2, w2, L_d, L_q, psi_f,
                          frame="observer", n_newton=2):
    """Element-wise classification; every argument broadcasts (SI units)."""
    sg = jnp.sign(w0)
    aw = jnp.abs(w0)
    awn = jnp.where(aw > 0, aw, 1.0)
    dL = L_d - L_q
    pad = dL * i_d + psi_f
    paq = -dL * i_q
    pn = jnp.sqrt(pad * pad + paq * paq)
    ipn = 1.0 / jnp.where(pn > 0, pn, 1.0)
    ud, uq = pad * ipn, paq * ipn
    lam_d, lam_q, phi = 0.5 * dL * i_d * ipn, 0.5 * dL * i_q * ipn, psi_f * ipn
    rho = ratio
    W2 = w2 / awn
    # r(theta) ~ n . e0(theta), n = rho J u + 2 zeta1 sign(w0) u (see _equilibria):
    # Fourier coefficients P1..P4 (P5 = -P1 - P3), then the binary cubic in theta/2.
    nd = -rho * uq + 2.0 * zeta1 * sg * ud
    nq = rho * ud + 2.0 * zeta1 * sg * uq
    P1 = -nd * lam_d + nq * lam_q
    P2 = -nd * lam_q - nq * lam_d
    P3 = -phi * nd
    P4 = -phi * nq
    roots, ok_form = _cubic_cs(2 * P2 + P4, -(4 * P1 + P3), P4 - 2 * P2, -P3, n_newton)

    # Gains in the scaled variables (flux / |psi_a0|, speed / |w0|, time * |w0|):
    # G1 = M1 u u^T with M1 = [[k, -cc], [cc, k]]; g2, g3 along (u_q, -u_d).
    k = 2.0 * zeta1 * rho
    cc = sg * (rho * rho - 1.0)
    m0, m1 = k * ud - cc * uq, cc * ud + k * uq
    G = [[m0 * ud, m0 * uq], [m1 * ud, m1 * uq]]
    g2 = [2.0 * zeta2 * W2 * uq, -2.0 * zeta2 * W2 * ud]
    g3 = [W2 * W2 * uq, -W2 * W2 * ud]
    irho2 = 1.0 / jnp.where(rho > 0, rho * rho, 1.0)
    o = frame == "observer"

    def stability(ct, st, origin):
        """Hurwitz test of the scaled Jacobian zhang2022 (37) at the equilibrium with angle theta
        given by (cos theta, sin theta)."""
        c2t, s2t = ct * ct - st * st, 2.0 * st * ct
        # de0/dtheta (scaled) and u.e0
        de_d = 2 * lam_d * s2t - 2 * lam_q * c2t + phi * st
        de_q = -2 * lam_q * s2t - 2 * lam_d * c2t - phi * ct
        ued = ud * de_d + uq * de_q
        gd = g2[0] * de_d + g2[1] * de_q
        hd = g3[0] * de_d + g3[1] * de_q
        if origin:
            j0 = j1 = 0.0
        else:
            e0d = lam_d * (1 - c2t) - lam_q * s2t + phi * (1 - ct)
            e0q = -lam_q * (1 - c2t) - lam_d * s2t - phi * st
            # equilibrium flux error psi = sign(w0) (u.e0) / rho^2 J M1 u; J psi = (j0, j1)
            sc = sg * (ud * e0d + uq * e0q) * irho2
            j0, j1 = -sc * m0, -sc * m1
        og = o and not origin
        A = [
            [(-j0 * g2[0] if og else 0.0) - G[0][0], sg - (j0 * g2[1] if og else 0.0) - G[0][1],
             (-j0 * gd if og else 0.0) - m0 * ued, j0],
            [-sg - (j1 * g2[0] if og else 0.0) - G[1][0], (-j1 * g2[1] if og else 0.0) - G[1][1],
             (-j1 * gd if og else 0.0) - m1 * ued, j1],
            [-g2[0], -g2[1], -gd, 1.0],
            [-g3[0], -g3[1], -hd, 0.0],
        ]
        return _hurwitz4(*_charpoly4(A))

    principal_stable = stability(1.0, 0.0, True)
    thetas, valids, stables = [], [], []
    for c, s, valid in roots:
        ct, st = c * c - s * s, 2.0 * c * s
        th = jnp.arctan2(st, ct)
        valid = valid & jnp.isfinite(th)
        thetas.append(th)
        valids.append(valid)
        stables.append(stability(ct, st, False) & valid)
    theta = jnp.stack(thetas, -1)
    valid = jnp.stack(valids, -1)
    stable = jnp.stack(stables, -1)
    finite_in = jnp.isfinite(w0 + i_d + i_q + zeta1 + ratio + zeta2 + w2)
    deg = ((aw == 0) | ~(rho > 0) | ~(pn > 0) | ~ok_form | ~finite_in
           | jnp.any(valid & (jnp.abs(theta) < 1e-5), -1))
    inf = jnp.any(stable, -1) & ~deg
    status = jnp.where(deg, -1, jnp.where(inf, 1, 0)).astype(jnp.int32)
    key = jnp.where(stable, jnp.abs(theta), jnp.inf)
    st = jnp.take_along_axis(theta, jnp.argmin(key, -1)[..., None], -1)[..., 0]
    return DesignClass(status=status, n_nonzero=jnp.where(deg, 0, jnp.sum(valid, -1)),
                       stable_theta=jnp.where(inf, st, jnp.nan),
                       theta=jnp.where(valid & ~deg[..., None], theta, jnp.nan),
                       stable=stable & ~deg[..., None],
                       principal_stable=principal_stable & ~deg,
                       principal_theta=jnp.where(deg, jnp.nan, 0.0 * w0))


_closed_form_jit = jax.jit(_closed_form_classify, static_argnames=("frame", "n_newton"))
