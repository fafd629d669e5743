r"""Equilibria of the zhang2022 ESO/LESO error dynamics (11) at constant speed.

Two routes, which agree where both apply (tests):

1. **General route** (`eso_equilibria`): every equilibrium of the full nonlinear
   right-hand side, with parameter mismatch and with linear or fal feedback.
2. **Quartic route** (`quartic_equilibria`, `pmsmjax.analysis._quartic`): the paper's
   closed form zhang2022 (34)-(36), matched parameters and linear feedback only.

**Reduction used by the general route.** Write $f = \eta^{1-a}\mathrm{fal}(e)$ for the
feedback ($f = e$ when $a = 1$). At an equilibrium $\dot{\tilde\omega} = 0$ gives
$g_3 f = 0$, so $f = s\,u$ for a scalar $s$ and the unit vector $u = J g_3^T/\|g_3\|$
($u \parallel \psi_{a0}$ for the gains (25)); $\dot{\tilde\theta} = 0$ gives
$\tilde\omega = g_2 f$, so the frame speed is exactly $\omega_0$ (in both frame
conventions when $g_2 \parallel g_3$; always in the observer's), and the flux equation
becomes $\omega_0 J\tilde\psi + s\,G_1 u + \Delta R\, i_0 = 0$, i.e.
$\tilde\psi = J(s\,G_1 u + \Delta R\, i_0)/\omega_0$ ($\Delta R = R_s - \hat R_s$).
With $e = e_0(\tilde\theta) + \tilde\psi$ ($e_0$ = `error_signal(0, theta, ...)`, which
contains the inductance and flux mismatch) and $e = \mathrm{fal}^{-1}(s\,u\,\eta^{a-1})
=: E(s)$ this leaves two equations in $(\tilde\theta, s)$:

$$b(\tilde\theta) := e_0(\tilde\theta) + J\Delta R\, i_0/\omega_0
  = E(s) - s\,J G_1 u/\omega_0 =: c(s).$$

Component along $u$: $\varphi(s) := u\cdot c(s) = u\cdot b(\tilde\theta)$. Since fal is
odd and increasing with slope $\le\eta^{a-1}$, $u\cdot E'(s) \ge 1$, and with the gains
zhang2022 (17) $u\cdot JG_1u = -(\omega_1^2/\omega_0 - \omega_0)$, so
$\varphi'(s) \ge \kappa := 1 - u\cdot JG_1 u/\omega_0 = \omega_1^2/\omega_0^2 > 0$:
$\varphi$ is strictly increasing, $s(\tilde\theta)$ is unique and lies in
$[0, u\cdot b/\kappa]$ (closed form $s = u\cdot b/\kappa$ for linear feedback). The
equilibria are then exactly the zeros on $(-\pi, \pi]$ of the scalar function

$$r(\tilde\theta) = Ju\cdot\big(b(\tilde\theta) - c(s(\tilde\theta))\big).$$

For linear feedback $r$ is a trigonometric polynomial of degree 2 in $\tilde\theta$
(with or without mismatch), so it has at most 4 zeros unless it vanishes identically.
With matched parameters it equals, up to a constant factor,
$Ju\cdot e_0 + (2\zeta_1\omega_0/\omega_1)\,u\cdot e_0$: the left side of zhang2022 (34).

The zeros are bracketed by sign changes of $r$ on a periodic grid offset by half a step
(so $\tilde\theta = 0, \pi$ are never grid points), and each bracket is refined by
bisection until it is below tolerance or at rounding level (plus one Newton step),
vmapped over brackets with a fixed number of slots and a validity mask. Two zeros
closer than a grid step leave no sign change of $r$ but a sign change of $r'$
(`jax.grad`) in their cell: such a cell is refined to the extremum
$r'(\tilde\theta_c) = 0$ (plain bisection on $r'$); if $r(\tilde\theta_c)$ has the
opposite sign both halves are bracketed, and if it is zero (to tolerance) the double
zero is reported as a `tangent` equilibrium (a saddle-node: its Jacobian is singular, so
it is never classified stable). Tangencies are the boundary between 1 and 3 nonzero
equilibria, a measure-zero set of designs. Not resolved: more than two zeros, or two
extrema, inside one grid cell (a cusp; refine `n_grid`).

**Stability** of each equilibrium from the Jacobian zhang2022 (37) (`jax.jacfwd` of the error
dynamics, in the frame convention `frame`), by the exact Routh-Hurwitz test on its
characteristic polynomial (`routh_hurwitz`), after the similarity and time scaling
$\mathrm{diag}(1/|\psi_{a0}|, 1/|\psi_{a0}|, 1, 1/|\omega_0|)$, $1/|\omega_0|$ (which
change no sign of a real part and keep the entries O(1)).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._frames import jmul, wrap_angle
from .._plant._params import PMSMParams
from ..observers import ESOGains, error_signal, psi_a
from ._args import as_arrays
from ._linearize import charpoly, check_frame, eso_rhs, routh_hurwitz


class Equilibria(eqx.Module):
    """All equilibria of the ESO error dynamics at one operating point and design.

    Arrays have a trailing axis of `max_roots` slots (plus any batch axes in front);
    slots with `valid = False` hold NaN. Valid equilibria come first, sorted by angle.

    - `theta`: angle error of each equilibrium, wrapped to (-pi, pi] (rad).
    - `x`: the full state `[psi_err_d, psi_err_q, theta_err, w_err]` (V s, V s, rad,
      rad/s), shape `(..., max_roots, 4)`.
    - `valid`: slot holds an equilibrium.
    - `stable`: its Jacobian zhang2022 (37) is Hurwitz (Routh-Hurwitz).
    - `tangent`: a double zero of the reduced function (saddle-node; never stable).
    - `residual`: max |f(x)| after the scaling of the module docstring (dimensionless;
      ~1e-12 or less in float64).
    - `principal`: index of the equilibrium closest to `theta = 0` (the designed one;
      exactly 0 with matched parameters).
    - `n`: number of equilibria; `n_nonzero = n - 1` (all but the principal one). With
      parameter mismatch `n = 0` happens (e.g. a large resistance error at low speed):
      there is no equilibrium and the angle error drifts for ever.
    - `status`: 0 ok, 2 no equilibrium at all (possible with observer-model mismatch),
      -1 degenerate or failed (w0 = 0, w1 = 0, psi_a0 = 0, the reduction's kappa <= 0
      for non-designed gains, non-finite values, more zeros than slots, or a refinement
      that did not converge).
    - `jacobian`: the Jacobian of the error dynamics at each equilibrium (SI units, time
      in s), `(..., max_roots, n, n)`; NaN in invalid slots.
    """

    theta: jnp.ndarray
    x: jnp.ndarray
    valid: jnp.ndarray
    stable: jnp.ndarray
    tangent: jnp.ndarray
    residual: jnp.ndarray
    principal: jnp.ndarray
    n: jnp.ndarray
    status: jnp.ndarray
    jacobian: jnp.ndarray

    @property
    def n_nonzero(self):
        return jnp.maximum(self.n - 1, 0)

    @property
    def nonprincipal(self):
        """Mask of valid equilibria other than the principal one."""
        k = jnp.arange(self.valid.shape[-1])
        return self.valid & (k != self.principal[..., None])


def _tol(dtype):
    return float(jnp.finfo(dtype).eps) ** 0.75


def _fal_inv(y, a, eta):
    """Inverse of fal (element-wise): y eta^(1-a) for |y| <= eta^a, sign(y)|y|^(1/a)."""
    big = jnp.abs(y) > eta ** a
    safe = jnp.where(big, jnp.abs(y), 1.0)
    return jnp.where(big, jnp.sign(y) * safe ** (1.0 / a), y * eta ** (1.0 - a))


class _Reduction(eqx.Module):
    """The pieces of the reduction r(theta) (see the module docstring)."""

    w0: jnp.ndarray
    i0: jnp.ndarray
    gains: ESOGains
    motor: PMSMParams
    motor_hat: PMSMParams
    a: jnp.ndarray
    eta: jnp.ndarray
    linear: bool = eqx.field(static=True)
    u: jnp.ndarray
    JG1u: jnp.ndarray
    kappa: jnp.ndarray
    scale: jnp.ndarray  # flux scale |psi_a0| of the observer (V s)

    def b(self, theta):
        e0 = error_signal(jnp.zeros(2, self.u.dtype), theta, self.i0, self.motor,
                          self.motor_hat)
        dR = self.motor.R_s - self.motor_hat.R_s
        return e0 + jmul(dR * self.i0) / self.w0

    def c(self, s):
        E = s * self.u if self.linear else _fal_inv(
            s * self.u * self.eta ** (self.a - 1.0), self.a, self.eta)
        return E - s * self.JG1u / self.w0

    def s_of(self, ub):
        """Unique s with u.c(s) = ub (monotone; closed form for linear feedback)."""
        if self.linear:
            return ub / self.kappa
        phi = lambda s, ub: jnp.dot(self.u, self.c(s)) - ub  # noqa: E731
        ub0 = jax.lax.stop_gradient(ub)
        lo = jnp.minimum(0.0, ub0 / self.kappa)
        hi = jnp.maximum(0.0, ub0 / self.kappa)
        eps = jnp.finfo(lo.dtype).eps

        # Safeguarded Newton: a Newton step is taken only if it stays in the bracket
        # and the last one at least halved |phi|; otherwise bisect. It stops when a step
        # or the bracket is at rounding level: at most 9 iterations on all but 8 of the
        # 102,400 points of tests/test_contract.py's fal designs, at most 37 (under vmap
        # the loop runs as long as the slowest point; at most 60, bisection speed).
        def body(carry):
            k, s, lo, hi, prev, _ = carry
            f, df = jax.jvp(lambda s_: phi(s_, ub0), (s,), (jnp.ones_like(s),))
            lo = jnp.where(f < 0, s, lo)
            hi = jnp.where(f < 0, hi, s)
            sn = s - f / jnp.where(df > 0, df, 1.0)
            # (in fal's linear zone the root is the bracket's end: a step onto it, or past
            # it by rounding, counts as inside)
            tiny = 4.0 * eps * jnp.abs(s)
            edge = 4.0 * eps * jnp.maximum(jnp.abs(lo), jnp.abs(hi))
            newton = (sn >= lo - edge) & (sn <= hi + edge) & (df > 0) \
                & (jnp.abs(f) <= 0.5 * prev)
            # converged: the Newton step is at rounding level, or the bracket is
            step_done = (df > 0) & (jnp.abs(sn - s) <= tiny)
            done = (f == 0) | step_done | (hi - lo <= tiny)
            s_new = jnp.where(newton | step_done, jnp.clip(sn, lo, hi), 0.5 * (lo + hi))
            return k + 1, jnp.where(f == 0, s, s_new), lo, hi, jnp.abs(f), done

        carry = (jnp.zeros((), jnp.int32), 0.5 * (lo + hi), lo, hi,
                 jnp.asarray(jnp.inf, lo.dtype), jnp.zeros((), bool))
        s = jax.lax.while_loop(lambda c: (c[0] < 60) & ~c[5], body, carry)[1]
        # The loop is not differentiated: one Newton step from its (constant) root carries
        # the derivative of the implicit function s(ub) (ds/dub = 1/phi'(s), since
        # phi(s) = 0 there) and polishes the value.
        f, df = jax.jvp(lambda s_: phi(s_, ub), (s,), (jnp.ones_like(s),))
        return s - f / jnp.where(df > 0, df, 1.0)

    def r(self, theta):
        """Reduced scalar function, divided by the flux scale (dimensionless)."""
        b = self.b(theta)
        s = self.s_of(jnp.dot(self.u, b))
        return jnp.dot(jmul(self.u), b - self.c(s)) / self.scale

    def state(self, theta):
        """Full equilibrium state x = [psi_err, theta, w_err] for a zero of r."""
        b = self.b(theta)
        s = self.s_of(jnp.dot(self.u, b))
        dR = self.motor.R_s - self.motor_hat.R_s
        psi = jmul(s * (self.gains.G1 @ self.u) + dR * self.i0) / self.w0
        w_err = jnp.dot(self.gains.g2, s * self.u)
        return jnp.concatenate([psi, jnp.stack([theta, w_err])])


def _make_reduction(w0, i0, gains, motor, motor_hat, a, eta, linear):
    g3 = gains.g3
    ng3 = jnp.sqrt(jnp.sum(g3 ** 2))
    u = jmul(g3) / jnp.where(ng3 > 0, ng3, 1.0)
    JG1u = jmul(gains.G1 @ u)
    w0s = jnp.where(w0 == 0, 1.0, w0)
    kappa = 1.0 - jnp.dot(u, JG1u) / w0s
    scale = jnp.sqrt(jnp.sum(psi_a(motor_hat, i0) ** 2))
    red = _Reduction(w0=w0s, i0=i0, gains=gains, motor=motor, motor_hat=motor_hat,
                     a=jnp.asarray(a, u.dtype), eta=jnp.asarray(eta, u.dtype),
                     linear=linear, u=u, JG1u=JG1u, kappa=jnp.where(kappa > 0, kappa, 1.0),
                     scale=jnp.where(scale > 0, scale, 1.0))
    ok = (w0 != 0) & (ng3 > 0) & (kappa > 0) & (scale > 0)
    return red, ok


def _bisect(fn, lo, hi, valid, tol, max_steps=200):
    """Vmapped bisection on brackets [lo, hi] of a scalar function fn(theta).

    The function is normalised so that it is <= 0 at `lo`; invalid slots get a dummy
    linear function. A bracket is done when it is narrower than `tol` with |f| below
    `tol` at its last midpoint (the test of `optimistix.Bisection`), or when it has collapsed
    to rounding level while |f| stays above `tol` (a steep zero, e.g. with fal feedback,
    where |f| at the last representable angle can exceed `tol`): the loop ends when every
    bracket is done, not after `max_steps` for all of them as soon as one zero is steep.
    Returns (root, converged).
    """
    def collapsed(lower, upper, y):
        return jnp.abs(upper - lower) <= 64 * jnp.finfo(y.dtype).eps * (1.0 + jnp.abs(y))

    def one(lo_, hi_, ok):
        sgn = jnp.where(fn(lo_) > 0, -1.0, 1.0).astype(lo_.dtype)
        g = lambda y: jnp.where(ok, sgn * fn(y), y - 0.5 * (lo_ + hi_))  # noqa: E731

        def body(c):
            k, y, lower, upper, _ = c
            err = g(y)
            lower, upper = jnp.where(err < 0, y, lower), jnp.where(err < 0, upper, y)
            return k + 1, lower + 0.5 * (upper - lower), lower, upper, err

        def done(c):
            _, y, lower, upper, err = c
            small = (jnp.abs(upper - lower) < tol) & (jnp.abs(err) < tol)
            return small | collapsed(lower, upper, y)

        inf = jnp.asarray(jnp.inf, lo_.dtype)
        c = jax.lax.while_loop(lambda c: (c[0] < max_steps) & ~done(c), body,
                               (jnp.zeros((), jnp.int32), 0.5 * (lo_ + hi_), lo_, hi_, inf))
        y, conv = c[1], done(c)
        # one Newton step polishes the bisection tolerance to rounding level
        fy, dfy = jax.jvp(fn, (y,), (jnp.ones_like(y),))
        yn = y - fy / jnp.where(dfy != 0, dfy, 1.0)
        y = jnp.where((dfy != 0) & (yn >= lo_) & (yn <= hi_) & ok, yn, y)
        return y, conv

    return jax.vmap(one)(lo, hi, valid)


def _plain_bisect(fn, lo, hi, n_iter=60):
    """Fixed-iteration vectorised bisection (for the rare critical-point brackets of r',
    where a second convergence-tested loop is not worth its compile time). Any sign of
    fn(lo)."""
    s_lo = jax.vmap(fn)(lo) >= 0

    def body(_, c):
        a, b = c
        m = 0.5 * (a + b)
        same = (jax.vmap(fn)(m) >= 0) == s_lo
        return jnp.where(same, m, a), jnp.where(same, b, m)

    a, b = jax.lax.fori_loop(0, n_iter, body, (lo, hi))
    return 0.5 * (a + b)


def _wrapdist(a, b):
    return jnp.abs(wrap_angle(a - b))


def _finish(red: _Reduction, theta, valid, tangent, frame, a, eta, ok):
    """From candidate angles to an `Equilibria`: states, residuals, stability, sorting."""
    K = theta.shape[0]
    theta = wrap_angle(jnp.where(valid, theta, 0.0))
    # drop duplicates (a zero exactly on a grid point can be bracketed twice)
    close = _wrapdist(theta[:, None], theta[None, :]) < 1e-7
    earlier = jnp.tril(jnp.ones((K, K), bool), -1)
    dup = jnp.any(close & earlier & valid[None, :], axis=1)
    valid = valid & ~dup
    x = jax.vmap(red.state)(theta)
    w0 = red.w0
    d = jnp.stack([1 / red.scale, 1 / red.scale, jnp.ones_like(red.scale),
                   1 / jnp.abs(w0)])
    mh = red.motor_hat

    def rhs(xx):
        return eso_rhs(xx, w0, red.i0, red.gains, red.motor, mh, a, eta, frame)

    f = jax.vmap(rhs)(x)
    residual = jnp.max(jnp.abs(f * d / jnp.abs(w0)), axis=-1)
    A_si = jax.vmap(jax.jacfwd(rhs))(x)
    A = A_si * d[:, None] / d[None, :] / jnp.abs(w0)
    stable = routh_hurwitz(charpoly(A)) & ~tangent
    finite = jnp.all(jnp.isfinite(x), -1) & jnp.isfinite(residual)
    bad = valid & ~finite
    valid = valid & finite
    order = jnp.argsort(jnp.where(valid, theta, jnp.inf))
    theta, x, valid, stable, tangent, residual, A_si = (
        v[order] for v in (theta, x, valid, stable, tangent, residual, A_si))
    n = jnp.sum(valid)
    principal = jnp.argmin(jnp.where(valid, jnp.abs(theta), jnp.inf))
    nan = jnp.nan
    status = jnp.where(ok & ~jnp.any(bad), jnp.where(n == 0, 2, 0), -1).astype(jnp.int32)
    return Equilibria(
        theta=jnp.where(valid, theta, nan), x=jnp.where(valid[:, None], x, nan),
        valid=valid, stable=stable & valid, tangent=tangent & valid,
        residual=jnp.where(valid, residual, nan), principal=principal.astype(jnp.int32),
        n=n.astype(jnp.int32), status=status,
        jacobian=jnp.where(valid[:, None, None], A_si, nan))


def eso_equilibria(w0, i0, gains: ESOGains, motor: PMSMParams,
                   motor_hat: PMSMParams | None = None, *, a=1.0, eta=1.0,
                   frame: str = "observer", n_grid: int = 256, max_roots: int = 8,
                   n_crit: int = 8) -> Equilibria:
    r"""Every equilibrium of the ESO error dynamics zhang2022 (11) at constant speed (general
    route).

    **Arguments:**

    - `w0`: electrical speed (rad/s), nonzero.
    - `i0`: controlled current in the estimator frame (A, `(2,)`).
    - `gains`: the observer's `ESOGains` (computed from the observer's model).
    - `motor`: plant parameters; `motor_hat`: observer's model (default `motor`).
    - `a`, `eta`: fal exponent in (0, 1] and linear-zone half-width (V s); `a = 1` is
      the linear feedback (LESO), any `eta`.
    - `frame`: `"observer"` or `"paper"` (see `eso_rhs`); only stability depends on it.
    - `n_grid`: bracketing grid on (-pi, pi] (static). `max_roots`: output slots
      (static; 4 suffice for linear feedback). `n_crit`: slots for close-pair detection.

    Pure and vmappable (all shapes static); failures are reported in `status`, never
    raised. See the module docstring for the method.

    !!! note
        The reduction needs $\kappa = 1 - u\cdot JG_1u/\omega_0 > 0$, which makes its
        scalar equation in $s$ monotone. The minimum-norm gains zhang2022 (25) give
        $\kappa = \omega_1^2/\omega_0^2 > 0$; null-space components of zhang2022 (19)
        (`ESODesign(n2=..., n3=...)`) rotate $u$ away from $\psi_{a0}$ and can make
        $\kappa \le 0$ (mostly with $\zeta_1 > 1$): then $s(\tilde\theta)$ need not
        be unique and this route reports status -1 instead of guessing. The generic
        route (`analysis.equilibria`) has no such condition and handles those gains
        (tested against a multi-start `scipy.optimize.fsolve`).
    """
    check_frame("eso_equilibria", frame)
    if not isinstance(n_grid, int) or n_grid < 16:
        raise ValueError(f"`eso_equilibria(n_grid=...)` must be an int >= 16; got {n_grid!r}.")
    if not isinstance(max_roots, int) or max_roots < 2:
        raise ValueError(
            f"`eso_equilibria(max_roots=...)` must be an int >= 2; got {max_roots!r}.")
    if not isinstance(n_crit, int) or n_crit < 1:
        raise ValueError(f"`eso_equilibria(n_crit=...)` must be an int >= 1; got {n_crit!r}.")
    motor_hat = motor if motor_hat is None else motor_hat
    linear = isinstance(a, int | float) and float(a) == 1.0
    dtype = jnp.result_type(w0, gains.G1, float)
    w0, i0, gains, motor, motor_hat, a_, eta = as_arrays(
        (w0, i0, gains, motor, motor_hat, a, eta), dtype)
    return _eso_equilibria(w0, i0, gains, motor, motor_hat, 1.0 if linear else a_, eta,
                           frame, n_grid, max_roots, n_crit)


@eqx.filter_jit
def _eso_equilibria(w0, i0, gains, motor, motor_hat, a, eta, frame, n_grid, max_roots,
                    n_crit):
    linear = isinstance(a, float)
    dtype = w0.dtype
    red, ok = _make_reduction(w0, i0, gains, motor, motor_hat, a, eta, linear)
    tol = _tol(dtype)

    N = n_grid
    h = 2 * math.pi / N
    grid = -math.pi + h * (jnp.arange(N, dtype=dtype) + 0.5)
    rv = jax.vmap(red.r)(grid)
    ok = ok & jnp.all(jnp.isfinite(rv))
    rmax = jnp.max(jnp.abs(rv))
    rmax = jnp.where(rmax > 0, rmax, 1.0)
    rn = lambda t: red.r(t) / rmax
    rv = rv / rmax
    nxt = jnp.roll(rv, -1)
    # sign-change brackets [grid_k, grid_k + h] (periodic)
    sc = (rv >= 0) != (nxt >= 0)
    (idx,) = jnp.nonzero(sc, size=max_roots, fill_value=0)
    n_sc = jnp.sum(sc)
    ok = ok & (n_sc <= max_roots)
    slot = jnp.arange(max_roots) < n_sc
    lo = grid[idx]

    # close pairs: a cell without a sign change of r but with one of r' holds an
    # extremum of r; if r changes sign there, the cell holds two zeros.
    drn = jax.grad(rn)
    dv = jax.vmap(drn)(grid)
    ext = ~sc & ((dv >= 0) != (jnp.roll(dv, -1) >= 0))
    (cidx,) = jnp.nonzero(ext, size=n_crit, fill_value=0)
    cslot = jnp.arange(n_crit) < jnp.sum(ext)
    ok = ok & (jnp.sum(ext) <= n_crit)
    clo = grid[cidx]
    chi = clo + h
    thc = _plain_bisect(drn, clo, chi)
    rc = jax.vmap(rn)(thc)
    tangent_c = cslot & (jnp.abs(rc) < 1e2 * tol)
    split = cslot & ~tangent_c & ((rc >= 0) != (rv[cidx] >= 0))

    # one vmapped bisection over every bracket: sign changes, then both halves of splits
    blo = jnp.concatenate([lo, clo, thc])
    bhi = jnp.concatenate([lo + h, thc, chi])
    bvalid = jnp.concatenate([slot, split, split])
    th_b, conv = _bisect(rn, blo, bhi, bvalid, tol)
    ok = ok & jnp.all(conv | ~bvalid)

    theta = jnp.concatenate([th_b, thc])
    valid = jnp.concatenate([bvalid, tangent_c])
    tangent = jnp.concatenate([jnp.zeros(max_roots + 2 * n_crit, bool), tangent_c])
    ok = ok & (jnp.sum(valid) <= max_roots)
    # compact to max_roots slots
    order = jnp.argsort(~valid, stable=True)[:max_roots]
    eq = _finish(red, theta[order], valid[order], tangent[order], frame, a, eta, ok)
    return eq
