r"""Analysis generic over the observer contract (`pmsmjax.observers.AbstractObserver`).

Every function here takes an observer (its own machine model `observer.motor`, its design)
and the true machine `plant` (`PMSMParams`); observer-model mismatch in any parameter is
`observer.with_motor(...)`. The error dynamics are the observer's `error_rhs` at an
`OperatingPoint` (constant speed $\omega_0$, current $i_0$ in the estimated frame).

**Scaling.** All tests and tolerances work on the scaled system
$F(z) = f(Dz)/(D\,\Omega)$ with $D$ = `observer.error_scale(op, plant)` and the rate
$\Omega = |\omega_0|$ (1 rad/s at standstill): a positive similarity and time scaling,
which changes no sign of a real part and keeps the entries O(1).

**Equilibria (generic route).** With $a$ the angle coordinate and $y$ the other $n-1$
coordinates, for a fixed angle error $\tilde\theta$ the other coordinates are found by
Gauss-Newton on the weighted least-squares problem
$\min_y \|W F(\tilde\theta, y)\|^2$ ($W$ = 1, except `angle_weight` on the angle row, so
that the solution follows the branch where the estimated frame turns at the true speed;
for observers whose other equations are affine in $y$ there, one step is exact). The
residual that is left is measured with a sign,

$$r(\tilde\theta) = \frac{\det[\,J_y \mid WF\,]}{\sqrt{\det J_y^TJ_y}},\qquad
J_y = \partial(WF)/\partial y,$$

which is $\pm\|WF\|$ at a least-squares solution (the residual is orthogonal to the
columns of $J_y$) and continuous in $\tilde\theta$ while $J_y$ keeps full rank: its zeros
are exactly the equilibria. Zeros are bracketed by sign changes on a periodic grid offset
by half a step (so $\tilde\theta = 0, \pi$ are never grid points), refined by the Illinois
method, and polished by Newton steps on the full square system $F(z) = 0$; a slot counts
only if the polished residual is below tolerance. Two zeros inside one grid cell leave no
sign change but a local minimum of $|r|$ close to 0: such cells are searched by Newton
steps from both cell ends (`n_crit` slots). All shapes are static, so the route jits
and vmaps over operating points, designs and mismatches; failures are reported in
`status` (0 ok, 2 no equilibrium, -1 degenerate), never raised.

**Stability** of each equilibrium: the exact Routh-Hurwitz test on the characteristic
polynomial (Faddeev-LeVerrier) of the scaled Jacobian (forward-mode Jacobian of
`error_rhs`, taken with the final Newton residual); a (numerically) singular Jacobian is
a tangent (saddle-node) equilibrium, never stable.

**Compile time.** Every phase (continuation, close-pair search, refinement, Newton
polish) is a `lax.scan` whose body evaluates the error dynamics and their Jacobian once,
so `error_rhs` is traced four times in all, and the small linear algebra is written as
loops: the program's size, and XLA's compile time, stay moderate for the larger observers
(BENCHMARKS.md, "Compile time of the generic analysis").
"""

from __future__ import annotations

import inspect
import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._frames import rotate, wrap_angle
from .._plant._params import PMSMParams
from ..observers._base import AbstractObserver, Measurement, OperatingPoint, PlantPoint
from ._equilibria import Equilibria, as_arrays
from ._linearize import charpoly, routh_hurwitz


#: `Equilibria.status` / `DesignClass.status` codes.
STATUS_OK, STATUS_NONE, STATUS_DEGENERATE = 0, 2, -1


def check_observer(owner: str, observer) -> None:
    if not isinstance(observer, AbstractObserver):
        raise ValueError(f"`{owner}(observer=...)` must be an `AbstractObserver` (e.g. "
                         f"`pj.observers.make_observer('eso', drive)`); got "
                         f"{type(observer).__name__}.")


def check_plant(owner: str, plant) -> None:
    if not isinstance(plant, PMSMParams):
        raise ValueError(f"`{owner}(plant=...)` must be the true machine's `PMSMParams` "
                         f"(e.g. `drive.three_phase_motor`); got {type(plant).__name__}.")


def _op(w_m, i_dq, dtype):
    return OperatingPoint(jnp.asarray(w_m, dtype), jnp.asarray(i_dq, dtype))


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


# ---------------------------------------------------------------------------------------
# Linearisation and stability
# ---------------------------------------------------------------------------------------

def linearization(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq=(0.0, 0.0),
                  x=None, theta=None):
    """Jacobian $\\partial f/\\partial x$ of `observer.error_rhs` at state `x` (default:
    the designed equilibrium `observer.designed_error`, the origin for most), operating
    point `w_m` (rad/s, electrical), `i_dq` (A, estimated frame), true machine `plant`.
    SI units, time in s; `(n, n)`. `theta`: the true rotor angle (rad) for observers
    whose error dynamics depend on it (`OperatingPoint.theta`; default None: their
    average over one period).
    Pure: vmap it over operating points or designs."""
    check_observer("linearization", observer)
    check_plant("linearization", plant)
    dtype = jnp.result_type(w_m, float)
    op = _op(w_m, i_dq, dtype)
    if theta is not None:
        op = OperatingPoint(op.w_m, op.i_dq, theta)
    x = (jnp.asarray(observer.designed_error(op, plant), dtype) if x is None
         else jnp.asarray(x, dtype))
    return _linearization(as_arrays(observer, dtype), as_arrays(plant, dtype), op, x)


@eqx.filter_jit
def _linearization(observer, plant, op, x):
    # compiled once per observer structure (values traced): run op by op, the forward
    # Jacobian of a LESO's error dynamics took seconds per call
    return jax.jacfwd(lambda v: observer.error_rhs(v, op, plant))(x)


class Stability(eqx.Module):
    """Stability of a linearisation `A` (any batch shape).

    - `hurwitz`: every eigenvalue in the open left half plane (exact Routh-Hurwitz on the
      characteristic polynomial).
    - `charpoly`: `[1, c1, ..., cn]` of det(sI - A).
    - `eigenvalues`: complex, `(..., n)` (eigenvalue solver, for reporting).
    - `max_real`: largest real part (1/s).
    """

    hurwitz: jnp.ndarray
    charpoly: jnp.ndarray
    eigenvalues: jnp.ndarray
    max_real: jnp.ndarray


def stability(A) -> Stability:
    """Routh-Hurwitz and eigenvalues of the square matrix (matrices) `A`."""
    A = jnp.asarray(A)
    c = charpoly(A)
    ev = jnp.linalg.eigvals(A)
    return Stability(hurwitz=routh_hurwitz(c), charpoly=c, eigenvalues=ev,
                     max_real=jnp.max(jnp.real(ev), -1))


# ---------------------------------------------------------------------------------------
# Equilibria
# ---------------------------------------------------------------------------------------

def _continuation(sys: _Scaled, grid, y0, n_iter):
    """The other coordinates along the angle grid, continued outwards from the two grid
    points next to 0 (where the designed equilibrium is), each warm-started from its
    neighbour, so that they follow one branch of least-squares solutions. Also returns
    the signed residual `r` and the angle row of `F` at every grid point.

    Both directions run in one scan (vmapped over the direction), and the start (`2
    n_iter` Gauss-Newton steps at the first angle before the sweep) is two extra scan
    steps at that angle: the same iterations as separate calls, but the error dynamics
    and their Jacobian are traced once (the compile time of the generic route grows with
    the number of places that trace them)."""
    N = grid.shape[0]
    mid = N // 2
    up = grid[mid:]
    down = grid[:mid][::-1]
    L = up.shape[0]
    down = jnp.concatenate([down, jnp.broadcast_to(down[-1:], (L - mid,))])
    thetas = jnp.stack([up, down])
    thetas = jnp.concatenate([thetas[:, :1], thetas[:, :1], thetas], 1)

    def run(th):
        def body(y, t):
            y, rv, fa = sys.solve_y(t, y, n_iter)
            return y, (y, rv, fa)

        _, out = jax.lax.scan(body, y0, th)
        return jax.tree_util.tree_map(lambda a: a[2:], out)

    ys, rv, fa = jax.vmap(run)(thetas)
    cat = lambda a: jnp.concatenate([a[1, :mid][::-1], a[0]], 0)  # noqa: E731
    return cat(ys), cat(rv), cat(fa)


def equilibria(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq=(0.0, 0.0), *,
               method: str = "auto", n_grid: int = 64, max_roots: int = 6, n_crit: int = 2,
               n_golden: int = 16,
               angle_weight: float = 1000.0, n_gauss_newton: int = 3, n_refine: int = 10,
               n_newton: int = 8, tol: float | None = None) -> Equilibria:
    r"""Every equilibrium of `observer`'s error dynamics at one operating point.

    **Arguments:**

    - `observer`: any `AbstractObserver` (its `motor` is its model: mismatch).
    - `plant`: the true machine (`PMSMParams`, SI).
    - `w_m`: electrical speed (rad/s); `i_dq`: current in the estimated frame (A, `(2,)`).
    - `n_grid`: bracketing grid on (-pi, pi]; `max_roots`: output slots; `n_crit`:
      slots for close pairs (all static).
    - `angle_weight`, `n_gauss_newton`, `n_refine`, `n_newton`: the inner solve, the
      Illinois refinement and the final Newton polish (module docstring).
    - `tol`: accepted scaled residual (default eps^0.6: about 4e-10 in float64).
    - `method`: `"auto"` uses the family's own route where it declares one
      (`observer.fast_equilibria`: zhang2022's reduction for fal feedback), else the
      generic route; `"generic"` forces the generic route.

    Returns an `Equilibria` (angles in (-pi, pi], states in the observer's
    `coordinates`, SI). Pure and vmappable: wrap it in `jax.vmap` over any leaf.
    """
    observer, plant, op, options = _equilibria_args(
        observer, plant, w_m, i_dq, method=method, n_grid=n_grid, max_roots=max_roots,
        n_crit=n_crit, n_golden=n_golden, angle_weight=angle_weight,
        n_gauss_newton=n_gauss_newton, n_refine=n_refine, n_newton=n_newton, tol=tol)
    if method == "auto" and (type(observer).fast_equilibria
                             is not AbstractObserver.fast_equilibria):
        fast = _fast_equilibria(observer, plant, op)
        if fast is not None:
            return fast
    return _equilibria(observer, plant, op, options)


@eqx.filter_jit
def _fast_equilibria(observer, plant, op):
    """The family's own route (`observer.fast_equilibria`) as one compiled program: run
    op by op, each of its small operations compiles on its own (the parallel-model
    estimator's closed form: 183 of them: 4.2 s for the first call, 1.9 s compiled)."""
    return observer.fast_equilibria(plant, op)


def _equilibria_args(observer, plant, w_m, i_dq, *, method, n_grid, max_roots, n_crit,
                     n_golden, angle_weight, n_gauss_newton, n_refine, n_newton, tol):
    """`equilibria`'s argument checks and conversions: (observer, plant, op, options of
    the generic route)."""
    check_observer("equilibria", observer)
    check_plant("equilibria", plant)
    for name, v, lo in (("n_grid", n_grid, 8), ("max_roots", max_roots, 1),
                        ("n_crit", n_crit, 0)):
        if not isinstance(v, int) or v < lo:
            raise ValueError(f"`equilibria({name}=...)` must be an int >= {lo}; got {v!r}.")
    if method not in ("auto", "generic"):
        raise ValueError(f"`equilibria(method=...)` must be 'auto' or 'generic'; got "
                         f"{method!r}.")
    dtype = jnp.result_type(w_m, float)
    observer, plant = as_arrays(observer, dtype), as_arrays(plant, dtype)
    op = _op(w_m, i_dq, dtype)
    tol = float(jnp.finfo(dtype).eps) ** 0.6 if tol is None else float(tol)
    return observer, plant, op, dict(
        method="generic", n_grid=n_grid, max_roots=max_roots, n_crit=n_crit, n_golden=n_golden,
        angle_weight=angle_weight, n_gauss_newton=n_gauss_newton, n_refine=n_refine,
        n_newton=n_newton, tol=tol)


def equilibria_stored(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq=(0.0, 0.0),
                      **kwargs) -> Equilibria:
    """`equilibria(observer, plant, w_m, i_dq, **kwargs)` for a process that repeats the
    same analysis (the `pmsmjax equilibria` command): the whole analysis (the family's own
    route included, `method="auto"`) as one program kept by `pmsmjax.runtime.stored_call`
    next to the compilation cache, so that a repeated call skips the tracing. Where no
    program can be stored (the cache is off, a static value without a stable
    description), it is `equilibria` itself. Concrete inputs only (not for use under
    `jax.jit`/`jax.vmap`)."""
    from .. import runtime

    method = kwargs.pop("method", "auto")
    full = {k: p.default for k, p in inspect.signature(equilibria).parameters.items()
            if p.kind is p.KEYWORD_ONLY and k != "method"}
    unknown = set(kwargs) - set(full)
    if unknown:
        raise TypeError(f"equilibria_stored: unknown arguments {sorted(unknown)}; allowed: "
                        f"{sorted(full)} and method")
    full.update(kwargs)
    if runtime.stored_programs_dir() is not None:
        obs, pl, op, options = _equilibria_args(observer, plant, w_m, i_dq, method=method,
                                                **full)
        options["method"] = method
        out = runtime.stored_call("equilibria", _equilibria_program, (obs, pl, op, options),
                                  Equilibria)
        if out is not None:
            return out
    return equilibria(observer, plant, w_m, i_dq, method=method, **full)


def _equilibria_program(observer, plant, op, options):
    return equilibria_traced(observer, plant, op, **options)


@eqx.filter_jit
def _equilibria(observer, plant, op, options):
    return equilibria_traced(observer, plant, op, **options)


def equilibria_traced(observer, plant, op: OperatingPoint, *, method="auto", n_grid=64,
                      max_roots=6, n_crit=2, n_golden=16, angle_weight=1000.0,
                      n_gauss_newton=3, n_refine=10, n_newton=8, tol=1e-9) -> Equilibria:
    """`equilibria` without argument checks or jit, for use inside a jitted/vmapped
    function (e.g. a feasibility map or a tuning penalty)."""
    if method == "auto":
        fast = observer.fast_equilibria(plant, op)
        if fast is not None:
            return fast
    sys = _make_scaled(observer, plant, op, angle_weight)
    dtype = op.w_m.dtype
    n = observer.coordinates.n
    m = n - 1
    y0 = jnp.zeros(m, dtype)
    h = 2 * math.pi / n_grid
    grid = -math.pi + h * (jnp.arange(n_grid, dtype=dtype) + 0.5)
    ys, rv, Fa = _continuation(sys, grid, y0, n_gauss_newton)
    # Grid points where the inner solve did not settle (the angle row is not satisfied,
    # e.g. oscillating Gauss-Newton steps across a kink of a piecewise-smooth feedback
    # such as fal) are skipped: brackets join the nearest settled points on each side.
    settled = jnp.isfinite(rv) & (jnp.abs(Fa) < 1e-6)
    finite = jnp.sum(settled) >= n_grid // 2
    rv = jnp.where(jnp.isfinite(rv), rv, 0.0)
    k = jnp.arange(n_grid)
    last_any = jnp.max(jnp.where(settled, k, -n_grid - 1))
    prev = jax.lax.cummax(jnp.where(settled, k, -n_grid - 1))
    prev = jnp.where(prev >= 0, prev, last_any - n_grid)  # wrap round to the end
    # bracket (prev(j), j + 1) for every settled grid point j + 1
    nxt = (k + 1) % n_grid
    lo_i = prev % n_grid
    lo_t = grid[lo_i] - jnp.where(prev < 0, 2 * math.pi, 0.0)
    hi_t = grid[nxt] + jnp.where(k == n_grid - 1, 2 * math.pi, 0.0)
    sc = settled[nxt] & ((rv[lo_i] >= 0) != (rv[nxt] >= 0)) & (prev > -n_grid - 1)
    (idx,) = jnp.nonzero(sc, size=max_roots, fill_value=0)
    n_sc = jnp.sum(sc)
    slot = jnp.arange(max_roots) < n_sc

    # Illinois refinement of a bracket, warm-starting the inner solve from its ends.
    def refine(a, b, fa, fb, ya, yb):
        def body(c, _):
            a, b, fa, fb, ya, yb, side = c
            den = fa - fb  # regula falsi: c = a + fa / (fa - fb) (b - a)
            t = jnp.where(den != 0, fa / jnp.where(den != 0, den, 1.0), 0.5)
            t = jnp.clip(t, 0.02, 0.98)
            c_ = a + t * (b - a)
            yc, fc, _ = sys.solve_y(c_, ya + t * (yb - ya), 2)
            left = (fc >= 0) == (fa >= 0)  # the root is in [c, b]
            # Illinois: halve the value kept at the end that survives twice
            fb = jnp.where(left & (side == 1), 0.5 * fb, fb)
            fa = jnp.where(~left & (side == -1), 0.5 * fa, fa)
            return (jnp.where(left, c_, a), jnp.where(left, b, c_),
                    jnp.where(left, fc, fa), jnp.where(left, fb, fc),
                    jnp.where(left, yc, ya), jnp.where(left, yb, yc),
                    jnp.where(left, 1, -1)), None

        c0 = (a, b, fa, fb, ya, yb, jnp.asarray(0))
        (a, b, fa, fb, ya, yb, _), _ = jax.lax.scan(body, c0, None, length=n_refine)
        t = jnp.where(jnp.abs(fa) < jnp.abs(fb), 0.0, 1.0)
        return a + t * (b - a), ya + t * (yb - ya)

    blo, bhi, flo, fhi = lo_t[idx], hi_t[idx], rv[lo_i[idx]], rv[nxt[idx]]
    ylo, yhi = ys[lo_i[idx]], ys[nxt[idx]]
    bvalid = slot

    if n_crit:
        # Close pairs: a local minimum of |r| without a sign change on either side may
        # hide two zeros in one cell. Find the extremum of r between the neighbouring
        # grid points (golden section); if r changes sign there, bracket both halves.
        ar = jnp.abs(rv)
        rmax = jnp.maximum(jnp.max(ar), jnp.finfo(dtype).tiny)
        prev_sc = jnp.roll(sc, 1)
        locmin = (ar <= jnp.roll(ar, 1)) & (ar <= jnp.roll(ar, -1)) & ~sc & ~prev_sc \
            & (ar < 0.05 * rmax) & settled & jnp.roll(settled, 1) & jnp.roll(settled, -1)
        (cidx,) = jnp.nonzero(locmin, size=n_crit, fill_value=0)
        cslot = jnp.arange(n_crit) < jnp.sum(locmin)
        g = (math.sqrt(5.0) - 1.0) / 2.0

        def extremum(k):
            sgn = jnp.where(rv[k] >= 0, 1.0, -1.0)
            yk = ys[k]
            last = n_golden + 2

            # golden section, one evaluation per scan step: steps 0 and 1 evaluate the
            # two inner points, then `n_golden` section steps, and the last step the
            # midpoint of the final interval with one more Gauss-Newton iteration (one
            # traced copy of the inner solve and the residual instead of four)
            def body(c, i):
                a, b, x1, x2, f1, f2, tc, yc, rc = c
                left = f1 < f2  # the minimum is in [a, x2]
                a2, b2 = jnp.where(left, a, x1), jnp.where(left, x2, b)
                xn = jnp.where(left, b2 - g * (b2 - a2), a2 + g * (b2 - a2))
                sec = (i >= 2) & (i < last)
                t = jnp.where(i == 0, x1, jnp.where(i == 1, x2,
                                                    jnp.where(i == last, 0.5 * (a + b), xn)))
                y, rt, _ = sys.solve_y(t, yk, 3, n_active=jnp.where(i == last, 3, 2))
                fn = sgn * rt
                x1n = jnp.where(left, xn, x2)
                x2n = jnp.where(left, x1, xn)
                f1n = jnp.where(left, fn, f2)
                f2n = jnp.where(left, f1, fn)
                return (jnp.where(sec, a2, a), jnp.where(sec, b2, b),
                        jnp.where(sec, x1n, x1), jnp.where(sec, x2n, x2),
                        jnp.where(sec, f1n, jnp.where(i == 0, fn, f1)),
                        jnp.where(sec, f2n, jnp.where(i == 1, fn, f2)),
                        jnp.where(i == last, t, tc), jnp.where(i == last, y, yc),
                        jnp.where(i == last, rt, rc)), None

            a, b = grid[k] - h, grid[k] + h
            x1, x2 = b - g * (b - a), a + g * (b - a)
            zero = jnp.zeros((), dtype)
            c0 = (a, b, x1, x2, zero, zero, zero, yk, zero)
            c, _ = jax.lax.scan(body, c0, jnp.arange(last + 1))
            return c[6], c[7], c[8]

        tc, yc, rc = jax.vmap(extremum)(cidx)
        split = cslot & ((rc >= 0) != (rv[cidx] >= 0))
        km, kp = (cidx - 1) % n_grid, (cidx + 1) % n_grid
        blo = jnp.concatenate([blo, grid[cidx] - h, tc])
        bhi = jnp.concatenate([bhi, tc, grid[cidx] + h])
        flo = jnp.concatenate([flo, rv[km], rc])
        fhi = jnp.concatenate([fhi, rc, rv[kp]])
        ylo = jnp.concatenate([ylo, ys[km], yc])
        yhi = jnp.concatenate([yhi, yc, ys[kp]])
        bvalid = jnp.concatenate([bvalid, split, split])

    th_all, y_all = jax.vmap(refine)(blo, bhi, flo, fhi, ylo, yhi)
    cand = bvalid
    z = jax.vmap(sys.insert)(th_all, y_all)
    z, Fz, A = jax.vmap(lambda v: sys.newton(v, n_newton))(z)
    res = jnp.max(jnp.abs(Fz), -1)
    conv = jnp.isfinite(res) & (res < tol)
    valid = cand & conv
    failed = jnp.any(cand & ~conv)  # a bracket whose zero does not polish
    # duplicates (two starts converging to one equilibrium)
    K = z.shape[0]
    theta = z[:, sys.angle]
    close = (jnp.abs(wrap_angle(theta[:, None] - theta[None, :])) < 1e-6) & \
        (jnp.max(jnp.abs(z[:, None, :] - z[None, :, :]), -1) < 1e-5)
    earlier = jnp.tril(jnp.ones((K, K), bool), -1)
    dup = jnp.any(close & earlier & valid[None, :], axis=1)
    valid = valid & ~dup
    too_many = (n_sc > max_roots) | (jnp.sum(valid) > max_roots)
    order = jnp.argsort(jnp.where(valid, theta, jnp.inf))[:max_roots]
    z, valid, res, A = z[order], valid[order], res[order], A[order]
    theta = z[:, sys.angle]

    c, hurwitz, A_si = jacobian_readout(sys, A)
    tangent = valid & (jnp.abs(c[:, -1]) < 1e3 * tol)
    stable = valid & hurwitz & ~tangent
    x = z * sys.scale
    nval = jnp.sum(valid)
    principal = jnp.argmin(jnp.where(valid, jnp.abs(theta), jnp.inf))
    degenerate = ~finite | too_many | failed | ~jnp.all(jnp.isfinite(sys.scale)) | \
        ~(sys.rate > 0)
    status = jnp.where(degenerate, STATUS_DEGENERATE,
                       jnp.where(nval == 0, STATUS_NONE, STATUS_OK)).astype(jnp.int32)
    # a degenerate point has no equilibria to report (nothing valid, everything NaN)
    valid = valid & ~degenerate
    stable, tangent = stable & valid, tangent & valid
    nval = jnp.sum(valid)
    nan = jnp.nan
    return Equilibria(
        theta=jnp.where(valid, theta, nan), x=jnp.where(valid[:, None], x, nan),
        valid=valid, stable=stable, tangent=tangent,
        residual=jnp.where(valid, res, nan), principal=principal.astype(jnp.int32),
        n=nval.astype(jnp.int32), status=status,
        jacobian=jnp.where(valid[:, None, None], A_si, nan))


def jacobian_readout(sys, A):
    """What the equilibria report of the scaled error dynamics' Jacobians `A` (K, n, n)
    at their K equilibria: the characteristic polynomials `[1, c1, ..., cn]` (K, n + 1),
    their Routh-Hurwitz test (K,) and the Jacobians in SI units (K, n, n)."""
    c = charpoly(A)
    A_si = A * sys.scale[None, :, None] / sys.scale[None, None, :] * sys.rate
    return c, routh_hurwitz(c), A_si


# ---------------------------------------------------------------------------------------
# The discrete observer in error coordinates (consistency with the continuous model)
# ---------------------------------------------------------------------------------------

def _true_flux_ab(plant: PMSMParams, theta, i_ab):
    i_dq = rotate(i_ab, -theta)
    psi = jnp.stack([plant.L_d * i_dq[0] + plant.psi_f, plant.L_q * i_dq[1]])
    return rotate(psi, theta)


def discrete_error_map(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq, T_s, *,
                       theta_k=0.0, n_fixed_point: int = 3):
    r"""One real `observer.step` as a map of error coordinates $x_k \mapsto x_{k+1}$.

    The plant turns at constant electrical speed `w_m` (rad/s); ideal current control
    holds the current at `i_dq` (A) in the observer's estimated frame, so the sampled
    current at $t_{k+1}$ is $e^{\hat\theta_{k+1}J} i_{dq}$ (a fixed point with the
    observer's own estimate, solved by `n_fixed_point` iterations); the voltage held over
    $[t_k, t_{k+1})$ is the one that moves the true flux between the two samples with a
    trapezoidal resistive drop. At $t_k$ the rotor is at `theta_k` (rad).

    Returns `fn(x_k) -> x_{k+1}` (pure; `jax.jacfwd(fn)(x)` is the Jacobian of the
    discrete observer, which agrees with $I + T_s A$ of `linearization` to $O(T_s^2)$).
    """
    check_observer("discrete_error_map", observer)
    check_plant("discrete_error_map", plant)
    a = observer.coordinates.angle
    i0 = jnp.asarray(i_dq, float)

    def fn(x):
        x = jnp.asarray(x)
        dtype = x.dtype
        th0 = jnp.asarray(theta_k, dtype)
        th1 = th0 + w_m * T_s
        w = jnp.asarray(w_m, dtype)
        i_k = rotate(i0, th0 - x[a]).astype(dtype)
        truth0 = PlantPoint(theta=th0, w_m=w, i_ab=i_k)
        state = observer.observer_state(x, truth0, plant)
        psi0 = _true_flux_ab(plant, th0, i_k)
        i_next = rotate(i0, th1 - x[a])
        nan = jnp.full((), jnp.nan, dtype)
        for _ in range(n_fixed_point):
            u = (_true_flux_ab(plant, th1, i_next) - psi0) / T_s \
                + 0.5 * plant.R_s * (i_k + i_next)
            new, est = observer.step(state, Measurement(i_ab=i_next, u_ab=u, theta=nan,
                                                        w_m=nan), T_s)
            i_next = rotate(i0, est.theta_hat)
        return observer.error_state(new, PlantPoint(theta=th1, w_m=w, i_ab=i_next), plant)

    return fn


def _program_inputs(observer, plant, dtype=float):
    """`observer` and `plant` with their float values (design, machine parameters) as
    arrays of `dtype`: inputs of a compiled program, not constants compiled into it, so
    another design or a mismatched model reuses the program (Python ints, an observer's
    counts and sizes, stay as they are)."""
    return as_arrays(observer, dtype, ints=False), as_arrays(plant, dtype, ints=False)


def discrete_jacobian(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq, T_s, *,
                      x=None, theta_k=0.0):
    r"""The Jacobian $\partial x_{k+1} / \partial x_k$ of one real `observer.step` in
    error coordinates (`discrete_error_map`), at the error state `x` (SI units; default
    the designed equilibrium, `observer.designed_error`).

    `w_m` (rad/s), `i_dq` (A, estimated frame), `T_s` (s) and `theta_k` (rad) as in
    `discrete_error_map`. It agrees with $I + T_s A$ of `linearization` to $O(T_s^2)$
    (tested). Compiled once per observer structure: the speed, current, period, angle and
    state are the program's inputs, so a sweep over any of them, or `jax.vmap` over them,
    reuses one program (run op by op, one Jacobian of a LESO took seconds). Returns
    `(n, n)`."""
    observer, plant = _program_inputs(observer, plant)
    return _discrete_jacobian(observer, plant, jnp.asarray(w_m, float),
                              jnp.asarray(i_dq, float), jnp.asarray(T_s, float),
                              jnp.asarray(theta_k, float),
                              None if x is None else jnp.asarray(x, float))


@eqx.filter_jit
def _discrete_jacobian(observer, plant, w_m, i_dq, T_s, theta_k, x):
    if x is None:
        x = observer.designed_error(OperatingPoint(w_m, i_dq), plant)
    fn = discrete_error_map(observer, plant, w_m, i_dq, T_s, theta_k=theta_k)
    return jax.jacfwd(fn)(x)


def discrete_poles(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq, T_s, *,
                   theta_k=0.0):
    r"""The poles of the discrete observer: the eigenvalues $z$ of the Jacobian of one
    real `observer.step` (`discrete_jacobian`) at its designed equilibrium
    (`observer.designed_error`; with a mismatched model pass the equilibrium of
    `equilibria` to `discrete_jacobian` instead).

    $|z| < 1$ for every pole: locally stable at sampling period `T_s` (s). For small
    `T_s` they approach $e^{T_s\lambda}$ of the continuous `linearization`'s
    eigenvalues $\lambda$ (tested); at the firmware's `T_s` they say how far the real
    observer is from its continuous design. `w_m` (rad/s) and `i_dq` (A, estimated
    frame) as in `discrete_error_map`; pure, so `jax.vmap` it over speeds. Returns the
    `(n,)` complex eigenvalues, unordered."""
    return jnp.linalg.eigvals(discrete_jacobian(observer, plant, w_m, i_dq, T_s,
                                                theta_k=theta_k))


def discrete_error_run(observer: AbstractObserver, plant: PMSMParams, w_m, i_dq, T_s,
                       x0, n_steps: int):
    """Iterate `discrete_error_map` `n_steps` times from `x0` (the discrete observer in a
    closed loop with ideal current control at constant speed). Returns the error
    coordinates `(n_steps + 1, n)` at t_0 ... t_N (SI units). Compiled once per observer
    structure and `n_steps` (static), as `discrete_jacobian`: a new speed, current, period,
    start or design reuses the program (run op by op, every call compiled its loop anew)."""
    check_observer("discrete_error_run", observer)
    check_plant("discrete_error_run", plant)
    if not isinstance(n_steps, int) or n_steps < 1:
        raise ValueError(f"`discrete_error_run(n_steps=...)` must be an int >= 1; got "
                         f"{n_steps!r}.")
    observer, plant = _program_inputs(observer, plant)
    return _discrete_error_run(observer, plant, jnp.asarray(w_m, float),
                               jnp.asarray(i_dq, float), jnp.asarray(T_s, float),
                               jnp.asarray(x0, float), n_steps)


@eqx.filter_jit
def _discrete_error_run(observer, plant, w_m, i_dq, T_s, x0, n_steps):
    def body(carry, k):
        x = carry
        fn = discrete_error_map(observer, plant, w_m, i_dq, T_s, theta_k=k * w_m * T_s)
        x1 = fn(x)
        return x1, x1

    _, xs = jax.lax.scan(body, x0, jnp.arange(n_steps, dtype=x0.dtype))
    return jnp.concatenate([x0[None], xs], 0)
