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
- **Larger matrices, applied to one vector** (`phi2_action`): $\varphi_2(X)v$ by the
  Taylor series $\sum_n X^nv/(n+2)!$ and Horner's rule, one product with $X$ a degree,
  the product given by the caller (the GI-LESO writes it on the non-zero entries of its
  $X$ and reduces $e^Xy + \varphi_1(X)g_0 + \varphi_2(X)g_1$ to this one action:
  `GILESOObserver._transition_c`). The degree (`taylor_degree`) makes the truncation
  below the unit round-off of the number type for a row-sum norm of $X$ (in the caller's
  units) up to the branch's bound in `ACTION_NORMS` = (0.5, 3) (the GI-LESO: about
  $3\omega_0T_s$, 0.47 on `li_dtp` at 100 us, 2.4 on `zhang750` at 125 us): 12 and 24 in
  float64, 6 and 14 in float32. Beyond 3, the three matrix functions (`phi_matrix`:
  balanced, degree 12, five doublings).

The switches are `switched`: a `lax.switch`, with one branch for the whole batch under
`vmap`. Exact to round-off for eigenvalues (balanced norms) of $X$ up to about 8, far
beyond the designs' $|X| \approx 0.2$ (`tests/test_li_leso.py` checks every branch of
each switch against `scipy.linalg.expm`).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from .._sim._batching import by_batch


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


#: The row-sum norms of X up to which the Taylor branches of the GI-LESO's transition
#: (`phi2_action` at the degree `taylor_degree` gives for them) serve; beyond the last,
#: the balanced matrix functions (`phi_matrix`).
ACTION_NORMS = (0.5, 3.0)


def taylor_degree(norm: float, dtype) -> int:
    r"""The least degree $N$ whose truncation of $\varphi_2(X)v = \sum_n X^nv/(n+2)!$,
    bounded by the remainder $\sum_{n > N}\rho^n/(n+2)! \le \rho^{N+1}/((N+3)!\,(1 -
    \rho/(N+4)))$ at the row-sum norm $\rho$ = `norm` (relative to $\|v\|$ in the same
    units), is below the unit round-off of `dtype` ($2^{-53}$ in float64, $2^{-24}$ in
    float32): 12 at 0.5 and 24 at 3 in float64, 6 and 14 in float32."""
    u = 0.5 * float(jnp.finfo(dtype).eps)
    n = 0
    while norm ** (n + 1) / (math.factorial(n + 3) * (1.0 - norm / (n + 4))) > u:
        n += 1
    return n


def phi2_action(matvec, v, order: int, unroll: int = 1):
    r"""$\varphi_2(X)v = \sum_{n \le N} X^nv/(n+2)!$ ($N$ = `order`) by Horner's rule,
    $t \leftarrow Xt + v/(n+2)!$ from $t = v/(N+2)!$, where `matvec(t)` is the product
    $Xt$ (the caller's layout of `v`, one array). The degrees run in a loop (`fori_loop`,
    `unroll` of them a pass): written out, XLA fuses the last product with everything
    before it and computes the shared products again for every component."""
    inv = jnp.asarray([1.0 / math.factorial(n + 2) for n in range(order + 1)], v.dtype)

    def body(j, t):
        return matvec(t) + inv[order - 1 - j] * v

    return jax.lax.fori_loop(0, order, body, inv[order] * v, unroll=unroll)


def switched(branches, limits, native=()):
    """`f(*args, rho)`: `branches[i](*args)` for the first `i` with `rho <= limits[i]`
    (ascending), the last branch beyond them (same values to round-off in every branch
    that serves; `rho` is a bound held constant for differentiation).

    Plainly a `lax.switch`. Under `vmap` a switch on a batched index would evaluate
    every branch (a select): a batching rule (`by_batch`) takes one branch for the
    whole batch instead, the one that serves its largest `rho`, so the cheaper branches
    are not paid for on top of it; it calls a branch whose index is in `native` on the
    batch directly (every argument with its batch axis first, unbatched scalars as they
    are: the branch lays the batch out itself), the others under `vmap`, and a batch of
    one as no batch. That rule has no reverse mode: a `custom_jvp`
    differentiates through the plain switch (same values)."""
    branches = tuple(branches)
    limits = tuple(float(x) for x in limits)
    assert len(branches) == len(limits) + 1 and list(limits) == sorted(limits)
    native = set(native)

    def index(rho):
        return sum((rho > x).astype(jnp.int32) for x in limits)

    def plain(*a):
        return jax.lax.switch(index(a[-1]), [lambda o, b=b: b(*o) for b in branches],
                              a[:-1])

    def many(axis_size, in_batched, *a):
        # native branches: unbatched scalars as they are (they broadcast), other
        # unbatched arguments with the batch axis; the others under `vmap`
        on = jax.tree_util.tree_map(
            lambda x, b: x if b or jnp.ndim(x) == 0
            else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)), list(a[:-1]),
            list(in_batched[:-1]))
        axes = jax.tree_util.tree_map(lambda b: 0 if b else None, list(in_batched[:-1]))

        def call(i, b):
            if i in native:
                return lambda o: b(*o[0])
            return lambda o: jax.vmap(b, in_axes=axes)(*o[1])

        return jax.lax.switch(jnp.max(index(a[-1])),
                              [call(i, b) for i, b in enumerate(branches)], (on, a[:-1]))

    return by_batch(plain, many, plain)


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


_phi_pair_switched = switched((lambda mu, d: phi_pair(mu, d, squarings=0), phi_pair),
                              (PAIR_NORM,))


def phi_pair_apply(mu, d):
    """`phi_pair(mu, d)`: the series directly at $Y$ (no doublings) where
    `pair_radius(mu, d) <= PAIR_NORM`, else with three doublings (`switched`)."""
    return _phi_pair_switched(mu, d, pair_radius(mu, d))

