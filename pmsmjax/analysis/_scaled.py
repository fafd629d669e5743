r"""The scaled error system of an observer at an operating point, and the small dense
linear algebra its solves use (`pmsmjax.analysis._generic`'s equilibria).

**Scaling.** All tests and tolerances work on the scaled system
$F(z) = f(Dz)/(D\,\Omega)$ with $D$ = `observer.error_scale(op, plant)` and the rate
$\Omega = |\omega_0|$ (1 rad/s at standstill): a positive similarity and time scaling,
which changes no sign of a real part and keeps the entries O(1).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .._frames import wrap_angle
from .._plant._params import PMSMParams
from ..observers import AbstractObserver, OperatingPoint


# ---------------------------------------------------------------------------------------
# Small dense linear algebra as loops over the matrix size (element-wise over any vmapped
# batch, so it fuses under vmap instead of calling LAPACK per point). Written as
# `lax.fori_loop`s rather than unrolled at trace time: unrolled, the elimination is a deep
# graph of scalar operations with much reuse, whose XLA compile time grew steeply with the
# size (the 10-state GI-LESO took over 17 minutes to compile; BENCHMARKS.md).
# ---------------------------------------------------------------------------------------

def _chol_solve(H, g):
    """Solve H x = g for a small symmetric positive definite H `(m, m)` (Cholesky;
    a non-positive pivot is clamped to 1e-300). Returns `(x, log det H)`."""
    m = H.shape[-1]
    idx = jnp.arange(m)

    def factor(j, L):
        # column j of L: the rows of L beyond column j - 1 are still zero
        col = H[:, j] - L @ L[j, :]
        d = jnp.sqrt(jnp.maximum(col[j], 1e-300))
        return L.at[:, j].set(jnp.where(idx > j, col / d, jnp.where(idx == j, d, 0.0)))

    L = jax.lax.fori_loop(0, m, factor, jnp.zeros_like(H))
    diag = jnp.diagonal(L)

    def forward(i, y):
        return y.at[i].set((g[i] - L[i, :] @ y) / diag[i])

    def backward(k, x):
        i = m - 1 - k
        return x.at[i].set((y[i] - L[:, i] @ x) / diag[i])

    y = jax.lax.fori_loop(0, m, forward, jnp.zeros_like(g))
    x = jax.lax.fori_loop(0, m, backward, jnp.zeros_like(g))
    return x, 2.0 * jnp.sum(jnp.log(diag))


def _det(M):
    """Determinant of a small square matrix `(m, m)` by elimination with partial
    pivoting."""
    m = M.shape[-1]
    idx = jnp.arange(m)

    def body(k, c):
        R, det = c
        p = jnp.argmax(jnp.where(idx >= k, jnp.abs(R[:, k]), -1.0))
        pivot_row, row_k = R[p], R[k]
        R = R.at[p].set(row_k).at[k].set(pivot_row)
        pv = pivot_row[k]
        det = det * jnp.where(p == k, 1.0, -1.0) * pv
        piv = jnp.where(pv != 0, pv, 1.0)
        R = R - jnp.where(idx > k, R[:, k] / piv, 0.0)[:, None] * pivot_row[None, :]
        return R, det

    _, det = jax.lax.fori_loop(0, m, body, (M, jnp.ones((), M.dtype)))
    return det


# ---------------------------------------------------------------------------------------
# The scaled system
# ---------------------------------------------------------------------------------------

class _Scaled(eqx.Module):
    observer: AbstractObserver
    plant: PMSMParams
    op: OperatingPoint
    scale: jnp.ndarray
    rate: jnp.ndarray
    weight: jnp.ndarray
    angle: int = eqx.field(static=True)

    def F(self, z):
        return self.observer.error_rhs(z * self.scale, self.op, self.plant) / (
            self.scale * self.rate)

    def insert(self, theta, y):
        a = self.angle
        return jnp.concatenate([y[:a], theta[None], y[a:]])

    def drop(self, z):
        a = self.angle
        return jnp.concatenate([z[:a], z[a + 1:]])

    def Fw(self, theta, y):
        return self.F(self.insert(theta, y)) * self.weight

    def gauss_newton_step(self, Fv, Jy):
        """One Gauss-Newton step for the other coordinates at a fixed angle error, from
        the weighted `F` and its Jacobian `J_y` at the current point, with the angle row
        as an equality constraint (null-space method): it solves
        min ||F_o + J_o d|| subject to F_a + J_a d = 0, so that the solution follows the
        branch on which the estimated frame turns at the true speed. Returns the step d
        (a full step: the iteration takes it undamped)."""
        m = Jy.shape[1]
        a = self.angle
        dtype = Jy.dtype
        eye = jnp.eye(m, dtype=dtype)
        e0 = eye[0]
        Fa, Ja = Fv[a], Jy[a]
        Fo = jnp.concatenate([Fv[:a], Fv[a + 1:]])
        Jo = jnp.concatenate([Jy[:a], Jy[a + 1:]], 0)
        nrm = jnp.sqrt(jnp.sum(Ja ** 2))
        ok = nrm > 1e-12 * (1.0 + jnp.max(jnp.abs(Jo)))
        nrm_s = jnp.where(ok, nrm, 1.0)
        # Householder reflector mapping Ja to a multiple of e0: its other columns span the
        # null space of Ja
        sg = jnp.where(Ja[0] >= 0, 1.0, -1.0)
        v = Ja / nrm_s + sg * e0
        Hh = eye - 2.0 * jnp.outer(v, v) / jnp.sum(v * v)
        N = Hh[:, 1:]
        dp = jnp.where(ok, -Fa * Ja / nrm_s ** 2, jnp.zeros_like(Ja))
        B = Jo @ N
        G = B.T @ B
        t, _ = _chol_solve(G + (1e-13 * jnp.trace(G) + 1e-300) * jnp.eye(m - 1, dtype=dtype),
                           -B.T @ (Fo + Jo @ dp))
        d_con = dp + N @ t
        # without a usable constraint: plain Gauss-Newton on every row
        H = Jy.T @ Jy
        d_gn, _ = _chol_solve(H + (1e-13 * jnp.trace(H) + 1e-300) * eye, -Jy.T @ Fv)
        return jnp.where(ok, d_con, d_gn)

    def solve_y(self, theta, y, n_iter, n_active=None):
        """`n_iter` Gauss-Newton steps (`gauss_newton_step`) for the other coordinates at
        the angle error `theta` from `y`; `n_active` (may be traced, <= `n_iter`): only
        the first `n_active` steps act. Returns `(y, r, Fa)`: the result, the signed
        residual `r(theta, y)` and the (unweighted) angle row of `F` there.

        One scan of `n_iter + 1` evaluations of F and its Jacobian (the last one for `r`
        only), so the error dynamics are traced once per call site: the compile time of
        the generic route grows with the number of places that trace them."""
        active = n_iter if n_active is None else jnp.minimum(n_active, n_iter)

        def body(y, k):
            Fv, Jy = self._FJ(theta, y)
            y_new = jnp.where(k < active, y + self.gauss_newton_step(Fv, Jy), y)
            return y_new, self._r(Fv, Jy)

        y, (r, fa) = jax.lax.scan(body, y, jnp.arange(n_iter + 1))
        return y, r[-1], fa[-1]

    def _FJ(self, theta, y):
        f = lambda v: self.Fw(theta, v)  # noqa: E731
        Fv, jvp = jax.linearize(f, y)
        Jy = jax.vmap(jvp, out_axes=1)(jnp.eye(y.shape[0], dtype=y.dtype))
        return Fv, Jy

    def _r(self, Fv, Jy):
        """The signed least-squares residual r and the (unweighted) angle row of F, from
        the weighted F and J_y at a point."""
        H = Jy.T @ Jy
        _, logdet = _chol_solve(H + 1e-300 * jnp.eye(H.shape[0], dtype=H.dtype),
                                jnp.zeros(H.shape[0], H.dtype))
        r = _det(jnp.concatenate([Jy, Fv[:, None]], 1)) * jnp.exp(-0.5 * logdet)
        return r, Fv[self.angle] / self.weight[self.angle]

    def newton(self, z, n_iter):
        """`n_iter` Newton steps on the full square system F(z) = 0 (normal equations),
        then the angle coordinate wrapped to (-pi, pi]. Returns `(z, F(z), dF/dz(z))` at
        the result: one scan of `n_iter + 1` evaluations of F and its Jacobian (the last
        one for the residual and the stability test only), so the error dynamics are
        traced once here."""
        n = z.shape[0]
        eye = jnp.eye(n, dtype=z.dtype)
        a = self.angle

        def body(z, k):
            z = jnp.where(k < n_iter, z, z.at[a].set(wrap_angle(z[a])))
            Fv, jvp = jax.linearize(self.F, z)
            Jz = jax.vmap(jvp, out_axes=1)(eye)
            H = Jz.T @ Jz
            dz, _ = _chol_solve(H + (1e-14 * jnp.trace(H) + 1e-300) * eye, Jz.T @ Fv)
            return jnp.where(k < n_iter, z - dz, z), (Fv, Jz)

        z, (Fv, Jz) = jax.lax.scan(body, z, jnp.arange(n_iter + 1))
        return z, Fv[-1], Jz[-1]


def _make_scaled(observer, plant, op, angle_weight):
    dtype = op.w_m.dtype
    scale = jnp.asarray(observer.error_scale(op, plant), dtype)
    aw = jnp.abs(op.w_m)
    rate = jnp.where(aw > 0, aw, jnp.ones_like(aw))
    n = observer.coordinates.n
    a = observer.coordinates.angle
    weight = jnp.ones(n, dtype).at[a].set(angle_weight)
    return _Scaled(observer, plant, op, scale, rate, weight, a)

