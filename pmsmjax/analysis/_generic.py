r"""Analysis generic over the observer contract (`pmsmjax.observers.AbstractObserver`).

Every function here takes an observer (its own machine model `observer.motor`, its design)
and the true machine `plant` (`PMSMParams`); observer-model mismatch in any parameter is
`observer.with_motor(...)`. The error dynamics are the observer's `error_rhs` at an
`OperatingPoint` (constant speed $\omega_0$, current $i_0$ in the estimated frame).

**Scaling.** All tests and tolerances work on the scaled system $F(z) = f(Dz)/(D\,\Omega)$
(`pmsmjax.analysis._scaled`): positive, so it changes no sign of a real part.

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
only if the polished residual is below tolerance. Where the inner problem has two
branches of solutions and the least-squares solution changes branch between neighbouring
grid points, $r$ jumps and changes sign without a zero; the refinement then closes in on
the jump with $|r|$ staying large (`JUMP_RATIO`) and its Newton polish does not converge:
such a bracket is dropped, while any other bracket that does not polish makes the point
degenerate. An equilibrium on the branch the continuation does not follow leaves no sign
change, so wherever a jump or an unsettled grid point shows two branches, Newton steps on
the full system also start from `n_starts` grid points (their angles and the
continuation's other coordinates there), and every start that converges is an
equilibrium (duplicates dropped). Under `jax.vmap` every point would pay for the starts,
so they are asked for (`n_starts`; the `pmsmjax equilibria` command and the saturated
analysis start from every grid point, and so does every call for an observer class that
declares `equilibria_starts`); without them a jump that does not polish leaves the point
degenerate, as any unpolished bracket does. The rotor-flux observer is the case met, with
inductance mismatch and even with a matched model under load: checked against SciPy's
root finder started from a grid of angles (tests/test_equilibria.py).
Two zeros inside one grid cell leave no sign change but a local minimum of $|r|$ close
to 0: such cells are searched by Newton steps from both cell ends (`n_crit` slots). All
shapes are static, so the route jits and vmaps over operating points, designs and
mismatches; failures are reported in `status` (0 ok, 2 no equilibrium, -1 degenerate),
never raised.

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

from .._frames import wrap_angle
from .._plant._params import PMSMParams
from ..observers import AbstractObserver, OperatingPoint
from ._args import _op, as_arrays, check_observer, check_plant
from ._equilibria import Equilibria
from ._linearize import charpoly, routh_hurwitz
from ._scaled import _make_scaled, _Scaled


#: `Equilibria.status` / `DesignClass.status` codes.
STATUS_OK, STATUS_NONE, STATUS_DEGENERATE = 0, 2, -1

#: |r| left at the end of a bracket's refinement, relative to the larger |r| at its ends,
#: above which the sign change is a jump of r, not a zero (module docstring). At a zero
#: the Illinois steps leave |r| at rounding level (1e-11 relative and below); at the
#: jumps met (the rotor-flux observer with inductance mismatch) it stays 0.1 to 1.
JUMP_RATIO = 1e-3


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
               angle_weight: float = 1000.0, n_gauss_newton: int | None = None,
               n_refine: int = 10,
               n_newton: int = 8, tol: float | None = None,
               n_starts: int | None = None) -> Equilibria:
    r"""Every equilibrium of `observer`'s error dynamics at one operating point.

    **Arguments:**

    - `observer`: any `AbstractObserver` (its `motor` is its model: mismatch).
    - `plant`: the true machine (`PMSMParams`, SI).
    - `w_m`: electrical speed (rad/s); `i_dq`: current in the estimated frame (A, `(2,)`).
    - `n_grid`: bracketing grid on (-pi, pi]; `max_roots`: output slots; `n_crit`:
      slots for close pairs (all static).
    - `angle_weight`, `n_gauss_newton`, `n_refine`, `n_newton`: the inner solve, the
      Illinois refinement and the final Newton polish (module docstring). Default
      `n_gauss_newton` (None): the observer class's `equilibria_gauss_newton` (3; 8 for
      the FA-LESO and the rotor-flux observer, whose inner problems are not affine).
    - `tol`: accepted scaled residual (default eps^0.6: about 4e-10 in float64).
    - `n_starts`: Newton starts on the full system from evenly spaced grid points, used
      where the inner problem shows two branches (module docstring; static). 0: such a
      point is reported degenerate when a bracket does not polish; `n_starts = n_grid`
      searches it (the `pmsmjax equilibria` command and the saturated analysis do).
      Default (None): `n_grid` for an observer class that declares
      `equilibria_starts` (the rotor-flux observer), else 0. Every point of a
      `jax.vmap` pays for the starts: 1.8x the time of a generic map with 64.
    - `method`: `"auto"` uses the family's own route where it declares one
      (`observer.fast_equilibria`: zhang2022's reduction for fal feedback), else the
      generic route; `"generic"` forces the generic route.

    Returns an `Equilibria` (angles in (-pi, pi], states in the observer's
    `coordinates`, SI). Pure and vmappable: wrap it in `jax.vmap` over any leaf.
    """
    observer, plant, op, options = _equilibria_args(
        observer, plant, w_m, i_dq, method=method, n_grid=n_grid, max_roots=max_roots,
        n_crit=n_crit, n_golden=n_golden, angle_weight=angle_weight,
        n_gauss_newton=n_gauss_newton, n_refine=n_refine, n_newton=n_newton, tol=tol,
        n_starts=n_starts)
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


def _starts(observer, n_starts, n_grid):
    """`n_starts` as given, or its default for `observer`'s class (`equilibria`)."""
    if n_starts is not None:
        return n_starts
    return n_grid if observer.equilibria_starts else 0  # a wrapper: the wrapped one's


def _gauss_newton(observer, n_gauss_newton):
    """`n_gauss_newton` as given, or its default for `observer`'s class."""
    return observer.equilibria_gauss_newton if n_gauss_newton is None else n_gauss_newton


def _equilibria_args(observer, plant, w_m, i_dq, *, method, n_grid, max_roots, n_crit,
                     n_golden, angle_weight, n_gauss_newton, n_refine, n_newton, tol,
                     n_starts=None):
    """`equilibria`'s argument checks and conversions: (observer, plant, op, options of
    the generic route)."""
    check_observer("equilibria", observer)
    check_plant("equilibria", plant)
    n_starts = _starts(observer, n_starts, n_grid)
    n_gauss_newton = _gauss_newton(observer, n_gauss_newton)
    for name, v, lo in (("n_grid", n_grid, 8), ("max_roots", max_roots, 1),
                        ("n_crit", n_crit, 0), ("n_starts", n_starts, 0),
                        ("n_gauss_newton", n_gauss_newton, 1)):
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
        n_newton=n_newton, tol=tol, n_starts=n_starts)


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
                      n_gauss_newton=None, n_refine=10, n_newton=8, tol=1e-9,
                      n_starts=None) -> Equilibria:
    """`equilibria` without argument checks or jit, for use inside a jitted/vmapped
    function (e.g. a feasibility map or a tuning penalty); `n_starts` None: the class's
    default, as in `equilibria`."""
    n_starts = _starts(observer, n_starts, n_grid)
    n_gauss_newton = _gauss_newton(observer, n_gauss_newton)
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
        return a + t * (b - a), ya + t * (yb - ya), jnp.minimum(jnp.abs(fa), jnp.abs(fb))

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

    th_all, y_all, f_end = jax.vmap(refine)(blo, bhi, flo, fhi, ylo, yhi)
    n_br = th_all.shape[0]
    # Newton from the refined brackets and, where the continuation left grid points
    # unsettled or r jumps (two branches of the inner problem, module docstring), also
    # from `n_starts` evenly spaced grid points (static; 0: none): one batch through the
    # same Newton call (traced once)
    jump = f_end > JUMP_RATIO * jnp.maximum(jnp.abs(flo), jnp.abs(fhi))
    sidx = (jnp.arange(n_starts) * n_grid) // max(n_starts, 1)
    z = jax.vmap(sys.insert)(jnp.concatenate([th_all, grid[sidx]]),
                             jnp.concatenate([y_all, ys[sidx]]))
    z, Fz, A = jax.vmap(lambda v: sys.newton(v, n_newton))(z)
    res = jnp.max(jnp.abs(Fz), -1)
    conv = jnp.isfinite(res) & (res < tol)
    branches = jnp.any(~settled) | jnp.any(bvalid & jump)
    cand = jnp.concatenate([bvalid, jnp.broadcast_to(branches, (n_starts,))])
    valid = cand & conv
    # A sign change that the refinement closes in on without |r| falling is a jump of r,
    # not a zero: with the grid's Newton starts, a bracket whose zero does not polish
    # fails the point only when it is not such a jump; without them, as before, any does
    # (an equilibrium off the followed branch could be missing).
    unpolished = bvalid & ~conv[:n_br]
    failed = jnp.any(unpolished & ~jump) if n_starts else jnp.any(unpolished)
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

