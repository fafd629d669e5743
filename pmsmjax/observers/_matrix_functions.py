r"""The exponential and the $\varphi$ functions of small complex matrices, for the exact
discretisation of a linear system whose inputs are polynomials in time:
$e^X y + \varphi_1(X)g_0 + \varphi_2(X)g_1$ is the state one period on
($\varphi_1(z) = (e^z - 1)/z$, $\varphi_2(z) = (e^z - 1 - z)/z^2$). li's back-EMF LESOs
(`_back_emf_leso`) integrate their observer this way every sample; the numbers here are
theirs (`li_dtp`, $T_s = 100\,\mu$s).

Every function is a Taylor polynomial and doublings with static shapes and no division
(jit-, vmap- and grad-friendly, smooth through coinciding and zero eigenvalues):

- **2x2 matrices** (`phi_pair`, `phi_pair_apply`): $X = \mu I + N$ with $N^2 = dI$, so
  every function of $X$ is a pair of complex numbers in the algebra of $I$ and $N$;
  $\varphi_2$ alone by Horner's rule (degree 14), $\varphi_1$ and $e^X$ from it;
  directly at $X$ while the bound `pair_radius` $= |\mathrm{Re}\,\mu| +
  |\mathrm{Im}\,\mu| + (|\mathrm{Re}\,d| + |\mathrm{Im}\,d|)^{1/2}$ on its eigenvalues
  $\mu \pm \sqrt d$ is at most `PAIR_NORM` = 0.5 (0.19 for the C-LESO, 0.05 for the
  FA-LESO; truncation below $4\times10^{-18}$), otherwise at $X/8$ followed by three
  doublings.
- **Larger matrices, applied to one vector** (`phi_apply`): while the row-sum norm of
  $X$ in the caller's units is at most `ACTION_NORM` = 0.5 (the GI-LESO: about
  $3\omega_0T_s$, 0.47), the Taylor series of the action (the exponential of the
  augmented matrix $[[X, g_1, g_0], [0, 0, 1], [0, 0, 0]]$ applied to $[y; 0; 1]$) of
  degree 14 by Horner's rule (one matrix-vector product a degree; truncation below
  $4\times10^{-17}$), otherwise the three matrix functions (`phi_matrix`: balanced,
  degree 12, five doublings).

Both switches are `switched`: a `lax.cond`, with one branch for the whole batch under
`vmap`. Exact to round-off for eigenvalues (balanced norms) of $X$ up to about 8, far
beyond the designs' $|X| \approx 0.2$ (`tests/test_li_leso.py` checks both sides of
each switch against `scipy.linalg.expm`).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp


def _pair_mul(x, y, d):
    """The product of two elements `aI + bN` of the algebra of a 2x2 matrix `N` with
    `N @ N = d I`, each given as `(a, b)`."""
    return (x[0] * y[0] + d * (x[1] * y[1]), x[0] * y[1] + x[1] * y[0])


def phi_pair(mu, d, order: int = 14, squarings: int = 3):
    r"""$e^Y$, $\varphi_1(Y)$, $\varphi_2(Y)$ ($\varphi_1(z) = (e^z - 1)/z$,
    $\varphi_2(z) = (e^z - 1 - z)/z^2$) of the 2x2 matrix $Y = \mu I + N$ with
    $N^2 = dI$, each as the pair `(a, b)` of $aI + bN$.

    Every function of $Y$ lies in the two-dimensional algebra spanned by $I$ and $N$:
    a product costs five complex multiplications, a product with $Y$ three. At
    $Y_s = Y/2^s$: the Taylor polynomial of degree `order` of $\varphi_2(Y_s) =
    \sum_j Y_s^j/(j + 2)!$ by Horner's rule (one product with $Y_s$ a degree), then
    $\varphi_1 = I + Y_s\varphi_2$ and $e^{Y_s} = I + Y_s\varphi_1$ (no cancellation at
    $|Y_s| \le 1$); then `squarings` doublings ($e^{2Y} = (e^Y)^2$,
    $2\varphi_1(2Y) = \varphi_1(Y)(e^Y + I)$, $4\varphi_2(2Y) = \varphi_2(Y)(e^Y + I) +
    \varphi_1(Y)$). The truncation depends on the eigenvalues $\mu \pm \sqrt d$ only (not
    on how non-normal $Y$ is): below round-off for $|\mu| + |\sqrt d|$ up to 8 (degree 14
    at $|Y_s| \le 1$: $1/17! = 3\times10^{-15}$). No division, no square root: exact and
    smooth through coinciding eigenvalues ($d = 0$, the C-LESO) and zero ones."""
    sc = 2.0 ** -squarings
    m, dd = mu * sc, d * (sc * sc)  # Y_s = m I + M with M = N / 2^s, M^2 = dd I
    inv_f = [1.0 / math.factorial(j + 2) for j in range(order + 1)]

    def times_y(x, c0):  # x Y_s + c0 I
        return (x[0] * m + dd * x[1] + c0, x[0] + x[1] * m)

    E2 = (inv_f[order] * m + inv_f[order - 1], inv_f[order] + 0.0 * m)
    for j in range(order - 2, -1, -1):
        E2 = times_y(E2, inv_f[j])
    E1 = times_y(E2, 1.0)
    E0 = times_y(E1, 1.0)
    E0, E1, E2 = [(e[0], e[1] * sc) for e in (E0, E1, E2)]  # back to the basis I, N
    for _ in range(squarings):
        E0p1 = (E0[0] + 1.0, E0[1])
        E2 = _pair_mul(E2, E0p1, d)
        E2 = (0.25 * (E2[0] + E1[0]), 0.25 * (E2[1] + E1[1]))
        E1 = _pair_mul(E1, E0p1, d)
        E1 = (0.5 * E1[0], 0.5 * E1[1])
        E0 = (E0[0] * E0[0] + d * (E0[1] * E0[1]), 2.0 * (E0[0] * E0[1]))
    return E0, E1, E2


def balance(X, n_sweeps: int = 4):
    """A diagonal `D` equalising the row and column norms of `D^-1 X D` off the diagonal
    (as LAPACK's balancing does: the states differ in size by orders of magnitude, A vs
    A/s). The similarity is exact for any diagonal, so it is held constant for
    differentiation."""
    n = X.shape[0]
    off = jnp.abs(X) * (1.0 - jnp.eye(n, dtype=jnp.abs(X).dtype))
    d = jnp.ones(n, off.dtype)
    for _ in range(n_sweeps):
        Mb = off * d[None, :] / d[:, None]
        r, c = jnp.sum(Mb, 1), jnp.sum(Mb, 0)
        ok = (r > 0) & (c > 0)
        d = d * jnp.where(ok, jnp.sqrt(jnp.where(ok, r / jnp.where(ok, c, 1.0), 1.0)), 1.0)
    return jax.lax.stop_gradient(d)


def phi_matrix(X, order: int = 12, squarings: int = 5):
    r"""$e^X$, $\varphi_1(X)$, $\varphi_2(X)$ of a small complex matrix: balanced
    (`balance`), a Taylor polynomial of degree `order` of $X/2^s$, then `squarings`
    doublings as in `phi_pair`. All shapes and loop counts are static (no branches);
    the truncation is below round-off for balanced norms up to 8."""
    n = X.shape[0]
    d = balance(X)
    Xs = (X * (d[None, :] / d[:, None])) * 2.0 ** -squarings
    eye = jnp.eye(n, dtype=X.dtype)
    P = eye
    E = [eye, eye, 0.5 * eye]
    fact = [1.0, 1.0, 2.0]
    for k in range(1, order + 1):
        P = P @ Xs
        fact = [fact[0] * k, fact[1] * (k + 1), fact[2] * (k + 2)]
        E = [e + P / f for e, f in zip(E, fact)]
    E0, E1, E2 = E
    for _ in range(squarings):
        E0p1 = E0 + eye
        E2 = 0.25 * (E2 @ E0p1 + E1)
        E1 = 0.5 * (E1 @ E0p1)
        E0 = E0 @ E0
    back = d[:, None] / d[None, :]
    return E0 * back, E1 * back, E2 * back


#: The Taylor action (`phi_action`) is used while the scaled norm of X is at most this;
#: its degree makes the truncation below round-off there:
#: 0.5^15/15! e^0.5 = 4e-17 (the remainder of the series bounded by the norm).
ACTION_NORM = 0.5
ACTION_ORDER = 14


def phi_action(X, y, g0, g1, order: int = ACTION_ORDER):
    r"""$e^X y + \varphi_1(X)g_0 + \varphi_2(X)g_1$ by its Taylor series
    $\sum_k X^k c_k$, $c_k = y/k! + g_0/(k+1)! + g_1/(k+2)!$ (the action of the
    exponential of the augmented matrix $[[X, g_1, g_0], [0, 0, 1], [0, 0, 0]]$ on
    $[y; 0; 1]$), by Horner's rule: one matrix-vector product a degree, no matrix
    products. The truncation is below round-off for a (diagonally scaled) norm of $X$ up
    to `ACTION_NORM`; the products are invariant to the diagonal scaling (no
    cancellation there), so it is applied to $X$ as it is."""
    inv = [1.0 / math.factorial(k) for k in range(order + 3)]
    v = y * inv[order] + g0 * inv[order + 1] + g1 * inv[order + 2]
    for k in range(order - 1, -1, -1):
        v = jnp.sum(X * v[..., None, :], -1) + (y * inv[k] + g0 * inv[k + 1]
                                                + g1 * inv[k + 2])
    return v


def _phi_full(X, y, g0, g1):
    E0, E1, E2 = phi_matrix(X)
    return E0 @ y + E1 @ g0 + E2 @ g1


def switched(cheap, full, limit: float):
    """`f(*args, rho)`: `cheap(*args)` where `rho <= limit`, else `full(*args)` (same
    values to round-off on either side; `rho` is a bound held constant for
    differentiation).

    Plainly a `lax.cond`. Under `vmap` a `cond` on a batched predicate would evaluate
    both branches (a select): a batching rule (`custom_vmap`) takes one branch for the
    whole batch instead, the cheap one only if it holds for every member, so the cheap
    path is not paid for twice. That rule has no reverse mode: a `custom_jvp`
    differentiates through the plain `cond` (same values)."""

    def plain(*a):
        return jax.lax.cond(a[-1] <= limit, lambda o: cheap(*o), lambda o: full(*o),
                            a[:-1])

    @jax.custom_batching.custom_vmap
    def batched(*a):
        return plain(*a)

    @batched.def_vmap
    def _rule(axis_size, in_batched, *a):
        a = [x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))
             for x, b in zip(a, in_batched)]
        out = jax.lax.cond(jnp.all(a[-1] <= limit), lambda o: jax.vmap(cheap)(*o),
                           lambda o: jax.vmap(full)(*o), a[:-1])
        return out, jax.tree_util.tree_map(lambda _: True, out)

    @jax.custom_jvp
    def f(*a):
        return batched(*a)

    @f.defjvp
    def _jvp(primals, tangents):
        return jax.jvp(plain, primals, tangents)

    return f


_phi_switched = switched(phi_action, _phi_full, ACTION_NORM)


def phi_apply(X, y, g0, g1, rho):
    r"""$e^X y + \varphi_1(X)g_0 + \varphi_2(X)g_1$ for a complex $X$ whose diagonally
    scaled norm is `rho`: the Taylor action (`phi_action`) where `rho <= ACTION_NORM`,
    else the balanced matrix functions (`phi_matrix`); `switched` (one branch for a
    batch under `vmap`, derivatives through the plain `cond`)."""
    return _phi_switched(X, y, g0, g1, rho)


#: The pair functions skip the doublings (`phi_pair` at `squarings=0`) while the bound
#: `pair_radius` on the eigenvalues of X is at most this (the degree stays 14): the
#: remainders of the three series there, and of their first derivatives (which set the
#: coefficient of N), are below 15 * 0.5^14/17! e^0.5 = 4e-18.
PAIR_NORM = 0.5


def pair_radius(mu, d):
    r"""An upper bound on the moduli of the eigenvalues $\mu \pm \sqrt d$ of
    $\mu I + N$ ($N^2 = dI$): $|\mathrm{Re}\,\mu| + |\mathrm{Im}\,\mu| +
    (|\mathrm{Re}\,d| + |\mathrm{Im}\,d|)^{1/2}$ (one square root), held constant."""
    mu, d = jax.lax.stop_gradient(mu), jax.lax.stop_gradient(d)
    return (jnp.abs(jnp.real(mu)) + jnp.abs(jnp.imag(mu))
            + jnp.sqrt(jnp.abs(jnp.real(d)) + jnp.abs(jnp.imag(d))))


_phi_pair_switched = switched(lambda mu, d: phi_pair(mu, d, squarings=0), phi_pair,
                               PAIR_NORM)


def phi_pair_apply(mu, d):
    """`phi_pair(mu, d)`: the series directly at $Y$ (no doublings) where
    `pair_radius(mu, d) <= PAIR_NORM`, else with three doublings (`switched`)."""
    return _phi_pair_switched(mu, d, pair_radius(mu, d))

