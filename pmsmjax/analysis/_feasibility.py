r"""Feasibility maps of the zhang2022 ESO flux-gain design (Fig. 1).

A design $(\zeta_1, \omega_1/|\omega_0|)$ at an operating point (speed, current, parameter
mismatch) is

- **feasible** (`status = 0`) if every equilibrium of the error dynamics zhang2022 (11) other than
  the designed one is unstable, so the error cannot settle at a static angle error;
- **infeasible** (`status = 1`) if at least one of them is stable (its angle is reported:
  the static position error the observer can lock to);
- **no equilibrium** (`status = 2`, only with parameter mismatch): the angle error
  cannot settle anywhere, the estimate drifts;
- **degenerate** (`status = -1`): the analysis does not apply or failed: $\omega_0 = 0$,
  $\omega_1 = 0$ (ratio 0: $\det(\omega_0J + G_1) = \omega_1^2 = 0$, a continuum of flux
  errors), $\psi_{a0} = 0$, a double root at the origin, non-finite values.

"Designed equilibrium": $\tilde\theta = 0$ with matched parameters; with mismatch the
equilibrium closest to $\tilde\theta = 0$. Whether it is itself stable is reported
separately (`principal_stable`; it is Hurwitz for every $\zeta_1, \omega_1, \zeta_2,
\omega_2 > 0$ with matched parameters, by zhang2022 (16)/(18)).

Two methods:

- `"closed_form"` (matched parameters, linear feedback): the quartic route zhang2022 (34)-(36) with
  its root $t = 0$ divided out, as a closed-form cubic, then the Jacobian zhang2022 (37) written out
  by hand and the exact Routh-Hurwitz test, all element-wise in dimensionless variables
  (flux / $|\psi_{a0}|$, speed error / $|\omega_0|$, time $\times|\omega_0|$). It is one
  fused, vectorised XLA computation: millions of designs per second on one CPU core.
- `"general"`: `eso_equilibria` (bracketing + `optimistix` bisection on the full
  right-hand side, Jacobian by `jax.jacfwd`), vmapped. Works with parameter mismatch and
  fal feedback; about 10^3 - 10^4 designs per second.

`"auto"` picks `"closed_form"` when it applies. With the minimum-norm gains zhang2022 (25) the
equilibria do not depend on $\zeta_2$, $\omega_2$ (the condition $g_3 f = 0$ fixes only
the direction of $f$), but their stability can.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._plant._params import Drive, PMSMParams
from ..observers._eso_design import eso_gains, psi_a, zhang38
from ._equilibria import as_arrays, eso_equilibria
from ._linearize import check_frame


METHODS = ("auto", "closed_form", "general")


class DesignClass(eqx.Module):
    """Classification of designs (any batch shape `...`).

    - `status`: 0 feasible, 1 infeasible, 2 no equilibrium at all (mismatch only), -1
      degenerate (see the module docstring).
    - `n_nonzero`: number of equilibria other than the designed one.
    - `stable_theta`: angle of the stable non-designed equilibrium closest to 0 (rad),
      NaN if there is none (the static position error of an infeasible design).
    - `theta`: angles of the non-designed equilibria (rad), `(..., K)`, NaN padded.
    - `stable`: which of them are stable, `(..., K)`.
    - `principal_stable`: the designed equilibrium is stable.
    - `principal_theta`: its angle (rad): 0 with matched parameters, the steady-state
      error caused by the mismatch otherwise (NaN if there is no equilibrium).
    """

    status: jnp.ndarray
    n_nonzero: jnp.ndarray
    stable_theta: jnp.ndarray
    theta: jnp.ndarray
    stable: jnp.ndarray
    principal_stable: jnp.ndarray
    principal_theta: jnp.ndarray


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


# ---------------------------------------------------------------------------------------
# General route per design
# ---------------------------------------------------------------------------------------

def _class_from_equilibria(eq, degenerate=False) -> DesignClass:
    """Feasibility of one operating point from its equilibria (any observer): status 0
    if no equilibrium other than the principal one is stable, 1 if one is, 2 if there
    is no equilibrium at all, -1 if the analysis is degenerate."""
    other = eq.nonprincipal
    stable = eq.stable & other
    deg = (eq.status == -1) | degenerate
    none = ~deg & (eq.status == 2)
    inf = jnp.any(stable)
    key = jnp.where(stable, jnp.abs(eq.theta), jnp.inf)
    st = eq.theta[jnp.argmin(key)]
    K = eq.valid.shape[-1]
    # move the non-principal equilibria to the front
    order = jnp.argsort(~other, stable=True)[: K - 1]
    theta = jnp.where(other, eq.theta, jnp.nan)[order]
    return DesignClass(
        status=jnp.where(deg, -1, jnp.where(none, 2, jnp.where(inf, 1, 0))).astype(jnp.int32),
        n_nonzero=jnp.where(deg, 0, eq.n_nonzero),
        stable_theta=jnp.where(inf & ~deg, st, jnp.nan),
        theta=jnp.where(deg, jnp.nan, theta),
        stable=stable[order] & ~deg,
        principal_stable=eq.stable[eq.principal] & ~deg,
        principal_theta=jnp.where(deg | none, jnp.nan, eq.theta[eq.principal]))


def _general_classify(w0, i0, zeta1, ratio, zeta2, w2, motor, motor_hat, a, eta, frame,
                      n_grid, max_roots):
    mh = motor if motor_hat is None else motor_hat
    g = eso_gains(psi_a(mh, i0), w0, zeta1, ratio * jnp.abs(w0), zeta2, w2)
    eq = eso_equilibria(w0, i0, g, motor, motor_hat, a=a, eta=eta, frame=frame,
                        n_grid=n_grid, max_roots=max_roots)
    return _class_from_equilibria(eq, ~(ratio > 0))


@eqx.filter_jit
def _general_batch(w0, i0, zeta1, ratio, zeta2, w2, motor, motor_hat, a, eta, frame,
                   n_grid, max_roots):
    fn = lambda *v: _general_classify(*v, motor, motor_hat, a, eta, frame, n_grid,  # noqa: E731
                                      max_roots)
    return jax.vmap(fn)(w0, i0, zeta1, ratio, zeta2, w2)


# ---------------------------------------------------------------------------------------
# Public entry points
# ---------------------------------------------------------------------------------------

def _check_array(owner, name, x, *, nonneg=False, nonzero=False, unit=""):
    a = np.asarray(x, dtype=float)
    u = f" ({unit})" if unit else ""
    if a.size == 0:
        raise ValueError(f"`{owner}({name}=...)`{u} is empty: nothing to evaluate.")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"`{owner}({name}=...)`{u} must be finite; it contains NaN or inf.")
    if nonneg and np.any(a < 0):
        raise ValueError(f"`{owner}({name}=...)`{u} must be >= 0; got min {a.min()!r}.")
    if nonzero and np.any(a == 0):
        raise ValueError(
            f"`{owner}({name}=...)`{u} must not contain 0: the gains (17) contain "
            f"w1^2/w0 and the error dynamics have a continuum of equilibria at standstill."
        )
    return a


def _resolve_method(owner, method, motor_hat, a):
    if method not in METHODS:
        raise ValueError(
            f"`{owner}(method=...)` must be one of {', '.join(map(repr, METHODS))}; "
            f"got {method!r}.")
    linear = isinstance(a, int | float) and float(a) == 1.0
    simple = motor_hat is None and linear
    if method == "closed_form" and not simple:
        raise ValueError(
            f"`{owner}(method='closed_form')` needs matched parameters (motor_hat=None) "
            f"and linear feedback (a=1); use method='general'.")
    return "closed_form" if (method == "auto" and simple) else (
        "general" if method == "auto" else method)


def classify_designs(motor: PMSMParams, w0, i_dq, zeta1, ratio, *, zeta2=1.0,
                     w2=2 * math.pi * 50.0, motor_hat: PMSMParams | None = None, a=1.0,
                     eta=1.0, frame: str = "observer", method: str = "auto",
                     n_grid: int = 256, max_roots: int = 8, dtype=None) -> DesignClass:
    """Classify ESO flux-gain designs at operating points (SI units, any batch shape).

    **Arguments:**

    - `motor`: the plant's `PMSMParams`; `motor_hat`: the observer's model (mismatch),
      default `motor`.
    - `w0`: electrical speed (rad/s), nonzero; `i_dq`: current in the estimator frame
      (A, last axis 2); `zeta1` (-), `ratio` = w1/|w0| (-); `zeta2` (-), `w2` (rad/s).
      All broadcast against each other (`i_dq` without its last axis).
    - `a`, `eta`: fal feedback (`a = 1`: linear). `frame`: `"observer"` or `"paper"`.
    - `method`: `"auto"`, `"closed_form"` or `"general"` (module docstring).
    - `n_grid`, `max_roots`: of the general route. `dtype`: computation dtype (default
      float64; float32 works for the closed form).

    Returns a `DesignClass` with the broadcast batch shape. Concrete inputs are checked
    (empty or NaN raise `ValueError`); `w0 = 0` (the gains zhang2022 (17) contain w1^2/w0 and the
    error dynamics have a continuum of equilibria at standstill) and, under
    `jit`/`vmap`, other bad points get status -1.
    """
    check_frame("classify_designs", frame)
    method = _resolve_method("classify_designs", method, motor_hat, a)
    for name, v in (("w0", w0), ("i_dq", i_dq), ("zeta1", zeta1), ("ratio", ratio),
                    ("zeta2", zeta2), ("w2", w2)):
        if not isinstance(v, jax.core.Tracer):
            _check_array("classify_designs", name, v,
                         nonneg=name in ("zeta1", "ratio", "zeta2", "w2"))
    dtype = jnp.float64 if dtype is None else dtype
    i_dq = jnp.asarray(i_dq, dtype)
    if i_dq.shape[-1:] != (2,):
        raise ValueError(f"`classify_designs(i_dq=...)` must have a last axis of length 2 "
                         f"(i_d, i_q); got shape {i_dq.shape}.")
    w0, zeta1, ratio, zeta2, w2 = (jnp.asarray(v, dtype) for v in (w0, zeta1, ratio, zeta2,
                                                                      w2))
    if method == "closed_form":
        return _closed_form_jit(w0, i_dq[..., 0], i_dq[..., 1], zeta1, ratio, zeta2, w2,
                                jnp.asarray(motor.L_d, dtype), jnp.asarray(motor.L_q, dtype),
                                jnp.asarray(motor.psi_f, dtype), frame=frame)
    # Arrays, not Python floats, so that new parameter values do not recompile.
    motor, motor_hat = as_arrays(motor, dtype), as_arrays(motor_hat, dtype)
    a = 1.0 if (isinstance(a, int | float) and float(a) == 1.0) else jnp.asarray(a, dtype)
    eta = jnp.asarray(eta, dtype)
    shape = jnp.broadcast_shapes(w0.shape, i_dq.shape[:-1], zeta1.shape, ratio.shape,
                                 zeta2.shape, w2.shape)
    flat = [jnp.broadcast_to(v, shape).reshape(-1) for v in (w0, zeta1, ratio, zeta2, w2)]
    i0 = jnp.broadcast_to(i_dq, shape + (2,)).reshape(-1, 2)
    res = _general_batch(flat[0], i0, flat[1], flat[2], flat[3], flat[4], motor, motor_hat,
                         a, eta, frame, n_grid, max_roots)
    return jax.tree_util.tree_map(lambda v: v.reshape(shape + v.shape[1:]), res)


class FeasibilityMap(eqx.Module):
    """A feasibility map over (speed, load, x, y), x and y two named design parameters of
    the observer (zhang2022 Fig. 1: x = zeta1, y = ratio).

    Arrays have shape `(n_speed, n_load, n_x, n_y)` (`theta_deg`, `stable` one more axis
    for the equilibria). Angles in degrees.

    - `status`, `n_nonzero`, `principal_stable`: as in `DesignClass`;
      `principal_theta_deg`: the designed equilibrium's angle (deg; nonzero only with
      mismatch).
    - `stable_theta_deg`: static position error of infeasible designs (deg), else NaN.
    - `theta_deg`, `stable`: every non-designed equilibrium and its stability.
    - `speeds`: speeds (p.u. of `w_rated`); `i_dq`: currents `(n_load, 2)` (p.u. of
      `I_b`); `x`, `y`: the design axes (SI values of the parameters named `x_name`,
      `y_name`); `zeta1`, `ratio` are the same arrays when the axes are zhang2022's.
    - `w_rated` (rad/s), `I_b` (A): the bases used. `method`, `frame`: how it was made;
      `observer`: the registry class name of the observer.
    """

    status: jnp.ndarray
    n_nonzero: jnp.ndarray
    stable_theta_deg: jnp.ndarray
    theta_deg: jnp.ndarray
    stable: jnp.ndarray
    principal_stable: jnp.ndarray
    principal_theta_deg: jnp.ndarray
    speeds: np.ndarray
    i_dq: np.ndarray
    x: np.ndarray
    y: np.ndarray
    w_rated: float
    I_b: float
    method: str = eqx.field(static=True)
    frame: str = eqx.field(static=True)
    x_name: str = eqx.field(static=True, default="zeta1")
    y_name: str = eqx.field(static=True, default="ratio")
    observer: str = eqx.field(static=True, default="LESOObserver")

    def _axis(self, name):
        if self.x_name == name:
            return self.x
        if self.y_name == name:
            return self.y
        raise AttributeError(f"this map's axes are {self.x_name!r} and {self.y_name!r}, "
                             f"not {name!r}")

    @property
    def zeta1(self):
        return self._axis("zeta1")

    @property
    def ratio(self):
        return self._axis("ratio")

    def schedule38(self):
        """The design zhang2022 (38) (`pmsmjax.observers.zhang38`) at each speed as
        `(zeta1, ratio)` arrays of shape (n_speed,): zeta1 (-) and ratio = w1/|w0| (-), a
        single point per speed (at zero speed the limit w0 -> 0)."""
        w0 = np.asarray(self.speeds, dtype=float) * float(self.w_rated)  # rad/s
        w0 = np.where(w0 == 0, np.finfo(float).tiny, w0)  # w1/|w0| -> its limit at 0
        zeta1, w1 = zhang38(w0, float(self.w_rated))
        return np.asarray(zeta1), np.asarray(w1) / np.abs(w0)

    def fraction(self, status: int = 0):
        """Fraction of designs with the given status, per (speed, load)."""
        return np.mean(np.asarray(self.status) == status, axis=(-2, -1))

    def summary(self) -> str:
        """One line per (speed, load): fractions feasible / infeasible / degenerate and
        the range of the static errors."""
        lines = []
        st = np.asarray(self.status)
        th = np.asarray(self.stable_theta_deg)
        for i, s in enumerate(self.speeds):
            for j, cur in enumerate(self.i_dq):
                a = st[i, j]
                t = th[i, j][np.isfinite(th[i, j])]
                rng = (f", static error {t.min():.2f}..{t.max():.2f} deg" if t.size else "")
                lines.append(
                    f"w0 = {s:g} p.u., i_dq = ({cur[0]:g}, {cur[1]:g}) p.u.: feasible "
                    f"{np.mean(a == 0):.1%}, infeasible {np.mean(a == 1):.1%}, degenerate "
                    f"{np.mean(a == -1):.1%}{rng}")
        return "\n".join(lines)


def feasibility_map(drive: Drive, speeds, zeta1, ratio, *, i_dq=(0.0, 0.0),
                    motor_hat: PMSMParams | None = None, zeta2=1.0,
                    w2=2 * math.pi * 50.0, a=1.0, eta=1.0, frame: str = "observer",
                    method: str = "auto", n_grid: int = 256, max_roots: int = 8,
                    dtype=None) -> FeasibilityMap:
    """Feasibility map of the flux-gain design over a `(zeta1, ratio)` grid (Fig. 1).

    **Arguments:**

    - `drive`: a `Drive` (its three-phase motor is the plant; `w_rated` and `base.I_b`
      give the per-unit bases).
    - `speeds`: electrical speeds in p.u. of `drive.w_rated`, 1-D, nonzero.
    - `zeta1`: flux damping values (-), 1-D, >= 0 (the paper: [0, 5]).
    - `ratio`: w1/|w0| values (-), 1-D, >= 0 (the paper: [0, 2]); 0 gives status -1.
    - `i_dq`: controlled current(s) in the estimator frame, p.u. of `drive.base.I_b`:
      `(2,)` or `(n_load, 2)`.
    - `motor_hat`: the observer's model (parameter mismatch), default the plant.
    - `zeta2`, `w2` (rad/s): speed/angle design zhang2022 (25). `a`, `eta` (V s): fal feedback.
    - `frame`, `method`, `n_grid`, `max_roots`, `dtype`: see `classify_designs`.

    One jitted, vmapped call. Returns a `FeasibilityMap`.
    """
    if not isinstance(drive, Drive):
        raise ValueError(f"`feasibility_map(drive=...)` must be a `Drive` (e.g. "
                         f"`pj.preset('zhang750')`); got {type(drive).__name__}.")
    check_frame("feasibility_map", frame)
    _resolve_method("feasibility_map", method, motor_hat, a)
    sp = _check_array("feasibility_map", "speeds", speeds, nonzero=True, unit="p.u.")
    z = _check_array("feasibility_map", "zeta1", zeta1, nonneg=True)
    r = _check_array("feasibility_map", "ratio", ratio, nonneg=True)
    cur = _check_array("feasibility_map", "i_dq", i_dq, unit="p.u.")
    for name, v in (("speeds", sp), ("zeta1", z), ("ratio", r)):
        if v.ndim != 1:
            raise ValueError(f"`feasibility_map({name}=...)` must be 1-D; got shape {v.shape}.")
    cur = cur.reshape(-1, 2) if cur.shape[-1:] == (2,) and cur.ndim <= 2 else None
    if cur is None:
        raise ValueError("`feasibility_map(i_dq=...)` must have shape (2,) or (n_load, 2) "
                         "(i_d, i_q in p.u.).")
    motor = drive.three_phase_motor
    w_r, I_b = float(drive.w_rated), float(drive.base.I_b)
    w0 = (sp * w_r)[:, None, None, None]
    i_si = (cur * I_b)[None, :, None, None, :]
    res = classify_designs(motor, w0, i_si, z[None, None, :, None], r[None, None, None, :],
                           zeta2=zeta2, w2=w2, motor_hat=motor_hat, a=a, eta=eta,
                           frame=frame, method=method, n_grid=n_grid, max_roots=max_roots,
                           dtype=dtype)
    shape = (len(sp), len(cur), len(z), len(r))
    bc = lambda v: jnp.broadcast_to(v, shape + v.shape[len(shape):])  # noqa: E731
    return FeasibilityMap(
        status=bc(res.status), n_nonzero=bc(res.n_nonzero),
        stable_theta_deg=bc(jnp.degrees(res.stable_theta)),
        theta_deg=bc(jnp.degrees(res.theta)), stable=bc(res.stable),
        principal_stable=bc(res.principal_stable),
        principal_theta_deg=bc(jnp.degrees(res.principal_theta)), speeds=sp, i_dq=cur,
        x=z, y=r,
        w_rated=w_r, I_b=I_b, method=_resolve_method("feasibility_map", method, motor_hat, a),
        frame=frame)



# ---------------------------------------------------------------------------------------
# Any observer: classification and maps over two named design parameters
# ---------------------------------------------------------------------------------------

CLASSIFY_METHODS = ("auto", "closed_form", "generic")


def _resolve_classify(owner, observer, plant, method, w_m, i_dq):
    if method not in CLASSIFY_METHODS:
        raise ValueError(f"`{owner}(method=...)` must be one of "
                         f"{', '.join(map(repr, CLASSIFY_METHODS))}; got {method!r}.")
    fast = plant is None and observer.fast_classify(w_m, i_dq) is not None
    if method == "closed_form" and not fast:
        raise ValueError(
            f"`{owner}(method='closed_form')`: {type(observer).__name__} with this design "
            f"has no closed-form classification" + (" with observer-model mismatch"
                                                     if plant is not None else "")
            + "; use method='generic'.")
    return "closed_form" if (fast and method != "generic") else "generic"


def classify(observer, plant=None, w_m=None, i_dq=(0.0, 0.0), *, method: str = "auto",
             **options) -> DesignClass:
    """Feasibility of `observer` at one operating point (any observer, vmappable).

    **Arguments:**

    - `observer`: any `AbstractObserver`; its `motor` is its model.
    - `plant`: the true machine (`PMSMParams`); None = the observer's own model (matched,
      which allows a closed form where the family has one).
    - `w_m`: electrical speed (rad/s); `i_dq`: current in the estimated frame (A).
    - `method`: `"auto"` (the closed form when it applies, else generic),
      `"closed_form"` or `"generic"` (`equilibria`).
    - `options`: passed to `equilibria` (grid, slots, tolerances).

    Returns a `DesignClass` (status 0 feasible, 1 infeasible, 2 no equilibrium, -1
    degenerate; never raises for a bad point).
    """
    from ._generic import _op, check_observer, equilibria_traced

    check_observer("classify", observer)
    if w_m is None:
        raise ValueError("`classify(w_m=...)` (rad/s) is required.")
    dtype = jnp.result_type(w_m, float)
    op = _op(w_m, i_dq, dtype)
    if _resolve_classify("classify", observer, plant, method, op.w_m, op.i_dq) == \
            "closed_form":
        return observer.fast_classify(op.w_m, op.i_dq)
    plant = observer.motor if plant is None else plant
    return _class_from_equilibria(equilibria_traced(observer, plant, op, **options))


def design_map(observer, drive: Drive, speeds, x, y, *, i_dq=(0.0, 0.0), plant=None,
               method: str = "auto", dtype=None, **options) -> FeasibilityMap:
    """Feasibility map of `observer` over two named design parameters (any observer).

    **Arguments:**

    - `observer`: any `AbstractObserver` (e.g. `observers.make_observer("leso", drive)`);
      its `motor` is its model (observer-model mismatch: `observer.with_motor(...)`).
    - `drive`: the `Drive`: its machine is the plant unless `plant` is given, and its
      `w_rated`, `base.I_b` are the per-unit bases.
    - `speeds`: electrical speeds in p.u. of `drive.w_rated`, 1-D.
    - `x`, `y`: `(name, values)` pairs: a design parameter of the observer (its
      `design_units`) and its 1-D values (SI units as there).
    - `i_dq`: current(s) in the estimated frame, p.u. of `drive.base.I_b`: `(2,)` or
      `(n_load, 2)`.
    - `plant`: the true machine; None = the drive's.
    - `method`: `"auto"` uses the family's closed form when the observer's model equals
      the plant's (compared by value) and one exists (zhang2022 (34)-(36) for the ESO/LESO), else
      `"generic"`; `"closed_form"` / `"generic"` force one.
    - `dtype`: computation dtype (default float64). `options`: passed to `equilibria`.

    One jitted, vmapped call over the whole grid. Returns a `FeasibilityMap`.
    """
    from ._generic import check_observer

    check_observer("design_map", observer)
    if not isinstance(drive, Drive):
        raise ValueError(f"`design_map(drive=...)` must be a `Drive`; got "
                         f"{type(drive).__name__}.")
    axes = []
    for arg, pair in (("x", x), ("y", y)):
        if not (isinstance(pair, tuple | list) and len(pair) == 2
                and isinstance(pair[0], str)):
            raise ValueError(f"`design_map({arg}=...)` must be a (name, values) pair; got "
                             f"{pair!r}.")
        name, vals = pair
        if name not in observer.design_units:
            raise ValueError(
                f"`design_map({arg}=...)`: {type(observer).__name__} has no design "
                f"parameter {name!r}; it has {', '.join(observer.design_units)}.")
        v = _check_array("design_map", arg, vals)
        if v.ndim != 1:
            raise ValueError(f"`design_map({arg}=...)` values must be 1-D; got shape "
                             f"{v.shape}.")
        axes.append((name, v))
    (xn, xv), (yn, yv) = axes
    if xn == yn:
        raise ValueError(f"`design_map`: x and y must be different parameters; both are "
                         f"{xn!r}.")
    sp = _check_array("design_map", "speeds", speeds, unit="p.u.")
    cur = _check_array("design_map", "i_dq", i_dq, unit="p.u.")
    if sp.ndim != 1:
        raise ValueError(f"`design_map(speeds=...)` must be 1-D; got shape {sp.shape}.")
    if not (cur.shape[-1:] == (2,) and cur.ndim <= 2):
        raise ValueError("`design_map(i_dq=...)` must have shape (2,) or (n_load, 2) "
                         "(i_d, i_q in p.u.).")
    cur = cur.reshape(-1, 2)
    dtype = jnp.float64 if dtype is None else dtype
    w_r, I_b = float(drive.w_rated), float(drive.base.I_b)
    obs_in, plant_in, resolved = _design_map_setup(observer, drive, sp, (xn, xv), (yn, yv),
                                                   cur, plant, method, dtype)
    grid = np.stack(np.meshgrid(sp * w_r, np.arange(len(cur)), xv, yv, indexing="ij"),
                    -1).reshape(-1, 4)
    i_all = (cur * I_b)[grid[:, 1].astype(int)]
    res = _design_map_batch(obs_in, plant_in,
                            jnp.asarray(grid[:, 0], dtype), jnp.asarray(i_all, dtype),
                            jnp.asarray(grid[:, 2], dtype), jnp.asarray(grid[:, 3], dtype),
                            xn, yn, resolved, options)
    shape = (len(sp), len(cur), len(xv), len(yv))
    res = jax.tree_util.tree_map(lambda v: v.reshape(shape + v.shape[1:]), res)
    return FeasibilityMap(
        status=res.status, n_nonzero=res.n_nonzero,
        stable_theta_deg=jnp.degrees(res.stable_theta), theta_deg=jnp.degrees(res.theta),
        stable=res.stable, principal_stable=res.principal_stable,
        principal_theta_deg=jnp.degrees(res.principal_theta), speeds=sp, i_dq=cur,
        x=xv, y=yv, w_rated=w_r, I_b=I_b, method=resolved, frame="observer",
        x_name=xn, y_name=yn, observer=type(observer).__name__)


def _design_map_setup(observer, drive, sp, x, y, cur, plant, method, dtype):
    """What `design_map` evaluates at each point: `(observer, plant, method)` for
    `_design_point` (the closed form or the generic route, resolved on a probe design)."""
    (xn, xv), (yn, yv) = x, y
    w_r, I_b = float(drive.w_rated), float(drive.base.I_b)
    plant_ = drive.three_phase_motor if plant is None else plant
    # the closed form needs the observer's model to be the plant's
    matched = bool(eqx.tree_equal(as_arrays(plant_, dtype), as_arrays(observer.motor, dtype)))
    # probe the design's structure with the largest values (a zero, allowed on an axis,
    # is refused by some design constructors outside a trace)
    probe = observer.with_design(**{xn: float(np.max(xv)), yn: float(np.max(yv))})
    resolved = _resolve_classify("design_map", probe, None if matched else plant_, method,
                                 jnp.asarray(sp[0] * w_r, dtype),
                                 jnp.asarray(cur[0] * I_b, dtype))
    # (the closed form decides on the design's structure, e.g. n2 = n3 = 0, so the
    # observer's Python-number leaves stay concrete there)
    obs_in = observer if resolved == "closed_form" else as_arrays(observer, dtype)
    return obs_in, as_arrays(plant_, dtype), resolved


def _design_point(observer, plant, w, i, a, b, xn, yn, method, options) -> DesignClass:
    """Classification of one design `xn = a`, `yn = b` at speed `w` (rad/s) and current
    `i` (A): the body of `design_map` (and of the command line's sweep of it)."""
    from ._generic import OperatingPoint, equilibria_traced

    obs = observer.with_design(**{xn: a, yn: b})
    if method == "closed_form":
        return obs.fast_classify(w, i)
    eq = equilibria_traced(obs, plant, OperatingPoint(w, i), **options)
    return _class_from_equilibria(eq)


@eqx.filter_jit
def _design_map_batch(observer, plant, w0, i0, xv, yv, xn, yn, method, options):
    def one(w, i, a, b):
        return _design_point(observer, plant, w, i, a, b, xn, yn, method, options)

    return jax.vmap(one)(w0, i0, xv, yv)
