r"""Slowly-varying-speed certificate of zhang2022 §V / Appendix A, computed numerically.

The error dynamics with a time-varying speed, zhang2022 (40), $\dot z = g(z, \omega(t))$, is
exponentially stable at $z = 0$ if (Khalil's Theorem 9.3, quoted as zhang2022 (41)-(45)) a
Lyapunov function $V = z^TP(\omega)z$ with (48) $PA + A^TP = -I$ satisfies zhang2022
(43a)-(43d)
with constants $c_1 \dots c_5$ on a ball $\|z\| < r$ and $|\dot\omega| \le \varepsilon <
c_3/c_5$ (52); then every solution with $\|z(0)\| < r\sqrt{c_1/c_2}$ converges.

This module computes every ingredient for a design, over a dense grid of the operating
range $\Omega = [\omega_{lo}, \omega_{hi}]$, two ways:

- **paper** constants zhang2022 (51)/(55)-(64): $\rho = \max\|A\|_2$; $\gamma$, $k$ with
  $\|e^{tA}\| \le k e^{-\gamma t}$; $c_1 = 1/(2\rho)$, $c_2 = k^2/(2\gamma)$,
  $c_4 = k^2/\gamma$, $c_5 = k^4 b/(2\gamma^2)$ with $b = \max\|\partial A/\partial\omega\|_2$
  computed (the paper's zhang2022 (49) sets $\|\partial A/\partial\omega_0\| = 1$, which is not true
  in general: its value depends on units and on the gain schedule; `c5_paper` keeps b = 1);
- **sharp** constants from $P$ itself: $c_1 = \min\lambda_{min}(P)$,
  $c_2 = \max\lambda_{max}(P)$, $c_4 = 2c_2$, $c_5 = \max\|P'(\omega)\|_2$ with $P'$ by
  `jax.jacfwd` through the Lyapunov solve.

$c_3$ and the radius $r$ come from (59): $\dot V \le -\|z\|^2 + 2c_2k_1\|z\|^3$, where
$k_1 = \max \|g(z,\omega) - A z\|/\|z\|^2$ over $\|z\| \le r$ and $\omega \in \Omega$ zhang2022 (54)
is estimated by sampling the ball (random directions and radii, every speed of a subgrid)
and refining the best samples by gradient ascent; so $c_3 = 1 - 2c_2k_1r$. For a target
$c_3$ (default 1/2) the largest sampled $r$ is used. The certified rate is
$\varepsilon = c_3/c_5$; $1/c_5$ is its supremum (as $r \to 0$).

Choices and their effect: $\gamma = \alpha\sigma$ with $\sigma = \min_\omega
(-\max\mathrm{Re}\,\lambda(A))$; $k(\gamma) = \max_\omega \sup_t \|e^{tA}\|e^{\gamma t}$
is evaluated on a geometric time grid with local refinement (a grid sup is a lower bound
of the true sup, to about 1e-6 relative after refinement). $k$ grows without bound as
$\gamma \to \sigma$ when $A$ has a Jordan block (the critically damped $\zeta_2 = 1$
design has one), and $c_5 \propto k^4/\gamma^2$, so `alpha` is chosen from a grid to
maximise the paper's bound (when the slowest eigenvalue is simple, as for the zhang2022 (38)
design, $k$ stays bounded as $\alpha \to 1$ and the best $\alpha$ is the largest).

**State scaling.** Norms of $z = [\tilde\psi, \tilde\theta, \tilde\omega]$ mix units, so
every constant and the bound depend on the scaling; `scale="pu"` (default) uses
$z = [\tilde\psi/\psi_b, \tilde\psi/\psi_b, \tilde\theta, \tilde\omega/\omega_b]$ (time
stays in seconds, $\omega$ in rad/s, so $\varepsilon$ is in rad/s^2); `"si"` uses SI.

**Which dynamics.** zhang2022 (40) is zhang2022 (11) with $\omega_0$ replaced by $\omega(t)$ and
the gains
scheduled at $\omega(t)$. The true error dynamics of the observer also contain
$+\dot\omega$ in $\dot{\tilde\omega}$ (the speed is the extended state, (6)'s $h_\delta$)
and schedule the gains at $\hat\omega$: `simulate_ramp(model="observer")`
(`pmsmjax.analysis._ramp`, which validates the certificate by simulation). That forcing
is not covered by zhang2022 (40): a ramp leaves a constant angle error of about
$\dot\omega/\omega_2^2$, so "convergence" there means back to zero after the ramp.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optimistix as optx

from .._plant._params import Drive, PMSMParams
from .._sim._batching import values_as_arrays
from ..observers import (
    AbstractFluxObserver,
    AbstractGainSchedule,
    AbstractObserver,
    ESOObserver,
    LESOObserver,
    OperatingPoint,
)
from ._args import as_arrays
from ._linearize import check_frame, eso_rhs


SCALES = ("pu", "si")


def lyapunov_solve(A, Q=None):
    r"""Solve $PA + A^TP = -Q$ ($Q = I$ by default) for a Hurwitz `A` (`(n, n)`).

    Kronecker form $(I\otimes A^T + A^T\otimes I)\,\mathrm{vec}(P) = -\mathrm{vec}(Q)$,
    an $n^2 \times n^2$ dense solve (16x16 here): exact to rounding, differentiable and
    vmappable. The result is symmetrised.
    """
    A = jnp.asarray(A)
    n = A.shape[-1]
    Q = jnp.eye(n, dtype=A.dtype) if Q is None else jnp.asarray(Q, A.dtype)
    eye = jnp.eye(n, dtype=A.dtype)
    K = jnp.kron(eye, A.T) + jnp.kron(A.T, eye)
    P = jnp.linalg.solve(K, -Q.reshape(-1)).reshape(n, n)
    return 0.5 * (P + P.T)


#: Coefficients b_0 .. b_13 of the [13/13] Pade approximant of exp and the largest
#: 1-norm for which it is accurate to double precision (Higham 2005, "The scaling and
#: squaring method for the matrix exponential revisited", Table 2.3 and (2.1)).
_PADE13 = (64764752532480000.0, 32382376266240000.0, 7771770303897600.0,
           1187353796428800.0, 129060195264000.0, 10559470521600.0, 670442572800.0,
           33522128640.0, 1323241920.0, 40840800.0, 960960.0, 16380.0, 182.0, 1.0)
_THETA13 = 5.371920351148152


def _expm(M):
    """exp(M) of one small matrix by scaling and squaring with the [13/13] Pade
    approximant: `M / 2^s` with `s` the fewest halvings that bring its 1-norm under
    `_THETA13`, then `s` squarings in a `while_loop`.

    `_k_of_gamma` evaluates about 200,000 of these (4 x 4, batched). jax's `expm` under
    `vmap` evaluates all five of its Pade approximants and a fixed number of squarings for
    every matrix (its `switch` and `cond` on batched values become selects): with the 64
    squarings that the long time horizons here need, 3 to 4 times the work of this one.
    tests/test_lyapunov.py checks it against SciPy's `expm` to 1e-10 relative. Under
    `vmap` the loop runs as many squarings as the largest `s` of the batch. A non-finite
    `M` gives NaN."""
    b = _PADE13
    eye = jnp.eye(M.shape[-1], dtype=M.dtype)
    norm1 = jnp.max(jnp.sum(jnp.abs(M), axis=-2))
    s = jnp.maximum(0.0, jnp.ceil(jnp.log2(norm1 / _THETA13)))
    s = jnp.where(jnp.isfinite(norm1), s, 0.0)  # an infinite norm: no endless loop, NaN
    X = jnp.where(jnp.isfinite(norm1), M * jnp.exp2(-s), jnp.nan)
    X2 = X @ X
    X4 = X2 @ X2
    X6 = X4 @ X2
    U = X @ (X6 @ (b[13] * X6 + b[11] * X4 + b[9] * X2)
             + b[7] * X6 + b[5] * X4 + b[3] * X2 + b[1] * eye)
    V = X6 @ (b[12] * X6 + b[10] * X4 + b[8] * X2) + b[6] * X6 + b[4] * X4 + b[2] * X2 \
        + b[0] * eye
    R = jnp.linalg.solve(V - U, V + U)
    _, R = jax.lax.while_loop(lambda c: c[0] < s, lambda c: (c[0] + 1, c[1] @ c[1]),
                              (jnp.zeros((), s.dtype), R))
    return R


def _norm2(M):
    return jnp.sqrt(jnp.max(jnp.linalg.eigvalsh(M.T @ M), -1))


class LyapunovCertificate(eqx.Module):
    """Constants of the slowly-varying certificate for one design (see module docstring).

    Speeds in rad/s, time in s, state in the chosen scaling. `eps*` are admissible speed
    rates |dw/dt| (rad/s^2).

    - `speeds`: the grid of the operating range. `sigma`: min decay rate (1/s);
      `rho` = max ||A||; `b` = max ||dA/dw||; `alpha`, `gamma` (1/s), `k`.
    - paper constants `c1, c2, c3, c4, c5` (with the true `b`), `c5_paper` (b = 1);
      sharp constants `c1_sharp, c2_sharp, c3_sharp, c4_sharp, c5_sharp`.
    - `k1`: the estimate of zhang2022 (54) on the ball of radius `r` (paper) / `r_sharp`.
    - `eps`: c3/c5 (paper constants, true b); `eps_paper`: c3/c5_paper (b = 1);
      `eps_sharp`: c3_sharp/c5_sharp; `eps_sup`, `eps_sup_sharp`: 1/c5, 1/c5_sharp.
    - `r_init`, `r_init_sharp`: certified initial ball r sqrt(c1/c2).
    - `lyap_residual`: max ||PA + A^T P + I|| over the grid; `min_eig_P`.
    - `status`: 0 ok, -1 if A is not uniformly Hurwitz on the range or no r was found.
    """

    speeds: jnp.ndarray
    sigma: jnp.ndarray
    rho: jnp.ndarray
    b: jnp.ndarray
    alpha: jnp.ndarray
    gamma: jnp.ndarray
    k: jnp.ndarray
    c1: jnp.ndarray
    c2: jnp.ndarray
    c3: jnp.ndarray
    c4: jnp.ndarray
    c5: jnp.ndarray
    c5_paper: jnp.ndarray
    c1_sharp: jnp.ndarray
    c2_sharp: jnp.ndarray
    c3_sharp: jnp.ndarray
    c4_sharp: jnp.ndarray
    c5_sharp: jnp.ndarray
    k1: jnp.ndarray
    r: jnp.ndarray
    k1_sharp: jnp.ndarray
    r_sharp: jnp.ndarray
    eps: jnp.ndarray
    eps_paper: jnp.ndarray
    eps_sharp: jnp.ndarray
    eps_sup: jnp.ndarray
    eps_sup_sharp: jnp.ndarray
    r_init: jnp.ndarray
    r_init_sharp: jnp.ndarray
    lyap_residual: jnp.ndarray
    min_eig_P: jnp.ndarray
    status: jnp.ndarray


class _ScaledDynamics(eqx.Module):
    """g(z, w) = D f(D^-1 z, w): the error dynamics of `observer` (its own model,
    `plant` the true machine) at speed w and current `i0` (estimated frame), scaled."""

    observer: AbstractObserver
    plant: PMSMParams
    i0: jnp.ndarray
    d: jnp.ndarray
    frame: str = eqx.field(static=True)
    matched: bool = eqx.field(static=True, default=True)

    def rhs(self, x, w):
        if self.frame == "paper":  # zhang2022 (11) with its rotation term as printed
            a, eta = self.observer.feedback_parameters()
            return eso_rhs(x, w, self.i0, self.observer.linear_gains(w, self.i0),
                           self.plant, self.observer.motor, a, eta, "paper")
        return self.observer.error_rhs(x, OperatingPoint(w, self.i0), self.plant)

    def x_eq(self, w):
        """The equilibrium the certificate is about at speed w: the origin with a matched
        model; with observer-model mismatch the principal (static-error) equilibrium,
        found by Newton steps from the origin (differentiable in w)."""
        x = jnp.zeros_like(self.d)
        if self.matched:
            return x

        def newton(_, x):
            f, J = self.rhs(x, w), jax.jacfwd(self.rhs)(x, w)
            return x - jnp.linalg.solve(J, f)

        # a loop rather than unrolled steps: the certificate differentiates this twice
        # (dA/dw, dP/dw); unrolled, its compilation took twice as long
        return jax.lax.fori_loop(0, 8, newton, x)

    def g(self, z, w):
        xe = self.x_eq(w)
        return self.d * self.rhs(xe + z / self.d, w)

    def A(self, w):
        return jax.jacfwd(self.g)(jnp.zeros_like(self.d), w)


#: per-unit base of each SI unit that error coordinates use (`scale="pu"`).
def _unit_base(drive: Drive, unit: str) -> float:
    b = drive.base
    return {"V s": b.psi_b, "rad/s": b.w_b, "A": b.I_b, "V": b.U_b, "rad": 1.0,
            "H": b.L_b}.get(unit, 1.0)


def _state_scale(drive, observer, scale, dtype):
    units = observer.coordinates.units
    if scale == "pu":
        return jnp.asarray([1.0 / _unit_base(drive, u) for u in units], dtype)
    return jnp.ones(len(units), dtype)


def _as_observer(owner, drive, design, a, eta):
    """An observer from `design`: an `AbstractObserver` as it is, or a zhang2022 gain
    schedule as the ESO (fal `a`, `eta`) or, for `a = 1`, the LESO on the drive's model."""
    if isinstance(design, AbstractObserver):
        return design
    if not isinstance(design, AbstractGainSchedule):
        raise ValueError(f"`{owner}(design=...)` must be an observer (`AbstractObserver`, "
                         f"e.g. `observers.make_observer('leso', drive)`) or a zhang2022 "
                         f"gain schedule (`observers.ESODesign`); got "
                         f"{type(design).__name__}.")
    m = drive.three_phase_motor
    if isinstance(a, int | float) and float(a) == 1.0:
        return LESOObserver(m, design)
    return ESOObserver(m, design, a=a, eta=eta)


def _check(owner, drive, design, speed_range, scale, frame, c3):
    if not isinstance(drive, Drive):
        raise ValueError(f"`{owner}(drive=...)` must be a `Drive`; got {type(drive).__name__}.")
    lo, hi = (float(v) for v in speed_range)
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
        raise ValueError(
            f"`{owner}(speed_range=...)` (p.u.) must be (lo, hi) with 0 < lo < hi: at w = 0 "
            f"the flux gains of zhang2022 (17)/(38) vanish and A is not Hurwitz; got "
            f"{speed_range!r}.")
    if scale not in SCALES:
        raise ValueError(f"`{owner}(scale=...)` must be one of {SCALES}; got {scale!r}.")
    check_frame(owner, frame)
    if frame == "paper" and not isinstance(design, AbstractFluxObserver):
        raise ValueError(f"`{owner}(frame='paper')` is the zhang2022 ESO/LESO/AFO's printed "
                         f"error dynamics (11); {type(design).__name__} has its own.")
    if not 0 < c3 < 1:
        raise ValueError(f"`{owner}(c3=...)` must lie in (0, 1); got {c3!r}.")
    return lo, hi


def _k_of_gamma(A_all, sigma, rho, alphas, n_time):
    """k(gamma) = max over speeds of sup_t ||exp(t (A + gamma I))|| (= ||e^{tA}|| e^{gamma t}),
    gamma = alpha sigma, on a geometric time grid up to 60/(sigma - gamma), refined by
    golden-section search around the grid maximum. A maximum at the end of the grid
    (not reached) gives k = inf."""
    gam = alphas * sigma
    eye = jnp.eye(A_all.shape[-1], dtype=A_all.dtype)

    def per_speed(A):
        def per_gamma(g):
            B = A + g * eye
            T = 60.0 / (sigma - g)
            t = jnp.concatenate([jnp.zeros(1, A.dtype),
                                 jnp.geomspace(1e-3 / rho, 1.0, n_time - 1) * T])
            h = lambda s: _norm2(_expm(s * B))  # noqa: E731
            f = jax.vmap(h)(t)
            j = jnp.argmax(f)
            lo = t[jnp.maximum(j - 1, 0)]
            hi = t[jnp.minimum(j + 1, t.shape[0] - 1)]
            gr = (math.sqrt(5.0) - 1.0) / 2.0

            def body(_, c):
                a, b_ = c
                x1, x2 = b_ - gr * (b_ - a), a + gr * (b_ - a)
                # both points in one batched call: two independent ones could run at the
                # same time, which a batched LAPACK call must not (pmsmjax/_lapack_pool.py)
                h12 = jax.vmap(h)(jnp.stack([x1, x2]))
                left = h12[0] >= h12[1]
                return jnp.where(left, a, x1), jnp.where(left, x2, b_)

            a, b_ = jax.lax.fori_loop(0, 40, body, (lo, hi))
            kk = jnp.maximum(f[j], h(0.5 * (a + b_)))
            return jnp.where(j == t.shape[0] - 1, jnp.inf, kk)

        return jax.vmap(per_gamma)(gam)

    k_all = jax.lax.map(per_speed, A_all)
    return jnp.max(k_all, 0), gam


def _k1_estimate(dyn: _ScaledDynamics, speeds, radii, key, n_dirs, n_refine):
    """k1(r) = max ||g(z,w) - A(w) z|| / ||z||^2 over 0 < ||z|| <= r, for each r in `radii`.

    For each radius: `n_dirs` random points of the ball (uniform directions, radii
    r U^(1/4), half of them on the sphere) at every speed of `speeds`, then
    gradient-ascent refinement (optimistix BFGS) of the best sample inside the ball.
    A sampled maximum is a lower bound of the true one; the refinement makes it tight in
    the cases we checked (the maximum sits on the sphere ||z|| = r).
    """
    kd, kr = jr.split(key)
    v = jr.normal(kd, (n_dirs, 4), dtype=radii.dtype)
    v = v / jnp.linalg.norm(v, axis=-1, keepdims=True)
    frac = jr.uniform(kr, (n_dirs,), dtype=radii.dtype) ** 0.25
    frac = jnp.where(jnp.arange(n_dirs) % 2 == 0, 1.0, frac)
    As = jax.vmap(dyn.A)(speeds)

    def ratio(zz, w, A):
        n2 = jnp.sum(zz ** 2)
        return jnp.linalg.norm(dyn.g(zz, w) - A @ zz) / jnp.where(n2 > 0, n2, 1.0)

    def k1_at(r):
        z = v * (r * frac)[:, None]
        R = jax.vmap(lambda w, A: jax.vmap(lambda zz: ratio(zz, w, A))(z))(speeds, As)
        R = jnp.where(jnp.isfinite(R), R, -jnp.inf)
        iw, iz = jnp.unravel_index(jnp.argmax(R), R.shape)
        best = R[iw, iz]
        w, A = speeds[iw], As[iw]
        # refine with z = r y / sqrt(1 + |y|^2), which keeps z inside the open ball
        f = jnp.minimum(frac[iz], 0.999)
        y0 = v[iz] * f / jnp.sqrt(1.0 - f ** 2)

        def loss(y, _):
            zz = r * y / jnp.sqrt(1.0 + jnp.sum(y ** 2))
            return -ratio(zz, w, A)

        sol = optx.minimise(loss, optx.BFGS(rtol=1e-6, atol=1e-9), y0, max_steps=n_refine,
                            throw=False)
        refined = -loss(sol.value, None)
        return jnp.maximum(best, jnp.where(jnp.isfinite(refined), refined, best))

    return jax.lax.map(k1_at, radii)


@eqx.filter_jit
def _certificate(dyn: _ScaledDynamics, speeds, alphas, radii, c3, key, n_time, n_dirs,
                 n_refine, n_k1_speeds):
    n = dyn.d.shape[0]

    def per_speed(w):
        # One speed at a time (`lax.map`), so that every LAPACK call here is on a single
        # matrix: a batched call over the speeds blocks a thread of XLA's pool, and two of
        # them at once (the P and dP solves did) deadlock a 2-core machine
        # (pmsmjax/_lapack_pool.py). A and dA/dw from one jvp, then P and dP/dw from one.
        A, dA = jax.jvp(dyn.A, (w,), (jnp.ones_like(w),))
        P, dP = jax.jvp(lyapunov_solve, (A,), (dA,))
        return dict(
            A=A, norm_A=_norm2(A), norm_dA=_norm2(dA),
            # the frozen equilibria must exist (with mismatch: static-error equilibria)
            g0=jnp.max(jnp.abs(dyn.g(jnp.zeros_like(dyn.d), w))),
            decay=-jnp.max(jnp.real(jnp.linalg.eigvals(A))),
            res=jnp.max(jnp.abs(P @ A + A.T @ P + jnp.eye(n, dtype=A.dtype))),
            lam=jnp.linalg.eigvalsh(P), c5=jnp.max(jnp.abs(jnp.linalg.eigvalsh(dP))))

    q = jax.lax.map(per_speed, speeds)
    A = q["A"]
    rho = jnp.max(q["norm_A"])
    at_eq = jnp.max(q["g0"]) / jnp.maximum(rho, 1.0) < 1e-8
    sigma = jnp.min(q["decay"])
    hurwitz = sigma > 0
    sig = jnp.where(hurwitz, sigma, 1.0)
    b = jnp.max(q["norm_dA"])
    res = jnp.max(q["res"])
    lam = q["lam"]
    c1s, c2s = jnp.min(lam[:, 0]), jnp.max(lam[:, -1])
    c5s = jnp.max(q["c5"])

    kk, gam = _k_of_gamma(A, sig, rho, alphas, n_time)
    c5_all = kk ** 4 * b / (2 * gam ** 2)
    j = jnp.argmin(jnp.where(jnp.isfinite(c5_all), c5_all, jnp.inf))
    k, gamma, alpha = kk[j], gam[j], alphas[j]
    c1 = 1.0 / (2.0 * rho)
    c2 = k ** 2 / (2.0 * gamma)
    c4 = k ** 2 / gamma
    c5 = c5_all[j]
    c5p = k ** 4 / (2 * gamma ** 2)

    sub = speeds[jnp.linspace(0, speeds.shape[0] - 1, n_k1_speeds).astype(jnp.int32)]
    k1r = _k1_estimate(dyn, sub, radii, key, n_dirs, n_refine)

    def pick(c2_):
        ok = 2.0 * c2_ * k1r * radii <= 1.0 - c3
        idx = jnp.max(jnp.where(ok, jnp.arange(radii.shape[0]), -1))
        return jnp.where(idx >= 0, radii[jnp.maximum(idx, 0)], jnp.nan), \
            k1r[jnp.maximum(idx, 0)], idx >= 0

    r, k1, okr = pick(c2)
    rs, k1s, okrs = pick(c2s)
    status = jnp.where(hurwitz & okr & okrs & jnp.isfinite(c5) & at_eq, 0, -1
                       ).astype(jnp.int32)
    return LyapunovCertificate(
        speeds=speeds, sigma=sigma, rho=rho, b=b, alpha=alpha, gamma=gamma, k=k,
        c1=c1, c2=c2, c3=jnp.asarray(c3), c4=c4, c5=c5, c5_paper=c5p,
        c1_sharp=c1s, c2_sharp=c2s, c3_sharp=jnp.asarray(c3), c4_sharp=2 * c2s,
        c5_sharp=c5s, k1=k1, r=r, k1_sharp=k1s, r_sharp=rs,
        eps=c3 / c5, eps_paper=c3 / c5p, eps_sharp=c3 / c5s, eps_sup=1 / c5,
        eps_sup_sharp=1 / c5s, r_init=r * jnp.sqrt(c1 / c2),
        r_init_sharp=rs * jnp.sqrt(c1s / c2s), lyap_residual=res, min_eig_P=jnp.min(lam),
        status=status)


def slowly_varying_certificate(drive: Drive, design, speed_range=(0.1, 1.0), *,
                               i_dq=(0.0, 0.0), plant: PMSMParams | None = None,
                               frame: str = "observer", a=1.0, eta=1.0, scale: str = "pu",
                               c3: float = 0.5, n_speed: int = 101,
                               alphas=(0.5, 0.8, 0.9, 0.95, 0.98, 0.99, 0.999),
                               n_time: int = 200,
                               radii=None, n_dirs: int = 1024, n_refine: int = 50,
                               n_k1_speeds: int = 11, key=None) -> LyapunovCertificate:
    r"""The certificate of §V for `design` over `speed_range` (see the module docstring).

    **Arguments:**

    - `drive`: the `Drive`; its machine is the plant unless `plant` is given.
    - `design`: any observer (`AbstractObserver`, e.g.
      `observers.make_observer("leso", drive)`; its `motor` is its model, so a model
      different from the plant is observer-model mismatch: then the origin must still be
      an equilibrium for the certificate to mean anything, which holds for
      resistance-only mismatch at zero current, and `status` reports -1 otherwise), or
      a zhang2022 gain schedule (`observers.ESODesign`, e.g.
      `ESODesign.zhang38(drive.w_rated)`): the LESO (`a = 1`) or ESO on the drive's model.
      With observer-model mismatch the certificate is about the principal equilibrium
      $x^*(\omega)$ (the static error the mismatch causes), in $z = x - x^*(\omega)$:
      it certifies that the frozen-speed family is uniformly exponentially stable and
      that the error tracks $x^*(\omega(t))$ for slowly varying speed; the motion of
      $x^*$ itself adds the forcing $-\partial x^*/\partial\omega\,\dot\omega$, which
      leaves an error of order $\dot\omega$ (Khalil, Sec. 9.6), not covered by zhang2022 (52).
      `status` is -1 when no such equilibrium is found.
    - `plant`: the true machine (`PMSMParams`); default the drive's.
    - `speed_range`: `(lo, hi)` in p.u. of `drive.w_rated`, `0 < lo < hi` (the paper's
      $\Omega = (0, \omega_{max}]$ cannot be used: the flux poles of zhang2022 (38) tend to 0 with
      the speed, so no uniform $\sigma$ exists).
    - `i_dq`: controlled current in the estimator frame (p.u. of `drive.base.I_b`).
    - `frame`, `a`, `eta`: for a gain schedule: the error dynamics used for $k_1$
      (`eso_rhs`; `frame="paper"` only for the zhang2022 observers).
    - `scale`: `"pu"` or `"si"` state scaling. `c3`: target in (0, 1).
    - `n_speed`, `alphas`, `n_time`, `radii`, `n_dirs`, `n_refine`, `n_k1_speeds`, `key`:
      resolution of the numerical estimates (defaults are accurate to a few per cent).

    Returns a `LyapunovCertificate`; `eps` (rad/s^2) is the certified rate.
    """
    owner = "slowly_varying_certificate"
    observer = _as_observer(owner, drive, design, a, eta)
    lo, hi = _check(owner, drive, observer, speed_range, scale, frame, c3)
    dtype = jnp.float64
    i0 = jnp.asarray(i_dq, dtype) * drive.base.I_b
    plant = drive.three_phase_motor if plant is None else plant
    # matched model: the origin is the equilibrium. Decided on concrete values (also under
    # an outer jit); a traced machine counts as mismatched (the general route is exact too)
    with jax.ensure_compile_time_eval():
        try:
            matched = bool(eqx.tree_equal(as_arrays(plant, dtype),
                                          as_arrays(observer.motor, dtype)))
        except jax.errors.ConcretizationTypeError:
            matched = False
    # Python floats of the observer and machine as traced values: another design or model
    # runs the compiled certificate again (pmsmjax._sim._batching.values_as_arrays)
    dyn = _ScaledDynamics(observer=values_as_arrays(observer, dtype),
                          plant=values_as_arrays(plant, dtype), i0=i0,
                          d=_state_scale(drive, observer, scale, dtype), frame=frame,
                          matched=matched)
    speeds = jnp.linspace(lo, hi, n_speed, dtype=dtype) * drive.w_rated
    radii = jnp.geomspace(1e-8, 10.0, 128, dtype=dtype) if radii is None else jnp.asarray(
        radii, dtype)
    key = jr.PRNGKey(0) if key is None else key
    return _certificate(dyn, speeds, jnp.asarray(alphas, dtype), radii, c3, key, n_time,
                        n_dirs, n_refine, n_k1_speeds)
