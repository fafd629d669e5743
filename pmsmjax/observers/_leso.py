r"""Back-EMF linear extended-state observers of li-fa-leso: C-LESO, GI-LESO and FA-LESO.

Reference: Y. Li, Y. Hu, X. Ma, L. Liu, "Sensorless Control of Dual Three-Phase IPMSM
Based on Frequency Adaptive Linear Extended State Observer" (li-fa-leso).

**Model.** The equivalent back-EMF model li-fa-leso (4)-(6) in the stationary frame (for a
dual three-phase machine: its alpha-beta subspace),
$L_q\,di_{ab}/dt = u_{ab} - R_s i_{ab} - e_{ab}$, $e_{ab} = \omega[\psi_f + (L_d - L_q)
i_d][-\sin\theta, \cos\theta]^T$, with $x_1 = i_{ab}$, $x_2 = -e_{ab}/L_q$ (7)-(8). The
LESO with gain functions $l_1(t)$, $l_2(t)$ (9) estimates $\hat e_{ab} = -\hat L_q\hat x_2$
(10); its transfer function is li-fa-leso (14),
$\hat e/e = L_2(s)/(s^2 + (\mu + L_1(s))s + L_2(s))$. Every observer here is that LESO
with $\hat x_1$ written as

$$\dot{\hat x}_1 = \frac{\dot\lambda}{\hat L_q} + \hat x_2 + D_1\varepsilon_1,\qquad
\dot\lambda = u_{ab} - \hat R_s i_{ab},\qquad \varepsilon_1 = \hat x_1 - i_{ab},$$

and the rest of its state $s$ linear in $\varepsilon_1$: $\dot s = A_s s + B_s\varepsilon_1$,
$\hat x_2 = C_s s + D_x\varepsilon_1$ (the $-\mu\hat x_1$ of (9) is $-\mu i - \mu
\varepsilon_1$; its $-\mu\varepsilon_1$ is in $D_1$). Every matrix is made of $2\times2$
blocks $aI + bJ$ (complex coefficients $a + jb$ acting on the space vector), so the
observers are rotation invariant and their transfer functions are complex functions of
$s$: `transfer_function`.

- C-LESO (15)-(17): $l_1 = 2\omega_0 - \mu$, $l_2 = \omega_0^2$: $s = \hat x_2$,
  $\dot{\hat x}_2 = -\omega_0^2\varepsilon_1$, $D_1 = -2\omega_0$.
- GI-LESO (29)-(30): $L_2(s) = \omega_0^2 + G(s)$, $G(s) = 2K_r\omega_c s/(s^2 +
  2\omega_c s + \omega_r^2)$: $s = (\hat x_2, r, q)$ with $\dot r = q$, $\dot q = \varepsilon_1 -
  \omega_r^2 r - 2\omega_c q$, $\dot{\hat x}_2 = -\omega_0^2\varepsilon_1 - 2K_r\omega_c q$;
  $\omega_r$ is the estimated speed (`resonance="estimated"`, the default) or fixed
  (`"fixed"`, Table II's $\hat\omega_e = 100\pi$ on `li_dtp`).
- FA-LESO (25)-(28): $L_1 = -j\hat\omega - \mu$, $L_2 = k_1 + k_2 s$: $s = z$ with
  $\hat x_2 = -k_2\varepsilon_1 - z$, $\dot z = k_1\varepsilon_1$, $D_1 = \hat\omega J$.

A `QuadraturePLL` (`_pll.py`) turns $\hat e_{ab}$ into $\hat\theta$, $\hat\omega$; the
FA-LESO (and the GI-LESO with `resonance="estimated"`) adapt to that $\hat\omega$.

**Lock, low speed, reversals** (measured, not from the paper; docs "Lock acquisition,
start-up and reversals"): with the PLL's acquisition assist all three lock from any
initial angle and speed estimate (zero and the wrong sign included) on a turning rotor,
within 0.1 s on `li_dtp` at 0.5 p.u. (`analysis.lock_basin`); they keep the lock down to
0.01 p.u. on zhang750 (matched model, ideal sensing); below the PLL's `w_min`
(0.05 p.u.) its loop gain fades. They reverse through zero speed in the closed loop at
about 1700 rad/s^2 (zhang750, 0.5 p.u.); the GI-LESO not at 2500 rad/s^2. At
standstill they cannot see the angle: a drive starts them with `pmsmjax.IfStartup`.

**Discretisation** (at $t_k$ with $i_k$ and the voltage held over $[t_{k-1}, t_k)$):

- $\Delta\lambda = T_s u - \tfrac12 T_s\hat R_s(i_{k-1} + i_k)$: the voltage exactly (ZOH),
  the resistive drop by the trapezoid rule (as zhang2022's flux observers);
- the whole observer ($\hat x_1$ and $s$, a linear system driven by the current and by
  $\dot\lambda$) is integrated *exactly* over the interval with its inputs described in
  the frame that turns at the speed estimate $\hat\omega_{k-1}$: the current as
  $i(t) = e^{\hat\omega tJ}(i_{k-1} + t\delta)$ with $\delta$ chosen so that it ends at
  $i_k$ (a first-order hold in the turning frame), $\dot\lambda$ as
  $e^{\hat\omega tJ}c$ with $c$ chosen so that its integral is $\Delta\lambda$. In that
  turning frame the inputs are polynomials in $t$, so the exact solution needs only
  $e^X$, $\varphi_1(X)$, $\varphi_2(X)$ of the observer's own matrix
  $X = (A_o - j\hat\omega I)T_s$ in complex form (`_transition`; size $1 + n_s/2$: 2 for
  the C-LESO and FA-LESO, whose functions are pairs of complex numbers in the algebra of
  $I$ and $X - \tfrac12\mathrm{tr}X$, 4 for the GI-LESO), by a Taylor polynomial and
  doublings with static shapes and no division (for the pairs: $\varphi_2$ alone by
  Horner's rule, degree 14, $\varphi_1$ and $e^X$ from it; directly at $X$ while the
  bound $|\mathrm{Re}\,\mu| + |\mathrm{Im}\,\mu| + (|\mathrm{Re}\,d| +
  |\mathrm{Im}\,d|)^{1/2}$ on its eigenvalues $\mu \pm \sqrt d$ is at most 0.5 (0.19
  for the C-LESO, 0.05 for the FA-LESO at $T_s = 100\,\mu$s on `li_dtp`; truncation
  below $4\times10^{-18}$), otherwise at $X/8$ followed by three doublings:
  `_phi_pair_apply`, a `lax.cond` as the GI-LESO's below). The GI-LESO needs only the
  action on one vector, $e^Xy + \varphi_1(X)g_0 + \varphi_2(X)g_1$ (the exponential of
  the augmented matrix $[[X, g_1, g_0], [0, 0, 1], [0, 0, 0]]$ applied to $[y; 0; 1]$):
  while the row-sum norm of $X$ in the design's units (`GILESOObserver._complex_scale`,
  about $3\omega_0T_s$: 0.47 at $T_s = 100\,\mu$s on `li_dtp`) is at most 0.5, its Taylor
  series of degree 14 by Horner's rule (one $4\times4$ matrix-vector product a degree;
  truncation below $4\times10^{-17}$), otherwise the three matrix functions (balanced,
  degree 12, five doublings; `_phi_apply`, a `lax.cond`; under `vmap` one branch for the
  whole batch).
  Exact to round-off for eigenvalues (balanced norms) of $X$ up to about 8, far beyond
  the designs' $|X| \approx 0.2$ at $T_s = 100\,\mu$s (`_propagator` assembles the
  real transition matrix; the tests check it against `scipy.linalg.expm` of the real
  augmented system, and `jax.grad` through a replay against finite differences). The
  observer's own dynamics (at a given speed estimate) are integrated exactly, so they stay
  stable for any bandwidth and $T_s$ (only the PLL's update is explicit); the one-step
  Jacobian in error coordinates is $I + T_sA + O(T_s^2)$ (the contract test).

In steady state at constant speed every signal turns at $\omega = \hat\omega$, and then
the rotating hold is exact: the discrete observer has exactly the continuous steady state,
so its gain and phase at the fundamental are those of the continuous transfer functions
(17), (26), (29) with no discretisation error; at harmonics $h\omega$ the hold is not
exact and the discrete response departs from them by $O((h - 1)\omega T_s)$
(`pmsmjax.analysis.bemf_response` computes it from this step).

**Error coordinates** (`error_rhs`): $\varepsilon_1$ and $s$ in the true rotor frame minus
their designed steady state at the true speed and current (`steady_state`), then
$\tilde\theta = \theta - \hat\theta$ and $\tilde\omega = \omega - \hat\omega$. The designed
equilibrium is $\varepsilon_1 = s = 0$, $\tilde\omega = 0$ and $\tilde\theta$ equal to the
observer's phase lag at the fundamental plus the parameter-mismatch offset
(`designed_error`): zero for the FA-LESO with a matched model, $-\arg G(j\omega)$
otherwise.
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._frames import rotate, wrap_angle
from .._plant._params import Drive, PMSMParams
from .._validate import check_positive
from ._base import (
    AbstractObserver,
    ErrorCoordinates,
    Estimate,
    Measurement,
    OperatingPoint,
    PlantPoint,
)
from ._pll import PLL_UNITS, QuadraturePLL


#: Table II of li-fa-leso is given for `li_dtp`, whose rated electrical speed is 100 pi
#: rad/s; `from_drive` scales every rate by w_rated / (100 pi) on other machines.
_W_REF = 100.0 * math.pi


def _blk(a, b=0.0):
    """The 2x2 block a I + b J."""
    a = jnp.asarray(a)
    b = jnp.asarray(b, a.dtype) + 0.0 * a
    return jnp.stack([jnp.stack([a, -b]), jnp.stack([b, a])])


def _rot_blocks(x, theta):
    """Rotate each consecutive 2-vector of `x` (shape (2m,)) by `theta`."""
    return rotate(x.reshape(-1, 2), theta).reshape(-1)


def _to_complex(M):
    """A real matrix of aI + bJ blocks -> the complex matrix of a + jb."""
    return M[0::2, 0::2] + 1j * M[1::2, 0::2]


def _pair_mul(x, y, d):
    """The product of two elements `aI + bN` of the algebra of a 2x2 matrix `N` with
    `N @ N = d I`, each given as `(a, b)`."""
    return (x[0] * y[0] + d * (x[1] * y[1]), x[0] * y[1] + x[1] * y[0])


def _phi_pair(mu, d, order: int = 14, squarings: int = 3):
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


def _balance(X, n_sweeps: int = 4):
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


def _phi_matrix(X, order: int = 12, squarings: int = 5):
    r"""$e^X$, $\varphi_1(X)$, $\varphi_2(X)$ of a small complex matrix: balanced
    (`_balance`), a Taylor polynomial of degree `order` of $X/2^s$, then `squarings`
    doublings as in `_phi_pair`. All shapes and loop counts are static (no branches);
    the truncation is below round-off for balanced norms up to 8."""
    n = X.shape[0]
    d = _balance(X)
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


#: The Taylor action (`_phi_action`) is used while the scaled norm of X is at most this;
#: its degree makes the truncation below round-off there:
#: 0.5^15/15! e^0.5 = 4e-17 (the remainder of the series bounded by the norm).
_ACTION_NORM = 0.5
_ACTION_ORDER = 14


def _phi_action(X, y, g0, g1, order: int = _ACTION_ORDER):
    r"""$e^X y + \varphi_1(X)g_0 + \varphi_2(X)g_1$ by its Taylor series
    $\sum_k X^k c_k$, $c_k = y/k! + g_0/(k+1)! + g_1/(k+2)!$ (the action of the
    exponential of the augmented matrix $[[X, g_1, g_0], [0, 0, 1], [0, 0, 0]]$ on
    $[y; 0; 1]$), by Horner's rule: one matrix-vector product a degree, no matrix
    products. The truncation is below round-off for a (diagonally scaled) norm of $X$ up
    to `_ACTION_NORM`; the products are invariant to the diagonal scaling (no
    cancellation there), so it is applied to $X$ as it is."""
    inv = [1.0 / math.factorial(k) for k in range(order + 3)]
    v = y * inv[order] + g0 * inv[order + 1] + g1 * inv[order + 2]
    for k in range(order - 1, -1, -1):
        v = jnp.sum(X * v[..., None, :], -1) + (y * inv[k] + g0 * inv[k + 1]
                                                + g1 * inv[k + 2])
    return v


def _phi_full(X, y, g0, g1):
    E0, E1, E2 = _phi_matrix(X)
    return E0 @ y + E1 @ g0 + E2 @ g1


def _switched(cheap, full, limit: float):
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


_phi_switched = _switched(_phi_action, _phi_full, _ACTION_NORM)


def _phi_apply(X, y, g0, g1, rho):
    r"""$e^X y + \varphi_1(X)g_0 + \varphi_2(X)g_1$ for a complex $X$ whose diagonally
    scaled norm is `rho`: the Taylor action (`_phi_action`) where `rho <= _ACTION_NORM`,
    else the balanced matrix functions (`_phi_matrix`); `_switched` (one branch for a
    batch under `vmap`, derivatives through the plain `cond`)."""
    return _phi_switched(X, y, g0, g1, rho)


#: The pair functions skip the doublings (`_phi_pair` at `squarings=0`) while the bound
#: `_pair_radius` on the eigenvalues of X is at most this (the degree stays 14): the
#: remainders of the three series there, and of their first derivatives (which set the
#: coefficient of N), are below 15 * 0.5^14/17! e^0.5 = 4e-18.
_PAIR_NORM = 0.5


def _pair_radius(mu, d):
    r"""An upper bound on the moduli of the eigenvalues $\mu \pm \sqrt d$ of
    $\mu I + N$ ($N^2 = dI$): $|\mathrm{Re}\,\mu| + |\mathrm{Im}\,\mu| +
    (|\mathrm{Re}\,d| + |\mathrm{Im}\,d|)^{1/2}$ (one square root), held constant."""
    mu, d = jax.lax.stop_gradient(mu), jax.lax.stop_gradient(d)
    return (jnp.abs(jnp.real(mu)) + jnp.abs(jnp.imag(mu))
            + jnp.sqrt(jnp.abs(jnp.real(d)) + jnp.abs(jnp.imag(d))))


_phi_pair_switched = _switched(lambda mu, d: _phi_pair(mu, d, squarings=0), _phi_pair,
                               _PAIR_NORM)


def _phi_pair_apply(mu, d):
    """`_phi_pair(mu, d)`: the series directly at $Y$ (no doublings) where
    `_pair_radius(mu, d) <= _PAIR_NORM`, else with three doublings (`_switched`)."""
    return _phi_pair_switched(mu, d, _pair_radius(mu, d))


def _x2(C, Dx, s, eps):
    r"""$\hat x_2 = C s + D_x\varepsilon_1$ on the real layout (2-vectors) for real
    coefficients `C` (one per complex state in `s`) and `Dx`, written out; terms with a
    Python zero coefficient are left out."""
    C = tuple(C) if isinstance(C, (tuple, list)) else (C,)
    terms = [c * v for c, v in zip(C + (Dx,), [s[2 * j:2 * j + 2] for j in range(len(C))]
                                    + [eps]) if not (isinstance(c, (int, float)) and c == 0)]
    return sum(terms[1:], terms[0])


def _cplx(v):
    """A real vector of consecutive 2-vectors -> the complex vector."""
    return v[0::2] + 1j * v[1::2]


def _real(z):
    """A complex vector -> the real vector of consecutive (re, im) pairs."""
    return jnp.stack([z.real, z.imag], -1).reshape(-1)


class LESOState(eqx.Module):
    """State of the li-fa-leso observers.

    - `s`: internal states (C-LESO: $\\hat x_2$ (A/s); GI-LESO: $\\hat x_2$, $r$ (A s^2),
      $q$ (A s); FA-LESO: $z$ (A/s)), stationary frame, `(n_s,)`.
    - `x1`: estimated current $\\hat x_1$ (A, stationary frame).
    - `theta`: PLL angle (rad, wrapped); `w`: PLL speed (rad/s, electrical).
    - `i_prev`: current sampled at the previous instant (A).
    - `started`: False until the first sample has been seen.
    """

    s: jnp.ndarray
    x1: jnp.ndarray
    theta: jnp.ndarray
    w: jnp.ndarray
    i_prev: jnp.ndarray
    started: jnp.ndarray


_EXTRAS = {"e_ab_hat": "V, estimated equivalent back-EMF li-fa-leso (10), stationary "
                       "frame (2,)"}


class AbstractBackEMFLESO(AbstractObserver):
    """Shared machinery of the li-fa-leso observers (see the module docstring).

    Subclasses give `_matrices(w_hat) -> (A_s, B_s, C_s, D_x, D_1)`, the design
    (`_own_design`) and the names of their internal states.
    """

    motor: eqx.AbstractVar[PMSMParams]
    pll: eqx.AbstractVar[QuadraturePLL]
    n_s: ClassVar[int] = 2
    extras: ClassVar[dict[str, str]] = _EXTRAS

    # --- the model --------------------------------------------------------------------
    @abc.abstractmethod
    def _matrices(self, w_hat):
        """`(A_s, B_s, C_s, D_x, D_1)` at speed estimate `w_hat` (rad/s)."""

    @abc.abstractmethod
    def _own_design(self) -> dict:
        ...

    def transfer_function(self, s, w_hat):
        r"""The continuous-time transfer function $\hat e_{ab}/e_{ab}$ (complex) at the
        complex frequency(ies) `s` (rad/s) for the speed estimate `w_hat` (rad/s), from the
        observer's own matrices: $G = H/(H + D_1 - s)$ with
        $H(s) = C_s(sI - A_s)^{-1}B_s + D_x$ (li-fa-leso (14) in this realisation)."""
        A, B, C, Dx, D1 = (_to_complex(M) for M in self._matrices(jnp.asarray(w_hat, float)))
        s = jnp.asarray(s, complex)

        def one(sv):
            n = A.shape[0]
            H = C @ jnp.linalg.solve(sv * jnp.eye(n, dtype=complex) - A, B) + Dx
            return (H / (H + D1 - sv))[0, 0]

        return jax.vmap(one)(s.reshape(-1)).reshape(s.shape)

    def _psi_ex(self, i_ab, theta):
        """Model extended flux $\\hat\\psi_f + (\\hat L_d - \\hat L_q)\\hat i_d$ (V s)."""
        m = self.motor
        # park(i_ab, theta)'s d component, written with cos and sin of `theta` (which the
        # PLL computes too: one evaluation for both)
        i_d = i_ab[..., 0] * jnp.cos(theta) + i_ab[..., 1] * jnp.sin(theta)
        return m.psi_f + (m.L_d - m.L_q) * i_d

    # --- running ----------------------------------------------------------------------
    def init(self, theta0=0.0, w0=0.0) -> LESOState:
        theta0, w0 = jnp.asarray(theta0), jnp.asarray(w0)
        dtype = jnp.result_type(theta0, w0, float)
        return LESOState(s=jnp.zeros(self.n_s, dtype), x1=jnp.zeros(2, dtype),
                         theta=wrap_angle(theta0.astype(dtype)), w=w0.astype(dtype),
                         i_prev=jnp.zeros(2, dtype), started=jnp.asarray(False))

    def _complex_system(self, w_hat):
        r"""The observer in complex form (`_to_complex` of `_matrices`) at speed estimate
        `w_hat`, as `(Ao, g_i, C, Dx)`: $\dot y = A_o y + g_i i + g_c\dot\lambda$ with
        $y = [x_1, s]$, $A_o = [[D_x + D_1, C], [B, A]]$, $g_i = -[D_x + D_1; B]$, and
        $\hat x_2 = Cs + D_x\varepsilon_1$. Subclasses write it from their coefficients
        directly (complex scalars, or constant patterns times scalars), so that the step
        builds no block matrices; this generic version slices `_matrices`."""
        A, B, C, Dx, D1 = (_to_complex(M) for M in self._matrices(w_hat))
        K = Dx + D1
        return jnp.block([[K, C], [B, A]]), -jnp.concatenate([K, B])[:, 0], C[0], Dx[0, 0]

    def _transition_c(self, w_hat, T_s, y, i0, dl, c, rot=None):
        r"""`_transition` in complex form: the complex state `y` (size $p$) one period on
        (stationary frame), from the complex current `i0`, its hold slope `dl` and the
        voltage-integral rate `c`; `rot` is $e^{j\hat\omega T_s}$ if the caller has it."""
        T = jnp.asarray(T_s, jnp.real(i0).dtype)
        Ao, g_i, _, _ = self._complex_system(w_hat)
        jwT = jax.lax.complex(jnp.zeros_like(T), -jnp.asarray(w_hat, T.dtype) * T)
        inv_lq = 1.0 / self.motor.L_q
        if isinstance(Ao, tuple):  # p = 2: the four entries as complex scalars
            (k, cc), (b, a) = Ao
            mu = 0.5 * (k + a) * T + jwT
            n00, n01, n10 = 0.5 * (k - a) * T, cc * T, b * T  # N = X - mu I, traceless
            E0, E1, E2 = _phi_pair_apply(mu, n00 * n00 + n01 * n10)
            # as vectors of the two components (one kernel for the whole transition;
            # written on scalars XLA computed it once for each component)
            yv = jnp.stack(y, -1)
            g0 = jnp.stack([T * (g_i[0] * i0 + inv_lq * c), T * (g_i[1] * i0)], -1)
            g1 = (T * T) * (jnp.stack([g_i[0], g_i[1] + 0.0 * g_i[0]], -1) * dl[..., None])
            ua = E0[0][..., None] * yv + E1[0][..., None] * g0 + E2[0][..., None] * g1
            ub = E0[1][..., None] * yv + E1[1][..., None] * g0 + E2[1][..., None] * g1
            out = ua + jnp.stack([n00 * ub[..., 0] + n01 * ub[..., 1],
                                  n10 * ub[..., 0] - n00 * ub[..., 1]], -1)
            rot = jnp.exp(-jwT) if rot is None else rot
            out = rot[..., None] * out
            return out[..., 0], out[..., 1]
        p = Ao.shape[0]
        X = Ao * T + jwT * jnp.eye(p, dtype=Ao.dtype)
        g_c = jnp.zeros(p, Ao.dtype).at[0].set(inv_lq)
        g0, g1 = T * (g_i * i0 + g_c * c), (T * T) * (g_i * dl)
        d = jax.lax.stop_gradient(self._complex_scale(w_hat).astype(T.dtype))
        rho = jnp.max(jnp.sum(jnp.abs(X) * (d[None, :] / d[:, None]), 1))
        rot = jnp.exp(-jwT) if rot is None else rot
        return rot * _phi_apply(X, y, g0, g1, jax.lax.stop_gradient(rho))

    def _transition(self, w_hat, T_s, v):
        r"""The state `[x1, s]` one period after `v = [x1, s, i, delta, c]` (real, `(n_s +
        8,)`), the observer driven by the current $i(t) = e^{\hat\omega tJ}(i +
        t\,\delta)$ and the voltage-integral rate $e^{\hat\omega tJ}c$ (see the module
        docstring), integrated exactly.

        In complex form (`_complex_system`) the observer is $\dot y = A_o y + g_i\,i(t) +
        g_c\,c(t)$ with $y = [x_1, s]$ of size $p = 1 + n_s/2$; in the frame turning at
        $\hat\omega$, $\hat y = e^{-j\hat\omega t}y$, the inputs are a polynomial in $t$,
        so with $X = (A_o - j\hat\omega I)T_s$:
        $y(T_s) = e^{j\hat\omega T_s}[e^X y + T_s\varphi_1(X)(g_i i + g_c c) +
        T_s^2\varphi_2(X)g_i\delta]$. For $p = 2$ (C-LESO, FA-LESO) the three functions
        of $X$ are pairs of complex numbers (`_phi_pair`); for the GI-LESO the sum is
        evaluated as one action (`_phi_apply`: a Taylor series of the action where the
        scaled norm of $X$ is small, the $4\times4$ matrix functions `_phi_matrix`
        otherwise). `step` calls `_transition_c` on the complex state directly."""
        p = 1 + self.n_s // 2
        z = _cplx(v)
        y = z[:p]
        out = self._transition_c(w_hat, T_s, tuple(y) if p == 2 else y, z[p], z[p + 1],
                                 z[p + 2])
        out = jnp.stack(out) if isinstance(out, tuple) else out
        return _real(out).astype(v.dtype)

    def _complex_scale(self, w_hat):
        """A diagonal scaling of the complex state `[x1, s]` (its units) under which the
        norm of `X` measures the Taylor truncation (`_phi_apply`)."""
        return jnp.ones(1 + self.n_s // 2, jnp.result_type(w_hat, float))

    def _propagator(self, w_hat, T_s):
        """The exact transition matrix over one period, `(n_s + 2, n_s + 8)`: rows of
        `[x1, s]`, columns of `[x1, s, i, delta, c]` (`_transition` of each unit vector;
        for analysis and tests, `step` calls `_transition`)."""
        dtype = jnp.result_type(w_hat, float)
        eye = jnp.eye(self.n_s + 8, dtype=dtype)
        return jax.vmap(lambda v: self._transition(w_hat, T_s, v), out_axes=1)(eye)

    def step(self, state: LESOState, meas: Measurement, T_s):
        # the hold and the transition on complex scalars (space vectors), with the
        # coefficients written directly, so that XLA fuses the step into few kernels
        m = self.motor
        dtype = state.x1.dtype
        cx = lambda v: jax.lax.complex(v[..., 0], v[..., 1])  # noqa: E731
        i_k = cx(jnp.asarray(meas.i_ab).astype(dtype))
        u = cx(jnp.asarray(meas.u_ab).astype(dtype))
        i_prev, x1 = cx(state.i_prev), cx(state.x1)
        s = state.s
        s_c = [jax.lax.complex(s[2 * j], s[2 * j + 1]) for j in range(self.n_s // 2)]
        w_hat = state.w
        T = jnp.asarray(T_s, dtype)
        _, _, C, Dx = self._complex_system(w_hat)
        d_lam = T * u - (0.5 * T * m.R_s) * (i_prev + i_k)
        # the rate of lambda held in the turning frame, with the same integral d_lam:
        # int_0^T exp(w t J) c dt = T sinc(w T / 2) exp(w T J / 2) c
        # (one cosine and sine of the half angle serve the hold and the transition's
        # turn e^{j w_hat T} = h^2)
        half = 0.5 * T * w_hat
        sin_h = jnp.sin(half)
        h = jax.lax.complex(jnp.cos(half), sin_h)
        small = jnp.abs(half) < 1e-4  # sin(x)/x = 1 - x^2/6 + x^4/120: below round-off
        half_s = jnp.where(small, 1.0, half)
        sinc = jnp.where(small, 1.0 - half * half / 6.0, sin_h / half_s)
        c = d_lam * jnp.conj(h) / (T * sinc)
        # the current between the samples: turning at w_hat, linear in that frame
        rot = h * h
        delta = (i_k * jnp.conj(rot) - i_prev) / T
        if self.n_s == 2:
            out = self._transition_c(w_hat, T, (x1, s_c[0]), i_prev, delta, c, rot)
        else:
            out = self._transition_c(w_hat, T, jnp.stack([x1] + s_c), i_prev, delta, c,
                                     rot)
            out = [out[j] for j in range(1 + self.n_s // 2)]
        # back to the real layout [x1, s] as one array: every consumer reads it (XLA
        # would otherwise duplicate the transition's graph into each of them)
        z = _real(jnp.stack(out)).astype(dtype)
        x1_new, s_new = z[:2], z[2:]
        i_k = jnp.asarray(meas.i_ab).astype(dtype)
        go = state.started
        # first sample: the estimated current starts at the measured one, the extended
        # states at zero (no back-EMF assumed)
        s_new = jnp.where(go, s_new, jnp.zeros_like(s_new)).astype(state.s.dtype)
        x1_new = jnp.where(go, x1_new, i_k)
        e_hat = -m.L_q * _x2(C, Dx, s_new, x1_new - i_k)
        # the estimate one period earlier, from the previous state (zero before the
        # first two samples: the PLL's acquisition assist is off until then)
        e_prev = -m.L_q * _x2(C, Dx, state.s, state.x1 - state.i_prev)
        theta, w = self.pll.step(state.theta, state.w, e_hat,
                                 lambda th: self._psi_ex(i_k, th), T_s, e_prev=e_prev)
        theta = jnp.where(go, theta, state.theta).astype(state.theta.dtype)
        w = jnp.where(go, w, state.w).astype(state.w.dtype)
        new = LESOState(s=s_new, x1=x1_new, theta=theta, w=w, i_prev=i_k,
                        started=jnp.ones_like(state.started))
        return new, Estimate(theta_hat=theta, w_hat=w, extras={"e_ab_hat": e_hat})

    # --- design -----------------------------------------------------------------------
    def design_parameters(self) -> dict:
        return {**self._own_design(), "w_pll": self.pll.w_pll,
                "zeta_pll": self.pll.zeta_pll, "w_min": self.pll.w_min}

    def with_design(self, **values):
        self._check_design_names(values)
        for k, v in values.items():  # every design parameter here is a positive rate
            check_positive(f"{type(self).__name__}.with_design", k, v,
                           self.design_units[k].split(",")[0])
        pll_values = {k: values.pop(k) for k in list(values) if k in PLL_UNITS}
        obs = self._replace(**values) if values else self
        if pll_values:
            obs = eqx.tree_at(lambda o: [getattr(o.pll, k) for k in pll_values], obs,
                              list(pll_values.values()))
        return obs

    # --- analysis ---------------------------------------------------------------------
    def steady_state(self, w, rho_dq):
        r"""The designed steady state $(\varepsilon_1, s)$ in the frame turning at `w`
        (rad/s) with $\hat\omega = \omega$, for the model back-EMF signal
        $\rho = (\dot\lambda - \hat L_q\,di/dt)/\hat L_q$ (A/s; $= e/L_q = -x_2$ with a
        matched model) given in that frame: solves
        $0 = \rho + C_s s + (D_x + D_1 - \omega J)\varepsilon_1$,
        $0 = (A_s - \omega J)s + B_s\varepsilon_1$."""
        A, B, C, Dx, D1 = self._matrices(w)
        n = self.n_s
        dtype = A.dtype
        wJ1 = _blk(0.0 * w, w).astype(dtype)
        wJn = jnp.kron(jnp.eye(n // 2, dtype=dtype), wJ1)
        K = jnp.block([[Dx + D1 - wJ1, C], [B, A - wJn]])
        rhs = jnp.concatenate([-rho_dq, jnp.zeros(n, dtype)])
        sol = jnp.linalg.solve(K, rhs)
        return sol[:2], sol[2:]

    def _rho_steady(self, plant: PMSMParams, w, i_dq):
        """$\\rho$ in the rotor frame at constant speed `w` and rotor-frame current `i_dq`."""
        m = self.motor
        psi = jnp.stack([plant.L_d * i_dq[0] + plant.psi_f, plant.L_q * i_dq[1]])
        J = lambda v: jnp.stack([-v[1], v[0]])  # noqa: E731
        return (w * J(psi) + (plant.R_s - m.R_s) * i_dq - m.L_q * w * J(i_dq)) / m.L_q

    def _steady_truth(self, plant, w, i_dq):
        return self.steady_state(w, self._rho_steady(plant, w, i_dq))

    def error_rhs(self, x, op: OperatingPoint, plant: PMSMParams):
        m = self.motor
        n = self.n_s
        x = jnp.asarray(x)
        a = 2 + n
        w = jnp.asarray(op.w_m, x.dtype)
        i0 = jnp.asarray(op.i_dq, x.dtype)
        th = x[a]  # true angle; the estimated frame is at 0 (rotation invariance)
        w_hat = w - x[a + 1]
        i_ab = i0
        i_dq = rotate(i0, -th)
        eps_s, s_s = self._steady_truth(plant, w, i_dq)
        eps = rotate(x[:2] + eps_s, th)
        s = _rot_blocks(x[2:a] + s_s, th)
        A, B, C, Dx, D1 = self._matrices(w_hat)
        x2_hat = C @ s + Dx @ eps
        e_hat = -m.L_q * x2_hat
        eps_pll = self.pll.error(e_hat, jnp.zeros_like(w), w_hat,
                                 m.psi_f + (m.L_d - m.L_q) * i0[0])
        th_hat_dot, w_hat_dot = self.pll.rates(w_hat, eps_pll)
        J = lambda v: jnp.stack([-v[1], v[0]])  # noqa: E731
        di_ab = th_hat_dot * J(i_ab)
        psi_ab = rotate(jnp.stack([plant.L_d * i_dq[0] + plant.psi_f,
                                   plant.L_q * i_dq[1]]), th)
        di_rel = rotate(di_ab - w * J(i_ab), -th)  # = d i_dq / dt in the rotor frame
        dpsi = w * J(psi_ab) + rotate(jnp.stack([plant.L_d * di_rel[0],
                                                 plant.L_q * di_rel[1]]), th)
        rho = (dpsi + (plant.R_s - m.R_s) * i_ab - m.L_q * di_ab) / m.L_q
        d_eps = rho + x2_hat + D1 @ eps
        d_s = A @ s + B @ eps
        _, (d_eps_s, d_s_s) = jax.jvp(lambda v: self._steady_truth(plant, w, v), (i_dq,),
                                      (di_rel,))
        dx_eps = rotate(d_eps - w * J(eps), -th) - d_eps_s
        d_s_rot = d_s - w * jnp.stack([-s[1::2], s[0::2]], -1).reshape(-1)
        dx_s = _rot_blocks(d_s_rot, -th) - d_s_s
        return jnp.concatenate([dx_eps, dx_s, jnp.stack([w - th_hat_dot, -w_hat_dot])])

    def error_scale(self, op: OperatingPoint, plant: PMSMParams):
        m = self.motor
        w = jnp.asarray(op.w_m, float)
        aw = jnp.abs(w)
        i_mag = jnp.sqrt(jnp.sum(jnp.asarray(op.i_dq) ** 2))
        psi_ref = jnp.abs(m.psi_f) + jnp.abs(m.L_d - m.L_q) * i_mag + m.L_q * i_mag
        w_ref = jnp.maximum(aw, self.pll.w_min)
        rho_ref = jnp.stack([0.0 * w, w_ref * psi_ref / m.L_q])
        eps_s, s_s = self.steady_state(w, rho_ref)
        blocks = jnp.concatenate([eps_s, s_s]).reshape(-1, 2)
        mag = jnp.sqrt(jnp.sum(blocks ** 2, -1))
        mag = jnp.where(mag > 0, mag, 1.0)
        del plant
        return jnp.concatenate([jnp.repeat(mag, 2),
                                jnp.stack([jnp.ones_like(w), jnp.where(aw > 0, aw, 1.0)])])

    def error_state(self, state: LESOState, truth: PlantPoint, plant: PMSMParams):
        th = truth.theta
        i_dq = rotate(truth.i_ab, -th)
        eps_s, s_s = self._steady_truth(plant, truth.w_m, i_dq)
        x_eps = rotate(state.x1 - truth.i_ab, -th) - eps_s
        x_s = _rot_blocks(state.s, -th) - s_s
        return jnp.concatenate([x_eps, x_s, jnp.stack([wrap_angle(th - state.theta),
                                                       truth.w_m - state.w])])

    def observer_state(self, x, truth: PlantPoint, plant: PMSMParams) -> LESOState:
        x = jnp.asarray(x)
        n = self.n_s
        th = truth.theta
        i_ab = jnp.asarray(truth.i_ab, x.dtype)
        i_dq = rotate(i_ab, -th)
        eps_s, s_s = self._steady_truth(plant, truth.w_m, i_dq)
        x1 = i_ab + rotate(x[:2] + eps_s, th)
        s = _rot_blocks(x[2:2 + n] + s_s, th)
        return LESOState(s=s, x1=x1, theta=wrap_angle(th - x[2 + n]),
                         w=truth.w_m - x[3 + n], i_prev=i_ab, started=jnp.asarray(True))

    def designed_error(self, op: OperatingPoint, plant: PMSMParams, n_iter: int = 12):
        r"""The equilibrium of `error_rhs` on the designed branch ($\hat\omega = \omega$,
        $\varepsilon_1$, $s$ at their steady state): the angle error $\tilde\theta$ at
        which the PLL's phase detector is zero, $\tilde\theta = \mathrm{atan2}(\sigma\hat
        e_d, \sigma\hat e_q)$ with $\hat e_{dq}$ the steady-state estimate in the rotor
        frame and $\sigma = \mathrm{sign}\,\omega$. The rotor-frame current
        $e^{-\tilde\theta J}i_0$ depends on $\tilde\theta$ when the model is mismatched,
        so this is iterated (`n_iter` fixed-point steps; exact after one step with a
        matched model). Compiled once per observer (its loop, run op by op, compiled anew
        at every call; the operating point's numbers are its inputs)."""
        return _designed_error(self, jax.tree_util.tree_map(jnp.asarray, op), plant, n_iter)


def _coords(s_names, s_units, s_doc):
    return ErrorCoordinates(
        names=("eps_d", "eps_q", *s_names, "theta", "w"),
        units=("A", "A", *s_units, "rad", "rad/s"), angle=2 + len(s_names),
        doc=("current-estimate error x1_hat - i, rotor frame d axis, minus its designed "
             "steady state", "the same, q axis", *s_doc,
             "angle error theta - theta_hat", "speed error w - w_hat (PLL speed)"))


def _check_motor(owner, motor):
    if not isinstance(motor, PMSMParams):
        raise ValueError(f"`{owner}(motor=...)` must be a `PMSMParams` (the observer's "
                         f"machine model, alpha-beta subspace); got {type(motor).__name__}.")


def _check_pll(owner, pll):
    if not isinstance(pll, QuadraturePLL):
        raise ValueError(f"`{owner}(pll=...)` must be a `QuadraturePLL`; got "
                         f"{type(pll).__name__}.")


def _scale(drive: Drive) -> float:
    return float(drive.w_rated) / _W_REF


@eqx.filter_jit
def _designed_error(obs: AbstractBackEMFLESO, op: OperatingPoint, plant: PMSMParams,
                    n_iter: int):
    """`AbstractBackEMFLESO.designed_error`."""
    m = obs.motor
    n = obs.n_s
    w = jnp.asarray(op.w_m, float)
    i0 = jnp.asarray(op.i_dq, w.dtype)
    sg = jnp.sign(w)
    _, _, C, Dx, _ = obs._matrices(w)

    def body(th, _):
        eps_s, s_s = obs._steady_truth(plant, w, rotate(i0, -th))
        e_dq = -m.L_q * (C @ s_s + Dx @ eps_s)
        return jnp.arctan2(sg * e_dq[0], sg * e_dq[1]), None

    th, _ = jax.lax.scan(body, jnp.zeros((), w.dtype), None, length=n_iter)
    return jnp.zeros(n + 4, w.dtype).at[2 + n].set(th)


class CLESOObserver(AbstractBackEMFLESO):
    r"""Conventional LESO, li-fa-leso (9), (15)-(17), with a quadrature PLL.

    $l_1 = 2\omega_0 - \mu$, $l_2 = \omega_0^2$ (16): $\hat e/e = \omega_0^2/(s^2 +
    2\omega_0 s + \omega_0^2)$ (17), a low-pass whose phase lag
    $2\arctan(\omega/\omega_0)$ becomes the steady-state angle error.

    **Arguments:**

    - `motor`: the observer's machine model (`PMSMParams`; uses $R_s$, $L_q$, and $L_d$,
      $\psi_f$ in the PLL's normalisation).
    - `w0`: observer bandwidth $\omega_0$ (rad/s), > 0.
    - `pll`: `QuadraturePLL`.
    """

    motor: PMSMParams
    w0: float
    pll: QuadraturePLL

    coordinates: ClassVar[ErrorCoordinates] = _coords(
        ("x2_d", "x2_q"), ("A/s", "A/s"),
        ("extended state x2_hat (= -e_hat/L_q) minus its steady state, rotor frame d",
         "the same, q"))
    design_units: ClassVar[dict[str, str]] = {
        "w0": "rad/s, C-LESO bandwidth li-fa-leso (16)", **PLL_UNITS}
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "w0": (0.3, 3.0), "w_pll": (0.25, 4.0), "zeta_pll": (0.5, 2.0)}

    def __init__(self, motor: PMSMParams, w0, pll: QuadraturePLL):
        _check_motor("CLESOObserver", motor)
        _check_pll("CLESOObserver", pll)
        self.motor, self.w0, self.pll = motor, w0, pll

    def __check_init__(self):
        check_positive("CLESOObserver", "w0", self.w0, "rad/s")

    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None, **design):
        """Table II of li-fa-leso on `li_dtp` ($\\omega_0 = 500\\pi$), scaled by
        `w_rated / (100 pi)` elsewhere; PLL `QuadraturePLL.for_speed(w_rated)`."""
        motor = drive.three_phase_motor if motor is None else motor
        obs = cls(motor, 500.0 * math.pi * _scale(drive),
                  QuadraturePLL.for_speed(float(drive.w_rated)))
        return obs.with_design(**design) if design else obs

    def _own_design(self):
        return {"w0": self.w0}

    def _matrices(self, w_hat):
        w0 = jnp.asarray(self.w0) + 0.0 * w_hat
        z = 0.0 * w0
        return (_blk(z), _blk(-w0 ** 2), _blk(1.0 + z), _blk(z), _blk(-2.0 * w0))

    def _complex_system(self, w_hat):
        w0 = jnp.asarray(self.w0, jnp.result_type(w_hat, float))
        k, b = -2.0 * w0, -w0 ** 2
        return ((k, 1.0), (b, 0.0)), (-k, -b), 1.0, 0.0


class GILESOObserver(AbstractBackEMFLESO):
    r"""LESO with a generalised integrator, li-fa-leso (29)-(30), with a quadrature PLL.

    $L_1 = 2\omega_0 - \mu$, $L_2(s) = \omega_0^2 + G(s)$,
    $G(s) = 2K_r\omega_c s/(s^2 + 2\omega_c s + \omega_r^2)$ (30): $\hat e/e =
    (G + \omega_0^2)/(s^2 + 2\omega_0 s + G + \omega_0^2)$ (29), order 4 per axis.
    At $s = j\omega_r$ the integrator's gain is $K_r$, finite: (37)'s
    "$|G(j\hat\omega_e)| \to \infty$" does not hold, and with Table II's
    $K_r = 2\omega_0^2$ the GI-LESO keeps a lag $\arg(3\omega_0^2/(3\omega_0^2 - \omega^2 +
    2j\omega_0\omega))$ at its resonance.

    **Arguments:**

    - `motor`, `pll`: as `CLESOObserver`.
    - `w0`: bandwidth $\omega_0$ (rad/s); `K_r`: integrator gain (rad^2/s^2);
      `w_c`: its attenuation coefficient $\omega_c$ (rad/s); all > 0.
    - `w_r`: fixed resonant frequency (rad/s, used when `resonance="fixed"`), > 0.
    - `resonance`: `"estimated"` ($\omega_r = |\hat\omega|$, the PLL's speed; default)
      or `"fixed"` ($\omega_r$ = `w_r`). The resonance is floored at $\omega_c$ so that
      the integrator stays a damped band-pass at standstill.
    """

    motor: PMSMParams
    w0: float
    K_r: float
    w_c: float
    w_r: float
    pll: QuadraturePLL
    resonance: str = eqx.field(static=True)

    n_s: ClassVar[int] = 6
    coordinates: ClassVar[ErrorCoordinates] = _coords(
        ("x2_d", "x2_q", "r_d", "r_q", "q_d", "q_q"),
        ("A/s", "A/s", "A s^2", "A s^2", "A s", "A s"),
        ("extended state x2_hat minus its steady state, rotor frame d", "the same, q",
         "generalised-integrator state r (dr/dt = q) minus steady state, d", "same, q",
         "generalised-integrator state q minus steady state, d", "same, q"))
    design_units: ClassVar[dict[str, str]] = {
        "w0": "rad/s, LESO bandwidth li-fa-leso (16), (29)",
        "K_r": "rad^2/s^2, generalised-integrator gain li-fa-leso (30)",
        "w_c": "rad/s, generalised-integrator attenuation coefficient li-fa-leso (30)",
        "w_r": "rad/s, fixed resonant frequency (resonance='fixed'; Table II 100 pi)",
        **PLL_UNITS}
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "w0": (0.3, 3.0), "w_pll": (0.25, 4.0), "zeta_pll": (0.5, 2.0)}

    def __init__(self, motor: PMSMParams, w0, K_r, w_c, w_r, pll: QuadraturePLL,
                 resonance: str = "estimated"):
        _check_motor("GILESOObserver", motor)
        _check_pll("GILESOObserver", pll)
        if resonance not in ("estimated", "fixed"):
            raise ValueError(f"`GILESOObserver(resonance=...)` must be 'estimated' or "
                             f"'fixed'; got {resonance!r}.")
        self.motor, self.w0, self.K_r, self.w_c, self.w_r = motor, w0, K_r, w_c, w_r
        self.pll, self.resonance = pll, resonance

    def __check_init__(self):
        for k, u in (("w0", "rad/s"), ("K_r", "rad^2/s^2"), ("w_c", "rad/s"),
                     ("w_r", "rad/s")):
            check_positive("GILESOObserver", k, getattr(self, k), u)

    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None,
                   resonance: str = "estimated", **design):
        """Table II on `li_dtp`: $\\omega_0 = 500\\pi$, $K_r = 2\\omega_0^2$,
        $\\omega_c = \\pi$, $\\omega_r = 100\\pi$ (used with `resonance="fixed"`); every
        rate scaled by `w_rated / (100 pi)` on other machines."""
        motor = drive.three_phase_motor if motor is None else motor
        a = _scale(drive)
        w0 = 500.0 * math.pi * a
        obs = cls(motor, w0, 2.0 * w0 ** 2, math.pi * a, 100.0 * math.pi * a,
                  QuadraturePLL.for_speed(float(drive.w_rated)), resonance=resonance)
        return obs.with_design(**design) if design else obs

    def _own_design(self):
        return {"w0": self.w0, "K_r": self.K_r, "w_c": self.w_c, "w_r": self.w_r}

    def fast_equilibria(self, plant: PMSMParams, op: OperatingPoint, n_grid=None):
        r"""With the resonance at the estimated speed (`resonance="estimated"`): the
        equilibria located on this observer's twin with the resonance fixed at
        $\max(|\omega|, \omega_c)$, their stability from this observer's own Jacobian.
        None with a fixed resonance (the generic route).

        Why the twin has the same equilibria: at an equilibrium the PLL's integrator is at
        rest and the estimated frame turns at the true speed, so $\hat\omega = \omega$,
        and the resonance $\max(|\hat\omega|, \omega_c)$ takes the twin's value there;
        every other equation is the same. The Jacobians differ in the speed-error column
        (the resonance moves with $\hat\omega$), so stability is read from this
        observer's. Why not the generic route directly: its inner least-squares solve at
        fixed angle errors away from the equilibria oscillates for this observer (the
        resonator's gain $K_r$ makes the residual strongly curved in the speed error:
        undamped Gauss-Newton steps then never settle, and every point was reported
        degenerate), while on the twin it converges as for the C-LESO. `n_grid`: the
        generic route's grid (None: its default)."""
        if self.resonance != "estimated":
            return None
        return _gi_twin_equilibria(self, plant, op, n_grid)


    def _matrices(self, w_hat):
        w0 = jnp.asarray(self.w0) + 0.0 * w_hat
        z = 0.0 * w0
        wr = (jnp.abs(w_hat) if self.resonance == "estimated"
              else jnp.asarray(self.w_r) + z)
        wr2 = jnp.maximum(wr ** 2, jnp.asarray(self.w_c) ** 2)
        O, I2 = _blk(z), _blk(1.0 + z)
        A = jnp.block([[O, O, _blk(-2.0 * self.K_r * self.w_c + z)],
                       [O, O, I2],
                       [O, _blk(-wr2), _blk(-2.0 * self.w_c + z)]])
        B = jnp.concatenate([_blk(-w0 ** 2), O, I2], 0)
        C = jnp.concatenate([I2, O, O], 1)
        return A, B, C, O, _blk(-2.0 * w0)

    def _complex_system(self, w_hat):
        # constant patterns times the coefficients (one elementwise expression, no
        # assembly); rows and columns [x1, x2_hat, r, q]
        dt = jnp.result_type(w_hat, float)
        w0 = jnp.asarray(self.w0, dt)
        wr = (jnp.abs(w_hat) if self.resonance == "estimated" else jnp.asarray(self.w_r, dt))
        wr2 = jnp.maximum(wr ** 2, jnp.asarray(self.w_c, dt) ** 2)
        P = _GI_PATTERNS.astype(dt)
        Ao = (P[0] - 2.0 * w0 * P[1] - w0 ** 2 * P[2] - (2.0 * self.K_r * self.w_c) * P[3]
              - wr2 * P[4] - (2.0 * self.w_c) * P[5])
        g_i = 2.0 * w0 * P[1, :, 0] + w0 ** 2 * P[2, :, 0] - P[0, :, 0]
        return Ao, g_i, (1.0, 0.0, 0.0), 0.0

    def _complex_scale(self, w_hat):
        r"""$[1, \omega_0, d_q/\omega_r, d_q]$, $d_q = \sqrt{\omega_0/(2K_r\omega_c)}$:
        scales the cycles $x_1 \leftrightarrow \hat x_2$ ($\omega_0T_s$ each way),
        $r \leftrightarrow q$ ($\omega_rT_s$) and $x_1 \to q \to \hat x_2$ to equal
        entries, so the row-sum norm is about $3\omega_0T_s$ (0.47 at 100 us on
        `li_dtp`)."""
        w0 = jnp.asarray(self.w0) + 0.0 * w_hat
        wr = (jnp.abs(w_hat) if self.resonance == "estimated"
              else jnp.asarray(self.w_r) + 0.0 * w0)
        wr = jnp.sqrt(jnp.maximum(wr ** 2, jnp.asarray(self.w_c) ** 2))
        dq = jnp.sqrt(w0 / (2.0 * self.K_r * self.w_c))
        return jnp.stack([jnp.ones_like(w0), w0, dq / wr, dq])


def _unit(i, j, n=4):
    return np.eye(n)[i][:, None] * np.eye(n)[j][None, :]


#: The GI-LESO's complex observer matrix as constant patterns (`_complex_system`): the
#: ones, then the entries of -2 w0, -w0^2, -2 K_r w_c, -w_r^2, -2 w_c.
_GI_PATTERNS = np.stack([_unit(0, 1) + _unit(2, 3) + _unit(3, 0), _unit(0, 0), _unit(1, 0),
                         _unit(1, 3), _unit(3, 2), _unit(3, 3)])


class FALESOObserver(AbstractBackEMFLESO):
    r"""Frequency-adaptive LESO, li-fa-leso (25)-(28), with a quadrature PLL.

    $L_1(s) = -j\hat\omega - \mu$, $L_2(s) = k_1 + k_2 s$ (25): $\hat e/e = (k_1 + k_2 s)/
    (s^2 - j\hat\omega s + k_1 + k_2 s)$ (26), unity gain and zero phase at
    $s = j\hat\omega$ (19): no steady-state angle error at any constant speed, of either
    sign, with a matched model. Stable for $k_1, k_2 > 0$ at every $\hat\omega$ (22)-(24);
    the generalised Routh array's last entry is $a_2^{(2)} = k_1k_2^2$ (the printed
    (23) drops a factor $k_2$, the sign is the same: `pmsmjax.analysis.routh_complex2`).

    The price of (26) passing DC ($G(0) = 1$): one root of (22) sits near
    $s \approx -k_1/(k_2 - j\hat\omega)$, real part $-k_1k_2/(k_2^2 + \hat\omega^2)$, about
    $-0.08$ 1/s at 25 Hz with Table II's gains: a constant (stationary-frame) error in the
    estimate, e.g. left by a start-up transient, decays with a time constant of about
    10 s. It shows in the linearised error dynamics as a pair at $-0.08 \pm j\omega$
    (`pmsmjax equilibria`), and the tuner's Hurwitz margin penalises it.

    **Arguments:**

    - `motor`, `pll`: as `CLESOObserver`.
    - `k1` (1/s^2), `k2` (1/s): the gains of (25), > 0.
    """

    motor: PMSMParams
    k1: float
    k2: float
    pll: QuadraturePLL

    coordinates: ClassVar[ErrorCoordinates] = _coords(
        ("z_d", "z_q"), ("A/s", "A/s"),
        ("integral state z (x2_hat = -k2 eps - z) minus its steady state, rotor frame d",
         "the same, q"))
    design_units: ClassVar[dict[str, str]] = {
        "k1": "1/s^2, FA-LESO gain k1 li-fa-leso (25)",
        "k2": "1/s, FA-LESO gain k2 li-fa-leso (25)", **PLL_UNITS}
    tunable: ClassVar[dict[str, tuple[float, float]]] = {
        "k1": (0.1, 10.0), "k2": (0.3, 3.0), "w_pll": (0.25, 4.0), "zeta_pll": (0.5, 2.0)}

    def __init__(self, motor: PMSMParams, k1, k2, pll: QuadraturePLL):
        _check_motor("FALESOObserver", motor)
        _check_pll("FALESOObserver", pll)
        self.motor, self.k1, self.k2, self.pll = motor, k1, k2, pll

    def __check_init__(self):
        check_positive("FALESOObserver", "k1", self.k1, "1/s^2")
        check_positive("FALESOObserver", "k2", self.k2, "1/s")

    @classmethod
    def from_drive(cls, drive: Drive, *, motor: PMSMParams | None = None, **design):
        """Table II on `li_dtp`: $k_1 = 10\\pi$, $k_2 = 100\\pi$; scaled as time is
        ($k_1$ by the square, $k_2$ by the ratio `w_rated / (100 pi)`) elsewhere."""
        motor = drive.three_phase_motor if motor is None else motor
        a = _scale(drive)
        obs = cls(motor, 10.0 * math.pi * a ** 2, 100.0 * math.pi * a,
                  QuadraturePLL.for_speed(float(drive.w_rated)))
        return obs.with_design(**design) if design else obs

    def _own_design(self):
        return {"k1": self.k1, "k2": self.k2}

    def _matrices(self, w_hat):
        w_hat = jnp.asarray(w_hat)
        z = 0.0 * w_hat
        return (_blk(z), _blk(self.k1 + z), _blk(-1.0 + z), _blk(-self.k2 + z),
                _blk(z, w_hat))

    def _complex_system(self, w_hat):
        w_hat = jnp.asarray(w_hat)
        dt = jnp.result_type(w_hat, float)
        k2 = jnp.asarray(self.k2, dt)
        k = jax.lax.complex(-k2, w_hat.astype(dt))
        b = jnp.asarray(self.k1, dt)
        return ((k, -1.0), (b, 0.0)), (-k, -b), -1.0, -k2


@eqx.filter_jit
def _gi_twin_equilibria(obs, plant, op, n_grid):
    # `GILESOObserver.fast_equilibria`, one compiled program (inlined under an outer
    # jit): run op by op, the twin's generic route traced its loops anew at every call
    # (about 25 s per operating point)
    from ..analysis._generic import _make_scaled, equilibria_traced, jacobian_readout

    dtype = jnp.result_type(op.w_m, float)
    wr = jnp.maximum(jnp.abs(jnp.asarray(op.w_m, dtype)), jnp.asarray(obs.w_c, dtype))
    twin = GILESOObserver(obs.motor, obs.w0, obs.K_r, obs.w_c, wr, obs.pll,
                          resonance="fixed")
    grid = {} if n_grid is None else {"n_grid": n_grid}
    eq = equilibria_traced(twin, plant, op, method="generic", **grid)
    sys = _make_scaled(obs, plant, op, 1.0)
    z = jnp.where(eq.valid[:, None], eq.x, 0.0) / sys.scale
    A = jax.vmap(jax.jacfwd(sys.F))(z)  # scaled, as the generic route's test
    _, hurwitz, A_si = jacobian_readout(sys, A)
    stable = eq.valid & hurwitz & ~eq.tangent
    return eqx.tree_at(lambda e: (e.stable, e.jacobian), eq,
                       (stable, jnp.where(eq.valid[:, None, None], A_si, jnp.nan)))
