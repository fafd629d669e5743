r"""Linearisation of observer error dynamics and exact stability tests for small matrices.

- `linearize(fn, x, *args)`: the Jacobian $\partial f/\partial x$ of any error dynamics
  `fn(x, *args) -> dx/dt` at `x`, by `jax.jacfwd` (forward mode: the state is small).
  Pure, so `jax.vmap` over operating points and designs works directly.
- `eso_rhs(...)`: the zhang2022 error dynamics (11) in one of two frame conventions (see
  below), and `eso_linearization(...)`: its Jacobian zhang2022 (37) at an operating point
  $(\omega_0, i_0$, parameter mismatch$)$ and a state (default the origin, where it is
  zhang2022 (15)).
- `charpoly(A)`: characteristic-polynomial coefficients by Faddeev-LeVerrier (exact
  rational arithmetic on the entries, no eigenvalues), `routh_hurwitz(c)`: the exact
  Routh test "every root in the open left half plane", `is_hurwitz(A)` = both.
  `max_real_eig(A)` is the eigenvalue route used to cross-check them.

Frame convention of the error dynamics. The observers of `pmsmjax.observers` rotate their
estimator frame at $\omega_f = \hat\omega + g_2 f(e)$, which gives the error dynamics
`observers.error_dynamics` (`frame="observer"`, the default):
$\dot{\tilde\psi} = -(\omega_0 - \tilde\omega + g_2 f) J\tilde\psi - G_1 f - \Delta R\, i_0$.
zhang2022 (11) prints the rotation term as $-(\omega_0 - \tilde\omega) J\tilde\psi$
(`frame="paper"`). Both have the same linearisation at the origin zhang2022 (15) and the same
equilibria with the minimum-norm gains zhang2022 (25), but their Jacobians differ at nonzero
equilibria by $-(J\tilde\psi)\,\partial(g_2 f)/\partial x$, so the stability of a
static-error equilibrium may depend on the convention. `frame="paper"` is kept so that
the paper's own model can be evaluated; the implemented observers follow `"observer"`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._frames import jmul
from .._plant._params import PMSMParams
from ..observers import ESOGains, error_dynamics, error_signal, fal


FRAMES = ("observer", "paper")


def check_frame(owner: str, frame: str) -> None:
    if frame not in FRAMES:
        raise ValueError(
            f"`{owner}(frame=...)` must be one of {', '.join(map(repr, FRAMES))}; "
            f"got {frame!r}."
        )


def linearize(fn, x, *args, **kwargs):
    """Jacobian of the error dynamics `fn(x, *args, **kwargs)` with respect to `x`.

    `fn` maps a state vector (shape `(n,)`) to its time derivative (shape `(n,)`); the
    result has shape `(n, n)`. Forward mode (`jax.jacfwd`): n Jacobian-vector products.
    Vmap it over operating points or designs, e.g.
    `jax.vmap(lambda w0: linearize(f, x0, w0, ...))(speeds)`.
    """
    return jax.jacfwd(lambda y: fn(y, *args, **kwargs))(jnp.asarray(x))


def eso_rhs(x, w0, i0, gains: ESOGains, motor: PMSMParams,
            motor_hat: PMSMParams | None = None, a=1.0, eta=1.0, frame: str = "observer"):
    r"""Error dynamics zhang2022 (11) of the zhang2022 ESO at constant speed `w0` (rad/s).

    State `x = [psi_err_d, psi_err_q, theta_err, w_err]` (V s, V s, rad, rad/s), errors
    true minus estimate; `i0` the controlled current in the estimator frame (A); `gains`
    the observer's gains; `motor` the plant and `motor_hat` (default `motor`) the
    observer's model; `a`, `eta` the fal parameters (`a = 1`: linear feedback, LESO).
    `frame`: `"observer"` (= `observers.error_dynamics`) or `"paper"` (the rotation term
    exactly as printed in zhang2022 (11)); see the module docstring.
    """
    check_frame("eso_rhs", frame)
    f = error_dynamics(x, w0, i0, gains, motor, motor_hat, a, eta)
    if frame == "paper":
        mh = motor if motor_hat is None else motor_hat
        e = error_signal(x[:2], x[2], i0, motor, mh)
        fb = fal(e, a, eta) * eta ** (1.0 - a)
        # observer form rotates at w0 - w_err + g2 f; the paper's at w0 - w_err.
        f = f.at[:2].add((gains.g2 @ fb) * jmul(x[:2]))
    return f


def eso_linearization(w0, i0, gains: ESOGains, motor: PMSMParams,
                      motor_hat: PMSMParams | None = None, x=None, a=1.0, eta=1.0,
                      frame: str = "observer"):
    r"""Jacobian zhang2022 (37) of the ESO error dynamics at state `x` (default: the origin).

    At the origin with matched parameters this is the matrix $A$ of zhang2022 (15)
    (`observers.error_matrix`) for any `a`, `eta` (fal's slope at 0 is scaled to 1).
    Arguments as for `eso_rhs`. Returns a `(4, 4)` array in SI units of the state.
    """
    x = jnp.zeros(4, jnp.result_type(w0, float)) if x is None else jnp.asarray(x)
    return linearize(eso_rhs, x, w0, i0, gains, motor, motor_hat, a, eta, frame)


def charpoly(A):
    r"""Coefficients `[1, c1, ..., cn]` of $\det(sI - A) = s^n + c_1 s^{n-1} + \dots + c_n$.

    Faddeev-LeVerrier: $M_0 = 0$, $M_k = A M_{k-1} + c_{k-1} I$,
    $c_k = -\mathrm{tr}(A M_k)/k$ ($c_0 = 1$). Only products and sums of the entries, so
    it is exact up to rounding (no eigenvalue solver) and vmaps to fused element-wise
    code. `A`: `(..., n, n)`.
    """
    A = jnp.asarray(A)
    n = A.shape[-1]
    eye = jnp.eye(n, dtype=A.dtype)
    c = [jnp.ones(A.shape[:-2], A.dtype)]
    M = jnp.zeros_like(A)
    for k in range(1, n + 1):
        M = A @ M + c[-1][..., None, None] * eye
        c.append(-jnp.trace(A @ M, axis1=-2, axis2=-1) / k)
    return jnp.stack(c, -1)


def routh_hurwitz(coeffs):
    r"""True iff every root of $c_0 s^n + c_1 s^{n-1} + \dots + c_n$ has negative real part.

    Routh array: with $c_0 > 0$ the polynomial is (strictly) Hurwitz iff every entry of
    the first column is positive. A zero entry means a root on or to the right of the
    imaginary axis or a symmetric root pair, so "not strictly stable" is the exact answer
    there too (no epsilon substitution is needed for a strict test). `coeffs`: `(..., n+1)`.
    For n = 4 (monic) this is $c_1, c_3, c_4 > 0$, $c_1c_2 - c_3 > 0$,
    $(c_1c_2 - c_3)c_3 - c_1^2 c_4 > 0$.
    """
    c = jnp.asarray(coeffs)
    c = c * jnp.sign(c[..., :1])  # make c0 > 0 (c0 = 0 gives all-zero -> unstable)
    n = c.shape[-1] - 1
    rows = [c[..., 0::2], c[..., 1::2]]
    width = rows[0].shape[-1]
    rows = [jnp.concatenate([r, jnp.zeros(r.shape[:-1] + (width - r.shape[-1],), r.dtype)],
                            -1) for r in rows]
    ok = rows[0][..., 0] > 0
    for _ in range(n):
        top, bot = rows[-2], rows[-1]
        ok = ok & (bot[..., 0] > 0)
        safe = jnp.where(bot[..., :1] > 0, bot[..., :1], 1.0)
        new = top[..., 1:] - top[..., :1] / safe * bot[..., 1:]
        new = jnp.concatenate([new, jnp.zeros(new.shape[:-1] + (1,), new.dtype)], -1)
        rows.append(new)
        if len(rows) > n + 1:
            break
    return ok


def is_hurwitz(A):
    """True iff every eigenvalue of the square matrix `A` has negative real part
    (Routh-Hurwitz on `charpoly(A)`; no eigenvalue solver)."""
    return routh_hurwitz(charpoly(A))


def max_real_eig(A):
    """Largest real part of the eigenvalues of `A` (eigenvalue solver; for checks)."""
    return jnp.max(jnp.real(jnp.linalg.eigvals(A)), -1)
